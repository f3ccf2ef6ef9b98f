"""Mitsuba access and scene-dict utilities shared by the scene builders.

:func:`_mi` returns the ``mitsuba`` module with a variant set (``llvm_ad_rgb``
unless the caller already chose one); :func:`_bitmap` wraps a numpy image;
:func:`copy_scene_dict` copies a scene dict whose leaves cannot be deep-copied.
"""

from __future__ import annotations

import numpy as np


def _mi():
    """Return the ``mitsuba`` module with a variant set (default llvm_ad_rgb)."""
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb")
        import drjit as dr

        try:
            ver = tuple(dr.detail.llvm_version())
        except Exception:  # pragma: no cover - API differences
            ver = None
        if ver is not None and ver[0] < 17:
            raise RuntimeError(
                f"Mitsuba's llvm_ad_rgb variant needs LLVM >= 17, found {ver}. "
                "Install LLVM 19 (Debian/Ubuntu: `apt-get install -y libllvm19`)."
            )
    return mi


def _bitmap(arr: np.ndarray):
    return _mi().Bitmap(np.ascontiguousarray(arr, dtype=np.float32))


def copy_scene_dict(scene: dict) -> dict:
    """Copy the nested dicts of a scene dict; leaf objects (Bitmap, transforms,
    lists of numbers) are shared.  ``copy.deepcopy`` fails on Mitsuba objects."""
    out = {}
    for k, v in scene.items():
        if isinstance(v, dict):
            out[k] = copy_scene_dict(v)
        elif isinstance(v, list):
            out[k] = list(v)
        else:
            out[k] = v
    return out
