"""Settings of the report: :class:`ReportConfig`, the constants shared by its modules, :func:`nearest_spp`."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

log = logging.getLogger("kpcn.report")  #: one logger for the whole package (its name shows in the CLI's log lines)

METRICS = ("relmse", "smape", "psnr", "ssim")
TIMES = ("render_s", "denoise_s", "total_s")
CSV_FIELDS = ("scene", "spp", "method", *METRICS, *TIMES, "width", "height", "ref_spp")
MC = "mc"  #: method name of the raw Monte Carlo rows
DEFAULT_SCENES = ("random:900001", "random:900002", "random:900003", "test:glossy", "test:glass")
INPUT_ROLE_BASE = 2  #: input at s spp renders with role 2 + s (as kpcn.render's data sets); reference role 1
WARMUP_ROLE = 10_000_000  #: role of the untimed warm-up render (its noise is never used)
#: pause between a scene's renders and its timed denoising. Mitsuba's worker threads keep
#: spinning briefly after a render; a torch denoiser started at once ran 20x slower (2 cores).
SETTLE_SECONDS = 0.5


@dataclass
class ReportConfig:
    """What to render and compare. ``resolution`` is ``(width, height)``."""

    scenes: list[Any] = field(default_factory=lambda: list(DEFAULT_SCENES))
    spp: list[int] = field(default_factory=lambda: [2, 4, 8, 16, 32, 64])
    ref_spp: int = 1024
    resolution: tuple[int, int] = (128, 128)
    models: list[str] = field(default_factory=lambda: ["kpcn", "dpcn"])
    oidn: bool = True  #: include OIDN when pyoidn imports
    out: str = "results/report"
    name: str = "default"
    seed: int = 0
    device: str = "auto"
    tile: int = 256
    repeats: int = 1  #: timed denoise calls per frame; the median is reported (the result of the last is kept)
    equal_time_spp: int = 8  #: the model's spp for the equal-time figure (nearest ladder spp if absent)
    contact_spp: int = 8  #: spp shown in the contact sheet (nearest ladder spp if absent)
    crop: int = 128  #: side of the centre crop in the contact sheet
    rerender: bool = False
    max_depth: int = 8
    trust_checkpoint: bool = False  #: allow .pt model files that need full unpickling (runs their code)

    #: the ``--quick`` preset: two 24x24 scenes (chosen for low firefly noise), 2 and 4 spp, 64-spp reference
    QUICK = {"scenes": ["random:900003", "test:textured"], "spp": [2, 4], "ref_spp": 64, "resolution": [24, 24],
             "name": "quick"}

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
        if self.ref_spp <= max(self.spp):
            log.warning("reference spp %d is not above the largest input spp %d", self.ref_spp, max(self.spp))
        if len(self.resolution) != 2 or min(self.resolution) < 8:
            raise ValueError(f"resolution must be (width, height), each >= 8, got {self.resolution}")

    @property
    def folder(self) -> Path:
        return Path(self.out) / self.name


def nearest_spp(ladder: Sequence[int], want: int) -> int:
    """The ladder spp closest to ``want`` in log scale (ties: the smaller)."""
    return min(sorted(ladder), key=lambda s: abs(math.log(s / want)))
