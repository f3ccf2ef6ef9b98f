"""``python -m kpcn.bench data``: training-patch throughput and memory, frames in memory vs the patch store.

Iterates the training DataLoader (shuffled patches, ``--batch`` a batch, one
epoch or ``--batches``) over the same data set folder three ways, each in a
fresh process: the frames held in memory as float32 tensors (``data.store:
none``, the loader before the store), and the patch store (:mod:`kpcn.store`)
read in the main process and with ``--workers`` DataLoader workers. Prints
patches/s with the ratio to the in-memory loader, the setup time (reading the
frames, or checking the store), and memory: the peak RSS of the process, its
anonymous RSS after the epoch (what cannot be given back: RSS also counts the
store's pages mapped from the page cache) and the largest worker's peak RSS.
The store is prepared first (only missing or stale frames are preprocessed)
and its pages are then warm in the page cache.
"""
from __future__ import annotations

import gc
import json
import multiprocessing as mp
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..config import parse_config
from .common import _proc_status_kb, run_isolated


@dataclass
class DataBenchConfig:
    """``python -m kpcn.bench data`` settings (``--config``, ``--set`` or the flags)."""

    root: str | None = field(default=None, metadata={
        "help": "data set folder (python -m kpcn.render dataset); default: a small one rendered into a temporary folder"})
    store: str | None = field(default=None, metadata={
        "help": "patch store folder (default: <root>/.store/<spec>, where training's data.store: auto puts it)"})
    spec: str = field(default="kpcn_split", metadata={"help": "input spec whose tensors are built"})
    spp: list[int] | None = field(default=None, metadata={"help": "input spp to use (default: all)"})
    workers: int = field(default=2, metadata={"help": "DataLoader workers of the third loader"})
    batch: int = field(default=16, metadata={"help": "patches per batch"})
    patch: int = field(default=65, metadata={"help": "patch side in pixels"})
    batches: int = field(default=128, metadata={
        "help": "timed batches per loader (epochs are started as training does: resample, a new loader)"})
    patches_per_frame: int | None = field(default=None, metadata={
        "help": "patches per frame (default: the paper's 400 per 1280x720; 32 for the rendered data set)"})
    sampling: str = field(default="importance", metadata={"help": "importance or uniform"})
    threads: int = field(default=1, metadata={"help": "torch threads of the measuring process"})
    timeout: float = field(default=600.0, metadata={"help": "seconds per measurement before it is stopped"})
    json: str | None = field(default=None, metadata={"help": "also write the raw results as JSON to this path"})
    # the default data set, rendered when no --root is given
    scenes: int = field(default=4, metadata={"help": "default data set: procedural scenes"})
    resolution: int = field(default=128, metadata={"help": "default data set: frame side in pixels"})


def _mb(kb) -> float | None:
    return None if kb is None else kb / 1024.0


def _measure(kind: str, root: str, store: str, spec: str, spp, workers: int, batch: int, patch: int,
             n_batches: int, per_frame: int | None, sampling: str, threads: int, start_method: str) -> dict:
    """One loader in this (fresh) process: setup seconds, patches/s and memory.

    ``start_method``: how the workers start, as in a training process (this process was spawned,
    and would spawn its workers: fresh interpreters that import torch, every epoch).
    """
    import resource

    import torch
    from torch.utils.data import DataLoader, RandomSampler

    from ..data import PatchDataset, read_manifest
    from ..store import prepare

    torch.set_num_threads(threads)
    rss0 = _proc_status_kb("VmRSS")
    t0 = time.perf_counter()
    pairs = read_manifest(root, spp)
    if kind == "build":
        prepared = prepare(pairs, spec, store)
        sizes = sum(os.path.getsize(e.path / f) for e in prepared.entries
                    for f in [g["file"] for g in e.groups.values()] + ([e.importance] if e.importance else []))
        tensors = sum(e.shape[0] * e.shape[1] * sum(e.channels.values()) * 4 for e in prepared.entries)
        return {"status": "ok", "frames": len(pairs), "built": len(prepared.built), "seconds": time.perf_counter() - t0,
                "store_mb": sizes / 2**20, "float32_mb": tensors / 2**20, "peak_mb": _mb(_proc_status_kb("VmHWM"))}
    ds = PatchDataset(pairs, patch, per_frame, sampling, seed=0, spec=spec, store=None if kind == "memory" else store)
    setup = time.perf_counter() - t0
    if len(ds) < batch:
        raise ValueError(f"{len(ds)} patches an epoch, fewer than a batch of {batch}: lower --batch or raise "
                         f"--patches-per-frame")
    n = done = epoch = 0
    t1 = time.perf_counter()
    while done < n_batches:  # as training does: new positions and a new loader each epoch
        ds.resample(epoch)
        sampler = RandomSampler(ds, generator=torch.Generator().manual_seed(epoch))
        loader = DataLoader(ds, batch_size=batch, sampler=sampler, drop_last=True, num_workers=workers,
                            persistent_workers=False, multiprocessing_context=start_method if workers else None)
        for b in loader:
            n += b["albedo"].shape[0]
            done += 1
            if done >= n_batches:
                break
        epoch += 1
    seconds = time.perf_counter() - t1
    anon, filed = _proc_status_kb("RssAnon"), _proc_status_kb("RssFile")
    del loader, b
    gc.collect()  # the workers are joined: their peak RSS is in RUSAGE_CHILDREN
    child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss if workers else None
    return {"status": "ok", "frames": len(pairs), "patches": n, "seconds": seconds, "patches_per_s": n / seconds,
            "setup_s": setup, "rss_before_mb": _mb(rss0), "peak_mb": _mb(_proc_status_kb("VmHWM")),
            "anon_mb": _mb(anon), "file_mb": _mb(filed), "worker_peak_mb": _mb(child), "epochs": epoch}


