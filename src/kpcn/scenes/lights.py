"""Lights: how bright a light must be (radiometry against a reference
surface) and the placement of outdoor area lights, point/spot lights, room
lamps and the sun of a sky map."""

from __future__ import annotations

import math

import numpy as np

from .builder import _Builder
from .colours import _random_light_tint
from .geometry import _loguniform, _rot, _rot3, _solid_angle_disklike, _solid_angle_sphere, _xf

LIGHT_CLASSES = ("area", "environment", "delta")
_RHO_REF = 0.5  # albedo of the reference surface used to set light intensities


def _area_radiance(target_lo: float, omega: float, cos_l: float = 1.0) -> float:
    """Radiance an emitter needs so a reference surface facing it has radiance
    target_lo: Lo = rho * L * omega * cos / pi."""
    return target_lo * math.pi / (_RHO_REF * max(omega * max(cos_l, 0.1), 1e-6))


def _point_intensity(target_lo: float, dist: float) -> float:
    return target_lo * math.pi * dist * dist / _RHO_REF


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
