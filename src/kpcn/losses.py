"""Training losses, by name (``create_loss("l1")``). All take ``(B, C, H, W)`` prediction and target.

* ``l1``      mean absolute error (the paper's choice)
* ``relmse``  relative MSE ``(x - y)^2 / (y^2 + eps)`` (Rousselle et al.)
* ``smape``   symmetric MAPE ``|x - y| / (|x| + |y| + eps)``
* ``log``     the log-space loss of Salehi et al. 2022: with ``x' = log(1 + x)``,
  ``0.5 |x' - y'| / (y' + eps) + 0.5 |LoG(x') - LoG(y')| / (y' + eps)``,
  LoG a 5×5 Laplacian-of-Gaussian filter applied per channel.
"""
from __future__ import annotations

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


def create_loss(name: str) -> LossFn:
    """The loss function registered as ``name``."""
    try:
        return _LOSSES[name]
    except KeyError:
        raise ValueError(f"unknown loss {name!r}; known: {', '.join(sorted(_LOSSES))}") from None


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


@register_loss("log")
def log_loss(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-2) -> torch.Tensor:
    xl, yl = torch.log1p(x.clamp_min(0)), torch.log1p(y.clamp_min(0))
    w = 1.0 / (yl.detach() + eps)
    spatial = ((xl - yl).abs() * w).mean()
    freq = ((laplacian_of_gaussian(xl) - laplacian_of_gaussian(yl)).abs() * w).mean()
    return 0.5 * spatial + 0.5 * freq
