"""Replacing the non-finite values (NaN, ±Inf) of a frame's layers."""
from __future__ import annotations

import numpy as np


def sanitize_layers(layers: dict[str, np.ndarray]) -> dict[str, int]:
    """Replace NaN/-Inf by 0 and +Inf by the layer's largest finite value, in place.

    Returns the number of replaced values per layer (only layers with any).
    """
    counts = {}
    for name, arr in layers.items():
        with np.errstate(invalid="ignore", over="ignore"):  # inf - inf, or a finite sum past float32's range
            clean = arr.dtype.kind == "f" and np.isfinite(arr.sum())
        if clean:
            continue  # a NaN or an infinity makes the sum non-finite: one summing pass, no mask, for a clean layer
        bad = ~np.isfinite(arr)
        n = int(bad.sum())
        if not n:
            continue
        finite = arr[~bad]
        top = float(finite.max()) if finite.size else 0.0
        fixed = np.where(np.isposinf(arr), max(top, 0.0), arr)
        fixed = np.where(np.isnan(fixed) | np.isneginf(fixed), 0.0, fixed).astype(np.float32)
        layers[name] = fixed
        counts[name] = n
    return counts
