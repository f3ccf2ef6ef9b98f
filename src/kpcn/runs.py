"""The run folder: refusing or clearing an earlier run, and resuming one from its checkpoints.

Nothing here trains. :func:`_check_run_folder` refuses a new run in a folder
that holds one; :func:`_clear_run` removes an earlier run's files
(``--overwrite``); :func:`find_resume_state` picks the checkpoint to resume
from (``latest.pt``, else the newest readable ``step_<N>.pt``, see
:func:`step_checkpoints`); :func:`_check_resumable` checks that it fits the
configured model and loads its weights; :func:`_truncate_metrics` drops the
validation lines a resumed run writes again.
"""
from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path
from typing import Any, Mapping

from .checkpoint import CheckpointError, load_train_state, set_rng_state
from .config import ConfigError, to_dict
from .io import atomic_write
from .train_config import RunConfig

log = logging.getLogger("kpcn.train")  # the training log, whichever module of it speaks

__all__ = ["RunFolderError", "RUN_FILES", "RUN_DIRS", "step_checkpoints", "find_resume_state"]


class RunFolderError(ValueError):
    """The run folder cannot be used as asked (an earlier run is there); the message names it and the way out."""


#: what a run writes into its folder (``--overwrite`` removes these and nothing else)
RUN_FILES = ("config.yaml", "metrics.jsonl", "model.safetensors")
RUN_DIRS = ("checkpoints", "tb")
_STEP_FILE = re.compile(r"step_(\d+)\.pt")


def step_checkpoints(ckpt_dir: Path) -> list[tuple[int, Path]]:
    """``[(N, checkpoints/step_<N>.pt), ...]``, newest first."""
    if not ckpt_dir.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in ckpt_dir.iterdir() if (m := _STEP_FILE.fullmatch(p.name)) and p.is_file()]
    return sorted(found, reverse=True)


def _check_run_folder(run: Path, resume: bool, overwrite: bool) -> None:
    """Refuse a new run in a folder that holds one, unless ``overwrite`` (nothing is written here)."""
    if resume and overwrite:
        raise RunFolderError(f"{run}: --resume continues a run and --overwrite replaces it; pass one of them")
    if run.exists() and not run.is_dir():
        raise RunFolderError(f"{run}: exists and is not a folder; choose another --name or --results-dir")
    if resume or overwrite or not run.is_dir():
        return
    entries = sorted(p.name + ("/" if p.is_dir() else "") for p in run.iterdir())
    if entries:
        shown = ", ".join(entries[:4]) + (f" and {len(entries) - 4} more" if len(entries) > 4 else "")
        raise RunFolderError(f"{run}: holds an earlier run ({shown}); pass --resume to continue it, --overwrite to "
                             f"replace it, or choose another --name")


def _clear_run(run: Path) -> None:
    """Remove kpcn's files of an earlier run from ``run`` (``--overwrite``); other files are left alone."""
    removed = []
    for name in RUN_DIRS:
        if (run / name).is_dir():
            shutil.rmtree(run / name)
            removed.append(name + "/")
    for name in RUN_FILES:
        for p in [run / name, *run.glob(f".{name}.*.tmp*")]:  # and atomic_write's leftovers of a crash
            if p.is_file() or p.is_symlink():
                p.unlink()
                removed.append(p.name)
    kept = sorted(p.name for p in run.iterdir()) if run.is_dir() else []
    log.info("--overwrite: removed the earlier run's %s from %s%s", ", ".join(removed) or "nothing", run,
             f" (kept {', '.join(kept)}: not written by kpcn)" if kept else "")


