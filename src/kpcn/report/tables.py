"""Tabular outputs: the CSV files and the Markdown report."""
from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..io import atomic_write
from .config import CSV_FIELDS, MORE_SAMPLES_TOLERANCE


def write_csv(path: Path, rows: Sequence[dict], fields: Sequence[str] = CSV_FIELDS) -> None:
    """One row per item of ``rows`` with ``fields`` (default: per (scene, spp, method), :data:`CSV_FIELDS`)."""
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=list(fields), extrasaction="ignore", lineterminator="\n")
    wr.writeheader()
    for r in rows:
        wr.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    atomic_write(path, lambda tmp: Path(tmp).write_text(buf.getvalue()))


def _fmt(v: Any, key: str = "") -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (str, int, np.integer)):
        return str(v)
    if key.endswith("psnr"):
        return f"{v:.2f}"
    if key.endswith("ssim"):
        return f"{v:.4f}"
    if key.endswith("_s") or "_s_" in key or key.endswith("seconds"):
        return f"{v:.3f}"
    return f"{v:.4g}"


def _md_table(rows: Sequence[dict], cols: Sequence[tuple[str, str]]) -> str:
    head = "| " + " | ".join(title for _, title in cols) + " |"
    sep = "|" + "|".join("---" for _ in cols) + "|"
    body = ["| " + " | ".join(_fmt(r.get(k), k) for k, _ in cols) + " |" for r in rows]
    return "\n".join([head, sep, *body])


_ROW_COLS = [("relmse", "relMSE"), ("smape", "SMAPE"), ("psnr", "PSNR dB"), ("ssim", "SSIM"),
             ("render_s", "render s"), ("denoise_s", "denoise s"), ("total_s", "total s")]


def _k(summary: dict) -> str:
    return f"{summary['config']['floor_factor']:g}×"


def equal_time_markdown(eq: Sequence[dict], summary: dict | None) -> str:
    """The equal-time headline (median over the scenes kept), the scenes left out and why, and the per-scene table."""
    if not eq:
        return "No equal-time figure (the model or raw MC rows are missing)."
    m, s = eq[0]["model"], eq[0]["model_spp"]
    head = (summary or {}).get("equal_time_headline")
    lines = []
    if head and head["mc_spp"] is not None:
        lo, hi = head["time_ratio_range"]
        lines += [f"**Median over {head['n_scenes']} of {head['n_total']} scenes: raw MC needs "
                  f"{head['mc_spp']:.1f} spp and {head['time_ratio']:.2f}× the time of {m} at {s} spp** "
                  f"(time ratio {lo:.2f}–{hi:.2f} across those scenes)."]
    elif head:
        lines += [f"**No equal-time headline: all {head['n_total']} scenes were left out** (reasons below)."]
    if head and head["left_out"]:
        lines += ["", f"Left out of the median ({len(head['left_out'])}):",
                  *[f"- {x['scene']}: {x['why']}" for x in head["left_out"]]]
    rows = [{**e, "mc_spp_txt": f"{e['mc_spp']:.1f}" + (" (extrapolated)" if e["extrapolated"] else "")
             + (" (beyond reference spp)" if e["beyond_reference"] else ""),
             "used": "left out" if e["left_out"] else "yes"} for e in eq]
    cols = [("scene", "scene"), ("used", "in median"), ("model_relmse", f"{m} relMSE @ {s} spp"),
            ("mc_spp_txt", "raw MC spp for that relMSE"), ("fitted_slope", "fitted MC slope"),
            ("mc_seconds", "raw MC seconds"), ("model_seconds", f"{m} seconds"),
            ("time_ratio", "time ratio (MC / model)"), ("reference_floor_relmse", "reference noise relMSE")]
    k = _k(summary) if summary else "a few times"
    lines += [
        "",
        f"For each scene: the spp at which raw Monte Carlo reaches the relMSE of **{m} at {s} spp** "
        "(log-log interpolation along the raw ladder; outside it, extrapolation with the fitted slope of "
        "log relMSE against log spp, marked *extrapolated*; the fit uses the ladder points above "
        f"{k} the reference's noise), and the ratio of the raw MC render time at that "
        f"spp (fit `seconds = overhead + spp × seconds-per-sample` over the scene's renders) to {m}'s "
        "render + denoise seconds. A ratio above 1 means the denoiser reaches that error faster. "
        "The headline is the **median** over the scenes kept, so no single scene drives it. A scene is left "
        "out when its figure means little: raw MC's fitted slope is far from −1 (the error does not fall "
        f"like Monte Carlo on this ladder), the model's error is below {k} the reference's own noise "
        "(last column: the relMSE the reference's noise adds, from its variance buffer), or raw MC would "
        "need more spp than the reference has. Leaving out scenes where the model is too good to measure "
        "makes the median conservative.",
        "",
        _md_table(rows, cols),
    ]
    return "\n".join(lines)


