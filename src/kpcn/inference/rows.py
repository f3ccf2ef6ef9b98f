"""A whole frame through a model's row streams (:class:`kpcn.models.unet_rows.RowStream`).

For models that offer them (:meth:`~kpcn.models.DenoiserModel.row_stream`: the ``stem: half`` U-Net),
:func:`kpcn.inference.denoise_result` runs a frame it would denoise whole on the CPU, of at least
:func:`rows_min_pixels`, this way instead (light groups and other ``layers=`` too): the
features are built a band of rows at a time (with the whole frame's depth scale or noise precision,
and the one row below that the forward differences read), fed to each branch's stream, the networks
run once at half resolution, and the output is assembled band by band (each band's branches
reconstructed into colour at once). Same result as the whole-frame call to float rounding, in about
half the memory and less time (``python -m kpcn.bench denoise``).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..features import frame_to_tensors
from ..io import Frame
from ..models import unet_rows
from ..models.unet_rows import clamped_rows
from ..ops import native
from .aovs import aov_signals, compose_aovs
from .frames import normal_of

__all__ = ["denoise_rows", "supports_rows", "rows_min_pixels", "ROWS_MIN_PIXELS", "ROWS_MIN_PIXELS_PYTORCH",
           "ROWS_MIN_PIXELS_NATIVE"]

#: frames smaller than this go whole at once on the PyTorch paths: below about 0.3 MP the bands' per-call overhead
#: outweighs what they save (the default U-Net on 2 threads: 256² 0.084 s in bands against 0.073 s whole, 512² 0.29
#: against 0.24; 640² 0.65 against 0.80, 1024² 1.25–1.45 against 1.6–1.7)
ROWS_MIN_PIXELS_PYTORCH = 600 * 600
#: ... and with the native kernels (kpcn.ops.native), whose bands cost less than the whole frame's passes at every
#: size measured (thirty-seventh session, 2 threads, bands against whole: 128² 10.3 against 11.2 ms, 256² 44 against
#: 51, 512² 136 against 159)
ROWS_MIN_PIXELS_NATIVE = 128 * 128
#: a fixed threshold (pixels) instead of the one the kernels in use choose (:func:`rows_min_pixels`); None: theirs
ROWS_MIN_PIXELS: int | None = None


def rows_min_pixels() -> int:
    """The smallest frame (pixels) taken in row bands: :data:`ROWS_MIN_PIXELS` where set, else
    :data:`ROWS_MIN_PIXELS_NATIVE` with the native kernels and :data:`ROWS_MIN_PIXELS_PYTORCH` without."""
    if ROWS_MIN_PIXELS is not None:
        return ROWS_MIN_PIXELS
    return ROWS_MIN_PIXELS_NATIVE if native.library() is not None else ROWS_MIN_PIXELS_PYTORCH


def supports_rows(net, height: int | None = None, width: int | None = None) -> bool:
    """Whether ``net`` has row streams for every branch (and, given a size, whether the frame is large enough
    for bands to pay: :func:`rows_min_pixels`)."""
    if not getattr(net, "streams_rows", False):
        return False
    return height is None or width is None or height * width >= rows_min_pixels()


def denoise_rows(frame: Frame, net, spec, frame_value, branches, device, plans=(), band: int | None = None
                 ) -> tuple[np.ndarray, dict[str, np.ndarray], int]:
    """Denoise ``frame`` (sanitised, the spec's layers) with ``net``'s row streams.

    ``branches``: those to run (the others are zero); ``frame_value``: the whole frame's depth scale or
    noise precision; ``plans``: other layers to denoise with the beauty's kernels (:mod:`.aovs`).

    Returns:
        the colour ``(H, W, 3)`` float32, ``{plan name: (H, W, 3)}``, and the number of bands (of ``band``
        rows, default :data:`kpcn.models.unet_rows.BAND_ROWS`).
    """
    band = int(band or unet_rows.BAND_ROWS)
    band += band % 2
    h, w = frame.shape
    out = np.empty((h, w, 3), dtype=np.float32)
    layers_out = {p.name: np.empty((h, w, 3), dtype=np.float32) for p in plans}
    streams = {b: net.row_stream(b, h, w, device) for b in branches}
    shared: dict = {}  # the guided blend's tap weights follow from the normal alone: one computation a band for all
    first = next(iter(streams.values()), None)
    for s in streams.values():
        s.guide_weights_cache = shared
        s.share_normal(first)  # one copy of the frame's normal (edge_upsample), filled by the first stream
    hp, wp = next(iter(streams.values())).padded_size
    layers = spec.layers_for(branches)
    albedo = torch.empty(1, 3, h, w, device=device)
    filters_albedo = any(s.branch.albedo_kernel for s in streams.values())

    def rows_of(t, r0, r1, c0):  # rows [r0, r1) of the padded frame from a crop starting at row c0
        x = clamped_rows(t, r0 - c0, r1 - c0)
        return F.pad(x, (0, wp - w, 0, 0), mode="replicate") if wp > w else x

    for r0 in range(0, hp, band):
        r1 = min(r0 + band, hp)
        c0, c1 = min(r0, h - 1), min(r1 + spec.halo, h)  # padded rows >= h repeat row h - 1
        crop = (slice(c0, c1), slice(0, w))
        inputs = spec.build(frame_to_tensors(frame, layers, crop, device, contiguous=False), frame_value, branches)
        n_rows = rows_of(normal_of(frame, crop, device), r0, r1, c0) if net.reads_normal else None
        if r0 < h:
            albedo[..., r0:min(r1, h), :] = inputs["albedo"][..., : min(r1, h) - r0, :]
        signals = {}
        # the albedo over the padded rows: for the layers' demodulation and a branch that filters it (albedo_kernel)
        a_rows = rows_of(inputs["albedo"], r0, r1, c0) if plans or filters_albedo else None
        if plans:  # the layers each branch filters, over the same padded rows
            signals = aov_signals(plans, branches, lambda n: rows_of(frame_to_tensors(frame, (n,), crop, device)[n], r0, r1, c0),
                                  a_rows)
        for b, s in streams.items():
            s.feed(r0, rows_of(inputs[b], r0, r1, c0), signals.get(b), a_rows if s.branch.albedo_kernel else None,
                   n_rows)
        del inputs, signals
    for s in streams.values():
        s.run()
    beauty = unet_rows.RowStream.BEAUTY
    for r0 in range(0, h, band):
        r1 = min(r0 + band, hp)
        n = min(r1, h) - r0
        res = {b: {k: v[..., :n, :w] for k, v in s.rows(r0, r1).items()} for b, s in streams.items()}
        noisy = {b: {k: v[..., r0:r0 + n, :w] for k, v in s.signals.items()} for b, s in streams.items()} if plans else {}
        outs = {b: r[beauty] for b, r in res.items()}
        # the albedo the colour is remodulated with: a branch's own (albedo kernels), else the frame's
        a = next((r[unet_rows.RowStream.ALBEDO] for r in res.values() if unet_rows.RowStream.ALBEDO in r),
                 albedo[..., r0:r0 + n, :])
        color = spec.reconstruct(outs, {"albedo": a})
        out[r0:r0 + n] = color[0].float().permute(1, 2, 0).cpu().numpy()
        if plans:
            for name, v in compose_aovs(plans, branches, res, noisy, a, outs).items():
                layers_out[name][r0:r0 + n] = v[0].float().permute(1, 2, 0).cpu().numpy()
    return out, layers_out, -(-hp // band)
