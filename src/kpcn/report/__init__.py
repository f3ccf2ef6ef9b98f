"""Error against run time: raw Monte Carlo, kpcn models and OIDN on held-out scenes.

Command line::

    python -m kpcn.report                                   # defaults below, into results/report/default/
    python -m kpcn.report --quick --out /tmp/r              # tiny smoke run (24x24, 2, 4 and 8 spp)
    python -m kpcn.report --scenes test:glossy file:lamp_room my.xml --spp 2 4 8 --ref-spp 512 \\
        --resolution 64 64 --models kpcn dpcn mine=results/exp1/checkpoints/latest.pt

Python API::

    from kpcn.report import ReportConfig, run_report
    result = run_report(ReportConfig(scenes=["test:glossy"], spp=[2, 4], models=["kpcn"]))
    result.summary["equal_time_headline"]                   # the median equal-time figure, scenes left out
    result.paths["markdown"]                                # report.md

Scenes: ``random:<seed>`` (procedural; the defaults use seeds 900001-900003 and 910001-910006,
far from the training data's), ``test:<name>`` (:func:`kpcn.scenes.list_test_scenes`),
``file:<name>`` (the Mitsuba XML files shipped in ``kpcn/scenes/files/``,
:func:`kpcn.scenes.list_scene_files`) or the path of any XML scene file.
The default: 16 scenes (9 procedural, 3 test scenes, the 4 shipped files) at
256x256, spp 2, 4, … 256, a 1024-spp converged input and a 2048-spp reference, refined
up to 16384 spp where its own noise adds more than relMSE 0.0015 (``ref_floor_target``):
about 135 minutes on a 2-core CPU (docs/measured.md).

What it does, per scene:

1. renders the noisy input at every spp of the ladder (each spp its own
   independent seed), a converged input (``converged_spp``, its own seed) and a
   high-spp reference (``role=1``: noise independent of the inputs), caching
   every render as an EXR in ``<out>/<name>/renders/<scene>/<W>x<H>-<scene fingerprint>/``
   (written atomically; a re-run reuses them, ``--rerender`` forces new ones; the
   fingerprint changes when the scene's content does). A reference whose own
   noise adds more relMSE than ``ref_floor_target`` keeps its samples and gets
   more (:func:`refined_spp`, :func:`kpcn.render.extend_frame`), cached as
   ``reference_<spp>spp_seed<seed>.exr`` beside the first. Before the first timed
   render of a scene one untimed 2-spp render compiles Mitsuba's kernels, so
   render seconds are the wall time of the sampling, as ``renderTimeSeconds`` says;
2. evaluates raw MC, each model (``kpcn.denoise`` on the in-memory
   frame, model loaded once beforehand) and OIDN (when ``pyoidn`` imports)
   against the reference: relMSE, SMAPE, PSNR, SSIM (:mod:`kpcn.metrics`);
   denoise seconds are the wall time of the denoise call (OIDN's with albedo
   and normal; ``--repeats N``: median of N) after one untimed warm-up call per
   method, and after a short pause following the renders (:data:`SETTLE_SECONDS`);
   total seconds = render + denoise. Every row whose relMSE is below
   ``floor_factor`` (3) times the relMSE the reference's own noise adds
   (:func:`reference_floor`, from its variance buffer) is flagged ``ref_limited``;
3. runs every method on the converged input and measures how much it changes it
   (:func:`kpcn.report.checks.evaluate_converged`), runs every method on the ``exposure_spp`` inputs at other
   exposures (× 0.01 and × 100: :func:`kpcn.report.checks.evaluate_exposure`) and on a frame whose spp varies
   per pixel (the ``mixed_spp`` inputs, 4 and 64, in halves: :func:`kpcn.report.checks.evaluate_mixed`), lists
   every frame a method
   made further from the reference than its noisy input and every output that
   got further from it with more samples
   (:func:`kpcn.report.checks.worse_with_more_samples`), and marks per spp
   whether each model beats OIDN on mean relMSE, PSNR and SSIM together;
4. writes ``results.csv`` (one row per scene, spp, method), ``equal_time.csv``,
   ``converged.csv``, ``exposure.csv``, ``mixed.csv``, ``report.md`` (equal-time headline, mean table, against
   OIDN, the methods' cost: denoise seconds and multiply-adds per pixel, the
   converged-input table, the other exposures, the varying spp, the frames made worse, the outputs worse with more
   samples, per-scene tables),
   ``error_vs_time.png`` (log-log relMSE against total seconds, one panel per
   scene plus the mean), ``contact_sheet.png`` (tone-mapped crops at one spp)
   and ``summary.json``; all atomically. The Markdown up to the per-scene table
   is printed.

The equal-time figure: for each scene, the spp at which raw MC reaches the
relMSE of the first model at 8 spp (log-log interpolation along the raw ladder;
outside it, extrapolation with the slope of a least-squares fit of log relMSE
against log spp over the ladder points the reference resolves, MC error ~ 1/spp,
flagged as extrapolated), and the time ratio (raw MC seconds at that spp, from a
linear fit ``seconds = overhead + spp × seconds-per-sample`` over the scene's
renders, divided by the model's render + denoise seconds at 8 spp). The headline
is the **median** over scenes, leaving out (and naming, with the reason) each
scene whose figure means little: raw MC's fitted slope outside ``slope_range``
(-1.5 … -0.5), the model's error below ``floor_factor`` x the reference's noise,
or raw MC needing more spp than the reference has (:func:`equal_time`,
:func:`equal_time_headline`).

Models are given as registry names (``kpcn``, ``dpcn``: shipped weights),
checkpoint paths, or ``label=name-or-path``.
"""
from __future__ import annotations

