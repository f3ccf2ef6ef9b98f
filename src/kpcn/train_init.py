"""The weights a training run starts from: ``train.init`` (a weights file or a shipped ``model:tag``), and
``train.init_extend``, which lets the config's model extend the file's (more input channels, a precision gate,
a demodulation weight, a coarser U-Net kernel level, wider U-Net levels, U-Net high-band gains) so that it starts
from the file's outputs; with ``train.init_prune`` also narrower U-Net levels (a start for training, not the file's
outputs)."""
from __future__ import annotations

import dataclasses
import fnmatch
import re

import torch

from .config import ConfigError, to_dict
from .models.base import NO_WEIGHT_SETTINGS
from .models.registry import create_model, model_config_class
from .train_config import RunConfig

__all__ = ["load_init", "resolve_init"]


def resolve_init(cfg: RunConfig):
    """The weights file ``cfg.train.init`` names (a ``.safetensors`` path or a shipped ``model:tag``);
    :class:`ConfigError` when there is none."""
    from .inference.weights import DefaultWeightsMissing, resolve_weights

    try:
        return resolve_weights(cfg.train.init)
    except (DefaultWeightsMissing, FileNotFoundError) as exc:
        raise ConfigError(f"train.init: no weights file {cfg.train.init!r} (a .safetensors path or a shipped "
                          f"model:tag): {exc}") from None


def load_init(model: torch.nn.Module, cfg: RunConfig) -> str:
    """Load ``cfg.train.init`` (a weights file or a shipped ``model:tag``) into ``model``; the file's
    model and the hyper-parameters the config sets must agree (:class:`ConfigError` otherwise)."""
    from .checkpoint import read_weights

    path = resolve_init(cfg)
    record, weights = read_weights(path)
    want = to_dict(cfg)["model"]
    extendable = {"input_spec", "in_channels", "precision_gate", "demodulate", "kernel_scales", "widths",
                  "guide_channels", "guide_kernel", "band_gain", "up_kernel", "albedo_kernel", "albedo_gate_gain",
                  "albedo_clamp", "specular_widths", "radiance_pool", "radiance_mix", "deep_blocks",
                  "fullres_channels"}
    # settings that add no parameter (NO_WEIGHT_SETTINGS): a file trained without them starts one trained with them
    free = {"name", *NO_WEIGHT_SETTINGS} | (extendable if cfg.train.init_extend else set())
    if cfg.train.init_extend:  # U-Net kernels of another size start from the file's (_resize_kernels)
        free |= {"kernel_size", "coarse_kernel"}
    # a file written before a field existed holds that field's default
    fields = model_config_class(record["model"]).__dataclass_fields__ if record["model"] == want.get("name") else {}
    held = {k: f.default for k, f in fields.items() if f.default is not dataclasses.MISSING} | record["hparams"]
    mismatch = {k: (held.get(k), v) for k, v in want.items() if k not in free and held.get(k) != v}
    for k in ("albedo_gate_gain", "albedo_clamp"):
        # a file's trained albedo gates read through another gain or bound would be other gates: only new ones may
        if held.get("albedo_kernel") and k in want and held.get(k) != want[k]:
            mismatch[k] = (held.get(k), want[k])
    if record["model"] != want.get("name") or mismatch:
        raise ConfigError(f"train.init: {path} holds {record['model']} with other hyper-parameters than the "
                          f"config's {want.get('name')} (file, config): {mismatch}")
    state = {k: v.to(torch.float32) for k, v in weights.items()}
    if cfg.train.init_extend:
        source = create_model(**record["hparams"])
        groups = model.channel_groups()
        source_groups = source.channel_groups() if groups else None
        state = _resize_kernels(state, source, model, path, cfg.train.init_prune)
        state = _realign_heads(state, source, model)
        # on the CPU, where the file was read: the model may already sit on a GPU
        state = _extend(state, {k: v.detach().cpu() for k, v in model.state_dict().items()}, path, groups,
                        source_groups, prune=cfg.train.init_prune)
    model.load_state_dict(state)
    _reopen_blends(model, cfg.train.init_reopen)
    return str(path)


