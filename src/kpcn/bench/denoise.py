"""``python -m kpcn.bench denoise``: whole-frame denoising time and memory against OIDN.

``denoise``: whole-frame :func:`kpcn.inference.denoise` (tiled) for model configs
(``configs/small.yaml``, ``configs/paper.yaml``; random-init weights) against
Intel OIDN (``pyoidn``) on the same frames rendered with Mitsuba at each size,
with kpcn/OIDN ratios from the same run. Memory is measured as for ``kernel``
(fresh process per configuration, after reading the frame, building the model
and a 64x64 warm-up). ``denoise --skip`` times the same model with and without
skipping what a scene does not need (see :mod:`kpcn.inference.pipeline`).
"""


import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import dataclass, field

from ..config import parse_config, to_dict
from .common import run_isolated, _peak_rss_kb, _proc_status_kb, _ratio, _reset_peak_rss
from .models import _bench_model, _denoise_model_spec

# --------------------------------------------------------------------------- denoise
#
# ``denoise``: whole-frame denoising with kpcn.denoise (tiled) for model configs
# (configs/<name>.yaml, random-init weights: the time does not depend on the
# values) against Intel Open Image Denoise (pyoidn) on the same rendered frames.
# Memory method: as for ``kernel`` -- every (model, size) runs in a fresh
# spawned process that reads the frame, builds the model and warms up on a
# 64x64 crop, then resets the peak-RSS counter and denoises once; reported
# memory is peak RSS during that call minus RSS before it (what denoising needed
# on top of the loaded frame and the model's weights, the output included).
# ``denoise --skip``: the same model with and without leaving out what a scene
# does not need (zero branches, zero KPCN tiles, no-hit converged tiles), timed
# alternately in one process.

def _parse_size(text: str) -> tuple[int, int]:
    """``"256"`` -> (256, 256); ``"1920x1080"`` -> (1920, 1080), as (width, height)."""
    parts = text.lower().split("x")
    try:
        if len(parts) == 1:
            return int(parts[0]), int(parts[0])
        if len(parts) == 2:
            return int(parts[0]), int(parts[1])
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"size must be N or WxH, got {text!r}")


def _denoise_measure(impl: str, path: str, model_name: str, model_kw: dict, tile: int, threads: int | None, repeats: int,
                     rows: bool = True, precision: str = "auto", kernels: str = "native") -> dict:
    import gc

    os.environ["KPCN_NATIVE"] = "1" if kernels == "native" else "0"  # this spawned process's own environment

    import numpy as np
    import torch

    from kpcn.io import read_exr

    if threads:
        torch.set_num_threads(threads)
    frame = read_exr(path)
    h, w = frame.shape
    extra: dict = {}
    if impl in ("oidn", "oidn_prefiltered"):
        import pyoidn

        from kpcn.baselines import oidn_denoise, oidn_prefilter_threads

        if threads:
            extra["oidn_threads"] = _oidn_set_threads(threads)
            if impl == "oidn_prefiltered":
                oidn_prefilter_threads(threads)
        color = np.ascontiguousarray(np.maximum(frame["color"], 0.0))
        albedo = np.ascontiguousarray(np.clip(frame["albedo"], 0.0, 1.0))  # OIDN wants albedo in [0, 1]
        normal = np.ascontiguousarray(frame["normal"])

        def call(c, a, n):  # OIDN as the report calls it; prefiltered: its guides denoised by its own filters first
            if impl == "oidn":
                return pyoidn.denoise(c, a, n, hdr=True, quality="high")
            return oidn_denoise(c, a, n, prefilter=True)

        def run():
            return call(color, albedo, normal)

        s = (slice(0, min(h, 64)), slice(0, min(w, 64)))
        call(color[s].copy(), albedo[s].copy(), normal[s].copy())
    else:
        from kpcn.inference import denoise_result

        model = _bench_model(model_name, model_kw)
        from kpcn.models.cost import macs_per_pixel

        extra["macs_per_px"] = macs_per_pixel(model)
        from kpcn.ops import native

        extra["native"] = native.status()

        def run():
            r = denoise_result(frame, model, tile=tile, device="cpu", rows=rows, precision=precision)
            extra.update(stats=r.stats.summary(), halo=r.stats.halo, tiles=r.stats.tiles, precision=r.stats.precision)
            return r.color

        denoise_result(frame.crop(0, min(h, 64), 0, min(w, 64)), model, tile=tile, device="cpu", rows=rows,
                       precision=precision)
    gc.collect()
    rss_before_kb = _proc_status_kb("VmRSS")
    reset_ok = _reset_peak_rss()
    c0, t0 = time.process_time(), time.perf_counter()
    out = run()
    first_s = time.perf_counter() - t0
    cpu = [time.process_time() - c0]
    peak_kb, method = _peak_rss_kb(reset_ok)
    del out
    times = [first_s]
    for _ in range(max(0, repeats - 1)):
        c0, t0 = time.process_time(), time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {
        "status": "ok",
        "cpu_s": statistics.median(cpu),
        "first_s": first_s,
        "median_s": statistics.median(times),
        "min_s": min(times),
        "times_s": times,
        "mem_mb": (peak_kb - (rss_before_kb or 0)) / 1024.0,
        "mem_method": method,
        "threads": torch.get_num_threads(),
        **extra,
    }