def _truncate_metrics(path: Path, upto: int) -> None:
    """Drop the validation lines of steps after ``upto`` (a resumed run writes them again)."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines()
    keep = []
    for ln in lines:
        try:
            if int(json.loads(ln)["step"]) <= upto:
                keep.append(ln)
        except (ValueError, KeyError, TypeError):  # a line cut short by a crash
            pass
    if keep != lines:
        log.info("%s: dropped %d line(s) of steps after %d", path, len(lines) - len(keep), upto)
        atomic_write(path, lambda tmp: Path(tmp).write_text("".join(x + "\n" for x in keep)))


# ----------------------------------------------------------------------------- resuming


def _without_path(exc: CheckpointError, path: Path) -> str:
    text = str(exc)
    return text[len(f"{path}: "):] if text.startswith(f"{path}: ") else text


def find_resume_state(ckpt_dir: Path, trust_pickle: bool = False, map_location="cpu",
                      verbose: bool = True) -> tuple[dict, Path | None]:
    """``(state, path)`` of the checkpoint to resume from: ``latest.pt``, else the newest readable ``step_<N>.pt``.

    ``({}, None)`` when there is no checkpoint at all; a :class:`CheckpointError`
    naming every file (and why) when none is readable.
    """
    latest = ckpt_dir / "latest.pt"
    candidates = ([latest] if latest.exists() else []) + [p for _, p in step_checkpoints(ckpt_dir)]
    skipped: list[tuple[Path, str]] = []
    for path in candidates:
        try:
            state = load_train_state(path, trust_pickle=trust_pickle, map_location=map_location)
        except CheckpointError as exc:
            skipped.append((path, _without_path(exc, path)))
            if verbose:
                log.warning("%s: cannot resume from it: %s", path, skipped[-1][1])
            continue
        if verbose and path != latest:
            why = "is unreadable" if latest.exists() else "is missing"
            log.warning("resuming from %s (step %s): %s %s", path, state.get("step"), latest.name, why)
        return state, path
    if skipped:
        listed = "; ".join(f"{p.name}: {why}" for p, why in skipped)
        raise CheckpointError(f"{ckpt_dir}: no checkpoint there can be resumed from ({listed}); start the run again "
                              f"with --overwrite, or under another --name")
    return {}, None


def _model_differences(saved_name, saved_hparams: Mapping, model) -> list[str]:
    before = to_dict({**dict(saved_hparams), "name": saved_name})
    now = to_dict(model.hparams())
    missing = object()
    out = []
    for k in sorted(set(before) | set(now), key=lambda k: (k != "name", k)):
        a, b = before.get(k, missing), now.get(k, missing)
        if a != b:
            out.append(f"model.{k}: {'(absent)' if a is missing else repr(a)} in the checkpoint, "
                       f"{'(absent)' if b is missing else repr(b)} now")
    return out


def _flat(d: Any, prefix: str = "") -> dict:
    if not isinstance(d, Mapping):
        return {prefix: d}
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, Mapping) else {f"{prefix}{k}": v})
    return out


def _check_resumable(cfg: RunConfig, model, state: dict, source: Path, log_changes: bool) -> None:
    """The checkpoint's model must be ``cfg``'s (its weights are loaded into ``model``); other changes are logged."""
    name, hparams = state.get("model_name"), state.get("hparams")
    if isinstance(name, str) and isinstance(hparams, Mapping):
        diffs = _model_differences(name, hparams, model)
        if diffs:
            raise ConfigError(f"{source}: --resume needs the model the run was trained with: {'; '.join(diffs)}. "
                              f"Resume with the run's own model section (its config.yaml), or start a new run "
                              f"(another --name, or --overwrite to replace this one)")
    try:
        model.load_state_dict(state["model"])
    except (RuntimeError, TypeError, AttributeError) as exc:
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        detail = next((ln for ln in lines if ln.startswith(("size mismatch", "Missing key", "Unexpected key"))),
                      lines[0] if lines else type(exc).__name__)
        raise CheckpointError(f"{source}: its weights do not fit the configured model {cfg.model}: "
                              f"{detail[:300]}") from None
    saved = state.get("config")
    if log_changes and isinstance(saved, Mapping):
        ignore = ("name", "results_dir")
        before = {k: v for k, v in _flat({k: v for k, v in saved.items() if k not in ignore and k != "model"}).items()}
        now = _flat({k: v for k, v in to_dict(cfg).items() if k not in ignore and k != "model"})
        changes = [f"{k}: {before.get(k, '(absent)')!r} -> {now.get(k, '(absent)')!r}"
                   for k in sorted(set(before) | set(now)) if before.get(k) != now.get(k)]
        if changes:
            log.info("resuming %s with changed settings: %s", source, "; ".join(changes))


def _restore_optimizer(optimizer, state: dict, source: Path) -> None:
    """The file's optimiser moments and RNG state into ``optimizer``, built from the run's config: its groups' rate
    factors (``train.lr_mult``) stay the config's, which a resume may have changed (``load_state_dict`` would put
    back the file's)."""
    factors = [g.get("lr_mult") for g in optimizer.param_groups]
    try:
        if state["optimizer"] is not None:
            optimizer.load_state_dict(state["optimizer"])
            for group, factor in zip(optimizer.param_groups, factors):
                if factor is not None:
                    group["lr_mult"] = factor
        set_rng_state(state["rng"])
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError, AttributeError) as exc:
        raise CheckpointError(f"{source}: its optimiser or RNG state cannot be restored "
                              f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
