"""One training step's parts: the model, the batch of each step, the two stages' losses, and validation."""
from __future__ import annotations

from fnmatch import fnmatchcase

import numpy as np
import torch
from torch.utils.data import DataLoader, DistributedSampler

from .augment import Augmentation, augment_patch, undo_flips
from .data import FrameDataset, PatchDataset, model_inputs as net_inputs
from .distributed import Dist
from .losses import create_loss
from .metrics import all_metrics, tonemap
from .models import create_model
from .ops.regression import residual_regression
from .schedule import lr_at
from .train_config import RunConfig
from .train_init import unmatched_patterns

__all__ = ["build_model", "stage_of", "set_lr", "model_inputs", "build_teacher", "distill_targets", "teacher_outputs",
           "with_detail", "compute_loss", "batches", "validate"]


def build_model(cfg: RunConfig) -> torch.nn.Module:
    """The model ``cfg.model`` names, built with its hyper-parameters."""
    return create_model(**cfg.model)


def _unwrap(model):
    return model.module if hasattr(model, "module") else model


def stage_of(step: int, cfg: RunConfig) -> int:
    return 1 if step < cfg.train.stage1_steps else 2


def set_lr(optimizer, step: int, cfg: RunConfig) -> float:
    """Set (and return) the rate of ``step`` from ``train.schedule``, within its stage."""
    t = cfg.train
    if stage_of(step, cfg) == 1:
        lr = lr_at(step, 0, t.stage1_steps, t.lr, t.schedule, t.warmup)
    else:
        lr = lr_at(step, t.stage1_steps, t.stage2_steps, t.stage2_lr or t.lr, t.schedule, t.warmup)
    for group in optimizer.param_groups:
        group["lr"] = lr * group.get("lr_mult", 1.0)
    return lr


def model_inputs(model, batch: dict) -> dict:
    """The entries of ``batch`` the model (or its DDP wrapper) reads (:func:`kpcn.data.model_inputs`)."""
    return net_inputs(_unwrap(model), batch)


def build_teacher(cfg: RunConfig, model, device) -> torch.nn.Module:
    """The ``train.init`` file's own model (before any ``init_extend`` or ``init_reopen``), frozen, in eval mode
    and ``train.precision``: the teacher of ``train.distill_min_spp``.

    Raises:
        ConfigError: no such file (a resumed run reads it here first), or its model reads another input spec
            than ``model``.
    """
    from .checkpoint import load_model_file
    from .config import ConfigError
    from .train_init import resolve_init

    teacher = load_model_file(resolve_init(cfg)).to(device).eval()
    have, want = teacher.input_spec.name, _unwrap(model).input_spec.name
    if have != want:
        raise ConfigError(f"train.distill_min_spp: the init file's model reads {have}, the config's {want}: "
                          f"it cannot be the teacher of these inputs")
    teacher.set_compute_dtype(cfg.train.precision)
    for p in teacher.parameters():
        p.requires_grad_(False)
    return teacher


def with_detail(model, out: dict, batch: dict) -> dict:
    """``out`` with its ``color`` passed through ``model``'s detail stage (:attr:`DenoiserModel.detail_regression`)
    as the pipeline applies it after the network, one fit per 2×2 block, guided by ``batch["noisy_normal"]`` with
    ``batch["noisy_color"]`` as the noisy colour (``(B, 3, H, W)``); differentiable. ``out`` is not changed.

    Raises:
        ValueError: the model has no detail stage, or the batch no ``noisy_normal``.
    """
    reg = _unwrap(model).detail_regression
    if reg is None:
        raise ValueError("train.detail_stage: the model has no detail stage (its config's detail_radius is 0)")
    if "noisy_normal" not in batch:
        raise ValueError("train.detail_stage: the batch has no noisy_normal (the input spec reads no normal)")
    radius, eps, clip = reg
    color = out["color"]
    refined = residual_regression(color, batch["noisy_color"].to(color.dtype), batch["noisy_normal"].to(color.dtype),
                                  radius=radius, eps=eps, stride=2, clip=clip)
    return {**out, "color": refined}


#: the flips and transposes a teacher's outputs are averaged over (``train.distill_tta`` takes the first n)
TEACHER_VIEWS = tuple(Augmentation(flip_x=fx, flip_y=fy, transpose=t) for t, fx, fy in (
    (False, False, False), (True, False, False), (False, True, False), (False, False, True),
    (False, True, True), (True, True, False), (True, False, True), (True, True, True)))


def teacher_outputs(teacher, inputs: dict, views: int = 1) -> dict:
    """``teacher``'s outputs on ``inputs`` (square ``(B, C, S, S)`` patches), averaged over the first ``views`` of
    :data:`TEACHER_VIEWS`: each view's inputs transformed as training's augmentation transforms them
    (:func:`kpcn.augment.augment_patch`), its outputs transformed back. Averaging removes part of the network's own
    variance (on the report's frames the mean of 8 views closes 45 % of the default's 4-spp PSNR gap to OIDN)."""
    spec = teacher.input_spec
    total: dict = {}
    for view in TEACHER_VIEWS[:views]:
        x = {k: augment_patch(v, view, spec if k in spec.branches else None) for k, v in inputs.items()}
        for k, v in teacher(x).items():
            v = undo_flips(v, view)
            total[k] = v if k not in total else total[k] + v
    return {k: v / views for k, v in total.items()} if views > 1 else total


