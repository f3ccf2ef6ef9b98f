"""``python -m kpcn.bench train``: training throughput (patches/s) per config.

Times full training steps (forward of every branch, L1 loss on every branch
target, backward, Adam step) on batches of ``patch``×``patch`` patches for each
config file, after ``--warmup`` steps, and prints patches/s and the ratio to the
first config, all in one run (``--precisions float32 bfloat16``: each config in both compute dtypes,
``train.precision``). Step time does not depend on pixel values, so the
batches are random tensors of the shapes the model's input spec builds.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field

from ..config import parse_config


@dataclass
class TrainBenchConfig:
    """``python -m kpcn.bench train`` settings (``--config``, ``--set`` or the flags)."""

    configs: list[str] = field(
        default_factory=lambda: ["configs/small.yaml", "configs/small_dpcn.yaml", "configs/small_unet.yaml",
                                 "configs/paper.yaml"],
        metadata={"help": "training configs whose models are timed; the first is the baseline"})
    batch: int = field(default=4, metadata={"help": "patches per step"})
    patch: int = field(default=65, metadata={"help": "patch side in pixels"})
    steps: int = field(default=3, metadata={"help": "timed steps (median)"})
    warmup: int = field(default=1, metadata={"help": "untimed steps first"})
    threads: int | None = field(default=None, metadata={"help": "torch threads (default: torch's)"})
    precisions: list[str] = field(default_factory=lambda: ["config"], metadata={
        "help": "compute dtype(s) of the hidden layers: config (each config's train.precision), float32, bfloat16; "
                "each config runs at each (rows labelled config@precision when more than one)"})


def bench_train(argv: list[str]) -> int:
    args = parse_config(TrainBenchConfig, argv, "python -m kpcn.bench train", __doc__.split("\n\n")[0])

    import torch

    from ..config import load_config
    from ..losses import l1
    from ..models.cost import macs_per_pixel
    from ..train import build_model
    from ..train_config import RunConfig

    if args.threads:
        torch.set_num_threads(args.threads)
    b, s = args.batch, args.patch
    print(f"training throughput: batch {b} of {s}x{s}, {torch.get_num_threads()} threads, median of {args.steps} steps")
    from ..constants import PRECISIONS

    choices = ("config", *PRECISIONS)
    bad = [p for p in args.precisions if p not in choices]
    if bad or not args.precisions:
        print(f"python -m kpcn.bench train: precisions: expected {', '.join(choices[:-1])} or {choices[-1]}, "
              f"got {bad or '[]'}")
        return 2
    runs = [(path, p) for path in args.configs for p in args.precisions]
    w = max([28] + [len(f"{path}@{p}") + 1 for path, p in runs])
    print(f"{'config':<{w}} {'inputs':<20} {'params':>9} {'kMAC/px':>8} {'s/step':>8} {'patches/s':>10} {'vs first':>9}")
    base = None
    for path, precision in runs:
        cfg = load_config(RunConfig, path)
        torch.manual_seed(0)
        model = build_model(cfg)
        precision = cfg.train.precision if precision == "config" else precision
        model.set_compute_dtype(precision)
        label = f"{path}@{precision}" if len(args.precisions) > 1 else path
        spec = model.input_spec
        # the batch the model's input spec builds: one tensor per branch, the albedo and a target per branch
        batch = {br: torch.rand(b, spec.channels, s, s) for br in spec.branches}
        batch["albedo"] = torch.rand(b, 3, s, s)
        if model.reads_normal:
            batch["normal"] = torch.rand(b, 3, s, s) * 2 - 1
        targets = {br: torch.rand(b, 3, s, s) for br in spec.branches}
        opt = torch.optim.Adam(model.parameters(), lr=1e-4)
        times = []
        for i in range(args.warmup + args.steps):
            t0 = time.perf_counter()
            out = model(batch)
            loss = sum(l1(out[br], targets[br]) for br in spec.branches)
            opt.zero_grad()
            loss.backward()
            opt.step()
            if i >= args.warmup:
                times.append(time.perf_counter() - t0)
        t = statistics.median(times)
        rate = b / t
        base = base or rate
        n = sum(p.numel() for p in model.parameters())
        macs = macs_per_pixel(model) / 1e3
        print(f"{label:<{w}} {spec.name:<20} {n:>9} {macs:>8.1f} {t:>8.3f} {rate:>10.2f} {rate / base:>8.3f}x")
    return 0
