"""Command line: ``python -m kpcn.report`` (see the package docstring for the options)."""
from __future__ import annotations

import argparse
import dataclasses
import logging
import sys

from ..config import ConfigError, add_config_args, config_from_args
from . import __doc__ as _package_doc
from ..scenes.files import list_scene_files
from .config import DEFAULT_SCENES, ReportConfig
from .run import run_report


class _NoTarget:
    """``--ref-floor-target none``: set to None (an unset flag is None too, and keeps the default)."""


def _target(value: str):
    if value.strip().lower() in ("none", "off", "0"):
        return _NoTarget
    try:
        return float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a relMSE such as 0.0015, or none; got {value!r}") from None


def _parse_args(argv=None) -> tuple[ReportConfig, argparse.Namespace]:
    p = argparse.ArgumentParser(prog="python -m kpcn.report", description=_package_doc.split("\n\n")[0])
    add_config_args(p)
    p.add_argument("--scenes", nargs="+", help="XML paths, test:<name>, random:<seed>, file:<name>, cycles:generated[:<N>] or cycles:<file.blend> (Blender Cycles) (shipped XML files: "
                   f"{' '.join('file:' + n for n in list_scene_files())}) (default: {' '.join(DEFAULT_SCENES)})")
    p.add_argument("--spp", type=int, nargs="+", help="input spp ladder, each >= 2 (default: 2 4 8 16 32 64 128 256)")
    p.add_argument("--ref-spp", type=int, help="reference spp (default: 2048)")
    p.add_argument("--ref-floor-target", type=_target,
                   help="give a reference more samples (its spp doubled, its samples kept) while its own noise adds "
                        "more relMSE than this; 'none' for none (default: 0.0015)")
    p.add_argument("--ref-spp-max", type=int, help="the most samples a refined reference gets (default: 16384)")
    p.add_argument("--converged-spp", type=int,
                   help="spp of the converged input every method is also run on, 0 for none (default: 1024)")
    p.add_argument("--exposure-factors", type=float, nargs="*",
                   help="every method is also run on the --exposure-spp input with its radiance times each factor; "
                        "none: leave it out (default: 0.01 100)")
    p.add_argument("--exposure-spp", type=int, help="spp of the inputs run at other exposures (default: 4)")
    p.add_argument("--mixed-spp", type=int, nargs="*", metavar="SPP",
                   help="every method is also run on a frame made of the first spp's input in half the frame and the "
                        "second's in the other half (a varying spp); none: leave it out (default: 4 64)")
    p.add_argument("--floor-factor", type=float,
                   help="flag relMSE below this many times the reference's own noise (default: 3)")
    p.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), help="default: 256 256")
    p.add_argument("--models", nargs="+",
                   help="shipped model names, weights files or label=file, each with an optional @N (2, 4 or 8): "
                        "the mean of N mirrored views (default: unet_kpcn mskpcn kpcn dpcn)")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="allow .pt model files that only full unpickling can load (runs their code: trusted files only)")
    p.add_argument("--no-oidn", action="store_true", help="leave OIDN out even if pyoidn is installed")
    p.add_argument("--no-oidn-prefiltered", action="store_true",
                   help="leave out OIDN with its albedo and normal prefiltered (oidn_prefiltered; OIDN itself stays)")
    p.add_argument("--out", help="results root (default: results/report)")
    p.add_argument("--name", help="report name: files go to <out>/<name>/ (default: default, or quick)")
    p.add_argument("--seed", type=int, help="base render seed (default: 0)")
    p.add_argument("--device", help="auto, cpu or cuda (default: auto)")
    p.add_argument("--tile", type=int, help="denoise tile size (default: 0, whole frames)")
    p.add_argument("--repeats", type=int, help="timed denoise calls per frame, median reported (default: 1)")
    p.add_argument("--equal-time-spp", type=int, help="model spp of the equal-time figure (default: 8)")
    p.add_argument("--contact-spp", type=int, help="spp of the contact sheet (default: 8)")
    p.add_argument("--rerender", action="store_true", help="render again even when cached EXRs exist")
    p.add_argument("--quick", action="store_true",
                   help="tiny run: 3 scenes at 24x24, spp 2 4 8, converged input 32, reference 128")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the Markdown summary")
    a = p.parse_args(argv)
    flags = {
        "scenes": a.scenes, "spp": a.spp, "ref_spp": a.ref_spp,
        "ref_floor_target": None if a.ref_floor_target is _NoTarget else a.ref_floor_target,
        "ref_spp_max": a.ref_spp_max, "converged_spp": a.converged_spp,
        "floor_factor": a.floor_factor, "resolution": a.resolution, "models": a.models,
        "out": a.out, "name": a.name, "seed": a.seed, "device": a.device, "tile": a.tile, "repeats": a.repeats,
        "equal_time_spp": a.equal_time_spp, "contact_spp": a.contact_spp,
        "exposure_factors": a.exposure_factors, "exposure_spp": a.exposure_spp,
        "mixed_spp": a.mixed_spp,
        "oidn": False if a.no_oidn else None,
        "oidn_prefiltered": False if a.no_oidn_prefiltered else None, "rerender": True if a.rerender else None,
        "trust_checkpoint": True if a.trust_checkpoint else None,
    }
    cfg = config_from_args(ReportConfig, a, flags, defaults=ReportConfig.QUICK if a.quick else None)
    if a.ref_floor_target is _NoTarget:
        cfg = dataclasses.replace(cfg, ref_floor_target=None)
    return cfg, a


def main(argv=None) -> int:
    try:
        cfg, args = _parse_args(argv)
    except ConfigError as exc:
        print(f"python -m kpcn.report: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(name)s: %(message)s")
    logging.getLogger("kpcn.render").setLevel(logging.WARNING)  # its per-render override notes
    from ..render import RendererUnavailable, SceneError
    from ..render.cycles import BlenderUnavailable
    from .methods import MissingLayersError

    try:
        cfg.validate()
    except ValueError as exc:  # a setting it refuses: an unknown file: scene, spp < 2, ...
        print(f"python -m kpcn.report: {exc}", file=sys.stderr)
        return 2
    try:
        result = run_report(cfg)
    except (RendererUnavailable, SceneError, BlenderUnavailable, MissingLayersError) as exc:
        print(f"error: {exc}")
        return 2
    md = result.markdown
    # stdout: everything up to the per-scene table (equal time, means, against OIDN, methods, converged
    # input, frames made worse); the per-scene table is in the file
    print(md.split("\n## Per scene")[0].rstrip())
    print(f"\nwrote {', '.join(str(p) for p in result.paths.values())}")
    left_out = [n for n in result.summary["notes"] if n.startswith("model ")]
    if left_out:
        print(f"WARNING: {len(left_out)} of {len(cfg.models)} model(s) could not be loaded and are not in the report (see Notes)")
    return 0