def _resize_kernels(state: dict, source: torch.nn.Module, model: torch.nn.Module, path, prune: bool) -> dict:
    """Each U-Net kernel level whose kernels (``kernel_size``, ``coarse_kernel``) differ in size from the file's.

    * Larger (``train.init_extend``): the file's logits stay as the centre taps (so the kernels over those taps,
      renormalised, are the file's), and each new outer tap starts as a copy of the nearest old tap's logit, lower by
      :data:`GROWN_TAP_OFFSET`: a start near the file's outputs from which the new taps can learn (new taps at the
      logits' bound, the file's outputs to 1e-6, stayed shut through 600 steps of Adam at 5e-5).
    * Smaller (also ``train.init_prune``): the centre taps of the file's logits, the file's kernels truncated and
      renormalised by the softmax: a start for training rather than the file's outputs.

    The head's other channels (blend, gain, albedo kernel, mixing weight) follow as they are; an albedo kernel
    (``albedo_kernel``) of another size is resized the same way."""
    out = dict(state)
    for b in getattr(model, "branches", ()):
        src, dst = getattr(source, b, None), getattr(model, b, None)
        if not (hasattr(src, "heads") and hasattr(dst, "heads")):
            continue
        for level in range(min(src.cfg.kernel_scales, dst.cfg.kernel_scales)):
            ks, km = src.cfg.level_kernel(level), dst.cfg.level_kernel(level)
            if km == ks:
                continue
            name = f"{b}.head" if level == 0 else f"{b}.heads.{level - 1}"
            for p in ("weight", "bias"):
                v = state[f"{name}.{p}"]
                out[f"{name}.{p}"] = torch.cat([_resized_taps(v[:ks * ks], ks, km, p, prune, path, b,
                                                              f"level {level}"), v[ks * ks:]])
        ka_s, ka_m = getattr(src, "albedo_kernel", 0), getattr(dst, "albedo_kernel", 0)
        if ka_s and ka_m and ka_s != ka_m:  # the albedo kernel's logits, after the (resized) level-0 kernel's rows
            at = dst.head_layout[0] + src.head_layout[1]  # and the file's blend rows
            for p in ("weight", "bias"):
                v = out[f"{b}.head.{p}"]
                out[f"{b}.head.{p}"] = torch.cat([v[:at], _resized_taps(v[at:at + ka_s * ka_s], ka_s, ka_m, p, prune,
                                                                        path, b, "albedo"), v[at + ka_s * ka_s:]])
    return out


def _head_segments(branch, level: int) -> tuple[int, int, int, int] | None:
    """A U-Net branch's :meth:`~kpcn.models.unet_branch.UNetBranch.head_segments` at ``level``; None where the
    branch has no such head."""
    cfg = getattr(branch, "cfg", None)
    if not hasattr(branch, "head_segments") or level >= cfg.kernel_scales:
        return None
    return branch.head_segments(level)


def _realign_heads(state: dict, source: torch.nn.Module, model: torch.nn.Module) -> dict:
    """Each U-Net kernel head whose segments (:func:`_head_segments`) the model has more of than the file (a band
    gain after the blend, a blend on a level that gained a coarser one) with the file's rows moved to their
    segment's start and the new rows in place: weight 0, the model's own initial bias (a gain's 0: β = 1). Rows
    added at a head's end need nothing (:func:`_extend` pads them), but a gain added before an albedo kernel or a
    mixing weight would otherwise shift those rows. Runs after :func:`_resize_kernels` (the logits are the model's
    size by then, and a resized albedo kernel too)."""
    target = model.state_dict()
    out = dict(state)
    for b in getattr(model, "branches", ()):
        src, dst = getattr(source, b, None), getattr(model, b, None)
        for level in range(getattr(getattr(src, "cfg", None), "kernel_scales", 0)):
            have, want = _head_segments(src, level), _head_segments(dst, level)
            if have is None or want is None:
                continue
            have = (want[0], have[1], want[2] if have[2] else 0, have[3])  # as _resize_kernels left them
            if have == want or any(h > w for h, w in zip(have, want)):
                continue  # the same rows, or a cut (for _extend to refuse)
            name = f"{b}.head" if level == 0 else f"{b}.heads.{level - 1}"
            rows = torch.cat([torch.arange(h) + sum(want[:i]) for i, h in enumerate(have)])
            for p in ("weight", "bias"):
                key, v = f"{name}.{p}", out[f"{name}.{p}"]
                if key not in target or v.shape[0] != sum(have):
                    continue
                t = target[key]
                w = t.detach().clone().to(v.dtype) if p == "bias" else torch.zeros((t.shape[0],) + tuple(v.shape[1:]),
                                                                                   dtype=v.dtype)
                w[rows] = v
                out[key] = w
    return out


#: a grown kernel's new tap starts as a copy of the nearest old tap's logit this much lower (e^-2: 0.14 of its weight)
GROWN_TAP_OFFSET = 2.0


