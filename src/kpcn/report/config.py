"""Settings of the report: :class:`ReportConfig`, the constants shared by its modules, :func:`nearest_spp`."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ..render.refine import REF_SPP_MAX

log = logging.getLogger("kpcn.report")  #: one logger for the whole package (its name shows in the CLI's log lines)

METRICS = ("relmse", "smape", "psnr", "ssim")
TIMES = ("render_s", "denoise_s", "total_s")
#: ``ref_floor``: relMSE the reference's own noise adds (:func:`~kpcn.report.analysis.reference_floor`);
#: ``ref_limited``: the row's relMSE is below ``floor_factor`` times it (not resolved by this reference)
CSV_FIELDS = ("scene", "spp", "method", *METRICS, *TIMES, "width", "height", "ref_spp", "ref_floor", "ref_limited")
MC = "mc"  #: method name of the raw Monte Carlo rows
OIDN = "oidn"  #: method name of Intel Open Image Denoise (the frame's noisy albedo and normal as they are)
#: method name of OIDN with its guides prefiltered by its own filters (Blender's "Accurate" prefilter): stronger, and
#: several times slower; shown beside, while "Against OIDN" compares with :data:`OIDN`
OIDN_PREFILTERED = "oidn_prefiltered"
BASELINES = (OIDN, OIDN_PREFILTERED)  #: the methods that are not kpcn models (nor raw Monte Carlo)
#: a rise in relMSE (a fraction) that "worse with more samples" lets pass (independent renders differ a little)
MORE_SAMPLES_TOLERANCE = 0.02
#: unseen scenes: procedural seeds far from the training data's (all below 70 000), named test scenes, and
#: the XML scene files shipped in kpcn/scenes/files/ (real Mitsuba files, not from the generator)
#: (seeds 910001-910006 joined in the twenty-sixth session: on the first ten alone the default led OIDN at 8-64 spp,
#: on these six OIDN leads it there, so a choice made on ten scenes was not general)
DEFAULT_SCENES = ("random:900001", "random:900002", "random:900003", "random:910001", "random:910002", "random:910003",
                  "random:910004", "random:910005", "random:910006", "test:glossy", "test:glass", "test:textured",
                  "file:cbox_glossy", "file:material_test", "file:sun_yard", "file:lamp_room")
INPUT_ROLE_BASE = 2  #: input at s spp renders with role 2 + s (as kpcn.render's data sets); reference role 1
CONVERGED_ROLE = 3  #: role of the converged input (2 + 1: no input has 1 spp), independent of inputs and reference
WARMUP_ROLE = 10_000_000  #: role of the untimed warm-up render (its noise is never used)
#: pause between a scene's renders and its timed denoising. Mitsuba's worker threads keep
#: spinning briefly after a render; a torch denoiser started at once ran 20x slower (2 cores).
SETTLE_SECONDS = 0.5
#: OIDN's multiply-adds per pixel as the report calls it (RT filter, HDR colour with noisy albedo and normal,
#: quality "high"), counted from its network's layer list (docs/measured.md); not measured by the report. Without
#: cleanAux, "high" runs the same U-Net as "balanced" (3x3 convs 9-32-32 at full resolution, 48 ... 96 below, the
#: decoder back to 64-32-3 at full resolution: 125.4 k; the outputs are identical, tests/test_report.py); its larger
#: "high" network (about 312 k) is for prefiltered, clean auxiliary images only
OIDN_MACS_PER_PX = 125.4e3


@dataclass
class ReportConfig:
    """What to render and compare. ``resolution`` is ``(width, height)``.

    The defaults (16 scenes at 256x256, spp 2 … 256, 1024-spp converged inputs,
    2048-spp references, refined up to 16384 spp where their own noise is above relMSE 0.0015) take about
    135 minutes on a 2-core CPU (docs/measured.md).
    """

    scenes: list[Any] = field(default_factory=lambda: list(DEFAULT_SCENES))
    spp: list[int] = field(default_factory=lambda: [2, 4, 8, 16, 32, 64, 128, 256])
    ref_spp: int = 2048
    #: a reference whose own noise adds more relMSE than this (:func:`~kpcn.report.cache.reference_floor`) gets
    #: more samples: its passes are kept and more are added (:func:`kpcn.render.extend_frame`), doubling its spp as
    #: often as the floor's ``1/spp`` fall predicts the target needs, up to ``ref_spp_max``. None: ``ref_spp`` for
    #: every scene. Blender Cycles references are not refined
    ref_floor_target: float | None = 0.0015
    ref_spp_max: int = REF_SPP_MAX
    converged_spp: int = 1024  #: spp of the converged input every method is also run on (0: none)
    resolution: tuple[int, int] = (256, 256)
    models: list[str] = field(default_factory=lambda: ["unet_kpcn", "mskpcn", "kpcn", "dpcn"])
    oidn: bool = True  #: include OIDN when pyoidn imports
    oidn_prefiltered: bool = True  #: and OIDN with prefiltered guides (OIDN_PREFILTERED) beside it
    out: str = "results/report"
    name: str = "default"
    seed: int = 0
    device: str = "auto"
    tile: int = 0  #: denoise tile size; 0: whole frames (the report's frames are small)
    repeats: int = 1  #: timed denoise calls per frame; the median is reported (the result of the last is kept)
    equal_time_spp: int = 8  #: the model's spp for the equal-time figure (nearest ladder spp if absent)
    contact_spp: int = 8  #: spp shown in the contact sheet (nearest ladder spp if absent)
    #: every method is also run on the ``exposure_spp`` input (nearest ladder spp) × each factor (empty: none)
    exposure_factors: list[float] = field(default_factory=lambda: [0.01, 100.0])
    exposure_spp: int = 4
    #: every method is also run on a frame whose spp varies per pixel: the first spp's input (nearest ladder spp) in
    #: half the frame, the second's in the other half (:func:`kpcn.report.checks.evaluate_mixed`; empty: none)
    mixed_spp: list[int] = field(default_factory=lambda: [4, 64])
    crop: int = 128  #: side of the centre crop in the contact sheet
    rerender: bool = False
    max_depth: int = 8
    trust_checkpoint: bool = False  #: allow .pt model files that need full unpickling (runs their code)
    #: a relMSE below floor_factor x the reference's own noise (relMSE) is flagged as not resolved
    floor_factor: float = 3.0
    #: the fitted slope of log relMSE against log spp of raw MC must lie in this range (theory: -1) for
    #: a scene's equal-time figure to count in the headline median
    slope_range: tuple[float, float] = (-1.5, -0.5)

    #: the ``--quick`` preset: three 24x24 scenes (one shipped XML file), spp 2 4 8, 32-spp converged
    #: input, 128-spp reference
    QUICK = {"scenes": ["random:900003", "test:textured", "file:material_test"], "spp": [2, 4, 8], "ref_spp": 128,
             "ref_floor_target": None, "converged_spp": 32, "resolution": [24, 24], "name": "quick"}

    @classmethod
    def quick(cls, **overrides) -> "ReportConfig":
        """Tiny settings for tests and smoke runs (:data:`QUICK`), with ``overrides``."""
        return cls(**{**cls.QUICK, **overrides})

    def validate(self) -> None:
        if not self.scenes:
            raise ValueError("no scenes to render")
        if not self.spp or min(self.spp) < 2:
            raise ValueError(f"every spp must be >= 2 (variances need two samples), got {self.spp}")
        if self.ref_spp < 2:
            raise ValueError(f"ref_spp must be >= 2, got {self.ref_spp}")
        if self.ref_floor_target is not None and not self.ref_floor_target > 0:
            raise ValueError(f"ref_floor_target must be > 0 (or None: no refinement), got {self.ref_floor_target}")
        if self.ref_floor_target is not None and self.ref_spp_max < self.ref_spp:
            raise ValueError(f"ref_spp_max ({self.ref_spp_max}) is below ref_spp ({self.ref_spp})")
        if self.converged_spp and self.converged_spp < 2:
            raise ValueError(f"converged_spp must be 0 (none) or >= 2, got {self.converged_spp}")
        if self.ref_spp <= max(self.spp):
            log.warning("reference spp %d is not above the largest input spp %d", self.ref_spp, max(self.spp))
        if self.converged_spp and self.converged_spp >= self.ref_spp:
            log.warning("converged input spp %d is not below the reference spp %d", self.converged_spp, self.ref_spp)
        if len(self.resolution) != 2 or min(self.resolution) < 8:
            raise ValueError(f"resolution must be (width, height), each >= 8, got {self.resolution}")
        if any(not (math.isfinite(float(f)) and float(f) > 0) for f in self.exposure_factors):
            raise ValueError(f"exposure_factors must be finite and > 0, got {self.exposure_factors}")
        if self.mixed_spp and (len(self.mixed_spp) != 2 or not 1 <= self.mixed_spp[0] < self.mixed_spp[1]):
            raise ValueError(f"mixed_spp must be two sample counts, low then high (or empty: none), got "
                             f"{self.mixed_spp}")
        if not self.floor_factor > 0:
            raise ValueError(f"floor_factor must be > 0, got {self.floor_factor}")
        if len(self.slope_range) != 2 or not self.slope_range[0] < self.slope_range[1] < 0:
            raise ValueError(f"slope_range must be (low, high) with low < high < 0, got {self.slope_range}")
        for s in self.scenes:
            if isinstance(s, str) and s.startswith("file:"):
                from ..scenes import scene_file

                scene_file(s)  # ValueError naming the shipped files
            if isinstance(s, str) and s.startswith("cycles:"):
                from ..render.cycles import BLENDER_HELP, blender_available

                from ..render.cycles_scene import generated_variant, is_generated
                from .cache import cycles_blend

                if is_generated(s):
                    generated_variant(s)  # ValueError for a bad variant
                elif not cycles_blend(s).is_file():
                    raise ValueError(f"{s}: no such .blend file (cycles:generated[:<N>] is kpcn's generated scene)")
                if not blender_available():
                    raise ValueError(f"{s}: Blender's Python module bpy is not installed: {BLENDER_HELP}")

    @property
    def folder(self) -> Path:
        return Path(self.out) / self.name


def nearest_spp(ladder: Sequence[int], want: int) -> int:
    """The ladder spp closest to ``want`` in log scale (ties: the smaller)."""
    return min(sorted(ladder), key=lambda s: abs(math.log(s / want)))
