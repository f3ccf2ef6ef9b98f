"""Loading scenes for kpcn: the Mitsuba variant, and kpcn's overrides of a scene.

A scene is parsed with Mitsuba's own parser (:mod:`mitsuba.parser`) into its
intermediate representation — the same first step as ``mi.load_file`` /
``mi.load_dict``, so ``<include>``, ``<default>`` / ``$name`` parameters,
version upgrades and relative file paths behave exactly as there — then edited
there (never as XML text, and nothing is written to disk), then instantiated:

* every integrator is removed (renders use ``kpcn_split``);
* the first sensor keeps all its parameters but gets kpcn's film — ``hdrfilm``,
  box reconstruction filter, ``rgb`` / ``float32``, the requested size — and
  an ``independent`` sampler (the sample count is given to ``mi.render``);
* scenes kpcn cannot render faithfully are refused with a :class:`SceneError`:
  no sensor, a sensor that is not an image camera, participating media.

Each override is returned as a note (and logged).
"""
from __future__ import annotations

import logging
import os
import re
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Mapping

from ..integrator import register

log = logging.getLogger("kpcn.render")

VARIANT = "llvm_ad_rgb"
#: variants kpcn renders with: the CPU default, or Mitsuba's CUDA/OptiX one on a machine with an NVIDIA GPU
VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
VARIANT_ENV = "KPCN_MITSUBA_VARIANT"
LLVM_HELP = (
    "Mitsuba's llvm_ad_rgb variant needs LLVM >= 17 (LLVM 15/16 crash on the first render). "
    "On Debian/Ubuntu install it with: sudo apt-get install -y libllvm19 "
    "(or run scripts/setup.sh); or point DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= 17."
)

#: sensors kpcn renders: image cameras whose only overridden parts (film, sampler) do not change the view
CAMERAS = ("perspective", "thinlens", "orthographic")
_CAMERAS_TEXT = "perspective, thinlens or orthographic"
_HDRFILM_DEFAULT_SIZE = (768, 576)  # Mitsuba's hdrfilm without width/height
_FILM_FORMAT = {"pixel_format": "rgb", "component_format": "float32"}
_CROP = ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height")


class RendererUnavailable(RuntimeError):
    """Mitsuba cannot render here (no suitable LLVM)."""


class SceneError(ValueError):
    """A scene that cannot be loaded, or that kpcn cannot render faithfully (one-line message naming it)."""


def chosen_variant() -> str:
    """The Mitsuba variant to render with: ``$KPCN_MITSUBA_VARIANT`` if set (one of :data:`VARIANTS`),
    else ``llvm_ad_rgb``. Both give the same estimator (same integrator and sampler), not the same bits."""
    name = os.environ.get(VARIANT_ENV, "").strip() or VARIANT
    if name not in VARIANTS:
        raise RendererUnavailable(f"{VARIANT_ENV}={name!r} is not a variant kpcn renders with: "
                                  f"use one of {', '.join(VARIANTS)}")
    return name


def ensure_variant():
    """Select the variant (:func:`chosen_variant`), check the LLVM that Dr.Jit found for the
    LLVM one, register kpcn's integrator; return ``mitsuba``."""
    import mitsuba as mi

    name = chosen_variant()
    if mi.variant() != name:
        try:
            mi.set_variant(name)
        except Exception as exc:  # drjit raises when it finds no libLLVM (or no CUDA) at all
            hint = LLVM_HELP if name.startswith("llvm") else "it needs an NVIDIA GPU and driver (with OptiX)"
            raise RendererUnavailable(f"cannot select {name}: {exc}. {hint}") from exc
    if name.startswith("llvm"):
        import drjit as dr

        version = tuple(dr.detail.llvm_version())
        if version < (17,):
            raise RendererUnavailable(f"found LLVM {'.'.join(map(str, version))}. {LLVM_HELP}")
    register()
    return mi


def _log_notes(name: str, notes: list[str]) -> None:
    for n in notes:
        log.info("%s: %s", name, n)


# ----------------------------------------------------------------------------- parser state helpers
# Nodes are addressed by index only: ``state.nodes[i]`` is a reference into a C++
# vector, which an append may move (a kept reference then crashes the process).


