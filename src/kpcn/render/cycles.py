"""Rendering with Blender Cycles into multilayer EXRs that kpcn reads (:func:`render_cycles`).

Python API::

    from kpcn.render.cycles import render_cycles
    render_cycles("scene.blend", "frame.exr", spp=16, seed=1)                # the .blend's scene and camera
    render_cycles(None, "frame.exr", spp=16, seed=1, resolution=(64, 64))    # a small generated scene

Command line::

    python -m kpcn.render cycles scene.blend --spp 16 --out frame.exr [--seed N] [--resolution W H]
    python -m kpcn.render cycles --generated --spp 16 --out frame.exr

Blender's Python module ``bpy`` is an optional dependency (``pip install
'kpcn[blender]'``: bpy 5.0.1, CPython 3.11, Linux x86-64); kpcn imports
without it, and a missing ``bpy`` is a :class:`BlenderUnavailable` error that
says how to install it.

Each render runs in a child Python process that imports ``bpy``: Blender's
state is process-wide (one open file, one set of add-ons), and a render that
crashes Blender ends the child, not the caller. The child

* opens the ``.blend`` (or, with ``None``, builds a scene: a textured diffuse
  plane, a glossy metal sphere, a glass sphere, an area light, a uniform world
  light and a camera);
* renders with Cycles on the CPU: ``spp`` samples exactly (adaptive sampling
  off unless asked for, then with the Debug Sample Count pass; view-layer
  sample overrides ignored, no time limit), no denoiser, fixed
  ``scene.cycles.seed``, a 1-pixel box pixel filter (wider filters correlate
  neighbouring pixels), no sample clamping, compositing and sequencer off (the
  file holds the render passes, not a composite);
* switches on, on every rendered view layer, the passes :mod:`kpcn.io.cycles`
  reads: Combined; Diffuse, Glossy and Transmission Direct/Indirect/Color;
  Volume Direct/Indirect; Emission; Environment; Normal; Z; Denoising Data;
* writes them all as one multilayer EXR (``media_type = 'MULTI_LAYER_IMAGE'``,
  ``file_format = 'OPEN_EXR_MULTILAYER'``, float32, ZIP) with
  ``bpy.ops.render.render(write_still=True)`` into a private temporary folder,
  adds kpcn's header attributes (``spp``, ``seed``, ``scene``,
  ``renderTimeSeconds``) to the first part, and writes the result to ``out``
  atomically (:func:`kpcn.io.atomic_write`).

The settings it changed in a ``.blend`` are logged (logger ``kpcn.render``).
"""
from __future__ import annotations

import importlib.util
import json
import logging
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .cycles_scene import GENERATED, GENERATED_RESOLUTION, build_scene, scene_params
from .scene import RendererUnavailable, SceneError

__all__ = ["BLENDER_HELP", "BlenderUnavailable", "CyclesRender", "blender_available", "render_cycles",
           "GENERATED_RESOLUTION", "PASSES"]

log = logging.getLogger("kpcn.render")

BLENDER_HELP = "pip install 'kpcn[blender]' (Blender's Python module bpy 5.0.1, for CPython 3.11)"


#: view-layer properties switched on for every rendered view layer (``cycles.`` ones live in ``view_layer.cycles``)
PASSES = (
    "use_pass_combined", "use_pass_z", "use_pass_normal",
    "use_pass_diffuse_direct", "use_pass_diffuse_indirect", "use_pass_diffuse_color",
    "use_pass_glossy_direct", "use_pass_glossy_indirect", "use_pass_glossy_color",
    "use_pass_transmission_direct", "use_pass_transmission_indirect", "use_pass_transmission_color",
    "use_pass_emit", "use_pass_environment",
    "cycles.use_pass_volume_direct", "cycles.use_pass_volume_indirect", "cycles.denoising_store_passes",
)

#: renders started again after the Blender child process crashed (killed by one of :data:`CRASH_SIGNALS`)
SIGNAL_RETRIES = 1
#: the signals of a crash inside the child (an abort on a corrupted heap, a bad memory access): worth a second try,
#: unlike a kill from outside (the out-of-memory killer's SIGKILL would only come again)
CRASH_SIGNALS = frozenset(int(getattr(signal, n)) for n in ("SIGABRT", "SIGSEGV", "SIGBUS") if hasattr(signal, n))

_RESULT_TAG = "KPCN_CYCLES_RESULT "
_ERROR_TAG = "KPCN_CYCLES_ERROR "


class BlenderUnavailable(RendererUnavailable):
    """Blender's Python module (``bpy``) cannot be imported here."""