def _with_cost(method: str, summary: dict) -> str:
    macs = summary.get("method_macs_per_px", {}).get(method)
    approx = "≈ " if method == "oidn" else ""
    return f"{method} ({approx}{macs / 1e3:.1f} k multiply-adds per pixel)" if macs is not None else method


def _mark(ok: bool) -> str:
    return "✓" if ok else "✗"


def distinct_pair(a: float, b: float, kind: str, digits: int, most: int = 8) -> str:
    """``"a / b"`` formatted with ``digits`` (``kind`` ``g``: significant digits, ``f``: decimals), or with as many
    more as it takes, up to ``most``, for two different values not to print the same (a ✓ or ✗ beside two equal
    numbers says nothing)."""
    for d in range(digits, max(digits, most) + 1):
        x, y = format(a, f".{d}{kind}"), format(b, f".{d}{kind}")
        if x != y or a == b:
            break
    return f"{x} / {y}"


def _oidn_markdown(vs: Sequence[dict]) -> str:
    if not vs:
        return "No OIDN rows: no comparison."
    rows = [{"method": v["method"], "spp": v["spp"],
             "r": f"{_mark(v['relmse_ok'])} {distinct_pair(v['relmse'], v['oidn_relmse'], 'g', 4)}",
             "p": f"{_mark(v['psnr_ok'])} {distinct_pair(v['psnr'], v['oidn_psnr'], 'f', 2)}",
             "s": f"{_mark(v['ssim_ok'])} {distinct_pair(v['ssim'], v['oidn_ssim'], 'f', 4)}",
             "all": "**yes**" if v["beats_oidn"] else "no", "won": f"{v['scenes_won_relmse']}/{v['scenes']}"}
            for v in vs]
    return ("Means over scenes, model / OIDN. *Beats OIDN* only when relMSE ≤, PSNR ≥ and SSIM ≥ all hold.\n\n"
            + _md_table(rows, [("method", "method"), ("spp", "spp"), ("r", "relMSE ≤ OIDN"), ("p", "PSNR ≥ OIDN"),
                               ("s", "SSIM ≥ OIDN"), ("all", "beats OIDN on all three"),
                               ("won", "scenes with relMSE ≤ OIDN")]))


def _methods_markdown(mt: Sequence[dict]) -> str:
    rows = [{**r, "macs": (f"{'≈ ' if r['method'] == 'oidn' else ''}{r['macs_per_px'] / 1e3:.1f} k"
                           if r["macs_per_px"] is not None else "n/a")} for r in mt]
    return _md_table(rows, [("method", "method"), ("macs", "multiply-adds per pixel"),
                            ("denoise_s_mean", "denoise s per frame (mean)"), ("denoise_s_median", "median s"),
                            ("frames", "frames timed"), ("mpix_per_s", "Mpixel/s"), ("macs_source", "multiply-adds from")])


def _converged_markdown(ct: Sequence[dict], summary: dict) -> str:
    if not ct:
        return "No converged input (converged_spp = 0)."
    spp = ct[0]["spp"]
    text = (f"Each method applied to an independent {spp}-spp render (its own seed, not the reference's). "
            "*change* compares the output with that input: a denoiser must leave a converged input nearly as it "
            "is (relMSE near 0, PSNR high). The last columns compare output and input with the reference "
            f"(on scenes where the input is within {_k(summary)} the reference's noise, those cannot show "
            "a change: read the change columns).")
    cols = [("method", "method"), ("scenes", "scenes"), ("change_relmse", "change relMSE (mean)"),
            ("change_relmse_max", "change relMSE (max)"), ("change_psnr", "change PSNR dB (median)"),
            ("relmse", "output relMSE vs ref"), ("input_relmse", "input relMSE vs ref"),
            ("psnr", "output PSNR vs ref"), ("input_psnr", "input PSNR vs ref"),
            ("worse_than_input", "scenes worse than input")]
    return text + "\n\n" + _md_table(ct, cols)