def _one_line(exc: Exception) -> str:
    """Mitsuba's message on one line, without its source locations (``[parser.cpp:1087]``)."""
    out = ""
    for line in str(exc).splitlines():
        line = re.sub(r"^\[[\w.]+:\d+\]\s*", "", line.strip())
        if not line:
            continue
        if line.startswith("- "):  # a list of items continues the sentence
            out += (" " if out.endswith(":") else ", ") + line[2:]
        else:
            out += ("; " if out else "") + line
    return out


def _call(label: str, fn, *args, **kwargs):
    """Run a Mitsuba parser step; its errors become one-line :class:`SceneError` naming ``label``."""
    try:
        return fn(*args, **kwargs)
    except RuntimeError as exc:
        raise SceneError(f"cannot load scene {label}: {_one_line(exc)}") from exc


def _children(mi, state, index: int) -> list[tuple[str, int]]:
    """``(property name, node index)`` of the child objects of node ``index``, in order."""
    props = state.nodes[index].props
    ref = mi.Properties.Type.ResolvedReference
    return [(k, props[k].index()) for k in props.keys() if props.type(k) == ref]


def _child_of_type(mi, state, index: int, object_type) -> tuple[str, int] | None:
    return next(((k, i) for k, i in _children(mi, state, index) if state.nodes[i].type == object_type), None)


def _add_node(mi, state, object_type, props):
    from mitsuba import parser

    node = parser.SceneNode()
    node.type = object_type
    node.props = props
    state.nodes.append(node)
    return mi.Properties.ResolvedReference(len(state.nodes) - 1)


def _describe(mi, state, index: int) -> str:
    from mitsuba import parser

    node = state.nodes[index]
    kind = str(node.type).split(".")[-1].lower()
    ident = f" '{node.props.id()}'" if node.props.id() else ""
    return f"{kind}{ident} ({node.props.plugin_name()}) at {parser.file_location(state, node)}"


def _reachable(mi, state) -> list[int]:
    seen, todo = {0}, [0]
    while todo:
        for _, i in _children(mi, state, todo.pop()):
            if i not in seen:
                seen.add(i)
                todo.append(i)
    return sorted(seen)


# ----------------------------------------------------------------------------- overrides


