"""Procedural training scenes and small named test scenes for Mitsuba 3.

Every function here returns a Mitsuba scene *dict* (as accepted by
``mi.load_dict``) containing only plain Python values, nested dicts,
``mi.Bitmap`` and ``mi.ScalarTransform4f`` objects.  The dict holds:

* ``"type": "scene"``
* ``"integrator"``: a plain ``path`` integrator (callers such as
  :mod:`kpcn.render` replace it),
* ``"sensor"``: a ``perspective`` camera with a ``look_at`` ``to_world``, an
  ``hdrfilm`` (box reconstruction filter) and an ``independent`` sampler,
* shapes with BSDFs and emitters (area, environment, point/spot lights).

Public API
----------
``random_scene(seed, resolution=(128, 128)) -> dict``
``random_scene_with_meta(seed, resolution=(128, 128)) -> (dict, dict)``
``describe_scene(seed) -> str``
``test_scene(name, resolution=(32, 32)) -> dict``
``test_scene_with_meta(name, resolution=(32, 32)) -> (dict, dict)``
``list_test_scenes() -> list[str]``
``copy_scene_dict(scene) -> dict``

``resolution`` is ``(width, height)`` like Mitsuba's film.

Mitsuba variant: the scene builders need a variant to create ``mi.Bitmap`` /
transform objects.  If no variant is set, ``llvm_ad_rgb`` is selected (and
the LLVM version is checked); if the caller already set a variant it is kept.
The dicts are written for RGB variants (``llvm_ad_rgb``, ``scalar_rgb``,
``cuda_ad_rgb``).

Mitsuba's ``Bitmap`` and transform objects cannot be deep-copied or pickled;
use :func:`copy_scene_dict` (copies the nested dicts, shares the leaves)
before editing a scene dict, or rebuild it from its seed / name.

Layouts of random scenes: ``open`` (ground plane, sky map / constant
environment, optional area and delta lights), ``corner`` (ground plus one or
two backdrop walls), ``closed`` (room with lamps: ceiling panels, sphere
lamps, wall panels, hidden lights facing the ceiling, point/spot), ``window``
(closed room lit by a sky seen through a hole in a wall, sun aimed in) and
``cornell`` (box with an open front, camera outside).  3-10 objects
(sphere, cube, capped cylinder, disk, rectangle; stacked, floating or
intersecting now and then), sometimes a cluster of small clutter objects.

Brightness: no render in the loop.  Open scenes set each light from a target
radiance T (log-uniform 0.2-1) of a grey (albedo 0.5) surface facing it
(solid angle / inverse square / sky irradiance); rooms use an energy balance
(emitted flux ~ T * pi * area * (1 - rho) / rho, rho = mean wall albedo).
Measured (Mitsuba ``path``, 120 seeds): image mean radiance 0.013-8.5,
median 0.37, 5-95 % range 0.07-1.5; the high end comes from large emitters
seen directly.

Known Mitsuba 3.9 issue avoided here: ``bumpmap`` around ``roughplastic``
gives NaNs on some axis-aligned rectangles, so bump maps never wrap
``roughplastic``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "random_scene",
    "random_scene_with_meta",
    "describe_scene",
    "test_scene",
    "test_scene_with_meta",
    "list_test_scenes",
    "copy_scene_dict",
    "MATERIAL_CLASSES",
    "LIGHT_CLASSES",
]

MATERIAL_CLASSES = ("diffuse", "textured", "conductor", "plastic", "dielectric")
LIGHT_CLASSES = ("area", "environment", "delta")

_RHO_REF = 0.5  # albedo of the reference surface used to set light intensities
_T_RANGE = (0.2, 1.0)  # radiance of a reference surface facing the lights (log-uniform)
_K_ROOM = 0.7  # calibration of the room energy balance (measured, see tests)
_CONDUCTORS = ("Au", "Cu", "Al", "Ag", "Cr", "Ni_palik", "W", "Rh")


# --------------------------------------------------------------------------
# Mitsuba access
# --------------------------------------------------------------------------

def _mi():
    """Return the ``mitsuba`` module with a variant set (default llvm_ad_rgb)."""
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb")
        import drjit as dr

        try:
            ver = tuple(dr.detail.llvm_version())
        except Exception:  # pragma: no cover - API differences
            ver = None
        if ver is not None and ver[0] < 17:
            raise RuntimeError(
                f"Mitsuba's llvm_ad_rgb variant needs LLVM >= 17, found {ver}. "
                "Install LLVM 19 (Debian/Ubuntu: `apt-get install -y libllvm19`)."
            )
    return mi


def _xf(m: np.ndarray):
    return _mi().ScalarTransform4f(np.asarray(m, dtype=np.float64).tolist())


def _look_at(origin, target, up):
    mi = _mi()
    return mi.ScalarTransform4f().look_at(
        origin=[float(v) for v in origin],
        target=[float(v) for v in target],
        up=[float(v) for v in up],
    )


def _bitmap(arr: np.ndarray):
    return _mi().Bitmap(np.ascontiguousarray(arr, dtype=np.float32))


def copy_scene_dict(scene: dict) -> dict:
    """Copy the nested dicts of a scene dict; leaf objects (Bitmap, transforms,
    lists of numbers) are shared.  ``copy.deepcopy`` fails on Mitsuba objects."""
    out = {}
    for k, v in scene.items():
        if isinstance(v, dict):
            out[k] = copy_scene_dict(v)
        elif isinstance(v, list):
            out[k] = list(v)
        else:
            out[k] = v
    return out


# --------------------------------------------------------------------------
# small linear algebra helpers (numpy 4x4, y is up)
# --------------------------------------------------------------------------

def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def _rot3(axis, angle_rad: float) -> np.ndarray:
    x, y, z = _unit(axis)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
    )


def _rot(axis, angle_rad: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = _rot3(axis, angle_rad)
    return m


def _frame(n, hint=None) -> np.ndarray:
    """3x3 rotation with columns (u, v, n), right-handed; v is the part of
    ``hint`` orthogonal to n (default: world up, or x for vertical n)."""
    n = _unit(n)
    if hint is None:
        hint = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = _unit(np.cross(hint, n))
    v = np.cross(n, u)
    return np.stack([u, v, n], axis=1)


def _random_rotation3(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rect_matrix(center, normal, half_u: float, half_v: float, hint=None) -> np.ndarray:
    """to_world of Mitsuba's rectangle ([-1,1]^2 in xy, normal +z)."""
    R = _frame(normal, hint)
    m = np.eye(4)
    m[:3, 0] = R[:, 0] * half_u
    m[:3, 1] = R[:, 1] * half_v
    m[:3, 2] = R[:, 2]
    m[:3, 3] = center
    return m


def _disk_matrix(center, normal, radius: float) -> np.ndarray:
    R = _frame(normal)
    m = np.eye(4)
    m[:3, :3] = R * radius
    m[:3, 3] = center
    return m


