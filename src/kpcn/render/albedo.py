"""Bring frames rendered before albedo revision 2 up to date without rendering them again.

Albedo revision 1 (``kpcn.integrator``) wrote Mitsuba's ``eval_diffuse_reflectance`` for every
BSDF. On a BSDF without a diffuse lobe that evaluates the glossy lobe at normal incidence: values up
to 37 on rough metals seen head-on and near 0 beside them, a guide that says nothing about the
surface. Revision 2 writes the directional albedo there instead.

A frame's albedo depends only on its first hit and its first BSDF sample, so it can be rendered
alone (``render_frame(..., albedo_only=True)``: a camera ray and three BSDF calls per sample, no
paths) with the frame's own seed and role and comes out as a full render would write it. The frame
keeps its radiance layers, normal, depth and their variances bit for bit; only ``albedo`` and
``albedoVariance`` are replaced, and the file is rewritten atomically.

``python -m kpcn.render dataset`` does this by itself for frames whose only difference from what it
would render is the albedo revision, and :mod:`kpcn.report` does it for its cached renders.
"""
from __future__ import annotations

import os
from typing import Any, Mapping

from ..integrator import ALBEDO_REVISION
from ..io import Frame, read_exr, write_exr
from .frame import render_frame

__all__ = ["ALBEDO_REVISION", "albedo_revision", "update_albedo"]

ALBEDO_LAYERS = ("albedo", "albedoVariance")


def albedo_revision(frame: Frame) -> int:
    """The albedo revision a kpcn-rendered frame was written with (1: before the header recorded it)."""
    return int(frame.meta.get("albedoRevision", 1))


def update_albedo(path: str | os.PathLike, scene: Any, spp: int, seed: int, *, role: int,
                  resolution: tuple[int, int] | None = None, pass_spp: int = 256, loaded=None,
                  meta: Mapping[str, Any] | None = None) -> Frame:
    """Re-render the albedo layers of the frame at ``path`` (rendered from ``scene`` with ``spp``,
    ``seed``, ``role``, ``resolution`` and ``pass_spp``, as :func:`kpcn.render.render_frame` takes them)
    and rewrite the file with every other layer as it was. ``meta``: header attributes to set as well
    (e.g. an updated render record). Returns the updated frame."""
    old = read_exr(path, require=ALBEDO_LAYERS)
    new = render_frame(scene, spp, seed, resolution, role=role, pass_spp=pass_spp, loaded=loaded, albedo_only=True)
    if new.shape != old.shape:
        raise ValueError(f"{path}: the frame is {old.shape[1]}x{old.shape[0]} but the scene renders "
                         f"{new.shape[1]}x{new.shape[0]}; not the frame's scene or resolution")
    layers = dict(old.layers)
    for name in ALBEDO_LAYERS:
        layers[name] = new[name]
    header = {**old.meta, **(meta or {}), "albedoRevision": ALBEDO_REVISION}
    write_exr(path, layers, header)
    return Frame(layers, header, os.fspath(path), dict(old.nonfinite))
