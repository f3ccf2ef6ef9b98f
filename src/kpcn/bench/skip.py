"""``python -m kpcn.bench denoise --skip``: the time saved by leaving out what a frame does not need.

The same model (random init) denoises each scene with ``skip=False`` and
``skip=True``, timed alternately in one process, and the ratio is printed:
zero branches, zero tiles of zero-preserving models and no-hit converged
tiles are left out (see :mod:`kpcn.inference.pipeline`).
"""
from __future__ import annotations

import statistics
import sys
import time

from .denoise import _loadavg
from .models import _bench_model, _denoise_model_spec


def bench_denoise_skip(args) -> int:
    import numpy as np
    import torch

    from kpcn.inference import denoise_result
    from kpcn.io import Frame
    from kpcn.render import render_frame

    if args.threads:
        torch.set_num_threads(args.threads)
    name = args.models[0]
    model_name, kw, origin = _denoise_model_spec(name)
    model = _bench_model(model_name, kw)
    w, h = args.sizes[0]
    tile = args.tile if args.tile_given else 64
    print(f"denoise --skip: model {name} ({origin if kw is None else f'{model_name} {kw}, from {origin}, random init'}), {w}x{h}, tile {tile}, "
          f"{args.spp} spp, torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"full (skip=False) and skip (skip=True) timed alternately, {args.repeats} repeats, median seconds", flush=True)
    rows = []
    for scene in args.scenes:
        variants = []
        frame = render_frame(scene, spp=args.spp, seed=args.seed, resolution=(w, h))
        variants.append((scene, frame))
        if args.zero_specular:
            layers = {k: v.copy() for k, v in frame.layers.items()}
            layers["specular"][:] = 0.0
            layers["specularVariance"][:] = 0.0
            layers["color"] = layers["diffuse"].copy()
            if "colorVariance" in layers:
                layers["colorVariance"] = layers["diffuseVariance"].copy()
            variants.append((f"{scene} (specular zeroed)", Frame(layers, dict(frame.meta))))
        for label, fr in variants:
            denoise_result(fr, model, tile=tile, device="cpu", skip=False)  # warm up
            denoise_result(fr, model, tile=tile, device="cpu", skip=True)
            t_full, t_skip, c_full, c_skip = [], [], [], []
            for _ in range(args.repeats):
                c0, t0 = time.process_time(), time.perf_counter()
                full = denoise_result(fr, model, tile=tile, device="cpu", skip=False)
                t_full.append(time.perf_counter() - t0)
                c_full.append(time.process_time() - c0)
                c0, t0 = time.process_time(), time.perf_counter()
                sk = denoise_result(fr, model, tile=tile, device="cpu", skip=True)
                t_skip.append(time.perf_counter() - t0)
                c_skip.append(time.process_time() - c0)
            scale = max(float(np.abs(full.color).max()), 1e-12)
            diff = float(np.abs(full.color - sk.color).max()) / scale
            med = statistics.median
            rows.append((label, med(t_full), med(t_skip), med(c_full), med(c_skip), sk.stats, diff))
            print(f"  {label}: full {med(t_full):.3f} s, skip {med(t_skip):.3f} s", file=sys.stderr, flush=True)
    print(f"load average (1, 5, 15 min) at the end: {_loadavg()}")
    print(f"\n{'scene':<34} {'full s':>7} {'skip s':>7} {'ratio':>7} {'full cpu':>8} {'skip cpu':>8} {'ratio':>7} "
          f"{'max|diff|/max':>13}  what was skipped")
    for label, tf, ts, cf, cs, st, diff in rows:
        what = []
        if st.branches_skipped:
            what.append(f"branch {'+'.join(st.branches_skipped)} (whole frame)")
        for b in ("diffuse", "specular"):
            if b not in st.branches_skipped and st.branch_tiles_skipped[b]:
                what.append(f"{b} on {st.branch_tiles_skipped[b]}/{st.tiles} tiles")
        if st.tiles_passed_through:
            what.append(f"{st.tiles_passed_through}/{st.tiles} tiles passed through")
        if st.tiles_zero:
            what.append(f"{st.tiles_zero}/{st.tiles} zero tiles")
        print(f"{label:<34} {tf:>7.3f} {ts:>7.3f} {tf / max(ts, 1e-9):>6.2f}x {cf:>8.3f} {cs:>8.3f} {cf / max(cs, 1e-9):>6.2f}x "
              f"{diff:>13.2e}  {'; '.join(what) or 'nothing'}")
    return 0