def _loguniform(rng, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


# --------------------------------------------------------------------------
# colours
# --------------------------------------------------------------------------

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


# --------------------------------------------------------------------------
# procedural sky
# --------------------------------------------------------------------------

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


# --------------------------------------------------------------------------
# scene builder
# --------------------------------------------------------------------------

class _Obj:
    """Bounding info for a placed object."""

    def __init__(self, center, radius, top, stackable=False, footprint=None):
        self.center = np.asarray(center, dtype=np.float64)
        self.radius = float(radius)  # bounding sphere
        self.top = float(top)
        self.stackable = stackable
        self.footprint = float(footprint if footprint is not None else radius)


class _Builder:
    def __init__(self, rng, resolution, spp: int = 16):
        self.rng = rng
        w, h = int(resolution[0]), int(resolution[1])
        self.resolution = (w, h)
        self.spp = spp
        self.d: dict[str, Any] = {"type": "scene", "integrator": {"type": "path"}}
        self.meta: dict[str, Any] = {"objects": [], "lights": [], "surfaces": []}
        self.objs: list[_Obj] = []
        self.n = 0

    def key(self, prefix: str) -> str:
        self.n += 1
        return f"{prefix}_{self.n:03d}"

    # -- camera -----------------------------------------------------------
    def camera(self, origin, target, fov: float, roll_deg: float = 0.0):
        origin, target = np.asarray(origin, float), np.asarray(target, float)
        fwd = _unit(target - origin)
        up0 = np.array([0.0, 1.0, 0.0])
        if abs(fwd @ up0) > 0.98:
            up0 = np.array([0.0, 0.0, 1.0])
        up = _rot3(fwd, math.radians(roll_deg)) @ up0
        w, h = self.resolution
        self.d["sensor"] = {
            "type": "perspective",
            "fov": float(fov),
            "fov_axis": "x",
            "near_clip": 0.01,
            "far_clip": 1000.0,
            "to_world": _look_at(origin, target, up),
            "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": int(self.spp)},
        }
        self.meta["camera"] = {"origin": origin.tolist(), "target": target.tolist(),
                               "fov": float(fov), "roll_deg": float(roll_deg)}

    # -- shapes -------------------------------------------------------------
    def shape(self, prefix: str, shape: dict, bsdf: dict | None = None, emitter: dict | None = None):
        s = dict(shape)
        if bsdf is not None:
            s["bsdf"] = bsdf
        if emitter is not None:
            s["emitter"] = emitter
        k = self.key(prefix)
        self.d[k] = s
        return k

    def surface(self, name: str, shape: dict, cls: str | None = None, weights=None, flat=False,
                bsdf=None, mmeta=None):
        if bsdf is None:
            if cls is None:
                cls = _pick_class(self.rng, _SURF_WEIGHTS if weights is None else weights)
            bsdf, mmeta = _material(self.rng, cls, flat=flat)
        elif mmeta is None:
            mmeta = {"class": cls or "diffuse", "type": bsdf["type"]}
        self.shape(name, shape, bsdf)
        self.meta["surfaces"].append({"name": name, **mmeta})
        return mmeta

    def rect(self, name, center, normal, hu, hv, hint=None, **kw):
        m = self.surface(name, {"type": "rectangle", "to_world": _xf(_rect_matrix(center, normal, hu, hv, hint))},
                         **kw)
        self.meta["surfaces"][-1]["area"] = float(4 * hu * hv)
        return m

    # -- lights -------------------------------------------------------------
    def add_light_meta(self, kind: str, cls: str, **info):
        self.meta["lights"].append({"type": kind, "class": cls, **info})

    def area_rect(self, center, normal, hu, hv, radiance_rgb, hint=None, note=""):
        m = _rect_matrix(center, normal, hu, hv, hint)
        self.shape("light", {"type": "rectangle", "to_world": _xf(m)},
                   {"type": "diffuse", "reflectance": _rgb([0.5, 0.5, 0.5])},
                   {"type": "area", "radiance": _rgb(radiance_rgb)})
        self.add_light_meta("rectangle", "area", area=4 * hu * hv, radiance=float(_luminance(radiance_rgb)), note=note)

    def area_sphere(self, center, radius, radiance_rgb, note=""):
        self.shape("light", {"type": "sphere", "center": [float(x) for x in center], "radius": float(radius)},
                   {"type": "diffuse", "reflectance": _rgb([0.5, 0.5, 0.5])},
                   {"type": "area", "radiance": _rgb(radiance_rgb)})
        self.add_light_meta("sphere", "area", radius=float(radius), radiance=float(_luminance(radiance_rgb)), note=note)
        self.objs.append(_Obj(center, radius, center[1] + radius))

    def point(self, pos, intensity_rgb):
        self.d[self.key("light")] = {"type": "point", "position": [float(x) for x in pos],
                                     "intensity": _rgb(intensity_rgb)}
        self.add_light_meta("point", "delta", intensity=float(_luminance(intensity_rgb)))

    def spot(self, pos, target, intensity_rgb, cutoff: float, beam: float):
        up = [0.0, 1.0, 0.0] if abs(_unit(np.subtract(target, pos))[1]) < 0.95 else [0.0, 0.0, 1.0]
        self.d[self.key("light")] = {"type": "spot", "to_world": _look_at(pos, target, up),
                                     "intensity": _rgb(intensity_rgb),
                                     "cutoff_angle": float(cutoff), "beam_width": float(beam)}
        self.add_light_meta("spot", "delta", intensity=float(_luminance(intensity_rgb)), cutoff=float(cutoff))

    def constant_env(self, radiance_rgb):
        self.d["env"] = {"type": "constant", "radiance": _rgb(radiance_rgb)}
        self.add_light_meta("constant", "environment", radiance=float(_luminance(radiance_rgb)))

    def sky_env(self, scale: float, width: int = 256, sun=None, rotate_deg: float = 0.0):
        img, smeta = _sky_image(self.rng, width, sun=sun)
        env = {"type": "envmap", "bitmap": _bitmap(img), "scale": float(scale)}
        if rotate_deg:
            env["to_world"] = _xf(_rot([0, 1, 0], math.radians(rotate_deg)))
        self.d["env"] = env
        self.add_light_meta("envmap", "environment", scale=float(scale), **smeta)
        return smeta


# --------------------------------------------------------------------------
# radiometry helpers: how bright must a light be
# --------------------------------------------------------------------------

def _solid_angle_disklike(area: float, dist: float) -> float:
    a2 = area / math.pi
    return 2 * math.pi * (1 - dist / math.sqrt(dist * dist + a2))


def _solid_angle_sphere(radius: float, dist: float) -> float:
    dist = max(dist, radius * 1.05)
    return 2 * math.pi * (1 - math.sqrt(1 - (radius / dist) ** 2))


def _area_radiance(target_lo: float, omega: float, cos_l: float = 1.0) -> float:
    """Radiance an emitter needs so a reference surface facing it has radiance
    target_lo: Lo = rho * L * omega * cos / pi."""
    return target_lo * math.pi / (_RHO_REF * max(omega * max(cos_l, 0.1), 1e-6))


def _point_intensity(target_lo: float, dist: float) -> float:
    return target_lo * math.pi * dist * dist / _RHO_REF


# --------------------------------------------------------------------------
# objects
# --------------------------------------------------------------------------

_SHAPE_KINDS = ("sphere", "cube", "cylinder", "disk", "rectangle")
_SHAPE_P = np.array([0.30, 0.28, 0.20, 0.10, 0.12])


