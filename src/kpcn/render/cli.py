"""Render Mitsuba 3 scenes into kpcn's multi-layer EXR contract.

Command line::

    python -m kpcn.render frame scene.xml --spp 8 --out noisy.exr --ref-spp 1024 --ref-out ref.exr
    python -m kpcn.render frame scene.xml --param albedo=0.3 --param res=64 --spp 8 --out noisy.exr
    python -m kpcn.render dataset --out data/train --scenes 64 --spp 2 4 8 16 --ref-spp 1024
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from ..config import ConfigError, add_config_args, config_from_args, save_config
from .dataset import DatasetConfig, render_dataset
from .frame import render_to_exr
from .scene import RendererUnavailable, SceneError, ensure_variant


def _param(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    return name, value


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
    f.add_argument("--param", type=_param, action="append", default=[], metavar="NAME=VALUE",
                   help="value of the XML scene's $NAME parameter (<default name=..>); repeatable")
    d = sub.add_parser("dataset", help="render N procedural scenes with inputs and references "
                                          "(settings: kpcn.render.dataset.DatasetConfig; flags override --config/--set)")
    add_config_args(d)
    d.add_argument("--out", help="data set folder (default data/train)")
    d.add_argument("--scenes", type=int, help="number of procedural scenes (default 16)")
    d.add_argument("--first-seed", type=int, help="seed of the first scene (default 0)")
    d.add_argument("--spp", type=int, nargs="+", help="input spp (default 2 4 8 16 32)")
    d.add_argument("--ref-spp", type=int, help="reference spp (default 1024)")
    d.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), help="default 128 128")
    return p.parse_args(argv)


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    args = _parse_args(argv)
    try:
        ensure_variant()
    except RendererUnavailable as exc:
        print(f"error: {exc}")
        return 2
    try:
        if args.cmd == "frame":
            res = tuple(args.resolution) if args.resolution else None
            kw = dict(resolution=res, max_depth=args.max_depth, params=dict(args.param))
            fr = render_to_exr(args.scene, args.out, args.spp, args.seed, **kw)
            print(f"{args.out}: {fr.shape[1]}x{fr.shape[0]}, {args.spp} spp, {fr.meta['renderTimeSeconds']:.2f} s")
            if args.ref_spp:
                ref_out = args.ref_out or str(Path(args.out).with_name(Path(args.out).stem + "_ref.exr"))
                fr = render_to_exr(args.scene, ref_out, args.ref_spp, args.seed, role=1, **kw)
                print(f"{ref_out}: {args.ref_spp} spp, {fr.meta['renderTimeSeconds']:.2f} s")
        else:
            flags = {"out": args.out, "scenes": args.scenes, "first_seed": args.first_seed, "spp": args.spp,
                     "ref_spp": args.ref_spp, "resolution": args.resolution}
            cfg = config_from_args(DatasetConfig, args, flags)
            out = render_dataset(cfg.out, cfg.scenes, cfg.spp, cfg.ref_spp, tuple(cfg.resolution), cfg.first_seed)
            save_config(cfg, out / "config.yaml")
            print(f"wrote {out / 'manifest.json'}")
    except (SceneError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