def _override(mi, state, resolution: tuple[int, int] | None, label: str) -> list[str]:
    """Apply kpcn's overrides to a resolved parser state; return the notes."""
    T = mi.ObjectType
    notes: list[str] = []
    if state.nodes[0].type != T.Scene:
        raise SceneError(f"{label}: not a scene but a {state.nodes[0].props.plugin_name()} object")
    top = _children(mi, state, 0)
    for key, i in top:
        if state.nodes[i].type == T.Integrator:
            notes.append(f"integrator {state.nodes[i].props.plugin_name()} -> kpcn_split")
            del state.nodes[0].props[key]
    sensors = [(k, i) for k, i in top if state.nodes[i].type == T.Sensor]
    if not sensors:
        raise SceneError(f"{label}: the scene has no sensor (a {_CAMERAS_TEXT} camera is needed)")
    for key, i in sensors[1:]:
        notes.append(f"{_describe(mi, state, i)} dropped: only the first sensor is rendered")
        del state.nodes[0].props[key]
    si = sensors[0][1]
    stype = state.nodes[si].props.plugin_name()
    if stype not in CAMERAS:
        raise SceneError(f"{label}: cannot render {_describe(mi, state, si)}: "
                         f"kpcn renders images seen by a {_CAMERAS_TEXT} sensor")

    # the film: kept size (or the requested one) and crop window; kpcn's filter and format
    film = mi.Properties("hdrfilm")
    old_film = _child_of_type(mi, state, si, T.Film)
    old = mi.Properties(state.nodes[old_film[1]].props) if old_film else mi.Properties("hdrfilm")
    if old.plugin_name() != "hdrfilm":
        notes.append(f"film {old.plugin_name()} -> hdrfilm")
    size = tuple(int(old[k]) if k in old else d for k, d in zip(("width", "height"), _HDRFILM_DEFAULT_SIZE))
    sensor = state.nodes[si].props  # a dict may hold a ready-made film or sampler object instead
    objects = [k for k in sensor.keys() if sensor.type(k) == mi.Properties.Type.Object
               and isinstance(sensor[k], (mi.Film, mi.Sampler))]
    size = next((tuple(sensor[k].size()) for k in objects if isinstance(sensor[k], mi.Film)), size)
    w, h = (int(resolution[0]), int(resolution[1])) if resolution else size
    if (w, h) != size:
        notes.append(f"film size {size[0]}x{size[1]} -> {w}x{h}")
    film["width"], film["height"] = w, h
    crop = [k for k in _CROP if k in old]
    if crop and resolution:
        notes.append("film crop window dropped (the film has the requested size)")
    elif crop:
        for k in crop:
            film[k] = old[k]
    for k, v in _FILM_FORMAT.items():
        if k in old and str(old[k]).lower() != v:
            notes.append(f"film {k} {old[k]} -> {v}")
        film[k] = v
    kept = {"width", "height", *_CROP, *_FILM_FORMAT}
    ref = mi.Properties.Type.ResolvedReference
    for k in old.keys():
        if k not in kept and old.type(k) != ref:
            notes.append(f"film {k} dropped")
    old_rf = _child_of_type(mi, state, old_film[1], T.ReconstructionFilter) if old_film else None
    rf_type = state.nodes[old_rf[1]].props.plugin_name() if old_rf else "gaussian (default)"
    if rf_type != "box":
        notes.append(f"film rfilter {rf_type} -> box")
    old_smp = _child_of_type(mi, state, si, T.Sampler)
    smp_type = state.nodes[old_smp[1]].props.plugin_name() if old_smp else "independent"
    if smp_type != "independent":
        notes.append(f"sampler {smp_type} -> independent")

    # new nodes first (appending may move the nodes), then re-point the sensor to them
    film["rfilter"] = _add_node(mi, state, T.ReconstructionFilter, mi.Properties("box"))
    film_ref = _add_node(mi, state, T.Film, film)
    sampler_ref = _add_node(mi, state, T.Sampler, mi.Properties("independent"))
    for found in (old_film, old_smp):
        if found:
            del state.nodes[si].props[found[0]]
    for k in objects:
        notes.append(f"{state.nodes[si].props[k].class_name()} object {k!r} replaced by kpcn's")
        del state.nodes[si].props[k]
    state.nodes[si].props["film"] = film_ref
    state.nodes[si].props["sampler"] = sampler_ref
    return notes


_MEDIUM_HELP = "kpcn_split renders surfaces only and would ignore it; remove the medium to render this scene"


def _refuse_media(mi, state, label: str) -> None:
    """Participating media attached to anything the scene uses: SceneError naming medium and owner."""
    for i in _reachable(mi, state)[1:]:  # (a medium declared at the top level is attached to nothing)
        for key, j in _children(mi, state, i):
            if state.nodes[j].type == mi.ObjectType.Medium:
                role = f"{key} medium" if key in ("interior", "exterior") else "medium"
                raise SceneError(f"{label}: participating {_describe(mi, state, j)} is the {role} of "
                                 f"{_describe(mi, state, i)}; {_MEDIUM_HELP}")


def _refuse_instantiated_media(scene, label: str) -> None:
    """The same check on the loaded scene (media passed as ready-made objects in a dict)."""
    def name(obj):
        return f"'{obj.id()}' ({obj.class_name()})" if obj.id() else f"({obj.class_name()})"

    owners = [(f"shape {name(s)}", role, m) for s in scene.shapes()
              for role, m in (("interior", s.interior_medium()), ("exterior", s.exterior_medium()))]
    owners += [(f"sensor {name(s)}", "", s.get_medium()) for s in scene.sensors()]
    for owner, role, medium in owners:
        if medium is not None:
            raise SceneError(f"{label}: participating medium {name(medium)} is the "
                             f"{role + ' ' if role else ''}medium of {owner}; {_MEDIUM_HELP}")


@contextmanager
def _resolving_from(mi, folder: Path | None):
    """Resolve relative file names (meshes, textures) from ``folder`` first, as ``mi.load_file`` does."""
    if folder is None:
        yield
        return
    resolver = mi.file_resolver()
    saved = list(resolver)
    resolver.prepend(str(folder))
    try:
        yield
    finally:
        resolver.clear()
        for p in saved:
            resolver.append(p)


