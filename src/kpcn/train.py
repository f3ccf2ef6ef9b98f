"""Train a denoiser: ``python -m kpcn.train --config configs/small.yaml``.

Two stages, as in Bako et al. 2017:

1. ``stage1_steps``: the diffuse and specular branches, each on its own target
   (irradiance and log-specular of the reference);
2. ``stage2_steps``: the whole system fine-tuned on the final colour.

Results go to ``<results_dir>/<name>/``: ``config.yaml`` (the resolved config),
``checkpoints/latest.pt`` and ``checkpoints/step_<N>.pt`` (written atomically,
with optimiser, step and RNG state), ``tb/`` (TensorBoard scalars and images),
``metrics.jsonl`` (validation). ``--resume`` continues from ``latest.pt`` and
gives the same losses as an uninterrupted run: the batch of step ``t`` depends
only on the seed and ``t``.

Under ``torchrun --nproc_per_node=N`` the same command trains with
DistributedDataParallel (gloo on CPU, nccl on GPU); each rank takes its share
of every batch through a ``DistributedSampler`` and only rank 0 writes.
"""
from __future__ import annotations

import json
import logging
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, DistributedSampler

from .config import Config, config_from_args, make_parser, save_config
from .data import FrameDataset, PatchDataset, read_manifest
from .io import atomic_write
from .losses import create_loss
from .metrics import all_metrics, tonemap
from .models import create_model

log = logging.getLogger("kpcn.train")


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


# ----------------------------------------------------------------------------- checkpoints


def save_checkpoint(path: Path, model, optimizer, step: int, cfg: Config, extra: dict | None = None) -> None:
    """Write a checkpoint atomically (temporary file, then rename)."""
    state = {
        "model": _unwrap(model).state_dict(),
        "model_name": cfg.model.name,
        "model_kwargs": model_kwargs(cfg),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "step": step,
        "config": cfg.to_dict(),
        "rng": {
            "torch": torch.get_rng_state(),
            "numpy": np.random.get_state(),
            "python": random.getstate(),
        },
        **(extra or {}),
    }
    atomic_write(path, lambda tmp: torch.save(state, tmp))


def load_checkpoint(path: str | Path, map_location="cpu") -> dict:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:
        raise RuntimeError(f"{path}: not a readable kpcn checkpoint ({exc})") from exc


def model_kwargs(cfg: Config) -> dict:
    m = cfg.model
    return {"layers": m.layers, "width": m.width, "conv_size": m.conv_size, "kernel_size": m.kernel_size, **m.extra}


def build_model(cfg: Config) -> torch.nn.Module:
    return create_model(cfg.model.name, **model_kwargs(cfg))