def _run(timeout: float, *args) -> dict:
    """:func:`_measure` in a fresh spawned process (its memory is its own), stopped after ``timeout`` s."""
    return run_isolated(_measure, args, timeout)


def _fmt(v, spec: str = ".0f") -> str:
    return "-" if v is None else format(v, spec)


def bench_data(argv: list[str]) -> int:
    cfg = parse_config(DataBenchConfig, argv, "python -m kpcn.bench data", __doc__.split("\n\n")[0])
    from ..store import default_store_dir

    tmp = None
    root = cfg.root
    try:
        if root is None:
            from ..render import render_dataset

            tmp = tempfile.TemporaryDirectory(prefix="kpcn-bench-data-")
            root = tmp.name
            r = cfg.resolution
            print(f"rendering {cfg.scenes} scenes at {r}x{r}, 4 and 8 spp into {root} ...", file=sys.stderr, flush=True)
            render_dataset(root, n_scenes=cfg.scenes, spp_list=(4, 8), ref_spp=64, resolution=(r, r), first_seed=0,
                           progress=False)
        store = str(cfg.store or default_store_dir(root, cfg.spec))
        common = (root, store, cfg.spec, cfg.spp)
        per_frame = cfg.patches_per_frame or (32 if tmp is not None else None)
        loader = (cfg.batch, cfg.patch, cfg.batches, per_frame, cfg.sampling, cfg.threads, mp.get_start_method())
        print("preparing the patch store ...", file=sys.stderr, flush=True)
        build = _run(cfg.timeout, "build", *common, 0, *loader)
        results = []
        for kind, workers, label in (("memory", 0, "in memory (before), 0 workers"),
                                     ("store", 0, "store, 0 workers"),
                                     ("store", cfg.workers, f"store, {cfg.workers} workers")):
            print(f"timing {label} ...", file=sys.stderr, flush=True)
            r = _run(cfg.timeout, kind, *common, workers, *loader)
            r.update(loader=label, kind=kind, workers=workers)
            results.append(r)
    finally:
        if tmp is not None:
            tmp.cleanup()

    print(f"\ndata loader benchmark: {root}{' (rendered, removed)' if tmp else ''}, spec {cfg.spec}, "
          f"spp {' '.join(map(str, cfg.spp)) if cfg.spp else 'all'}, {cfg.patch}x{cfg.patch} patches "
          f"({per_frame or 'paper'} per frame), {cfg.batches} batches of {cfg.batch}, {cfg.sampling} sampling, "
          f"workers started by {mp.get_start_method()}, {cfg.threads} torch thread(s), {os.cpu_count()} CPUs")
    if build.get("status") == "ok":
        print(f"store {store}: {build['frames']} frames, {build['built']} preprocessed by this run in "
              f"{build['seconds']:.1f} s; {build['store_mb']:.0f} MB on disk for {build['float32_mb']:.0f} MB of "
              f"float32 tensors (peak RSS while preparing {build['peak_mb']:.0f} MB)")
    else:
        print(f"store: {build.get('status')}")
    print("peak = the process's peak RSS; anon = its anonymous RSS after the epoch (the store's mapped pages are "
          "file-backed, reclaimable); worker = the largest worker's peak RSS")
    head = f"{'loader':<30} {'setup s':>8} {'epochs':>7} {'patches/s':>10} {'vs memory':>10} " \
           f"{'peak MB':>8} {'anon MB':>8} {'worker MB':>10}"
    print(head)
    base = results[0].get("patches_per_s") if results[0].get("status") == "ok" else None
    for r in results:
        if r.get("status") != "ok":
            print(f"{r['loader']:<30} {r['status']}")
            continue
        ratio = f"{r['patches_per_s'] / base:.2f}x" if base else "n/a"
        print(f"{r['loader']:<30} {r['setup_s']:>8.1f} {r['epochs']:>7} {r['patches_per_s']:>10.0f} {ratio:>10} "
              f"{_fmt(r['peak_mb']):>8} {_fmt(r['anon_mb']):>8} {_fmt(r['worker_peak_mb']):>10}")
    if cfg.json:
        Path(cfg.json).write_text(json.dumps({"config": vars(cfg), "build": build, "results": results}, indent=1))
    return 0 if all(r.get("status") == "ok" for r in [build, *results]) else 1