@dataclass(frozen=True)
class CyclesRender:
    """What :func:`render_cycles` wrote."""

    path: Path
    spp: int
    seed: int
    resolution: tuple[int, int]  # (width, height) in pixels
    seconds: float  # Cycles' render time (not counting Blender's start)
    passes: tuple[str, ...]  # the layers of the file (``<view layer>.<pass>``)
    notes: tuple[str, ...]  # settings of the .blend that were changed


def blender_available() -> bool:
    """Whether ``bpy`` is installed (it is imported only by the render's child process)."""
    try:
        return importlib.util.find_spec("bpy") is not None
    except (ImportError, ValueError):
        return False


def _check(blend, out_path, spp, seed, resolution) -> tuple[Path | None, Path, tuple[int, int] | None]:
    if isinstance(spp, bool) or not isinstance(spp, int) or not 1 <= spp <= 16_777_216:
        raise ValueError(f"render_cycles: spp must be an integer in [1, 16777216], got {spp!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= 2**31 - 1:
        raise ValueError(f"render_cycles: seed must be an integer in [0, 2147483647] (scene.cycles.seed), got {seed!r}")
    if resolution is not None:
        try:
            w, h = (int(v) for v in resolution)
        except (TypeError, ValueError):
            raise ValueError(f"render_cycles: resolution must be (width, height), got {resolution!r}") from None
        if (w, h) != tuple(resolution) or min(w, h) < 1:
            raise ValueError(f"render_cycles: resolution must be two integers >= 1, got {resolution!r}")
        resolution = (w, h)
    out = Path(out_path)
    if out.is_dir():
        raise ValueError(f"render_cycles: {out} is a folder; give the EXR file to write")
    if blend is None:
        return None, out, resolution
    blend = Path(blend)
    if not blend.is_file():
        raise SceneError(f"{blend}: no such .blend file")
    if out.resolve() == blend.resolve():
        raise ValueError(f"render_cycles: the output {out} is the .blend file itself")
    return blend, out, resolution


def cycles_seed(seed: int, role: int) -> int:
    """``scene.cycles.seed`` for render ``role`` of a frame seeded ``seed``: independent noise per (seed, role)."""
    return (seed * 100_003 + role) % (2**31 - 1)


def render_cycles(blend_path_or_none, out_path, spp: int, seed: int = 0, resolution=None, *,
                  timeout: float | None = None, variant: int | None = None,
                  adaptive_threshold: float | None = None) -> CyclesRender:
    """Render a ``.blend`` (or, with ``None``, a generated scene) with Cycles into a multilayer EXR.

    Args:
        blend_path_or_none: the ``.blend`` file (its active scene and camera), or
            ``None`` for kpcn's generated scene (:data:`GENERATED_RESOLUTION` unless
            ``resolution`` is given).
        out_path: the EXR to write (atomically; missing folders are created).
        spp: samples per pixel (exactly; adaptive sampling is switched off), or with ``adaptive_threshold`` the
            most a pixel gets.
        seed: ``scene.cycles.seed``.
        resolution: ``(width, height)``; ``None`` keeps the ``.blend``'s size.
        timeout: seconds after which the render is stopped (``None``: no limit).
        variant: for the generated scene, a seed >= 0 that draws its materials, layout, light and view
            (:func:`kpcn.render.cycles_scene.scene_params`); ``None``: the fixed layout.
        adaptive_threshold: Cycles' adaptive sampling with this noise threshold (``cycles.adaptive_threshold``,
            minimum samples Cycles' automatic): a pixel stops taking samples once its noise is below it, and the
            file gets the Debug Sample Count pass, which :func:`kpcn.io.read_exr` reads as the ``sampleCount``
            layer. ``None``: every pixel gets ``spp``.

    Returns:
        A :class:`CyclesRender` (path, size, render seconds, the file's layers,
        the ``.blend`` settings that were changed).

    Raises:
        BlenderUnavailable: ``bpy`` is not installed (``pip install 'kpcn[blender]'``).
        SceneError: the ``.blend`` cannot be opened or rendered (no camera, ...).
        ValueError: a bad argument.
        RuntimeError: Blender failed otherwise (the message ends with its last output). A child process that
            crashed (:data:`CRASH_SIGNALS`: an abort inside Cycles) is started again :data:`SIGNAL_RETRIES` times
            first, within ``timeout``; an exit status, or a kill from outside, is not retried.
    """
    blend, out, resolution = _check(blend_path_or_none, out_path, spp, seed, resolution)
    if adaptive_threshold is not None and not 0 < float(adaptive_threshold) < 1:
        raise ValueError(f"render_cycles: adaptive_threshold must be in (0, 1), got {adaptive_threshold!r}")
    if variant is not None:
        if blend is not None:
            raise ValueError("render_cycles: variant is for the generated scene, not a .blend file")
        scene_params(variant)  # ValueError for a bad variant, before Blender starts
    if not blender_available():
        raise BlenderUnavailable(f"Blender's Python module bpy is not installed: {BLENDER_HELP}")
    label = str(blend) if blend else GENERATED + (f":{variant}" if variant is not None else "")
    job = {"blend": str(blend.resolve()) if blend else None, "scene": label, "variant": variant,
           "out": str(out.resolve()), "spp": spp, "seed": seed, "resolution": list(resolution) if resolution else None,
           "adaptive_threshold": None if adaptive_threshold is None else float(adaptive_threshold)}
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[2])  # the folder that holds the kpcn package
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    code = "import sys; from kpcn.render.cycles import _child; sys.exit(_child(sys.argv[1]))"
    deadline = None if timeout is None else time.monotonic() + timeout
    for attempt in range(1 + SIGNAL_RETRIES):
        try:
            left = None if deadline is None else max(deadline - time.monotonic(), 0.001)
            proc = subprocess.run([sys.executable, "-c", code, json.dumps(job)], env=env, capture_output=True,
                                  text=True, errors="replace", timeout=left)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"Blender Cycles render of {job['scene']} stopped after {timeout} s") from None
        if -proc.returncode not in CRASH_SIGNALS or attempt == SIGNAL_RETRIES:
            break
        # killed by a signal (Cycles has aborted on a corrupted heap once in a fresh child: a fault of that
        # process, not of the scene): the same job once more, in a new process, up to the same deadline
        log.warning("%s: the Blender child process died of signal %d; rendering again", job["scene"],
                    -proc.returncode)
    lines = (proc.stdout or "").splitlines() + (proc.stderr or "").splitlines()
    result = next((ln[len(_RESULT_TAG):] for ln in lines if ln.startswith(_RESULT_TAG)), None)
    if proc.returncode == 0 and result is not None:
        info = json.loads(result)
        for note in info["notes"]:
            log.info("%s: %s", job["scene"], note)
        return CyclesRender(Path(out_path), spp, seed, tuple(info["resolution"]), float(info["seconds"]),
                            tuple(info["passes"]), tuple(info["notes"]))
    error = next((ln[len(_ERROR_TAG):] for ln in lines if ln.startswith(_ERROR_TAG)), None)
    if error is not None:
        kind, _, msg = error.partition(" ")
        if kind == "scene":
            raise SceneError(msg)
        if kind == "bpy":
            raise BlenderUnavailable(f"Blender's Python module bpy cannot be imported ({msg}): {BLENDER_HELP}")
        raise RuntimeError(msg)
    tail = " | ".join(ln.strip() for ln in lines[-5:] if ln.strip())
    how = (f"exit status {proc.returncode}" if proc.returncode >= 0 else
           f"killed by signal {-proc.returncode}" + (f", {1 + SIGNAL_RETRIES} times" if -proc.returncode in CRASH_SIGNALS
                                                      else ""))
    raise RuntimeError(f"Blender Cycles render of {job['scene']} failed ({how}): {tail}")