def _resized_taps(v: torch.Tensor, ks: int, km: int, p: str, prune: bool, path, branch: str,
                  what: str) -> torch.Tensor:
    """The ``ks²`` logit rows ``v`` (a head's ``weight`` or ``bias``, ``p``) of one kernel as ``km²`` rows: the centre
    taps when smaller (needs ``prune``); when larger, ``v`` as the centre and each new tap a copy of the nearest old
    tap's row, its bias :data:`GROWN_TAP_OFFSET` lower (:func:`_resize_kernels`)."""
    if km < ks and not prune:
        raise ConfigError(f"train.init_extend: {path}'s {branch} kernels ({what}) are {ks}x{ks}, the model's "
                          f"{km}x{km}: cropping them needs train.init_prune")
    small, m = min(ks, km), abs(ks - km) // 2
    if km < ks:
        return v[torch.tensor([r * ks + c for r in range(m, m + km) for c in range(m, m + km)])]
    near = [min(max(r - m, 0), ks - 1) * ks + min(max(c - m, 0), ks - 1) for r in range(km) for c in range(km)]
    taps = v[torch.tensor(near)].clone()
    if p == "bias":
        inner = torch.tensor([m <= r < m + ks and m <= c < m + ks for r in range(km) for c in range(km)])
        taps[~inner] -= GROWN_TAP_OFFSET
    return taps


#: the logit a reopened blending weight restarts at: α = sigmoid(-1) ≈ 0.27
REOPEN_LOGIT = -1.0


def _reopen_blends(model: torch.nn.Module, entries) -> None:
    """``train.init_reopen``: each ``"<branch>:<level>"``'s blending weight α restarts at ``sigmoid(REOPEN_LOGIT)``
    (the α channel of that level's head: weights zeroed, bias set)."""
    for entry in entries:
        branch, level = entry.split(":")
        level = int(level)
        net = getattr(model, branch, None) if branch in getattr(model, "branches", ()) else None
        if net is None or not hasattr(net, "heads"):
            raise ConfigError(f"train.init_reopen: {entry!r}: the model has no U-Net branch {branch!r} "
                              f"(branches: {list(getattr(model, 'branches', ()))})")
        n = net.cfg.kernel_scales
        if not 0 <= level < n - 1:
            raise ConfigError(f"train.init_reopen: {entry!r}: kernel level {level} of the {branch} branch blends in "
                              f"no coarser level (with kernel_scales {n}, levels 0..{n - 2} do)")
        head = net.head if level == 0 else net.heads[level - 1]
        kk = net.cfg.level_kernel(level) ** 2
        with torch.no_grad():
            head.weight[kk].zero_()
            head.bias[kk] = REOPEN_LOGIT


#: what ``train.init_extend`` may add to a file: a coarser kernel level's head, a deep block, a full-resolution level
ADDABLE = r"(^|\.)(heads\.\d+|deep\.\d+\.conv[12]|fullres\.\w+)\.(weight|bias)$"


