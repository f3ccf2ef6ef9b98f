"""The detail stage after the network: shading detail the normal shows, added back to the denoised colour.

A kernel predictor's output is a weighted mean of noisy neighbours, so the shading of a bump-mapped surface
(glints on a bumpy glossy wall) is averaged away wherever the noise is not yet well below it, although the
frame's normal layer shows every bump. For models that declare ``detail_regression = (radius, eps, clip)`` (the
``detail_*`` fields of :class:`~kpcn.models.UNetConfig` and of KPCN's ``BranchConfig``), :func:`refine_detail` fits,
in each window, the denoised colour's log residual on the normal and adds back the fitted part
(:func:`~kpcn.ops.residual_regression`), no channel moved further from the denoised value than its noisy value,
nor by more than ``clip``.

It runs on the assembled frame a band of rows at a time (:func:`~kpcn.ops.residual_regression_rows`), so a tiled
or row-streamed run gives the same result as a whole-frame one, in about 60 MB more at 1080p, with one fit per 2×2
block (``stride 2``: on the validation scenes nearly the per-pixel figures, in about a third of the time).
Denoised light groups are scaled by the colour's per-pixel ratio, so they still add up to it; other layers (an AOV
filtered with a branch's kernels) are left as the kernels made them.
"""
from __future__ import annotations

import numpy as np
import torch

from ..ops.regression import residual_regression_rows

__all__ = ["refine_detail"]


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).permute(2, 0, 1)[None]


def refine_detail(color: np.ndarray, noisy: np.ndarray, normal: np.ndarray, radius: int, eps: float,
                  clip: float | None = None, layers: dict[str, np.ndarray] | None = None, noisy_scale: float = 1.0
                  ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The denoised ``color`` with the normal-guided detail of its residual to ``noisy`` added back.

    Args:
        color: ``(H, W, 3)`` the network's denoised colour (>= 0).
        noisy: ``(H, W, 3)`` the noisy input colour.
        normal: ``(H, W, 3)`` the frame's first-hit normal (0 where nothing was hit: a flat guide, no change).
        radius, eps, clip: the regression's window radius, ridge and clip (:func:`~kpcn.ops.residual_regression`).
        layers: denoised layers that add up to ``color`` (light groups), scaled by the same per-pixel ratio.
        noisy_scale: ``noisy`` × this is the noisy colour at the exposure ``color`` was denoised at (scaled a band
            at a time: no scaled copy of the frame's colour).
    Returns:
        ``(color, layers)``: new arrays, float32.
    """
    with torch.inference_mode():
        out = residual_regression_rows(_t(color), _t(noisy), _t(normal), radius=radius, eps=eps, stride=2,
                                       clip=clip, noisy_scale=noisy_scale)
    refined = np.ascontiguousarray(out[0].permute(1, 2, 0).numpy(), dtype=np.float32)
    scaled = {}
    if layers:
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(color > 0, refined / np.where(color > 0, color, 1), 1).astype(np.float32)
        scaled = {name: v * ratio for name, v in layers.items()}
    return refined, scaled