def _add_object(b: _Builder, region, floor_y: float, mat_weights, allow_overlap_p=0.15):
    """Place one random object in region = (xmin, xmax, zmin, zmax) on a floor."""
    rng = b.rng
    kind = str(rng.choice(_SHAPE_KINDS, p=_SHAPE_P))
    flat = kind in ("disk", "rectangle")
    cls = _pick_class(rng, mat_weights)
    bsdf, mmeta = _material(rng, cls, flat=flat)
    xmin, xmax, zmin, zmax = region
    span = min(xmax - xmin, zmax - zmin)
    smax = max(0.25, min(0.8, span * 0.2))

    stack_on = None
    stackables = [o for o in b.objs if o.stackable]
    if kind in ("sphere", "cube", "cylinder") and stackables and rng.random() < 0.25:
        stack_on = stackables[int(rng.integers(len(stackables)))]
    floating = stack_on is None and rng.random() < 0.08
    overlap_ok = rng.random() < allow_overlap_p

    for attempt in range(40):
        if stack_on is not None:
            xz = stack_on.center[[0, 2]] + rng.normal(0, 0.3, 2) * stack_on.footprint * 0.5
            base = stack_on.top
        else:
            xz = np.array([rng.uniform(xmin, xmax), rng.uniform(zmin, zmax)])
            base = floor_y + (rng.uniform(0.3, 1.5) if floating else 0.0)
        stackable = False
        shapes = []
        if kind == "sphere":
            r = rng.uniform(0.15, smax)
            if stack_on is not None:
                r = min(r, stack_on.footprint * 1.2)
            sink = r * rng.uniform(0.0, 0.15) if (stack_on is None and not floating) else 0.0
            c = np.array([xz[0], base + r - sink, xz[1]])
            shapes.append({"type": "sphere", "center": c.tolist(), "radius": float(r)})
            top, brad, foot = c[1] + r, r, r
            info = {"radius": float(r)}
        elif kind == "cube":
            s = rng.uniform(0.12, smax * 0.8, 3)
            if rng.random() < 0.3:
                s[:] = s[0]
            if stack_on is not None:
                s[[0, 2]] = np.minimum(s[[0, 2]], stack_on.footprint)
            if rng.random() < 0.15:
                R = _random_rotation3(rng)
            else:
                R = _rot3([0, 1, 0], rng.uniform(0, 2 * np.pi))
                stackable = True
            hy = float(np.sum(np.abs(R[1, :]) * s))
            c = np.array([xz[0], base + hy, xz[1]])
            m = np.eye(4)
            m[:3, :3] = R @ np.diag(s)
            m[:3, 3] = c
            shapes.append({"type": "cube", "to_world": _xf(m)})
            top, brad, foot = c[1] + hy, float(np.linalg.norm(s)), float(np.hypot(s[0], s[2]))
            info = {"half_size": s.tolist()}
        elif kind == "cylinder":
            r = rng.uniform(0.08, smax * 0.7)
            hgt = rng.uniform(0.2, 2.2 * smax)
            if stack_on is not None:
                r = min(r, stack_on.footprint)
            if rng.random() < 0.7:
                axis = np.array([0.0, 1.0, 0.0])
                p0 = np.array([xz[0], base, xz[1]])
                stackable = True
                top = base + hgt
            else:
                a = rng.uniform(0, 2 * np.pi)
                axis = np.array([math.cos(a), 0.0, math.sin(a)])
                c = np.array([xz[0], base + r, xz[1]])
                p0 = c - axis * hgt / 2
                top = base + 2 * r
            p1 = p0 + axis * hgt
            R = _frame(axis)
            m = np.eye(4)
            m[:3, :3] = R @ np.diag([r, r, hgt])
            m[:3, 3] = p0
            shapes.append({"type": "cylinder", "to_world": _xf(m)})
            # caps: keep the solid closed (needed for glass)
            shapes.append({"type": "disk", "to_world": _xf(_disk_matrix(p1, axis, r))})
            shapes.append({"type": "disk", "to_world": _xf(_disk_matrix(p0, -axis, r))})
            c = (p0 + p1) / 2
            brad, foot = math.hypot(r, hgt / 2), max(r, hgt / 2 if axis[1] == 0 else r)
            info = {"radius": float(r), "height": float(hgt)}
        elif kind == "disk":
            r = rng.uniform(0.15, smax * 1.2)
            if rng.random() < 0.4 and not floating:
                n = np.array([0.0, 1.0, 0.0])
                c = np.array([xz[0], base + 0.003 + 0.002 * rng.random(), xz[1]])
                top = c[1]
            else:
                a = rng.uniform(0, 2 * np.pi)
                tilt = rng.uniform(-0.5, 0.5)
                n = _unit([math.cos(a), math.sin(tilt), math.sin(a)])
                c = np.array([xz[0], base + r * math.cos(tilt) + 0.01, xz[1]])
                top = c[1] + r
            shapes.append({"type": "disk", "to_world": _xf(_disk_matrix(c, n, r))})
            brad, foot = r, r
            info = {"radius": float(r)}
        else:  # rectangle
            hu, hv = rng.uniform(0.15, smax * 1.2, 2)
            mode = rng.random()
            if mode < 0.3 and not floating:  # lying on the floor
                n = np.array([0.0, 1.0, 0.0])
                c = np.array([xz[0], base + 0.003 + 0.002 * rng.random(), xz[1]])
                hint = _rot3([0, 1, 0], rng.uniform(0, 2 * np.pi)) @ np.array([1.0, 0, 0])
                top = c[1]
            else:  # standing / leaning panel
                a = rng.uniform(0, 2 * np.pi)
                lean = rng.uniform(-0.35, 0.35) if mode < 0.8 else rng.uniform(-1.2, 1.2)
                n = _unit([math.cos(a) * math.cos(lean), math.sin(lean), math.sin(a) * math.cos(lean)])
                hint = np.array([0.0, 1.0, 0.0])
                # v axis of the frame is (roughly) up; bottom edge on the floor
                R = _frame(n, hint)
                vy = abs(R[1, 1]) * hv + abs(R[1, 0]) * hu
                c = np.array([xz[0], base + vy + 0.005, xz[1]])
                top = c[1] + vy
            m = _rect_matrix(c, n, hu, hv, hint)
            shapes.append({"type": "rectangle", "to_world": _xf(m)})
            brad, foot = math.hypot(hu, hv), math.hypot(hu, hv)
            info = {"half_size": [float(hu), float(hv)]}

        if stack_on is not None or floating or overlap_ok:
            break
        ok = all(np.hypot(*(xz - o.center[[0, 2]])) > 0.9 * (foot + o.footprint) for o in b.objs)
        if ok:
            break
    else:
        return None  # could not place it without overlap

    for i, sh in enumerate(shapes):
        b.shape("obj" if i == 0 else "objpart", sh, bsdf)
    o = _Obj(c, brad, top, stackable=stackable, footprint=foot)
    b.objs.append(o)
    b.meta["objects"].append({"shape": kind, **mmeta, **info,
                              "center": [float(x) for x in c],
                              "placement": "stacked" if stack_on is not None else ("floating" if floating else "floor")})
    return o


def _add_clutter(b: _Builder, region, floor_y: float, mat_weights):
    """Many small objects (fine detail) sharing a few materials."""
    rng = b.rng
    mats = [_material(rng, _pick_class(rng, mat_weights), bump=False) for _ in range(int(rng.integers(1, 4)))]
    xmin, xmax, zmin, zmax = region
    # a patch of the region
    cx, cz = rng.uniform(xmin, xmax), rng.uniform(zmin, zmax)
    rad = min(xmax - xmin, zmax - zmin) * rng.uniform(0.15, 0.5)
    n = int(rng.integers(8, 40))
    size = _loguniform(rng, 0.025, 0.1)
    for _ in range(n):
        bsdf, mmeta = mats[int(rng.integers(len(mats)))]
        x = float(np.clip(cx + rng.normal(0, rad / 2), xmin, xmax))
        z = float(np.clip(cz + rng.normal(0, rad / 2), zmin, zmax))
        r = size * rng.uniform(0.5, 1.5)
        if rng.random() < 0.6:
            b.shape("clutter", {"type": "sphere", "center": [x, floor_y + r, z], "radius": float(r)}, bsdf)
            kind = "sphere"
        else:
            m = np.eye(4)
            R = _rot3([0, 1, 0], rng.uniform(0, 2 * np.pi))
            m[:3, :3] = R * r
            m[:3, 3] = [x, floor_y + r, z]
            b.shape("clutter", {"type": "cube", "to_world": _xf(m)}, bsdf)
            kind = "cube"
        b.meta["objects"].append({"shape": kind, **mmeta, "placement": "clutter", "radius": float(r),
                                  "center": [x, floor_y + r, z]})
        b.objs.append(_Obj([x, floor_y + r, z], r * 1.8, floor_y + 2 * r, footprint=r))


