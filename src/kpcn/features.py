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

Variances are bounded before they are divided or squared (:func:`bound_variance`):
the variance of the mean of n >= 2 non-negative samples is at most the mean
squared, and that of normals (in [-1, 1]) at most 1. A larger value (a corrupt
file, a variance near the float maximum) is clamped to that bound, and the
clamped values are counted, per layer, in a RuntimeWarning; a kpcn render never
reaches the bound, so its features do not change.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Mapping

import numpy as np
import torch

from .constants import BRANCH_LAYERS, EPS, N_FEATURES  # noqa: F401  (BRANCH_LAYERS, N_FEATURES re-exported)
from .io import Frame
from .ops.fused import branch_features_native

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


def frame_to_tensors(frame: Frame, layers=INPUT_LAYERS, crop=None, device=None, contiguous: bool = True
                     ) -> dict[str, torch.Tensor]:
    """Layers of a frame as float32 ``(1, C, H, W)`` tensors (checks they are present); ``crop``: a
    ``(rows, columns)`` pair of slices to take; ``device``: where to put them. ``contiguous=False``: on the
    CPU, views of the frame's ``(H, W, C)`` arrays (no copy; :func:`branch_features` copies them once)."""
    frame.require(layers)
    out = {}
    for n in layers:
        a = frame.region(n, crop)  # only the crop of a layer computed when read (kpcn.exposure.ScaledLayers)
        if contiguous:
            a = np.ascontiguousarray(a.transpose(2, 0, 1))
            t = torch.from_numpy(a)[None].float()
        else:
            t = torch.from_numpy(a).permute(2, 0, 1)[None].float()
        out[n] = t if device is None else t.to(device, non_blocking=True)
    return out