from .analysis import (
    equal_time,
    equal_time_headline,
    evaluate_scene,
    fitted_slope,
    is_ref_limited,
    mc_spp_for_error,
    mean_table,
    render_time_model,
)
from .cache import SceneRenders, reference_floor, refined_spp, render_scene, scene_label, scene_slug, scene_source
from .checks import (
    CONVERGED_FIELDS,
    EXPOSURE_FIELDS,
    MIXED_FIELDS,
    against_oidn,
    converged_table,
    evaluate_converged,
    evaluate_exposure,
    evaluate_mixed,
    exposure_table,
    method_table,
    mixed_table,
    worse_than_input,
    worse_with_more_samples,
)
from .cli import main
from .config import (
    BASELINES,
    CONVERGED_ROLE,
    CSV_FIELDS,
    DEFAULT_SCENES,
    INPUT_ROLE_BASE,
    MC,
    METRICS,
    OIDN,
    OIDN_MACS_PER_PX,
    OIDN_PREFILTERED,
    SETTLE_SECONDS,
    TIMES,
    WARMUP_ROLE,
    ReportConfig,
    log,
    nearest_spp,
)
from .methods import Method, build_methods, model_method, oidn_method, oidn_prefiltered_method, parse_model_spec
from .plots import contact_sheet, plot_error_vs_time
from .run import ReportResult, build_summary, run_report, write_outputs
from .tables import equal_time_markdown, markdown_report, write_csv

__all__ = [
    "CONVERGED_FIELDS", "CONVERGED_ROLE", "EXPOSURE_FIELDS", "MIXED_FIELDS",
    "CSV_FIELDS", "DEFAULT_SCENES", "INPUT_ROLE_BASE", "MC", "METRICS", "OIDN",
    "OIDN_MACS_PER_PX", "OIDN_PREFILTERED", "BASELINES", "SETTLE_SECONDS", "TIMES", "WARMUP_ROLE",
    "Method", "ReportConfig", "ReportResult", "SceneRenders",
    "against_oidn", "build_methods", "build_summary", "contact_sheet", "converged_table", "equal_time",
    "equal_time_headline", "equal_time_markdown", "evaluate_converged", "evaluate_exposure",
    "evaluate_mixed", "evaluate_scene", "exposure_table", "fitted_slope",
    "is_ref_limited", "main", "markdown_report", "mc_spp_for_error", "mean_table", "method_table", "mixed_table",
    "model_method", "nearest_spp", "oidn_method", "oidn_prefiltered_method", "parse_model_spec",
    "plot_error_vs_time", "reference_floor", "refined_spp",
    "render_scene", "render_time_model", "run_report", "scene_label", "scene_slug", "scene_source", "worse_than_input",
    "worse_with_more_samples", "write_csv", "write_outputs",
]
