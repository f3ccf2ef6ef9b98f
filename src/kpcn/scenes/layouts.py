"""Layouts of random scenes (``open``, ``corner``, ``closed``, ``window``,
``cornell``) and the public API for them: :func:`random_scene`,
:func:`random_scene_with_meta`, :func:`describe_scene`."""

from __future__ import annotations

import math

import numpy as np

from .base import _mi
from .builder import _Builder, _finish_meta
from .colours import _random_light_tint
from .geometry import _disk_matrix, _frame, _loguniform, _unit, _xf
from .lights import _RHO_REF, _aim_sun, _delta_light, _light_share, _outdoor_area_lights, _room_lamps
from .materials import _OBJ_WEIGHTS, _WALL_WEIGHTS, _material, _pick_class
from .objects import _add_clutter, _add_object, _camera_clear, _content_bounds, _random_roll

_T_RANGE = (0.2, 1.0)  # radiance of a reference surface facing the lights (log-uniform)
_K_ROOM = 0.7  # calibration of the room energy balance (measured, see tests)


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
