"""Maps of where a frame's samples went: smooth random regions, as an adaptive sampler leaves them.

An adaptive sampler (Salehi et al. 2022, whose denoiser is trained on Perlin-noise sample maps) gives more samples
to some regions of a frame than to others, so the frame's spp varies from pixel to pixel. :func:`region_mask` draws
such regions; :func:`kpcn.render.mix_frames` makes a frame with them from two renders at different spp, and
training mixes patches the same way (``data.spp_mix``, :func:`kpcn.augment.mix_patches`).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["region_mask"]


def region_mask(shape: tuple[int, int], rng: np.random.Generator, cell: int | None = None,
                quantile: float | None = None) -> np.ndarray:
    """``(H, W)`` bool: the pixels of a smooth random field above a quantile of it.

    The field is uniform noise on a grid of ``cell``-pixel cells (None: 4, 8, 16 or 32, drawn), bilinearly
    upsampled; ``quantile`` (None: drawn in [0.2, 0.8]) is the share of the pixels left ``False``, in regions a few
    cells across.
    """
    h, w = (int(v) for v in shape)
    cell = int(2 ** rng.integers(2, 6)) if cell is None else int(cell)
    q = float(rng.uniform(0.2, 0.8)) if quantile is None else float(quantile)
    if cell < 1 or not 0.0 <= q <= 1.0:
        raise ValueError(f"region_mask: cell must be >= 1 and quantile in [0, 1], got {cell} and {q}")
    field = torch.from_numpy(rng.random((1, 1, h // cell + 2, w // cell + 2)).astype(np.float32))
    up = F.interpolate(field, scale_factor=cell, mode="bilinear", align_corners=False)[0, 0, :h, :w]
    return (up > torch.quantile(up.flatten(), q)).numpy()
