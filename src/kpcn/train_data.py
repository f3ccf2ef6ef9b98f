"""The training data: the data set folder (rendered when missing) and its train/validation split."""
from __future__ import annotations

import logging
from pathlib import Path

from .data import CONVERGED_SPP, read_manifest
from .distributed import _agree, _rank_of_world
from .train_config import RunConfig

log = logging.getLogger("kpcn.train")  # the training log, whichever module of it speaks

__all__ = ["ensure_dataset", "split_pairs", "converged_pairs", "CONVERGED_SPP", "store_dir", "root_spp", "balance_spp"]


def _is_default_dataset(status, d) -> bool:
    """Whether the data set ``status`` describes is the built-in one ``data.render_*`` asks for (or part of it)."""
    from .render import manifest as mf

    want = mf.settings(d.render_scenes, d.render_spp, d.render_ref_spp, d.render_resolution, d.render_first_seed)
    have = dict(status.settings)
    if status.legacy and status.rendered < d.render_scenes:  # maybe an interrupted render of it
        have["n_scenes"] = d.render_scenes
    return not mf.differences(have, want)


def ensure_dataset(cfg: RunConfig, is_main: bool = True, progress: bool = True) -> Path:
    """The training data folder ``data.root``.

    A data set already there is used as it is (its own settings; :func:`kpcn.data.read_manifest`
    checks it is complete). When there is none — or there is an interrupted render of
    the built-in data set ``data.render_*`` describes — :func:`kpcn.render.ensure_dataset`
    renders or finishes it (if ``data.render_if_missing``; else a :class:`~kpcn.render.DatasetError`
    with the command that does). Under torchrun rank 0 renders while the others wait, and an
    error on rank 0 stops every rank.
    """
    from .render import dataset_status
    from .render import ensure_dataset as ensure_rendered

    d = cfg.data
    root = Path(d.root)

    def work() -> None:
        if not is_main:
            return
        status = dataset_status(root)
        if status.manifest is not None and not _is_default_dataset(status, d):
            log.info("training on the data set in %s", root)
            return
        ensure_rendered(root, d.render_scenes, d.render_spp, d.render_ref_spp, tuple(d.render_resolution),
                        d.render_first_seed, render_if_missing=d.render_if_missing, progress=progress)

    _agree(work)  # the other ranks wait here for rank 0
    return root


#: outdated data sets named one by one in training's warnings; the others are counted in one line
NAMED_OUTDATED = 3
#: what an older albedo or normal revision (kpcn.integrator) lacks, as the warnings say it
_ALBEDO_BEFORE = {1: "Mitsuba's eval_diffuse_reflectance: up to 37 on rough metals"}
_NORMAL_BEFORE = {1: "blind to bump and normal maps", 2: "blind to normal maps"}


def warn_outdated_albedo(roots) -> int:
    """Warn about data sets whose Mitsuba frames were rendered before the current albedo or normal revision
    (:mod:`kpcn.render.albedo`), the first :data:`NAMED_OUTDATED` by name and command and the rest in one line;
    returns how many such frames there are."""
    from .render import dataset_status
    from .render.albedo import ALBEDO_REVISION, NORMAL_REVISION
    from .render.cycles_scene import is_generated

    total, named, more = 0, 0, []
    for root in roots:
        status = dataset_status(root)
        frames = [rec for sc in (status.manifest or {}).get("scenes", []) for rec in sc.get("frames", {}).values()]
        mitsuba = [rec for rec in frames if not is_generated(rec.get("source"))]
        albedo_revs = [rec.get("albedo", 1) for rec in mitsuba]
        old = sum(1 for v in albedo_revs if v < ALBEDO_REVISION)
        normal_revs = [rec.get("normal", 1) for rec in mitsuba]
        old_normal = sum(1 for v in normal_revs if v < NORMAL_REVISION)
        total += max(old, old_normal)
        if not (old or old_normal):
            continue
        if named == NAMED_OUTDATED:
            more.append((root, max(old, old_normal)))
            continue
        named += 1
        if old:
            rev = min(albedo_revs)
            log.warning("%s: %d of %d frames have albedo revision %d (%s); `%s` rewrites their albedo layers only",
                        root, old, len(frames), rev, _ALBEDO_BEFORE.get(rev, "outdated"), status.command())
        if old_normal:
            rev = min(normal_revs)
            log.warning("%s: %d of %d frames have normal revision %d (%s); `%s` rewrites their normal layers only",
                        root, old_normal, len(frames), rev, _NORMAL_BEFORE.get(rev, "outdated"), status.command())
    if more:
        log.warning("%d more data sets (%d frames, %s ...) have outdated albedo or normal layers; `python -m "
                    "kpcn.render dataset` with each one's own arguments rewrites those layers only", len(more),
                    sum(n for _, n in more), more[0][0])
    return total


