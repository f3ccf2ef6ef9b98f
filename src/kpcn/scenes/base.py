"""Mitsuba access and scene-dict utilities shared by the scene builders.

:func:`_mi` returns the ``mitsuba`` module with a variant set (``llvm_ad_rgb``
unless the caller already chose one); :func:`_bitmap` wraps a numpy image;
:func:`copy_scene_dict` copies a scene dict whose leaves cannot be deep-copied.
"""

from __future__ import annotations

import numpy as np


def _mi():
    """Return the ``mitsuba`` module with kpcn's variant set (see :func:`kpcn.render.scene.ensure_variant`)."""
    import mitsuba as mi

    if mi.variant() is None:
        from ..render.scene import ensure_variant

        ensure_variant()
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
