"""Bring frames rendered before the current albedo, normal or denoising-guide revision up to date without rendering
them again.

Albedo revision 1 (``kpcn.integrator``) wrote Mitsuba's ``eval_diffuse_reflectance`` for every
BSDF. On a BSDF without a diffuse lobe that evaluates the glossy lobe at normal incidence: values up
to 37 on rough metals seen head-on and near 0 beside them, a guide that says nothing about the
surface. Revision 2 writes the directional albedo there instead. Normal revision 1 wrote Mitsuba's
interpolated shading normal, blind to bump maps; revision 2 writes the bumped normal (:mod:`kpcn.bump`).

The denoising guides (``denoisingAlbedo``, ``denoisingNormal``: OIDN's, which follow glass and mirrors;
:data:`kpcn.integrator.DENOISING_REVISION`) are added to frames rendered before them the same way.

A frame's albedo and normal depend only on its first hit and its first BSDF sample, and its denoising guides
on the delta bounces that follow, so they can be rendered alone (``render_frame(..., albedo_only=True)``: a
camera ray, a few BSDF calls per sample and, behind glass and mirrors, up to
:data:`kpcn.integrator.CHASE_BOUNCES` more rays, no light paths) with the frame's own seed and role and come out
as a full render would write them. The frame keeps its radiance layers, depth and their variances bit for
bit; only the outdated layers (``albedo``/``albedoVariance``, ``normal``/``normalVariance``,
``denoisingAlbedo``/``denoisingNormal``) are replaced or added, and the file is rewritten atomically.

``python -m kpcn.render dataset`` does this by itself for frames whose only difference from what it
would render is the albedo or normal revision (training reads neither denoising guide, and a data set's frames
rendered before them stay without), and :mod:`kpcn.report` does it for its cached renders, the denoising guides
included.
"""
from __future__ import annotations

import os
from typing import Any, Iterable, Mapping

from ..constants import OIDN_ALBEDO, OIDN_NORMAL
from ..integrator import ALBEDO_REVISION, DENOISING_REVISION, NORMAL_REVISION
from ..io import Frame, read_exr, write_exr
from .frame import render_frame

__all__ = ["ALBEDO_REVISION", "DENOISING_REVISION", "NORMAL_REVISION", "outdated_first_hit", "update_first_hit"]

#: the layers each first-hit revision covers
FIRST_HIT_LAYERS = {"albedo": ("albedo", "albedoVariance"), "normal": ("normal", "normalVariance"),
                    "denoising": (OIDN_ALBEDO, OIDN_NORMAL)}
#: per kind: the header key, the revision the integrator writes, the revision of a header without the key (a
#: frame from before the denoising guides has none: 0)
_HEADER = {"albedo": ("albedoRevision", ALBEDO_REVISION, 1), "normal": ("normalRevision", NORMAL_REVISION, 1),
           "denoising": ("denoisingRevision", DENOISING_REVISION, 0)}


def outdated_first_hit(frame: Frame) -> list[str]:
    """Which of ``"albedo"``, ``"normal"``, ``"denoising"`` (``denoisingAlbedo`` and ``denoisingNormal``) the frame
    holds at an older revision than the integrator writes, or lacks."""
    return [k for k, (key, rev, absent) in _HEADER.items() if int(frame.meta.get(key, absent)) != rev]


def update_first_hit(path: str | os.PathLike, scene: Any, spp: int, seed: int, *, role: int,
                     which: Iterable[str] = ("albedo", "normal"), resolution: tuple[int, int] | None = None,
                     pass_spp: int = 256, loaded=None, meta: Mapping[str, Any] | None = None) -> Frame:
    """Re-render the first-hit layers ``which`` (``"albedo"``, ``"normal"``, ``"denoising"``) of the frame at ``path``
    (rendered from ``scene`` with ``spp``, ``seed``, ``role``, ``resolution`` and ``pass_spp``, as
    :func:`kpcn.render.render_frame` takes them) and rewrite the file with every other layer as it was.
    ``meta``: header attributes to set as well (e.g. an updated render record). Returns the updated frame."""
    which = [w for w in FIRST_HIT_LAYERS if w in set(which)]
    names = [n for w in which for n in FIRST_HIT_LAYERS[w]]
    # a kind a frame can be without (revision 0 where its header has no key) is added, not required
    old = read_exr(path, require=[n for w in which if _HEADER[w][2] for n in FIRST_HIT_LAYERS[w]])
    new = render_frame(scene, spp, seed, resolution, role=role, pass_spp=pass_spp, loaded=loaded, albedo_only=True)
    if new.shape != old.shape:
        raise ValueError(f"{path}: the frame is {old.shape[1]}x{old.shape[0]} but the scene renders "
                         f"{new.shape[1]}x{new.shape[0]}; not the frame's scene or resolution")
    layers = dict(old.layers)
    for name in names:
        layers[name] = new[name]
    header = {**old.meta, **(meta or {}), **{_HEADER[w][0]: _HEADER[w][1] for w in which}}
    write_exr(path, layers, header)
    return Frame(layers, header, os.fspath(path), dict(old.nonfinite))
