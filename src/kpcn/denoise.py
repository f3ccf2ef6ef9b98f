"""Denoise multi-layer EXR renders with a trained KPCN/DPCN.

Python::

    from kpcn.denoise import denoise
    color = denoise("noisy.exr")                            # shipped default weights
    color = denoise("noisy.exr", "results/small/model.pt", out_path="clean.exr")
    result = denoise_result(frame, model)                   # colour + DenoiseStats

Command line (also installed as ``kpcn-denoise``)::

    python -m kpcn.denoise in.exr [more.exr ...] [-o out.exr | --out-dir DIR]
                           [--model NAME_OR_CKPT] [--tile N] [--device cpu]

How a frame is processed
------------------------
* The file is read with :func:`kpcn.io.read_exr`, requiring
  :data:`kpcn.features.INPUT_LAYERS` (a missing layer is named, with the layers
  found). NaN/Inf are replaced and counted by the reader; a :class:`Frame` given
  in memory is sanitised the same way (on a copy).
* **Tiles with a halo.** The frame is cut into ``tile x tile`` interiors. Each
  is processed on its own, on the crop ``interior + halo`` (clamped to the
  frame), with ``halo = model.receptive_radius + 1`` (+1 because the gradient
  features are forward differences). The features of a tile are the features
  of that crop, computed when the tile is processed (each tile once), with the
  depth normaliser of the *whole* frame; only the crop's interior is kept. So
  the tiled result equals the untiled one (to float rounding), and memory is
  bounded by the tile size whatever the frame size.
* **What a frame does not need is left out** (``skip=True``, the default):

  - a branch whose colour is zero over the whole frame (no specular, or no
    diffuse, anywhere) is not run and its 27 features are not computed; the
    :class:`~kpcn.models.Denoiser` gets ``None`` for it (that component is 0).
    For KPCN this is exact: a convex combination of zeros is zero. For DPCN it
    is not bit-identical (a DPCN adds a learned residual even to a zero input);
    the skipped component is 0, which is the correct radiance there.
  - KPCN only, per tile: a branch whose colour is zero on the tile's crop is
    not run on that tile (exact, for the same reason; the kernel reaches at most
    ``kernel_size // 2 < halo`` pixels).
  - a tile whose crop has no geometry (depth <= 0 everywhere) and converged
    colour (variance of the pixel mean <= ``(PASSTHROUGH_REL_STD * colour)^2``,
    i.e. zero up to the float rounding of the renderer's moments) is passed
    through: its output is the noisy colour, without running the network.

  :class:`DenoiseStats` counts what was skipped.

Weights
-------
``model`` may be ``None`` (the shipped default weights
``src/kpcn/weights/default.pt``), a registered model name (``"kpcn"``: the
shipped weights for that architecture, ``weights/<name>.pt`` or ``default.pt``
when it is of that kind), a checkpoint path written by
:func:`kpcn.train.save_checkpoint`, or a :class:`~kpcn.models.Denoiser`. There is
no fallback to random weights: when no weights are shipped, the error says how
to train some. Checkpoints are pickles (``torch.load(weights_only=False)``):
only load files you trust. Loaded models are cached per (path, mtime, device).
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import os
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np
import torch
from torch import nn

from .features import BRANCH_LAYERS as _BRANCH_LAYERS
from .features import BRANCHES, INPUT_LAYERS, branch_features, depth_scale_of
from .features import SHARED_LAYERS as _SHARED_LAYERS
from .io import ExrError, Frame, MissingLayerError, read_exr, sanitize_layers, write_exr

__all__ = [
    "denoise",
    "denoise_result",
    "load_model",
    "DenoiseResult",
    "DenoiseStats",
    "DefaultWeightsMissing",
    "branch_features",
    "plan_tiles",
    "Tile",
    "DEFAULT_WEIGHTS",
    "WEIGHTS_DIR",
    "PASSTHROUGH_REL_STD",
    "main",
]

log = logging.getLogger("kpcn.denoise")

#: folder of the shipped weights (``default.pt`` and optionally ``<model name>.pt``)
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
#: the weights ``denoise(path)`` uses when no model is given
DEFAULT_WEIGHTS = WEIGHTS_DIR / "default.pt"
#: a no-hit tile is passed through when every pixel's standard error is at most this fraction of its colour
PASSTHROUGH_REL_STD = 1e-3

_THREE_CHANNEL = ("diffuse", "specular", "albedo", "normal")

_HOW_TO_GET_WEIGHTS = (
    "train a model with `python -m kpcn.train --config configs/small.yaml` and pass its checkpoint "
    "(model='results/small/model.pt' or a checkpoints/step_N.pt; --model on the command line), "
    f"or copy a checkpoint to {DEFAULT_WEIGHTS} to make it the default"
)


class DefaultWeightsMissing(FileNotFoundError):
    """No shipped weights were found for the requested model."""


# ----------------------------------------------------------------------------- results


@dataclass
class DenoiseStats:
    """What one :func:`denoise_result` call did and how long it took.

    Attributes:
        seconds: wall time of the denoising (features, network, assembly), without reading or writing files.
        read_seconds, write_seconds: time spent reading the input / writing the output EXR.
        size: ``(H, W)`` of the frame.
        tile, halo: interior tile size and halo in pixels.
        tiles: number of tiles.
        tiles_run: tiles on which at least one branch ran.
        tiles_passed_through: no-hit, converged tiles whose output is the noisy colour.
        tiles_zero: tiles with both branch colours zero (KPCN output is exactly 0; nothing run).
        tiles_fp32_fallback: ``half=True`` only: tiles re-run in float32 because float16 overflowed.
        branches_skipped: branches not run anywhere because their colour is zero over the whole frame.
        branch_tiles_run / branch_tiles_skipped: per branch, tiles on which it ran / was left out.
        device: where the network ran.
        peak_rss_mb: the process's peak resident memory (``VmHWM``) after the call, in MiB. It is
            the peak over the process's life so far, so only an upper bound for this call unless
            the caller reset it first (``python -m kpcn.bench denoise`` does, in a fresh process).
        peak_cuda_mb: peak CUDA memory allocated by torch during the call (CUDA only).
        nonfinite: NaN/Inf values replaced per layer (by the reader or here).
    """

    seconds: float = 0.0
    read_seconds: float = 0.0
    write_seconds: float = 0.0
    size: tuple[int, int] = (0, 0)
    tile: int = 0
    halo: int = 0
    tiles: int = 0
    tiles_run: int = 0
    tiles_passed_through: int = 0
    tiles_zero: int = 0
    tiles_fp32_fallback: int = 0
    branches_skipped: tuple[str, ...] = ()
    branch_tiles_run: dict[str, int] = field(default_factory=lambda: {b: 0 for b in BRANCHES})
    branch_tiles_skipped: dict[str, int] = field(default_factory=lambda: {b: 0 for b in BRANCHES})
    device: str = "cpu"
    peak_rss_mb: float | None = None
    peak_cuda_mb: float | None = None
    nonfinite: dict[str, int] = field(default_factory=dict)

    def summary(self) -> str:
        h, w = self.size
        parts = [f"{w}x{h}", f"{self.seconds:.2f} s", f"tiles run {self.tiles_run}/{self.tiles}"]
        if self.tiles_passed_through:
            parts.append(f"passed through {self.tiles_passed_through}")
        if self.tiles_zero:
            parts.append(f"zero {self.tiles_zero}")
        if self.branches_skipped:
            parts.append(f"branch skipped: {', '.join(self.branches_skipped)}")
        else:
            partial = [f"{b} on {self.branch_tiles_run[b]}/{self.tiles}" for b in BRANCHES if self.branch_tiles_skipped[b]]
            if partial:
                parts.append("ran " + ", ".join(partial))
        return ", ".join(parts)


@dataclass
class DenoiseResult:
    """Denoised colour ``(H, W, 3)`` float32, the stats, and the model's description."""

    color: np.ndarray
    stats: DenoiseStats
    model_name: str = ""
    out_path: str | None = None


