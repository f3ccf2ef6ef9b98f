"""Rendering data sets: noisy inputs at several sample counts and a reference per scene.

A data set knows whether it is complete (``"complete"`` in its manifest, see
:mod:`kpcn.render.manifest`) and what each of its frames was rendered with (a
render record in the frame's EXR header and in the manifest, see
:mod:`kpcn.render.record`). :func:`render_dataset` reuses a frame on disk only
when its record matches what it would render now, and renders every other
frame again, logging one line per frame — so a folder never mixes settings.
:func:`ensure_dataset` is what training calls: it returns a complete data set
with the requested settings, resumes an incomplete one, and never overwrites a
data set rendered with other settings.
"""
from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ..io import atomic_write, read_exr, write_exr
from . import manifest as mf
from .frame import extend_frame, render_to_exr
from .manifest import DatasetError, DatasetStatus, dataset_status
from .cycles_scene import GENERATED, generated_variant, is_generated
from ..integrator import ALBEDO_REVISION, NORMAL_REVISION
from .albedo import update_first_hit
from .record import (HEADER_KEY, fewer_samples, first_hit_differences, frame_record, more_samples, scene_identity,
                     stale_reason)
from .refine import REF_SPP_MAX, reference_floor, refined_spp
from .scene import load_scene

log = logging.getLogger("kpcn.render")

MAX_DEPTH = 8  #: path length of data set frames (render_frame's default)
PASS_SPP = 256  #: samples per pass (render_frame's default; the pass split changes the noise)

__all__ = ["DatasetConfig", "DatasetError", "DatasetStatus", "dataset_status", "render_dataset", "ensure_dataset"]


@dataclass
class DatasetConfig:
    """What ``python -m kpcn.render dataset`` renders (``--config FILE``, ``--set key=value`` or the flags)."""

    out: str = "data/train"  #: the data set folder (manifest.json, one folder per scene)
    scenes: int = 16  #: procedural scenes random:<first_seed> ... random:<first_seed + scenes - 1>
    first_seed: int = 0
    spp: list[int] = field(default_factory=lambda: [2, 4, 8, 16, 32])  #: input sample counts
    ref_spp: int = 1024
    resolution: tuple[int, int] = (128, 128)  #: (width, height)
    #: a reference whose own noise adds more relMSE than this (:func:`kpcn.render.refine.reference_floor`) gets
    #: more samples, its own kept (:func:`kpcn.render.refine.refined_spp`), up to ``ref_spp_max``; None: ref_spp
    ref_floor_target: float | None = None
    ref_spp_max: int = REF_SPP_MAX
    #: mitsuba: kpcn's procedural Mitsuba scenes (full split with variances); cycles: variants of kpcn's
    #: generated Blender Cycles scene, cycles:generated:<first_seed> ... (no variance layers; needs kpcn[blender])
    renderer: str = "mitsuba"

    def __post_init__(self) -> None:
        from ..config import ConfigError

        if self.renderer not in ("mitsuba", "cycles"):
            raise ConfigError(f"renderer: expected mitsuba or cycles, got {self.renderer!r}")
        try:
            check_settings(self.scenes, self.spp, self.ref_spp, self.resolution, self.first_seed,
                           self.ref_floor_target, self.ref_spp_max)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

    def scene_list(self) -> list[str] | None:
        """The scenes to render (None: the procedural Mitsuba ones)."""
        if self.renderer == "mitsuba":
            return None
        return [f"{GENERATED}:{self.first_seed + i}" for i in range(self.scenes)]


def check_settings(n_scenes, spp, ref_spp, resolution, first_seed, ref_floor_target=None,
                   ref_spp_max=REF_SPP_MAX) -> None:
    """ValueError naming the setting (and its ``python -m kpcn.render dataset`` flag) that is invalid."""
    if n_scenes is not None and n_scenes < 1:
        raise ValueError(f"scenes (--scenes): must be >= 1, got {n_scenes}")
    if first_seed < 0:
        raise ValueError(f"first_seed (--first-seed): must be >= 0, got {first_seed}")
    spp = list(spp)
    need = "spp and ref_spp: every sample count must be >= 2 (variances need two samples)"
    if not spp or min(spp) < 2:
        raise ValueError(f"{need}; spp (--spp) got {spp}")
    if ref_spp < 2:
        raise ValueError(f"{need}; ref_spp (--ref-spp) got {ref_spp}")
    res = list(resolution)
    if len(res) != 2 or min(res) < 1:
        raise ValueError(f"resolution (--resolution): width and height must be >= 1, got {res}")
    if ref_floor_target is not None and not ref_floor_target > 0:
        raise ValueError(f"ref_floor_target (--ref-floor-target): must be > 0 (or none), got {ref_floor_target}")
    if ref_floor_target is not None and ref_spp_max < ref_spp:
        raise ValueError(f"ref_spp_max (--ref-spp-max): must be >= ref_spp ({ref_spp}), got {ref_spp_max}")


