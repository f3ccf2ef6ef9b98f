"""The driver: :func:`run_report` renders, evaluates and writes everything; :class:`ReportResult`."""
from __future__ import annotations

import json
import math
import os
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..config import save_config
from ..io import atomic_write
from .analysis import equal_time, equal_time_headline, evaluate_scene, mean_table
from .cache import render_scene, scene_label
from .checks import (CONVERGED_FIELDS, EXPOSURE_FIELDS, MIXED_FIELDS, against_oidn, converged_table,
                     evaluate_converged, evaluate_exposure, evaluate_mixed, exposure_table, method_table, mixed_table,
                     worse_than_input, worse_with_more_samples)
from .config import BASELINES, MC, METRICS, SETTLE_SECONDS, TIMES, ReportConfig, log, nearest_spp
from .methods import Method, build_methods, check_layers
from .plots import contact_sheet, plot_error_vs_time
from .tables import markdown_report, write_csv

#: columns of ``equal_time.csv``
EQUAL_TIME_FIELDS = ("scene", "model", "model_spp", "model_relmse", "model_seconds", "mc_spp", "extrapolated",
                     "beyond_reference", "fitted_slope", "slope", "mc_points_fitted", "mc_seconds", "time_ratio",
                     "reference_floor_relmse", "left_out", "why")


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _finite(o):
    """``o`` with every non-finite float (an infinite PSNR of identical images) replaced by None, for JSON."""
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def _machine() -> str:
    import torch

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    dev = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, {dev}, "
            f"torch {torch.__version__} with {torch.get_num_threads()} threads, load average {load:.2f} at start")


@dataclass
class ReportResult:
    """What :func:`run_report` produced: CSV rows, mean rows, equal-time rows, summary.json content, Markdown,
    file paths, the converged-input rows (one per scene and method), the other-exposure rows (one per scene,
    method and factor) and the varying-spp rows (one per scene and method)."""

    rows: list[dict]
    means: list[dict]
    equal_time: list[dict]
    summary: dict
    markdown: str
    paths: dict[str, Path]
    rendered: list[str]  #: EXRs rendered in this run (empty when everything came from the cache)
    converged: list[dict]
    exposure: list[dict] = field(default_factory=list)
    mixed: list[dict] = field(default_factory=list)


def build_summary(cfg: ReportConfig, scenes: Sequence[str], methods: Sequence[Method], means: Sequence[dict],
                  eq: Sequence[dict], notes: list[str], machine: str, contact_spp: int, eq_spp: int,
                  rows: Sequence[dict] = (), converged: Sequence[dict] = (), exposure: Sequence[dict] = (),
                  mixed: Sequence[dict] = ()) -> dict:
    """The content of ``summary.json``: config, mean metrics per method and spp, equal-time figures and their
    median headline, the comparison with OIDN, the methods' costs, the converged-input table and the
    frames made worse than their input, the methods at other exposures and on frames whose spp varies, and the
    outputs that got worse with more samples."""
    scene_names = [scene_label(s) if isinstance(s, dict) else os.fspath(s) for s in cfg.scenes]
    return {
        "config": {**asdict(cfg), "scenes": scene_names, "resolution": list(cfg.resolution),
                   "contact_spp": contact_spp, "equal_time_spp": eq_spp},
        "scenes": list(scenes),
        "methods": [MC] + [m.name for m in methods],
        "method_descriptions": {m.name: m.description for m in methods},
        "method_macs_per_px": {m.name: m.macs_per_px for m in methods if m.macs_per_px is not None},
        "methods_table": method_table(methods, rows, converged),
        "machine": machine,
        "notes": notes,
        "mean": {m: {str(r["spp"]): {k: r[k] for k in METRICS + TIMES} for r in means if r["method"] == m}
                 for m in dict.fromkeys(r["method"] for r in means)},
        "mean_relmse_median": {m: {str(r["spp"]): r["relmse_median"] for r in means if r["method"] == m}
                               for m in dict.fromkeys(r["method"] for r in means)},
        "ref_limited_rows": sum(bool(r.get("ref_limited")) for r in rows),
        #: each scene's reference spp (above ``ref_spp`` where ``ref_floor_target`` refined it) and its noise
        "reference": {r["scene"]: {"spp": int(r["ref_spp"]), "floor_relmse": r["ref_floor"]} for r in rows},
        "equal_time": list(eq),
        "equal_time_headline": equal_time_headline(eq),
        "against_oidn": against_oidn(means, rows),
        "converged": list(converged),
        "converged_table": converged_table(converged),
        "exposure": list(exposure),
        "exposure_table": exposure_table(exposure),
        "mixed": list(mixed),
        "mixed_table": mixed_table(mixed),
        "worse_than_input": worse_than_input(rows, converged, exposure, mixed),
        "frames_checked": sum(r["method"] != MC for r in rows) + len(converged) + len(exposure) + len(mixed),
        "worse_with_more_samples": worse_with_more_samples(rows),
    }


