"""Evaluation and the equal-time analysis: metrics rows, mean tables, MC error and render-time fits,
the reference's noise floor, and the equal-time headline (median over the scenes where it means something)."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..metrics import all_metrics
from .cache import SceneRenders, reference_floor
from .config import MC, METRICS, TIMES
from .methods import Method


def evaluate_scene(sr: SceneRenders, methods: Sequence[Method], keep_spp: int | None = None,
                   floor_factor: float = 3.0, outputs: dict[int, dict[str, np.ndarray]] | None = None):
    """Rows (dicts with :data:`CSV_FIELDS`) for raw MC and every method at every spp of ``sr``.

    Every row carries ``ref_floor`` (:func:`reference_floor` of the scene's
    reference) and ``ref_limited``: its relMSE is below ``floor_factor`` times
    that floor, so the reference's own noise is a large part of the measured
    error and the row does not tell how good the image is.

    Returns ``(rows, images)`` where ``images[method]`` is the ``(H, W, 3)`` result
    at ``keep_spp`` (for the contact sheet), including ``"mc"`` and ``"reference"``. ``outputs``: for each spp it
    has a key for, its dict gets every method's result there (``outputs[spp][method name]``), for a later table on
    the same inputs (:func:`kpcn.report.checks.evaluate_mixed`) not to denoise them again.
    """
    ref = sr.reference["color"]
    h, w = sr.reference.shape
    floor = reference_floor(sr.reference)
    rows, images = [], {"reference": ref}
    for spp, frame in sorted(sr.inputs.items()):
        render_s = float(frame.meta["renderTimeSeconds"])
        results = [(MC, frame["color"], 0.0)]
        for m in methods:
            img, secs = m(frame)
            results.append((m.name, img, secs))
        for name, img, secs in results:
            with np.errstate(divide="ignore"):  # PSNR of an exact image is infinite
                met = all_metrics(img, ref)
            row = {"scene": sr.label, "spp": spp, "method": name, **met}
            row.update(render_s=render_s, denoise_s=secs, total_s=render_s + secs, width=w, height=h)
            row.update(ref_spp=sr.reference.spp, ref_floor=floor, ref_limited=is_ref_limited(row["relmse"], floor, floor_factor))
            rows.append(row)
            if spp == keep_spp:
                images[name] = img
            if outputs is not None and spp in outputs and name != MC:
                outputs[spp][name] = img
    return rows, images


def is_ref_limited(relmse: float, floor: float | None, factor: float) -> bool:
    """True when ``relmse`` is below ``factor`` times the reference's noise ``floor`` (False without a floor)."""
    return floor is not None and relmse < factor * floor


def mean_table(rows: Sequence[dict]) -> list[dict]:
    """Mean over scenes of every metric and time, per (method, spp); sorted by method order then spp.

    Also ``relmse_median`` (the median over scenes, which one scene cannot drive) and
    ``ref_limited`` (how many of the scenes' rows are flagged as not resolved by the reference).
    """
    order = list(dict.fromkeys(r["method"] for r in rows))
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["method"], int(r["spp"])), []).append(r)
    out = []
    for (method, spp), rs in sorted(groups.items(), key=lambda kv: (order.index(kv[0][0]), kv[0][1])):
        out.append({"method": method, "spp": spp, "scenes": len(rs),
                    **{k: float(np.mean([r[k] for r in rs])) for k in METRICS + TIMES},
                    "relmse_median": float(np.median([r["relmse"] for r in rs])),
                    "ref_limited": sum(bool(r.get("ref_limited")) for r in rs)})
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


def fitted_slope(spp: Sequence[float], err: Sequence[float]) -> float | None:
    """Least-squares slope of log(err) against log(spp) (None with fewer than two points or a zero error)."""
    if len(spp) < 2 or min(err) <= 0 or np.ptp(np.log(np.asarray(spp, dtype=np.float64))) == 0:
        return None
    return float(np.polyfit(np.log(np.asarray(spp, dtype=np.float64)), np.log(np.asarray(err, dtype=np.float64)), 1)[0])


