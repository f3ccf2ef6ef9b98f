"""Error against run time: raw Monte Carlo, kpcn models and OIDN on held-out scenes.

Command line::

    python -m kpcn.report                                   # defaults below, into results/report/default/
    python -m kpcn.report --quick --out /tmp/r              # tiny smoke run (24x24, 2 and 4 spp)
    python -m kpcn.report --scenes test:glossy my.xml --spp 2 4 8 --ref-spp 512 \\
        --resolution 64 64 --models kpcn dpcn mine=results/exp1/checkpoints/latest.pt

Python API::

    from kpcn.report import ReportConfig, run_report
    result = run_report(ReportConfig(scenes=["test:glossy"], spp=[2, 4], models=["kpcn"]))
    result.summary["equal_time"]                            # the equal-time figures
    result.paths["markdown"]                                # report.md

What it does, per scene:

1. renders the noisy input at every spp of the ladder (default 2 … 64; each spp
   its own independent seed) and a high-spp reference (default 1024 spp,
   ``role=1``: noise independent of the inputs), caching every render as an EXR
   in ``<out>/<name>/renders/<scene>/<W>x<H>-<scene fingerprint>/`` (written
   atomically; a re-run reuses them, ``--rerender`` forces new ones; the
   fingerprint changes when the scene's content does). Before the first timed
   render of a scene one untimed 2-spp render compiles Mitsuba's kernels, so
   render seconds are the wall time of the sampling, as ``renderTimeSeconds`` says;
2. evaluates raw MC, each model (``kpcn.denoise`` on the in-memory
   frame, model loaded once beforehand) and OIDN (when ``pyoidn`` imports)
   against the reference: relMSE, SMAPE, PSNR, SSIM (:mod:`kpcn.metrics`);
   denoise seconds are the wall time of the denoise call (OIDN's with albedo
   and normal; ``--repeats N``: median of N) after one untimed warm-up call per
   method, and after a short pause following the renders (:data:`SETTLE_SECONDS`);
   total seconds = render + denoise;
3. writes ``results.csv`` (one row per scene, spp, method), ``report.md`` (mean
   table per method and spp, per-scene table, equal-time table),
   ``error_vs_time.png`` (log-log relMSE against total seconds, one panel per
   scene plus the mean), ``contact_sheet.png`` (tone-mapped crops at one spp)
   and ``summary.json``; all atomically. The Markdown summary is printed.

The equal-time figure: for each scene, the spp at which raw MC reaches the
relMSE of the first model at 8 spp (log-log interpolation along the raw ladder;
outside it, extrapolation with the slope of a least-squares fit of log relMSE
against log spp, MC error ~ 1/spp, flagged as extrapolated), and the time ratio
(raw MC seconds at that spp, from a linear fit ``seconds = overhead + spp ×
seconds-per-sample`` over the scene's renders, divided by the model's render +
denoise seconds at 8 spp).

Models are given as registry names (``kpcn``, ``dpcn``: shipped weights),
checkpoint paths, or ``label=name-or-path``.
"""
from __future__ import annotations

from .analysis import (
    equal_time,
    evaluate_scene,
    geomean,
    mc_spp_for_error,
    mean_table,
    reference_floor,
    render_time_model,
)
from .cache import SceneRenders, render_scene, scene_label, scene_slug, scene_source
from .cli import main
from .config import (
    CSV_FIELDS,
    DEFAULT_SCENES,
    INPUT_ROLE_BASE,
    MC,
    METRICS,
    SETTLE_SECONDS,
    TIMES,
    WARMUP_ROLE,
    ReportConfig,
    log,
    nearest_spp,
)
from .methods import Method, build_methods, model_method, oidn_method, parse_model_spec
from .plots import contact_sheet, plot_error_vs_time
from .run import ReportResult, build_summary, run_report, write_outputs
from .tables import equal_time_markdown, markdown_report, write_csv

__all__ = [
    "CSV_FIELDS", "DEFAULT_SCENES", "INPUT_ROLE_BASE", "MC", "METRICS", "SETTLE_SECONDS", "TIMES", "WARMUP_ROLE",
    "Method", "ReportConfig", "ReportResult", "SceneRenders",
    "build_methods", "build_summary", "contact_sheet", "equal_time", "equal_time_markdown", "evaluate_scene",
    "geomean", "main", "markdown_report", "mc_spp_for_error", "mean_table", "model_method", "nearest_spp",
    "oidn_method", "parse_model_spec", "plot_error_vs_time", "reference_floor", "render_scene", "render_time_model",
    "run_report", "scene_label", "scene_slug", "scene_source", "write_csv", "write_outputs",
]
