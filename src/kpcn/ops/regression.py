"""First-order regression of a denoiser's residual on guide features: the detail a kernel cannot keep.

A kernel-predicting denoiser outputs a weighted mean of noisy neighbours, so shading detail that lives in the
guides but not yet in the noisy colour (a bump-mapped wall's glints at 4-16 spp) is averaged away. The residual
``r = log1p(noisy) - log1p(denoised)`` holds that detail plus the noise. Within each ``(2 radius + 1)²`` window a
ridge regression of ``r`` on the guide ``g`` (e.g. the normal) keeps only the part that varies with ``g``:

    A = (cov(g, g) + eps I)^-1 cov(g, r),      detail = mean_window(A) · g - mean_window(A · mean(g))

and the output is ``expm1(log1p(denoised) + detail)`` (the guided filter's form without its mean term: the
denoiser's local mean is kept). Where the guide is flat over the window ``cov(g, g)`` is 0, ``A`` is 0 and the
pixel is left as it is; a converged input (``r`` = 0) is left as it is. With ``bound`` (the default) ``detail`` is
clipped to ``[-|r|, |r|]``: no output channel moves further from the denoised value (in ``log1p``) than its noisy
value is, so no detail is carried into a pixel whose input lacks it (a black pixel beside a bumpy highlight stays
black). ``clip`` bounds both what the fit sees and the detail by a constant as well (see the argument). Clipping to
``[min(0, r), max(0, r)]`` instead (the output between the denoised and the noisy value) lost
16-22 % of the SSIM gain at 4-16 spp on the validation scenes.

Windows that cross the frame's edge average the pixels they hold. With ``stride = 2`` one fit serves each 2×2
block of pixels: its statistics are the means of the per-pixel terms (``g``, ``r``, ``g gᵀ``, ``g r``) over a window
of ``2 (radius // 2) + 1`` blocks either way, so the pixel-scale variance of the guide stays in them, and each pixel
applies its block's coefficients to its own guide. A quarter of the solves and of the window sums; on the 18
validation scenes it gave the per-pixel figures to within 0.03 dB, 0.5 % of relMSE and 0.0004 SSIM (docs/measured.md).
Pooling the guide 2×2 before the products, as the fast guided filter of He and Sun 2015 does, lost a third of the
gain: bump detail lives at the pixel scale. The construction is the guided filter's (He et al. 2010) and that of
the first-order feature regression of Bitterli et al. 2016, applied to the residual of a learned denoiser rather
than to the noisy colour.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .fused import residual_regression_native

__all__ = ["box_mean", "regression_reach", "residual_regression", "residual_regression_rows"]


def _inside(n: int, radius: int, stride: int, like: torch.Tensor) -> torch.Tensor:
    """For each of the ``ceil(n / stride)`` window centres ``0, stride, ...``, the fraction of its ``2 radius + 1``
    positions that lie in ``[0, n)``."""
    p = torch.arange(0, n, stride, dtype=like.dtype, device=like.device)
    return ((p + radius).clamp(max=n - 1) - (p - radius).clamp(min=0) + 1) / (2 * radius + 1)


def box_mean(x: torch.Tensor, radius: int, stride: int = 1) -> torch.Tensor:
    """Mean over the ``(2 radius + 1)²`` window around each pixel (two 1-D depthwise convolutions; at the frame's
    edges the mean of the window's pixels inside it), at every pixel or, with ``stride 2``, at every other one.

    Args:
        x: ``(B, C, H, W)``; channels-last memory makes it several times faster for a few tens of channels.
    Returns:
        ``(B, C, ceil(H / stride), ceil(W / stride))``, in ``x``'s memory format.
    """
    if radius <= 0 and stride == 1:
        return x
    c, h, w = x.shape[1:]
    k = 2 * radius + 1
    y = F.conv2d(x, x.new_full((c, 1, 1, k), 1.0 / k), stride=(1, stride), padding=(0, radius), groups=c)
    y = F.conv2d(y, x.new_full((c, 1, k, 1), 1.0 / k), stride=(stride, 1), padding=(radius, 0), groups=c)
    return y / (_inside(h, radius, stride, x)[:, None] * _inside(w, radius, stride, x))


def _solve(lhs: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """``lhs⁻¹ rhs`` for symmetric positive definite ``lhs (..., K, K)``, ``rhs (..., K, C)`` (guides of other than
    three channels; :func:`_fit` solves the 3 × 3 systems by cofactors itself)."""
    if lhs.shape[-1] == 1:
        return rhs / lhs
    return torch.linalg.solve(lhs, rhs)


def _box(x: torch.Tensor, radius: int, stride: int = 1) -> torch.Tensor:
    """:func:`box_mean` of a planar ``(B, C, H, W)`` tensor through channels-last memory, back to planar."""
    return box_mean(x.contiguous(memory_format=torch.channels_last), radius, stride).contiguous()


def _stats(g: torch.Tensor, r: torch.Tensor) -> list[torch.Tensor]:
    """The per-pixel terms whose window means the fit needs: ``g``, ``r``, ``g_i g_j`` (i <= j), ``g_i r``."""
    k = g.shape[1]
    iu = torch.triu_indices(k, k).tolist()
    return [g, r, *(g[:, i:i + 1] * g[:, j:j + 1] for i, j in zip(*iu)), *(g[:, i:i + 1] * r for i in range(k))]


def _fit(m: torch.Tensor, k: int, c: int, radius: int, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Ridge coefficients ``(B, K, C, h, w)`` and offsets ``(B, C, h, w)``, each averaged over the
    ``(2 radius + 1)²`` window, from the window means ``m`` of :func:`_stats`'s terms (planar, concatenated)."""
    b, _, h, w = m.shape
    iu = torch.triu_indices(k, k).tolist()
    n = len(iu[0])
    mg, mr = m[:, :k], m[:, k:k + c]
    gg = m[:, k + c:k + c + n]
    cgr = m[:, k + c + n:].reshape(b, k, c, h, w) - mg[:, :, None] * mr[:, None]
    cov = {}
    for q, (i, j) in enumerate(zip(*iu)):
        cov[i, j] = cov[j, i] = gg[:, q] - mg[:, i] * mg[:, j] + (eps if i == j else 0.0)
    if k == 3:  # cofactors of the symmetric 3x3, plane by plane
        a, bb, cc, d, e, f = cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2]
        adj = {(0, 0): d * f - e * e, (0, 1): cc * e - bb * f, (0, 2): bb * e - cc * d,
               (1, 1): a * f - cc * cc, (1, 2): bb * cc - a * e, (2, 2): a * d - bb * bb}
        inv = 1.0 / (a * adj[0, 0] + bb * adj[0, 1] + cc * adj[0, 2])
        row = lambda i: [adj[min(i, j), max(i, j)] for j in range(3)]  # noqa: E731
        coef = torch.stack([sum(q[:, None] * cgr[:, j] for j, q in enumerate(row(i))) * inv[:, None]
                            for i in range(3)], 1)
    else:
        lhs = torch.stack([torch.stack([cov[i, j] for j in range(k)], -1) for i in range(k)], -2)  # (B, h, w, K, K)
        coef = _solve(lhs, cgr.permute(0, 3, 4, 1, 2)).permute(0, 3, 4, 1, 2)
    off = -(coef * mg[:, :, None]).sum(1)
    both = _box(torch.cat([coef.reshape(b, k * c, h, w), off], 1), radius)
    return both[:, :k * c].reshape(b, k, c, h, w), both[:, k * c:]