# ----------------------------------------------------------------------------- loading


def check_resolution(resolution) -> None:
    """ValueError unless ``resolution`` is None or two integers >= 1 (width, height)."""
    if resolution is None:
        return
    res = list(resolution)
    if len(res) != 2 or any(int(v) != v or v < 1 for v in res):
        raise ValueError(f"resolution: expected width and height >= 1, got {res}")


def generated_scene(scene: str, resolution: tuple[int, int] | None = None) -> tuple[str, dict]:
    """``(name, scene dict)`` of ``"test:<name>"`` or ``"random:<seed>"`` (default size 64x64).

    Raises:
        SceneError: an unknown test scene or a seed that is not an integer >= 0.
    """
    from .. import scenes

    kind, arg = scene.split(":", 1)
    res = tuple(resolution) if resolution else (64, 64)
    if kind == "test":
        if arg not in scenes.list_test_scenes():
            raise SceneError(f"unknown test scene {scene!r}; available: "
                             f"{', '.join('test:' + n for n in scenes.list_test_scenes())}")
        return scene, scenes.test_scene(arg, resolution=res)
    try:
        seed = int(arg)
    except ValueError:
        seed = -1
    if seed < 0:
        raise SceneError(f"{scene!r}: a procedural scene is random:<seed> with an integer seed >= 0")
    return scene, scenes.random_scene(seed, resolution=res)


def load_scene(scene: Any, resolution: tuple[int, int] | None = None, params: Mapping[str, Any] | None = None):
    """Load ``scene`` with kpcn's overrides. Returns ``(mi.Scene, name, notes)``.

    Args:
        scene: an XML path (anything ``mi.load_file`` reads), a Mitsuba scene
            dict (optionally with a ``"kpcn_name"`` key naming it),
            ``"test:<name>"`` for a built-in test scene or ``"random:<seed>"``
            for a procedural one.
        resolution: ``(width, height)`` of the film; default: the scene's own
            film size (and crop window); ``test:``/``random:`` scenes: 64x64.
        params: values for the XML file's ``<default name=..>`` / ``$name``
            parameters, as the keyword arguments of ``mi.load_file``.

    The returned scene has no integrator and one sensor, with kpcn's film and
    sampler; ``notes`` lists what was overridden (also logged).

    Raises:
        SceneError: the file is missing or broken (XML syntax, a missing mesh,
            ...), the scene has no image camera, or it has participating media.
    """
    mi = ensure_variant()
    from mitsuba import parser

    cfg = parser.ParserConfig(mi.variant())  # the defaults of mi.load_file: parallel, merged meshes
    params = {str(k): str(v) for k, v in (params or {}).items()}
    check_resolution(resolution)
    name, folder = "dict", None
    if isinstance(scene, (str, os.PathLike)) and str(scene).startswith(("test:", "random:")):
        name, scene = generated_scene(str(scene), resolution)
    if isinstance(scene, dict):
        if params:
            raise SceneError(f"{name}: scene parameters ({', '.join(params)}) apply to XML files only")
        # callers may name a dict scene with a "kpcn_name" key (Mitsuba would reject it)
        name = label = scene.get("kpcn_name", name)
        state = _call(label, parser.parse_dict, cfg, {k: v for k, v in scene.items() if k != "kpcn_name"})
    else:
        path = Path(scene)
        name, label = path.stem, str(path)
        if not path.is_file():
            raise SceneError(f"scene file not found: {path}")
        state = _call(label, parser.parse_file, cfg, str(path), **params)
        folder = path.resolve().parent
    _call(label, parser.transform_upgrade, cfg, state)
    _call(label, parser.transform_resolve, cfg, state)
    notes = _override(mi, state, resolution, label)
    _refuse_media(mi, state, label)
    if cfg.merge_equivalent:
        _call(label, parser.transform_merge_equivalent, cfg, state)
    if cfg.merge_meshes:
        _call(label, parser.transform_merge_meshes, cfg, state)
    with _resolving_from(mi, folder):
        mi_scene = _call(label, parser.instantiate, cfg, state)
    _refuse_instantiated_media(mi_scene, label)
    _log_notes(name, notes)
    return mi_scene, name, notes