def _content_bounds(b: _Builder, default_target):
    if not b.objs:
        return np.asarray(default_target, float), 1.0
    cs = np.array([o.center for o in b.objs])
    rs = np.array([o.radius for o in b.objs])
    tgt = cs.mean(axis=0)
    tgt[1] = float(np.clip(tgt[1], 0.1, 2.0))
    extent = float(np.max(np.linalg.norm(cs - tgt, axis=1) + rs))
    return tgt, max(extent, 0.3)


def _camera_clear(b: _Builder, pos, margin=0.08) -> bool:
    return all(np.linalg.norm(pos - o.center) > o.radius + margin for o in b.objs)


def _random_roll(rng) -> float:
    r = rng.random()
    if r < 0.6:
        return 0.0
    if r < 0.93:
        return float(rng.normal(0, 5.0))
    return float(rng.uniform(-25, 25))


# --------------------------------------------------------------------------
# layouts
# --------------------------------------------------------------------------

def _light_share(rng, n: int) -> np.ndarray:
    return rng.dirichlet(np.full(n, 2.0)) if n > 1 else np.ones(1)


def _blocks_view(b: _Builder, pos, radius: float) -> bool:
    """True if a light at pos (bounding radius) would sit near the camera or
    between the camera and its target (inside the view cone)."""
    cam = b.meta.get("camera")
    if cam is None:
        return False
    o, t = np.array(cam["origin"]), np.array(cam["target"])
    to_l, to_t = np.asarray(pos) - o, t - o
    dl = float(np.linalg.norm(to_l))
    if dl < radius + 0.3:
        return True
    if dl > float(np.linalg.norm(to_t)):
        return False
    ang = math.degrees(math.acos(float(np.clip(to_l @ to_t / (dl * np.linalg.norm(to_t)), -1, 1))))
    return ang < cam["fov"] * 0.75 + math.degrees(math.atan(radius / dl))


def _outdoor_area_lights(b: _Builder, n: int, shares, T: float, tgt, min_elev=20.0):
    rng = b.rng
    for i in range(n):
        is_rect = rng.random() < 0.55
        size = _loguniform(rng, 0.05, 1.5) if is_rect else _loguniform(rng, 0.03, 0.6)
        for _ in range(30):
            az = rng.uniform(0, 2 * np.pi)
            el = math.radians(rng.uniform(min_elev, 80.0))
            dist = rng.uniform(1.8, 6.0)
            dirv = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
            pos = tgt + dirv * dist
            if not _blocks_view(b, pos, size * 1.5):
                break
        tint, tname = _random_light_tint(rng)
        lo = shares[i] * T
        if is_rect:
            hu, hv = size, size * rng.uniform(0.3, 1.0)
            om = _solid_angle_disklike(4 * hu * hv, dist)
            L = _area_radiance(lo, om)
            b.area_rect(pos, -dirv, hu, hv, tint * L, note=tname)
        else:
            r = size
            L = _area_radiance(lo, _solid_angle_sphere(r, dist))
            b.area_sphere(pos, r, tint * L, note=tname)


def _delta_light(b: _Builder, T: float, tgt, pos=None, flux: float | None = None):
    """Point or spot light aimed at tgt; intensity from the target radiance T
    at tgt or, if given, from the emitted flux (rooms)."""
    rng = b.rng
    if pos is None:
        for _ in range(30):
            az = rng.uniform(0, 2 * np.pi)
            el = math.radians(rng.uniform(25, 80))
            dist = rng.uniform(1.5, 5.0)
            pos = tgt + dist * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
            if not _blocks_view(b, pos, 0.1):
                break
    dist = float(np.linalg.norm(pos - tgt))
    tint, _ = _random_light_tint(rng)
    if rng.random() < 0.5:
        I = _point_intensity(T, dist) if flux is None else flux / (4 * math.pi)
        b.point(pos, tint * I)
    else:
        cutoff = rng.uniform(15, 50)
        if flux is None:
            I = _point_intensity(T, dist)
        else:
            I = flux / (2 * math.pi * (1 - math.cos(math.radians(cutoff))))
        b.spot(pos, tgt + rng.normal(0, 0.2, 3), tint * I, cutoff, cutoff * rng.uniform(0.5, 0.9))


def _layout_open(b: _Builder, corner: bool):
    rng = b.rng
    b.meta["layout"] = "corner" if corner else "open"
    # ground
    gsize = rng.uniform(20, 60)
    if rng.random() < 0.75:
        b.rect("ground", [0, 0, 0], [0, 1, 0], gsize, gsize, hint=[0, 0, 1])
    else:
        b.surface("ground", {"type": "disk", "to_world": _xf(_disk_matrix([0, 0, 0], [0, 1, 0], gsize))})
    # objects
    R = rng.uniform(1.0, 3.0)
    weights = rng.dirichlet(_OBJ_WEIGHTS * 12)
    for _ in range(int(rng.integers(3, 11))):
        _add_object(b, (-R, R, -R, R), 0.0, weights)
    if rng.random() < 0.2:
        _add_clutter(b, (-R, R, -R, R), 0.0, weights)
    tgt, ext = _content_bounds(b, [0, 0.5, 0])

    # camera
    fov = rng.uniform(30, 70)
    d = ext / math.tan(math.radians(fov) / 2) * rng.uniform(0.8, 1.5)
    d = max(d, ext + 0.5)
    az = rng.uniform(0, 2 * np.pi)
    el = math.radians(rng.uniform(4, 55))
    dirv = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    pos = tgt + dirv * d
    while not _camera_clear(b, pos) or pos[1] < 0.15:
        d *= 1.15
        pos = tgt + dirv * d
        pos[1] = max(pos[1], 0.15)
    b.camera(pos, tgt + rng.normal(0, 0.1 * ext, 3), fov, _random_roll(rng))

    if corner:  # back wall (and maybe a side wall) behind the content
        nb = _unit([dirv[0], 0, dirv[2]])
        ns = np.array([nb[2], 0, -nb[0]]) * (1 if rng.random() < 0.5 else -1)
        hw = rng.uniform(6, 15)
        ht = rng.uniform(3, 8)
        wb = tgt - nb * (R + rng.uniform(0.3, 1.5))
        b.rect("wall", [wb[0], ht, wb[2]], nb, hw, ht, hint=[0, 1, 0], flat=True, weights=_WALL_WEIGHTS)
        if rng.random() < 0.6:
            ws = tgt - ns * (R + rng.uniform(0.3, 1.5))
            b.rect("wall", [ws[0], ht, ws[2]], ns, hw, ht, hint=[0, 1, 0], flat=True, weights=_WALL_WEIGHTS)

    # lights
    T = _loguniform(rng, _T_RANGE[0], _T_RANGE[1])
    b.meta["target_radiance"] = T
    if corner:
        T *= 2.0  # the walls block about half of the sky and the lights' surroundings
    r = rng.random()
    env = "sky" if r < 0.5 else ("constant" if r < 0.82 else "none")
    n_area = int(rng.choice([0, 1, 2], p=[0.45, 0.4, 0.15])) if env != "none" else int(rng.integers(1, 4))
    n_delta = int(rng.random() < 0.15)
    n = (env != "none") + n_area + n_delta
    shares = _light_share(rng, n)
    i = 0
    if env == "sky":
        b.sky_env(shares[0] * T / _RHO_REF, width=int(rng.choice([256, 512])))
        i = 1
    elif env == "constant":
        tint, _ = _random_light_tint(rng)
        b.constant_env(tint * shares[0] * T / _RHO_REF)
        i = 1
    _outdoor_area_lights(b, n_area, shares[i:i + n_area], T, tgt)
    if n_delta:
        _delta_light(b, shares[-1] * T, tgt)


