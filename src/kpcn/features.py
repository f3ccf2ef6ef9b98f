"""KPCN input features and training targets (DESIGN §2.2, Bako et al. 2017 eq. 6).

Each branch gets a ``(B, 27, H, W)`` tensor with this channel layout:

=========  ===========================================================
channels   content
=========  ===========================================================
0–2        branch colour: ``diffuse / (albedo + eps)`` or ``log1p(specular)``
3          its variance (delta method for specular), mean over RGB
4–13       x-gradients of branch colour (3), normal (3), albedo (3), depth (1)
14–23      y-gradients of the same ten channels
24–26      variances of normal, albedo, depth (one channel each)
=========  ===========================================================

Gradients are forward differences, zero on the last column / row. Depth is
divided by the image's largest depth (``depth_scale``; pass the whole frame's
value when working on tiles) and its variance by the square of that.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import torch

from .constants import EPS, N_FEATURES  # noqa: F401  (N_FEATURES re-exported)
from .io import Frame

#: layers the features read from a noisy render
INPUT_LAYERS = (
    "diffuse",
    "specular",
    "albedo",
    "normal",
    "depth",
    "diffuseVariance",
    "specularVariance",
    "albedoVariance",
    "normalVariance",
    "depthVariance",
)
#: layers a reference render must have for training targets
TARGET_LAYERS = ("diffuse", "specular")

# channel indices, for code that reads the features
COLOR = slice(0, 3)
COLOR_VAR = slice(3, 4)
GRAD_X = slice(4, 14)
GRAD_Y = slice(14, 24)
FEATURE_VAR = slice(24, 27)


def frame_to_tensors(frame: Frame, layers=INPUT_LAYERS) -> dict[str, torch.Tensor]:
    """Layers of a frame as float32 ``(1, C, H, W)`` tensors (checks they are present)."""
    frame.require(layers)
    return {n: torch.from_numpy(np.ascontiguousarray(frame[n].transpose(2, 0, 1)))[None].float() for n in layers}


def _mean_c(x: torch.Tensor) -> torch.Tensor:
    return x.mean(dim=1, keepdim=True)


def gradients(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences of ``(B, C, H, W)`` in x and y, zero on the last column / row."""
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    gx[..., :, :-1] = x[..., :, 1:] - x[..., :, :-1]
    gy[..., :-1, :] = x[..., 1:, :] - x[..., :-1, :]
    return gx, gy


def depth_scale_of(depth: torch.Tensor) -> torch.Tensor:
    """Per-image depth normaliser ``(B, 1, 1, 1)``: the largest depth, or 1 where nothing was hit."""
    m = depth.flatten(1).amax(dim=1).view(-1, 1, 1, 1)
    return torch.where(m > 0, m, torch.ones_like(m))


def _variance(v: torch.Tensor) -> torch.Tensor:
    """One-channel variance: non-finite and negative values zeroed, mean over RGB."""
    return _mean_c(_variance_rgb(v))


