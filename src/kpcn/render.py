"""Render Mitsuba 3 scenes into kpcn's multi-layer EXR contract.

Python API::

    from kpcn.render import render_frame
    frame = render_frame("scene.xml", spp=8, seed=1, resolution=(256, 256))
    frame = render_frame("test:glossy", spp=1024, seed=7)     # a built-in test scene
    frame = render_frame("random:42", spp=4)                   # a procedural scene

Command line::

    python -m kpcn.render frame scene.xml --spp 8 --out noisy.exr --ref-spp 1024 --ref-out ref.exr
    python -m kpcn.render dataset --out data/train --scenes 64 --spp 2 4 8 16 --ref-spp 1024

Every render uses the ``kpcn_split`` integrator (:mod:`kpcn.integrator`) on the
``llvm_ad_rgb`` variant. The renderer overrides what it must — integrator,
film size, box reconstruction filter, RGB pixel format, sample count — and
logs what it changed. Large sample counts are rendered in passes of at most
``pass_spp`` samples with independent seeds, whose moments are combined, so
memory stays bounded.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .integrator import MOMENT2, aov_layout, register
from .io import Frame, atomic_write, write_exr

log = logging.getLogger("kpcn.render")

VARIANT = "llvm_ad_rgb"
LLVM_HELP = (
    "Mitsuba's llvm_ad_rgb variant needs LLVM >= 17 (LLVM 15/16 crash on the first render). "
    "On Debian/Ubuntu install it with: sudo apt-get install -y libllvm19 "
    "(or run scripts/setup.sh); or point DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= 17."
)


class RendererUnavailable(RuntimeError):
    """Mitsuba cannot render here (no suitable LLVM)."""


def ensure_variant():
    """Select ``llvm_ad_rgb`` and check the LLVM that Dr.Jit found; return ``mitsuba``."""
    import mitsuba as mi

    if mi.variant() != VARIANT:
        try:
            mi.set_variant(VARIANT)
        except Exception as exc:  # drjit raises when it finds no libLLVM at all
            raise RendererUnavailable(f"cannot select {VARIANT}: {exc}. {LLVM_HELP}") from exc
    import drjit as dr

    version = tuple(dr.detail.llvm_version())
    if version < (17,):
        raise RendererUnavailable(f"found LLVM {'.'.join(map(str, version))}. {LLVM_HELP}")
    register()
    return mi


# ----------------------------------------------------------------------------- scenes


def _film_dict(width: int, height: int) -> dict:
    return {
        "type": "hdrfilm",
        "width": int(width),
        "height": int(height),
        "rfilter": {"type": "box"},
        "pixel_format": "rgb",
        "component_format": "float32",
    }


def _override_dict(scene: dict, resolution: tuple[int, int] | None) -> tuple[dict, list[str]]:
    scene = dict(scene)
    notes = []
    sensor_key = next((k for k, v in scene.items() if isinstance(v, dict) and v.get("type") in _SENSORS), None)
    if sensor_key is None:
        raise ValueError("scene dict has no sensor (perspective/thinlens/orthographic camera)")
    sensor = dict(scene[sensor_key])
    film = sensor.get("film", {})
    w, h = resolution or (film.get("width", 256), film.get("height", 256))
    if film.get("rfilter", {}).get("type", "gaussian") != "box":
        notes.append("film rfilter -> box")
    if (film.get("width"), film.get("height")) != (w, h):
        notes.append(f"film size -> {w}x{h}")
    sensor["film"] = _film_dict(w, h)
    sensor["sampler"] = {"type": "independent"}
    scene[sensor_key] = sensor
    for k in [k for k, v in scene.items() if isinstance(v, dict) and v.get("type") in _INTEGRATORS]:
        notes.append(f"integrator {scene[k]['type']} -> kpcn_split")
        del scene[k]
    return scene, notes


_SENSORS = {"perspective", "thinlens", "orthographic"}
_INTEGRATORS = {"path", "direct", "volpath", "volpathmis", "prb", "aov", "moment", "depth", "ptracer", "stokes"}


def _override_xml(path: Path, resolution: tuple[int, int] | None) -> tuple[str, list[str]]:
    tree = ET.parse(path)
    root = tree.getroot()
    notes = []
    for integ in root.findall("integrator"):
        notes.append(f"integrator {integ.get('type')} -> kpcn_split")
        root.remove(integ)
    sensor = root.find("sensor")
    if sensor is None:
        raise ValueError(f"{path}: no <sensor> in the scene")
    film = sensor.find("film")
    if film is None:
        film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
    if film.get("type") != "hdrfilm":
        notes.append(f"film {film.get('type')} -> hdrfilm")
        film.set("type", "hdrfilm")

    def set_param(tag, name, value):
        el = next((e for e in film if e.get("name") == name), None)
        if el is None:
            el = ET.SubElement(film, tag, {"name": name})
        el.tag = tag
        el.set("value", str(value))

    if resolution is not None:
        set_param("integer", "width", resolution[0])
        set_param("integer", "height", resolution[1])
        notes.append(f"film size -> {resolution[0]}x{resolution[1]}")
    set_param("string", "pixel_format", "rgb")
    set_param("string", "component_format", "float32")
    filters = film.findall("rfilter")
    if [rf.get("type") for rf in filters] != ["box"]:
        old = filters[0].get("type") if filters else "gaussian (default)"
        notes.append(f"film rfilter {old} -> box")
    for rf in filters:
        film.remove(rf)
    ET.SubElement(film, "rfilter", {"type": "box"})
    # the sample count is given to mi.render; make the sampler independent
    for smp in sensor.findall("sampler"):
        sensor.remove(smp)
    ET.SubElement(sensor, "sampler", {"type": "independent"})
    return ET.tostring(root, encoding="unicode"), notes


def _log_notes(name: str, notes: list[str]) -> None:
    for n in notes:
        log.info("%s: %s", name, n)


def load_scene(scene: Any, resolution: tuple[int, int] | None = None):
    """Load ``scene`` with kpcn's overrides. Returns ``(mi.Scene, name, notes)``.

    ``scene`` is an XML path, a Mitsuba scene dict, ``"test:<name>"`` for a
    built-in test scene or ``"random:<seed>"`` for a procedural one.
    """
    mi = ensure_variant()
    name = "dict"
    if isinstance(scene, (str, os.PathLike)) and str(scene).startswith(("test:", "random:")):
        from . import scenes

        kind, arg = str(scene).split(":", 1)
        res = resolution or (64, 64)
        name = str(scene)
        scene = scenes.test_scene(arg, resolution=res) if kind == "test" else scenes.random_scene(int(arg), resolution=res)
    if isinstance(scene, dict):
        # callers may name a dict scene with a "kpcn_name" key (Mitsuba would reject it)
        name = scene.get("kpcn_name", name)
        d, notes = _override_dict({k: v for k, v in scene.items() if k != "kpcn_name"}, resolution)
        _log_notes(name, notes)
        return mi.load_dict(d), name, notes
    path = Path(scene)
    if not path.exists():
        raise FileNotFoundError(f"scene file not found: {path}")
    text, notes = _override_xml(path, resolution)
    _log_notes(path.stem, notes)
    # write next to the original so relative paths (meshes, textures) resolve
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.kpcn.", suffix=".xml", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        return mi.load_file(tmp), path.stem, notes
    finally:
        os.unlink(tmp)


# ----------------------------------------------------------------------------- rendering


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

    Returns:
        Frame with ``color``, ``diffuse``, ``specular``, ``albedo``, ``normal``,
        ``depth`` and ``<layer>Variance`` (variance of the pixel mean), and meta
        ``spp``, ``renderTimeSeconds`` (wall time of the passes), ``seed``, ``scene``.
    """
    if spp < 2:
        raise ValueError(f"spp must be >= 2 to estimate variances, got {spp}")
    mi = ensure_variant()
    mi_scene, name, notes = loaded or load_scene(scene, resolution)
    integrator = mi.load_dict({"type": "kpcn_split", "max_depth": int(max_depth)})

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
    meta = {"spp": int(spp), "renderTimeSeconds": float(seconds), "seed": int(seed), "scene": str(name)}
    return Frame(layers, meta)