def _room_walls(b: _Builder, W, D, H, open_front=False, window=None, floor_cls=None):
    """Axis-aligned room [-W/2, W/2] x [0, H] x [-D/2, D/2], normals inward.
    window: (wall, u0, u1, v0, v1) hole on the wall 'x+' given in wall coords."""
    rng = b.rng
    same = rng.random() < 0.4
    shared = _material(rng, _pick_class(rng, _WALL_WEIGHTS)) if same else None

    def wall_kw():
        if shared is not None:
            return {"bsdf": shared[0], "cls": shared[1]["class"], "mmeta": shared[1]}
        return _wall_material_kw(rng)

    b.rect("floor", [0, 0, 0], [0, 1, 0], W / 2, D / 2, hint=[0, 0, 1], cls=floor_cls)
    b.rect("ceiling", [0, H, 0], [0, -1, 0], W / 2, D / 2, hint=[0, 0, 1], **wall_kw())
    walls = {
        "x-": ([-W / 2, H / 2, 0], [1, 0, 0], D / 2),
        "x+": ([W / 2, H / 2, 0], [-1, 0, 0], D / 2),
        "z-": ([0, H / 2, -D / 2], [0, 0, 1], W / 2),
        "z+": ([0, H / 2, D / 2], [0, 0, -1], W / 2),
    }
    for name, (c, n, hw) in walls.items():
        if open_front and name == "z+":
            continue
        if window is not None and window[0] == name:
            _wall_with_hole(b, np.array(c, float), np.array(n, float), hw, H / 2, window[1:], wall_kw())  # one material
        else:
            b.rect("wall", c, n, hw, H / 2, hint=[0, 1, 0], **wall_kw())


def _wall_material_kw(rng) -> dict:
    bsdf, mmeta = _material(rng, _pick_class(rng, _WALL_WEIGHTS))
    return {"bsdf": bsdf, "cls": mmeta["class"], "mmeta": mmeta}


def _wall_with_hole(b, c, n, hw, hh, hole, kw):
    """Wall rectangle minus an axis-aligned hole (u0,u1,v0,v1) in [-1,1] wall coords."""
    u0, u1, v0, v1 = hole
    R = _frame(n, [0, 1, 0])
    eu, ev = R[:, 0], R[:, 1]

    def piece(a0, a1, b0, b1):
        if a1 - a0 < 1e-3 or b1 - b0 < 1e-3:
            return
        cc = c + eu * hw * (a0 + a1) / 2 + ev * hh * (b0 + b1) / 2
        b.rect("wall", cc, n, hw * (a1 - a0) / 2, hh * (b1 - b0) / 2, hint=[0, 1, 0], **kw)

    piece(-1, u0, -1, 1)
    piece(u1, 1, -1, 1)
    piece(u0, u1, -1, v0)
    piece(u0, u1, v1, 1)


def _room_camera(b: _Builder, W, D, H, tgt, ext, fov):
    rng = b.rng
    want = ext / math.tan(math.radians(fov) / 2) * rng.uniform(0.9, 1.4)
    best, best_err = None, float("inf")
    for _ in range(60):
        p = np.array([rng.uniform(-W / 2 + 0.25, W / 2 - 0.25), rng.uniform(0.3, H - 0.3),
                      rng.uniform(-D / 2 + 0.25, D / 2 - 0.25)])
        if not _camera_clear(b, p, 0.15):
            continue
        d = np.linalg.norm(p - tgt)
        err = abs(d - want) + (2.0 if p[1] < 0.5 else 0.0)
        if err < best_err:
            best, best_err = p, err
    if best is None:
        best = np.array([0.0, H * 0.6, D / 2 - 0.2])
    return best


def _layout_room(b: _Builder, kind: str):
    """kind: 'closed', 'window' or 'cornell' (open front)."""
    rng = b.rng
    b.meta["layout"] = kind
    if kind == "cornell":
        W = rng.uniform(2.0, 5.0)
        D, H = W * rng.uniform(0.8, 1.3), W * rng.uniform(0.8, 1.2)
    else:
        W, D, H = rng.uniform(3.5, 9.0), rng.uniform(3.5, 9.0), rng.uniform(2.4, 4.5)
    b.meta["room"] = [float(W), float(D), float(H)]

    window = None
    if kind == "window":
        wall = str(rng.choice(["x-", "x+", "z-", "z+"]))
        wu = rng.uniform(0.2, 0.6)
        uc = rng.uniform(-0.9 + wu, 0.9 - wu)
        v0 = rng.uniform(-0.8, -0.1)
        v1 = rng.uniform(v0 + 0.4, 0.9)
        window = (wall, uc - wu, uc + wu, v0, v1)
        b.meta["window"] = list(window)

    floor_cls = None
    if rng.random() < 0.2:
        floor_cls = str(rng.choice(["plastic", "conductor"], p=[0.75, 0.25]))
    _room_walls(b, W, D, H, open_front=(kind == "cornell"), window=window, floor_cls=floor_cls)

    mx = 0.45 if kind == "cornell" else 0.6
    region = (-W / 2 + mx, W / 2 - mx, -D / 2 + mx, D / 2 - mx)
    if kind != "cornell":
        # keep a strip free for the camera sometimes
        region = (region[0], region[1], region[2], region[3] - rng.uniform(0.0, 0.4) * D)
    weights = rng.dirichlet(_OBJ_WEIGHTS * 12)
    for _ in range(int(rng.integers(3, 11))):
        _add_object(b, region, 0.0, weights)
    if rng.random() < 0.2:
        _add_clutter(b, region, 0.0, weights)
    tgt, ext = _content_bounds(b, [0, H / 3, 0])

    fov = rng.uniform(30, 70)
    if kind == "cornell":
        d = max(W, H) * 0.5 / math.tan(math.radians(fov) / 2) * rng.uniform(0.75, 1.05)
        pos = np.array([rng.uniform(-0.15, 0.15) * W, H * rng.uniform(0.35, 0.65), D / 2 + max(d - D / 2, 0.2)])
        look = 0.5 * np.array([pos[0] * 0.5, H * rng.uniform(0.35, 0.55), 0.0]) + 0.5 * tgt
    else:
        pos = _room_camera(b, W, D, H, tgt, ext, fov)
        look = tgt + rng.normal(0, 0.1 * ext, 3)
    b.camera(pos, look, fov, _random_roll(rng))

    T = _loguniform(rng, _T_RANGE[0], _T_RANGE[1])
    b.meta["target_radiance"] = T

    # Rooms: set the emitted flux from an energy balance.  With total surface
    # area A (openings count as black) and mean albedo ~0.5, the mean surface
    # radiance is about rho * Phi / (pi * A * (1 - rho)); aim it at T.
    area_tot = 2 * (W * D + W * H + D * H)
    walls = [sf for sf in b.meta["surfaces"] if "area" in sf]
    rho = sum(sf["area"] * sf.get("albedo", 0.5) for sf in walls) / area_tot  # openings are black
    rho = float(np.clip(rho, 0.15, 0.85))
    flux = T * math.pi * area_tot * _K_ROOM * (1 - rho) / rho
    b.meta["room_flux"] = float(flux)
    b.meta["room_albedo"] = rho

    if kind == "window":
        wall = window[0]
        n = {"x-": [1, 0, 0], "x+": [-1, 0, 0], "z-": [0, 0, 1], "z+": [0, 0, -1]}[wall]
        hw = D / 2 if wall[0] == "x" else W / 2
        area = (window[2] - window[1]) * hw * (window[4] - window[3]) * H / 2
        lamp = rng.random() < 0.3
        share = rng.uniform(0.5, 0.9) if lamp else 1.0
        smeta = b.sky_env(1.0, width=512, sun=rng.random() < 0.75)
        # irradiance on the window at sky scale 1 (the map gives pi on a
        # horizontal surface): about half of the sky part, plus the sun
        frac = smeta.get("sun_fraction", 0.0)
        e_win = math.pi * (1 - frac) * 0.5
        if "sun_dir" in smeta:
            # rotate the sky so the sun tends to shine in through the window
            _aim_sun(b, -np.array(n, float), rng.normal(0, 0.5))
            b.meta["lights"][-1]["sun_through_window"] = True
            sd = np.array(b.meta["lights"][-1]["sun_dir"])
            sin_e = max(sd[1], 0.05)
            e_win += math.pi * frac / sin_e * max(float(-np.dot(sd, n)), 0.0)
        scale = share * flux / (area * e_win)
        b.d["env"]["scale"] = float(scale)
        b.meta["lights"][-1]["scale"] = float(scale)
        if lamp:
            _room_lamps(b, W, D, H, tgt, flux * (1 - share), 1)
        return

    n_lights = int(rng.choice([1, 2, 3], p=[0.55, 0.33, 0.12])) if kind == "closed" else int(rng.choice([1, 2], p=[0.75, 0.25]))
    _room_lamps(b, W, D, H, tgt, flux, n_lights, first_ceiling=(kind == "cornell"), open_front=(kind == "cornell"))
    if kind == "cornell" and rng.random() < 0.4:
        tint, _ = _random_light_tint(rng)
        b.constant_env(tint * T * rng.uniform(0.05, 0.4) / _RHO_REF)


