"""Benchmarks: ``python -m kpcn.bench <subcommand> [options]``.

Each subcommand prints figures and compares against a baseline measured in the
same run (a ratio):

* ``render``  — the one-pass split integrator against Mitsuba's ``path`` (:mod:`.render`)
* ``kernel``  — the kernel-apply op against ``F.unfold`` (:mod:`.kernel`)
* ``train``   — training throughput of configs, patches/s (:mod:`.train`)
* ``aov``     — light groups: the sum of kpcn's shared-kernel results and of OIDN's
  per-group results against each one's denoised beauty (:mod:`.aov`)
* ``data``    — training-patch throughput and memory: the frames in memory against the
  patch store, with and without DataLoader workers (:mod:`.data`)
* ``denoise`` — whole-frame denoising against Intel OIDN; ``--skip`` the time saved
  by leaving out what a scene does not need (:mod:`.denoise`, :mod:`.skip`)
* ``exr``     — reading and writing a render's EXR with OpenEXR's thread pool against its
  single thread (:mod:`.exr`)

Subcommands live in :data:`SUBCOMMANDS`, a dict mapping the name to a function
``fn(argv: list[str]) -> int`` that parses its own options.
"""
from __future__ import annotations

import sys
from typing import Callable


def _lazy(module: str, func: str) -> Callable[[list[str]], int]:
    def run(argv: list[str]) -> int:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{module}"), func)(argv)

    return run


SUBCOMMANDS: dict[str, Callable[[list[str]], int]] = {
    "render": _lazy("render", "bench_render"),
    "kernel": _lazy("kernel", "bench_kernel"),
    "train": _lazy("train", "bench_train"),
    "denoise": _lazy("denoise", "bench_denoise"),
    "aov": _lazy("aov", "bench_aov"),
    "data": _lazy("data", "bench_data"),
    "exr": _lazy("exr", "bench_exr"),
}

def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    names = ", ".join(sorted(SUBCOMMANDS))
    if not argv or argv[0] in ("-h", "--help"):
        print(f"usage: python -m kpcn.bench {{{names}}} [options]\n\nsubcommands: {names}\n"
              "run 'python -m kpcn.bench <subcommand> --help' for its options")
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"python -m kpcn.bench: unknown subcommand {name!r}; known: {names}", file=sys.stderr)
        return 2
    return SUBCOMMANDS[name](rest)