# ----------------------------------------------------------------------------- models


def _resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None or (isinstance(device, str) and device == "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {device!r} requested but CUDA is not available; use device='cpu'")
    return dev


def _strip_prefixes(state: dict) -> dict:
    for prefix in ("module.", "_orig_mod."):
        if state and all(k.startswith(prefix) for k in state):
            state = {k[len(prefix):]: v for k, v in state.items()}
    return state


def _model_from_checkpoint(ckpt: Mapping, source: str) -> nn.Module:
    from .models import create_model

    if not isinstance(ckpt, Mapping):
        raise ValueError(f"{source}: not a kpcn checkpoint (a {type(ckpt).__name__}, expected a dict)")
    missing = [k for k in ("model", "model_name", "model_kwargs") if k not in ckpt]
    if missing:
        raise ValueError(
            f"{source}: not a kpcn checkpoint: missing key(s) {missing} (found: {sorted(ckpt)}); "
            "checkpoints written by kpcn.train.save_checkpoint have 'model', 'model_name' and 'model_kwargs'"
        )
    model = create_model(ckpt["model_name"], **dict(ckpt["model_kwargs"] or {}))
    try:
        model.load_state_dict(_strip_prefixes(dict(ckpt["model"])))
    except RuntimeError as exc:
        raise ValueError(f"{source}: weights do not fit model {ckpt['model_name']!r} {ckpt['model_kwargs']}: {exc}") from exc
    return model


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int, size: int, device: str) -> nn.Module:
    """Load a checkpoint file into an eval-mode model on ``device`` (cached; do not modify the result)."""
    from .train import load_checkpoint

    ckpt = load_checkpoint(path, map_location="cpu")
    model = _model_from_checkpoint(ckpt, path)
    model.eval().requires_grad_(False)
    model._kpcn_source = path  # for the output's metadata
    return model.to(device)


