"""Evaluation and the equal-time analysis: metrics rows, mean tables, MC error and render-time fits."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..io import Frame
from ..metrics import all_metrics
from .cache import SceneRenders
from .config import MC, METRICS, TIMES
from .methods import Method


def evaluate_scene(sr: SceneRenders, methods: Sequence[Method], keep_spp: int | None = None):
    """Rows (dicts with :data:`CSV_FIELDS`) for raw MC and every method at every spp of ``sr``.

    Returns ``(rows, images)`` where ``images[method]`` is the ``(H, W, 3)`` result
    at ``keep_spp`` (for the contact sheet), including ``"mc"`` and ``"reference"``.
    """
    ref = sr.reference["color"]
    h, w = sr.reference.shape
    rows, images = [], {"reference": ref}
    for spp, frame in sorted(sr.inputs.items()):
        render_s = float(frame.meta["renderTimeSeconds"])
        results = [(MC, frame["color"], 0.0)]
        for m in methods:
            img, secs = m(frame)
            results.append((m.name, img, secs))
        for name, img, secs in results:
            row = {"scene": sr.label, "spp": spp, "method": name, **all_metrics(img, ref)}
            row.update(render_s=render_s, denoise_s=secs, total_s=render_s + secs, width=w, height=h)
            row["ref_spp"] = sr.reference.spp
            rows.append(row)
            if spp == keep_spp:
                images[name] = img
    return rows, images


def reference_floor(ref: Frame) -> float | None:
    """relMSE the reference's own noise adds: mean(colorVariance / (ref² + 0.01)), or None without variance."""
    var = ref.get("colorVariance")
    if var is None:
        return None
    c = ref["color"].astype(np.float64)
    return float(np.mean(np.broadcast_to(var, c.shape) / (c**2 + 1e-2)))


def mean_table(rows: Sequence[dict]) -> list[dict]:
    """Mean over scenes of every metric and time, per (method, spp); sorted by method order then spp."""
    order = list(dict.fromkeys(r["method"] for r in rows))
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["method"], int(r["spp"])), []).append(r)
    out = []
    for (method, spp), rs in sorted(groups.items(), key=lambda kv: (order.index(kv[0][0]), kv[0][1])):
        out.append({"method": method, "spp": spp, "scenes": len(rs), **{k: float(np.mean([r[k] for r in rs])) for k in METRICS + TIMES}})
    return out


def mc_spp_for_error(spp: Sequence[float], err: Sequence[float], target: float) -> tuple[float, bool, float]:
    """Samples per pixel at which raw MC reaches relMSE ``target``.

    Interpolates log(err) against log(spp) between the ladder points (first
    crossing in spp order); outside the ladder, extrapolates from the nearest end
    with the least-squares slope of log(err) on log(spp) (MC theory: -1; a fitted
    slope that does not fall, > -0.05, is replaced by -1).

    Returns ``(spp_star, extrapolated, slope)``.
    """
    s = np.log(np.asarray(spp, dtype=np.float64))
    e = np.log(np.maximum(np.asarray(err, dtype=np.float64), 1e-30))
    idx = np.argsort(s)
    s, e = s[idx], e[idx]
    t = math.log(max(target, 1e-30))
    slope = float(np.polyfit(s, e, 1)[0]) if len(s) >= 2 else -1.0
    if not slope < -0.05:
        slope = -1.0
    for i in range(len(s) - 1):
        lo, hi = sorted((e[i], e[i + 1]))
        if lo <= t <= hi and e[i] != e[i + 1]:
            f = (t - e[i]) / (e[i + 1] - e[i])
            return float(math.exp(s[i] + f * (s[i + 1] - s[i]))), False, slope
    # outside the ladder: extrapolate from the end on the target's side
    j = -1 if t < e[-1] else 0
    return float(math.exp(s[j] + (t - e[j]) / slope)), True, slope


def render_time_model(spp: Sequence[float], seconds: Sequence[float]) -> tuple[float, float]:
    """Fit ``seconds = overhead + spp * per_sample`` (least squares; overhead >= 0, per_sample > 0).

    Returns ``(overhead, per_sample)``; falls back to ``(0, sum(seconds) / sum(spp))``.
    """
    x = np.asarray(spp, dtype=np.float64)
    y = np.asarray(seconds, dtype=np.float64)
    if len(x) >= 2 and np.ptp(x) > 0:
        b, a = np.polyfit(x, y, 1)
        if b > 0 and a >= 0:
            return float(a), float(b)
        if b > 0:  # negative intercept: force it to 0
            return 0.0, float(np.sum(x * y) / np.sum(x * x))
    return 0.0, float(y.sum() / x.sum())


def equal_time(rows: Sequence[dict], renders: dict[str, SceneRenders], model: str, model_spp: int) -> list[dict]:
    """The equal-time figure of every scene for ``model`` at ``model_spp`` (see the package docstring, :mod:`kpcn.report`)."""
    out = []
    for label, sr in renders.items():
        mc = sorted((r for r in rows if r["scene"] == label and r["method"] == MC), key=lambda r: r["spp"])
        mr = [r for r in rows if r["scene"] == label and r["method"] == model and r["spp"] == model_spp]
        if not mc or not mr:
            continue
        target = mr[0]["relmse"]
        s_star, extrap, slope = mc_spp_for_error([r["spp"] for r in mc], [r["relmse"] for r in mc], target)
        times = [(s, float(f.meta["renderTimeSeconds"])) for s, f in sr.inputs.items()]
        times.append((sr.reference.spp, float(sr.reference.meta["renderTimeSeconds"])))
        overhead, per_sample = render_time_model(*zip(*times))
        mc_s = overhead + per_sample * s_star
        out.append({
            "scene": label, "model": model, "model_spp": model_spp, "model_relmse": target,
            "model_seconds": mr[0]["total_s"], "mc_spp": s_star, "extrapolated": extrap,
            "beyond_reference": s_star > sr.reference.spp, "slope": slope, "mc_seconds": mc_s,
            "seconds_per_sample": per_sample, "render_overhead_s": overhead,
            "time_ratio": mc_s / mr[0]["total_s"], "reference_floor_relmse": reference_floor(sr.reference),
        })
    return out


def geomean(xs: Sequence[float]) -> float | None:
    xs = [x for x in xs if x and x > 0 and math.isfinite(x)]
    return float(math.exp(np.mean(np.log(xs)))) if xs else None