@torch.no_grad()
def distill_targets(teacher, batch: dict, min_spp: int, detail_of=None, views: int = 1) -> dict:
    """``batch`` with the targets of its patches whose input has ``min_spp`` or more samples per pixel
    (``batch["spp"]``, ``(B,)``; converged pairs, spp 0, are never) replaced by ``teacher``'s outputs on them
    (averaged over ``views`` flips and transposes, :func:`teacher_outputs`): ``y_<k>`` for every output ``k`` of
    ``teacher`` that the batch has a target for, its colour passed through ``detail_of``'s detail stage first where
    given (:func:`with_detail`). The batch is not changed."""
    pick = batch["spp"] >= min_spp
    if not bool(pick.any()):
        return batch
    out = teacher_outputs(teacher, {k: v[pick] for k, v in model_inputs(teacher, batch).items()}, views)
    if detail_of is not None:
        out = with_detail(detail_of, out, {k: batch[k][pick] for k in ("noisy_color", "noisy_normal")})
    batch = dict(batch)
    for k, v in out.items():
        if f"y_{k}" in batch:
            y = batch[f"y_{k}"].clone()
            y[pick] = v.to(y.dtype)
            batch[f"y_{k}"] = y
    return batch


def unconverged_pixels(batch: dict, spec, max_noise: float) -> torch.Tensor | None:
    """``(B, 1, H, W)`` bool: True on the pixels of converged patches whose reference is not converged.

    The reference's relative noise is the standard deviation of its pixel mean (from the converged input's
    own variance features, ``spec.colour_variance``) over ``sqrt(colour^2 + 0.01)``; above ``max_noise`` the
    pixel is not converged. None when the batch has no converged patch.
    """
    flags = batch.get("converged")
    if flags is None or not bool(flags.any()):
        return None
    var = spec.colour_variance(batch).clamp_min(0.0)
    c = batch["y_color"].mean(1, keepdim=True)
    noisy = var > (max_noise * max_noise) * (c * c + 0.01)
    return noisy & flags.view(-1, 1, 1, 1).bool()


def compute_loss(out: dict, batch: dict, stage: int, cfg: RunConfig, branches, spec=None) -> torch.Tensor:
    """Stage 1: the sum over branches of the loss in each branch's space; stage 2: on the colour.

    With ``data.converged_max_noise`` (and ``spec``), the output is replaced by its target on the pixels
    :func:`unconverged_pixels` marks, so that they add nothing to the loss or its gradient.
    """
    skip = None
    if cfg.data.converged_max_noise is not None and spec is not None:
        skip = unconverged_pixels(batch, spec, cfg.data.converged_max_noise)
    if skip is not None:
        out = {k: torch.where(skip, batch[f"y_{k}"].to(v.dtype), v) if f"y_{k}" in batch else v
               for k, v in out.items()}
    if stage == 1:
        loss = create_loss(*cfg.train.loss_of(1))
        return sum(loss(out[b], batch[f"y_{b}"]) for b in branches)
    loss = create_loss(*cfg.train.loss_of(2))
    return loss(out["color"], batch["y_color"])


def _workers(cfg: RunConfig, d: Dist) -> int:
    """``data.workers``, or (None) 2 on CUDA and 0 on the CPU."""
    return cfg.data.workers if cfg.data.workers is not None else (2 if d.device.type == "cuda" else 0)


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
        loader = DataLoader(ds, batch_size=per_rank, sampler=sampler, drop_last=True, num_workers=_workers(cfg, d),
                            persistent_workers=False, pin_memory=d.device.type == "cuda")
        for i, batch in enumerate(loader):
            if i < within:
                continue
            if step >= total or i >= steps_per_epoch:
                break
            yield step, batch
            step += 1


@torch.no_grad()
def validate(model, frames: FrameDataset, device, detail: bool = False,
             keep: list | None = None) -> dict[str, float]:
    """Mean metrics of the full-frame reconstruction over the validation frames (``detail``: after the model's
    detail stage, :func:`with_detail`). ``keep``: a list the first frame's colour ``(C, H, W)`` (the one the
    metrics saw) is appended to, for TensorBoard."""
    model.eval()
    sums: dict[str, float] = {}
    for i in range(len(frames)):
        f = frames[i]
        inputs = {k: v[None].to(device) for k, v in model_inputs(model, f).items()}
        out = _unwrap(model)(inputs)
        if detail:
            out = with_detail(model, out, {k: f[k][None].to(device) for k in ("noisy_color", "noisy_normal")})
        if keep is not None and i == 0:
            keep.append(out["color"][0].cpu())
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


def _make_optimizer(model, lr: float, lr_mult: dict[str, float] | None = None):
    """Adam over the parameters that are trained (``train.train_only`` freezes the others); with ``lr_mult``
    (``train.lr_mult``: parameter-name glob -> factor, the first match counts) a parameter group per factor, each
    at ``lr`` times its factor (:func:`set_lr` keeps it so)."""
    lr_mult = lr_mult or {}
    groups: dict[float, list] = {}
    used, names = set(), []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        name = name.removeprefix("module.")  # a DistributedDataParallel wrapper's
        names.append(name)
        pat = next((k for k in lr_mult if fnmatchcase(name, k)), None)
        used.add(pat)
        groups.setdefault(float(lr_mult[pat]) if pat else 1.0, []).append(p)
    unused = [k for k in lr_mult if k not in used]
    if unused:
        raise unmatched_patterns("train.lr_mult", unused, names, " that is trained and no earlier pattern takes")
    return torch.optim.Adam([{"params": ps, "lr": lr * m, "lr_mult": m} for m, ps in groups.items()], lr=lr)


def _tonemap_t(x: torch.Tensor) -> torch.Tensor:
    """:func:`kpcn.metrics.tonemap` of a ``(C, H, W)`` tensor, for TensorBoard images."""
    return torch.from_numpy(tonemap(x.detach().cpu().numpy())).float()
