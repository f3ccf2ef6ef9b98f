"""Train a denoiser: ``python -m kpcn.train --config configs/small.yaml``.

Two stages, as in Bako et al. 2017:

1. ``stage1_steps``: every branch of the model's input spec on its own target
   (for the split specs: irradiance and log-specular of the reference);
2. ``stage2_steps``: the whole system fine-tuned on the final colour.

The model is built by name from ``model:`` (its keys are checked against the
model's config dataclass); its input spec decides which layers the data set
frames must have and what the inputs and targets are (:mod:`kpcn.inputs`).

Results go to the run folder ``<results_dir>/<name>/``:

* ``config.yaml`` — the resolved config;
* ``checkpoints/latest.pt`` — the training state (weights, optimiser, step,
  stage, RNG), loadable with ``weights_only=True``; ``checkpoints/step_<N>.pt``
  — the same state at each of the last ``train.keep_checkpoints`` checkpoints
  (every ``train.ckpt_every`` steps and at the end). Every file is written
  atomically (a crash leaves the previous file, never a half-written one);
* ``tb/`` — TensorBoard scalars and images;
* ``metrics.jsonl`` — one line of validation metrics per validation step;
* ``model.safetensors`` — the final weights, for :func:`kpcn.denoise`.

Guarantees of the run folder:

* **A new run never touches an earlier one.** Without ``--resume`` a run
  folder that already holds files is refused (exit code 2) before anything is
  written: ``--resume`` continues it, ``--overwrite`` (``train(...,
  overwrite=True)``) replaces it — kpcn's files of the old run (config,
  checkpoints, TensorBoard events, metrics, weights) are removed first, so
  nothing of the two runs mixes; files kpcn did not write are left alone — or
  another ``--name`` starts a run beside it.
* **Everything is checked before anything is written**: the config values
  (:mod:`kpcn.train_config`), the run folder, the checkpoint to resume from,
  and the data set (rendered into ``data.root`` when it has none and
  ``data.render_if_missing``). A mistake is one line on stderr and exit code 2
  (``--debug`` shows the traceback), and leaves the run folder as it was.
* **``--resume`` continues the same run**: the model section must equal the
  checkpoint's (an error names each key that differs); other settings may
  change (more steps, another lr, ...) and the changes are logged. It loads
  ``latest.pt``, or, when that is unreadable (empty, truncated, or a pickle
  that needs ``--trust-checkpoint``), the newest readable ``step_<N>.pt``,
  saying which one and why; when none is readable it stops with one line that
  names them all. Validation lines of steps after the resumed one are dropped
  from ``metrics.jsonl`` (one line per step) and their TensorBoard events are
  hidden (``purge_step``), as those steps are run again. The
  batch of step ``t`` depends only on the seed and ``t``, so a resumed run
  gives the same losses as an uninterrupted one.

Under ``torchrun --nproc_per_node=N`` the same command trains with
DistributedDataParallel (gloo on CPU, nccl on GPU); each rank takes its share
of every batch through a ``DistributedSampler`` and only rank 0 writes. The
checks run on every rank and the ranks agree on their outcome, so a mistake
stops all of them instead of leaving some waiting.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import pickle
import re
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, DistributedSampler

from .checkpoint import (
    CheckpointError,
    load_train_state,
    save_train_state,
    save_weights,
    set_rng_state,
    weights_sha256,
)
from .config import ConfigError, add_config_args, config_from_args, from_dict, save_config, to_dict
from .data import FrameDataset, PatchDataset, read_manifest
from .io import atomic_write
from .losses import create_loss
from .metrics import all_metrics, tonemap
from .models import create_model
from .train_config import RunConfig

log = logging.getLogger("kpcn.train")

__all__ = ["train", "build_model", "main", "RunConfig", "RunFolderError"]


class RunFolderError(ValueError):
    """The run folder cannot be used as asked (an earlier run is there); the message names it and the way out."""


# ----------------------------------------------------------------------------- distributed


@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0


def setup_distributed(device: str = "auto") -> Dist:
    """Initialise ``torch.distributed`` when launched by torchrun; pick the device."""
    use_cuda = torch.cuda.is_available() if device == "auto" else device.startswith("cuda")
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1:
        if not dist.is_initialized():
            dist.init_process_group("nccl" if use_cuda else "gloo")
        rank, world = dist.get_rank(), dist.get_world_size()
        local = int(os.environ.get("LOCAL_RANK", rank))
        dev = torch.device(f"cuda:{local}") if use_cuda else torch.device("cpu")
        if use_cuda:
            torch.cuda.set_device(dev)
        return Dist(rank, world, dev)
    return Dist(0, 1, torch.device("cuda" if use_cuda else "cpu"))


def _rank_of_world() -> int:
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling (to send it to the other ranks), else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def _agree(fn: Callable[[], Any]) -> Any:
    """``fn()`` on every rank; when it fails on any rank, every rank raises (nobody is left waiting).

    Rank 0 raises its own error when it has one, else the first failing rank's;
    the other ranks raise rank 0's error when rank 0 failed (marked with
    ``kpcn_echo`` so that only rank 0 prints it), else their own.
    """
    err: BaseException | None = None
    out = None
    try:
        out = fn()
    except Exception as exc:
        err = exc
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        errs: list = [None] * dist.get_world_size()
        dist.all_gather_object(errs, None if err is None else _portable(err))
        rank = dist.get_rank()
        if rank != 0 and errs[0] is not None:
            echo = errs[0]
            echo.kpcn_echo = True
            raise echo
        if err is None:
            other = next((e for e in errs if e is not None), None)
            if other is not None:
                other.kpcn_echo = rank != 0
                raise other
    if err is not None:
        raise err
    return out


# ----------------------------------------------------------------------------- model


def build_model(cfg: RunConfig) -> torch.nn.Module:
    """The model ``cfg.model`` names, built with its hyper-parameters."""
    return create_model(**cfg.model)


def _unwrap(model):
    return model.module if hasattr(model, "module") else model


# ----------------------------------------------------------------------------- data


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


def split_pairs(cfg: RunConfig, progress: bool = True):
    """``(train_pairs, val_pairs)``: the validation frames are ``data.val_root``'s or the last ``data.val_scenes`` scenes."""
    from .render import DatasetError

    root = ensure_dataset(cfg, _rank_of_world() == 0, progress)
    pairs = read_manifest(root, cfg.data.spp)
    if cfg.data.val_root:
        try:
            val_pairs = read_manifest(cfg.data.val_root, cfg.data.spp)
        except FileNotFoundError as exc:
            raise DatasetError(f"data.val_root: {exc}") from None
        return pairs, val_pairs
    scenes = sorted({p.scene for p in pairs})
    n_val = min(cfg.data.val_scenes, max(len(scenes) - 1, 0))
    val_scenes = set(scenes[len(scenes) - n_val :]) if n_val else set()
    return [p for p in pairs if p.scene not in val_scenes], [p for p in pairs if p.scene in val_scenes]


