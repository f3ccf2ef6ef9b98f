"""``python -m kpcn.inference`` (installed as ``kpcn-denoise``): denoise EXR files.

::

    kpcn-denoise in.exr [more.exr ...] [-o out.exr | --out-dir DIR] [--model NAME_OR_FILE]
                 [--tile N] [--device cpu] [--trust-checkpoint]

Before anything is denoised the whole call is checked (:func:`.paths.check_jobs`):
every input exists and is a file, no input is given twice, no output is an input
(under any spelling: relative, symlink, hard link), no two inputs share an output
(``a/x.exr b/x.exr --out-dir OUT``), and no output is a folder or lies under a file.
A problem is one line on stderr and exit code 2. Missing output folders are
created. Outputs are written atomically, so a failed file leaves none.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

import torch

from ..checkpoint import CheckpointError
from ..config import ConfigError
from ..io import ExrError, MissingLayerError
from ..models import list_weights
from .ensemble import VIEWS
from .paths import check_jobs
from .pipeline import denoise_result
from .weights import DEFAULT_MODEL, describe, load_model, resolve_device

__all__ = ["main"]


def _default_out(path: Path, out_dir: str | None) -> Path:
    name = f"{path.stem}_denoised.exr"
    return Path(out_dir) / name if out_dir else path.with_name(name)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="kpcn-denoise",
        description="Denoise multi-layer EXR renders with a kpcn model. "
        "Writes <name>_denoised.exr next to each input unless -o or --out-dir is given.",
    )
    p.add_argument("inputs", nargs="+", help="noisy multi-layer EXR files")
    g = p.add_mutually_exclusive_group()
    g.add_argument("-o", "--out", help="output EXR (only with a single input)")
    g.add_argument("--out-dir", help="folder for the outputs (<name>_denoised.exr)")
    p.add_argument("--model", default=None,
                   help=f"weights file (.safetensors, or a .pt training checkpoint) or a shipped model name "
                        f"(default: {DEFAULT_MODEL}; shipped: {', '.join(list_weights())})")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="allow a .pt checkpoint that only full unpickling can load; unpickling runs any code "
                        "the file contains, so use this only for files you trust (kpcn's own files never need it)")
    p.add_argument("--tile", type=_tile_arg, default="auto",
                   help="tile size in pixels, 0 = whole frame, auto = whole frame up to 1920x1080 (up to "
                        "4096x4096 for a model that runs whole frames in row bands, as the default does), else "
                        "tiles of max(512, 4 x the model's halo) (default auto)")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda, cuda:1, ... (default auto)")
    p.add_argument("--half", action="store_true", help="float16 autocast (CUDA only)")
    p.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default="auto",
                   help="dtype of the model's hidden layers: auto = bfloat16 on a CPU with native bfloat16 "
                        "(AMX, AVX-512 BF16) for models that can, else float32 (default auto)")
    p.add_argument("--no-skip", action="store_true", help="run the network on every tile and branch")
    p.add_argument("--layers", nargs="+", default=None, metavar="NAME",
                   help="also denoise these light groups (NAME.diffuse + NAME.specular) or other 3-channel layers "
                        "with the beauty's kernels, written to the output beside the colour (kernel predictors only)")
    p.add_argument("--aov-branch", default=None,
                   help="branch whose kernels filter --layers that are not light groups (default: the first)")
    p.add_argument("--views", type=int, choices=VIEWS, default=1,
                   help="average this many mirrored copies of each frame, denoised (a little closer to the reference "
                        "at low spp, in that many times the time; default 1)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    return p


def _refuse(problems: list[str]) -> int:
    for msg in problems:
        print(f"kpcn-denoise: {msg}", file=sys.stderr)
    return 2


def _jobs(args) -> list[tuple[str, str]]:
    """``(input, output)`` for each input, both spelled as the user gave them (so messages quote them)."""
    if args.out:
        return [(args.inputs[0], args.out)]
    return [(inp, os.fspath(_default_out(Path(inp), args.out_dir))) for inp in args.inputs]


def _tile_arg(value: str):
    if value == "auto":
        return value
    try:
        return int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer or 'auto', got {value!r}") from None


def main(argv: list[str] | None = None) -> int:
    """Exit codes: 0 all written; 1 some files failed (the others are written); 2 refused before any work
    (a usage mistake: a missing input, an output that is an input or is shared, a folder where a file
    must be, unusable weights or device), with one line per problem on stderr."""
    p = build_parser()
    args = p.parse_args(argv)
    if args.out and len(args.inputs) > 1:
        p.error("-o/--out takes a single input; use --out-dir for several")
    if args.threads is not None and args.threads < 1:
        p.error(f"--threads must be at least 1, got {args.threads}")

    # everything about the files is checked before the model is loaded or anything is denoised
    if args.out_dir and os.path.lexists(args.out_dir) and not os.path.isdir(args.out_dir):
        return _refuse([f"--out-dir {args.out_dir} is a file, not a folder"])
    jobs = _jobs(args)
    problems = check_jobs(jobs)
    if problems:
        return _refuse(problems)

    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        resolve_device(args.device)
    except (RuntimeError, ValueError) as exc:
        return _refuse([f"--device {args.device}: {exc}"])
    try:
        net = load_model(args.model, args.device, trust_pickle=args.trust_checkpoint)
    except (FileNotFoundError, CheckpointError, ConfigError, ValueError, TypeError, RuntimeError) as exc:
        print(f"kpcn-denoise: cannot load the model: {exc}", file=sys.stderr)
        return 2
    dev = next(net.parameters()).device
    how = " (files without its layers get the shipped model for the layers they have)" if args.model is None else ""
    print(f"model: {describe(net)}, inputs {net.input_spec.name}, receptive radius {net.receptive_radius}, "
          f"tile {args.tile}, device {dev}{how}", flush=True)

    failures: list[tuple[str, str]] = []
    for inp, dst in jobs:
        try:
            # denoise_result repeats the output checks (the same functions), in case a file changed meanwhile
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                res = denoise_result(inp, None if args.model is None else net, dst, tile=args.tile, device=args.device, half=args.half,
                                     skip=not args.no_skip, layers=args.layers, aov_branch=args.aov_branch,
                                     precision=args.precision, views=args.views)
            for wmsg in caught:
                print(f"warning: {wmsg.message}", file=sys.stderr)
        except (MissingLayerError, ExrError, FileNotFoundError, ValueError, OSError, RuntimeError) as exc:
            print(f"FAILED {inp}: {exc}", file=sys.stderr, flush=True)
            failures.append((inp, str(exc)))
            continue
        print(f"{inp} -> {dst}: {res.model_name}, {res.stats.seconds:.2f} s ({res.stats.summary()})", flush=True)
    if failures:
        print(f"\n{len(failures)} of {len(args.inputs)} file(s) failed:", file=sys.stderr)
        for inp, msg in failures:
            print(f"  {inp}: {msg}", file=sys.stderr)
        return 1
    return 0
