"""A whole frame through a model's row streams (:class:`kpcn.models.unet_rows.RowStream`).

For models that offer them (:meth:`~kpcn.models.DenoiserModel.row_stream`: the ``stem: half`` U-Net),
:func:`kpcn.inference.denoise_result` runs a frame it would denoise whole this way instead: the
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

from ..io import Frame
from ..models import unet_rows
from ..models.unet_rows import clamped_rows

__all__ = ["denoise_rows", "supports_rows"]


def supports_rows(net) -> bool:
    """Whether ``net`` has row streams for every branch."""
    fn = getattr(net, "row_stream", None)
    return callable(fn) and bool(getattr(net, "streams_rows", False))


def denoise_rows(frame: Frame, net, spec, frame_value, branches, device, tensors, band: int | None = None) -> tuple[np.ndarray, int]:
    """Denoise ``frame`` (sanitised, the spec's layers) with ``net``'s row streams: the colour ``(H, W, 3)``
    float32, and the number of bands (of ``band`` rows, default :data:`kpcn.models.unet_rows.BAND_ROWS`).

    ``branches``: those to run (the others are zero); ``frame_value``: the whole frame's depth scale or
    noise precision; ``tensors(frame, layers, crop, device)``: the layer tensors of a crop (the pipeline's).
    """
    band = int(band or unet_rows.BAND_ROWS)
    band += band % 2
    h, w = frame[spec.layers[0]].shape[:2]
    out = np.empty((h, w, 3), dtype=np.float32)
    streams = {b: net.row_stream(b, h, w, device) for b in branches}
    hp, wp = next(iter(streams.values())).padded_size
    layers = spec.layers_for(branches)
    albedo = torch.empty(1, 3, h, w, device=device)
    for r0 in range(0, hp, band):
        r1 = min(r0 + band, hp)
        c0, c1 = min(r0, h - 1), min(r1 + spec.halo, h)  # padded rows >= h repeat row h - 1
        inputs = spec.build(tensors(frame, layers, (slice(c0, c1), slice(0, w)), device), frame_value, branches)
        if r0 < h:
            albedo[..., r0:min(r1, h), :] = inputs["albedo"][..., : min(r1, h) - r0, :]
        for b, s in streams.items():
            x = clamped_rows(inputs[b], r0 - c0, r1 - c0)
            s.feed(r0, F.pad(x, (0, wp - w, 0, 0), mode="replicate") if wp > w else x)
        del inputs
    for s in streams.values():
        s.run()
    for r0 in range(0, h, band):
        r1 = min(r0 + band, hp)
        n = min(r1, h) - r0
        outs = {b: s.rows(r0, r1)[..., :n, :w] for b, s in streams.items()}
        color = spec.reconstruct(outs, {"albedo": albedo[..., r0:r0 + n, :]})
        out[r0:r0 + n] = color[0].float().permute(1, 2, 0).cpu().numpy()
    return out, -(-hp // band)
