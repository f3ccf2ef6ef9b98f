"""Checkpoints: model weights (weights-only) and training state, in one place.

Two kinds of file:

* **Weights** — ``*.safetensors``: the model's tensors plus, in the file's
  metadata, a JSON record ``{"format", "model", "hparams", ...}`` from which
  :func:`kpcn.models.create_model` rebuilds the architecture. Loading parses
  the file; nothing is unpickled. The shipped weights and a run's final
  ``model.safetensors`` are of this kind.
* **Training state** — ``*.pt`` (a run's ``checkpoints/latest.pt`` and
  ``checkpoints/step_<N>.pt``, each written atomically): weights, optimiser
  state, step, stage, the resolved config and the RNG states, saved with
  ``torch.save`` but holding only tensors, numbers, strings, lists and dicts,
  so it loads with ``torch.load(weights_only=True)``.

Any ``.pt``/``.pth`` path a user passes is loaded with ``weights_only=True``.
A checkpoint that needs full unpickling (kpcn's older checkpoints kept NumPy
arrays) is refused with a message that names the file, unless the caller
passes ``trust_pickle=True`` (``--trust-checkpoint`` on the command line):
unpickling runs whatever code the file contains.

Every failure is a :class:`CheckpointError` naming the file and the problem.
"""
from __future__ import annotations

import json
import os
import random
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from torch import nn

from .io import atomic_write

__all__ = [
    "CheckpointError",
    "WEIGHTS_FORMAT",
    "TRAIN_STATE_FORMAT",
    "save_weights",
    "read_weights",
    "save_train_state",
    "load_train_state",
    "load_model_file",
    "model_from_record",
    "rng_state",
    "set_rng_state",
    "weights_sha256",
]

WEIGHTS_FORMAT = "kpcn-weights/1"
TRAIN_STATE_FORMAT = "kpcn-train-state/1"
PICKLE_SUFFIXES = (".pt", ".pth", ".ckpt", ".bin")
TRUST_HINT = ("pass trust_pickle=True (--trust-checkpoint on the command line) only if you trust where the file "
              "came from: unpickling runs any code it contains")


class CheckpointError(ValueError):
    """A checkpoint file cannot be used; the message names the file and why."""


def _unwrap(model: nn.Module) -> nn.Module:
    return model.module if hasattr(model, "module") else model


