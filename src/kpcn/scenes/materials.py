"""Materials: procedural textures (value noise, patterns, bitmap and
checkerboard textures) and random BSDF dicts of the material classes
(:data:`MATERIAL_CLASSES`) with their meta records.

Known Mitsuba 3.9 issue avoided here: ``bumpmap`` around ``roughplastic``
gives NaNs on some axis-aligned rectangles, so bump maps never wrap
``roughplastic``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .base import _bitmap, _mi
from .colours import _hsv_to_rgb, _random_albedo, _rgb
from .geometry import _loguniform

MATERIAL_CLASSES = ("diffuse", "textured", "conductor", "plastic", "dielectric")
_CONDUCTORS = ("Au", "Cu", "Al", "Ag", "Cr", "Ni_palik", "W", "Rh")


# --------------------------------------------------------------------------
# procedural textures (numpy)
# --------------------------------------------------------------------------

def _grid_coords(n: int):
    t = (np.arange(n) + 0.5) / n
    return np.meshgrid(t, t, indexing="xy")  # x across columns, y down rows


def _value_noise(rng, n: int, octaves: int = 4, base_cells: int = 4, persistence: float = 0.5):
    """Tileable multi-octave value noise in [0, 1], shape (n, n)."""
    out = np.zeros((n, n))
    amp, total = 1.0, 0.0
    cells = base_cells
    for _ in range(octaves):
        g = rng.random((cells, cells))
        pos = (np.arange(n) + 0.5) / n * cells - 0.5
        i0 = np.floor(pos).astype(int)
        f = pos - i0
        f = f * f * (3 - 2 * f)
        i0m, i1m = i0 % cells, (i0 + 1) % cells
        a = g[np.ix_(i0m, i0m)]
        b = g[np.ix_(i0m, i1m)]
        c = g[np.ix_(i1m, i0m)]
        d = g[np.ix_(i1m, i1m)]
        fy, fx = f[:, None], f[None, :]
        out += amp * ((a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy)
        total += amp
        amp *= persistence
        cells *= 2
        if cells > n:
            break
    out /= total
    lo, hi = out.min(), out.max()
    return (out - lo) / max(hi - lo, 1e-8)


def _pattern(rng, n: int) -> tuple[np.ndarray, str]:
    """A scalar pattern in [0, 1] and its name."""
    x, y = _grid_coords(n)
    kind = rng.choice(["noise", "stripes", "checkers", "blotches", "rings", "tiles", "marble"])
    if kind == "noise":
        s = _value_noise(rng, n, octaves=int(rng.integers(2, 6)), base_cells=int(rng.choice([2, 4, 8])))
        if rng.random() < 0.4:
            s = (s > rng.uniform(0.35, 0.65)).astype(float) * 0.8 + 0.2 * s
    elif kind == "stripes":
        freq = int(rng.integers(2, 16))
        if rng.random() < 0.5:
            u = x if rng.random() < 0.5 else y
            t = u * freq
        else:
            fx, fy = int(rng.integers(0, 6)), int(rng.integers(1, 6))
            t = x * fx + y * fy
            freq = 1
        if rng.random() < 0.5:
            s = 0.5 + 0.5 * np.sin(2 * np.pi * t)
        else:
            duty = rng.uniform(0.2, 0.8)
            s = ((t % 1.0) < duty).astype(float)
    elif kind == "checkers":
        k = int(rng.choice([2, 4, 6, 8, 12]))
        s = ((np.floor(x * k) + np.floor(y * k)) % 2).astype(float)
    elif kind == "blotches":
        s = np.zeros((n, n))
        for _ in range(int(rng.integers(5, 40))):
            cx, cy = rng.random(2)
            r = rng.uniform(0.02, 0.15)
            dx = np.minimum(abs(x - cx), 1 - abs(x - cx))
            dy = np.minimum(abs(y - cy), 1 - abs(y - cy))
            s = np.maximum(s, np.exp(-(dx * dx + dy * dy) / (2 * r * r)))
        if rng.random() < 0.5:
            s = (s > 0.5).astype(float)
    elif kind == "rings":  # wood-like
        cx, cy = rng.uniform(-0.5, 1.5, 2)
        warp = _value_noise(rng, n, octaves=3, base_cells=4)
        r = np.sqrt((x - cx) ** 2 * rng.uniform(0.05, 1) + (y - cy) ** 2) * rng.uniform(8, 30)
        s = (r + warp * rng.uniform(0.5, 3)) % 1.0
        s = s**2
    elif kind == "tiles":
        k = int(rng.choice([2, 3, 4, 6, 8]))
        gw = rng.uniform(0.03, 0.12)
        fx, fy = (x * k) % 1.0, (y * k) % 1.0
        grout = (fx < gw) | (fy < gw)
        tile_val = rng.random((k, k))[np.floor(y * k).astype(int) % k, np.floor(x * k).astype(int) % k]
        s = np.where(grout, 0.0, 0.4 + 0.6 * tile_val * rng.uniform(0, 1))
    else:  # marble
        noise = _value_noise(rng, n, octaves=5, base_cells=4)
        s = 0.5 + 0.5 * np.sin(2 * np.pi * (x * rng.uniform(1, 4) + noise * rng.uniform(1, 4)))
        s = s ** rng.uniform(0.5, 3)
    return np.clip(s, 0.0, 1.0), str(kind)


def _random_texture_image(rng, n: int = 128) -> tuple[np.ndarray, str]:
    s, kind = _pattern(rng, n)
    c0, c1 = _random_albedo(rng), _random_albedo(rng)
    img = c0[None, None, :] * (1 - s[..., None]) + c1[None, None, :] * s[..., None]
    if rng.random() < 0.35:  # grime / variation
        m = _value_noise(rng, n, octaves=4, base_cells=8)
        img = img * (1 - rng.uniform(0.1, 0.5) * m[..., None])
    return np.clip(img, 0.02, 0.9).astype(np.float32), kind


def _random_texture(rng, n: int = 128) -> tuple[dict, str, float]:
    """A Mitsuba texture dict with a reflectance in [0.02, 0.9], its kind and
    its mean albedo."""
    mi = _mi()
    rep = float(rng.choice([1.0, 1.0, 2.0, 3.0, 4.0]))
    if rng.random() < 0.2:
        c0, c1 = _random_albedo(rng), _random_albedo(rng)
        return (
            {
                "type": "checkerboard",
                "color0": _rgb(c0),
                "color1": _rgb(c1),
                "to_uv": mi.ScalarTransform4f().scale([rep * 2, rep * 2, 1.0]),
            },
            "checkerboard",
            float((c0.mean() + c1.mean()) / 2),
        )
    img, kind = _random_texture_image(rng, n)
    tex = {
        "type": "bitmap",
        "bitmap": _bitmap(img),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "repeat",
    }
    if rep != 1.0:
        tex["to_uv"] = mi.ScalarTransform4f().scale([rep, rep, 1.0])
    return tex, "bitmap:" + kind, float(img.mean())


# --------------------------------------------------------------------------
# materials
# --------------------------------------------------------------------------

_OBJ_WEIGHTS = np.array([0.30, 0.20, 0.17, 0.18, 0.15])  # MATERIAL_CLASSES order
_SURF_WEIGHTS = np.array([0.50, 0.28, 0.06, 0.16, 0.0])  # floors / ground
_WALL_WEIGHTS = np.array([0.60, 0.24, 0.0, 0.16, 0.0])  # walls, ceilings, backdrops


def _material(rng, cls: str, flat: bool = False, bump: bool = True) -> tuple[dict, dict]:
    """BSDF dict of material class ``cls`` and its meta record."""
    meta: dict[str, Any] = {"class": cls}
    if cls == "diffuse":
        c = _random_albedo(rng)
        bsdf = {"type": "diffuse", "reflectance": _rgb(c)}
        meta["albedo"] = float(c.mean())
    elif cls == "textured":
        tex, kind, alb = _random_texture(rng)
        bsdf = {"type": "diffuse", "reflectance": tex}
        meta["texture"] = kind
        meta["albedo"] = alb
    elif cls == "conductor":
        mat = str(rng.choice(_CONDUCTORS))
        if rng.random() < 0.25:
            bsdf = {"type": "conductor", "material": mat}
            meta["alpha"] = 0.0
        else:
            dist = str(rng.choice(["ggx", "beckmann"]))
            bsdf = {"type": "roughconductor", "material": mat, "distribution": dist}
            if rng.random() < 0.12:
                au, av = _loguniform(rng, 0.03, 0.5), _loguniform(rng, 0.03, 0.5)
                bsdf["alpha_u"], bsdf["alpha_v"] = au, av
                meta["alpha"] = (au, av)
            else:
                a = _loguniform(rng, 0.03, 0.5)
                bsdf["alpha"] = a
                meta["alpha"] = a
        meta["material"] = mat
        meta["albedo"] = 0.7
    elif cls == "plastic":
        if rng.random() < 0.2:
            refl, kind, alb = _random_texture(rng)
            meta["texture"] = kind
        else:
            c = _random_albedo(rng)
            refl, alb = _rgb(c), float(c.mean())
        meta["albedo"] = 0.9 * alb + 0.05
        ior = float(rng.uniform(1.4, 1.6))
        if rng.random() < 0.35:
            bsdf = {"type": "plastic", "diffuse_reflectance": refl, "int_ior": ior}
            meta["alpha"] = 0.0
        else:
            a = _loguniform(rng, 0.03, 0.4)
            bsdf = {"type": "roughplastic", "diffuse_reflectance": refl, "int_ior": ior,
                    "alpha": a, "distribution": str(rng.choice(["ggx", "beckmann"]))}
            meta["alpha"] = a
        bsdf["nonlinear"] = bool(rng.random() < 0.3)
    elif cls == "dielectric":
        ior = float(rng.choice([1.33, 1.45, 1.5, 1.52, 1.6, 1.75]))
        meta["albedo"] = 0.9
        r = rng.random()
        if flat or r < 0.15:
            bsdf = {"type": "thindielectric", "int_ior": ior}
        elif r < 0.65:
            bsdf = {"type": "dielectric", "int_ior": ior}
        else:
            a = _loguniform(rng, 0.02, 0.3)
            bsdf = {"type": "roughdielectric", "int_ior": ior, "alpha": a,
                    "distribution": str(rng.choice(["ggx", "beckmann"]))}
            meta["alpha"] = a
        if rng.random() < 0.2:
            tint = np.clip(_hsv_to_rgb(rng.random(), rng.uniform(0.1, 0.5), 1.0), 0.3, 1.0)
            bsdf["specular_transmittance"] = _rgb(tint)
            meta["tinted"] = True
    else:  # pragma: no cover
        raise ValueError(cls)
    meta["type"] = bsdf["type"]
    # bumpmap + roughplastic gives NaNs in Mitsuba 3.9 on some axis-aligned
    # rectangles (e.g. walls facing +-x): never combine them.
    if bump and cls != "dielectric" and bsdf["type"] != "roughplastic" and rng.random() < 0.12:
        s, kind = _pattern(rng, 128)
        bsdf = {"type": "bumpmap",
                "arbitrary": {"type": "bitmap", "bitmap": _bitmap(s[..., None]), "raw": True,
                              "to_uv": _mi().ScalarTransform4f().scale([float(rng.choice([1, 2, 4]))] * 2 + [1.0])},
                "scale": _loguniform(rng, 0.002, 0.03), "bsdf": bsdf}
        meta["bump"] = kind
    if flat and cls != "dielectric":
        bsdf = {"type": "twosided", "material": bsdf}
    return bsdf, meta


def _pick_class(rng, weights: np.ndarray) -> str:
    return str(MATERIAL_CLASSES[int(rng.choice(len(MATERIAL_CLASSES), p=weights / weights.sum()))])
