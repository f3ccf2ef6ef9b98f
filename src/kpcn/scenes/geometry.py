"""Small geometry helpers (numpy, y is up): rotations, frames, the 4x4
``to_world`` matrices of Mitsuba's rectangle and disk, Mitsuba transforms and
look-at, solid angles of lights, log-uniform sampling."""

from __future__ import annotations

import math

import numpy as np

from .base import _mi


def _xf(m: np.ndarray):
    return _mi().ScalarTransform4f(np.asarray(m, dtype=np.float64).tolist())


def _look_at(origin, target, up):
    mi = _mi()
    return mi.ScalarTransform4f().look_at(
        origin=[float(v) for v in origin],
        target=[float(v) for v in target],
        up=[float(v) for v in up],
    )


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


def _solid_angle_disklike(area: float, dist: float) -> float:
    a2 = area / math.pi
    return 2 * math.pi * (1 - dist / math.sqrt(dist * dist + a2))


def _solid_angle_sphere(radius: float, dist: float) -> float:
    dist = max(dist, radius * 1.05)
    return 2 * math.pi * (1 - math.sqrt(1 - (radius / dist) ** 2))
