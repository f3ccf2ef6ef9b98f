"""Image error metrics against a reference: relMSE, SMAPE, PSNR, SSIM.

Arrays are ``(H, W, 3)`` linear radiance (NumPy). relMSE and SMAPE are computed
on linear HDR values; PSNR and SSIM (scikit-image) on a tone-mapped image
``(x / (1 + x)) ** (1 / 2.2)`` in [0, 1], so that bright highlights do not
dominate and the numbers mean what they mean for LDR images.
"""
from __future__ import annotations

import numpy as np


def tonemap(x: np.ndarray) -> np.ndarray:
    """Reinhard + gamma 2.2 tone map of linear radiance into [0, 1]."""
    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=1e30), 0.0, None)
    return (x / (1.0 + x)) ** (1.0 / 2.2)


def relmse(x: np.ndarray, ref: np.ndarray, eps: float = 1e-2) -> float:
    return float(np.mean((x - ref) ** 2 / (ref**2 + eps)))


def smape(x: np.ndarray, ref: np.ndarray, eps: float = 1e-2) -> float:
    return float(np.mean(np.abs(x - ref) / (np.abs(x) + np.abs(ref) + eps)))


def psnr(x: np.ndarray, ref: np.ndarray) -> float:
    from skimage.metrics import peak_signal_noise_ratio

    return float(peak_signal_noise_ratio(tonemap(ref), tonemap(x), data_range=1.0))


def ssim(x: np.ndarray, ref: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    a, b = tonemap(x), tonemap(ref)
    win = min(7, *[s - (1 - s % 2) for s in a.shape[:2]])
    return float(structural_similarity(b, a, data_range=1.0, channel_axis=-1, win_size=max(win, 3)))


def all_metrics(x: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """relMSE, SMAPE, PSNR and SSIM of ``x`` against ``ref``."""
    x = np.asarray(x, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if x.shape != ref.shape:
        raise ValueError(f"image {x.shape} and reference {ref.shape} differ in shape")
    return {"relmse": relmse(x, ref), "smape": smape(x, ref), "psnr": psnr(x, ref), "ssim": ssim(x, ref)}