def render_to_exr(scene: Any, out: str | os.PathLike, spp: int, seed: int = 0, **kw) -> Frame:
    """Render and write one EXR (atomically). Returns the frame."""
    frame = render_frame(scene, spp, seed, **kw)
    write_exr(out, frame.layers, frame.meta)
    frame.path = os.fspath(out)
    return frame


# ----------------------------------------------------------------------------- data sets


def render_dataset(
    out_dir: str | os.PathLike,
    n_scenes: int,
    spp_list: Sequence[int] = (2, 4, 8, 16, 32),
    ref_spp: int = 1024,
    resolution: tuple[int, int] = (128, 128),
    first_seed: int = 0,
    scenes: Sequence[Any] | None = None,
    progress: bool = True,
) -> Path:
    """Render procedural scenes (or ``scenes``) into ``out_dir`` with a manifest.

    Layout: ``out_dir/<scene>/input_<spp>spp.exr`` for each input spp, and
    ``out_dir/<scene>/reference.exr``; ``out_dir/manifest.json`` lists them.
    Frames already on disk are kept (an interrupted run resumes).
    """
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    items = list(scenes) if scenes is not None else [f"random:{first_seed + i}" for i in range(n_scenes)]
    manifest = {"ref_spp": int(ref_spp), "spp": [int(s) for s in spp_list], "resolution": list(resolution), "scenes": []}
    for i, sc in enumerate(tqdm(items, desc="render", disable=not progress)):
        sname = f"scene_{i:04d}" if isinstance(sc, dict) else str(sc).replace(":", "_").replace("/", "_")
        folder = out / sname
        folder.mkdir(exist_ok=True)
        seed = first_seed + i
        # role 1 = reference; each input spp gets a role of its own so no two frames share noise
        jobs = [(s, folder / f"input_{s}spp.exr", 2 + s) for s in spp_list] + [(ref_spp, folder / "reference.exr", 1)]
        loaded = None
        for s, path, role in jobs:
            if path.exists():  # resume: keep what an earlier run finished
                continue
            loaded = loaded or load_scene(sc, resolution)
            render_to_exr(sc, path, s, seed=seed, role=role, loaded=loaded)
        manifest["scenes"].append({
            "name": sname,
            "source": sc if isinstance(sc, str) else "dict",
            "seed": seed,
            "inputs": {str(s): str(p.relative_to(out)) for s, p, role in jobs if role != 1},
            "reference": str(jobs[-1][1].relative_to(out)),
        })
        atomic_write(out / "manifest.json", lambda tmp: Path(tmp).write_text(json.dumps(manifest, indent=1)))
    return out


