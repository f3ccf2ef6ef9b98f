"""References given more samples where their own noise is near the errors they are to measure.

A reference's *floor* is the relMSE its own noise adds to a comparison against it (:func:`reference_floor`, from
its variance-of-the-mean layer). :func:`refined_spp` says how many samples bring a floor under a target, assuming it
falls as ``1/spp``; the report (``ReportConfig.ref_floor_target``) and the data sets (``render_dataset(...,
ref_floor_target=...)``, ``python -m kpcn.render dataset --ref-floor-target``) refine references with it, adding
the passes after a frame's own (:func:`kpcn.render.extend_frame`) so that no sample is rendered twice.
"""
from __future__ import annotations

import numpy as np

from ..io import Frame

__all__ = ["reference_floor", "refined_spp", "REF_SPP_MAX"]

#: the most samples a refined reference gets unless told otherwise (a heavy tail falls slower than 1/spp: the
#: report's noisiest scene went from 0.0107 at 2048 spp to 0.0022 at 16384)
REF_SPP_MAX = 16384


def reference_floor(ref: Frame) -> float | None:
    """relMSE the reference's own noise adds: mean(colorVariance / (ref² + 0.01)), or None without variance."""
    var = ref.get("colorVariance")
    if var is None:
        return None
    c = ref["color"].astype(np.float64)
    return float(np.mean(np.broadcast_to(var, c.shape) / (c**2 + 1e-2)))


def refined_spp(spp: int, floor: float, target: float, most: int) -> int:
    """The reference spp a floor of ``floor`` at ``spp`` samples is refined to: ``spp`` doubled until the floor,
    falling as ``1/spp``, is predicted at or below ``target``, and no further than ``most``; ``spp`` itself when
    the floor is already there or no doubling fits."""
    want = spp
    while floor * spp / want > target and want * 2 <= most:
        want *= 2
    return want
