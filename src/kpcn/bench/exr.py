"""``python -m kpcn.bench exr``: reading and writing a render's EXR with OpenEXR's thread pool against one thread.

Renders a frame once (every layer of the contract: 32 channels, ZIP), then, in a fresh spawned process per thread
count (the pool is process-global, :mod:`kpcn.io.exr_threads`), times :func:`kpcn.io.read_exr` and
:func:`kpcn.io.write_exr` of it; the baseline is ``KPCN_EXR_THREADS=0``, OpenEXR's own single thread, in the same run.
"""
from __future__ import annotations

import os
import statistics
import tempfile
import time
from dataclasses import dataclass, field

from ..config import parse_config
from .common import run_isolated


@dataclass
class ExrBenchConfig:
    """``python -m kpcn.bench exr`` settings (``--config``, ``--set`` or the flags)."""

    size: tuple[int, int] = field(default=(1920, 1080), metadata={"help": "width height of the rendered frame"})
    scene: str = field(default="random:3", metadata={"help": "scene to render"})
    spp: int = field(default=4, metadata={"help": "samples per pixel"})
    threads: list[int] = field(default_factory=lambda: [0], metadata={
        "help": "KPCN_EXR_THREADS values to time besides the default (0: OpenEXR's single thread, the baseline)"})
    repeats: int = field(default=5, metadata={"help": "timed reads and writes per thread count (after one untimed)"})
    timeout: float = 600.0


def _measure(path: str, threads: str | None, repeats: int) -> dict:
    """Runs in a fresh process: read and write ``path`` ``repeats`` times with ``KPCN_EXR_THREADS=threads``."""
    if threads is None:
        os.environ.pop("KPCN_EXR_THREADS", None)
    else:
        os.environ["KPCN_EXR_THREADS"] = threads
    import OpenEXR

    from kpcn.io import read_exr, write_exr

    frame = read_exr(path)  # untimed: the imports, the pool's start
    out = path + f".{os.getpid()}.exr"
    reads, writes = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        frame = read_exr(path)
        reads.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        write_exr(out, frame.layers, frame.meta)
        writes.append(time.perf_counter() - t0)
    os.remove(out)
    return {"status": "ok", "read_s": statistics.median(reads), "write_s": statistics.median(writes),
            "pool": OpenEXR.global_thread_count(), "channels": sum(a.shape[2] for a in frame.layers.values())}


def bench_exr(argv: list[str]) -> int:
    cfg = parse_config(ExrBenchConfig, argv, "python -m kpcn.bench exr", __doc__.split("\n\n")[0])
    from ..io import write_exr
    from ..render import render_frame

    w, h = cfg.size
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "frame.exr")
        frame = render_frame(cfg.scene, spp=cfg.spp, seed=0, resolution=(w, h))
        write_exr(path, frame.layers, frame.meta)
        size_mb = os.path.getsize(path) / 2**20
        runs = {"default": run_isolated(_measure, (path, None, cfg.repeats), cfg.timeout)}
        for n in sorted(set(cfg.threads)):
            runs[f"KPCN_EXR_THREADS={n}"] = run_isolated(_measure, (path, str(n), cfg.repeats), cfg.timeout)
    base = runs.get("KPCN_EXR_THREADS=0", {})
    channels = next((r["channels"] for r in runs.values() if r.get("status") == "ok"), "?")
    print(f"EXR read and write: {cfg.scene} at {w}x{h}, {cfg.spp} spp, {channels} channels, {size_mb:.0f} MB (ZIP); "
          f"median of {cfg.repeats} calls each, each thread count in a fresh process; {os.cpu_count()} CPUs")
    print(f"{'threads':<22} {'pool':>4} {'read s':>8} {'write s':>8} {'read ×':>7} {'write ×':>8}")
    for name, r in runs.items():
        if r.get("status") != "ok":
            print(f"{name:<22} {r.get('status')}")
            continue
        ratio = (lambda k: f"{r[k] / base[k]:.2f}" if base.get("status") == "ok" else "n/a")
        print(f"{name:<22} {r['pool']:>4} {r['read_s']:>8.3f} {r['write_s']:>8.3f} {ratio('read_s'):>7} "
              f"{ratio('write_s'):>8}")
    print("× : seconds against KPCN_EXR_THREADS=0 (OpenEXR's single thread) in this run")
    return 0 if all(r.get("status") == "ok" for r in runs.values()) else 1
