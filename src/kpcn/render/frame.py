"""Rendering one frame: ``kpcn_split`` passes combined into a :class:`~kpcn.io.Frame`."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..integrator import ALBEDO_REVISION, MOMENT2, NORMAL_REVISION, aov_layout
from ..io import Frame, write_exr
from .scene import ensure_variant, load_scene


def pass_seed(seed: int, role: int, index: int) -> int:
    """Seed for pass ``index`` of a render; ``role`` keeps inputs and references independent."""
    return int(np.random.SeedSequence([int(seed), int(role), int(index)]).generate_state(1)[0] & 0x7FFFFFFF)


@dataclass
class RenderStats:
    seconds: float
    spp: int
    passes: int


def render_frame(
    scene: Any,
    spp: int,
    seed: int = 0,
    resolution: tuple[int, int] | None = None,
    *,
    max_depth: int = 8,
    pass_spp: int = 256,
    role: int = 0,
    loaded=None,
    params: Mapping[str, Any] | None = None,
    albedo_only: bool = False,
) -> Frame:
    """Render ``scene`` at ``spp`` samples per pixel into a :class:`~kpcn.io.Frame`.

    Args:
        scene: XML path, Mitsuba dict, ``"test:<name>"`` or ``"random:<seed>"``.
        spp: samples per pixel (>= 2, needed for variances).
        seed: base seed; the same seed gives the same image.
        resolution: ``(width, height)``; default: the scene's own film size.
        max_depth: longest path (Mitsuba's convention: 1 = emitters seen directly).
        pass_spp: samples per pass; larger renders are split into passes.
        role: 0 for noisy inputs, 1 for references — different roles never
            share seeds, so inputs and references have independent noise.
        loaded: a ``(mi.Scene, name, notes)`` from :func:`load_scene` to reuse.
        params: the XML file's ``$name`` parameters (see :func:`load_scene`).
        albedo_only: trace only the first hit: ``albedo``, ``normal`` and ``depth`` (and their
            variances) as a full render with the same arguments writes them, the radiance layers 0
            (:mod:`kpcn.render.albedo`).

    Returns:
        Frame with ``color``, ``diffuse``, ``specular``, ``albedo``, ``normal``,
        ``depth`` and ``<layer>Variance`` (variance of the pixel mean), and meta
        ``spp``, ``renderTimeSeconds`` (wall time of the passes), ``seed``, ``scene`` and
        ``albedoRevision`` and ``normalRevision`` (:data:`kpcn.integrator.ALBEDO_REVISION`,
        :data:`kpcn.integrator.NORMAL_REVISION`).
    """
    if spp < 2:
        raise ValueError(f"spp must be >= 2 to estimate variances, got {spp}")
    mi = ensure_variant()
    mi_scene, name, notes = loaded or load_scene(scene, resolution, params)
    integrator = mi.load_dict({"type": "kpcn_split", "max_depth": int(max_depth), "albedo_only": bool(albedo_only)})

    layout = [("color", 3)] + aov_layout()
    n_ch = sum(c for _, c in layout)
    passes = []
    left = spp
    while left > 0:
        passes.append(min(pass_spp, left))
        left -= passes[-1]
    acc = None
    t0 = time.perf_counter()
    for i, n in enumerate(passes):
        img = mi.render(mi_scene, integrator=integrator, spp=n, seed=pass_seed(seed, role, i))
        arr = np.array(img, dtype=np.float64)
        if arr.shape[-1] != n_ch:
            raise RuntimeError(f"film returned {arr.shape[-1]} channels, expected {n_ch}")
        acc = arr * n if acc is None else acc + arr * n
    seconds = time.perf_counter() - t0
    acc /= spp

    raw: dict[str, np.ndarray] = {}
    c0 = 0
    for layer, c in layout:
        raw[layer] = acc[..., c0 : c0 + c]
        c0 += c
    layers = {layer: raw[layer].astype(np.float32) for layer, _ in layout if not layer.endswith("_m2")}
    for layer, _ in MOMENT2:
        var = (raw[f"{layer}_m2"] - raw[layer] ** 2) / (spp - 1)
        layers[f"{layer}Variance"] = np.maximum(var, 0.0).astype(np.float32)
    meta = {"spp": int(spp), "renderTimeSeconds": float(seconds), "seed": int(seed), "scene": str(name),
            "albedoRevision": ALBEDO_REVISION, "normalRevision": NORMAL_REVISION}
    return Frame(layers, meta)


def render_to_exr(scene: Any, out: str | os.PathLike, spp: int, seed: int = 0, *,
                  meta: Mapping[str, Any] | None = None, **kw) -> Frame:
    """Render and write one EXR (atomically). Returns the frame.

    ``meta``: extra header attributes (int, float or str), added to ``frame.meta``.
    """
    frame = render_frame(scene, spp, seed, **kw)
    frame.meta.update(meta or {})
    write_exr(out, frame.layers, frame.meta)
    frame.path = os.fspath(out)
    return frame