def _loadavg() -> str:
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def _oidn_set_threads(n: int) -> str:
    """Give pyoidn's shared CPU device ``n`` threads (OIDN's ``numThreads``) before its first use.

    ``pyoidn.denoise`` has no thread option, so this creates the device it would
    create, sets ``numThreads`` and registers it in pyoidn's resource cache (a
    private structure: if that changes, OIDN keeps its default and this says so).
    """
    try:
        import importlib

        mod = importlib.import_module("pyoidn.denoise")
        from pyoidn.device import Device

        dev = Device()
        dev.set_int("numThreads", int(n))
        dev.commit()
        mod._denoiser._resources[("cpu", 0, 0)] = mod._DeviceResources(dev, None)
        return str(n)
    except Exception as exc:  # pragma: no cover - depends on pyoidn internals
        return f"default (could not set: {exc})"


def _run_denoise_config(impl, path, model_name, model_kw, tile, threads, repeats, timeout, rows=True,
                        precision="auto", kernels="native") -> dict:
    return run_isolated(_denoise_measure, (impl, path, model_name, model_kw, tile, threads, repeats, rows, precision,
                                           kernels), timeout)


def _merge_rounds(rs: list[dict]) -> dict:
    """One configuration's measurements over ``--rounds``: the median of every timed call, the median CPU
    seconds, the largest memory; the first failed round's status if any failed."""
    bad = [r for r in rs if r.get("status") != "ok"]
    if bad or len(rs) == 1:
        return bad[0] if bad else rs[0]
    times = [t for r in rs for t in r["times_s"]]
    return {**rs[0], "times_s": times, "median_s": statistics.median(times), "min_s": min(times),
            "cpu_s": statistics.median(r["cpu_s"] for r in rs), "mem_mb": max(r["mem_mb"] for r in rs),
            "rounds": len(rs), "round_medians_s": [r["median_s"] for r in rs]}


def _render_bench_frame(scene: str, size: tuple[int, int], spp: int, seed: int, path: str) -> float:
    from kpcn.io import write_exr
    from kpcn.render import render_frame

    t0 = time.perf_counter()
    frame = render_frame(scene, spp=spp, seed=seed, resolution=size)
    write_exr(path, frame.layers, frame.meta)
    return time.perf_counter() - t0


