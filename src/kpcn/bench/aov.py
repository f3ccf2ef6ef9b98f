"""``python -m kpcn.bench aov``: light groups denoised by kpcn (shared kernels) and by OIDN (one call per group).

Renders a scene's light groups (:func:`kpcn.render.groups.render_light_groups`),
denoises the beauty and every group, and prints how far the sum of the denoised
groups is from the denoised beauty (max and mean relative difference), for kpcn
(``layers=...``: the beauty's kernels) and for OIDN run on each group on its
own, in the same run; and the time of each.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..config import parse_config


@dataclass
class AovBenchConfig:
    """``python -m kpcn.bench aov`` settings (``--config``, ``--set`` or the flags)."""

    scenes: list[str] = field(default_factory=lambda: ["test:textured", "random:1", "random:3", "random:7"],
                              metadata={"help": "scenes with two or more emitters (test:<name>, random:<seed>)"})
    resolution: tuple[int, int] = field(default=(128, 128), metadata={"help": "width height"})
    spp: int = field(default=8, metadata={"help": "samples per pixel of each group"})
    model: str | None = field(default=None, metadata={"help": "kpcn model (default: the shipped default)"})
    tile: int = field(default=256, metadata={"help": "kpcn tile size"})


def _sum_errors(total: np.ndarray, beauty: np.ndarray) -> tuple[float, float]:
    diff = np.abs(total - beauty)
    return float(diff.max() / max(np.abs(beauty).max(), 1e-12)), float(diff.mean() / max(np.abs(beauty).mean(), 1e-12))


def bench_aov(argv: list[str]) -> int:
    cfg = parse_config(AovBenchConfig, argv, "python -m kpcn.bench aov", __doc__.split("\n\n")[0])
    from ..baselines import oidn_available, oidn_denoise, oidn_guides
    from ..inference import denoise_result, load_model
    from ..render.groups import render_light_groups

    net = load_model(cfg.model, "cpu")
    w, h = cfg.resolution
    print(f"light groups, {w}x{h}, {cfg.spp} spp per group; sum of the denoised groups against the denoised beauty "
          "(relative difference: max over pixels / max of the beauty, and mean)")
    print(f"{'scene':<16} {'groups':>6} {'kpcn max':>10} {'kpcn mean':>10} {'kpcn s':>8} "
          f"{'oidn max':>10} {'oidn mean':>10} {'oidn s':>8}")
    for scene in cfg.scenes:
        frame = render_light_groups(scene, cfg.spp, seed=1, resolution=(w, h))
        names = frame.meta["lightGroups"].split(",")
        if len(names) < 2:
            print(f"{scene:<16} {len(names):>6}  (one emitter: skipped)")
            continue
        t0 = time.perf_counter()
        res = denoise_result(frame, net, tile=cfg.tile, device="cpu", layers=names)
        kpcn_s = time.perf_counter() - t0
        k_max, k_mean = _sum_errors(sum(res.layers[n] for n in names), res.color)
        o = ("-", "-", "-")
        if oidn_available():
            t0 = time.perf_counter()
            guides = oidn_guides(frame)
            beauty = oidn_denoise(frame["color"], *guides)
            total = sum(oidn_denoise(frame[n], *guides) for n in names)
            oidn_s = time.perf_counter() - t0
            o_max, o_mean = _sum_errors(total, beauty)
            o = (f"{o_max:.2e}", f"{o_mean:.2e}", f"{oidn_s:.2f}")
        print(f"{scene:<16} {len(names):>6} {k_max:>10.2e} {k_mean:>10.2e} {kpcn_s:>8.2f} {o[0]:>10} {o[1]:>10} {o[2]:>8}")
    return 0
