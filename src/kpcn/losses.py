"""Training losses, by name (``create_loss("l1")``). All take ``(B, C, H, W)`` prediction and target;
a loss's keyword parameters are bound by ``create_loss(name, params)`` (``train.loss_params``).

* ``l1``      mean absolute error (the paper's choice)
* ``relmse``  relative MSE ``(x - y)^2 / (y^2 + eps)`` (Rousselle et al.)
* ``smape``   symmetric MAPE ``|x - y| / (|x| + |y| + eps)``
* ``log``     the log-space loss of Salehi et al. 2022: with ``x' = log(1 + x)``,
  ``0.5 |x' - y'| / (y' + eps) + 0.5 |LoG(x') - LoG(y')| / (y' + eps)``,
  LoG a 5×5 Laplacian-of-Gaussian filter applied per channel.
* ``l1_msssim`` ``0.16 · L1 + 0.84 · (1 - MS-SSIM)`` (Zhao et al. 2017's mix, as
  OIDN trains), both on tone-mapped values ``x / (1 + x)`` so that SSIM's
  constants suit HDR radiance; MS-SSIM over 3 scales of 2×2 average pooling,
  Gaussian window σ = 1.5 (7×7), so that 64-pixel patches have room for all scales
  (smaller patches use fewer scales).
* ``log_msssim`` ``log + w · (1 - MS-SSIM)`` (``ssim_weight`` w, default 1), the MS-SSIM on the report's tone map
  (Reinhard, then gamma 2.2): the log loss keeps what it does against fireflies
  (``l1_msssim`` alone saturates on them), the MS-SSIM term weighs the structure
  the report's SSIM measures; the two are of the same size on this project's
  renders (0.007-0.13 and 0.002-0.24 per frame). ``coarse_weight`` c (default 0: off) adds
  ``c · mean_p log(P_p x, P_p y)`` over the pools ``p`` of ``coarse_pools`` (default 4 and 16): the log loss's
  spatial term on the prediction and target average-pooled ``p × p`` in *linear* radiance first. A per-pixel
  L1 in log space is met by the conditional median, and a kernel predictor that is unsure drops bright samples
  (the default's 4-spp outputs are 1-3 % darker than the reference on the file scenes, OIDN's 0-1 %); the
  pooled means, being averages, are met by the mean: the term weighs low-frequency error and lost energy.
"""
from __future__ import annotations

import functools
import inspect
import math
from typing import Callable

import torch
import torch.nn.functional as F

LossFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
_LOSSES: dict[str, LossFn] = {}


def register_loss(name: str):
    def deco(fn: LossFn) -> LossFn:
        _LOSSES[name] = fn
        return fn

    return deco


def create_loss(name: str, params: dict | None = None) -> LossFn:
    """The loss function registered as ``name``, with its keyword ``params`` (e.g. ``{"ssim_weight": 2}``) bound."""
    try:
        fn = _LOSSES[name]
    except KeyError:
        raise ValueError(f"unknown loss {name!r}; known: {', '.join(sorted(_LOSSES))}") from None
    if not params:
        return fn
    known = list(inspect.signature(fn).parameters)[2:]  # after the prediction and the target
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise ValueError(f"loss {name!r} has no parameter {', '.join(map(repr, unknown))}; "
                         f"its parameters: {', '.join(known) or 'none'}")
    return functools.partial(fn, **params)


def list_losses() -> list[str]:
    return sorted(_LOSSES)