# ----------------------------------------------------------------------------- the child process (imports bpy)


class _SceneProblem(Exception):
    pass


def _child(job_json: str) -> int:
    """Entry point of the render's child process: render ``job``, print one result or error line."""
    job = json.loads(job_json)
    try:
        import bpy
    except Exception as exc:  # ImportError, or Blender's libraries failing to load
        print(_ERROR_TAG + "bpy " + " ".join(str(exc).split()), flush=True)
        return 3
    try:
        info = _render(bpy, job)
    except _SceneProblem as exc:
        print(_ERROR_TAG + "scene " + " ".join(str(exc).split()), flush=True)
        return 2
    except Exception as exc:
        print(_ERROR_TAG + "other " + f"Blender Cycles render of {job['scene']} failed: {type(exc).__name__}: "
              + " ".join(str(exc).split()), flush=True)
        return 1
    print(_RESULT_TAG + json.dumps(info), flush=True)
    return 0


def _set(obj, attr: str, value, notes: list[str] | None, label: str) -> None:
    """``obj.attr = value``, with a note when a ``.blend`` had another value."""
    old = getattr(obj, attr)
    if isinstance(old, float) and isinstance(value, (int, float)):
        same = math.isclose(old, value, rel_tol=1e-6, abs_tol=1e-9)
    else:
        same = old == value
    if not same:
        setattr(obj, attr, value)
        if notes is not None:
            notes.append(f"{label}: {old!r} -> {value!r}")


