"""``python -m kpcn.bench kernel``: the kernel-apply op against the ``F.unfold`` reference.

``kernel``: the per-pixel kernel application (:func:`kpcn.ops.kernel_apply`,
shift loop) against the ``F.unfold`` reference, forward and forward+backward.

How memory is measured (``kernel``): every (implementation, size, pass)
configuration runs in a fresh process (``multiprocessing`` "spawn"), which
allocates its inputs, warms up on a small 64x64 input (OpenMP threads, autograd
engine), then resets the kernel's peak-RSS counter (writing ``5`` to
``/proc/self/clear_refs`` resets ``VmHWM``) and runs the operation once;
the reported memory is ``VmHWM - VmRSS`` (peak resident memory during the run
minus resident memory before it), i.e. what the operation itself needed on
top of its inputs, including its output and, for forward+backward, the input
gradients (the weights gradient alone is ``B*k*k*H*W*4`` bytes). Where
``clear_refs`` is not writable it falls back to ``ru_maxrss`` minus the RSS
before the run, which can over-report if importing torch peaked higher (the
output says which method was used). Python's ``tracemalloc`` does not see
torch's allocations, hence RSS. Times are wall-clock over ``--repeats`` runs
after that first (measured) run; the table gives the median and the minimum.
The forward pass runs under ``torch.no_grad()`` (inference); forward+backward
runs with gradients for both the image and the weights and a random output
gradient.

Timing caveat: the shift loop issues ``k*k`` small element-wise ops (441 for
k = 21), each an OpenMP parallel region when the tensor is large enough. When
other processes keep the cores busy, every region waits for a descheduled
thread, and 2-thread timings can be 10-50x worse and very noisy; ``--threads 1``
gives stable numbers on a loaded machine.
"""


import json
import multiprocessing as mp
import os
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field

from ..config import ConfigError, parse_config, to_dict


from .common import _fmt_mb, _fmt_s, _mem_available_bytes, _peak_rss_kb, _proc_status_kb, _ratio, _reset_peak_rss


def _kernel_worker(impl: str, size: int, mode: str, k: int, channels: int, batch: int, repeats: int, threads: int | None) -> dict:
    """Runs in a fresh spawned process: one (impl, size, mode) configuration."""

    import torch

    from kpcn.ops import kernel_apply, kernel_apply_unfold

    if threads:
        torch.set_num_threads(threads)
    fn = kernel_apply if impl == "shift-loop" else kernel_apply_unfold
    g = torch.Generator().manual_seed(0)
    image = torch.rand(batch, channels, size, size, generator=g)
    weights = torch.rand(batch, k * k, size, size, generator=g)
    weights /= weights.sum(dim=1, keepdim=True)
    backward = mode == "fwd+bwd"
    grad_out = torch.randn(batch, channels, size, size, generator=g) if backward else None
    if backward:
        image.requires_grad_(True)
        weights.requires_grad_(True)

    def run_once() -> None:
        if backward:
            out = fn(image, weights, k)
            out.backward(grad_out)
            del out
            image.grad = None
            weights.grad = None
        else:
            with torch.no_grad():
                out = fn(image, weights, k)
            del out

    # warm up lazily initialised machinery (OpenMP threads, autograd engine) on a small input first,
    # so the measured run sees only the operation's own allocations
    wi = torch.rand(batch, channels, 64, 64, requires_grad=backward)
    ww = torch.rand(batch, k * k, 64, 64, requires_grad=backward)
    if backward:
        wo = fn(wi, ww, k)
        wo.backward(torch.randn_like(wo))  # an explicit gradient, like the measured run
        del wo
    else:
        with torch.no_grad():
            fn(wi, ww, k)
    del wi, ww

    rss_before_kb = _proc_status_kb("VmRSS")
    reset_ok = _reset_peak_rss()
    t0 = time.perf_counter()
    run_once()
    first_s = time.perf_counter() - t0
    peak_kb, method = _peak_rss_kb(reset_ok)
    mem_mb = (peak_kb - (rss_before_kb or 0)) / 1024.0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run_once()
        times.append(time.perf_counter() - t0)
    return {
        "impl": impl,
        "size": size,
        "mode": mode,
        "status": "ok",
        "first_s": first_s,
        "median_s": statistics.median(times) if times else first_s,
        "min_s": min(times) if times else first_s,
        "times_s": times,
        "mem_mb": mem_mb,
        "inputs_mb": (rss_before_kb or 0) / 1024.0,
        "mem_method": method,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
    }


def _unfold_bytes_needed(size: int, k: int, channels: int, batch: int, mode: str) -> int:
    # forward: the (B, C*k*k, H*W) columns plus an equally large product;
    # backward roughly doubles that again (gradient of the product and of the columns).
    cols = batch * channels * k * k * size * size * 4
    weights = batch * k * k * size * size * 4
    return 2 * cols + 2 * weights if mode == "fwd" else 4 * cols + 3 * weights


