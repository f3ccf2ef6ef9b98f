"""A flip-and-transpose ensemble: the mean of the denoised views of one frame (``denoise(..., views=N)``).

A network's output is not exactly equivariant to mirroring: the same noisy frame, flipped, gives a slightly
different estimate, and the differences are the network's own error, not the frame's. :func:`ensemble_result`
denoises ``views`` mirrored copies of the frame (the dihedral group's elements in a fixed order: identity, flip in
x, flip in y, both, then each of those transposed), maps each result back, and averages them. On the validation
scenes (docs/measured.md, thirty-fifth session) 8 views took the default from 36.18 to 36.35 dB at 4 spp and from
38.77 to 38.98 at 16, with lower relMSE and higher SSIM, for 8 times the time: a setting for final frames whose
render took far longer than the denoiser, not for previews.

Every view is an ordinary :func:`~kpcn.inference.denoise_result` call on the mirrored layers (the features are
built on the mirrored frame, as training's flips and transposes see them), so tiles, row bands, skipping, light
groups and the detail stage work in each exactly as without views. The mean of the light groups still adds up to
the mean colour. With all 8 views the result is exactly invariant to mirroring or transposing the input (to float
rounding); with 4, to flips.
"""
from __future__ import annotations

import os
import time

import numpy as np

from ..io import Frame
from .frames import as_frame, check_output, default_model, write_output
from .results import DenoiseResult
from .weights import load_model, resolve_device

__all__ = ["VIEWS", "view", "unview", "ensemble_result"]

#: the view counts :func:`ensemble_result` takes: the first 1, 2, 4 or 8 of the dihedral group's elements
VIEWS = (1, 2, 4, 8)


def view(a: np.ndarray, k: int) -> np.ndarray:
    """View ``k`` (0 ... 7) of an ``(H, W, C)`` layer: bit 0 flips x, bit 1 flips y, bit 2 transposes (after them)."""
    if k & 1:
        a = a[:, ::-1]
    if k & 2:
        a = a[::-1]
    if k & 4:
        a = a.transpose(1, 0, 2)
    return np.ascontiguousarray(a)


def unview(a: np.ndarray, k: int) -> np.ndarray:
    """The inverse of :func:`view`: an ``(H, W, C)`` result of view ``k`` back in the frame's orientation."""
    if k & 4:
        a = a.transpose(1, 0, 2)
    if k & 2:
        a = a[::-1]
    if k & 1:
        a = a[:, ::-1]
    return np.ascontiguousarray(a)


def check_views(views) -> int:
    """``views`` as an int, or a ValueError naming the counts :data:`VIEWS` allows."""
    if isinstance(views, bool) or views not in VIEWS:
        raise ValueError(f"denoise: views must be one of {', '.join(map(str, VIEWS))} (mirrored copies of the frame "
                         f"to average), got {views!r}")
    return int(views)


def ensemble_result(src, model=None, out_path=None, *, views: int, device="auto", trust_pickle: bool = False,
                    **kw) -> DenoiseResult:
    """The mean of ``views`` mirrored denoisings of ``src`` (a path, :class:`~kpcn.io.Frame` or dict of layers),
    as a :class:`DenoiseResult` whose stats are the first view's with the summed ``seconds`` (``stats.views``
    says how many). ``model``, ``out_path``, ``device``, ``trust_pickle`` and ``kw`` as
    :func:`~kpcn.inference.denoise_result` takes them; the output file is written once, from the mean."""
    from .pipeline import denoise_result  # the pipeline imports this module

    n = check_views(views)
    check_output(out_path, src)  # refused before any work, as a single view is
    frame, read_s = as_frame(src, ())
    dev = resolve_device(device)
    if model is None:
        model = default_model(frame, stacklevel=3)
    net = load_model(model, dev, trust_pickle=trust_pickle)  # once for every view
    color, layers, first, seconds, detail_s = None, {}, None, 0.0, 0.0
    for k in range(n):
        part = Frame({name: view(a, k) for name, a in frame.layers.items()}, dict(frame.meta), frame.path,
                     dict(frame.nonfinite))
        res = denoise_result(part, net, None, device=dev, **kw)
        seconds += res.stats.seconds
        detail_s += res.stats.detail_seconds
        c = unview(res.color, k)
        color = c if color is None else color + c
        for name, v in res.layers.items():
            v = unview(v, k)
            layers[name] = v if name not in layers else layers[name] + v
        first = first or res
    scale = np.float32(1.0 / n)
    stats = first.stats
    stats.seconds, stats.detail_seconds, stats.read_seconds, stats.views = seconds, detail_s, read_s, n
    result = DenoiseResult(color * scale, stats, first.model_name, layers={k: v * scale for k, v in layers.items()})
    if out_path is not None:
        t0 = time.perf_counter()
        write_output(out_path, result.color, frame, result)
        stats.write_seconds = time.perf_counter() - t0
        result.out_path = os.fspath(out_path)
    return result