def _extend(state: dict, target: dict, path, groups: dict | None = None, source_groups: dict | None = None,
            prune: bool = False) -> dict:
    """``state`` made to fit ``target`` (``train.init_extend``).

    * A conv the model lists in ``groups`` (:meth:`~kpcn.models.base.DenoiserModel.channel_groups`, the
      file's in ``source_groups``) may be wider: each of the file's channel groups goes to the start of the
      model's group. New hidden channels keep the model's initial weights; the file's outputs read them
      with zero weights, so the widened model computes what the file's did. With ``prune``
      (``train.init_prune``) a group may also be narrower: it keeps the file's first channels (not the
      file's function: a start for training).
    * Any other tensor that reads fewer input channels (dim 1) is zero-padded to the new ones (the last:
      a zero weight ignores them).
    * A conv with more outputs (dim 0: the demodulation weight's channel, the blending weight of a
      U-Net kernel level that gains a coarser level, its high-band gain, or the diffuse head's albedo kernel
      and gate) gets zero weights and the model's own initial bias for them (a gain's: 0, so ``β = 1``; the
      albedo gate's: 0, so the albedo is the input's).
    * A conv weight with a smaller odd kernel (a 1x1 U-Net guide in a model whose guide is 3x3) becomes the
      centre taps of the model's kernel, zero elsewhere.
    * A precision gate, or the head of a coarser kernel level (``heads.<i>``), that the file lacks takes
      the model's own initial value.
    * A U-Net decoder's first conv over ``[nearest_up2(coarse), skip]`` (3x3 taps on both) into a model with
      ``up_kernel: 1`` (:class:`~kpcn.models.layers.UpAddConv`): the skip's taps as they are, the coarse
      level's summed into its 1x1 (the same function where the coarse level is constant over 3x3 pixels).

    Anything else that differs is a ConfigError.
    """
    cut = [k for k in state if k not in target]
    if cut:
        raise ConfigError(f"train.init_extend: {path} has {', '.join(cut)}, which the config's model lacks (a model "
                          f"can only be extended, not cut)")
    state = _split_up_convs(state, target)
    out = dict(state)
    for k, t in target.items():
        if k not in state:
            if not (k.endswith(".gate") or re.search(ADDABLE, k)):
                raise ConfigError(f"train.init_extend: {path} has no {k} (only a precision gate, a coarser "
                                  f"kernel level, a deep block or a full-resolution level can be added)")
            out[k] = t.detach().clone()
    groups, source_groups = groups or {}, source_groups or {}
    for k, v in state.items():
        t = target[k]
        if v.dim() == 4 and t.dim() == 4 and v.shape[2:] != t.shape[2:]:
            v = _embed_taps(k, v, t, path)
            out[k] = v
        module = k.rpartition(".")[0]
        if module in groups and module in source_groups and t.shape != v.shape:
            out[k] = _widen(k, v, t, source_groups[module], groups[module], path, prune)
            continue
        if t.shape == v.shape:
            continue
        if v.dim() != t.dim() or v.shape[2:] != t.shape[2:] or v.shape[0] > t.shape[0] \
                or (v.dim() >= 2 and v.shape[1] > t.shape[1]):
            raise ConfigError(f"train.init_extend: {path}'s {k} is {tuple(v.shape)}; the model's is "
                              f"{tuple(t.shape)} (only more input or output channels can be added)")
        w = t.detach().clone().to(v.dtype) if v.dim() == 1 else torch.zeros(t.shape, dtype=v.dtype)
        w[tuple(slice(0, n) for n in v.shape)] = v
        out[k] = w
    return out


def _split_up_convs(state: dict, target: dict) -> dict:
    """``state`` with each decoder conv the model has as an :class:`~kpcn.models.layers.UpAddConv` (a ``<m>.coarse.weight``
    the file lacks, ``<m>.weight`` reading fewer channels than the file's) split into the skip's taps and the 1x1 of
    the coarse channels (the file's first ones) summed over its taps (see :func:`_extend`)."""
    out = dict(state)
    for k, t in target.items():
        m = k[: -len(".coarse.weight")] if k.endswith(".coarse.weight") else None
        if m is None or k in state or m + ".weight" not in state:
            continue
        v, skip = state[m + ".weight"], target[m + ".weight"]
        cc = v.shape[1] - skip.shape[1]
        if v.dim() != 4 or cc != t.shape[1] or v.shape[2:] != skip.shape[2:]:
            continue  # left for _extend to report
        out[m + ".weight"] = v[:, cc:].clone()
        out[k] = v[:, :cc].sum(dim=(2, 3), keepdim=True)
    return out


def _embed_taps(k: str, v: torch.Tensor, t: torch.Tensor, path) -> torch.Tensor:
    """A conv weight ``v`` with a smaller odd kernel than the model's ``t`` (a 1x1 guide that became 3x3) as the
    centre taps of a kernel of ``t``'s size, zero elsewhere: the same function on the same padding."""
    (kh, kw), (th, tw) = v.shape[2:], t.shape[2:]
    if kh > th or kw > tw or (th - kh) % 2 or (tw - kw) % 2:
        raise ConfigError(f"train.init_extend: {path}'s {k} is {tuple(v.shape)}; the model's is {tuple(t.shape)} "
                          f"(a kernel can only grow, by the same number of taps on each side)")
    dy, dx = (th - kh) // 2, (tw - kw) // 2
    w = torch.zeros(tuple(v.shape[:2]) + (th, tw), dtype=v.dtype)
    w[..., dy:dy + kh, dx:dx + kw] = v
    return w