def _exposure_markdown(et: Sequence[dict]) -> str:
    if not et:
        return "Not measured (exposure_factors is empty)."
    text = (f"Each method on the {et[0]['spp']}-spp inputs with every radiance layer multiplied by the factor (the "
            "same scene in other units), its output divided by it; *own*: the same method at the frames' own "
            "exposure. A denoiser's result should not depend on the units of the radiance.")
    cols = [("method", "method"), ("exposure", "× exposure"), ("scenes", "scenes"), ("relmse", "relMSE"),
            ("psnr", "PSNR"), ("ssim", "SSIM"), ("own_relmse", "own relMSE"), ("own_psnr", "own PSNR"),
            ("own_ssim", "own SSIM"), ("relmse_ratio_max", "largest relMSE / own"),
            ("worse_than_input", "frames worse than input")]
    return text + "\n\n" + _md_table(et, cols)


def _mixed_markdown(mt: Sequence[dict]) -> str:
    if not mt:
        return "Not measured (mixed_spp is empty)."
    lo, hi = mt[0]["spp_low"], mt[0]["spp_high"]
    text = (f"Each method on a frame whose spp varies per pixel, as an adaptive sampler leaves it: the {lo}-spp "
            f"input in half the frame (smooth regions), the {hi}-spp input in the other half, with its "
            "`sampleCount` layer. relMSE in each half against the same method's on the uniform frame there "
            "(*uniform*): a ratio above 1 is error the change of spp added.")
    cols = [("method", "method"), ("scenes", "scenes"), ("relmse", "relMSE"), ("psnr", "PSNR"), ("ssim", "SSIM"),
            ("relmse_low", f"{lo}-spp half"), ("uniform_relmse_low", "uniform"), ("ratio_low", "ratio"),
            ("relmse_high", f"{hi}-spp half"), ("uniform_relmse_high", "uniform"), ("ratio_high", "ratio"),
            ("worse_than_input", "frames worse than input")]
    return text + "\n\n" + _md_table(mt, cols)


def _worse_markdown(worse: Sequence[dict], summary: dict) -> str:
    n_frames = summary.get("frames_checked", 0)
    if not worse:
        return f"None: every output of every method is closer to the reference than its input ({n_frames} frames checked)."
    counts = {}
    for w in worse:
        counts[w["method"]] = counts.get(w["method"], 0) + 1
    lines = [f"**{len(worse)} of {n_frames} frames** came out further from the reference than their noisy input "
             f"(relMSE output > relMSE input): " + ", ".join(f"{m} {c}" for m, c in counts.items()) + ".", ""]
    for w in worse:
        tag = " (converged input)" if w["converged"] else ""
        tag += f" (× {w['exposure']:g} exposure)" if w.get("exposure") else ""
        tag += f" (varying spp, {w['mixed'][0]}/{w['mixed'][1]})" if w.get("mixed") else ""
        tag += f" (input within {_k(summary)} reference noise)" if w["ref_limited"] else ""
        lines.append(f"- {w['scene']} @ {w['spp']} spp{tag}: {w['method']} relMSE {w['relmse']:.4g} > "
                     f"input {w['input_relmse']:.4g} (×{w['ratio']:.3g})")
    return "\n".join(lines)


def _more_samples_markdown(worse: Sequence[dict]) -> str:
    if not worse:
        return "None: no method's output moved further from the reference when it was given more samples."
    lines = [f"**{len(worse)} outputs** are further from the reference than the same method's output on the same "
             f"scene at fewer samples (relMSE more than {MORE_SAMPLES_TOLERANCE * 100:g} % above its best at a lower spp): the "
             "method keeps, at "
             "that spp, noise it removed at fewer samples.", ""]
    for w in worse:
        lines.append(f"- {w['scene']} @ {w['spp']} spp: {w['method']} relMSE {w['relmse']:.4g} > "
                     f"{w['best_relmse']:.4g} at {w['best_spp']} spp (×{w['ratio']:.3g})")
    return "\n".join(lines)