def _aim_sun(b: _Builder, want_dir, jitter_rad: float = 0.0):
    """Rotate the sky env about +y so the sun's azimuth matches want_dir."""
    light = [l for l in b.meta["lights"] if l["type"] == "envmap"][-1]
    sd = np.array(light["sun_dir"])
    rot = math.atan2(want_dir[0], want_dir[2]) + jitter_rad - math.atan2(sd[0], sd[2])
    b.d["env"]["to_world"] = _xf(_rot([0, 1, 0], rot))
    light["sun_dir"] = [float(x) for x in _rot3([0, 1, 0], rot) @ sd]


def _room_lamps(b: _Builder, W, D, H, tgt, flux, n, first_ceiling=False, open_front=False):
    """n lights inside the room sharing the emitted flux."""
    rng = b.rng
    shares = _light_share(rng, n)
    for i in range(n):
        phi = shares[i] * flux
        tint, tname = _random_light_tint(rng)
        r = 0.0 if (first_ceiling and i == 0) else rng.random()
        if r < 0.45:  # ceiling panel facing down
            hu = rng.uniform(0.05, 0.3) * W if rng.random() < 0.7 else _loguniform(rng, 0.03, 0.15)
            hv = min(hu * rng.uniform(0.4, 1.0), 0.4 * D)
            c = np.array([rng.uniform(-W / 2 + hu, W / 2 - hu) * 0.7, H - 0.005,
                          rng.uniform(-D / 2 + hv, D / 2 - hv) * 0.7])
            L = phi / (math.pi * 4 * hu * hv)
            b.area_rect(c, [0, -1, 0], hu, hv, tint * L, hint=[0, 0, 1], note="ceiling " + tname)
        elif r < 0.65:  # sphere lamp
            rad = _loguniform(rng, 0.03, 0.3)
            for _ in range(30):
                c = np.array([rng.uniform(-W / 2, W / 2) * 0.7, rng.uniform(H * 0.55, H - rad - 0.1),
                              rng.uniform(-D / 2, D / 2) * 0.7])
                if np.linalg.norm(c - np.array(b.meta["camera"]["origin"])) > rad + 0.4:
                    break
            L = phi / (math.pi * 4 * math.pi * rad * rad)
            b.area_sphere(c, rad, tint * L, note="lamp " + tname)
        elif r < 0.8:  # wall panel
            wall = int(rng.integers(3 if open_front else 4))  # 3 is z+, the open side
            hu, hv = rng.uniform(0.1, 0.5), rng.uniform(0.1, 0.4)
            y = rng.uniform(0.8, H - 0.6)
            if wall == 0:
                c, nrm = [-W / 2 + 0.005, y, rng.uniform(-D / 3, D / 3)], [1, 0, 0]
            elif wall == 1:
                c, nrm = [W / 2 - 0.005, y, rng.uniform(-D / 3, D / 3)], [-1, 0, 0]
            elif wall == 2:
                c, nrm = [rng.uniform(-W / 3, W / 3), y, -D / 2 + 0.005], [0, 0, 1]
            else:
                c, nrm = [rng.uniform(-W / 3, W / 3), y, D / 2 - 0.005], [0, 0, -1]
            L = phi / (math.pi * 4 * hu * hv)
            b.area_rect(np.array(c), nrm, hu, hv, tint * L, hint=[0, 1, 0], note="wall " + tname)
        elif r < 0.92:  # cove light facing the ceiling: indirect only
            hu, hv = rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.6)
            c = np.array([rng.uniform(-W / 3, W / 3), H - rng.uniform(0.3, 0.8), rng.uniform(-D / 3, D / 3)])
            L = phi / (math.pi * 4 * hu * hv)
            b.area_rect(c, [0, 1, 0], hu, hv, tint * L, hint=[0, 0, 1], note="indirect " + tname)
            b.meta["lights"][-1]["indirect"] = True
        else:
            pos = np.array([rng.uniform(-W / 3, W / 3), H - rng.uniform(0.1, 0.5), rng.uniform(-D / 3, D / 3)])
            _delta_light(b, 0.0, tgt, pos=pos, flux=phi)


# --------------------------------------------------------------------------
# public API: random scenes
# --------------------------------------------------------------------------

_LAYOUTS = ("open", "corner", "closed", "window", "cornell")
_LAYOUT_P = np.array([0.30, 0.14, 0.24, 0.12, 0.20])


def random_scene_with_meta(seed: int, resolution: tuple[int, int] = (128, 128)) -> tuple[dict, dict]:
    """Random scene dict plus a JSON-serialisable meta record.

    meta keys: seed, layout, objects (shape, class, type, ...), surfaces,
    lights (type, class, ...), camera, target_radiance, material_classes,
    light_classes.  ``resolution`` is (width, height).
    """
    _mi()
    rng = np.random.default_rng(int(seed))
    b = _Builder(rng, resolution)
    b.meta["seed"] = int(seed)
    layout = str(rng.choice(_LAYOUTS, p=_LAYOUT_P))
    if layout in ("open", "corner"):
        _layout_open(b, corner=(layout == "corner"))
    else:
        _layout_room(b, layout)
    _finish_meta(b)
    return b.d, b.meta


def _finish_meta(b: _Builder):
    classes = {o["class"] for o in b.meta["objects"]} | {s["class"] for s in b.meta["surfaces"]}
    if any("texture" in o for o in b.meta["objects"] + b.meta["surfaces"]):
        classes.add("textured")
    b.meta["material_classes"] = sorted(classes)
    b.meta["light_classes"] = sorted({l["class"] for l in b.meta["lights"]})
    b.meta["resolution"] = list(b.resolution)


def random_scene(seed: int, resolution: tuple[int, int] = (128, 128)) -> dict:
    """Deterministic random scene dict for training data (see module doc)."""
    return random_scene_with_meta(seed, resolution)[0]


def describe_scene(seed: int) -> str:
    """One-line human-readable summary of ``random_scene(seed)``."""
    _, m = random_scene_with_meta(seed, (8, 8))
    objs = ", ".join(f"{o['shape']}:{o['type']}" for o in m["objects"])
    lights = ", ".join(l["type"] for l in m["lights"])
    return (f"seed {seed}: layout={m['layout']} objects=[{objs}] lights=[{lights}] "
            f"classes={m['material_classes']} target={m.get('target_radiance', 0):.2f}")


# --------------------------------------------------------------------------
# named test scenes
# --------------------------------------------------------------------------

