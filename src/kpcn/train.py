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

This module is the entry point (:func:`train`, :func:`main`); its parts live in
:mod:`kpcn.distributed` (ranks, cross-rank agreement), :mod:`kpcn.runs` (the
run folder, resuming), :mod:`kpcn.train_data` (the data set and its split),
:mod:`kpcn.train_init` (the weights to start from: ``train.init``, ``train.init_extend``) and
:mod:`kpcn.train_steps` (batches, losses, validation).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from .augment import augment_batch, check_exposure_spec, check_mix_spec, exposure_batch
from .checkpoint import CheckpointError, save_train_state, save_weights, weights_sha256
from .config import ConfigError, add_config_args, config_from_args, from_dict, save_config, to_dict
from .data import FrameDataset, PatchDataset
from .distributed import _agree, setup_distributed
from .runs import (
    RunFolderError,
    _check_resumable,
    _check_run_folder,
    _clear_run,
    _restore_optimizer,
    _truncate_metrics,
    find_resume_state,
    step_checkpoints,
)
from .train_config import RunConfig
from .train_data import split_pairs, store_dir
from .train_init import freeze_except, load_init
from .train_steps import (
    _make_optimizer,
    _set_seed,
    _tonemap_t,
    batches,
    build_model,
    build_teacher,
    compute_loss,
    distill_targets,
    model_inputs,
    set_lr,
    stage_of,
    validate,
    with_detail,
)

log = logging.getLogger("kpcn.train")

__all__ = ["train", "build_model", "main", "RunConfig", "RunFolderError"]

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
    try:
        model.set_compute_dtype(cfg.train.precision)
    except ValueError as exc:
        raise ConfigError(f"train.precision: {exc}") from None
    spec = model.input_spec
    if cfg.data.converged_max_noise is not None and spec.colour_variance is None:
        raise ConfigError(f"data.converged_max_noise: the input spec {spec.name} carries no variance to tell "
                          f"converged pixels from noisy ones; set it to null or train a model that reads variances")
    exposure_keys = cfg.train.exposure_range or model.exposure_range
    if cfg.train.exposure_augment:
        if exposure_keys is None:
            raise ConfigError("train.exposure_augment: give train.exposure_range (the keys to draw from) or a model "
                              "with an exposure_range")
        try:
            check_exposure_spec(spec)
        except ValueError as exc:
            raise ConfigError(f"train.exposure_augment: {exc}") from None
    if cfg.data.spp_mix:
        try:
            check_mix_spec(spec)
        except ValueError as exc:
            raise ConfigError(f"data.spp_mix: {exc}") from None
    if cfg.train.detail_stage and model.detail_regression is None:  # a stage implies a spec with the normal
        raise ConfigError(f"train.detail_stage: the model has no detail stage to train for (set model.detail_radius "
                          f"> 0 with an input spec that reads the normal; {spec.name} reads {spec.layers})")

    # 1. the run folder, the checkpoint and the weights to start from (every rank reads; nothing is written)
    def check_run() -> tuple[dict, Path | None, str | None]:
        _check_run_folder(run, resume, overwrite)
        state, source = find_resume_state(ckpt_dir, trust_pickle, d.device, verbose=d.main) if resume else ({}, None)
        if state:
            _check_resumable(cfg, model, state, source, log_changes=d.main)
        # a resumed run continues from its checkpoint; otherwise train.init is loaded (and refused) here
        return state, source, load_init(model, cfg) if cfg.train.init and not state else None

    state, source, init_source = _agree(check_run)
    trained = freeze_except(model, cfg.train.train_only)
    if cfg.train.train_only and d.main:
        log.info("train.train_only: %d of %d parameters trained", trained, sum(p.numel() for p in model.parameters()))

    # 2. the data (rank 0 renders the default data set when it is missing)
    def load_data():
        train_pairs, val_pairs = split_pairs(cfg, progress=progress and d.main)
        if not train_pairs:
            raise ConfigError(f"data: no training frames in {cfg.data.root} (spp {cfg.data.spp or 'all'})")
        # the patch store (data.store): every rank prepares it, one at a time (a lock), so rank 0 builds
        # what is missing or stale and the others find it done
        ds = PatchDataset(train_pairs, cfg.data.patch_size, cfg.data.patches_per_frame, cfg.data.sampling,
                          cfg.train.seed, spec=spec, store=store_dir(cfg, spec), progress=progress and d.main,
                          store_workers=cfg.data.prepare_workers, label_spp=cfg.train.distill_min_spp is not None,
                          spp_mix=cfg.data.spp_mix)
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
    teacher = _agree(lambda: build_teacher(cfg, model, d.device)) if cfg.train.distill_min_spp is not None else None

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
    optimizer = _make_optimizer(model, cfg.train.lr, cfg.train.lr_mult)
    if state:
        if state.get("stage", 1) == 2:  # the optimiser in the file is the fine-tuning one
            optimizer = _make_optimizer(model, stage2_lr, cfg.train.lr_mult)
        _restore_optimizer(optimizer, state, source)
        if d.main:
            log.info("resumed from %s at step %d", source, step)
    else:
        if resume and d.main:
            log.info("no checkpoint in %s: starting from scratch", ckpt_dir)
        if init_source and d.main:
            log.info("initialised from %s", init_source)

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
            optimizer = _make_optimizer(model, stage2_lr, cfg.train.lr_mult)
            current_stage = stage
        batch = {k: v.to(d.device, non_blocking=True) for k, v in batch.items()}
        if cfg.train.augment:  # the same transforms for the same (seed, step, rank): resumable
            batch = augment_batch(batch, spec, torch.Generator().manual_seed(cfg.train.seed * 1_000_003 + step * 7919 + d.rank))
        if cfg.train.exposure_augment:
            batch = exposure_batch(batch, spec, torch.Generator().manual_seed(cfg.train.seed * 1_000_033 + step * 7907
                                                                              + d.rank),
                                   cfg.train.exposure_augment, exposure_keys)
        if teacher is not None:  # after augmenting: the teacher sees what the model sees
            batch = distill_targets(teacher, batch, cfg.train.distill_min_spp,
                                    model if cfg.train.detail_stage else None, cfg.train.distill_tta)
        lr_now = set_lr(optimizer, step, cfg)
        out = ddp(model_inputs(model, batch))
        if cfg.train.detail_stage and stage == 2:  # the colour the pipeline gives: the network's, then its detail stage
            out = with_detail(model, out, batch)
        loss = compute_loss(out, batch, stage, cfg, spec.branches, spec)
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
            writer.add_scalar("lr", lr_now, done)
            writer.add_scalar("throughput/patches_per_s", rate, done)
        if done % cfg.train.ckpt_every == 0 or done == total:
            checkpoint(done)
        if d.main and len(val) and (done % cfg.train.val_every == 0 or done == total):
            first: list = []  # the first frame's colour as validation scored it (after the stage, in eval mode)
            last_val = validate(ddp, val, d.device, cfg.train.detail_stage, keep=first)
            for k, v in last_val.items():
                writer.add_scalar(f"val/{k}", v, done)
            f = val[0]
            shown = [_tonemap_t(f["noisy_color"]), _tonemap_t(first[0]), _tonemap_t(f["y_color"])]
            writer.add_images("val/noisy_denoised_reference", torch.stack(shown), done)
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
    if d.world > 1:  # every rank leaves together: a rank that tears the group down while rank 0 still writes can
        dist.barrier()  # abort at exit (gloo: "terminate called without an active exception"; once in the suite)
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
