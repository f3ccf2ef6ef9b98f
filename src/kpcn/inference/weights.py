"""Which model a denoise call means: shipped weights, a file, or a module in memory.

``model`` may be

* ``None`` — the shipped default for the layers the file has
  (:func:`choose_default`): :data:`DEFAULT_MODEL` for kpcn's full split with
  variances, else a shipped model for the split without variances, else one
  for colour + albedo + normal (and the choice is said);
* a registered model name, ``"kpcn"``, or ``"name:tag"`` (``"kpcn:small"``) —
  the weights registered beside that model (:func:`kpcn.models.register_weights`);
* a path — a ``.safetensors`` weights file, or a training state / older
  ``.pt`` checkpoint (loaded with ``weights_only=True`` unless ``trust_pickle``);
* a :class:`~kpcn.models.DenoiserModel`.

There is no fallback to random weights: when nothing is shipped, the error says
how to train some. Models loaded from files are cached per (path, mtime, size,
device) and shared between calls: do not modify them.
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

import torch
from torch import nn

from ..checkpoint import load_model_file
from ..models import DenoiserModel, is_model, list_models, list_weights, weights_entry

__all__ = ["DEFAULT_MODEL", "DEFAULT_BY_SPEC", "DefaultWeightsMissing", "choose_default", "load_model",
           "resolve_weights", "resolve_device", "describe"]

#: the model ``denoise(path)`` uses when none is given, with its default shipped weights: unet_kpcn:wide64v
#: (configs/unet_wide64v.yaml, with the detail stage at detail_eps 0.001)
DEFAULT_MODEL = "unet_kpcn"

#: the shipped model used, when none is given, for a file whose best input spec is the key (in this order)
DEFAULT_BY_SPEC = {"kpcn_split": DEFAULT_MODEL, "split_novar": "kpcn:novar_small_r",
                   "color_albedo_normal_noise": "kpcn:can_small_r"}

HOW_TO_GET_WEIGHTS = (
    "train a model with `python -m kpcn.train --config configs/small.yaml` and pass its weights "
    "(model='results/small/model.safetensors'; --model on the command line)"
)


class DefaultWeightsMissing(FileNotFoundError):
    """No shipped weights were found for the requested model."""


def resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None or (isinstance(device, str) and device == "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {device!r} requested but CUDA is not available; use device='cpu'")
    return dev


def resolve_weights(model=None) -> Path:
    """The weights file meant by ``model`` (None, ``"name"``, ``"name:tag"`` or a path)."""
    if model is None:
        model = DEFAULT_MODEL
    text = os.fspath(model)
    path = Path(text)
    if path.is_file():
        return path
    name, _, tag = str(text).partition(":")
    if is_model(name):
        try:
            entry = weights_entry(name, tag or None)
        except KeyError as exc:
            raise DefaultWeightsMissing(f"{exc.args[0]}; {HOW_TO_GET_WEIGHTS}") from None
        if not entry.path.is_file():
            raise DefaultWeightsMissing(f"shipped weights {name}:{entry.tag} are registered but {entry.path} is "
                                        f"missing; {HOW_TO_GET_WEIGHTS}")
        return entry.path
    raise FileNotFoundError(
        f"{text}: neither a weights file nor a registered model name (models: {', '.join(list_models())}; "
        f"shipped weights: {', '.join(list_weights()) or 'none'})"
    )


def _registered_config(model) -> tuple:
    """The config fields a registered ``"name:tag"`` sets over its file's (``()`` for a path or a bare file)."""
    text = os.fspath(model)
    if Path(text).is_file():
        return ()
    name, _, tag = text.partition(":")
    return weights_entry(name, tag or None).config if is_model(name) else ()


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int, size: int, device: str, trust_pickle: bool, config: tuple = ()) -> nn.Module:
    model = load_model_file(path, trust_pickle=trust_pickle, config=dict(config))
    model.eval().requires_grad_(False)
    model._kpcn_source = path  # for the output's metadata
    model._kpcn_config = config
    return model.to(device)


def load_model(model=None, device: str | torch.device = "auto", trust_pickle: bool = False) -> DenoiserModel:
    """The denoiser meant by ``model`` (see the module docstring), in eval mode on ``device``.

    Raises:
        DefaultWeightsMissing: no shipped weights for ``None`` / a model name (says how to get some).
        FileNotFoundError: ``model`` is neither a file nor a registered name.
        kpcn.checkpoint.CheckpointError: the file is not a usable checkpoint (names it and why).
    """
    dev = resolve_device(device)
    if isinstance(model, nn.Module):
        if not isinstance(model, DenoiserModel):
            raise TypeError(f"denoise: model must be a kpcn DenoiserModel (see kpcn.models), got {type(model).__name__}")
        return model.to(dev).eval()
    path = resolve_weights(model)
    config = _registered_config(DEFAULT_MODEL if model is None else model)
    st = path.stat()
    return _load_cached(str(path.resolve()), st.st_mtime_ns, st.st_size, str(dev), bool(trust_pickle), config)


def choose_default(layers) -> tuple[str, str | None]:
    """The shipped model for a file with ``layers``, and a note when it is not :data:`DEFAULT_MODEL`.

    The first spec of :data:`DEFAULT_BY_SPEC` whose layers are all present and
    whose weights ship; the default model when none fits (its reader then names
    the missing layers).
    """
    from ..inputs import get_input_spec

    have = set(layers)
    for spec_name, ref in DEFAULT_BY_SPEC.items():
        name, _, tag = ref.partition(":")
        if set(get_input_spec(spec_name).layers) <= have and (tag or "") in ("", *list_weights(name)):
            if ref == DEFAULT_MODEL:
                return ref, None
            lacking = "per-pixel variances" if spec_name == "split_novar" else "diffuse/specular split"
            return ref, f"the file has no {lacking}: denoising with {ref} ({get_input_spec(spec_name).description})"
    return DEFAULT_MODEL, None


def describe(model: nn.Module) -> str:
    src = getattr(model, "_kpcn_source", None)
    name = getattr(model, "name", "") or type(model).__name__
    over = "".join(f", {k}={v}" for k, v in getattr(model, "_kpcn_config", ()))
    return f"{name} ({Path(src).name}{over})" if src else f"{name} (in-memory)"