def _ts_diffuse_box(b: _Builder):
    W, D, H = 2.0, 3.0, 2.0
    red = {"type": "diffuse", "reflectance": _rgb([0.63, 0.065, 0.05])}
    green = {"type": "diffuse", "reflectance": _rgb([0.14, 0.45, 0.091])}
    white = {"type": "diffuse", "reflectance": _rgb([0.725, 0.71, 0.68])}
    b.rect("floor", [0, 0, 0], [0, 1, 0], W / 2, D / 2, hint=[0, 0, 1], bsdf=white)
    b.rect("ceiling", [0, H, 0], [0, -1, 0], W / 2, D / 2, hint=[0, 0, 1], bsdf=white)
    b.rect("wall", [-W / 2, H / 2, 0], [1, 0, 0], D / 2, H / 2, hint=[0, 1, 0], bsdf=red)
    b.rect("wall", [W / 2, H / 2, 0], [-1, 0, 0], D / 2, H / 2, hint=[0, 1, 0], bsdf=green)
    b.rect("wall", [0, H / 2, -D / 2], [0, 0, 1], W / 2, H / 2, hint=[0, 1, 0], bsdf=white)
    b.rect("wall", [0, H / 2, D / 2], [0, 0, -1], W / 2, H / 2, hint=[0, 1, 0], bsdf=white)
    for c, s, a in (([-0.4, 0.55, -0.8], [0.27, 0.55, 0.27], 0.3), ([0.4, 0.27, -0.2], [0.27, 0.27, 0.27], -0.3)):
        m = np.eye(4)
        m[:3, :3] = _rot3([0, 1, 0], a) @ np.diag(s)
        m[:3, 3] = c
        b.shape("obj", {"type": "cube", "to_world": _xf(m)}, white)
        b.meta["objects"].append({"shape": "cube", "class": "diffuse", "type": "diffuse"})
    b.area_rect([0, H - 0.005, -0.6], [0, -1, 0], 0.25, 0.2, [34.0, 24.0, 8.0], hint=[0, 0, 1])
    b.camera([0, 1.0, D / 2 - 0.05], [0, 0.9, -0.5], 58.0)
    b.meta["layout"] = "closed"


def _ts_glossy(b: _Builder):
    W, D, H = 4.0, 4.0, 3.0
    grey = {"type": "diffuse", "reflectance": _rgb([0.6, 0.6, 0.6])}
    b.rect("floor", [0, 0, 0], [0, 1, 0], W / 2, D / 2, hint=[0, 0, 1],
           bsdf={"type": "roughplastic", "diffuse_reflectance": _rgb([0.3, 0.25, 0.2]), "alpha": 0.1}, cls="plastic")
    b.rect("ceiling", [0, H, 0], [0, -1, 0], W / 2, D / 2, hint=[0, 0, 1], bsdf=grey)
    for c, n in (([-W / 2, H / 2, 0], [1, 0, 0]), ([W / 2, H / 2, 0], [-1, 0, 0]),
                 ([0, H / 2, -D / 2], [0, 0, 1])):
        b.rect("wall", c, n, 2.0, H / 2, hint=[0, 1, 0], bsdf=grey)
    objs = [
        ({"type": "sphere", "center": [-0.9, 0.5, -0.3], "radius": 0.5},
         {"type": "roughconductor", "material": "Au", "alpha": 0.08}, "conductor"),
        ({"type": "sphere", "center": [0.2, 0.4, 0.4], "radius": 0.4},
         {"type": "roughconductor", "material": "Cu", "alpha": 0.3}, "conductor"),
        ({"type": "sphere", "center": [1.0, 0.45, -0.6], "radius": 0.45},
         {"type": "plastic", "diffuse_reflectance": _rgb([0.1, 0.2, 0.6])}, "plastic"),
    ]
    m = np.eye(4)
    m[:3, :3] = _rot3([0, 1, 0], 0.5) @ np.diag([0.35, 0.35, 0.35])
    m[:3, 3] = [0.1, 0.35, -1.1]
    objs.append(({"type": "cube", "to_world": _xf(m)},
                 {"type": "roughplastic", "diffuse_reflectance": _rgb([0.7, 0.3, 0.1]), "alpha": 0.15}, "plastic"))
    for sh, bs, cls in objs:
        b.shape("obj", sh, bs)
        b.meta["objects"].append({"shape": sh["type"], "class": cls, "type": bs["type"]})
    b.area_rect([0, H - 0.005, 0], [0, -1, 0], 0.6, 0.4, [25.0, 24.0, 22.5], hint=[0, 0, 1])
    b.camera([0.3, 1.4, 1.95], [0, 0.4, -0.4], 55.0)
    b.meta["layout"] = "cornell"


def _ts_glass(b: _Builder):
    b.rect("ground", [0, 0, 0], [0, 1, 0], 20, 20, hint=[0, 0, 1],
           bsdf={"type": "diffuse", "reflectance": {
               "type": "checkerboard", "color0": _rgb([0.7, 0.7, 0.7]), "color1": _rgb([0.25, 0.25, 0.3]),
               "to_uv": _mi().ScalarTransform4f().scale([40.0, 40.0, 1.0])}}, cls="textured")
    b.meta["surfaces"][-1]["texture"] = "checkerboard"
    b.shape("obj", {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.6},
            {"type": "dielectric", "int_ior": 1.5})
    b.meta["objects"].append({"shape": "sphere", "class": "dielectric", "type": "dielectric"})
    b.shape("obj", {"type": "sphere", "center": [1.1, 0.3, -0.6], "radius": 0.3},
            {"type": "diffuse", "reflectance": _rgb([0.7, 0.2, 0.2])})
    b.meta["objects"].append({"shape": "sphere", "class": "diffuse", "type": "diffuse"})
    b.area_sphere([1.5, 3.5, 1.0], 0.15, np.array([1.0, 0.95, 0.85]) * _area_radiance(0.5, _solid_angle_sphere(0.15, 3.9)))
    b.constant_env([0.15, 0.17, 0.2])
    b.camera([0.0, 1.6, 3.2], [0.2, 0.4, 0.0], 45.0)
    b.meta["layout"] = "open"


def _ts_envmap_open(b: _Builder):
    b.rect("ground", [0, 0, 0], [0, 1, 0], 40, 40, hint=[0, 0, 1],
           bsdf={"type": "diffuse", "reflectance": _rgb([0.4, 0.38, 0.33])})
    specs = [
        ({"type": "sphere", "center": [-0.8, 0.5, 0.0], "radius": 0.5}, "diffuse", [0.2, 0.4, 0.7]),
        ({"type": "sphere", "center": [0.5, 0.35, 0.6], "radius": 0.35}, "conductor", None),
    ]
    for sh, cls, col in specs:
        bs = ({"type": "diffuse", "reflectance": _rgb(col)} if cls == "diffuse"
              else {"type": "roughconductor", "material": "Al", "alpha": 0.15})
        b.shape("obj", sh, bs)
        b.meta["objects"].append({"shape": "sphere", "class": cls, "type": bs["type"]})
    m = np.eye(4)
    m[:3, :3] = _rot3([0, 1, 0], 0.7) @ np.diag([0.4, 0.4, 0.4])
    m[:3, 3] = [0.6, 0.4, -0.8]
    b.shape("obj", {"type": "cube", "to_world": _xf(m)},
            {"type": "roughplastic", "diffuse_reflectance": _rgb([0.7, 0.6, 0.2]), "alpha": 0.2})
    b.meta["objects"].append({"shape": "cube", "class": "plastic", "type": "roughplastic"})
    b.sky_env(1.0, width=256, sun=True)
    _aim_sun(b, [-0.7, 0.0, 0.7])  # sun behind-left of the camera
    b.camera([0.0, 0.9, 4.0], [0.0, 0.6, 0.0], 50.0)
    b.meta["layout"] = "open"