def _load_path(path: Path, device: torch.device) -> nn.Module:
    st = path.stat()
    return _load_cached(str(path.resolve()), st.st_mtime_ns, st.st_size, str(device))


def _resolve_weights(model) -> Path:
    """The checkpoint file meant by ``model`` (None, a registered name or a path)."""
    from .models import is_model, list_models

    if model is None:
        if DEFAULT_WEIGHTS.is_file():
            return DEFAULT_WEIGHTS
        raise DefaultWeightsMissing(f"no default weights shipped ({DEFAULT_WEIGHTS} does not exist); {_HOW_TO_GET_WEIGHTS}")
    path = Path(os.fspath(model))
    if path.is_file():
        return path
    if isinstance(model, str) and is_model(model):
        named = WEIGHTS_DIR / f"{model}.pt"
        if named.is_file():
            return named
        if DEFAULT_WEIGHTS.is_file():
            from .train import load_checkpoint

            if load_checkpoint(DEFAULT_WEIGHTS).get("model_name") == model:
                return DEFAULT_WEIGHTS
        raise DefaultWeightsMissing(
            f"no shipped weights for model {model!r} (looked for {named} and a {model!r} checkpoint at "
            f"{DEFAULT_WEIGHTS}); {_HOW_TO_GET_WEIGHTS}"
        )
    raise FileNotFoundError(
        f"{model}: neither a checkpoint file nor a registered model name (known: {', '.join(list_models())})"
    )


def load_model(model=None, device: str | torch.device = "auto") -> nn.Module:
    """The denoiser meant by ``model``, in eval mode on ``device``.

    Args:
        model: ``None`` (shipped default weights), a registered model name, a
            checkpoint path, or an ``nn.Module`` (a :class:`~kpcn.models.Denoiser`;
            moved to ``device`` and put in eval mode).
        device: ``"auto"`` (CUDA if available, else CPU), ``"cpu"``, ``"cuda"``, ...

    Raises:
        DefaultWeightsMissing: no shipped weights for ``None`` / a model name (says how to get some).
        FileNotFoundError: ``model`` is neither a file nor a registered name.
        ValueError: the file is not a kpcn checkpoint or its weights do not fit.

    Models loaded from files are cached (``functools.lru_cache`` on path, mtime
    and device) and shared between calls: do not modify them.
    """
    dev = _resolve_device(device)
    if isinstance(model, nn.Module):
        _check_model(model)
        return model.to(dev).eval()
    return _load_path(_resolve_weights(model), dev)


