"""``python -m kpcn.bench render``: throughput of the one-pass split integrator.

Renders the same scenes with Mitsuba's built-in ``path`` integrator (colour
only) and with ``kpcn_split`` (colour, diffuse, specular, albedo, normal,
depth and all second moments in one pass), same film, spp and max depth, and
prints samples per second for both and their ratio, measured in the same run.
Each measurement is the median of ``--repeats`` renders after one warm-up
render (the warm-up pays the JIT compile).
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field

from ..config import parse_config


def _time_render(mi, scene, integrator, spp: int, repeats: int) -> float:
    import drjit as dr

    dr.eval(mi.render(scene, integrator=integrator, spp=spp, seed=0))  # warm-up / compile
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        img = mi.render(scene, integrator=integrator, spp=spp, seed=r + 1)
        dr.eval(img)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


@dataclass
class RenderBenchConfig:
    """``python -m kpcn.bench render`` settings (``--config``, ``--set`` or the flags)."""

    scenes: list[str] = field(default_factory=lambda: ["test:glossy", "random:5", "random:11"],
                              metadata={"help": "scenes (XML files, test:<name>, random:<seed>)"})
    resolution: tuple[int, int] = field(default=(256, 256), metadata={"help": "width height"})
    spp: int = field(default=64, metadata={"help": "samples per pixel"})
    max_depth: int = field(default=8, metadata={"help": "longest path"})
    repeats: int = field(default=3, metadata={"help": "timed renders per scene and integrator (median)"})


def bench_render(argv: list[str]) -> int:
    args = parse_config(RenderBenchConfig, argv, "python -m kpcn.bench render", __doc__.split("\n\n")[0])

    from ..render import ensure_variant, load_scene

    mi = ensure_variant()
    path = mi.load_dict({"type": "path", "max_depth": args.max_depth})
    split = mi.load_dict({"type": "kpcn_split", "max_depth": args.max_depth})
    w, h = args.resolution
    samples = w * h * args.spp
    print(f"render throughput, {w}x{h}, {args.spp} spp, max_depth {args.max_depth}, median of {args.repeats}")
    print(f"{'scene':<16} {'path Msamples/s':>16} {'kpcn_split Msamples/s':>22} {'cost ratio split/path':>22}")
    ratios = []
    for name in args.scenes:
        scene, _, _ = load_scene(name, (w, h))
        t_path = _time_render(mi, scene, path, args.spp, args.repeats)
        t_split = _time_render(mi, scene, split, args.spp, args.repeats)
        ratios.append(t_split / t_path)
        print(f"{name:<16} {samples / t_path / 1e6:>16.3f} {samples / t_split / 1e6:>22.3f} {t_split / t_path:>22.2f}")
    print(f"mean cost ratio (kpcn_split time / path time): {statistics.mean(ratios):.2f}")
    return 0