def _group_index(k: str, src: tuple[int, ...], dst: tuple[int, ...], path,
                 prune: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """The file's channels (groups ``src``) that the model keeps, and where they sit among the model's (groups
    ``dst``): each group's first ``min(src, dst)`` channels (a narrower group only with ``prune``)."""
    if len(src) != len(dst) or (not prune and any(a > b for a, b in zip(src, dst))):
        why = "the groups must match one to one" if prune else "a group can only grow without train.init_prune"
        raise ConfigError(f"train.init_extend: {path}'s {k} has channel groups {src}; the model's are {dst} ({why})")
    src_at = [sum(src[:i]) for i in range(len(src))]
    dst_at = [sum(dst[:i]) for i in range(len(dst))]
    n = [min(a, b) for a, b in zip(src, dst)]
    return (torch.cat([torch.arange(m) + s for m, s in zip(n, src_at)]),
            torch.cat([torch.arange(m) + s for m, s in zip(n, dst_at)]))


def _widen(k: str, v: torch.Tensor, t: torch.Tensor, src, dst, path, prune: bool = False) -> torch.Tensor:
    """The file's tensor ``v`` placed in the model's ``t`` by channel groups (see :func:`_extend`)."""
    (src_out, src_in), (dst_out, dst_in) = src, dst
    hidden = dst_out is not None
    keep, rows = _group_index(k, src_out if hidden else (v.shape[0],), dst_out if hidden else (t.shape[0],), path,
                              prune)
    w = t.detach().clone().to(v.dtype)
    if v.dim() == 1:
        w[rows] = v[keep]
        return w
    if v.shape[2:] != t.shape[2:]:
        raise ConfigError(f"train.init_extend: {path}'s {k} is {tuple(v.shape)}; the model's is {tuple(t.shape)}")
    keep_in, cols = _group_index(k, src_in, dst_in, path, prune)
    if not hidden:  # new result channels start silent (zero weights, the model's initial bias)
        w.zero_()
    block = torch.zeros((len(rows),) + tuple(t.shape[1:]), dtype=v.dtype)
    block[:, cols] = v[keep][:, keep_in]
    w[rows] = block
    return w


def _split_rows(pattern: str) -> tuple[str, slice | None]:
    """``"glob"`` -> (glob, None); ``"glob[i]"`` / ``"glob[a:b]"`` -> (glob, that slice of the first dimension)."""
    m = re.fullmatch(r"(.+)\[(-?\d*)(:?)(-?\d*)\]", pattern)
    if not m:
        return pattern, None
    glob, a, colon, b = m.groups()
    if not colon:
        if not a:
            raise ConfigError(f"train.train_only: {pattern!r}: expected '<glob>[i]' or '<glob>[a:b]'")
        i = int(a)
        return glob, slice(i, i + 1 if i != -1 else None)
    return glob, slice(int(a) if a else None, int(b) if b else None)


def unmatched_patterns(option: str, unused, names, why: str = "") -> ConfigError:
    """The error for parameter-name patterns of ``option`` that name none of the model's parameters ``names`` (a few
    of them listed); ``why``: what else such a pattern may have missed."""
    return ConfigError(f"{option}: {', '.join(map(repr, unused))} name no parameter of the model{why} (it has "
                       f"{len(names)}, e.g. {', '.join(names[:3])}, ..., {names[-1]})")


def freeze_except(model: torch.nn.Module, patterns) -> int:
    """``train.train_only``: freeze every parameter of ``model`` whose name matches none of the glob ``patterns``
    (``requires_grad`` False; nothing when ``patterns`` is empty) and return how many parameter values stay trainable.
    A pattern ``"<glob>[i]"`` or ``"<glob>[a:b]"`` trains only those rows (first dimension: a conv's output
    channels) of what it matches: the other rows' gradients are zeroed (Adam then leaves them as they are).

    Raises:
        ConfigError: a pattern that matches no parameter (listing a few names).
    """
    names = [n for n, _ in model.named_parameters()]
    if not patterns:
        return sum(p.numel() for p in model.parameters())
    parsed = [_split_rows(pat) for pat in patterns]
    unused = [pat for pat, (glob, _) in zip(patterns, parsed) if not any(fnmatch.fnmatchcase(n, glob) for n in names)]
    if unused:
        raise unmatched_patterns("train.train_only", unused, names)
    kept = 0
    for n, p in model.named_parameters():
        rows = [r for glob, r in parsed if fnmatch.fnmatchcase(n, glob)]
        p.requires_grad_(bool(rows))
        if not rows:
            continue
        if any(r is None for r in rows):
            kept += p.numel()
            continue
        mask = torch.zeros_like(p)
        for r in rows:
            mask[r] = 1
        p.register_hook(lambda g, mask=mask: g * mask)
        kept += int(mask.sum())
    return kept