def _check_model(model: nn.Module) -> None:
    for attr in ("receptive_radius", "diffuse", "specular"):
        if not hasattr(model, attr):
            raise TypeError(
                f"denoise: model must be a kpcn Denoiser (with .diffuse, .specular and .receptive_radius); "
                f"{type(model).__name__} has no {attr!r}"
            )


def _describe(model: nn.Module) -> str:
    kind = getattr(model, "kind", type(model).__name__)
    src = getattr(model, "_kpcn_source", None)
    return f"{kind} ({Path(src).name})" if src else f"{kind} (in-memory)"


def _is_kpcn(model: nn.Module) -> bool:
    from .models import KPCNBranch

    return isinstance(model.diffuse, KPCNBranch) and isinstance(model.specular, KPCNBranch)


# ----------------------------------------------------------------------------- features


# ----------------------------------------------------------------------------- tiles


@dataclass(frozen=True)
class Tile:
    """An output interior ``[y0, y1) x [x0, x1)`` and the crop ``[cy0, cy1) x [cx0, cx1)`` it is computed on."""

    y0: int
    y1: int
    x0: int
    x1: int
    cy0: int
    cy1: int
    cx0: int
    cx1: int

    @property
    def crop(self) -> tuple[slice, slice]:
        return slice(self.cy0, self.cy1), slice(self.cx0, self.cx1)

    @property
    def interior(self) -> tuple[slice, slice]:
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    @property
    def interior_in_crop(self) -> tuple[slice, slice]:
        return slice(self.y0 - self.cy0, self.y1 - self.cy0), slice(self.x0 - self.cx0, self.x1 - self.cx0)


def plan_tiles(height: int, width: int, tile: int | None, halo: int) -> Iterator[Tile]:
    """Row-major tiles covering ``height x width``; ``tile`` None or <= 0: one tile, the whole frame."""
    th = height if not tile or tile <= 0 else int(tile)
    tw = width if not tile or tile <= 0 else int(tile)
    for y0 in range(0, height, th):
        y1 = min(y0 + th, height)
        for x0 in range(0, width, tw):
            x1 = min(x0 + tw, width)
            yield Tile(y0, y1, x0, x1, max(0, y0 - halo), min(height, y1 + halo), max(0, x0 - halo), min(width, x1 + halo))


# ----------------------------------------------------------------------------- denoising


def _as_frame(src) -> tuple[Frame, float]:
    """A sanitised frame with the input layers, and the seconds spent reading it."""
    t0 = time.perf_counter()
    if isinstance(src, (str, os.PathLike)):
        frame = read_exr(src, require=INPUT_LAYERS)
        return frame, time.perf_counter() - t0
    if isinstance(src, Frame):
        frame = Frame(dict(src.layers), dict(src.meta), src.path, dict(src.nonfinite))
    elif isinstance(src, Mapping):
        frame = Frame({k: np.asarray(v) for k, v in src.items()})
    else:
        raise TypeError(f"denoise: expected an EXR path, a Frame or a dict of layers, got {type(src).__name__}")
    frame.require(INPUT_LAYERS)
    for name, arr in list(frame.layers.items()):
        a = np.asarray(arr)
        if a.ndim == 2:
            a = a[..., None]
        frame.layers[name] = a if a.dtype == np.float32 else a.astype(np.float32)
    counts = sanitize_layers(frame.layers)  # on the copied dict: the caller's arrays are untouched
    if counts:
        frame.nonfinite = {**frame.nonfinite, **counts}
        warnings.warn(
            f"{frame.path or 'frame'}: replaced non-finite values ({', '.join(f'{k}: {v}' for k, v in counts.items())})",
            RuntimeWarning,
            stacklevel=3,
        )
    return frame, time.perf_counter() - t0


