"""Light groups: render each emitter of a scene on its own, and the beauty as their sum.

``render_light_groups(scene, spp, seed)`` returns one :class:`~kpcn.io.Frame`
holding the usual layers for the whole scene plus, for each emitter ``g``,
``g.diffuse``, ``g.specular`` and ``g`` (its colour). Each group is rendered
with only that emitter (the others removed; a shape that carried an area
light keeps its geometry), with independent noise; the beauty's colour,
diffuse and specular are the sums of the groups (so the groups add up to the
beauty exactly) and its variances the sums of the groups' variances.
Albedo, normal and depth come from the first group's render.

Scenes are Mitsuba dicts, ``test:<name>`` or ``random:<seed>``.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..io import Frame
from ..scenes import copy_scene_dict
from .frame import render_frame
from .scene import SceneError, generated_scene

__all__ = ["EMITTER_TYPES", "emitter_keys", "render_light_groups"]

#: Mitsuba emitter plugins (top level, or ``area`` inside a shape)
EMITTER_TYPES = {"area", "point", "spot", "directional", "constant", "envmap", "sunsky", "projector",
                 "directionalarea"}
_SUMMED = ("color", "diffuse", "specular")


def _is_emitter(value) -> bool:
    return isinstance(value, dict) and value.get("type") in EMITTER_TYPES


def emitter_keys(scene: dict) -> list[str]:
    """Keys of the scene dict's entries that emit: emitters, and shapes that carry an area light."""
    return [k for k, v in scene.items()
            if _is_emitter(v) or (isinstance(v, dict) and any(_is_emitter(x) for x in v.values()))]


def _only(scene: dict, keep: str) -> dict:
    out = {}
    for k, v in scene.items():
        if k == keep or not isinstance(v, dict):
            out[k] = v
        elif _is_emitter(v):
            continue
        elif any(_is_emitter(x) for x in v.values()):
            out[k] = {kk: vv for kk, vv in v.items() if not _is_emitter(vv)}  # the geometry stays, dark
        else:
            out[k] = v
    return out


def render_light_groups(scene: Any, spp: int, seed: int = 0, resolution: tuple[int, int] | None = None,
                        **kw) -> Frame:
    """Render every emitter of ``scene`` on its own; the frame holds the beauty and the groups (see the module)."""
    if isinstance(scene, str) and scene.startswith(("test:", "random:")):
        name, scene = generated_scene(scene, resolution)
    if not isinstance(scene, dict):
        raise SceneError("render_light_groups takes a Mitsuba scene dict, test:<name> or random:<seed>")
    keys = emitter_keys(scene)
    if len(keys) < 1:
        raise SceneError("the scene has no emitter to make light groups of")
    layers: dict[str, np.ndarray] = {}
    first = None
    seconds = 0.0
    for i, key in enumerate(keys):
        fr = render_frame(copy_scene_dict(_only(scene, key)), spp, seed, resolution, role=1000 + i, **kw)
        seconds += fr.meta["renderTimeSeconds"]
        first = first or fr
        layers[key] = fr["color"]
        for part in ("diffuse", "specular"):
            layers[f"{key}.{part}"] = fr[part]
        for name in _SUMMED:
            layers[name] = layers.get(name, 0) + fr[name]
            layers[f"{name}Variance"] = layers.get(f"{name}Variance", 0) + fr[f"{name}Variance"]
    for name in ("albedo", "normal", "depth"):
        layers[name] = first[name]
        layers[f"{name}Variance"] = first[f"{name}Variance"]
    meta = {**first.meta, "renderTimeSeconds": seconds, "lightGroups": ",".join(keys)}
    return Frame({k: np.asarray(v, dtype=np.float32) for k, v in layers.items()}, meta)