# ----------------------------------------------------------------------------- training


def stage_of(step: int, cfg: RunConfig) -> int:
    return 1 if step < cfg.train.stage1_steps else 2


def model_inputs(model, batch: dict) -> dict:
    """The entries of ``batch`` the model reads: its spec's branches and the albedo."""
    return {k: batch[k] for k in (*_unwrap(model).branches, "albedo")}


def compute_loss(out: dict, batch: dict, stage: int, cfg: RunConfig, branches) -> torch.Tensor:
    """Stage 1: the sum over branches of the loss in each branch's space; stage 2: on the colour."""
    if stage == 1:
        loss = create_loss(cfg.train.loss)
        return sum(loss(out[b], batch[f"y_{b}"]) for b in branches)
    loss = create_loss(cfg.train.stage2_loss or cfg.train.loss)
    return loss(out["color"], batch["y_color"])


def batches(ds: PatchDataset, cfg: RunConfig, d: Dist, start_step: int):
    """Yield ``(step, batch)`` from ``start_step``; the batch of a step depends only on seed and step."""
    per_rank = max(1, cfg.train.batch_size // d.world)
    steps_per_epoch = max(1, len(ds) // (per_rank * d.world))
    total = cfg.train.stage1_steps + cfg.train.stage2_steps
    step = start_step
    while step < total:
        epoch, within = divmod(step, steps_per_epoch)
        ds.resample(epoch)
        sampler = DistributedSampler(ds, num_replicas=d.world, rank=d.rank, shuffle=True, seed=cfg.train.seed, drop_last=True)
        sampler.set_epoch(epoch)
        loader = DataLoader(ds, batch_size=per_rank, sampler=sampler, drop_last=True)
        for i, batch in enumerate(loader):
            if i < within:
                continue
            if step >= total or i >= steps_per_epoch:
                break
            yield step, batch
            step += 1


@torch.no_grad()
def validate(model, frames: FrameDataset, device) -> dict[str, float]:
    """Mean metrics of the full-frame reconstruction over the validation frames."""
    model.eval()
    sums: dict[str, float] = {}
    for i in range(len(frames)):
        f = frames[i]
        inputs = {k: v[None].to(device) for k, v in model_inputs(model, f).items()}
        out = _unwrap(model)(inputs)
        pred = out["color"][0].permute(1, 2, 0).cpu().numpy()
        ref = f["y_color"].permute(1, 2, 0).numpy()
        for k, v in all_metrics(pred, ref).items():
            sums[k] = sums.get(k, 0.0) + v
        noisy = f["noisy_color"].permute(1, 2, 0).numpy()
        sums["noisy_relmse"] = sums.get("noisy_relmse", 0.0) + all_metrics(noisy, ref)["relmse"]
    model.train()
    return {k: v / max(len(frames), 1) for k, v in sums.items()}


def _set_seed(seed: int) -> None:
    import random

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _make_optimizer(model, lr: float):
    return torch.optim.Adam(model.parameters(), lr=lr)


def _tonemap_t(x: torch.Tensor) -> torch.Tensor:
    """:func:`kpcn.metrics.tonemap` of a ``(C, H, W)`` tensor, for TensorBoard images."""
    return torch.from_numpy(tonemap(x.detach().cpu().numpy())).float()


# ----------------------------------------------------------------------------- the run folder

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
    try:
        if state["optimizer"] is not None:
            optimizer.load_state_dict(state["optimizer"])
        set_rng_state(state["rng"])
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError, AttributeError) as exc:
        raise CheckpointError(f"{source}: its optimiser or RNG state cannot be restored "
                              f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None


# ----------------------------------------------------------------------------- training run


def train(cfg: RunConfig, resume: bool = False, progress: bool = True, trust_pickle: bool = False,
          overwrite: bool = False) -> dict:
    """Run training for ``cfg``; returns a summary (final step, last losses, last validation).

    ``resume`` continues the run in ``cfg.run_dir``; ``overwrite`` replaces one
    that is there (without either, a run folder holding files is refused:
    :class:`RunFolderError`). Everything is checked before anything is written;
    errors are :class:`~kpcn.config.ConfigError`, :class:`RunFolderError`,
    :class:`~kpcn.checkpoint.CheckpointError` or :class:`~kpcn.render.DatasetError`.
    """
    from tqdm import tqdm

    from_dict(type(cfg), to_dict(cfg))  # values set after loading are checked too (ConfigError)
    d = setup_distributed(cfg.train.device)
    if cfg.train.threads:
        torch.set_num_threads(cfg.train.threads)
    _set_seed(cfg.train.seed)
    run = cfg.run_dir
    ckpt_dir = run / "checkpoints"
    latest = ckpt_dir / "latest.pt"
    model = build_model(cfg).to(d.device)
    spec = model.input_spec

    # 1. the run folder and the checkpoint (every rank reads; nothing is written)
    def check_run() -> tuple[dict, Path | None]:
        _check_run_folder(run, resume, overwrite)
        if not resume:
            return {}, None
        state, source = find_resume_state(ckpt_dir, trust_pickle, d.device, verbose=d.main)
        if state:
            _check_resumable(cfg, model, state, source, log_changes=d.main)
        return state, source

    state, source = _agree(check_run)

    # 2. the data (rank 0 renders the default data set when it is missing)
    def load_data():
        train_pairs, val_pairs = split_pairs(cfg, progress=progress and d.main)
        if not train_pairs:
            raise ConfigError(f"data: no training frames in {cfg.data.root} (spp {cfg.data.spp or 'all'})")
        ds = PatchDataset(train_pairs, cfg.data.patch_size, cfg.data.patches_per_frame, cfg.data.sampling,
                          cfg.train.seed, spec=spec)
        per_rank = max(1, cfg.train.batch_size // d.world)
        if len(ds) // d.world < per_rank:
            raise ConfigError(f"train.batch_size: {cfg.train.batch_size} is more than the {len(ds)} training "
                              f"patches ({len(train_pairs)} frames of {cfg.data.root}); lower it, or raise "
                              f"data.patches_per_frame")
        if d.main and per_rank * d.world != cfg.train.batch_size:
            log.warning("train.batch_size %d is not a multiple of the %d processes: each takes %d patches, %d a step",
                        cfg.train.batch_size, d.world, per_rank, per_rank * d.world)
        return ds, FrameDataset(val_pairs, spec=spec)

    ds, val = _agree(load_data)

    # 3. rank 0 writes: only now does the run folder change
    step = int(state["step"]) if state else 0

    def prepare_folder() -> None:
        if not d.main:
            return
        if overwrite and run.is_dir():
            _clear_run(run)
        ckpt_dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, run / "config.yaml")
        if resume:
            _truncate_metrics(run / "metrics.jsonl", step)

    _agree(prepare_folder)

    stage2_lr = cfg.train.stage2_lr or cfg.train.lr
    optimizer = _make_optimizer(model, cfg.train.lr)
    if state:
        if state.get("stage", 1) == 2:  # the optimiser in the file is the fine-tuning one
            optimizer = _make_optimizer(model, stage2_lr)
        _restore_optimizer(optimizer, state, source)
        if d.main:
            log.info("resumed from %s at step %d", source, step)
    elif resume and d.main:
        log.info("no checkpoint in %s: starting from scratch", ckpt_dir)

    ddp = model
    if d.world > 1:
        ddp = torch.nn.parallel.DistributedDataParallel(model, device_ids=[d.device.index] if d.device.type == "cuda" else None)

    writer = None
    if d.main:
        from torch.utils.tensorboard import SummaryWriter

        # a resumed run hides the events logged after its checkpoint (they are logged again)
        writer = SummaryWriter(str(run / "tb"), purge_step=step + 1 if resume else None)
    total = cfg.train.stage1_steps + cfg.train.stage2_steps
    if d.main and step >= total:
        log.info("the checkpoint is at step %d, the schedule ends at %d: nothing to train", step, total)
    losses: list[float] = []
    last_val: dict = {}
    bar = tqdm(total=total, initial=min(step, total), desc=cfg.name, disable=not (progress and d.main),
               dynamic_ncols=True)
    t0 = time.perf_counter()
    n_patches = 0

    # the stage whose optimiser is in use (a checkpoint taken at the boundary still holds stage 1's)
    current_stage = state.get("stage", 1) if state else stage_of(step, cfg)
    config_dict = to_dict(cfg)
    final_step = max(step, total)

    def checkpoint(at_step: int) -> None:
        """``latest.pt`` and ``step_<N>.pt`` (atomic), then only the last ``keep_checkpoints`` step files are kept."""
        if not d.main:
            return
        save_train_state(latest, model, optimizer, at_step, config_dict, stage=current_stage)
        keep = cfg.train.keep_checkpoints
        if keep:
            save_train_state(ckpt_dir / f"step_{at_step}.pt", model, optimizer, at_step, config_dict,
                             stage=current_stage)
        for _, old in step_checkpoints(ckpt_dir)[keep:]:
            old.unlink()

    for step, batch in batches(ds, cfg, d, step):
        stage = stage_of(step, cfg)
        if stage != current_stage:  # entering stage 2: fresh Adam at the fine-tuning rate
            optimizer = _make_optimizer(model, stage2_lr)
            current_stage = stage
        batch = {k: v.to(d.device, non_blocking=True) for k, v in batch.items()}
        out = ddp(model_inputs(model, batch))
        loss = compute_loss(out, batch, stage, cfg, spec.branches)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"step {step}: non-finite loss {loss.item()}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.train.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.train.grad_clip)
        optimizer.step()
        loss_value = float(loss.detach())
        losses.append(loss_value)
        n_patches += batch["albedo"].shape[0] * d.world
        done = step + 1
        bar.update(1)
        if d.main and done % cfg.train.log_every == 0:
            rate = n_patches / (time.perf_counter() - t0)
            bar.set_postfix(stage=stage, loss=f"{np.mean(losses[-cfg.train.log_every:]):.4g}", patches_s=f"{rate:.1f}")
            writer.add_scalar(f"loss/stage{stage}", loss_value, done)
            writer.add_scalar("throughput/patches_per_s", rate, done)
        if done % cfg.train.ckpt_every == 0 or done == total:
            checkpoint(done)
        if d.main and len(val) and (done % cfg.train.val_every == 0 or done == total):
            last_val = validate(ddp, val, d.device)
            for k, v in last_val.items():
                writer.add_scalar(f"val/{k}", v, done)
            f = val[0]
            with torch.no_grad():
                pred = model({k: v[None].to(d.device) for k, v in model_inputs(model, f).items()})["color"][0].cpu()
            writer.add_images("val/noisy_denoised_reference", torch.stack([_tonemap_t(f["noisy_color"]), _tonemap_t(pred), _tonemap_t(f["y_color"])]), done)
            line = json.dumps({"step": done, **last_val})
            with open(run / "metrics.jsonl", "a") as fh:
                fh.write(line + "\n")
            bar.write(f"step {done}: " + ", ".join(f"{k} {v:.4g}" for k, v in last_val.items()))
        if d.world > 1 and (done % cfg.train.ckpt_every == 0):
            dist.barrier()
    bar.close()
    digest = weights_sha256(model.state_dict())
    digests = [digest]
    if d.world > 1:  # every rank must end with the same weights
        digests = [None] * d.world
        dist.all_gather_object(digests, digest)
        if len(set(digests)) != 1:
            raise RuntimeError(f"ranks ended with different weights: {digests}")
    if writer:
        writer.close()
    if d.main:
        # the final weights alone (weights-only), for kpcn.denoise
        save_weights(run / "model.safetensors", model, step=final_step, config=config_dict)
    elapsed = time.perf_counter() - t0
    return {"step": final_step, "losses": losses, "val": last_val, "seconds": elapsed,
            "patches_per_s": n_patches / elapsed if elapsed > 0 else 0.0, "rank": d.rank, "world": d.world,
            "weight_sha256_per_rank": digests}


def user_errors() -> tuple[type[BaseException], ...]:
    """The exceptions that are the user's to fix: ``python -m kpcn.train`` prints them as one line (exit code 2)."""
    from .render import DatasetError, RendererUnavailable

    return ConfigError, RunFolderError, CheckpointError, DatasetError, RendererUnavailable


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m kpcn.train", description="Train a kpcn denoiser.")
    add_config_args(p)
    p.add_argument("--name", help="run name: results go to <results_dir>/<name> (default: the config file's name)")
    p.add_argument("--results-dir", help="parent folder of run folders (default: results)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run: from <run>/checkpoints/latest.pt, or the newest readable step_<N>.pt")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the run that is in <run> (its checkpoints, metrics, events and weights are removed)")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="allow a latest.pt that only full unpickling can load (runs any code in it: trusted files only)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    try:
        try:
            defaults = {"name": Path(args.config).stem} if args.config else None
            cfg = config_from_args(RunConfig, args, {"name": args.name, "results_dir": args.results_dir}, defaults)
            summary = train(cfg, resume=args.resume, progress=not args.no_progress, trust_pickle=args.trust_checkpoint,
                            overwrite=args.overwrite)
        except user_errors() as exc:
            if args.debug:
                raise
            if not getattr(exc, "kpcn_echo", False):  # under torchrun, rank 0 prints what every rank stopped on
                print(f"python -m kpcn.train: {exc}", file=sys.stderr)
            return 2
        if summary["rank"] == 0:
            print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
        return 0
    finally:
        if dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()


if __name__ == "__main__":
    raise SystemExit(main())
