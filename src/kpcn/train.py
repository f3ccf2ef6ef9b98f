"""Train a denoiser: ``python -m kpcn.train --config configs/small.yaml``.

Two stages, as in Bako et al. 2017:

1. ``stage1_steps``: every branch of the model's input spec on its own target
   (for the split specs: irradiance and log-specular of the reference);
2. ``stage2_steps``: the whole system fine-tuned on the final colour.

The model is built by name from ``model:`` (its keys are checked against the
model's config dataclass); its input spec decides which layers the data set
frames must have and what the inputs and targets are (:mod:`kpcn.inputs`).

Results go to ``<results_dir>/<name>/``: ``config.yaml`` (the resolved config),
``checkpoints/latest.pt`` (training state, written atomically: weights,
optimiser, step, RNG; loads with ``weights_only=True``), ``tb/`` (TensorBoard
scalars and images), ``metrics.jsonl`` (validation) and ``model.safetensors``
(the final weights, for :func:`kpcn.denoise`). ``--resume`` continues from
``latest.pt`` and gives the same losses as an uninterrupted run: the batch of
step ``t`` depends only on the seed and ``t``.

Under ``torchrun --nproc_per_node=N`` the same command trains with
DistributedDataParallel (gloo on CPU, nccl on GPU); each rank takes its share
of every batch through a ``DistributedSampler`` and only rank 0 writes.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

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
from .config import ConfigError, add_config_args, config_from_args, save_config, to_dict
from .data import FrameDataset, PatchDataset, read_manifest
from .losses import create_loss
from .metrics import all_metrics, tonemap
from .models import create_model
from .train_config import RunConfig

log = logging.getLogger("kpcn.train")

__all__ = ["train", "build_model", "main", "RunConfig"]


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


# ----------------------------------------------------------------------------- model


def build_model(cfg: RunConfig) -> torch.nn.Module:
    """The model ``cfg.model`` names, built with its hyper-parameters."""
    return create_model(**cfg.model)


def _unwrap(model):
    return model.module if hasattr(model, "module") else model


# ----------------------------------------------------------------------------- data


def ensure_dataset(cfg: RunConfig, is_main: bool = True) -> Path:
    """The training data folder; renders the built-in default data set when it is missing."""
    root = Path(cfg.data.root)
    if (root / "manifest.json").exists():
        return root
    if not cfg.data.render_if_missing:
        raise FileNotFoundError(f"{root}: no manifest.json and data.render_if_missing is false")
    if is_main:
        from .render import render_dataset

        d = cfg.data
        log.info("rendering the default data set into %s (%d scenes)", root, d.render_scenes)
        render_dataset(root, d.render_scenes, d.render_spp, d.render_ref_spp, tuple(d.render_resolution), d.render_first_seed)
    if dist.is_initialized():
        dist.barrier()
    return root


def split_pairs(cfg: RunConfig):
    root = ensure_dataset(cfg, not dist.is_initialized() or dist.get_rank() == 0)
    pairs = read_manifest(root, cfg.data.spp)
    if cfg.data.val_root:
        return pairs, read_manifest(cfg.data.val_root, cfg.data.spp)
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


def train(cfg: RunConfig, resume: bool = False, progress: bool = True, trust_pickle: bool = False) -> dict:
    """Run training for ``cfg``; returns a summary (final step, last losses, last validation)."""
    from tqdm import tqdm

    d = setup_distributed(cfg.train.device)
    if cfg.train.threads:
        torch.set_num_threads(cfg.train.threads)
    _set_seed(cfg.train.seed)
    run = cfg.run_dir
    ckpt_dir = run / "checkpoints"
    latest = ckpt_dir / "latest.pt"
    model = build_model(cfg).to(d.device)
    state: dict = {}
    if resume and latest.exists():
        state = load_train_state(latest, trust_pickle=trust_pickle, map_location=d.device)
        try:
            model.load_state_dict(state["model"])
        except RuntimeError as exc:
            raise CheckpointError(f"{latest}: its weights do not fit the configured model {cfg.model}: "
                                  f"{str(exc).splitlines()[0]}") from None
    if d.main:
        ckpt_dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, run / "config.yaml")

    spec = model.input_spec
    train_pairs, val_pairs = split_pairs(cfg)
    ds = PatchDataset(train_pairs, cfg.data.patch_size, cfg.data.patches_per_frame, cfg.data.sampling, cfg.train.seed,
                      spec=spec)
    val = FrameDataset(val_pairs, spec=spec)

    stage2_lr = cfg.train.stage2_lr or cfg.train.lr
    optimizer = _make_optimizer(model, cfg.train.lr)
    step = 0
    if state:
        step = state["step"]
        if state.get("stage", 1) == 2:  # the optimiser in the file is the fine-tuning one
            optimizer = _make_optimizer(model, stage2_lr)
        if state["optimizer"] is not None:
            optimizer.load_state_dict(state["optimizer"])
        set_rng_state(state["rng"])
        if d.main:
            log.info("resumed from %s at step %d", latest, step)
    elif resume and d.main:
        log.info("no checkpoint in %s: starting from scratch", ckpt_dir)

    ddp = model
    if d.world > 1:
        ddp = torch.nn.parallel.DistributedDataParallel(model, device_ids=[d.device.index] if d.device.type == "cuda" else None)

    writer = None
    if d.main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run / "tb"))
    total = cfg.train.stage1_steps + cfg.train.stage2_steps
    losses: list[float] = []
    last_val: dict = {}
    bar = tqdm(total=total, initial=step, desc=cfg.name, disable=not (progress and d.main), dynamic_ncols=True)
    t0 = time.perf_counter()
    n_patches = 0

    # the stage whose optimiser is in use (a checkpoint taken at the boundary still holds stage 1's)
    current_stage = state.get("stage", 1) if state else stage_of(step, cfg)
    config_dict = to_dict(cfg)

    def checkpoint(at_step: int) -> None:
        if d.main:
            save_train_state(latest, model, optimizer, at_step, config_dict, stage=current_stage)

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
        save_weights(run / "model.safetensors", model, step=total, config=config_dict)
    elapsed = time.perf_counter() - t0
    return {"step": total, "losses": losses, "val": last_val, "seconds": elapsed,
            "patches_per_s": n_patches / elapsed if elapsed > 0 else 0.0, "rank": d.rank, "world": d.world,
            "weight_sha256_per_rank": digests}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m kpcn.train", description="Train a kpcn denoiser.")
    add_config_args(p)
    p.add_argument("--name", help="run name: results go to <results_dir>/<name> (default: the config file's name)")
    p.add_argument("--results-dir", help="parent folder of run folders (default: results)")
    p.add_argument("--resume", action="store_true", help="continue from <run>/checkpoints/latest.pt")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="allow a latest.pt that only full unpickling can load (runs any code in it: trusted files only)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    try:
        defaults = {"name": Path(args.config).stem} if args.config else None
        cfg = config_from_args(RunConfig, args, {"name": args.name, "results_dir": args.results_dir}, defaults)
        summary = train(cfg, resume=args.resume, progress=not args.no_progress, trust_pickle=args.trust_checkpoint)
    except (ConfigError, CheckpointError) as exc:
        if args.debug:
            raise
        print(f"python -m kpcn.train: {exc}", file=sys.stderr)
        return 2
    if summary["rank"] == 0:
        print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    if dist.is_initialized():
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
