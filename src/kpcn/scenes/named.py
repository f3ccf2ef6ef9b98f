"""Small deterministic named test scenes: :func:`test_scene`,
:func:`test_scene_with_meta`, :func:`list_test_scenes`."""

from __future__ import annotations

import numpy as np

from .base import _bitmap, _mi
from .builder import _Builder, _finish_meta
from .colours import _rgb
from .geometry import _rot3, _solid_angle_disklike, _solid_angle_sphere, _unit, _xf
from .layouts import _wall_with_hole
from .lights import _aim_sun, _area_radiance
from .materials import _grid_coords, _value_noise


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
