"""Rendering and caching: scene names and fingerprints, :func:`render_scene`, :class:`SceneRenders`."""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..io import Frame, read_exr, write_exr
from ..render.cycles import cycles_seed  # Cycles' seed for a report render: per seed and role
from ..render.cycles_scene import generated_variant, is_generated
from ..render.record import update_hash
from ..render.refine import reference_floor, refined_spp
from .config import CONVERGED_ROLE, INPUT_ROLE_BASE, WARMUP_ROLE, ReportConfig, log

_NAMED = ("test:", "random:", "file:")  #: scene names (not paths): test scenes, procedural seeds, shipped XML files
CYCLES = "cycles:"  #: Blender Cycles scenes: ``cycles:generated`` (kpcn's generated scene), ``cycles:generated:<N>``
#: (its variant N) or ``cycles:<file.blend>``


def is_cycles(scene: Any) -> bool:
    return isinstance(scene, (str, os.PathLike)) and os.fspath(scene).startswith(CYCLES)


def cycles_blend(scene: Any) -> Path | None:
    """The ``.blend`` of a ``cycles:`` scene (None: the generated scene)."""
    return None if is_generated(scene) else Path(os.fspath(scene)[len(CYCLES):])


def scene_slug(scene: Any) -> str:
    """A folder name for a scene: ``test:glossy`` -> ``test_glossy``, ``a/b.xml`` -> ``b_<hash>``."""
    if isinstance(scene, dict):
        return str(scene.get("kpcn_name", "dict")).replace(":", "_").replace("/", "_")
    s = os.fspath(scene)
    if s.startswith(_NAMED) or is_generated(s):
        return s.replace(":", "_")
    if s.startswith(CYCLES):
        p = cycles_blend(s).resolve()
        return f"cycles_{p.stem}_{hashlib.sha1(str(p).encode()).hexdigest()[:8]}"
    p = Path(s).resolve()
    return f"{p.stem}_{hashlib.sha1(str(p).encode()).hexdigest()[:8]}"


def scene_label(scene: Any) -> str:
    """A short human-readable name for tables and plots."""
    if isinstance(scene, dict):
        return str(scene.get("kpcn_name", "dict"))
    s = os.fspath(scene)
    if s.startswith(CYCLES) and cycles_blend(s) is not None:
        return f"cycles:{cycles_blend(s).stem}"
    return s if s.startswith(_NAMED + (CYCLES,)) else Path(s).stem


@dataclass
class SceneRenders:
    """The renders of one scene: ``inputs[spp]``, ``reference`` and ``converged`` (Frames, layers ``(H, W, C)``)."""

    scene: Any
    label: str
    inputs: dict[int, Frame]
    reference: Frame
    rendered: list[str]  #: paths rendered in this run (the others came from the cache)
    converged: Frame | None = None  #: the high-spp input (``cfg.converged_spp``, own seed), or None


def _cached(path: Path, spp: int, resolution: tuple[int, int]) -> Frame | None:
    """The frame at ``path`` if it exists and matches ``spp`` and ``(W, H)``; else None."""
    if not path.exists():
        return None
    try:
        fr = read_exr(path, require=("color", "albedo", "normal"))
    except Exception as exc:  # a damaged cache file is rendered again
        log.warning("%s: unreadable cache (%s), rendering again", path, exc)
        return None
    w, h = resolution
    if fr.spp != spp or fr.shape != (h, w) or "renderTimeSeconds" not in fr.meta:
        log.warning("%s: cached render does not match (spp %s, size %s), rendering again", path, fr.spp, fr.shape)
        return None
    return fr