@dataclass
class DenoiseBenchConfig:
    """``python -m kpcn.bench denoise`` settings (``--config``, ``--set`` or the flags)."""

    sizes: list[str] | None = field(default=None, metadata={
        "help": "frame sizes, N or WxH (default: 256 1024 1920x1080; --skip: 256)"})
    models: list[str] = field(default_factory=lambda: ["small", "paper"], metadata={
        "help": "configs/<name>.yaml model configs, YAML paths, registry:key=value,... "
                "(e.g. kpcn:layers=5,width=32,conv_size=5,kernel_size=11; random-init weights), or shipped "
                "weights by name (unet_kpcn:wide); --skip: the first"})
    oidn: bool = field(default=True, metadata={"help": "leave out Intel OIDN"})
    oidn_prefiltered: bool = field(default=False, metadata={
        "help": "also time OIDN with its albedo and normal prefiltered by its own filters (Blender's Accurate mode, "
                "the report's oidn_prefiltered)"})
    rows: bool = field(default=True, metadata={
        "help": "run whole frames at once, not a band of rows at a time (models with row streams; the A/B baseline)"})
    precisions: list[str] = field(default_factory=lambda: ["auto"], metadata={
        "help": "kpcn's precision(s): auto, float32, bfloat16; each model runs at each (rows labelled model@precision "
                "when more than one)"})
    kernels: list[str] = field(default_factory=lambda: ["native"], metadata={
        "help": "kpcn's element-wise kernels: native (kpcn.ops.native, compiled for this CPU where a C compiler is; "
                "else the PyTorch paths), pytorch (KPCN_NATIVE=0); both: each model runs with each (rows labelled "
                "model+kernels), the A/B of the native kernels in one run"})
    tile: int | None = field(default=None, metadata={
        "help": "kpcn tile size (default: auto, the whole frame up to 1920x1080, or 4096x4096 for a model that runs "
                "in row bands; --skip: 64)"})
    scene: str = field(default="random:3", metadata={"help": "scene to render"})
    spp: int = field(default=4, metadata={"help": "samples per pixel of the rendered frames"})
    seed: int = 0
    repeats: int | None = field(default=None, metadata={
        "help": "runs per configuration; the first is the measured-memory one (default 1; --skip: 3)"})
    rounds: int = field(default=1, metadata={
        "help": "run every configuration this many times, in turn (A, B, OIDN, A, B, OIDN, ...), and report the "
                "median over all its timed calls: a slow spell of the machine then falls on every configuration, "
                "not on whichever ran during it (the first after a render or a larger frame ran up to 10 %% "
                "slower on the seventeenth session's machine)"})
    timeout: float = field(default=300.0, metadata={"help": "seconds per configuration before it is stopped"})
    threads: int | None = field(default=None, metadata={"help": "torch threads (default: torch's)"})
    frames_dir: str | None = field(default=None, metadata={"help": "keep the rendered frames here (default: a temporary folder)"})
    json: str | None = field(default=None, metadata={"help": "also write the raw results as JSON to this path"})
    skip: bool = field(default=False, metadata={"help": "measure the time saved by skipping (see above)"})
    scenes: list[str] = field(
        default_factory=lambda: ["test:diffuse_box", "test:glass", "test:envmap_open", "test:no_hit"],
        metadata={"help": "--skip: scenes to render"})
    zero_specular: bool = field(default=False, metadata={
        "help": "--skip: also run each scene with its specular buffers zeroed (a synthetic no-specular frame)"})


