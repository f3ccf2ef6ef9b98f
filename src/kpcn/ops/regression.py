"""First-order regression of a denoiser's residual on guide features: the detail a kernel cannot keep.

A kernel-predicting denoiser outputs a weighted mean of noisy neighbours, so shading detail that lives in the
guides but not yet in the noisy colour (a bump-mapped wall's glints at 4-16 spp) is averaged away. The residual
``r = log1p(noisy) - log1p(denoised)`` holds that detail plus the noise. Within each ``(2 radius + 1)²`` window a
ridge regression of ``r`` on the guide ``g`` (e.g. the normal) keeps only the part that varies with ``g``:

    A = (cov(g, g) + eps I)^-1 cov(g, r),      detail = (g - mean(g)) · mean_window(A)

and the output is ``expm1(log1p(denoised) + detail)``. Where the guide is flat over the window ``cov(g, g)`` is 0,
``A`` is 0 and the pixel is left as it is; a converged input (``r`` = 0) is left as it is. The same construction as
the guided filter (He et al. 2010) and the first-order feature regression of Bitterli et al. 2016, applied to the
residual of a learned denoiser rather than to the noisy colour.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["box_mean", "residual_regression"]


def box_mean(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over the ``(2 radius + 1)²`` window around each pixel, edges reflected.

    Args:
        x: ``(B, C, H, W)``.
    Returns:
        ``(B, C, H, W)``.
    """
    if radius <= 0:
        return x
    k = 2 * radius + 1
    pad = F.pad(x, (radius, radius, radius, radius), mode="reflect" if min(x.shape[-2:]) > radius else "replicate")
    return F.avg_pool2d(pad, k, stride=1)


def residual_regression(denoised: torch.Tensor, noisy: torch.Tensor, guide: torch.Tensor, *, radius: int = 5,
                        eps: float = 0.03) -> torch.Tensor:
    """Add back to ``denoised`` the part of its log residual that a local linear model of ``guide`` explains.

    Args:
        denoised: ``(B, 3, H, W)`` the denoiser's output (linear radiance, >= 0).
        noisy: ``(B, 3, H, W)`` the noisy input colour.
        guide: ``(B, K, H, W)`` guide features (e.g. the normal, K = 3).
        radius: window radius; the output depends on pixels up to ``2 radius`` away.
        eps: ridge on the guide's window covariance: larger keeps less of the residual.
    Returns:
        ``(B, 3, H, W)``.
    """
    if denoised.shape != noisy.shape or denoised.shape[-2:] != guide.shape[-2:] or denoised.dim() != 4:
        raise ValueError(f"residual_regression: denoised {tuple(denoised.shape)}, noisy {tuple(noisy.shape)} and "
                         f"guide {tuple(guide.shape)} must be (B, 3, H, W), (B, 3, H, W) and (B, K, H, W)")
    base = torch.log1p(denoised.clamp_min(0))
    r = torch.log1p(noisy.clamp_min(0)) - base
    b, k, h, w = guide.shape
    c = r.shape[1]
    mg = box_mean(guide, radius)
    mr = box_mean(r, radius)
    gg = (guide[:, :, None] * guide[:, None]).reshape(b, k * k, h, w)
    cgg = box_mean(gg, radius).reshape(b, k, k, h, w) - mg[:, :, None] * mg[:, None]
    gr = (guide[:, :, None] * r[:, None]).reshape(b, k * c, h, w)
    cgr = box_mean(gr, radius).reshape(b, k, c, h, w) - mg[:, :, None] * mr[:, None]
    eye = torch.eye(k, dtype=guide.dtype, device=guide.device)
    lhs = (cgg.permute(0, 3, 4, 1, 2) + eps * eye).to(torch.float64)
    coef = torch.linalg.solve(lhs, cgr.permute(0, 3, 4, 1, 2).to(torch.float64)).to(guide.dtype)  # (B, H, W, K, C)
    coef = box_mean(coef.permute(0, 3, 4, 1, 2).reshape(b, k * c, h, w), radius).reshape(b, k, c, h, w)
    detail = ((guide - mg)[:, :, None] * coef).sum(1)
    return torch.expm1(base + detail)
