"""Render Mitsuba 3 scenes into kpcn's multi-layer EXR contract.

Python API::

    from kpcn.render import render_frame
    frame = render_frame("scene.xml", spp=8, seed=1, resolution=(256, 256))
    frame = render_frame("scene.xml", spp=8, params={"albedo": "0.3"})  # the file's $albedo
    frame = render_frame("test:glossy", spp=1024, seed=7)     # a built-in test scene
    frame = render_frame("random:42", spp=4)                   # a procedural scene

Command line::

    python -m kpcn.render frame scene.xml --spp 8 --out noisy.exr --ref-spp 1024 --ref-out ref.exr
    python -m kpcn.render dataset --out data/train --scenes 64 --spp 2 4 8 16 --ref-spp 1024

Data sets (:func:`render_dataset`, :func:`ensure_dataset`) record whether they
are complete and what each frame was rendered with, so an interrupted render
resumes and a folder never mixes settings (:mod:`~kpcn.render.manifest`,
:mod:`~kpcn.render.record`); :class:`DatasetError` names what is wrong.

Any scene ``mitsuba.load_file`` reads renders (``<include>``, ``$name``
parameters, meshes next to the file, read-only folders), as do Mitsuba scene
dicts. Every render uses the ``kpcn_split`` integrator (:mod:`kpcn.integrator`)
on the ``llvm_ad_rgb`` variant. The renderer overrides what it must —
integrator, film size, box reconstruction filter, RGB float32 pixel format,
independent sampler, sample count — and logs what it changed; scenes it cannot
render faithfully (no image camera, participating media) raise
:class:`SceneError`. Large sample counts are rendered in passes of at most
``pass_spp`` samples with independent seeds, whose moments are combined, so
memory stays bounded.

Modules: :mod:`~kpcn.render.scene` (variant, loading, overrides),
:mod:`~kpcn.render.frame` (one frame), :mod:`~kpcn.render.dataset` (data sets),
:mod:`~kpcn.render.manifest` (manifest format, completeness, :class:`DatasetError`),
:mod:`~kpcn.render.record` (frame render records, scene fingerprints),
:mod:`~kpcn.render.cli` (command line).
"""
from .cli import main
from .dataset import DatasetConfig, ensure_dataset, render_dataset
from .manifest import DatasetError, DatasetStatus, dataset_status
from .frame import (RenderStats, extend_frame, merge_frames, mix_frames, n_passes, pass_seed, render_frame,
                    render_sample_map, render_to_exr)
from .scene import CAMERAS, LLVM_HELP, VARIANT, RendererUnavailable, SceneError, ensure_variant, load_scene

__all__ = [
    "CAMERAS", "LLVM_HELP", "VARIANT", "RendererUnavailable", "SceneError", "ensure_variant", "load_scene",
    "RenderStats", "extend_frame", "merge_frames", "mix_frames", "n_passes", "pass_seed", "render_frame",
    "render_sample_map", "render_to_exr",
    "render_dataset", "DatasetConfig", "main",
    "ensure_dataset", "DatasetError", "DatasetStatus", "dataset_status",
]