@register_loss("l1")
def l1(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return (x - y).abs().mean()


@register_loss("relmse")
def relmse(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-2) -> torch.Tensor:
    return ((x - y) ** 2 / (y.detach() ** 2 + eps)).mean()


@register_loss("smape")
def smape(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-2) -> torch.Tensor:
    return ((x - y).abs() / (x.abs() + y.abs() + eps)).mean()


def log_kernel(size: int = 5, sigma: float = 1.0, dtype=torch.float32) -> torch.Tensor:
    """A zero-sum Laplacian-of-Gaussian kernel ``(size, size)``."""
    r = torch.arange(size, dtype=torch.float64) - size // 2
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    q = (xx**2 + yy**2) / (2 * sigma**2)
    k = -(1 / (math.pi * sigma**4)) * (1 - q) * torch.exp(-q)
    return (k - k.mean()).to(dtype)


def laplacian_of_gaussian(x: torch.Tensor, size: int = 5, sigma: float = 1.0) -> torch.Tensor:
    """Per-channel LoG filter of ``(B, C, H, W)`` with replicate padding."""
    c = x.shape[1]
    k = log_kernel(size, sigma, x.dtype).to(x.device).expand(c, 1, size, size)
    return F.conv2d(F.pad(x, [size // 2] * 4, mode="replicate"), k, groups=c)


def _log_pair(x: torch.Tensor, y: torch.Tensor, eps: float):
    """``(log(1 + x), log(1 + y), 1 / (log(1 + y) + eps))``, the last without gradient."""
    xl, yl = torch.log1p(x.clamp_min(0)), torch.log1p(y.clamp_min(0))
    return xl, yl, 1.0 / (yl.detach() + eps)


def _weighted_l1(a: torch.Tensor, b: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return ((a - b).abs() * w).mean()


@register_loss("log")
def log_loss(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-2) -> torch.Tensor:
    xl, yl, w = _log_pair(x, y, eps)
    return 0.5 * _weighted_l1(xl, yl, w) + 0.5 * _weighted_l1(laplacian_of_gaussian(xl), laplacian_of_gaussian(yl), w)


def _gauss_window(size: int = 7, sigma: float = 1.5, dtype=torch.float32) -> torch.Tensor:
    r = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(r**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).to(dtype)


def _ssim_parts(x: torch.Tensor, y: torch.Tensor, win: torch.Tensor, c1: float, c2: float):
    """Per-pixel luminance and contrast-structure terms of SSIM (valid windows only)."""
    c = x.shape[1]
    w = win.to(x.device, x.dtype).expand(c, 1, *win.shape)

    def blur(t):
        return F.conv2d(t, w, groups=c)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    lum = (2 * mx * my + c1) / (mx * mx + my * my + c1)
    cs = (2 * sxy + c2) / (sxx + syy + c2)
    return lum, cs


def ms_ssim(x: torch.Tensor, y: torch.Tensor, scales: int = 3, weights=None) -> torch.Tensor:
    """Multi-scale SSIM of ``(B, C, H, W)`` images with values in about [0, 1] (Wang et al. 2003).

    ``weights`` per scale (default: the first ``scales`` of Wang's five, renormalised); the
    contrast-structure term at each scale, luminance only at the coarsest. The side must be at
    least ``7 · 2**(scales - 1)`` pixels.
    """
    base = torch.tensor([0.0448, 0.2856, 0.3001, 0.2363, 0.1333], dtype=torch.float64)
    wts = torch.as_tensor(weights if weights is not None else base[:scales] / base[:scales].sum(), dtype=torch.float64)
    win = _gauss_window(dtype=x.dtype)
    if min(x.shape[-2:]) < win.shape[-1] * 2 ** (scales - 1):
        raise ValueError(f"ms_ssim: images of {tuple(x.shape[-2:])} are too small for {scales} scales "
                         f"(need a side of {win.shape[-1] * 2 ** (scales - 1)})")
    c1, c2 = 0.01**2, 0.03**2
    value = torch.ones((), dtype=x.dtype, device=x.device)
    for s in range(scales):
        lum, cs = _ssim_parts(x, y, win, c1, c2)
        term = (lum * cs).mean() if s == scales - 1 else cs.mean()
        value = value * term.clamp_min(1e-6) ** float(wts[s])
        if s < scales - 1:
            x, y = F.avg_pool2d(x, 2), F.avg_pool2d(y, 2)
    return value


def _ms_scales(x: torch.Tensor) -> int:
    """As many of 3 MS-SSIM scales as the patch holds."""
    return 1 + max(0, min(2, int(math.floor(math.log2(max(min(x.shape[-2:]), 7) / 7)))))


def log_l1(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-2) -> torch.Tensor:
    """The log loss's spatial term: ``mean |log(1 + x) - log(1 + y)| / (log(1 + y) + eps)``."""
    return _weighted_l1(*_log_pair(x, y, eps))


def coarse_log_l1(x: torch.Tensor, y: torch.Tensor, pools=(4, 16)) -> torch.Tensor:
    """:func:`log_l1` of ``x`` and ``y`` ``(B, C, H, W)`` average-pooled ``p × p`` (linear), averaged over the
    pools ``p`` that fit the image; where none fits, one pool of the image's shorter side."""
    side = min(x.shape[-2:])
    fit = [p for p in pools if p <= side] or [max(1, side)]
    return sum(log_l1(F.avg_pool2d(x, p), F.avg_pool2d(y, p)) for p in fit) / len(fit)


@register_loss("log_msssim")
def log_msssim(x: torch.Tensor, y: torch.Tensor, ssim_weight: float = 1.0, coarse_weight: float = 0.0,
               coarse_pools=(4, 16), tone_l2_weight: float = 0.0, relmse_weight: float = 0.0) -> torch.Tensor:
    """The log loss + ``ssim_weight`` · (1 − MS-SSIM of the tone-mapped colours), ``+ coarse_weight`` ·
    :func:`coarse_log_l1`, ``+ tone_l2_weight`` · the mean squared error of the tone-mapped colours (what the
    report's PSNR measures), ``+ relmse_weight`` · :func:`relmse` (what the report's relMSE measures: dark pixels
    weigh most). The log loss is an L1: its optimum is a median, below the mean wherever what a noisy
    input can stand for is skewed (a glossy highlight a few samples missed); a squared error's optimum is the mean."""
    def tone(t):  # kpcn.metrics.tonemap; the offset keeps the gamma's slope finite at 0
        t = t.clamp_min(0)
        return (t / (1 + t) + 1e-4) ** (1 / 2.2)

    tx, ty = tone(x), tone(y)
    loss = log_loss(x, y) + ssim_weight * (1 - ms_ssim(tx, ty, _ms_scales(x)))
    if coarse_weight:
        loss = loss + coarse_weight * coarse_log_l1(x, y, tuple(coarse_pools))
    if tone_l2_weight:
        loss = loss + tone_l2_weight * (tx - ty).square().mean()
    if relmse_weight:
        loss = loss + relmse_weight * relmse(x, y)
    return loss


@register_loss("l1_msssim")
def l1_msssim(x: torch.Tensor, y: torch.Tensor, alpha: float = 0.84) -> torch.Tensor:
    xt, yt = x.clamp_min(0), y.clamp_min(0)
    xt, yt = xt / (1 + xt), yt / (1 + yt)
    return (1 - alpha) * (xt - yt).abs().mean() + alpha * (1 - ms_ssim(xt, yt, _ms_scales(x)))