def _validate(frame: Frame) -> tuple[int, int]:
    h, w = frame[INPUT_LAYERS[0]].shape[:2]
    for name in INPUT_LAYERS + (("color",) if "color" in frame else ()) + (("colorVariance",) if "colorVariance" in frame else ()):
        a = frame[name]
        if a.ndim != 3 or a.shape[:2] != (h, w):
            raise ValueError(f"{frame.path or 'frame'}: layer {name!r} has shape {a.shape}, expected ({h}, {w}, C)")
        if name in _THREE_CHANNEL and a.shape[2] != 3:
            raise ValueError(f"{frame.path or 'frame'}: layer {name!r} must have 3 channels, got {a.shape[2]}")
    if h == 0 or w == 0:
        raise ValueError(f"{frame.path or 'frame'}: empty image ({w}x{h})")
    return h, w


def _noisy_color(frame: Frame) -> np.ndarray:
    if "color" in frame and frame["color"].shape[2] == 3:
        return frame["color"]
    return frame["diffuse"] + frame["specular"]


def _color_variance(frame: Frame) -> np.ndarray:
    if "colorVariance" in frame:
        return frame["colorVariance"]
    return frame["diffuseVariance"] + frame["specularVariance"]


def _to_tensor(arr: np.ndarray, crop: tuple[slice, slice], device: torch.device) -> torch.Tensor:
    a = arr[crop]
    t = torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]
    return t.to(device, non_blocking=True)


def _run_net(net: nn.Module, feats: dict, half: bool) -> dict:
    ctx = torch.autocast("cuda", dtype=torch.float16) if half else contextlib.nullcontext()
    with ctx:
        return net(feats.get("diffuse"), feats.get("specular"), feats["albedo"])


def _peak_rss_mb() -> float | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    try:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    except Exception:  # pragma: no cover - non-POSIX
        return None