def _ts_no_hit(b: _Builder):
    b.constant_env([0.4, 0.5, 0.7])
    b.camera([0, 1, 0], [0, 2, -3], 50.0)
    b.meta["layout"] = "empty"


def _ts_textured(b: _Builder):
    rng = b.rng
    b.rect("floor", [0, 0, 0], [0, 1, 0], 10, 10, hint=[0, 0, 1],
           bsdf={"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": _bitmap(_tex_named(rng, "tiles")),
                                                   "raw": True, "to_uv": _mi().ScalarTransform4f().scale([8.0, 8.0, 1.0])}},
           cls="textured")
    b.meta["surfaces"][-1]["texture"] = "bitmap:tiles"
    b.rect("wall", [0, 3, -2.5], [0, 0, 1], 10, 3, hint=[0, 1, 0],
           bsdf={"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": _bitmap(_tex_named(rng, "stripes")),
                                                   "raw": True, "to_uv": _mi().ScalarTransform4f().scale([4.0, 2.0, 1.0])}},
           cls="textured")
    b.meta["surfaces"][-1]["texture"] = "bitmap:stripes"
    m = np.eye(4)
    m[:3, :3] = _rot3([0, 1, 0], 0.6) @ np.diag([0.5, 0.5, 0.5])
    m[:3, 3] = [-0.7, 0.5, -0.5]
    b.shape("obj", {"type": "cube", "to_world": _xf(m)},
            {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": _bitmap(_tex_named(rng, "noise")), "raw": True}})
    b.meta["objects"].append({"shape": "cube", "class": "textured", "type": "diffuse", "texture": "bitmap:noise"})
    b.shape("obj", {"type": "sphere", "center": [0.8, 0.5, 0.2], "radius": 0.5},
            {"type": "diffuse", "reflectance": {"type": "checkerboard", "color0": _rgb([0.8, 0.8, 0.75]),
                                                "color1": _rgb([0.1, 0.2, 0.5]),
                                                "to_uv": _mi().ScalarTransform4f().scale([8.0, 4.0, 1.0])}})
    b.meta["objects"].append({"shape": "sphere", "class": "textured", "type": "diffuse", "texture": "checkerboard"})
    b.area_rect([1.5, 3.0, 2.0], _unit([-1.5, -3.0, -2.0]), 0.5, 0.5,
                np.array([1.0, 0.97, 0.9]) * _area_radiance(0.6, _solid_angle_disklike(1.0, 3.9)))
    b.constant_env([0.1, 0.1, 0.12])
    b.camera([0.3, 1.5, 3.5], [0.0, 0.5, -0.3], 50.0)
    b.meta["layout"] = "corner"


def _tex_named(rng, kind: str) -> np.ndarray:
    n = 128
    x, y = _grid_coords(n)
    if kind == "tiles":
        k, gw = 4, 0.06
        fx, fy = (x * k) % 1.0, (y * k) % 1.0
        tile = 0.5 + 0.5 * rng.random((k, k))[np.floor(y * k).astype(int), np.floor(x * k).astype(int)]
        s = np.where((fx < gw) | (fy < gw), 0.0, tile)
        c0, c1 = np.array([0.1, 0.1, 0.1]), np.array([0.75, 0.7, 0.6])
    elif kind == "stripes":
        s = ((x * 6) % 1.0 < 0.5).astype(float)
        c0, c1 = np.array([0.7, 0.15, 0.1]), np.array([0.8, 0.8, 0.7])
    else:
        s = _value_noise(rng, n, octaves=5, base_cells=4)
        c0, c1 = np.array([0.05, 0.3, 0.1]), np.array([0.8, 0.7, 0.3])
    img = c0 * (1 - s[..., None]) + c1 * s[..., None]
    return np.clip(img, 0.02, 0.9).astype(np.float32)


def _ts_window(b: _Builder):
    W, D, H = 5.0, 5.0, 3.0
    white = {"type": "diffuse", "reflectance": _rgb([0.7, 0.7, 0.68])}
    b.rect("floor", [0, 0, 0], [0, 1, 0], W / 2, D / 2, hint=[0, 0, 1],
           bsdf={"type": "diffuse", "reflectance": _rgb([0.45, 0.3, 0.2])})
    b.rect("ceiling", [0, H, 0], [0, -1, 0], W / 2, D / 2, hint=[0, 0, 1], bsdf=white)
    for c, n in (([W / 2, H / 2, 0], [-1, 0, 0]), ([0, H / 2, -D / 2], [0, 0, 1]), ([0, H / 2, D / 2], [0, 0, -1])):
        b.rect("wall", c, n, 2.5, H / 2, hint=[0, 1, 0], bsdf=white)
    _wall_with_hole(b, np.array([-W / 2, H / 2, 0.0]), np.array([1.0, 0, 0]), D / 2, H / 2,
                    (-0.3, 0.3, -0.2, 0.6), {"bsdf": white, "cls": "diffuse"})
    b.shape("obj", {"type": "sphere", "center": [0.5, 0.5, -0.5], "radius": 0.5},
            {"type": "roughplastic", "diffuse_reflectance": _rgb([0.6, 0.5, 0.3]), "alpha": 0.2})
    b.meta["objects"].append({"shape": "sphere", "class": "plastic", "type": "roughplastic"})
    m = np.eye(4)
    m[:3, :3] = np.diag([0.4, 0.6, 0.4])
    m[:3, 3] = [-0.6, 0.6, 0.8]
    b.shape("obj", {"type": "cube", "to_world": _xf(m)}, {"type": "diffuse", "reflectance": _rgb([0.3, 0.5, 0.6])})
    b.meta["objects"].append({"shape": "cube", "class": "diffuse", "type": "diffuse"})
    b.sky_env(15.0, width=256, sun=True)
    _aim_sun(b, [-1.0, 0.0, 0.3])
    b.camera([2.3, 1.6, 2.2], [-1.0, 0.7, -0.5], 65.0)
    b.meta["layout"] = "window"


_TEST_SCENES = {
    "diffuse_box": _ts_diffuse_box,
    "glossy": _ts_glossy,
    "glass": _ts_glass,
    "envmap_open": _ts_envmap_open,
    "no_hit": _ts_no_hit,
    "textured": _ts_textured,
    "window": _ts_window,
}


def list_test_scenes() -> list[str]:
    """Names accepted by :func:`test_scene`."""
    return list(_TEST_SCENES)


def test_scene_with_meta(name: str, resolution: tuple[int, int] = (32, 32)) -> tuple[dict, dict]:
    """Named deterministic scene and its meta record (see :func:`test_scene`)."""
    if name not in _TEST_SCENES:
        raise ValueError(f"unknown test scene {name!r}; available: {', '.join(_TEST_SCENES)}")
    _mi()
    b = _Builder(np.random.default_rng(12345), resolution)
    b.meta["name"] = name
    _TEST_SCENES[name](b)
    _finish_meta(b)
    return b.d, b.meta


def test_scene(name: str, resolution: tuple[int, int] = (32, 32)) -> dict:
    """Small deterministic named scene for tests and benchmarks.

    Names (``list_test_scenes()``): ``diffuse_box`` (closed Cornell-like room,
    diffuse only, one area light), ``glossy`` (rough conductors and plastics in
    a room), ``glass`` (glass sphere on a diffuse floor), ``envmap_open``
    (objects on a ground plane lit only by a sky map), ``no_hit`` (camera sees
    only a constant environment), ``textured`` (diffuse textured surfaces),
    ``window`` (room lit by the sky through a window).  ``resolution`` is
    (width, height).
    """
    return test_scene_with_meta(name, resolution)[0]


# pytest would otherwise try to collect ``test_scene*`` when imported into a test module
test_scene.__test__ = False  # type: ignore[attr-defined]
test_scene_with_meta.__test__ = False  # type: ignore[attr-defined]
