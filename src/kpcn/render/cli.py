"""Render Mitsuba 3 scenes into kpcn's multi-layer EXR contract.

Command line::

    python -m kpcn.render frame scene.xml --spp 8 --out noisy.exr --ref-spp 1024 --ref-out ref.exr
    python -m kpcn.render frame scene.xml --param albedo=0.3 --param res=64 --spp 8 --out noisy.exr
    python -m kpcn.render dataset --out data/train --scenes 64 --spp 2 4 8 16 --ref-spp 1024
    python -m kpcn.render cycles scene.blend --spp 16 --out frame.exr [--seed N] [--resolution W H]
    python -m kpcn.render cycles --generated --spp 16 --out frame.exr

``cycles`` renders with Blender Cycles (optional: ``pip install 'kpcn[blender]'``)
into a multilayer EXR of Cycles passes, which kpcn reads (see
:mod:`kpcn.render.cycles` and :mod:`kpcn.io.cycles`).

Every option is checked, and the scene loaded, before anything is rendered;
``frame`` renders the input and the reference before it writes either, so a
failure writes nothing. Errors are one line on stderr (``error: ...``) with exit
status 2 (1 for an unexpected internal error); ``--debug`` shows the traceback.
``dataset`` into a folder that holds frames rendered with other settings
renders those frames again, one logged line each; run again after an
interruption, it resumes.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from ..config import ConfigError, add_config_args, config_from_args, save_config
from .dataset import DatasetConfig, render_dataset
from .manifest import DatasetError
from .scene import RendererUnavailable, SceneError, ensure_variant


class UsageError(ValueError):
    """An option value that cannot be rendered (message names the option)."""


def _param(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    return name, value


def _parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m kpcn.render", description=__doc__.split("\n\n")[0])
    p.add_argument("--debug", action="store_true", help="show the Python traceback of an error")
    sub = p.add_subparsers(dest="cmd", required=True)
    debug = dict(action="store_true", default=argparse.SUPPRESS, help="show the Python traceback of an error")
    f = sub.add_parser("frame", help="render one scene (XML file, test:<name> or random:<seed>)")
    f.add_argument("scene")
    f.add_argument("--spp", type=int, default=8, help="samples per pixel (>= 2)")
    f.add_argument("--seed", type=int, default=0, help="seed (>= 0)")
    f.add_argument("--out", required=True, help="noisy EXR to write")
    f.add_argument("--ref-spp", type=int, default=0, help="also render a reference with this many spp (>= 2)")
    f.add_argument("--ref-out", help="reference EXR path (default: <out>_ref.exr)")
    f.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"))
    f.add_argument("--max-depth", type=int, default=8, help="longest path (>= 1)")
    f.add_argument("--param", type=_param, action="append", default=[], metavar="NAME=VALUE",
                   help="value of the XML scene's $NAME parameter (<default name=..>); repeatable")
    f.add_argument("--debug", **debug)
    d = sub.add_parser("dataset", help="render N procedural scenes with inputs and references "
                                          "(settings: kpcn.render.dataset.DatasetConfig; flags override --config/--set)")
    add_config_args(d)
    d.add_argument("--out", help="data set folder (default data/train)")
    d.add_argument("--scenes", type=int, help="number of procedural scenes (default 16)")
    d.add_argument("--first-seed", type=int, help="seed of the first scene (default 0)")
    d.add_argument("--spp", type=int, nargs="+", help="input spp (default 2 4 8 16 32)")
    d.add_argument("--ref-spp", type=int, help="reference spp (default 1024)")
    d.add_argument("--ref-floor-target", type=float, metavar="RELMSE",
                   help="give a reference whose own noise adds more relMSE than this more samples, its own kept "
                        "(default none)")
    d.add_argument("--ref-spp-max", type=int, help="the most samples a refined reference gets (default 16384)")
    d.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), help="default 128 128")
    d.add_argument("--renderer", choices=("mitsuba", "cycles"),
                   help="mitsuba (default): procedural Mitsuba scenes; cycles: variants of kpcn's generated Blender "
                        "Cycles scene (no variance layers; needs kpcn[blender])")
    d.add_argument("--debug", **debug)
    c = sub.add_parser("cycles", help="render a Blender .blend (or --generated, a small built-in scene) with Cycles "
                                      "into a multilayer EXR of the passes kpcn reads (needs kpcn[blender])")
    c.add_argument("blend", nargs="?", help="the .blend file (its active scene and camera)")
    c.add_argument("--generated", action="store_true",
                   help="render kpcn's generated scene (diffuse plane, glossy and glass spheres) instead")
    c.add_argument("--variant", type=int, help="with --generated: draw materials, layout, light and view from this "
                                                "seed (>= 0; default: the fixed layout)")
    c.add_argument("--spp", type=int, default=16, help="samples per pixel (>= 1)")
    c.add_argument("--seed", type=int, default=0, help="scene.cycles.seed (>= 0)")
    c.add_argument("--out", required=True, help="multilayer EXR to write")
    c.add_argument("--adaptive-threshold", type=float, metavar="T",
                   help="Cycles' adaptive sampling with this noise threshold, --spp the most a pixel gets; the "
                        "file's sampleCount layer says how many each got (default: off, every pixel --spp)")
    c.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"),
                   help="image size (default: the .blend's; 128 128 for --generated)")
    c.add_argument("--debug", **debug)
    return p.parse_args(argv)


def _check_frame_args(args) -> Path | None:
    """UsageError naming the first bad option; returns the reference path (None: no reference)."""
    if args.spp < 2:
        raise UsageError(f"--spp: must be >= 2 (variances need two samples), got {args.spp}")
    if args.ref_spp != 0 and args.ref_spp < 2:
        raise UsageError(f"--ref-spp: must be >= 2 (variances need two samples; 0 renders no reference), "
                         f"got {args.ref_spp}")
    if args.resolution is not None and min(args.resolution) < 1:
        raise UsageError(f"--resolution: width and height must be >= 1, got {args.resolution[0]} {args.resolution[1]}")
    if args.max_depth < 1:
        raise UsageError(f"--max-depth: must be >= 1 (1 = emitters seen directly), got {args.max_depth}")
    if args.seed < 0:
        raise UsageError(f"--seed: must be >= 0, got {args.seed}")
    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out: {out} is a folder; give the EXR file to write")
    if not args.ref_spp:
        if args.ref_out:
            raise UsageError("--ref-out: given without --ref-spp (the reference's sample count)")
        return None
    ref_out = Path(args.ref_out) if args.ref_out else out.with_name(out.stem + "_ref.exr")
    if ref_out.resolve() == out.resolve():
        raise UsageError(f"--ref-out: the reference would overwrite the input {out}")
    if ref_out.is_dir():
        raise UsageError(f"--ref-out: {ref_out} is a folder; give the EXR file to write")
    return ref_out


def _frame(args) -> None:
    from ..io import write_exr
    from .frame import render_frame
    from .scene import load_scene

    ref_out = _check_frame_args(args)
    ensure_variant()
    res = tuple(args.resolution) if args.resolution else None
    loaded = load_scene(args.scene, res, dict(args.param))
    kw = dict(resolution=res, max_depth=args.max_depth, loaded=loaded)
    frames = [(Path(args.out), render_frame(args.scene, args.spp, args.seed, **kw))]
    if ref_out is not None:
        frames.append((ref_out, render_frame(args.scene, args.ref_spp, args.seed, role=1, **kw)))
    written = []
    try:
        for path, fr in frames:  # written only once every frame rendered
            write_exr(path, fr.layers, fr.meta)
            written.append(path)
    except BaseException:
        for path in written:  # all or nothing
            path.unlink(missing_ok=True)
        raise
    for path, fr in frames:
        print(f"{path}: {fr.shape[1]}x{fr.shape[0]}, {fr.meta['spp']} spp, {fr.meta['renderTimeSeconds']:.2f} s")


def _dataset(args) -> None:
    flags = {"out": args.out, "scenes": args.scenes, "first_seed": args.first_seed, "spp": args.spp,
             "ref_spp": args.ref_spp, "resolution": args.resolution, "renderer": args.renderer,
             "ref_floor_target": args.ref_floor_target, "ref_spp_max": args.ref_spp_max}
    cfg = config_from_args(DatasetConfig, args, flags)
    if cfg.renderer == "mitsuba":
        ensure_variant()
    try:
        out = render_dataset(cfg.out, cfg.scenes, cfg.spp, cfg.ref_spp, tuple(cfg.resolution), cfg.first_seed,
                             scenes=cfg.scene_list(), ref_floor_target=cfg.ref_floor_target,
                             ref_spp_max=cfg.ref_spp_max)
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"{cfg.out} is incomplete; run the same command again to resume") from None
    save_config(cfg, out / "config.yaml")
    print(f"wrote {out / 'manifest.json'}")


def _cycles(args) -> None:
    from .cycles import render_cycles

    if args.generated == (args.blend is not None):
        raise UsageError("cycles: give either a .blend file or --generated" if args.generated
                         else "cycles: give a .blend file to render, or --generated for kpcn's generated scene")
    if args.variant is not None and not args.generated:
        raise UsageError("--variant: only with --generated (it draws kpcn's generated scene)")
    if args.variant is not None and args.variant < 0:
        raise UsageError(f"--variant: must be >= 0, got {args.variant}")
    if args.spp < 1:
        raise UsageError(f"--spp: must be >= 1, got {args.spp}")
    if not 0 <= args.seed <= 2**31 - 1:
        raise UsageError(f"--seed: must be in [0, 2147483647] (scene.cycles.seed), got {args.seed}")
    if args.resolution is not None and min(args.resolution) < 1:
        raise UsageError(f"--resolution: width and height must be >= 1, got {args.resolution[0]} {args.resolution[1]}")
    if args.adaptive_threshold is not None and not 0 < args.adaptive_threshold < 1:
        raise UsageError(f"--adaptive-threshold: must be in (0, 1), got {args.adaptive_threshold}")
    out = Path(args.out)
    if out.is_dir():
        raise UsageError(f"--out: {out} is a folder; give the EXR file to write")
    if args.blend is not None and out.resolve() == Path(args.blend).resolve():
        raise UsageError(f"--out: {out} is the .blend file itself")
    r = render_cycles(args.blend, out, args.spp, args.seed, tuple(args.resolution) if args.resolution else None,
                      variant=args.variant, adaptive_threshold=args.adaptive_threshold)
    print(f"{r.path}: {r.resolution[0]}x{r.resolution[1]}, {r.spp} spp, {r.seconds:.2f} s "
          f"(Blender Cycles, {len(r.passes)} passes)")


_COMMANDS = {"frame": _frame, "dataset": _dataset, "cycles": _cycles}


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    args = _parse_args(argv)
    try:
        _COMMANDS[args.cmd](args)
    except (UsageError, SceneError, ConfigError, DatasetError, RendererUnavailable) as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        if args.debug:
            raise
        print(f"interrupted{': ' + str(exc) if str(exc) else ''}", file=sys.stderr)
        return 130
    except Exception as exc:  # anything else is a bug or an environment problem: still one line
        if args.debug:
            raise
        msg = " ".join(str(exc).split())
        print(f"error: {type(exc).__name__}: {msg} (run with --debug for the traceback)", file=sys.stderr)
        return 1
    return 0