def denoise_result(
    exr_path_or_frame,
    model=None,
    out_path: str | os.PathLike | None = None,
    *,
    tile: int | None = 256,
    device: str | torch.device = "auto",
    half: bool = False,
    skip: bool = True,
) -> DenoiseResult:
    """Like :func:`denoise`, but returns a :class:`DenoiseResult` (colour and :class:`DenoiseStats`)."""
    dev = _resolve_device(device)
    net = load_model(model, dev)
    _check_model(net)
    frame, read_s = _as_frame(exr_path_or_frame)
    h, w = _validate(frame)
    if tile is not None and (isinstance(tile, bool) or int(tile) != tile):
        raise ValueError(f"denoise: tile must be an integer (<= 0 or None: whole frame), got {tile!r}")
    halo = int(net.receptive_radius) + 1
    use_half = bool(half) and dev.type == "cuda"
    if half and not use_half:
        warnings.warn("denoise: half=True is only used on CUDA; running float32 on the CPU", RuntimeWarning, stacklevel=2)

    stats = DenoiseStats(size=(h, w), tile=int(tile) if tile and tile > 0 else max(h, w), halo=halo, device=str(dev))
    stats.read_seconds = read_s
    stats.nonfinite = dict(frame.nonfinite)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    t0 = time.perf_counter()

    kpcn = _is_kpcn(net)
    color_in = _noisy_color(frame)
    active = list(BRANCHES)
    if skip:
        active = [b for b in BRANCHES if np.any(frame[b] > 0)]  # branch colour is max(x, 0) / ... : zero iff x <= 0
        stats.branches_skipped = tuple(b for b in BRANCHES if b not in active)
    depth_full = torch.from_numpy(np.ascontiguousarray(frame["depth"][..., 0])).clamp_min(0.0)[None, None]
    depth_scale = depth_scale_of(depth_full).to(dev)
    del depth_full
    var_in = _color_variance(frame) if skip else None

    out = np.empty((h, w, 3), dtype=np.float32)
    with torch.inference_mode():
        for t in plan_tiles(h, w, tile, halo):
            stats.tiles += 1
            crop = t.crop
            if skip and not np.any(frame["depth"][crop] > 0):
                c = color_in[crop]
                if np.all(var_in[crop] <= np.square(PASSTHROUGH_REL_STD * c)):
                    out[t.interior] = np.maximum(color_in[t.interior], 0.0)
                    stats.tiles_passed_through += 1
                    for b in BRANCHES:
                        stats.branch_tiles_skipped[b] += 1
                    continue
            run = list(active)
            if skip and kpcn:  # exact for KPCN only: a convex combination of zeros is zero
                run = [b for b in active if np.any(frame[b][crop] > 0)]
            for b in BRANCHES:
                stats.branch_tiles_run[b] += b in run
                stats.branch_tiles_skipped[b] += b not in run
            if not run:
                # every component is zero; reconstruct(0, 0, albedo) == 0
                out[t.interior] = 0.0
                stats.tiles_zero += 1
                continue
            names = list(_SHARED_LAYERS) + [n for b in run for n in _BRANCH_LAYERS[b]]
            buffers = {n: _to_tensor(frame[n], crop, dev) for n in names}
            feats = branch_features(buffers, depth_scale, run)
            del buffers
            res = _run_net(net, feats, use_half)
            if use_half and not all(torch.isfinite(res[b]).all() for b in run):
                # float16 overflowed (features of very bright or very dark images exceed its range)
                res = _run_net(net, feats, False)
                stats.tiles_fp32_fallback += 1
            iy, ix = t.interior_in_crop
            out[t.interior] = res["color"][0, :, iy, ix].float().permute(1, 2, 0).cpu().numpy()
            stats.tiles_run += 1
            del feats, res
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
        stats.peak_cuda_mb = torch.cuda.max_memory_allocated(dev) / 2**20
    stats.seconds = time.perf_counter() - t0
    stats.peak_rss_mb = _peak_rss_mb()

    result = DenoiseResult(out, stats, _describe(net))
    if out_path is not None:
        t1 = time.perf_counter()
        _write_output(out_path, out, frame, result)
        stats.write_seconds = time.perf_counter() - t1
        result.out_path = os.fspath(out_path)
    return result


def _write_output(out_path, color: np.ndarray, frame: Frame, result: DenoiseResult) -> None:
    layers = {"color": color}
    for name in ("albedo", "normal", "depth"):
        if name in frame:
            layers[name] = frame[name]
    meta = {k: v for k, v in frame.meta.items() if k in ("spp", "seed", "scene", "renderTimeSeconds")}
    meta.update(
        {
            "source": os.path.abspath(frame.path) if frame.path else "<in-memory frame>",
            "denoiser": result.model_name,
            "denoiseSeconds": float(result.stats.seconds),
        }
    )
    write_exr(out_path, layers, meta)


def denoise(
    exr_path_or_frame,
    model=None,
    out_path: str | os.PathLike | None = None,
    *,
    tile: int | None = 256,
    device: str | torch.device = "auto",
    half: bool = False,
    skip: bool = True,
) -> np.ndarray:
    """Denoise one render and return its colour ``(H, W, 3)`` float32 (finite, >= 0).

    Args:
        exr_path_or_frame: a multi-layer EXR path, a :class:`~kpcn.io.Frame`, or a
            dict of ``(H, W, C)`` layers; it must have :data:`~kpcn.features.INPUT_LAYERS`.
        model: ``None`` (shipped default weights), a registered model name, a
            checkpoint path, or a :class:`~kpcn.models.Denoiser` (see :func:`load_model`).
        out_path: if given, also write an EXR (atomically): the denoised colour as
            ``R G B``, the input's ``albedo``/``normal``/``depth``, and header
            attributes ``source``, ``denoiser``, ``denoiseSeconds`` (and the input's
            ``spp``, ``seed``, ``scene``).
        tile: interior tile size in pixels (each tile gets a halo of
            ``model.receptive_radius + 1``); ``None`` or ``0``: the whole frame at once.
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"``, ...
        half: float16 autocast on CUDA (ignored, with a warning, on the CPU).
        skip: leave out zero branches, zero KPCN tiles and no-hit converged tiles
            (see the module docstring); ``False`` runs the network everywhere.

    Raises:
        MissingLayerError: the input lacks layers the features need (names them and those found).
        ExrError / FileNotFoundError: unreadable or missing file; see also :func:`load_model`.
    """
    return denoise_result(exr_path_or_frame, model, out_path, tile=tile, device=device, half=half, skip=skip).color


