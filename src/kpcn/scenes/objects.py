"""Random objects placed on a floor (spheres, cubes, capped cylinders, disks,
rectangles; stacked, floating or overlapping now and then), clutter, and the
helpers that frame the camera around them."""

from __future__ import annotations

import math

import numpy as np

from .builder import _Builder, _Obj
from .geometry import _disk_matrix, _frame, _loguniform, _random_rotation3, _rect_matrix, _rot3, _unit, _xf
from .materials import _material, _pick_class


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