def split_pairs(cfg: RunConfig, progress: bool = True):
    """``(train_pairs, val_pairs)``: the validation frames are ``data.val_root``'s or the last ``data.val_scenes``
    scenes (by name) of ``data.root`` and ``data.extra_roots`` together."""
    from .render import DatasetError

    root = ensure_dataset(cfg, _rank_of_world() == 0, progress)
    if _rank_of_world() == 0:
        warn_outdated_albedo([root, *cfg.data.extra_roots])
    pairs = read_manifest(root, root_spp(cfg.data, root))
    ref_spp = dict.fromkeys((p.scene for p in pairs), _ref_spp(root))  # one manifest read per data set
    for extra in cfg.data.extra_roots:  # more rendered data sets (complete ones; never rendered here)
        try:
            more = read_manifest(extra, root_spp(cfg.data, extra))
        except FileNotFoundError as exc:
            raise DatasetError(f"data.extra_roots: {exc}") from None
        clash = sorted({p.scene for p in more} & {p.scene for p in pairs})
        if clash:
            raise DatasetError(f"data.extra_roots: {extra} repeats scene names of the other data sets "
                               f"({', '.join(clash[:5])}{' ...' if len(clash) > 5 else ''}); render it with "
                               f"another --first-seed")
        pairs += more
        ref_spp.update(dict.fromkeys((p.scene for p in more), _ref_spp(extra)))
    if cfg.data.val_root:
        try:
            val = read_manifest(cfg.data.val_root, root_spp(cfg.data, cfg.data.val_root))
        except FileNotFoundError as exc:
            raise DatasetError(f"data.val_root: {exc}") from None
        train = pairs
    else:
        scenes = sorted({p.scene for p in pairs})
        n_val = min(cfg.data.val_scenes, max(len(scenes) - 1, 0))
        val_scenes = set(scenes[len(scenes) - n_val :]) if n_val else set()
        train = [p for p in pairs if p.scene not in val_scenes]
        val = [p for p in pairs if p.scene in val_scenes]
    # the converged pairs join the training pairs however the validation frames were chosen
    converged = []
    if cfg.data.converged_inputs:
        clean = [p for p in train if ref_spp[p.scene] >= cfg.data.converged_min_ref_spp]
        if not clean:
            raise DatasetError(f"data.converged_min_ref_spp={cfg.data.converged_min_ref_spp}: no training data set "
                               f"has references of that many spp (they have "
                               f"{' '.join(map(str, sorted(set(ref_spp.values()))))}); lower it or render one")
        converged = converged_pairs(clean)
    if cfg.data.balance_spp:
        train, converged = balance_spp(train + converged)
    return train + converged * cfg.data.converged_weight, val


def balance_spp(pairs) -> tuple[list, list]:
    """``(inputs, converged)``: ``pairs`` with each spp's pairs (the converged ones one more spp) repeated
    ``round(n_max / n)`` times, ``n`` their count and ``n_max`` the largest count."""
    groups: dict[int, list] = {}
    for p in pairs:
        groups.setdefault(p.spp, []).append(p)
    n_max = max((len(g) for g in groups.values()), default=0)
    out = {spp: g * max(1, round(n_max / len(g))) for spp, g in groups.items()}
    converged = out.pop(CONVERGED_SPP, [])
    return [p for g in out.values() for p in g], converged


def root_spp(data, root) -> list[int] | None:
    """The input spp trained on from the data set in ``root``: ``data.spp_by_root``'s entry for the longest folder
    at or above it, else ``data.spp`` (None: all)."""
    path = Path(root).resolve()
    best, spp = -1, data.spp
    for folder, counts in data.spp_by_root.items():
        f = Path(folder).resolve()
        if path.is_relative_to(f) and len(f.parts) > best:
            best, spp = len(f.parts), counts
    return spp


def _ref_spp(root) -> int:
    """The reference spp of the rendered data set in ``root`` (as its manifest records it)."""
    from .render import dataset_status

    return int(dataset_status(Path(root)).settings["ref_spp"])


def converged_pairs(pairs):
    """One (reference, reference) pair per scene of ``pairs``: a converged input whose target is itself."""
    from .data import FramePair

    refs = {p.scene: p.reference_path for p in pairs}
    return [FramePair(scene, CONVERGED_SPP, ref, ref) for scene, ref in sorted(refs.items())]


def store_dir(cfg: RunConfig, spec) -> Path | None:
    """The patch store folder of ``spec`` that ``data.store`` names (None: ``none``, frames kept in memory).

    ``auto``: ``<data.root>/.store/<spec name>``; any other value is a folder that gets a
    ``<spec name>`` subfolder (so models with other input specs never share entries).
    """
    from .inputs import get_input_spec
    from .store import default_store_dir

    value = cfg.data.store.strip()
    if value.lower() == "none":
        return None
    if value.lower() == "auto":
        return default_store_dir(cfg.data.root, spec)
    return Path(value).expanduser() / get_input_spec(spec).name
