"""Tabular outputs: ``results.csv`` and the Markdown report."""
from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..io import atomic_write
from .config import CSV_FIELDS


def write_csv(path: Path, rows: Sequence[dict]) -> None:
    """One row per (scene, spp, method) with :data:`CSV_FIELDS`."""
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=CSV_FIELDS, extrasaction="ignore", lineterminator="\n")
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
    if key in ("psnr",):
        return f"{v:.2f}"
    if key in ("ssim",):
        return f"{v:.4f}"
    if key.endswith("_s") or key.endswith("seconds"):
        return f"{v:.3f}"
    return f"{v:.4g}"


def _md_table(rows: Sequence[dict], cols: Sequence[tuple[str, str]]) -> str:
    head = "| " + " | ".join(title for _, title in cols) + " |"
    sep = "|" + "|".join("---" for _ in cols) + "|"
    body = ["| " + " | ".join(_fmt(r.get(k), k) for k, _ in cols) + " |" for r in rows]
    return "\n".join([head, sep, *body])


_ROW_COLS = [("relmse", "relMSE"), ("smape", "SMAPE"), ("psnr", "PSNR dB"), ("ssim", "SSIM"),
             ("render_s", "render s"), ("denoise_s", "denoise s"), ("total_s", "total s")]


def equal_time_markdown(eq: Sequence[dict], summary: dict | None) -> str:
    """The equal-time table and its explanation."""
    if not eq:
        return "No equal-time figure (the model or raw MC rows are missing)."
    m, s = eq[0]["model"], eq[0]["model_spp"]
    rows = [{**e, "mc_spp_txt": f"{e['mc_spp']:.1f}" + (" (extrapolated)" if e["extrapolated"] else "")
             + (" (beyond reference spp)" if e["beyond_reference"] else "")} for e in eq]
    cols = [("scene", "scene"), ("model_relmse", f"{m} relMSE @ {s} spp"), ("mc_spp_txt", "raw MC spp for that relMSE"),
            ("slope", "fitted MC slope"), ("mc_seconds", "raw MC seconds"), ("model_seconds", f"{m} seconds"),
            ("time_ratio", "time ratio (MC / model)"), ("reference_floor_relmse", "reference noise relMSE")]
    lines = [
        f"For each scene: the spp at which raw Monte Carlo reaches the relMSE of **{m} at {s} spp** "
        "(log-log interpolation along the raw ladder; outside it, extrapolation with the fitted slope of "
        "log relMSE against log spp, marked *extrapolated*), and the ratio of the raw MC render time at that "
        f"spp (fit `seconds = overhead + spp × seconds-per-sample` over the scene's renders) to {m}'s "
        "render + denoise seconds. A ratio above 1 means the denoiser reaches that error faster. "
        "The last column is the relMSE the reference's own noise contributes (from its variance buffer): "
        "errors near it are not resolved by this reference.",
        "",
        _md_table(rows, cols),
    ]
    if summary and summary.get("equal_time_geomean"):
        g = summary["equal_time_geomean"]
        lines += ["", f"Geometric mean over scenes: raw MC needs **{g['mc_spp']:.1f} spp** "
                      f"and **{g['time_ratio']:.2f}×** the time of {m} at {s} spp."]
    return "\n".join(lines)


def _with_cost(method: str, summary: dict) -> str:
    macs = summary.get("method_macs_per_px", {}).get(method)
    return f"{method} ({macs / 1e3:.1f} k multiply-adds per pixel)" if macs is not None else method


def markdown_report(rows: Sequence[dict], means: Sequence[dict], eq: Sequence[dict], summary: dict) -> str:
    """The full Markdown report (also printed, mean table and equal-time figure first)."""
    cfg = summary["config"]
    rep = f" (median of {cfg['repeats']})" if cfg["repeats"] > 1 else ""
    parts = [
        f"# kpcn report: {cfg['name']}",
        "",
        f"{len(summary['scenes'])} scenes at {cfg['resolution'][0]}×{cfg['resolution'][1]}, "
        f"spp {', '.join(map(str, cfg['spp']))}, reference {cfg['ref_spp']} spp (independent seed). "
        f"Methods: {', '.join(_with_cost(m, summary) for m in summary['methods'])}.",
        "",
        "Times: render seconds are the wall time of the sampling (kernels compiled by an untimed warm-up render); "
        f"denoise seconds are the wall time of one denoise call{rep} (model: `kpcn.denoise` on the in-memory frame; "
        "OIDN: `pyoidn.denoise` with albedo and normal), after one untimed warm-up call per method so that "
        "first-call set-up is not counted, and after a pause that lets the renderer's threads go idle; "
        "total = render + denoise. "
        f"Machine: {summary['machine']}.",
    ]
    if summary["notes"]:
        parts += ["", "Notes:", *[f"- {n}" for n in summary["notes"]]]
    parts += ["", "## Mean over scenes", "", _md_table(means, [("method", "method"), ("spp", "spp"), *_ROW_COLS])]
    parts += ["", "## Equal time", "", equal_time_markdown(eq, summary)]
    parts += ["", "## Per scene", "", _md_table(rows, [("scene", "scene"), ("spp", "spp"), ("method", "method"), *_ROW_COLS])]
    parts += ["", "Figures: `error_vs_time.png` (relMSE against total seconds), `contact_sheet.png` "
                  f"({cfg['contact_spp']} spp)."]
    return "\n".join(parts) + "\n"