def _run_config(impl: str, size: int, mode: str, args: "KernelBenchConfig") -> dict:
    ctx = mp.get_context("spawn")
    try:
        with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as ex:
            fut = ex.submit(
                _kernel_worker, impl, size, mode, args.k, args.channels, args.batch, args.repeats, args.threads
            )
            return fut.result()
    except BrokenProcessPool:
        return {"impl": impl, "size": size, "mode": mode, "status": "failed (worker died: out of memory?)"}



@dataclass
class KernelBenchConfig:
    """``python -m kpcn.bench kernel`` settings (``--config``, ``--set`` or the flags)."""

    sizes: list[int] = field(default_factory=lambda: [256, 1024], metadata={"help": "square image sizes"})
    k: int = field(default=21, metadata={"help": "kernel size"})
    channels: int = field(default=3, metadata={"help": "image channels C"})
    batch: int = field(default=1, metadata={"help": "batch size B"})
    repeats: int = field(default=3, metadata={"help": "timed runs after the first, measured one"})
    threads: int | None = field(default=None, metadata={"help": "torch threads in the workers (default: torch's)"})
    skip_unfold_above: int | None = field(default=None, metadata={
        "help": "skip the unfold reference for sizes > N (default: run it where its estimated memory fits in "
                "80%% of MemAvailable)"})
    modes: list[str] = field(default_factory=lambda: ["fwd", "fwd+bwd"], metadata={"help": "fwd and/or fwd+bwd"})
    json: str | None = field(default=None, metadata={"help": "also write the raw results as JSON to this path"})

    def __post_init__(self) -> None:
        if self.k < 1 or self.k % 2 == 0:
            raise ConfigError(f"k: must be a positive odd integer, got {self.k}")
        bad = [m for m in self.modes if m not in ("fwd", "fwd+bwd")]
        if bad:
            raise ConfigError(f"modes: unknown mode(s) {bad}; valid: fwd, fwd+bwd")


def bench_kernel(argv: list[str]) -> int:
    """``python -m kpcn.bench kernel``: shift-loop kernel_apply vs the F.unfold reference."""
    args = parse_config(KernelBenchConfig, argv, "python -m kpcn.bench kernel",
                        "Time and peak memory of kernel_apply (shift loop) vs the F.unfold reference; each "
                        "configuration in a fresh subprocess (see kpcn.bench docstring for the memory method).")

    results: dict[tuple[str, int, str], dict] = {}
    for size in args.sizes:
        for mode in args.modes:
            for impl in ("shift-loop", "unfold"):
                skip = None
                if impl == "unfold":
                    if args.skip_unfold_above is not None and size > args.skip_unfold_above:
                        skip = f"skipped (--skip-unfold-above {args.skip_unfold_above})"
                    elif args.skip_unfold_above is None:
                        need = _unfold_bytes_needed(size, args.k, args.channels, args.batch, mode)
                        avail = _mem_available_bytes()
                        if avail is not None and need > 0.8 * avail:
                            skip = f"skipped (needs ~{need / 2**30:.1f} GiB, {avail / 2**30:.1f} GiB available)"
                if skip:
                    r = {"impl": impl, "size": size, "mode": mode, "status": skip}
                else:
                    print(f"running {impl:10s} {mode:7s} {size}x{size} ...", file=sys.stderr, flush=True)
                    r = _run_config(impl, size, mode, args)
                results[(impl, size, mode)] = r

    ok = [r for r in results.values() if r.get("status") == "ok"]
    threads = ok[0]["threads"] if ok else "?"
    torch_version = ok[0]["torch"] if ok else "?"
    method = ok[0]["mem_method"] if ok else "?"
    print(
        f"\nkernel-apply benchmark: B={args.batch} C={args.channels} k={args.k} float32, "
        f"torch {torch_version}, {threads} threads, {os.cpu_count()} CPUs, repeats={args.repeats}"
    )
    print(f"memory = peak RSS during one run minus RSS before it [{method}]; time = median (min) seconds")
    header = f"{'size':>6}  {'impl':<10}  {'pass':<7}  {'time s':>28}  {'peak MB':>8}"
    print(header)
    print("-" * len(header))
    for size in args.sizes:
        for mode in args.modes:
            for impl in ("shift-loop", "unfold"):
                r = results[(impl, size, mode)]
                print(f"{size:>6}  {impl:<10}  {mode:<7}  {_fmt_s(r):>28}  {_fmt_mb(r):>8}")
    print("\nratios unfold / shift-loop (same run):")
    print(f"{'size':>6}  {'pass':<7}  {'time':>7}  {'memory':>7}")
    for size in args.sizes:
        for mode in args.modes:
            a, b = results[("unfold", size, mode)], results[("shift-loop", size, mode)]
            print(f"{size:>6}  {mode:<7}  {_ratio(a, b, 'median_s'):>7}  {_ratio(a, b, 'mem_mb'):>7}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": to_dict(args), "results": list(results.values())}, f, indent=2)
    return 0


