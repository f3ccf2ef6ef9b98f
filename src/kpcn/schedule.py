"""Learning-rate schedules, as pure functions of the step (a resumed run needs no scheduler state).

* ``constant``: the stage's rate throughout.
* ``onecycle`` (Smith & Topin 2018, as OIDN trains): over each stage, a cosine
  warm-up from ``lr / 25`` to ``lr`` during the first ``warmup`` fraction, then
  a cosine decay to ``lr / 25 / 1e4``.
"""
from __future__ import annotations

import math

__all__ = ["SCHEDULES", "lr_at"]

SCHEDULES = ("constant", "onecycle")
START_DIV = 25.0
FINAL_DIV = 1e4


def _cos(a: float, b: float, t: float) -> float:
    """Cosine interpolation from ``a`` (t=0) to ``b`` (t=1)."""
    return b + (a - b) * 0.5 * (1.0 + math.cos(math.pi * min(max(t, 0.0), 1.0)))


def lr_at(step: int, start: int, length: int, lr: float, schedule: str = "constant", warmup: float = 0.15) -> float:
    """The rate at ``step`` of a stage that runs steps ``start .. start + length - 1`` with peak rate ``lr``."""
    if schedule == "constant" or length <= 1:
        return lr
    if schedule != "onecycle":
        raise ValueError(f"unknown schedule {schedule!r}; known: {', '.join(SCHEDULES)}")
    t = (step - start) / (length - 1)
    low = lr / START_DIV
    if t < warmup:
        return _cos(low, lr, t / warmup)
    return _cos(lr, low / FINAL_DIV, (t - warmup) / max(1.0 - warmup, 1e-12))