def diffuse_color(diffuse: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """Irradiance-like diffuse branch colour ``diffuse / (albedo + eps)`` (negatives clamped)."""
    return diffuse.clamp_min(0.0) / (albedo.clamp_min(0.0) + EPS)


def specular_color(specular: torch.Tensor) -> torch.Tensor:
    """Log-space specular branch colour ``log1p(max(specular, 0))``."""
    return torch.log1p(specular.clamp_min(0.0))


@dataclass
class Features:
    """Network inputs for one batch; every tensor is ``(B, C, H, W)``.

    A branch left out (see :func:`make_features`) is ``None``.
    """

    x_diffuse: torch.Tensor | None  # (B, 27, H, W)
    x_specular: torch.Tensor | None  # (B, 27, H, W)
    albedo: torch.Tensor  # (B, 3, H, W), clamped at 0: reconstruction multiplies by albedo + eps

    def as_dict(self) -> dict[str, torch.Tensor]:
        return {"x_diffuse": self.x_diffuse, "x_specular": self.x_specular, "albedo": self.albedo}


BRANCHES = ("diffuse", "specular")
SHARED_LAYERS = ("albedo", "normal", "depth", "albedoVariance", "normalVariance", "depthVariance")
BRANCH_LAYERS = {"diffuse": ("diffuse", "diffuseVariance"), "specular": ("specular", "specularVariance")}


def make_features(
    buffers: dict[str, torch.Tensor],
    depth_scale: torch.Tensor | float | None = None,
    branches=BRANCHES,
) -> Features:
    """Compute the 27-channel features of both branches (or only those in ``branches``).

    Args:
        buffers: ``(B, C, H, W)`` tensors named as :data:`INPUT_LAYERS`.
            Non-finite values are replaced by 0 (readers already count them).
        depth_scale: divide depth by this; default: the largest depth per image.
        branches: the branches to build; the others are ``None`` and their
            buffers need not be present.

    Returns:
        :class:`Features`.
    """
    out = branch_features(buffers, depth_scale, branches)
    return Features(out.get("diffuse"), out.get("specular"), out["albedo"])


def branch_features(
    buffers: Mapping[str, torch.Tensor],
    depth_scale: torch.Tensor | float | None = None,
    branches=BRANCHES,
    variances: bool = True,
) -> dict[str, torch.Tensor]:
    """The 27-channel features of only the listed branches, plus the clamped albedo.

    Gives exactly the tensors of :func:`kpcn.features.make_features` (same ops
    on the same values; a test checks bit equality) but builds a branch's
    channels only when it is listed, reads only the buffers those branches
    need, and computes the shared normal/albedo/depth gradients once.

    Args:
        buffers: ``(B, C, H, W)`` tensors named as in :data:`INPUT_LAYERS`
            (those of an unlisted branch may be absent).
        depth_scale: depth normaliser; default the largest depth per image.
        branches: subset of ``("diffuse", "specular")``.
        variances: ``False`` leaves out the four variance channels (and does not
            read any variance layer): 23 channels, colour then gradients.

    Returns:
        ``{"albedo": (B, 3, H, W), "diffuse": (B, 27, H, W)?, "specular": (B, 27, H, W)?}``.
    """
    branches = tuple(branches)
    need = list(SHARED_LAYERS) + [n for b in branches for n in BRANCH_LAYERS[b]]
    if not variances:
        need = [n for n in need if not n.endswith("Variance")]
    missing = [n for n in need if n not in buffers]
    if missing:
        raise KeyError(f"branch_features: missing buffers {missing}; got {sorted(buffers)}")
    b = {k: torch.nan_to_num(buffers[k].float(), nan=0.0, posinf=0.0, neginf=0.0) for k in need}
    albedo = b["albedo"].clamp_min(0.0)
    depth = b["depth"][:, :1].clamp_min(0.0)
    if depth_scale is None:
        depth_scale = depth_scale_of(depth)
    depth = depth / depth_scale
    if variances:
        var_n = _variance(b["normalVariance"])
        var_a = _variance(b["albedoVariance"])
        var_d = _variance(b["depthVariance"][:, :1]) / (torch.as_tensor(depth_scale) ** 2)
    aux_gx, aux_gy = gradients(torch.cat([b["normal"], albedo, depth], dim=1))
    out = {"albedo": albedo}
    for name in branches:
        if name == "diffuse":
            color = diffuse_color(b["diffuse"], albedo)
            if variances:
                var = _mean_c(_variance_rgb(b["diffuseVariance"]) / (albedo + EPS) ** 2)
        elif name == "specular":
            raw = b["specular"].clamp_min(0.0)
            color = specular_color(raw)
            if variances:
                var = _mean_c(_variance_rgb(b["specularVariance"]) / (1.0 + raw) ** 2)
        else:
            raise ValueError(f"branch_features: unknown branch {name!r}; expected one of {BRANCHES}")
        gx, gy = gradients(color)
        if variances:
            out[name] = torch.cat([color, var, gx, aux_gx, gy, aux_gy, var_n, var_a, var_d], dim=1)
        else:
            out[name] = torch.cat([color, gx, aux_gx, gy, aux_gy], dim=1)
    return out


def _variance_rgb(v: torch.Tensor) -> torch.Tensor:
    v = torch.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    return v.expand(-1, 3, -1, -1) if v.shape[1] == 1 else v


def make_targets(reference: dict[str, torch.Tensor], albedo: torch.Tensor) -> dict[str, torch.Tensor]:
    """Training targets from a reference render, in each branch's space.

    Args:
        reference: ``(B, 3, H, W)`` ``diffuse`` and ``specular`` of the reference.
        albedo: the *noisy input's* albedo ``(B, 3, H, W)``, since reconstruction
            multiplies by it.

    Returns:
        ``y_diffuse`` (irradiance), ``y_specular`` (log1p) and ``y_color``
        (``diffuse + specular`` of the reference), each ``(B, 3, H, W)``.
    """
    d = torch.nan_to_num(reference["diffuse"].float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    s = torch.nan_to_num(reference["specular"].float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    return {"y_diffuse": d / (albedo + EPS), "y_specular": torch.log1p(s), "y_color": d + s}


def frame_features(frame: Frame) -> Features:
    """Features of a whole noisy frame (batch of one)."""
    return make_features(frame_to_tensors(frame))
