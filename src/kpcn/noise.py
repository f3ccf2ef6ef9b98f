"""A frame's noise level, estimated from its colour and guides alone (no variance layer, no sample count).

A colour + albedo + normal input says nothing of how many samples it holds.
Without that, a lone bright pixel in a nearly converged frame (a small
highlight) looks just like a firefly in a 2-spp frame, and a denoiser that
learnt to remove the one blurs the other. :func:`noise_level` measures how
noisy the frame is as a whole, so a model can tell the two apart.

The estimate: on pixels where the guides are flat (albedo and normal change
by less than :data:`FLAT_ALBEDO` / :data:`FLAT_NORMAL` in a 4-neighbour
Laplacian) and that see geometry (``|normal| > 0.5``), the Laplacian of the
colour's channel mean, relative to the local 3×3 mean plus 5 % of the frame's
median (not its mean, which a few fireflies would raise), clamped at 1 and
averaged. Texture and geometry edges are in the guides and so left out; what is
left is noise plus smooth shading. It is

* exposure-invariant (every term is a ratio of colours),
* robust to fireflies (each pixel counts at most 1, and the frame's scale is a median),
* falls with spp until shading detail is left: by about ``sqrt(2)`` a doubling on
  the Mitsuba training scenes, by less on the Cycles ones (docs/measured.md). Its
  level differs between scenes and renderers: it orders the frames of a scene by
  noise, it does not give their spp.

:func:`noise_precision` maps it to ``clamp(-log2(level), 0, PRECISION_MAX)``,
"bits of precision", which the ``color_albedo_normal_noise`` input spec
(:mod:`kpcn.inputs`) feeds the network as one constant channel. The value is a
property of the *whole frame*: tiles are given the frame's value, so tiled
inference equals untiled.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["noise_level", "noise_precision", "PRECISION_MAX", "FLAT_ALBEDO", "FLAT_NORMAL", "REVISION"]

#: bumped when the estimate changes (stores of built patches made with another are rebuilt)
REVISION = 1

#: largest precision (a frame with no measurable noise: black, constant, or converged)
PRECISION_MAX = 16.0
#: pixels whose albedo / normal Laplacian exceeds these are edges of the guides, not noise
FLAT_ALBEDO = 0.01
FLAT_NORMAL = 0.02
#: fewer flat pixels than this fraction of the frame: all pixels are used
MIN_FLAT_FRACTION = 0.05
#: pixels sampled for the mean (the estimate of a 4K frame need not read every pixel)
MAX_PIXELS = 1 << 20


def _laplacian(x: torch.Tensor) -> torch.Tensor:
    """``x - mean of its 4 neighbours`` on the interior ``(B, C, H-2, W-2)``."""
    return x[..., 1:-1, 1:-1] - 0.25 * (x[..., :-2, 1:-1] + x[..., 2:, 1:-1] + x[..., 1:-1, :-2] + x[..., 1:-1, 2:])


def _at_most(values: torch.Tensor, n: int = MAX_PIXELS) -> torch.Tensor:
    """An evenly strided subset of at most ``n`` of ``values`` (1-D): deterministic, the same for every run."""
    return values[:: -(-values.numel() // n)] if values.numel() > n else values


def _check(name: str, x: torch.Tensor, like: torch.Tensor | None = None) -> None:
    if not isinstance(x, torch.Tensor) or x.dim() != 4 or x.shape[1] not in (1, 3):
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"noise_level: {name} must be a (B, 3, H, W) tensor, got {shape}")
    if like is not None and (x.shape[0], *x.shape[2:]) != (like.shape[0], *like.shape[2:]):
        raise ValueError(f"noise_level: {name} is {tuple(x.shape)} but color is {tuple(like.shape)}")


def noise_level(color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Relative noise of each frame of a batch: ``(B, 1, 1, 1)``, in [0, 1].

    Args:
        color: ``(B, 3, H, W)`` noisy radiance (NaN/Inf count as 0, negatives are clamped).
        albedo: ``(B, 3, H, W)`` the albedo guide.
        normal: ``(B, 3, H, W)`` the normal guide (zero where no geometry was hit).

    Returns:
        The mean clamped relative Laplacian over flat geometry pixels; 0 for a
        frame smaller than 3×3 or one whose colour is constant.
    """
    _check("color", color)
    _check("albedo", albedo, color)
    _check("normal", normal, color)
    b, _, h, w = color.shape
    out = torch.zeros(b, 1, 1, 1, dtype=torch.float32, device=color.device)
    if h < 3 or w < 3:
        return out
    clean = lambda x: torch.nan_to_num(x.float(), nan=0.0, posinf=0.0, neginf=0.0)  # noqa: E731
    c = clean(color).clamp_min(0.0).mean(dim=1, keepdim=True)
    a, n = clean(albedo).clamp_min(0.0), clean(normal)
    for i in range(b):
        ci = c[i : i + 1]
        local = F.avg_pool2d(ci, 3, stride=1)
        scale = local + 0.05 * _at_most(ci.flatten()).median() + 1e-12
        rel = (_laplacian(ci).abs() / scale).clamp_max(1.0)
        flat = (_laplacian(a[i : i + 1]).abs().amax(dim=1, keepdim=True) < FLAT_ALBEDO) \
            & (_laplacian(n[i : i + 1]).abs().amax(dim=1, keepdim=True) < FLAT_NORMAL) \
            & (n[i : i + 1, :, 1:-1, 1:-1].norm(dim=1, keepdim=True) > 0.5)
        if flat.float().mean() < MIN_FLAT_FRACTION:
            flat = torch.ones_like(flat)
        out[i] = _at_most(rel[flat]).mean()
    return out


def noise_precision(color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """``clamp(-log2(noise_level), 0, PRECISION_MAX)`` per frame, ``(B, 1, 1, 1)``: "bits of precision",
    1.7 (Mitsuba) to 4.2 (Cycles) at 2 spp on the training scenes, up to about 0.5 more per doubling of spp,
    :data:`PRECISION_MAX` for a frame with no measurable noise."""
    level = noise_level(color, albedo, normal)
    return (-torch.log2(level.clamp_min(2.0**-PRECISION_MAX))).clamp(0.0, PRECISION_MAX)
