"""The frame a denoise call reads and the file it writes: the input made a sanitised :class:`~kpcn.io.Frame`
(:func:`as_frame`), checked (:func:`validate`), the shipped model its layers call for (:func:`default_model`), an
output path refused before any work when it is the input (:func:`check_output`), and the output EXR
(:func:`write_output`). Shared by :mod:`.pipeline` and :mod:`.ensemble`."""
from __future__ import annotations

import os
import time
import warnings
from typing import Mapping

import numpy as np

from ..io import SAMPLE_COUNT, Frame, read_exr, sanitize_layers, write_exr
from .paths import check_not_input, check_output_path
from .results import DenoiseResult
from .weights import choose_default

__all__ = ["THREE_CHANNEL", "source_path", "check_output", "default_model", "as_frame", "validate", "color_variance",
           "normal_of", "with_normal", "write_output"]

#: layers that must have three channels
THREE_CHANNEL = ("color", "diffuse", "specular", "albedo", "normal")


def source_path(src) -> str | None:
    """The file a denoise input came from: the path given, or the file a :class:`Frame` was read from."""
    if isinstance(src, (str, os.PathLike)):
        return os.fspath(src)
    if isinstance(src, Frame) and src.path:
        return os.fspath(src.path)
    return None


def check_output(out_path, src) -> None:
    """Refuse ``out_path`` (None: nothing to check) when it is a folder, lies under a file, or is the input ``src``
    under any spelling (:mod:`.paths`)."""
    if out_path is None:
        return
    check_output_path(out_path)
    source = source_path(src)
    if source is not None and os.path.exists(source):  # a missing input is the reader's error
        check_not_input(out_path, source)


def default_model(frame: Frame, stacklevel: int):
    """The shipped model for the layers ``frame`` has, with a warning (at the caller's ``stacklevel``) where it is
    not the default."""
    model, note = choose_default(frame.layers)
    if note:
        warnings.warn(f"{frame.path or 'frame'}: {note}", UserWarning, stacklevel=stacklevel + 1)
    return model


def as_frame(src, layers) -> tuple[Frame, float]:
    """A sanitised frame with ``layers``, and the seconds spent reading it."""
    t0 = time.perf_counter()
    if isinstance(src, (str, os.PathLike)):
        frame = read_exr(src, require=layers)
        return frame, time.perf_counter() - t0
    if isinstance(src, Frame):
        frame = Frame(dict(src.layers), dict(src.meta), src.path, dict(src.nonfinite))
    elif isinstance(src, Mapping):
        frame = Frame({k: np.asarray(v) for k, v in src.items()})
    else:
        raise TypeError(f"denoise: expected an EXR path, a Frame or a dict of layers, got {type(src).__name__}")
    frame.require(layers)
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


def validate(frame: Frame, layers) -> tuple[int, int]:
    """``(H, W)`` of ``frame``, after checking that ``layers`` (and colour, its variance and the sample count, where
    present) share it and that the colour-like ones have 3 channels (a clear ``ValueError`` naming the layer
    otherwise). Pixels whose sample count is below 1 (no samples), or 1 in a frame with variances (a variance from
    one sample is not known), are counted in a warning."""
    h, w = frame[layers[0]].shape[:2]
    extra = tuple(n for n in ("color", "colorVariance", SAMPLE_COUNT) if n in frame and n not in layers)
    for name in tuple(layers) + extra:
        a = frame[name]
        if a.ndim != 3 or a.shape[:2] != (h, w):
            raise ValueError(f"{frame.path or 'frame'}: layer {name!r} has shape {a.shape}, expected ({h}, {w}, C)")
        if name in THREE_CHANNEL and a.shape[2] != 3:
            raise ValueError(f"{frame.path or 'frame'}: layer {name!r} must have 3 channels, got {a.shape[2]}")
    if h == 0 or w == 0:
        raise ValueError(f"{frame.path or 'frame'}: empty image ({w}x{h})")
    if SAMPLE_COUNT in frame:
        n = frame[SAMPLE_COUNT]
        empty, single = int((n < 1).sum()), int(((n >= 1) & (n < 2)).sum())
        if empty:
            warnings.warn(f"{frame.path or 'frame'}: {empty} pixel(s) have no samples ({SAMPLE_COUNT} < 1): the "
                          f"denoiser takes their colour and variances for a pixel known exactly", stacklevel=3)
        if single and any(k.endswith("Variance") for k in frame.keys()):
            warnings.warn(f"{frame.path or 'frame'}: {single} pixel(s) have one sample ({SAMPLE_COUNT}), whose "
                          f"variance cannot be estimated; a variance of 0 there reads as a pixel known exactly",
                          stacklevel=3)
    return h, w


def color_variance(frame: Frame) -> np.ndarray | None:
    """The variance of the noisy colour's pixel mean: ``colorVariance``, or the split's two variances summed; None
    where the frame has neither."""
    if "colorVariance" in frame:
        return frame["colorVariance"]
    if "diffuseVariance" in frame and "specularVariance" in frame:
        return frame["diffuseVariance"] + frame["specularVariance"]
    return None


def normal_of(frame: Frame, crop, device):
    """The frame's normal over ``crop`` (a ``(rows, columns)`` pair of slices) as a ``(1, 3, h, w)`` float32 tensor
    (finite: the reader replaced what was not). Not clamped here: the models that read it clamp it to [-1, 1]
    themselves (``UNetBranch.guide_pyramid``, ``RowStream.feed``), as the contract's normal promises."""
    from ..features import frame_to_tensors

    return frame_to_tensors(frame, ("normal",), crop, device)["normal"]


def with_normal(net, inputs: dict, frame: Frame, crop, device) -> dict:
    """``inputs`` with the frame's normal over ``crop`` as ``inputs["normal"]`` where ``net`` reads it
    (:attr:`~kpcn.models.DenoiserModel.reads_normal`), in place; returned."""
    if net.reads_normal:
        inputs["normal"] = normal_of(frame, crop, device)
    return inputs


def write_output(out_path, color: np.ndarray, frame: Frame, result: DenoiseResult) -> None:
    """Write the denoised ``color`` and ``result``'s layers to ``out_path`` (atomically), with the input's albedo,
    normal, depth and sample count (:data:`~kpcn.io.SAMPLE_COUNT`) and a header that names the source, the model and
    the seconds."""
    layers = {"color": color, **result.layers}
    for name in ("albedo", "normal", "depth", SAMPLE_COUNT):
        if name in frame:
            layers[name] = frame[name]
    meta = {k: v for k, v in frame.meta.items()
            if k in ("spp", "seed", "scene", "renderTimeSeconds", "dataWindow", "displayWindow")}
    meta.update(
        {
            "source": os.path.abspath(frame.path) if frame.path else "<in-memory frame>",
            "denoiser": result.model_name,
            "denoiseSeconds": float(result.stats.seconds),
        }
    )
    write_exr(out_path, layers, meta)