def gradients(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences of ``(B, C, H, W)`` in x and y, zero on the last column / row."""
    gx, gy = torch.empty_like(x), torch.empty_like(x)
    _gradients_into(x, gx, gy)
    return gx, gy


def depth_scale_of(depth: torch.Tensor) -> torch.Tensor:
    """Per-image depth normaliser ``(B, 1, 1, 1)``: the largest depth, or 1 where nothing was hit."""
    m = depth.flatten(1).amax(dim=1).view(-1, 1, 1, 1)
    return torch.where(m > 0, m, torch.ones_like(m))


#: Ceiling of every variance fed to the features, whatever the layer's mean: keeps
#: ``var / (albedo + eps)^2`` (<= 1e35) and its mean over RGB finite in float32.
VARIANCE_MAX = 1e30
#: Slack of the bound ``mean^2`` for rounding: of the moments (float32) and of float16 files.
VARIANCE_BOUND_REL = 1e-2
VARIANCE_BOUND_ABS = 1e-6


def variance_bound(mean: torch.Tensor, unit_range: bool = False) -> torch.Tensor:
    """The largest variance of a pixel mean ``mean`` (``(B, C, H, W)``) can have, per channel.

    For n >= 2 non-negative samples of mean m, the variance of the mean
    ``(m2 - m^2) / (n - 1)`` is at most ``m^2`` (all the weight in one sample);
    for samples in [-1, 1] (``unit_range``: normals) at most 1. A slack of
    :data:`VARIANCE_BOUND_REL` and :data:`VARIANCE_BOUND_ABS` covers rounding;
    the bound never exceeds :data:`VARIANCE_MAX`.
    """
    m2 = mean.float().square()
    if unit_range:
        m2 = m2.clamp_min(1.0)
    return (m2 * (1.0 + VARIANCE_BOUND_REL) + VARIANCE_BOUND_ABS).clamp_max(VARIANCE_MAX)


def bound_variance(var: torch.Tensor, mean: torch.Tensor, unit_range: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``var`` with non-finite and negative values zeroed and values above :func:`variance_bound` clamped.

    Args:
        var: ``(B, C, H, W)`` variance of the pixel mean (C = 3 or 1).
        mean: ``(B, C', H, W)`` the layer itself; with a one-channel ``var`` the
            bound is that of the brightest channel.
        unit_range: the samples lie in [-1, 1] (normals).

    Returns:
        The bounded variance (same shape as ``var``; values within the bound
        unchanged) and the number of clamped values (a 0-dim tensor).
    """
    v = torch.nan_to_num(var.float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    return _bound_finite(v, torch.nan_to_num(mean, nan=0.0, posinf=0.0, neginf=0.0), unit_range)


def _bound_finite(v: torch.Tensor, mean: torch.Tensor, unit_range: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`bound_variance` of a finite, non-negative ``v`` and a finite ``mean`` (``v`` clamped in place)."""
    bound = variance_bound(mean, unit_range)
    if bound.shape[1] != v.shape[1]:
        bound = bound.amax(dim=1, keepdim=True)
    over = v > bound
    return torch.minimum(v, bound, out=v), over.sum()


def _warn_clamped(counts: Mapping[str, torch.Tensor]) -> None:
    if not counts:
        return
    values = torch.stack([c.reshape(()) for c in counts.values()]).tolist()  # one sync for all layers
    hit = {k: int(n) for k, n in zip(counts, values) if n}
    if hit:
        warnings.warn(
            "kpcn.features: clamped variances above the largest variance a pixel mean can have "
            f"(its mean squared; 1 for normals; at most {VARIANCE_MAX:g}): "
            + ", ".join(f"{k}: {n}" for k, n in hit.items())
            + " value(s); these variances are corrupt or not the variance of the pixel mean",
            RuntimeWarning,
            stacklevel=3,
        )


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

    What :func:`kpcn.features.make_features` returns, as a dict; builds a
    branch's channels only when it is listed, reads only the buffers those
    branches need, computes the shared normal/albedo/depth gradients and
    variances once, and writes each branch's channels in place into one
    tensor (no concatenation: on a 1080p frame in row bands this took a third
    off the features' time).

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
    unknown = [n for n in branches if n not in BRANCHES]
    if unknown:
        raise ValueError(f"branch_features: unknown branch {unknown[0]!r}; expected one of {BRANCHES}")
    if variances and buffers["albedo"].shape[0] == 1:  # one native pass where it applies (the same to float rounding)
        done = branch_features_native(buffers, depth_scale, branches)
        if done is not None:
            out, counts = done
            _warn_clamped(counts)
            return out
    # from here on every buffer is finite (its own copy), and every variance finite and >= 0
    b = {k: finite_copy(buffers[k]) for k in need}
    if variances:  # bound every variance by what its layer's mean allows, before any division
        clamped = {}
        for k in need:
            if k.endswith("Variance"):
                layer = k[: -len("Variance")]
                var = b[k][:, :1] if layer == "depth" else b[k]
                mean = b[layer][:, :1] if layer == "depth" else b[layer]
                b[k], clamped[k] = _bound_finite(var.clamp_min(0.0), mean, layer == "normal")
        _warn_clamped(clamped)
    albedo = b["albedo"].clamp_min_(0.0)
    depth = b["depth"][:, :1].clamp_min_(0.0)
    if depth_scale is None:
        depth_scale = depth_scale_of(depth)
    depth = depth / depth_scale
    # each branch's channels are written in place into one tensor (no concatenation): colour, its
    # variance, x-gradients of colour and of normal/albedo/depth, the same in y, the feature variances
    n_ch = N_FEATURES if variances else N_FEATURES - 4
    shape = (albedo.shape[0], n_ch) + tuple(albedo.shape[-2:])
    v = 1 if variances else 0
    gx_at, gy_at = 3 + v, 13 + v  # first x- and y-gradient channels
    out = {"albedo": albedo}
    first = None
    for name in branches:
        x = torch.empty(shape, dtype=albedo.dtype, device=albedo.device)
        color = x[:, 0:3]
        if name == "diffuse":
            torch.div(b["diffuse"].clamp_min_(0.0), albedo + EPS, out=color)
            if variances:
                torch.mean(_rgb(b["diffuseVariance"]) / (albedo + EPS) ** 2, dim=1, keepdim=True, out=x[:, 3:4])
        else:
            raw = b["specular"].clamp_min_(0.0)
            torch.log1p(raw, out=color)
            if variances:
                torch.mean(_rgb(b["specularVariance"]) / (1.0 + raw) ** 2, dim=1, keepdim=True, out=x[:, 3:4])
        _gradients_into(color, x[:, gx_at:gx_at + 3], x[:, gy_at:gy_at + 3])
        if first is None:  # the shared channels, computed once
            for i, t in enumerate((b["normal"], albedo, depth)):
                c0 = 3 * i
                _gradients_into(t, x[:, gx_at + 3 + c0:gx_at + 3 + c0 + t.shape[1]],
                                x[:, gy_at + 3 + c0:gy_at + 3 + c0 + t.shape[1]])
            if variances:
                c0 = FEATURE_VAR.start
                for c, k in enumerate(("normalVariance", "albedoVariance", "depthVariance"), c0):
                    torch.mean(_rgb(b[k]), dim=1, keepdim=True, out=x[:, c:c + 1])
                x[:, c0 + 2:c0 + 3].div_(torch.as_tensor(depth_scale) ** 2)
            first = x
        else:
            x[:, gx_at + 3:gx_at + 10] = first[:, gx_at + 3:gx_at + 10]
            x[:, gy_at + 3:] = first[:, gy_at + 3:]
        out[name] = x
    return out


def finite_copy(t: torch.Tensor) -> torch.Tensor:
    """``t`` as a new contiguous float32 tensor with NaN and ±Inf replaced by 0 (one pass, whatever ``t``'s strides)."""
    out = torch.empty(t.shape, dtype=torch.float32, device=t.device)
    return torch.nan_to_num(t.float(), nan=0.0, posinf=0.0, neginf=0.0, out=out)


def _gradients_into(x: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor) -> None:
    """:func:`gradients` of ``x`` written into ``gx`` and ``gy`` (views of the same shape)."""
    torch.sub(x[..., :, 1:], x[..., :, :-1], out=gx[..., :, :-1])
    gx[..., :, -1] = 0.0
    torch.sub(x[..., 1:, :], x[..., :-1, :], out=gy[..., :-1, :])
    gy[..., -1, :] = 0.0


def _rgb(v: torch.Tensor) -> torch.Tensor:
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
