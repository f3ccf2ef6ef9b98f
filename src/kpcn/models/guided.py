"""The U-Net's 2× upsampling guided by the frame's normal (``UNetConfig.edge_upsample``).

:func:`upsample2_guided` is :func:`~kpcn.models.layers.upsample2`'s bilinear upsampling with each of its four taps
also weighted by the similarity of a guide (the frame's normal) at the output pixel and at the tap, and the weights
renormalised: a coarse level's value does not bleed across an edge of the geometry. :func:`guided_weights` and
:func:`apply_guided` are the same in two steps, so maps that share a guide share the weights;
:func:`guide_pyramid` gives the guide at every level. One form serves inference and training: each output parity
``(row 2i + a, column 2j + b)`` is computed at the coarse resolution from shifted views (no full-resolution tap maps),
written into its slice of the result (autograd follows the slice writes).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .layers import pool2

__all__ = ["upsample2_guided", "guided_weights", "apply_guided", "guide_pyramid"]

#: the bilinear weights of the four taps: (near row, near column), (near, far), (far, near), (far, far)
_TAP_WEIGHTS = (9 / 16, 3 / 16, 3 / 16, 1 / 16)

#: for each output parity ``(a, b)`` (row 2i + a, column 2j + b), the coarse offsets of the four taps in the order of
#: :data:`_TAP_WEIGHTS`; far is -1 for an even index, +1 for an odd one
_PARITY_TAPS = {(a, b): ((0, 0), (0, 2 * b - 1), (2 * a - 1, 0), (2 * a - 1, 2 * b - 1))
                for a in (0, 1) for b in (0, 1)}


def _shifted(x: torch.Tensor):
    """A function giving ``x`` ``(B, C, H, W)`` shifted by ``(dy, dx)``: the value at ``(i + dy, j + dx)`` (a view of
    ``x`` replicate-padded by one: edges repeated)."""
    h, w = x.shape[-2:]
    xp = F.pad(x, (1, 1, 1, 1), mode="replicate")
    return lambda dy, dx: xp[..., 1 + dy:1 + dy + h, 1 + dx:1 + dx + w]


def guided_weights(guide_fine: torch.Tensor, guide_coarse: torch.Tensor, sigma: float) -> tuple[torch.Tensor, ...]:
    """The four tap weights ``(B, 1, 2H, 2W)`` of :func:`upsample2_guided` (normalised: they sum to one), from the
    guides alone, for :func:`apply_guided` to use on as many maps as share them."""
    if not sigma > 0:
        raise ValueError(f"upsample2_guided: sigma must be > 0, got {sigma!r}")
    h, w = guide_coarse.shape[-2:]
    if guide_fine.shape[-2:] != (2 * h, 2 * w) or guide_fine.shape[:2] != guide_coarse.shape[:2]:
        raise ValueError(f"upsample2_guided: guide_fine {tuple(guide_fine.shape)} and guide_coarse "
                         f"{tuple(guide_coarse.shape)} must be (B, G, 2H, 2W) and (B, G, H, W)")
    dist = [guide_fine.new_empty(guide_fine.shape[0], 1, 2 * h, 2 * w) for _ in range(4)]
    shift = _shifted(guide_coarse.to(guide_fine.dtype))
    for (a, b), offsets in _PARITY_TAPS.items():
        fine = guide_fine[..., a::2, b::2]
        for d, (dy, dx) in zip(dist, offsets):
            d[..., a::2, b::2] = (fine - shift(dy, dx)).square().sum(1, keepdim=True)
    # relative to the nearest tap's distance: that tap's factor is 1, so the sum never underflows to 0
    nearest = torch.minimum(torch.minimum(dist[0], dist[1]), torch.minimum(dist[2], dist[3]))
    scale = -0.5 / (sigma * sigma)
    wgt = [torch.exp((d - nearest) * scale) * bw for d, bw in zip(dist, _TAP_WEIGHTS)]
    total = wgt[0] + wgt[1] + wgt[2] + wgt[3]
    return tuple(v / total for v in wgt)


def apply_guided(x: torch.Tensor, weights: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``(B, C, H, W) -> (B, C, 2H, 2W)``: the four bilinear taps of ``x`` weighted by :func:`guided_weights`."""
    h, w = x.shape[-2:]
    if weights[0].shape[-2:] != (2 * h, 2 * w):
        raise ValueError(f"upsample2_guided: x {tuple(x.shape)} and weights {tuple(weights[0].shape)} must be "
                         f"(B, C, H, W) and (B, 1, 2H, 2W)")
    out = x.new_empty(*x.shape[:-2], 2 * h, 2 * w)
    shift = _shifted(x)
    for (a, b), offsets in _PARITY_TAPS.items():
        o = out[..., a::2, b::2]
        (dy, dx), wt = offsets[0], weights[0]
        o.copy_(shift(dy, dx) * wt[..., a::2, b::2])
        for (dy, dx), wt in zip(offsets[1:], weights[1:]):
            o.addcmul_(shift(dy, dx), wt[..., a::2, b::2])
    return out


def upsample2_guided(x: torch.Tensor, guide_fine: torch.Tensor, guide_coarse: torch.Tensor,
                     sigma: float) -> torch.Tensor:
    """Joint bilateral 2× upsampling: :func:`~kpcn.models.layers.upsample2`'s four bilinear taps of ``x``, each also
    weighted by ``exp(-|g_p - g_q|² / (2 σ²))``, ``g_p`` the fine guide at the output pixel and ``g_q`` the coarse
    guide at the tap, and renormalised. A tap across an edge of the guide (another surface's normal) then gives
    little, so a coarse level's value does not bleed across it. A constant guide gives the bilinear result.

    Args:
        x: ``(B, C, H, W)``.
        guide_fine: ``(B, G, 2H, 2W)``, e.g. the frame's normal.
        guide_coarse: ``(B, G, H, W)``, the same guide at ``x``'s resolution (:func:`~kpcn.models.layers.pool2` of
            the fine one).
        sigma: > 0, in the guide's units.
    Returns:
        ``(B, C, 2H, 2W)``.
    """
    return apply_guided(x, guided_weights(guide_fine.to(x.dtype), guide_coarse, sigma))


def guide_pyramid(guide: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """``guide`` and its :func:`~kpcn.models.layers.pool2` pyramid: ``levels`` maps, each half the size of the one
    before."""
    out = [guide]
    for _ in range(levels - 1):
        out.append(pool2(out[-1]))
    return out