def scene_source(scene: Any, resolution: tuple[int, int]) -> tuple[Any, str]:
    """What to render and its fingerprint: ``(dict or path, 12 hex digits)``.

    ``test:``/``random:`` names are built into their scene dicts here, so the
    fingerprint covers the generated content (a change to :mod:`kpcn.scenes`
    invalidates the cache); ``file:<name>`` is the shipped XML file of that name
    (:func:`kpcn.scenes.scene_file`). For an XML file the fingerprint is the
    file's bytes (not the meshes and textures it references: use ``--rerender``
    after changing those).
    """
    h = hashlib.sha1(repr(tuple(resolution)).encode())
    if is_cycles(scene):  # the .blend's bytes, or the generated scene's code
        blend = cycles_blend(scene)
        if blend is None:
            from ..render import cycles_scene

            h.update(Path(cycles_scene.__file__).read_bytes())
            h.update(repr(generated_variant(scene)).encode())
        else:
            h.update(blend.read_bytes())
        return blend, h.hexdigest()[:12]
    if isinstance(scene, (str, os.PathLike)) and str(scene).startswith(("test:", "random:")):
        from .. import scenes

        kind, arg = str(scene).split(":", 1)
        d = scenes.test_scene(arg, resolution=resolution) if kind == "test" else scenes.random_scene(int(arg), resolution=resolution)
        update_hash(h, d)
        return {**d, "kpcn_name": str(scene)}, h.hexdigest()[:12]
    if isinstance(scene, dict):
        update_hash(h, scene)
        return scene, h.hexdigest()[:12]
    if str(scene).startswith("file:"):
        from ..scenes import scene_file

        scene = scene_file(str(scene))
    h.update(Path(scene).read_bytes())
    return scene, h.hexdigest()[:12]


def render_scene(cfg: ReportConfig, scene: Any, progress: Callable[[str], None] = log.info) -> SceneRenders:
    """Render (or load from the cache) the input ladder, the converged input and the reference of one scene.

    Cache: ``<out>/<name>/renders/<scene>/<W>x<H>-<fingerprint>/input_<spp>spp_seed<seed>.exr``,
    ``converged_<spp>spp_seed<seed>.exr`` and ``reference_<spp>spp_seed<seed>.exr``; a cached
    file is used when its header's spp and its size match; one rendered before the current albedo or normal
    revision gets those layers rendered again (:mod:`kpcn.render.albedo`). Inputs, the converged input and the
    reference have independent noise (render roles ``2 + spp``, :data:`CONVERGED_ROLE`, 1).
    """
    from ..render import load_scene, render_frame
    from ..render.albedo import outdated_first_hit, update_first_hit

    w, h = cfg.resolution
    source, fingerprint = scene_source(scene, tuple(cfg.resolution))
    folder = cfg.folder / "renders" / scene_slug(scene) / f"{w}x{h}-{fingerprint}"
    jobs = [(s, folder / f"input_{s}spp_seed{cfg.seed}.exr", INPUT_ROLE_BASE + s) for s in sorted(set(cfg.spp))]
    n_inputs = len(jobs)
    if cfg.converged_spp:
        jobs.append((cfg.converged_spp, folder / f"converged_{cfg.converged_spp}spp_seed{cfg.seed}.exr", CONVERGED_ROLE))
    jobs.append((cfg.ref_spp, folder / f"reference_{cfg.ref_spp}spp_seed{cfg.seed}.exr", 1))
    frames: dict[Path, Frame] = {}
    rendered: list[str] = []
    loaded = for_albedo = None

    def scene_loaded():
        nonlocal loaded
        if loaded is None:
            loaded = load_scene(source, cfg.resolution)
            # untimed warm-up: the first render of a scene compiles its kernels (~2 s)
            render_frame(source, 2, cfg.seed, cfg.resolution, role=WARMUP_ROLE, loaded=loaded, max_depth=cfg.max_depth)
        return loaded
    for spp, path, role in jobs:
        fr = None if cfg.rerender else _cached(path, spp, cfg.resolution)
        outdated = [] if fr is None or is_cycles(scene) else outdated_first_hit(fr)
        if outdated:
            # rendered before the albedo's or the normal's revision, or the denoising guides: those layers alone
            # are rendered (a scene of its own: `loaded` set here would skip the timed renders' warm-up below)
            for_albedo = for_albedo or load_scene(source, cfg.resolution)
            fr = update_first_hit(path, source, spp, cfg.seed, role=role, which=outdated, resolution=cfg.resolution,
                                  loaded=for_albedo)
            words = [w.replace("denoising", "denoising guides") for w in outdated]
            what = " and ".join([", ".join(words[:-1]), words[-1]] if len(words) > 1 else words)
            progress(f"updated the {what} of {scene_label(scene)} {spp} spp (latest revision)")
        if fr is None and is_cycles(scene):  # Blender: one child process per render; Cycles times itself
            from ..render.cycles import render_cycles

            done = render_cycles(source, path, spp, seed=cycles_seed(cfg.seed, role), resolution=tuple(cfg.resolution),
                                 variant=None if source is not None else generated_variant(scene))
            fr = read_exr(path, require=("color", "albedo", "normal"))
            fr.meta.setdefault("renderTimeSeconds", done.seconds)
            fr.path = str(path)
            rendered.append(str(path))
            progress(f"rendered {scene_label(scene)} {spp} spp with Cycles in {done.seconds:.2f} s")
        if fr is None:
            fr = render_frame(source, spp, cfg.seed, cfg.resolution, role=role, loaded=scene_loaded(),
                              max_depth=cfg.max_depth)
            fr.meta["scene"] = scene_label(scene)
            write_exr(path, fr.layers, fr.meta)
            fr.path = str(path)
            rendered.append(str(path))
            progress(f"rendered {scene_label(scene)} {spp} spp in {fr.meta['renderTimeSeconds']:.2f} s")
        frames[path] = fr
    inputs = {s: frames[p] for s, p, _ in jobs[:n_inputs]}
    converged = frames[jobs[n_inputs][1]] if cfg.converged_spp else None
    reference = frames[jobs[-1][1]]
    if cfg.ref_floor_target is not None and not is_cycles(scene):
        reference = _refined_reference(cfg, scene, source, folder, reference, scene_loaded, rendered, progress)
    return SceneRenders(scene, scene_label(scene), inputs, reference, rendered, converged)