def _strip_prefixes(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    state = dict(state)
    for prefix in ("module.", "_orig_mod."):
        if state and all(k.startswith(prefix) for k in state):
            state = {k[len(prefix):]: v for k, v in state.items()}
    return state


# ----------------------------------------------------------------------------- weights


def save_weights(path: str | os.PathLike, model: nn.Module, **meta: Any) -> Path:
    """Write ``model``'s weights and architecture to a ``.safetensors`` file, atomically.

    ``meta`` (JSON-able) is stored beside the architecture (e.g. ``step``, ``config``).
    """
    from safetensors.torch import save_file

    model = _unwrap(model)
    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(f"{path}: weights files end in .safetensors")
    record = {"format": WEIGHTS_FORMAT, "model": model.name, "hparams": model.hparams(), **meta}
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    text = json.dumps(record, default=_json_default)
    atomic_write(path, lambda tmp: save_file(state, tmp, metadata={"kpcn": text}))
    return path


def _json_default(o):
    if isinstance(o, (np.integer, np.floating)):
        return o.item()
    if isinstance(o, (Path, tuple)):
        return str(o) if isinstance(o, Path) else list(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def read_weights(path: str | os.PathLike) -> tuple[dict, dict[str, torch.Tensor]]:
    """``(record, state_dict)`` of a ``.safetensors`` weights file (nothing is unpickled)."""
    from safetensors import safe_open

    path = Path(path)
    _check_file(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            state = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # SafetensorError, OSError, ...
        raise CheckpointError(f"{path}: not a readable safetensors file ({_short(exc)})") from None
    if "kpcn" not in meta:
        raise CheckpointError(f"{path}: a safetensors file without kpcn's metadata (no model name and "
                              "hyper-parameters); write weights with kpcn.checkpoint.save_weights")
    try:
        record = json.loads(meta["kpcn"])
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{path}: kpcn metadata is not valid JSON ({exc})") from None
    if not isinstance(record, dict) or "model" not in record or "hparams" not in record:
        raise CheckpointError(f"{path}: kpcn metadata lacks 'model' or 'hparams' (found {sorted(record)})")
    return record, state


def model_from_record(name: str, hparams: Mapping, state: Mapping[str, torch.Tensor], source: str) -> nn.Module:
    """Build model ``name`` with ``hparams`` and load ``state``; errors name ``source``."""
    from .config import ConfigError
    from .models import create_model, is_model, list_models

    if not isinstance(name, str) or not is_model(name):
        raise CheckpointError(f"{source}: model {name!r} is not registered in this kpcn "
                              f"(known: {', '.join(list_models())})")
    if not isinstance(hparams, Mapping):
        raise CheckpointError(f"{source}: hyper-parameters must be a mapping, got {type(hparams).__name__}")
    if not isinstance(state, Mapping) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise CheckpointError(f"{source}: 'model' must be a state dict of tensors, got {type(state).__name__}")
    hp = {k: v for k, v in dict(hparams).items() if k != "name"}
    try:
        model = create_model(name, **hp)
    except ConfigError as exc:
        raise CheckpointError(f"{source}: its hyper-parameters do not fit model {name!r}: {exc}") from None
    try:
        model.load_state_dict(_strip_prefixes(state))
    except RuntimeError as exc:
        raise CheckpointError(f"{source}: weights do not fit model {name!r} {hp}: {_short(exc)}") from None
    return model


# ----------------------------------------------------------------------------- training state


def rng_state() -> dict:
    """torch, NumPy and Python RNG states as tensors and plain lists (weights-only loadable)."""
    kind, key, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {"kind": kind, "key": torch.from_numpy(key.astype(np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "python": [version, list(internal), gauss_next],
    }


def set_rng_state(state: Mapping) -> None:
    # a checkpoint loaded onto a GPU (map_location) carries these tensors there: the RNGs take CPU ones
    torch.set_rng_state(state["torch"].cpu())
    n = state["numpy"]
    np.random.set_state((n["kind"], n["key"].cpu().numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached_gaussian"]))
    version, internal, gauss_next = state["python"]
    random.setstate((version, tuple(internal), gauss_next))


def save_train_state(path: str | os.PathLike, model: nn.Module, optimizer, step: int, config: dict, **extra) -> None:
    """Write the training state (weights, optimiser, step, config, RNG) atomically."""
    model = _unwrap(model)
    state = {
        "format": TRAIN_STATE_FORMAT,
        "model": model.state_dict(),
        "model_name": model.name,
        "hparams": model.hparams(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "step": int(step),
        "config": config,
        "rng": rng_state(),
        **extra,
    }
    atomic_write(path, lambda tmp: torch.save(state, tmp))


def _torch_load(path: Path, trust_pickle: bool, map_location="cpu"):
    _check_file(path)
    try:
        return torch.load(path, map_location=map_location, weights_only=not trust_pickle)
    except Exception as exc:
        text = str(exc)
        if not trust_pickle and ("Unsupported global" in text or "can still be loaded" in text):
            raise CheckpointError(f"{path}: holds Python objects beyond plain tensors and numbers, which only full "
                                  f"unpickling can load; {TRUST_HINT}") from None
        if not trust_pickle and "Weights only load failed" in text:
            detail = next((ln.strip() for ln in text.splitlines() if ln.strip().startswith("Unsupported")), "")
            raise CheckpointError(f"{path}: not a readable weights-only checkpoint ({detail or type(exc).__name__}): "
                                  f"either not a checkpoint at all, or a pickle only full unpickling can read; "
                                  f"{TRUST_HINT}") from None
        raise CheckpointError(f"{path}: not a readable checkpoint ({_short(exc)})") from None


def load_train_state(path: str | os.PathLike, trust_pickle: bool = False, map_location="cpu") -> dict:
    """The training state in ``path`` (see :func:`save_train_state`), checked for the keys resume needs."""
    path = Path(path)
    state = _torch_load(path, trust_pickle, map_location)
    need = ("model", "optimizer", "step", "rng")
    if not isinstance(state, dict) or any(k not in state for k in need):
        found = sorted(state) if isinstance(state, dict) else type(state).__name__
        raise CheckpointError(f"{path}: not a kpcn training state (needs {list(need)}, found {found})")
    return state


# ----------------------------------------------------------------------------- any model file


def load_model_file(path: str | os.PathLike, trust_pickle: bool = False, config: Mapping | None = None) -> nn.Module:
    """The model in ``path``: a ``.safetensors`` weights file, or a training state / older checkpoint.

    Pickle-based files load with ``weights_only=True`` unless ``trust_pickle``. ``config``: config fields set over
    the file's hyper-parameters (a registered tag's, :class:`~kpcn.models.WeightsEntry`).
    """
    path = Path(path)
    over = dict(config or {})
    if path.suffix == ".safetensors":
        record, state = read_weights(path)
        return model_from_record(record["model"], _with(record["hparams"], over), state, str(path))
    ckpt = _torch_load(path, trust_pickle)
    if not isinstance(ckpt, Mapping) or "model" not in ckpt:
        found = sorted(ckpt) if isinstance(ckpt, Mapping) else type(ckpt).__name__
        raise CheckpointError(f"{path}: not a kpcn checkpoint (no 'model' weights; found {found})")
    name = ckpt.get("model_name")
    hparams = ckpt["hparams"] if "hparams" in ckpt else ckpt.get("model_kwargs")  # model_kwargs: older checkpoints
    if name is None or hparams is None:
        raise CheckpointError(f"{path}: not a kpcn checkpoint: it lacks the model name and hyper-parameters "
                              f"(found keys {sorted(ckpt)})")
    return model_from_record(name, _with(hparams, over), ckpt["model"], str(path))


def _with(hparams, over: dict):
    """``hparams`` with ``over`` set on it (a malformed ``hparams`` is left for :func:`model_from_record` to name)."""
    return {**hparams, **over} if over and isinstance(hparams, Mapping) else hparams


def weights_sha256(state_dict: Mapping[str, torch.Tensor]) -> str:
    """A digest of a model's weights (distributed ranks must agree; converted weights must match)."""
    import hashlib

    h = hashlib.sha256()
    for k in sorted(state_dict):
        h.update(k.encode())
        h.update(state_dict[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _check_file(path: Path) -> None:
    if not path.exists():
        raise CheckpointError(f"{path}: checkpoint not found")
    if not path.is_file():
        raise CheckpointError(f"{path}: not a file")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{path}: empty file (an interrupted write?)")


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"[:300]