def bench_denoise(argv: list[str]) -> int:
    """``python -m kpcn.bench denoise``: kpcn.denoise (small / paper configs) vs OIDN; ``--skip``: time saved by skipping."""
    import tempfile

    cfg = parse_config(
        DenoiseBenchConfig, argv, "python -m kpcn.bench denoise",
        "Seconds and peak memory of kpcn.denoise for model configs (random-init weights) against "
        "Intel OIDN on the same rendered frames; each configuration in a fresh subprocess (memory = peak RSS "
        "during the call minus RSS before it). With --skip: the time saved by leaving out zero branches, zero "
        "tiles and no-hit tiles (full vs skip in the same process).",
    )
    args = argparse.Namespace(**to_dict(cfg))
    args.no_oidn = not cfg.oidn
    try:
        args.sizes = [_parse_size(x) for x in cfg.sizes] if cfg.sizes else None
    except argparse.ArgumentTypeError as exc:
        print(f"python -m kpcn.bench denoise: sizes: {exc}", file=sys.stderr)
        return 2
    args.tile_given = args.tile is not None
    if args.skip:
        args.sizes = args.sizes or [(256, 256)]
        args.repeats = args.repeats or 3
        from .skip import bench_denoise_skip

        return bench_denoise_skip(args)
    args.repeats = args.repeats or 1
    if args.rounds < 1:
        print(f"python -m kpcn.bench denoise: --rounds must be >= 1, got {args.rounds}", file=sys.stderr)
        return 2
    args.sizes = args.sizes or [(256, 256), (1024, 1024), (1920, 1080)]
    tile = args.tile if args.tile_given else "auto"
    specs = {name: _denoise_model_spec(name) for name in args.models}
    from kpcn.inference.precision import PRECISIONS

    bad = [p for p in args.precisions if p not in PRECISIONS]
    if bad or not args.precisions:
        print(f"python -m kpcn.bench denoise: precisions: expected {', '.join(PRECISIONS[:-1])} or {PRECISIONS[-1]}, "
              f"got {bad or '[]'}", file=sys.stderr)
        return 2
    bad = [k for k in args.kernels if k not in ("native", "pytorch")]
    if bad or not args.kernels:
        print(f"python -m kpcn.bench denoise: kernels: expected native or pytorch, got {bad or '[]'}", file=sys.stderr)
        return 2
    many, both = len(args.precisions) > 1, len(args.kernels) > 1
    labels = [((f"{name}@{p}" if many else name) + (f"+{k}" if both else ""), name, p, k)
              for name in args.models for p in args.precisions for k in args.kernels]

    tmp = None
    frames_dir = args.frames_dir
    if frames_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="kpcn-bench-denoise-")
        frames_dir = tmp.name
    os.makedirs(frames_dir, exist_ok=True)
    results: list[dict] = []
    try:
        for w, h in args.sizes:
            path = os.path.join(frames_dir, f"{args.scene.replace(':', '_')}_{w}x{h}_{args.spp}spp.exr")
            if not os.path.exists(path):
                print(f"rendering {args.scene} {w}x{h} at {args.spp} spp ...", file=sys.stderr, flush=True)
                secs = _render_bench_frame(args.scene, (w, h), args.spp, args.seed, path)
                print(f"  rendered in {secs:.1f} s", file=sys.stderr, flush=True)
            jobs = [("kpcn", label, name, p, k) for label, name, p, k in labels] + \
                ([] if args.no_oidn else [("oidn", "oidn", "oidn", "auto", "native")]) + \
                ([("oidn_prefiltered",) * 3 + ("auto", "native")] if args.oidn_prefiltered else [])
            rounds: dict[str, list[dict]] = {name: [] for _, name, _, _, _ in jobs}
            for _ in range(args.rounds):  # every configuration once a round, in the same order
                for impl, name, model, precision, kernels in jobs:
                    model_name, kw = (specs[model][0], specs[model][1]) if impl == "kpcn" else ("", {})
                    print(f"running {name:>8} {w}x{h} ...", file=sys.stderr, flush=True)
                    t0 = time.perf_counter()
                    r = _run_denoise_config(impl, path, model_name, kw, tile, args.threads, args.repeats, args.timeout,
                                            args.rows, precision, kernels)
                    r.update(impl=impl, model=name, size=f"{w}x{h}", wall_s=time.perf_counter() - t0)
                    print(f"  {r.get('status')}: {r.get('median_s', float('nan')):.2f} s", file=sys.stderr, flush=True)
                    rounds[name].append(r)
            results += [_merge_rounds(rs) for rs in rounds.values()]
    finally:
        if tmp is not None:
            tmp.cleanup()

    ok = [r for r in results if r.get("status") == "ok"]
    print(f"\ndenoise benchmark: scene {args.scene} at {args.spp} spp (rendered with Mitsuba at each size), kpcn tile {tile}, "
          f"configs with random-init weights, {'row bands' if args.rows else 'no row bands'}, {ok[0]['threads'] if ok else '?'} torch threads, {os.cpu_count()} CPUs, repeats={args.repeats}"
          + (f" x {args.rounds} rounds (each configuration in turn; time = median of all its calls)" if args.rounds > 1 else ""))
    for name in args.models:
        model_name, kw, origin = specs[name]
        print(f"  {name}: {origin}" if kw is None else f"  {name}: {model_name} {kw} (from {origin})")
    print(f"memory = peak RSS during one call minus RSS before it [{ok[0]['mem_method'] if ok else '?'}]; "
          "time = median wall seconds (frame already in memory, model built); cpu = process CPU seconds "
          "(less sensitive to other load on the machine, but it counts OpenMP spin-waiting)")
    print(f"load average (1, 5, 15 min) at the end: {_loadavg()}")
    for status in sorted({r["native"] for r in ok if "native" in r}):
        print(f"native kernels: {status}")
    mw = max([8] + [len(n) for n, _, _, _ in labels] + [len(r["model"]) for r in results])
    header = f"{'size':>10}  {'model':<{mw}}  {'time s':>9}  {'cpu s':>8}  {'peak MB':>8}  {'kMAC/px':>8}  notes"
    print(header)
    print("-" * len(header))
    for r in results:
        t = f"{r['median_s']:.2f}" if r.get("status") == "ok" else "-"
        m = f"{r['mem_mb']:.0f}" if r.get("status") == "ok" else "-"
        c = f"{r['cpu_s']:.2f}" if r.get("status") == "ok" else "-"
        note = r.get("stats", "") if r.get("status") == "ok" else r.get("status", "")
        macs = f"{r['macs_per_px'] / 1e3:.1f}" if "macs_per_px" in r else "-"
        print(f"{r['size']:>10}  {r['model']:<{mw}}  {t:>9}  {c:>8}  {m:>8}  {macs:>8}  {note}")
    if not args.no_oidn:
        print("\nratios kpcn / oidn (same run):")
        print(f"{'size':>10}  {'model':<{mw}}  {'time':>8}  {'memory':>8}")
        by = {(r["size"], r["model"]): r for r in results}
        for w, h in args.sizes:
            o = by.get((f"{w}x{h}", "oidn"), {})
            for name, _, _, _ in labels:
                k = by.get((f"{w}x{h}", name), {})
                print(f"{f'{w}x{h}':>10}  {name:<{mw}}  {_ratio(k, o, 'median_s'):>8}  {_ratio(k, o, 'mem_mb'):>8}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": {k: v for k, v in vars(args).items()}, "results": results}, f, indent=2, default=str)
    return 0