# ----------------------------------------------------------------------------- CLI


def _default_out(path: Path, out_dir: str | None) -> Path:
    name = f"{path.stem}_denoised.exr"
    return Path(out_dir) / name if out_dir else path.with_name(name)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="kpcn-denoise",
        description="Denoise multi-layer EXR renders (kpcn contract) with a KPCN/DPCN. "
        "Writes <name>_denoised.exr next to each input unless -o or --out-dir is given.",
    )
    p.add_argument("inputs", nargs="+", help="noisy multi-layer EXR files")
    g = p.add_mutually_exclusive_group()
    g.add_argument("-o", "--out", help="output EXR (only with a single input)")
    g.add_argument("--out-dir", help="folder for the outputs (<name>_denoised.exr)")
    p.add_argument("--model", default=None, help="checkpoint path or registered model name (default: shipped weights)")
    p.add_argument("--tile", type=int, default=256, help="tile size in pixels, 0 = whole frame (default 256)")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:1, ... (default auto)")
    p.add_argument("--half", action="store_true", help="float16 autocast (CUDA only)")
    p.add_argument("--no-skip", action="store_true", help="run the network on every tile and branch")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = p.parse_args(argv)
    if args.out and len(args.inputs) > 1:
        p.error("-o/--out takes a single input; use --out-dir for several")
    if args.threads:
        torch.set_num_threads(args.threads)

    try:
        net = load_model(args.model, args.device)
    except (FileNotFoundError, ValueError, TypeError, RuntimeError) as exc:
        print(f"kpcn-denoise: cannot load the model: {exc}", file=sys.stderr)
        return 2
    dev = next(net.parameters()).device
    print(f"model: {_describe(net)}, receptive radius {net.receptive_radius}, tile {args.tile}, device {dev}", flush=True)

    failures: list[tuple[str, str]] = []
    for inp in args.inputs:
        src = Path(inp)
        dst = Path(args.out) if args.out else _default_out(src, args.out_dir)
        try:
            if src.exists() and dst.exists() and os.path.samefile(src, dst):
                raise ValueError(f"output {dst} is the input file; choose another -o/--out-dir")
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                res = denoise_result(src, net, dst, tile=args.tile, device=args.device, half=args.half, skip=not args.no_skip)
            for wmsg in caught:
                print(f"warning: {wmsg.message}", file=sys.stderr)
        except (MissingLayerError, ExrError, FileNotFoundError, ValueError, OSError, RuntimeError) as exc:
            print(f"FAILED {inp}: {exc}", file=sys.stderr, flush=True)
            failures.append((inp, str(exc)))
            continue
        print(f"{inp} -> {dst}: {res.stats.seconds:.2f} s ({res.stats.summary()})", flush=True)
    if failures:
        print(f"\n{len(failures)} of {len(args.inputs)} file(s) failed:", file=sys.stderr)
        for inp, msg in failures:
            print(f"  {inp}: {msg}", file=sys.stderr)
        return 1
    return 0


class _CallableModule(type(sys)):
    """Lets ``kpcn.denoise("frame.exr")`` call :func:`denoise` while ``python -m
    kpcn.denoise`` and ``from kpcn.denoise import ...`` keep working on the module."""

    def __call__(self, *args, **kwargs):
        return denoise(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule


if __name__ == "__main__":
    sys.exit(main())