def _refined(summary: dict) -> str:
    """The header's words on references given more samples (``ref_floor_target``)."""
    cfg, refs = summary["config"], summary.get("reference", {})
    if not cfg.get("ref_floor_target"):
        return ""
    more = {s: r["spp"] for s, r in refs.items() if r["spp"] > cfg["ref_spp"]}
    which = ", ".join(f"{s} {n}" for s, n in more.items()) or "none"
    return (f", given more samples (up to {cfg['ref_spp_max']}) where its own noise adds more than relMSE "
            f"{cfg['ref_floor_target']:g}: {which}")


def markdown_report(rows: Sequence[dict], means: Sequence[dict], eq: Sequence[dict], summary: dict) -> str:
    """The full Markdown report (printed up to the per-scene table: equal time first)."""
    cfg = summary["config"]
    rep = f" (median of {cfg['repeats']})" if cfg["repeats"] > 1 else ""
    k = _k(summary)
    conv = f", converged input {cfg['converged_spp']} spp" if cfg.get("converged_spp") else ""
    parts = [
        f"# kpcn report: {cfg['name']}",
        "",
        f"{len(summary['scenes'])} scenes at {cfg['resolution'][0]}×{cfg['resolution'][1]}, "
        f"spp {', '.join(map(str, cfg['spp']))}{conv}, reference {cfg['ref_spp']} spp (independent seeds)"
        f"{_refined(summary)}. "
        f"Methods: {', '.join(_with_cost(m, summary) for m in summary['methods'])}.",
        "",
        "Times: render seconds are the wall time of the sampling (kernels compiled by an untimed warm-up render); "
        f"denoise seconds are the wall time of one denoise call{rep} (model: `kpcn.denoise` on the in-memory frame; "
        "OIDN: `pyoidn.denoise` with albedo and normal; oidn_prefiltered: the same after OIDN's own filters denoised "
        "the albedo and normal, as Blender's Accurate prefilter), after one untimed warm-up call per method so that "
        "first-call set-up is not counted, and after a pause that lets the renderer's threads go idle; "
        "total = render + denoise. "
        f"Rows whose relMSE is below {k} the relMSE the reference's own noise adds are flagged *ref-limited*: "
        "the reference cannot resolve them. "
        f"Machine: {summary['machine']}.",
    ]
    if summary["notes"]:
        parts += ["", "Notes:", *[f"- {n}" for n in summary["notes"]]]
    parts += ["", "## Equal time", "", equal_time_markdown(eq, summary)]
    parts += ["", "## Mean over scenes", "",
              f"Means over scenes (and the median relMSE); *ref-limited*: of those scenes, how many rows are below "
              f"{k} the reference's noise.", "",
              _md_table(means, [("method", "method"), ("spp", "spp"), ("relmse", "relMSE"),
                                ("relmse_median", "median relMSE"), *_ROW_COLS[1:], ("ref_limited", "ref-limited")])]
    parts += ["", "## Against OIDN", "", _oidn_markdown(summary.get("against_oidn", []))]
    parts += ["", "## Methods", "", _methods_markdown(summary.get("methods_table", []))]
    parts += ["", "## Converged input", "",
              _converged_markdown(summary.get("converged_table", []), summary)]
    parts += ["", "## Other exposures", "", _exposure_markdown(summary.get("exposure_table", []))]
    parts += ["", "## Varying spp", "", _mixed_markdown(summary.get("mixed_table", []))]
    parts += ["", "## Frames made worse than their input", "", _worse_markdown(summary.get("worse_than_input", []), summary)]
    parts += ["", "## Worse with more samples", "", _more_samples_markdown(summary.get("worse_with_more_samples", []))]
    parts += ["", "## Per scene", "", _md_table(rows, [("scene", "scene"), ("spp", "spp"), ("method", "method"),
                                                        *_ROW_COLS, ("ref_limited", f"below {k} ref noise")])]
    parts += ["", "Figures: `error_vs_time.png` (relMSE against total seconds; dashed: "
                  f"{k} the reference's noise), `contact_sheet.png` ({cfg['contact_spp']} spp). Tables: "
                  "`results.csv`, `equal_time.csv`, `converged.csv`, `exposure.csv`, `mixed.csv`, `summary.json`."]
    return "\n".join(parts) + "\n"