def _render(bpy, job: dict) -> dict:
    import tempfile

    notes: list[str] | None = []
    if job["blend"]:
        try:
            bpy.ops.wm.open_mainfile(filepath=job["blend"], load_ui=False)
        except RuntimeError as exc:
            raise _SceneProblem(f"{job['scene']}: Blender cannot open it: {exc}") from None
        scene = bpy.context.scene
        if scene is None:
            raise _SceneProblem(f"{job['scene']}: the file has no scene")
        if scene.camera is None:
            raise _SceneProblem(f"{job['scene']}: scene {scene.name!r} has no active camera "
                                "(set one in Scene Properties → Camera)")
        if not any(vl.use for vl in scene.view_layers):
            raise _SceneProblem(f"{job['scene']}: scene {scene.name!r} renders no view layer "
                                "(every view layer has 'Use for Rendering' off)")
    else:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        scene = bpy.context.scene
        build_scene(bpy, scene, job.get("variant"))
        notes = None  # nothing to report on kpcn's own scene
    _configure(scene, job, notes)
    view = [vl for vl in scene.view_layers if vl.use]
    for vl in view:
        for prop in PASSES + (("cycles.pass_debug_sample_count",) if job.get("adaptive_threshold") else ()):
            owner, attr = (vl.cycles, prop[len("cycles."):]) if prop.startswith("cycles.") else (vl, prop)
            setattr(owner, attr, True)

    with tempfile.TemporaryDirectory(prefix="kpcn-cycles-") as tmp:
        raw = os.path.join(tmp, "render.exr")  # no '#' or '//' for Blender to expand
        scene.render.filepath = raw
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True, scene=scene.name)
        seconds = time.perf_counter() - t0
        if not os.path.exists(raw):
            raise RuntimeError("Blender rendered but wrote no file")
        passes, size = _finish(raw, job, seconds)
    return {"seconds": seconds, "passes": passes, "resolution": size, "notes": notes or []}


def _configure(scene, job: dict, notes: list[str] | None) -> None:
    r = scene.render
    _set(r, "engine", "CYCLES", notes, "render engine")
    c = scene.cycles
    _set(c, "device", "CPU", notes, "cycles.device")
    _set(c, "samples", int(job["spp"]), notes, "cycles.samples")
    adaptive = job.get("adaptive_threshold")
    _set(c, "use_adaptive_sampling", bool(adaptive), notes, "cycles.use_adaptive_sampling")
    if adaptive:
        _set(c, "adaptive_threshold", float(adaptive), notes, "cycles.adaptive_threshold")
        _set(c, "adaptive_min_samples", 0, notes, "cycles.adaptive_min_samples")
    _set(c, "use_layer_samples", "IGNORE", notes, "cycles.use_layer_samples")
    _set(c, "time_limit", 0.0, notes, "cycles.time_limit")
    if hasattr(c, "use_sample_subset"):
        _set(c, "use_sample_subset", False, notes, "cycles.use_sample_subset")
    _set(c, "use_denoising", False, notes, "cycles.use_denoising")
    _set(c, "seed", int(job["seed"]), None, "cycles.seed")
    _set(c, "use_animated_seed", False, notes, "cycles.use_animated_seed")
    _set(c, "pixel_filter_type", "BOX", notes, "cycles.pixel_filter_type")
    _set(c, "filter_width", 1.0, notes, "cycles.filter_width")
    _set(c, "sample_clamp_direct", 0.0, notes, "cycles.sample_clamp_direct")
    _set(c, "sample_clamp_indirect", 0.0, notes, "cycles.sample_clamp_indirect")
    _set(r, "use_compositing", False, notes, "render.use_compositing")
    _set(r, "use_sequencer", False, notes, "render.use_sequencer")
    _set(r, "use_border", False, notes, "render.use_border")
    if job["resolution"]:
        w, h = job["resolution"]
        _set(r, "resolution_x", int(w), None, "")
        _set(r, "resolution_y", int(h), None, "")
        _set(r, "resolution_percentage", 100, None, "")
    r.use_file_extension = False
    s = r.image_settings
    s.media_type = "MULTI_LAYER_IMAGE"  # Blender 5: before file_format, which it restricts
    s.file_format = "OPEN_EXR_MULTILAYER"
    s.color_depth = "32"
    s.exr_codec = "ZIP"


def _finish(raw: str, job: dict, seconds: float) -> tuple[list[str], list[int]]:
    """Copy Blender's file to ``job["out"]`` atomically with kpcn's header attributes; its layers and size."""
    import OpenEXR

    from ..io import atomic_write

    with OpenEXR.File(raw, separate_channels=True) as f:
        parts = []
        for i, p in enumerate(f.parts):
            header = dict(p.header)
            if i == 0:
                header.update(spp=int(job["spp"]), seed=int(job["seed"]), scene=str(job["scene"]),
                              renderTimeSeconds=float(seconds))
            parts.append(OpenEXR.Part(header, dict(p.channels), name=p.name()))
        layers = sorted({n.rsplit(".", 1)[0] for p in f.parts for n in p.channels})
        size = [int(f.parts[0].width()), int(f.parts[0].height())]
        atomic_write(job["out"], lambda tmp: OpenEXR.File(parts).write(tmp))
    return layers, size