# ----------------------------------------------------------------------------- CLI


def _parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m kpcn.render", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("frame", help="render one scene (XML file, test:<name> or random:<seed>)")
    f.add_argument("scene")
    f.add_argument("--spp", type=int, default=8)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--out", required=True, help="noisy EXR to write")
    f.add_argument("--ref-spp", type=int, default=0, help="also render a reference with this many spp")
    f.add_argument("--ref-out", help="reference EXR path (default: <out>_ref.exr)")
    f.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"))
    f.add_argument("--max-depth", type=int, default=8)
    d = sub.add_parser("dataset", help="render N procedural scenes with inputs and references")
    d.add_argument("--out", required=True)
    d.add_argument("--scenes", type=int, default=16)
    d.add_argument("--first-seed", type=int, default=0)
    d.add_argument("--spp", type=int, nargs="+", default=[2, 4, 8, 16, 32])
    d.add_argument("--ref-spp", type=int, default=1024)
    d.add_argument("--resolution", type=int, nargs=2, default=[128, 128], metavar=("W", "H"))
    return p.parse_args(argv)


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    args = _parse_args(argv)
    try:
        ensure_variant()
    except RendererUnavailable as exc:
        print(f"error: {exc}")
        return 2
    if args.cmd == "frame":
        res = tuple(args.resolution) if args.resolution else None
        fr = render_to_exr(args.scene, args.out, args.spp, args.seed, resolution=res, max_depth=args.max_depth)
        print(f"{args.out}: {fr.shape[1]}x{fr.shape[0]}, {args.spp} spp, {fr.meta['renderTimeSeconds']:.2f} s")
        if args.ref_spp:
            ref_out = args.ref_out or str(Path(args.out).with_name(Path(args.out).stem + "_ref.exr"))
            fr = render_to_exr(args.scene, ref_out, args.ref_spp, args.seed, resolution=res, max_depth=args.max_depth, role=1)
            print(f"{ref_out}: {args.ref_spp} spp, {fr.meta['renderTimeSeconds']:.2f} s")
    else:
        out = render_dataset(args.out, args.scenes, args.spp, args.ref_spp, tuple(args.resolution), args.first_seed)
        print(f"wrote {out / 'manifest.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
