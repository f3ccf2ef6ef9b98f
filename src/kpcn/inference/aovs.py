"""Denoise other layers of a frame with the kernels predicted for its beauty.

A kernel predictor's per-pixel kernels can filter any layer of the same frame
(production renderers write light groups and AOVs). ``denoise(path,
layers=[...])`` does it, per branch:

* a **light group** ``g`` — layers ``g.diffuse`` and ``g.specular`` for the
  split input specs, or a colour layer ``g`` for ``color_albedo_normal`` — is
  split like the beauty and each part filtered with its branch's kernels:

  - diffuse (linear in the radiance): ``(albedo + eps) · K_d ⊛ (g.diffuse / (albedo + eps))``;
  - specular: the beauty's specular branch works in log space, which is not
    linear, so the group gets the share ``K_s ⊛ g.specular / K_s ⊛ specular``
    of the beauty's denoised specular;
  - colour (``color_albedo_normal``): ``K ⊛ g``.

  So when the groups add up to the beauty, the denoised groups add up to the
  denoised beauty (to float rounding), which per-layer denoising (OIDN's way)
  does not give. Where the beauty is not linear in the groups — it clamps a
  linear branch at 0, and beside a firefly the filtered specular can vanish
  while the log-space branch does not — :func:`compose_aovs` follows it (a
  clamped part is 0; the specular share falls back to the noisy pixel's);
* any other layer ``x`` (three channels) is filtered directly with the kernels
  of one branch (``aov_branch``, the first one by default): a constant layer
  stays constant, since the kernels are normalised and replicate the border.

Only ``zero_preserving`` kernel predictors have kernels; others are refused.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..constants import EPS
from ..inputs import InputSpec, radiance_of
from ..features import frame_to_tensors
from ..io import Frame, MissingLayerError

#: a group's specular share is taken from the filtered layers where the filtered beauty specular is at least
#: this fraction of the denoised one (else from the noisy pixel; see :func:`compose_aovs`)
SHARE_FLOOR = 1e-3

__all__ = ["SHARE_FLOOR", "AovPlan", "plan_aovs", "denoise_aovs", "noisy_aov", "aov_signals", "compose_aovs"]


@dataclass(frozen=True)
class AovPlan:
    """One requested layer: ``parts`` maps a branch to the frame layer filtered with its kernels."""

    name: str
    parts: dict[str, str]
    group: bool  #: a light group (split like the beauty) rather than a layer filtered directly


def plan_aovs(frame: Frame, names, spec: InputSpec, aov_branch: str | None = None) -> list[AovPlan]:
    """What each requested layer is and which frame layers it reads (missing ones are named)."""
    branch = aov_branch or spec.branches[0]
    if branch not in spec.branches:
        raise ValueError(f"denoise: aov_branch {branch!r} is not a branch of input spec {spec.name!r} ({spec.branches})")
    plans, missing = [], []
    for name in names:
        split = {b: f"{name}.{b}" for b in spec.branches}
        if len(spec.branches) > 1 and all(layer in frame for layer in split.values()):
            plans.append(AovPlan(name, split, True))
        elif name in frame:
            plans.append(AovPlan(name, {branch: name}, len(spec.branches) == 1))
        else:
            missing.append(name if len(spec.branches) == 1 else f"{name} (or {' and '.join(split.values())})")
            continue
        for layer in plans[-1].parts.values():
            if frame[layer].ndim != 3 or frame[layer].shape[2] != 3:
                raise ValueError(f"{frame.path or 'frame'}: layer {layer!r} must have 3 channels, got {frame[layer].shape}")
    if missing:
        raise MissingLayerError(frame.path or "frame", missing, frame.layers)
    return plans


def noisy_aov(frame: Frame, plan: AovPlan, region) -> np.ndarray:
    """The noisy value of a requested layer over ``region`` (its parts summed)."""
    return sum(np.maximum(frame.region(layer, region), 0.0) if plan.group else frame.region(layer, region)
               for layer in plan.parts.values())


def aov_signals(plans: list[AovPlan], run, layer, albedo: torch.Tensor) -> dict[str, dict[str, torch.Tensor]]:
    """Per branch in ``run``, the layers its kernels filter, in the space they are filtered in.

    ``layer(name) -> (1, 3, h, w)`` reads a frame layer over the region; ``albedo`` is the model's
    (clamped) albedo there. Keys name the layer and its space (``<layer>|demod``: ``/ (albedo + eps)``;
    ``|pos``: clamped at 0; ``|raw``: as it is); ``specular|pos`` is the beauty's specular, whose
    filtered value shares the denoised specular among the groups.
    """
    sig: dict[str, dict[str, torch.Tensor]] = {b: {} for b in run}
    for plan in plans:
        for b, name in plan.parts.items():
            if b not in run:
                continue
            if not plan.group:
                sig[b][f"{name}|raw"] = layer(name)
            elif b == "diffuse":
                sig[b][f"{name}|demod"] = layer(name).clamp_min(0.0) / (albedo + EPS)
            else:
                sig[b][f"{name}|pos"] = layer(name).clamp_min(0.0)
    if "specular" in run and any(p.group and "specular" in p.parts for p in plans):
        sig["specular"]["specular|pos"] = layer("specular").clamp_min(0.0)
    return sig


def compose_aovs(plans: list[AovPlan], run, filtered: dict[str, dict[str, torch.Tensor]],
                 noisy: dict[str, dict[str, torch.Tensor]], albedo: torch.Tensor,
                 outputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The requested layers ``{name: (1, 3, h, w)}`` from the :func:`aov_signals` ``noisy`` and their filtered
    values ``filtered`` (same keys); ``outputs``: each run branch's denoised output (its own space).

    The beauty clamps a linear branch's output at 0 (the multi-scale blend is not convex, so it can dip
    below): a group's part of that branch is kept where the branch is positive and is 0 where the beauty
    clamped it. A group's specular part is its share of the denoised specular: ``K ⊛ g / K ⊛ specular``
    where the filtered beauty specular is at least :data:`SHARE_FLOOR` of the denoised one; elsewhere
    (beside a firefly the filtered specular can be 0 or negative while the log-space branch is not) the
    noisy pixel's share ``g / specular``, or, where that is 0 too, an equal share of the groups asked
    for. So light groups add up to the beauty everywhere.
    """
    n_spec = sum(1 for p in plans if p.group and "specular" in p.parts)
    out = {}
    for plan in plans:
        value = torch.zeros_like(albedo)
        for b, name in plan.parts.items():
            if b not in run:  # a branch not run is zero here: its parts contribute 0
                continue
            if not plan.group:
                value = value + filtered[b][f"{name}|raw"]
            elif b == "diffuse":
                part = (albedo + EPS) * filtered[b][f"{name}|demod"]
                value = value + torch.where(outputs[b] > 0, part, torch.zeros_like(part))
            elif b == "specular":
                total, part = filtered[b]["specular|pos"], filtered[b][f"{name}|pos"]
                total_n, part_n = noisy[b]["specular|pos"], noisy[b][f"{name}|pos"]
                beauty = radiance_of(outputs[b])
                fallback = torch.where(total_n > 0, part_n / total_n.clamp_min(1e-30), torch.full_like(part, 1.0 / n_spec))
                share = torch.where(total > SHARE_FLOOR * beauty, part / total.clamp_min(1e-30), fallback)
                value = value + beauty * share
            else:  # a linear branch (color_albedo_normal)
                part = filtered[b][f"{name}|pos"]
                value = value + torch.where(outputs[b] > 0, part, torch.zeros_like(part))
        out[plan.name] = value
    return out


def denoise_aovs(net, inputs: dict, res: dict, context, frame: Frame, crop, run, plans: list[AovPlan],
                 device) -> dict[str, torch.Tensor]:
    """The requested layers over one crop, ``{name: (1, 3, h, w)}``, with the kernels of the branches in ``run``.

    ``inputs`` and ``res`` are the model's inputs and outputs on the crop; a
    branch not in ``run`` is zero on the crop (its parts contribute 0).
    """
    sig = aov_signals(plans, run, lambda name: frame_to_tensors(frame, (name,), crop, device)[name], inputs["albedo"])
    filtered = {}
    for b in run:
        if sig[b]:
            guide = (inputs["normal"],) if net.reads_normal else ()
            kernels = net.branch_kernels(b, inputs[b], context, *guide)
            apply = getattr(net, b).apply_kernels
            filtered[b] = {k: apply(v.contiguous(), kernels) for k, v in sig[b].items()}
    return compose_aovs(plans, run, filtered, sig, res.get("albedo", inputs["albedo"]), res)