def _phases(x: torch.Tensor) -> torch.Tensor:
    """``(B, C, 2h, 2w)`` -> ``(B, 4, C, h, w)``: the four pixels of each 2×2 block as planes."""
    b, c, h2, w2 = x.shape
    return x.reshape(b, c, h2 // 2, 2, w2 // 2, 2).permute(0, 3, 5, 1, 2, 4).reshape(b, 4, c, h2 // 2, w2 // 2)


def _unphase(x: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`_phases`."""
    b, _, c, h, w = x.shape
    return x.reshape(b, 2, 2, c, h, w).permute(0, 3, 4, 1, 5, 2).reshape(b, c, 2 * h, 2 * w)


def residual_regression(denoised: torch.Tensor, noisy: torch.Tensor, guide: torch.Tensor, *, radius: int = 5,
                        eps: float = 0.01, bound: bool = True, stride: int = 1, clip: float | None = None
                        ) -> torch.Tensor:
    """Add back to ``denoised`` the part of its log residual that a local linear model of ``guide`` explains.

    Args:
        denoised: ``(B, 3, H, W)`` the denoiser's output (linear radiance, >= 0).
        noisy: ``(B, 3, H, W)`` the noisy input colour.
        guide: ``(B, K, H, W)`` guide features (e.g. the normal, K = 3).
        radius: window radius in full-resolution pixels (``radius // stride`` at the statistics' resolution).
        eps: ridge on the guide's window covariance (> 0): larger keeps less of the residual.
        bound: clip each pixel's detail to ``[-|r|, |r|]``, ``r`` its own residual (channel by channel).
        stride: 1, or 2 (one fit per 2×2 block of pixels).
        clip: None, or ``c > 0``: the fit sees the residual clipped to ``[-c, c]`` and the detail is clipped to
            ``[-min(|r|, c), min(|r|, c)]``, so a firefly (a residual of several log units) can neither steer a
            window's fit nor come back through it.
    Returns:
        ``(B, 3, H, W)``: an output pixel depends on pixels up to :func:`regression_reach` away.
    """
    if denoised.shape != noisy.shape or denoised.shape[-2:] != guide.shape[-2:] or denoised.dim() != 4:
        raise ValueError(f"residual_regression: denoised {tuple(denoised.shape)}, noisy {tuple(noisy.shape)} and "
                         f"guide {tuple(guide.shape)} must be (B, 3, H, W), (B, 3, H, W) and (B, K, H, W)")
    if not eps > 0:
        raise ValueError(f"residual_regression: eps must be > 0 (the ridge keeps each window's system solvable), "
                         f"got {eps!r}")
    if clip is not None and not clip > 0:
        raise ValueError(f"residual_regression: clip must be None or > 0, got {clip!r}")
    if stride not in (1, 2) or radius // stride < 1:
        raise ValueError(f"residual_regression: stride must be 1 or 2 and radius >= stride, got stride {stride!r} "
                         f"and radius {radius!r}")
    if stride == 2 and guide.shape[1] == 3 and denoised.shape[:2] == (1, 3):  # one native pass where it applies
        out = residual_regression_native(denoised, noisy, guide, radius, eps, bound, clip)
        if out is not None:
            return out
    base = torch.log1p(denoised.clamp_min(0))
    r = torch.log1p(noisy.clamp_min(0)) - base
    k, c = guide.shape[1], r.shape[1]
    rf = r if clip is None else r.clamp(-clip, clip)  # what the fit sees
    if stride == 1:
        coef, off = _fit(_box(torch.cat(_stats(guide, rf), 1), radius), k, c, radius, eps)
        detail = off + sum(guide[:, i:i + 1] * coef[:, i] for i in range(k))
    else:  # 2x2 blocks: window means of per-pixel terms over whole blocks, one fit per block
        h, w = guide.shape[-2:]
        if h % 2 or w % 2:
            pad = lambda x: F.pad(x, (0, w % 2, 0, h % 2), mode="replicate")  # noqa: E731
            guide, rf = pad(guide), pad(rf)
        g4, f4 = _phases(guide), _phases(rf)  # (B, 4, K, h/2, w/2), (B, 4, C, h/2, w/2)
        blocks = sum(torch.cat(_stats(g4[:, p], f4[:, p]), 1) for p in range(4)) * 0.25
        coef, off = _fit(_box(blocks, radius // 2), k, c, radius // 2, eps)
        detail = _unphase(off[:, None] + sum(g4[:, :, i, None] * coef[:, None, i] for i in range(k)))[..., :h, :w]
    if bound:
        reach = r.abs() if clip is None else r.abs().clamp_max(clip)
        detail = torch.minimum(torch.maximum(detail, -reach), reach)
    return torch.expm1(base + detail).clamp_min(0)


def regression_reach(radius: int, stride: int = 1) -> int:
    """How far (pixels) an output pixel of :func:`residual_regression` reads: the coefficients' window and the
    statistics' window; with ``stride 2`` each spans ``radius // 2`` blocks of 2×2 pixels either side of the
    pixel's own block."""
    return 2 * radius if stride == 1 else 4 * (radius // 2) + 1


def residual_regression_rows(denoised: torch.Tensor, noisy: torch.Tensor, guide: torch.Tensor, *, radius: int = 5,
                             eps: float = 0.01, bound: bool = True, stride: int = 1, clip: float | None = None,
                             band: int = 128, noisy_scale: float = 1.0) -> torch.Tensor:
    """:func:`residual_regression` a band of ``band`` rows at a time, each with the rows it reads above and below
    (:func:`regression_reach`; bands start on even rows, so a stride-2 band samples the rows the frame does):
    the same result in a fraction of the memory.

    Args and returns as :func:`residual_regression`; ``noisy_scale``: ``noisy`` is multiplied by it, a band at a time.
    """
    def scaled(x: torch.Tensor) -> torch.Tensor:  # held at float32's largest, as kpcn.exposure.scale_array holds it
        if noisy_scale == 1.0:
            return x
        big = torch.finfo(torch.float32).max
        return (x * noisy_scale).clamp_(-big, big)

    h = denoised.shape[-2]
    reach = regression_reach(radius, stride)
    reach += reach % 2
    band += band % 2
    if h <= band + 2 * reach:
        return residual_regression(denoised, scaled(noisy), guide, radius=radius, eps=eps, bound=bound, stride=stride,
                                   clip=clip)
    out = torch.empty_like(denoised)
    for y0 in range(0, h, band):
        y1 = min(h, y0 + band)
        lo, hi = max(0, y0 - reach), min(h, y1 + reach)
        part = residual_regression(denoised[..., lo:hi, :], scaled(noisy[..., lo:hi, :]), guide[..., lo:hi, :],
                                   radius=radius, eps=eps, bound=bound, stride=stride, clip=clip)
        out[..., y0:y1, :] = part[..., y0 - lo:y1 - lo, :]
    return out
