"""The scene builder: :class:`_Builder` collects the scene dict and its meta
record (camera, surfaces, shapes, lights); :class:`_Obj` is the bounding
info of a placed object; :func:`_finish_meta` completes the meta record."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .base import _bitmap
from .colours import _luminance, _rgb
from .geometry import _look_at, _rect_matrix, _rot, _rot3, _unit, _xf
from .materials import _SURF_WEIGHTS, _material, _pick_class
from .sky import _sky_image


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


def _finish_meta(b: _Builder):
    classes = {o["class"] for o in b.meta["objects"]} | {s["class"] for s in b.meta["surfaces"]}
    if any("texture" in o for o in b.meta["objects"] + b.meta["surfaces"]):
        classes.add("textured")
    b.meta["material_classes"] = sorted(classes)
    b.meta["light_classes"] = sorted({l["class"] for l in b.meta["lights"]})
    b.meta["resolution"] = list(b.resolution)