def write_outputs(folder: Path, rows, means, images, summary: dict, markdown: str, contact_spp: int, crop: int,
                  cfg: ReportConfig | None = None) -> dict[str, Path]:
    """Write the CSVs, Markdown, plots, summary and resolved config (each atomically); returns their paths."""
    paths = {"csv": folder / "results.csv", "equal_time_csv": folder / "equal_time.csv",
             "converged_csv": folder / "converged.csv", "exposure_csv": folder / "exposure.csv",
             "mixed_csv": folder / "mixed.csv",
             "markdown": folder / "report.md",
             "plot": folder / "error_vs_time.png", "contact_sheet": folder / "contact_sheet.png",
             "summary": folder / "summary.json"}
    if cfg is not None and all(isinstance(s, str) for s in cfg.scenes):  # in-memory dict scenes are not YAML
        paths["config"] = folder / "config.yaml"
        save_config(cfg, paths["config"])
    write_csv(paths["csv"], rows)
    write_csv(paths["equal_time_csv"], summary.get("equal_time", []), EQUAL_TIME_FIELDS)
    write_csv(paths["converged_csv"], summary.get("converged", []), CONVERGED_FIELDS)
    write_csv(paths["exposure_csv"], summary.get("exposure", []), EXPOSURE_FIELDS)
    write_csv(paths["mixed_csv"], summary.get("mixed", []), MIXED_FIELDS)
    _write_text(paths["markdown"], markdown)
    plot_error_vs_time(paths["plot"], rows, means, floor_factor=cfg.floor_factor if cfg else None)
    contact_sheet(paths["contact_sheet"], images, rows, contact_spp, crop)
    _write_text(paths["summary"], json.dumps(_finite(summary), indent=1, default=_json_default))
    return paths


def run_report(cfg: ReportConfig | None = None, progress: Callable[[str], None] | None = None) -> ReportResult:
    """Render, evaluate and write the report for ``cfg`` (default :class:`ReportConfig`)."""
    cfg = cfg or ReportConfig()
    cfg.validate()
    say = progress or log.info
    machine = _machine()
    cfg.folder.mkdir(parents=True, exist_ok=True)

    methods, notes = build_methods(cfg)
    contact_spp = nearest_spp(cfg.spp, cfg.contact_spp)
    eq_spp = nearest_spp(cfg.spp, cfg.equal_time_spp)
    if eq_spp != cfg.equal_time_spp:
        notes.append(f"equal-time figure at {eq_spp} spp ({cfg.equal_time_spp} is not on the ladder)")

    exposure_spp = nearest_spp(cfg.spp, cfg.exposure_spp)
    mixed_spp = sorted({nearest_spp(cfg.spp, s) for s in cfg.mixed_spp})
    if cfg.mixed_spp and len(mixed_spp) < 2:
        notes.append(f"no varying-spp frames: {cfg.mixed_spp} spp are one spp of the ladder {cfg.spp}")
    rows, renders, images, rendered, converged, exposure, mixed = [], {}, {}, [], [], [], []
    for scene in cfg.scenes:
        sr = render_scene(cfg, scene, say)
        if sr.label in renders:  # two XML files with the same name
            sr.label = f"{sr.label}#{len(renders)}"
        renders[sr.label] = sr
        check_layers(methods, next(iter(sr.inputs.values())), sr.label)
        rendered += sr.rendered
        if sr.rendered:
            time.sleep(SETTLE_SECONDS)
        uniform = {int(s): {} for s in mixed_spp} if len(mixed_spp) == 2 else None  # kept for the mixed table
        r, imgs = evaluate_scene(sr, methods, keep_spp=contact_spp, floor_factor=cfg.floor_factor, outputs=uniform)
        rows += r
        converged += evaluate_converged(sr, methods, cfg.floor_factor)
        exposure += evaluate_exposure(sr, methods, exposure_spp, cfg.exposure_factors, r)
        if len(mixed_spp) == 2:
            mixed += evaluate_mixed(sr, methods, mixed_spp, uniform)
        images[sr.label] = imgs
        say(f"evaluated {sr.label}")

    means = mean_table(rows)
    model_names = [m.name for m in methods if m.name not in BASELINES]
    eq = (equal_time(rows, renders, model_names[0], eq_spp, cfg.floor_factor, tuple(cfg.slope_range))
          if model_names else [])
    if not model_names:
        notes.append("no kpcn model was evaluated: no equal-time figure")
    summary = build_summary(cfg, list(renders), methods, means, eq, notes, machine, contact_spp, eq_spp,
                            rows, converged, exposure, mixed)
    md = markdown_report(rows, means, eq, summary)
    paths = write_outputs(cfg.folder, rows, means, images, summary, md, contact_spp, cfg.crop, cfg)
    return ReportResult(rows, means, eq, summary, md, paths, rendered, converged, exposure, mixed)
