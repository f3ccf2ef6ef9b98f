"""Procedural lat-long sky maps (gradient, clouds, sun) for envmap emitters."""

from __future__ import annotations

from typing import Any

import numpy as np

from .colours import _random_albedo, _temperature_tint
from .materials import _value_noise


def _env_dir(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Direction of an envmap texel (Mitsuba lat-long: v=0 is +y, u=0.25 is +x)."""
    st = np.sin(theta)
    return np.stack([st * np.sin(phi), np.cos(theta), -st * np.cos(phi)], axis=-1)


def _sky_image(rng, width: int = 256, sun: bool | None = None) -> tuple[np.ndarray, dict]:
    """Procedural lat-long sky, normalised so a horizontal surface receives
    irradiance pi (i.e. a white Lambertian floor would have radiance 1)."""
    h = width // 2
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(width) + 0.5) / width
    theta = (np.pi * v)[:, None] * np.ones((1, width))
    phi = (2 * np.pi * u)[None, :] * np.ones((h, 1))
    d = _env_dir(theta, phi)
    cos_t = d[..., 1]
    meta: dict[str, Any] = {}

    style = rng.choice(["clear", "clear", "sunset", "overcast", "hazy"])
    meta["sky"] = str(style)
    if style == "clear":
        zen = np.array([0.15, 0.3, 0.8]) * rng.uniform(0.7, 1.2, 3)
        hor = np.array([0.75, 0.85, 1.0]) * rng.uniform(0.8, 1.1, 3)
    elif style == "sunset":
        zen = np.array([0.2, 0.25, 0.55]) * rng.uniform(0.7, 1.2, 3)
        hor = np.array([1.0, 0.55, 0.25]) * rng.uniform(0.7, 1.2, 3)
    elif style == "overcast":
        g = rng.uniform(0.6, 1.0)
        zen = np.full(3, g) * rng.uniform(0.9, 1.1, 3)
        hor = zen * rng.uniform(0.6, 0.9)
    else:
        zen = np.array([0.5, 0.6, 0.8]) * rng.uniform(0.8, 1.2, 3)
        hor = np.array([0.9, 0.9, 0.9]) * rng.uniform(0.8, 1.1, 3)
    p = rng.uniform(0.3, 1.0)
    t = np.clip(cos_t, 0, 1)[..., None] ** p
    img = hor * (1 - t) + zen * t
    if style in ("clear", "hazy") and rng.random() < 0.5:  # clouds
        cl = _value_noise(rng, h, octaves=5, base_cells=4)
        cl = np.concatenate([cl, cl], axis=1)[:, :width]
        cov = rng.uniform(0.3, 0.8)
        cmask = np.clip((cl - cov) / 0.15, 0, 1)[..., None]
        img = img * (1 - cmask) + np.full(3, rng.uniform(0.7, 1.2)) * cmask
        meta["clouds"] = True
    ground = _random_albedo(rng, 0.05, 0.5) * rng.uniform(0.3, 0.8)
    below = cos_t < 0
    img[below] = ground * np.mean(img[~below], axis=0)

    solid = (2 * np.pi / width) * (np.pi / h) * np.sin(theta)
    irr_h = lambda im: float(np.sum(_luminance_img(im) * np.clip(cos_t, 0, None) * solid))

    if sun is None:
        sun = style != "overcast" and rng.random() < 0.8
    if sun:
        elev = rng.uniform(3.0, 70.0) if style != "sunset" else rng.uniform(1.0, 12.0)
        az = rng.uniform(0, 2 * np.pi)
        th_s = np.radians(90.0 - elev)
        sdir = _env_dir(np.array(th_s), np.array(az))
        ang = np.arccos(np.clip(d @ sdir, -1, 1))
        size = np.radians(rng.uniform(0.6, 2.5)) * max(1.0, 256 / width)
        blob = np.exp(-0.5 * (ang / size) ** 2)
        halo = np.exp(-0.5 * (ang / (size * rng.uniform(4, 10))) ** 2) * rng.uniform(0.005, 0.03)
        sky_e = irr_h(img)
        sun_frac = rng.uniform(0.4, 0.9)
        blob_e = irr_h(np.repeat(blob[..., None], 3, -1))
        sun_col = _temperature_tint(5800.0 if style != "sunset" else rng.uniform(2500, 3500))
        k = sun_frac / (1 - sun_frac) * sky_e / max(blob_e, 1e-12)
        img = img + k * sun_col * (blob + halo)[..., None] * (cos_t > -0.02)[..., None]
        meta.update(sun_elevation_deg=float(elev), sun_dir=[float(x) for x in sdir], sun_fraction=float(sun_frac))
    img = img * (np.pi / irr_h(img))
    return img.astype(np.float32), meta


def _luminance_img(im: np.ndarray) -> np.ndarray:
    return 0.2126 * im[..., 0] + 0.7152 * im[..., 1] + 0.0722 * im[..., 2]