def _cycles_frame(scene: str, path: Path, spp: int, seed: int, role: int, resolution, rec: dict) -> None:
    """One frame of kpcn's generated Cycles scene (``cycles:generated[:<N>]``), stored in the contract layout
    (the Cycles passes mapped to colour, diffuse, specular, albedo, normal, depth: no variances) with its
    render record."""
    from .cycles import cycles_seed, render_cycles

    variant = generated_variant(scene)
    raw = path.with_name(path.stem + ".cycles.exr")
    try:
        done = render_cycles(None, raw, spp, seed=cycles_seed(seed, role), resolution=tuple(resolution), variant=variant)
        fr = read_exr(raw, require=("color", "diffuse", "specular", "albedo", "normal", "depth"))
    finally:
        raw.unlink(missing_ok=True)
    layers = {k: v for k, v in fr.layers.items() if "." not in k}  # the contract's layers, not the raw passes
    write_exr(path, layers, {"spp": spp, "renderTimeSeconds": done.seconds, "scene": scene,
                             HEADER_KEY: json.dumps(rec, sort_keys=True)})


def render_dataset(
    out_dir: str | os.PathLike,
    n_scenes: int,
    spp_list: Sequence[int] = (2, 4, 8, 16, 32),
    ref_spp: int = 1024,
    resolution: tuple[int, int] = (128, 128),
    first_seed: int = 0,
    scenes: Sequence[Any] | None = None,
    progress: bool = True,
    ref_floor_target: float | None = None,
    ref_spp_max: int = REF_SPP_MAX,
) -> Path:
    """Render procedural scenes (or ``scenes``) into ``out_dir`` with a manifest.

    Layout: ``out_dir/<scene>/input_<spp>spp.exr`` for each input spp, and
    ``out_dir/<scene>/reference.exr``; ``out_dir/manifest.json`` lists them
    (format: :mod:`kpcn.render.manifest`). Scene ``i`` is ``random:<first_seed + i>``
    (or ``scenes[i]``: XML paths, ``test:``/``random:`` names or dicts) and
    its frames use seed ``first_seed + i``.

    Frames already on disk are kept when their render record (resolution, spp,
    seed, role, scene source and fingerprint, ...) equals what would be
    rendered now — so an interrupted run resumes — and rendered again
    otherwise, with one logged line per frame naming what differed; a frame
    that differs only in having fewer samples (a larger ``ref_spp`` for the
    same data set) keeps them and gets the passes that follow
    (:func:`kpcn.render.extend_frame`): raising ``ref_spp`` costs only the
    samples added. With ``ref_floor_target``, a Mitsuba reference whose own noise adds more relMSE than that
    (:func:`kpcn.render.refine.reference_floor`) gets more samples the same way, doubled as often as
    :func:`kpcn.render.refine.refined_spp` predicts (and again while it falls short), up to ``ref_spp_max``: its
    record says its own spp, and a reference refined so is kept by a later run with the same settings. Before the
    first frame is changed the manifest says ``"complete": false`` (with the
    new settings and the scenes finished so far); ``"complete": true`` is
    written after the last scene. Files of an earlier data set that the new
    one does not list (other spp, more scenes) are left in place, unlisted.

    Raises:
        ValueError: invalid settings (nothing is written).
        SceneError: a scene cannot be loaded.
    """
    from tqdm import tqdm

    check_settings(None if scenes is not None else n_scenes, spp_list, ref_spp, resolution, first_seed,
                   ref_floor_target, ref_spp_max)
    spp_list = [int(s) for s in dict.fromkeys(spp_list)]
    resolution = (int(resolution[0]), int(resolution[1]))
    out = Path(out_dir)
    items = list(scenes) if scenes is not None else [f"random:{first_seed + i}" for i in range(n_scenes)]
    if not items:
        raise ValueError("scenes: the scene list is empty")
    manifest = {"format": mf.FORMAT, "complete": False, "procedural": scenes is None,
                **mf.settings(len(items), spp_list, ref_spp, resolution, first_seed, ref_floor_target, ref_spp_max),
                "max_depth": MAX_DEPTH, "pass_spp": PASS_SPP, "scenes": []}
    try:
        old = mf.load_manifest(out)
    except DatasetError as exc:
        log.warning("%s (it is replaced)", exc)
        old = None
    if old is not None:
        try:
            diff = mf.differences(mf.manifest_settings(old), manifest)
        except (KeyError, TypeError, ValueError, IndexError):
            diff = ["an unreadable manifest"]
        if diff:
            log.info("%s: the folder holds a data set with other settings (%s); its frames are checked one by one "
                     "and rendered again where they differ", out, ", ".join(diff))

    def save() -> None:
        text = json.dumps(manifest, indent=1)
        atomic_write(out / mf.MANIFEST, lambda tmp: Path(tmp).write_text(text))

    changing = False  # once a frame is rendered, the manifest says "complete": false until the end
    for i, sc in enumerate(tqdm(items, desc="render", disable=not progress)):
        sname = f"scene_{i:04d}" if isinstance(sc, dict) else str(sc).replace(":", "_").replace("/", "_")
        folder = out / sname
        seed = first_seed + i
        source, fingerprint, to_render = scene_identity(sc, resolution)
        # role 1 = reference; each input spp gets a role of its own so no two frames share noise
        jobs = [("input", s, folder / f"input_{s}spp.exr", 2 + s) for s in spp_list]
        jobs.append(("reference", ref_spp, folder / "reference.exr", 1))
        entry = {"name": sname, "source": source if isinstance(sc, (str, os.PathLike)) else "dict", "seed": seed,
                 "fingerprint": fingerprint,
                 "inputs": {str(s): path.relative_to(out).as_posix() for _, s, path, _ in jobs[:-1]},
                 "reference": jobs[-1][2].relative_to(out).as_posix(), "frames": {}}
        loaded = None
        for role, s, path, noise_role in jobs:
            rec = frame_record(role=role, spp=s, seed=seed, noise_role=noise_role, resolution=resolution,
                               max_depth=MAX_DEPTH, pass_spp=PASS_SPP, source=source, fingerprint=fingerprint,
                               albedo=None if is_generated(sc) else ALBEDO_REVISION,
                               normal=None if is_generated(sc) else NORMAL_REVISION)
            refines = role == "reference" and ref_floor_target is not None and not is_generated(sc)
            had = more_samples(path, rec, ref_spp_max) if refines else None
            if had is not None:  # refined earlier to a floor: its own spp
                rec = {**rec, "spp": had}
            reason = stale_reason(path, rec)
            if reason is not None:
                if not changing:
                    save()
                    changing = True
                first_hit = first_hit_differences(path, rec)
                if first_hit:  # the albedo or normal layers alone, at a fraction of a render's cost
                    log.info("updating the %s of %s: %s", " and ".join(first_hit), path, reason)
                    loaded = loaded or load_scene(to_render, resolution)
                    update_first_hit(path, to_render, s, seed, role=noise_role, which=first_hit, resolution=resolution,
                                     pass_spp=PASS_SPP, loaded=loaded, meta={HEADER_KEY: json.dumps(rec, sort_keys=True)})
                    entry["frames"][path.relative_to(out).as_posix()] = rec
                    continue
                had = None if is_generated(sc) else fewer_samples(path, rec)
                if had is not None:  # a frame of the same render with fewer samples: its passes kept, more added
                    log.info("adding %d samples to %s (%d -> %d spp)", s - had, path, had, s)
                    loaded = loaded or load_scene(to_render, resolution)
                    more = extend_frame(read_exr(path), to_render, s, seed, role=noise_role, pass_spp=PASS_SPP,
                                        loaded=loaded, max_depth=MAX_DEPTH)
                    write_exr(path, more.layers, {**more.meta, HEADER_KEY: json.dumps(rec, sort_keys=True)})
                    entry["frames"][path.relative_to(out).as_posix()] = rec
                    continue
                if reason != "missing":
                    log.info("re-rendering %s: %s", path, reason)
                folder.mkdir(parents=True, exist_ok=True)
                if is_generated(sc):
                    _cycles_frame(sc, path, s, seed, noise_role, resolution, rec)
                else:
                    loaded = loaded or load_scene(to_render, resolution)
                    render_to_exr(to_render, path, s, seed=seed, role=noise_role, loaded=loaded, max_depth=MAX_DEPTH,
                                  pass_spp=PASS_SPP, meta={HEADER_KEY: json.dumps(rec, sort_keys=True)})
            entry["frames"][path.relative_to(out).as_posix()] = rec
        if ref_floor_target is not None and not is_generated(sc):
            path = jobs[-1][2]
            key = path.relative_to(out).as_posix()
            rec = _refine(path, entry["frames"][key], ref_floor_target, ref_spp_max,
                          lambda: loaded or load_scene(to_render, resolution), to_render, seed,
                          None if changing else save)
            changing = changing or rec is not entry["frames"][key]
            entry["frames"][key] = rec
        manifest["scenes"].append(entry)
        if changing:
            save()
    manifest["complete"] = True
    if changing or old != manifest:
        save()
    return out