def weights_sha256(state_dict: dict) -> str:
    """A digest of a model's weights (to check that distributed ranks agree)."""
    import hashlib

    h = hashlib.sha256()
    for k in sorted(state_dict):
        h.update(k.encode())
        h.update(state_dict[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _unwrap(model):
    return model.module if hasattr(model, "module") else model


# ----------------------------------------------------------------------------- data


def ensure_dataset(cfg: Config, is_main: bool = True) -> Path:
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


def split_pairs(cfg: Config):
    root = ensure_dataset(cfg, not dist.is_initialized() or dist.get_rank() == 0)
    pairs = read_manifest(root, cfg.data.spp)
    if cfg.data.val_root:
        return pairs, read_manifest(cfg.data.val_root, cfg.data.spp)
    scenes = sorted({p.scene for p in pairs})
    n_val = min(cfg.data.val_scenes, max(len(scenes) - 1, 0))
    val_scenes = set(scenes[len(scenes) - n_val :]) if n_val else set()
    return [p for p in pairs if p.scene not in val_scenes], [p for p in pairs if p.scene in val_scenes]


# ----------------------------------------------------------------------------- training


def stage_of(step: int, cfg: Config) -> int:
    return 1 if step < cfg.train.stage1_steps else 2


def compute_loss(out: dict, batch: dict, stage: int, cfg: Config) -> torch.Tensor:
    if stage == 1:
        loss = create_loss(cfg.train.loss)
        return loss(out["diffuse"], batch["y_diffuse"]) + loss(out["specular"], batch["y_specular"])
    loss = create_loss(cfg.train.stage2_loss or cfg.train.loss)
    return loss(out["color"], batch["y_color"])


def batches(ds: PatchDataset, cfg: Config, d: Dist, start_step: int):
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
        out = _unwrap(model)(f["x_diffuse"][None].to(device), f["x_specular"][None].to(device), f["albedo"][None].to(device))
        pred = out["color"][0].permute(1, 2, 0).cpu().numpy()
        ref = f["y_color"].permute(1, 2, 0).numpy()
        for k, v in all_metrics(pred, ref).items():
            sums[k] = sums.get(k, 0.0) + v
        noisy = f["noisy_color"].permute(1, 2, 0).numpy()
        sums["noisy_relmse"] = sums.get("noisy_relmse", 0.0) + all_metrics(noisy, ref)["relmse"]
    model.train()
    return {k: v / max(len(frames), 1) for k, v in sums.items()}


def _set_seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _make_optimizer(model, lr: float):
    return torch.optim.Adam(model.parameters(), lr=lr)


def _tonemap_t(x: torch.Tensor) -> torch.Tensor:
    """:func:`kpcn.metrics.tonemap` of a ``(C, H, W)`` tensor, for TensorBoard images."""
    return torch.from_numpy(tonemap(x.detach().cpu().numpy())).float()


def train(cfg: Config, resume: bool = False, progress: bool = True) -> dict:
    """Run training for ``cfg``; returns a summary (final step, last losses, last validation)."""
    from tqdm import tqdm

    d = setup_distributed(cfg.train.device)
    if cfg.train.threads:
        torch.set_num_threads(cfg.train.threads)
    _set_seed(cfg.train.seed)
    run = cfg.run_dir
    ckpt_dir = run / "checkpoints"
    if d.main:
        ckpt_dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, run / "config.yaml")

    train_pairs, val_pairs = split_pairs(cfg)
    ds = PatchDataset(train_pairs, cfg.data.patch_size, cfg.data.patches_per_frame, cfg.data.sampling, cfg.train.seed)
    val = FrameDataset(val_pairs)

    model = build_model(cfg).to(d.device)
    stage2_lr = cfg.train.stage2_lr or cfg.train.lr
    optimizer = _make_optimizer(model, cfg.train.lr)
    step = 0
    state: dict = {}
    latest = ckpt_dir / "latest.pt"
    if resume and latest.exists():
        state = load_checkpoint(latest, d.device)
        model.load_state_dict(state["model"])
        step = state["step"]
        if state.get("stage", 1) == 2:  # the optimiser in the file is the fine-tuning one
            optimizer = _make_optimizer(model, stage2_lr)
        if state["optimizer"] is not None:
            optimizer.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
        random.setstate(state["rng"]["python"])
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

    def checkpoint(at_step: int) -> None:
        if d.main:
            save_checkpoint(latest, model, optimizer, at_step, cfg, {"stage": current_stage})

    for step, batch in batches(ds, cfg, d, step):
        stage = stage_of(step, cfg)
        if stage != current_stage:  # entering stage 2: fresh Adam at the fine-tuning rate
            optimizer = _make_optimizer(model, stage2_lr)
            current_stage = stage
        batch = {k: v.to(d.device, non_blocking=True) for k, v in batch.items()}
        out = ddp(batch["x_diffuse"], batch["x_specular"], batch["albedo"])
        loss = compute_loss(out, batch, stage, cfg)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"step {step}: non-finite loss {loss.item()}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.train.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.train.grad_clip)
        optimizer.step()
        loss_value = float(loss.detach())
        losses.append(loss_value)
        n_patches += batch["x_diffuse"].shape[0] * d.world
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
                pred = model(f["x_diffuse"][None].to(d.device), f["x_specular"][None].to(d.device), f["albedo"][None].to(d.device))["color"][0].cpu()
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
        # the final model alone, for kpcn.denoise
        final = run / "model.pt"
        save_checkpoint(final, model, None, total, cfg, {"stage": 2})
    elapsed = time.perf_counter() - t0
    return {"step": total, "losses": losses, "val": last_val, "seconds": elapsed,
            "patches_per_s": n_patches / elapsed if elapsed > 0 else 0.0, "rank": d.rank, "world": d.world,
            "weight_sha256_per_rank": digests}


def main(argv=None) -> int:
    p = make_parser("Train a KPCN/DPCN denoiser.", prog="python -m kpcn.train")
    p.add_argument("--resume", action="store_true", help="continue from <run>/checkpoints/latest.pt")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    cfg = config_from_args(args)
    summary = train(cfg, resume=args.resume, progress=not args.no_progress)
    if summary["rank"] == 0:
        print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    if dist.is_initialized():
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