def _refined_reference(cfg: ReportConfig, scene: Any, source: Any, folder: Path, ref: Frame,
                       scene_loaded: Callable, rendered: list[str], progress: Callable[[str], None]) -> Frame:
    """``ref`` with more samples while its floor is above ``cfg.ref_floor_target`` (:func:`refined_spp`).

    Each refined reference is cached as ``reference_<spp>spp_seed<seed>.exr`` beside the first; a larger one is
    built on the largest cached one below it (its samples are kept: the added passes follow its own), so a run
    killed while refining loses at most the refinement under way.
    """
    from ..render import extend_frame
    from ..render.albedo import outdated_first_hit

    while True:
        floor = reference_floor(ref)
        if floor is None:
            return ref
        want = refined_spp(ref.spp, floor, cfg.ref_floor_target, cfg.ref_spp_max)
        if want == ref.spp:
            return ref
        base, spp = ref, ref.spp * 2
        while spp <= want:  # the largest cached refinement on the way, each built on the ones before it
            path = folder / f"reference_{spp}spp_seed{cfg.seed}.exr"
            fr = None if cfg.rerender else _cached(path, spp, cfg.resolution)
            if fr is not None and not outdated_first_hit(fr):
                base = fr
            spp *= 2
        if base.spp < want:
            path = folder / f"reference_{want}spp_seed{cfg.seed}.exr"
            before = base.spp
            base = extend_frame(base, source, want, cfg.seed, role=1, resolution=cfg.resolution,
                                loaded=scene_loaded(), max_depth=cfg.max_depth)
            base.meta["scene"] = scene_label(scene)
            write_exr(path, base.layers, base.meta)
            base.path = str(path)
            rendered.append(str(path))
            progress(f"refined the reference of {scene_label(scene)} from {before} to {want} spp (its noise: relMSE "
                     f"{floor:.5f}, target {cfg.ref_floor_target})")
        ref = base