def _refine(path: Path, rec: dict, target: float, most: int, scene_loaded, to_render, seed: int,
            before_change) -> dict:
    """The reference at ``path`` (record ``rec``) given more samples while its floor is above ``target`` (see
    :func:`render_dataset`); returns its record. ``before_change`` (or None) runs before the file is changed."""
    loaded, fr = None, read_exr(path)
    while True:
        floor = reference_floor(fr)
        want = fr.spp if floor is None else refined_spp(fr.spp, floor, target, most)
        if want <= fr.spp:
            return rec
        if before_change is not None:
            before_change()
            before_change = None
        log.info("refining %s: its noise adds relMSE %.3g at %d spp (target %g): %d -> %d spp", path, floor, fr.spp,
                 target, fr.spp, want)
        loaded = loaded or scene_loaded()
        fr = extend_frame(fr, to_render, want, seed, role=int(rec["noise_role"]), pass_spp=int(rec["pass_spp"]),
                          loaded=loaded, max_depth=int(rec["max_depth"]))
        rec = {**rec, "spp": want}
        write_exr(path, fr.layers, {**fr.meta, HEADER_KEY: json.dumps(rec, sort_keys=True)})


def ensure_dataset(
    root: str | os.PathLike,
    n_scenes: int,
    spp: Sequence[int],
    ref_spp: int,
    resolution: Sequence[int],
    first_seed: int,
    render_if_missing: bool = True,
    progress: bool = True,
    ref_floor_target: float | None = None,
    ref_spp_max: int = REF_SPP_MAX,
) -> Path:
    """The procedural data set at ``root`` with these settings, complete; rendered or resumed if allowed.

    * complete, with these settings and every listed frame on disk: returned at
      once (only the manifest is read and the files stat'ed);
    * no data set there, or an incomplete one (an interrupted render) or one
      missing frames, with these settings: rendered or finished by
      :func:`render_dataset` (frames already rendered with these settings are
      kept) when ``render_if_missing``, else :class:`DatasetError`;
    * a data set with other settings (complete or not): :class:`DatasetError`
      naming each difference — it is never overwritten here (render it anew
      with ``python -m kpcn.render dataset``, or point at another folder).

    Settings are compared as ``scenes`` (n_scenes), ``first_seed``, the set of
    ``spp``, ``ref_spp``, ``resolution`` (width, height) and the references' refinement
    (``ref_floor_target``, ``ref_spp_max``; none unless given). A legacy manifest
    (written before completeness was recorded) counts as complete when it lists
    ``n_scenes`` scenes ``random:<first_seed + i>`` with these settings, and as
    incomplete when it lists a shorter prefix of them.

    Raises:
        DatasetError: as above; the message names the folder, what is missing
            or differs, and the command that renders the requested data set.
        ValueError: invalid settings.
    """
    check_settings(n_scenes, spp, ref_spp, resolution, first_seed, ref_floor_target, ref_spp_max)
    root = Path(root)
    want = mf.settings(n_scenes, spp, ref_spp, resolution, first_seed, ref_floor_target, ref_spp_max)
    cmd = mf.render_command(root, want)
    st = dataset_status(root)
    if st.manifest is None:
        if not render_if_missing:
            raise DatasetError(f"{root}: no data set (no {mf.MANIFEST}); render it with `{cmd}`")
        log.info("rendering the data set %s (%s)", root, mf.describe(want))
    else:
        have = st.settings
        if st.complete is None and st.rendered < n_scenes \
                and not mf.differences({**have, "n_scenes": n_scenes}, want):
            diff, incomplete = [], True  # a legacy manifest of this data set's first scenes: an interrupted render
        else:
            diff, incomplete = mf.differences(have, want), st.complete is False
        if diff:
            state = f"an incomplete ({st.rendered} of {have['n_scenes']} scenes)" if incomplete else "a complete"
            raise DatasetError(f"{root}: holds {state} data set with other settings: {'; '.join(diff)}. It is not "
                               f"overwritten: use another folder, or render this one anew with `{cmd}` (frames "
                               f"that differ are rendered again)")
        if not incomplete and not st.missing:
            return root
        what = (f"incomplete data set: {st.rendered} of {n_scenes} scenes rendered" if incomplete
                else mf.missing_text(st.missing))
        if not render_if_missing:
            raise DatasetError(f"{root}: {what}; finish it with `{cmd}` (it resumes and keeps the finished frames)")
        log.info("%s: %s; resuming", root, what)
    render_dataset(root, n_scenes, spp, ref_spp, tuple(resolution), first_seed, progress=progress,
                   ref_floor_target=ref_floor_target, ref_spp_max=ref_spp_max)
    return root
