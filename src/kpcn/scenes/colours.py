"""Colours: RGB dicts, HSV, random albedos, black-body tints of lights,
luminance."""

from __future__ import annotations

import numpy as np


def _rgb(v) -> dict:
    return {"type": "rgb", "value": [float(x) for x in v]}


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _random_albedo(rng, lo: float = 0.02, hi: float = 0.9) -> np.ndarray:
    """Plausible diffuse albedo: greys, muted and saturated colours."""
    r = rng.random()
    if r < 0.3:
        c = np.full(3, rng.uniform(0.05, 0.85))
    else:
        sat = rng.uniform(0.1, 0.5) if r < 0.7 else rng.uniform(0.5, 0.95)
        val = rng.uniform(0.1, 0.9)
        c = _hsv_to_rgb(rng.random(), sat, val)
    return np.clip(c, lo, hi)


def _wyman_g(x, mu, s1, s2):
    s = np.where(x < mu, s1, s2)
    return np.exp(-0.5 * ((x - mu) / s) ** 2)


def _blackbody_rgb_raw(temp_k: float) -> np.ndarray:
    lam = np.arange(380.0, 781.0, 5.0)
    lam_m = lam * 1e-9
    h, c, k = 6.62607e-34, 2.99792e8, 1.380649e-23
    planck = 1.0 / (lam_m**5 * (np.exp(h * c / (lam_m * k * temp_k)) - 1.0))
    # analytic multi-lobe fit of the CIE 1931 colour matching functions
    xb = (1.056 * _wyman_g(lam, 599.8, 37.9, 31.0) + 0.362 * _wyman_g(lam, 442.0, 16.0, 26.7)
          - 0.065 * _wyman_g(lam, 501.1, 20.4, 26.2))
    yb = 0.821 * _wyman_g(lam, 568.8, 46.9, 40.5) + 0.286 * _wyman_g(lam, 530.9, 16.3, 31.1)
    zb = 1.217 * _wyman_g(lam, 437.0, 11.8, 36.0) + 0.681 * _wyman_g(lam, 459.0, 26.0, 13.8)
    xyz = np.array([np.sum(planck * xb), np.sum(planck * yb), np.sum(planck * zb)])
    m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    return np.maximum(m @ xyz, 1e-6)


_WHITE_6500 = None


def _luminance(c) -> float:
    c = np.asarray(c, dtype=np.float64)
    return float(0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2])


def _temperature_tint(temp_k: float) -> np.ndarray:
    """RGB tint of a black body, white-balanced to 6500 K, luminance 1."""
    global _WHITE_6500
    if _WHITE_6500 is None:
        _WHITE_6500 = _blackbody_rgb_raw(6500.0)
    c = _blackbody_rgb_raw(temp_k) / _WHITE_6500
    return c / _luminance(c)


def _random_light_tint(rng) -> tuple[np.ndarray, str]:
    r = rng.random()
    if r < 0.25:
        return np.ones(3), "white"
    if r < 0.92:
        t = float(rng.uniform(2500.0, 10000.0))
        return _temperature_tint(t), f"{t:.0f}K"
    c = _hsv_to_rgb(rng.random(), rng.uniform(0.3, 0.7), 1.0)
    return c / _luminance(c), "coloured"