def equal_time(rows: Sequence[dict], renders: dict[str, SceneRenders], model: str, model_spp: int,
               floor_factor: float = 3.0, slope_range: tuple[float, float] = (-1.5, -0.5)) -> list[dict]:
    """The equal-time figure of every scene for ``model`` at ``model_spp`` (see the package docstring, :mod:`kpcn.report`).

    The raw-MC fit uses the ladder points the reference resolves (relMSE at least
    ``floor_factor`` x its noise floor; all points when fewer than two are). Each
    row says whether the scene is ``left_out`` of the headline median, and ``why``:

    * raw MC's fitted slope (log relMSE on log spp) is outside ``slope_range``
      (theory: -1), or cannot be fitted: the error does not fall like Monte Carlo
      on this ladder, so neither interpolation nor extrapolation means much;
    * the model's relMSE is below ``floor_factor`` x the reference's noise: the
      reference cannot tell how good the model is, nor which spp matches it;
    * raw MC would need more spp than the reference has: that error is not
      measurable against this reference (a hugely extrapolated figure).
    """
    out = []
    for label, sr in renders.items():
        mc = sorted((r for r in rows if r["scene"] == label and r["method"] == MC), key=lambda r: r["spp"])
        mr = [r for r in rows if r["scene"] == label and r["method"] == model and r["spp"] == model_spp]
        if not mc or not mr:
            continue
        target = mr[0]["relmse"]
        floor = reference_floor(sr.reference)
        resolved = [r for r in mc if not is_ref_limited(r["relmse"], floor, floor_factor)]
        fit = resolved if len(resolved) >= 2 else mc
        fit_spp, fit_err = [r["spp"] for r in fit], [r["relmse"] for r in fit]
        s_star, extrap, slope = mc_spp_for_error(fit_spp, fit_err, target)
        raw_slope = fitted_slope(fit_spp, fit_err)
        times = [(s, float(f.meta["renderTimeSeconds"])) for s, f in sr.inputs.items()]
        times.append((sr.reference.spp, float(sr.reference.meta["renderTimeSeconds"])))
        if sr.converged is not None:
            times.append((sr.converged.spp, float(sr.converged.meta["renderTimeSeconds"])))
        overhead, per_sample = render_time_model(*zip(*times))
        mc_s = overhead + per_sample * s_star
        why = []
        lo, hi = slope_range
        if raw_slope is None:
            why.append("raw MC's error slope cannot be fitted (zero error or one ladder point)")
        elif not lo <= raw_slope <= hi:
            why.append(f"raw MC's fitted slope {raw_slope:.2f} is outside [{lo:g}, {hi:g}] (theory: -1)")
        if len(resolved) < 2:
            why.append(f"fewer than two raw MC points above {floor_factor:g}x the reference's noise")
        if is_ref_limited(target, floor, floor_factor):
            why.append(f"{model}'s relMSE {target:.3g} is below {floor_factor:g}x the reference's noise ({floor:.3g})")
        if s_star > sr.reference.spp:
            why.append(f"raw MC would need {s_star:.4g} spp, more than the reference's {sr.reference.spp}")
        out.append({
            "scene": label, "model": model, "model_spp": model_spp, "model_relmse": target,
            "model_seconds": mr[0]["total_s"], "mc_spp": s_star, "extrapolated": extrap,
            "beyond_reference": s_star > sr.reference.spp, "slope": slope, "fitted_slope": raw_slope,
            "mc_points_fitted": len(fit), "mc_seconds": mc_s,
            "seconds_per_sample": per_sample, "render_overhead_s": overhead,
            "time_ratio": mc_s / mr[0]["total_s"], "reference_floor_relmse": floor,
            "left_out": bool(why), "why": "; ".join(why),
        })
    return out


def equal_time_headline(eq: Sequence[dict]) -> dict | None:
    """The headline: the median over the scenes not ``left_out`` of raw MC's spp and the time ratio.

    A median, not a mean: one scene with an extreme figure cannot move it.
    Returns None without equal-time rows; ``mc_spp``/``time_ratio`` are None when
    every scene was left out. ``left_out`` lists ``{"scene", "why"}``.
    """
    if not eq:
        return None
    used = [e for e in eq if not e["left_out"]]
    med = (lambda k: float(np.median([e[k] for e in used]))) if used else (lambda k: None)
    return {"model": eq[0]["model"], "model_spp": eq[0]["model_spp"], "statistic": "median",
            "scenes": [e["scene"] for e in used], "n_scenes": len(used), "n_total": len(eq),
            "mc_spp": med("mc_spp"), "time_ratio": med("time_ratio"),
            "time_ratio_range": [min(e["time_ratio"] for e in used), max(e["time_ratio"] for e in used)] if used else None,
            "left_out": [{"scene": e["scene"], "why": e["why"]} for e in eq if e["left_out"]]}

