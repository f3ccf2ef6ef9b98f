"""Input specifications: which EXR layers a model reads and how they become its tensors.

A model names its input spec (``model.input_spec``); everything else — the
layers :func:`kpcn.io.read_exr` must find, the features the data set builds,
the training targets, which tiles can be skipped, how the denoised components
add up to the colour — follows from the spec. Adding an input layout is one
:func:`register_input_spec` call.

Every spec turns ``(B, C, H, W)`` layer tensors into a dict with one tensor per
*branch* (the components the model denoises separately; channels 0..2 of each
are the noisy colour its kernels filter) plus ``albedo``:

============================  =========================  =========  =======================================
spec                          branches                   channels   layers read
============================  =========================  =========  =======================================
``kpcn_split``                ``diffuse``, ``specular``  27 each    diffuse, specular, albedo, normal, depth
                                                                    and the variances of all five
``split_novar``               ``diffuse``, ``specular``  23 each    diffuse, specular, albedo, normal, depth
``color_albedo_normal``       ``color``                  9          color, albedo, normal (OIDN's inputs)
``color_albedo_normal_noise`` ``color``                  10         the same, plus the frame's noise precision
                                                                    (:mod:`kpcn.noise`) as one constant channel
============================  =========================  =========  =======================================

The split specs use the KPCN transforms (DESIGN: ``diffuse / (albedo + eps)``
and ``log1p(specular)``, gradients as forward differences; see
:mod:`kpcn.features`); ``color_albedo_normal`` keeps the radiance linear
(clamped at 0) beside the albedo and normal.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Callable, Mapping

import numpy as np
import torch

from .constants import BRANCH_LAYERS, EPS, OIDN_ALBEDO
from .features import COLOR_VAR, FEATURE_VAR, branch_features, depth_scale_of, finite_copy, frame_to_tensors
from .noise import REVISION as NOISE_REVISION, noise_precision

__all__ = [
    "InputSpec",
    "SPECULAR_LOG_MAX",
    "radiance_of",
    "register_input_spec",
    "get_input_spec",
    "list_input_specs",
    "split_reconstruct",
    "finite_nonneg",
]

#: Upper clamp of the specular branch output (log1p space) before ``expm1``;
#: ``expm1(80) ~ 5.5e34`` is finite in float32.
SPECULAR_LOG_MAX = 80.0


def radiance_of(x: torch.Tensor) -> torch.Tensor:
    """The radiance ``expm1(x)`` of a ``log1p``-encoded colour (the specular branch's), ``x`` clamped to
    ``[0, SPECULAR_LOG_MAX]`` first (``log1p`` of a radiance ≥ 0; finite in float32)."""
    return torch.expm1(x.clamp(0.0, SPECULAR_LOG_MAX))

Tensors = dict[str, torch.Tensor]


@dataclass(frozen=True)
class InputSpec:
    """How EXR layers become a model's inputs, targets and output colour.

    Attributes:
        name: registry name.
        description: one line for ``--help`` and errors.
        layers: EXR layers a noisy input must have.
        branches: names of the components denoised separately (their tensors
            are keys of the built inputs; outputs carry the same keys).
        channels: channels of each branch tensor.
        branch_layers: per branch, the layers only that branch reads (a branch
            whose layers are zero over a region is zero there).
        halo: pixels beyond a pixel that its features read (1: forward differences).
        uses_depth_scale: the features divide depth by the whole frame's largest
            depth (tiles must be given that value: :meth:`frame_value`).
        frame_stat: ``frame_stat(frame) -> (1, 1, 1, 1)``, another whole-frame value
            the features read (the noise precision); like the depth scale, tiles
            are given the whole frame's (:meth:`frame_value`), and ``build``
            computes it from its buffers when it is not given.
        revision: bumped when the features' maths changes, so stores of built
            patches (:mod:`kpcn.store`) made before are rebuilt, not trusted.
        target_layers: layers a reference render must have.
        build: ``build(buffers, frame_value, branches) -> inputs``; ``frame_value``
            is the depth scale or ``frame_stat`` (None: from ``buffers``); ``branches``
            lists those to build (the others are absent from the result).
        targets: ``targets(reference_buffers, inputs) -> {"y_<branch>", "y_color"}``.
        reconstruct: ``reconstruct(outputs, inputs) -> (B, 3, H, W)`` colour from
            the denoised branches (a branch missing from ``outputs`` is zero).
        rgb_starts: first channels of the RGB triplets of a branch tensor (colour
            and colour-like features, permuted together by :mod:`kpcn.augment`).
        grad_x, grad_y: ``(start, stop)`` of the channels that are forward
            differences in x / in y (in the same feature order), or None.
        variance_channels: the channels of a branch tensor that are variances
            (the patch store keeps them float32; the ``logvar`` transform logs them).
        prefer: ``((layer, other), ...)``: ``layer`` is read from ``other`` in frames that have it
            (:meth:`select`); e.g. OIDN's albedo (Cycles' Denoising Albedo) for ``albedo``.
        colour_variance: ``colour_variance(inputs) -> (B, 1, H, W)``: the variance of the pixel mean of
            the colour (mean over RGB) as the built inputs carry it, or None where they carry no
            variance (training's ``data.converged_max_noise`` needs it).
        log_branches: the branches whose colour (channels 0..2) is ``log1p`` of the radiance (the split
            specs' specular): a model can pool them as radiance, ``log1p(mean(expm1(c)))``.
    """

    name: str
    description: str
    layers: tuple[str, ...]
    branches: tuple[str, ...]
    channels: int
    branch_layers: Mapping[str, tuple[str, ...]]
    halo: int
    uses_depth_scale: bool
    target_layers: tuple[str, ...]
    build: Callable[..., Tensors] = field(repr=False)
    targets: Callable[[Tensors, Tensors], Tensors] = field(repr=False)
    reconstruct: Callable[[Tensors, Tensors], torch.Tensor] = field(repr=False)
    rgb_starts: tuple[int, ...] = (0,)
    grad_x: tuple[int, int] | None = None
    grad_y: tuple[int, int] | None = None
    variance_channels: tuple[int, ...] = ()
    prefer: tuple[tuple[str, str], ...] = ()
    frame_stat: Callable | None = field(default=None, repr=False)
    revision: int = 0
    colour_variance: Callable[[Tensors], torch.Tensor] | None = field(default=None, repr=False)
    log_branches: tuple[str, ...] = ()

    def select(self, frame):
        """The :class:`~kpcn.io.Frame` this spec reads from ``frame``: its layers with :attr:`prefer` applied."""
        return frame.preferring(dict(self.prefer)) if self.prefer else frame

    def layers_for(self, branches) -> tuple[str, ...]:
        """The layers needed to build only ``branches``."""
        skip = {n for b in self.branches if b not in branches for n in self.branch_layers[b]}
        return tuple(n for n in self.layers if n not in skip)

    def frame_depth_scale(self, frame) -> torch.Tensor | None:
        """The whole frame's depth normaliser ``(1, 1, 1, 1)`` (None if the spec does not use depth)."""
        if not self.uses_depth_scale:
            return None
        depth = torch.from_numpy(np.ascontiguousarray(frame["depth"][..., 0])).clamp_min(0.0)[None, None]
        return depth_scale_of(depth)

    def frame_value(self, frame) -> torch.Tensor | None:
        """The whole-frame value ``build`` takes as its second argument: the depth scale, ``frame_stat``, or None."""
        if self.uses_depth_scale:
            return self.frame_depth_scale(frame)
        return self.frame_stat(frame) if self.frame_stat is not None else None

    def branch_is_zero(self, frame, branch: str, crop=(slice(None), slice(None))) -> bool:
        """Whether ``branch`` has no positive radiance in ``frame`` over ``crop`` (its output is then 0)."""
        return not np.any(frame.region(self.branch_layers[branch][0], crop) > 0)


_SPECS: dict[str, InputSpec] = {}


def register_input_spec(spec: InputSpec) -> InputSpec:
    if spec.name in _SPECS and _SPECS[spec.name] != spec:
        raise ValueError(f"an input spec named {spec.name!r} is already registered")
    _SPECS[spec.name] = spec
    return spec


def get_input_spec(name: str | InputSpec) -> InputSpec:
    """The spec registered as ``name`` (an :class:`InputSpec` is returned as is)."""
    if isinstance(name, InputSpec):
        return name
    try:
        return _SPECS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown input spec {name!r}; known: {', '.join(sorted(_SPECS))}") from None


def list_input_specs() -> list[str]:
    return sorted(_SPECS)


# ----------------------------------------------------------------------------- shared maths


def finite_nonneg(color: torch.Tensor) -> torch.Tensor:
    """NaN -> 0, +Inf -> the dtype's largest value, then clamped at 0."""
    big = torch.finfo(color.dtype).max
    return torch.nan_to_num(color, nan=0.0, posinf=big, neginf=0.0).clamp(min=0.0)


def _clean(x: torch.Tensor) -> torch.Tensor:
    return finite_copy(x).clamp_min_(0.0)


def split_reconstruct(outputs: Tensors, inputs: Tensors) -> torch.Tensor:
    """``(albedo + EPS) * max(diffuse, 0) + expm1(clamp(specular, 0, SPECULAR_LOG_MAX))``, finite and >= 0.

    A branch missing from ``outputs`` (not run: zero radiance) contributes 0.
    """
    albedo = inputs["albedo"]
    color = torch.zeros_like(albedo)
    if outputs.get("diffuse") is not None:
        color = color + (albedo + EPS) * outputs["diffuse"].clamp(min=0)
    if outputs.get("specular") is not None:
        color = color + radiance_of(outputs["specular"])
    return finite_nonneg(color)


def _split_targets(ref: Tensors, inputs: Tensors) -> Tensors:
    """Targets in each branch's space; the diffuse one against the *input's* albedo (reconstruction uses it)."""
    d, s = _clean(ref["diffuse"]), _clean(ref["specular"])
    return {"y_diffuse": d / (inputs["albedo"] + EPS), "y_specular": torch.log1p(s), "y_color": d + s}


def _split_colour_variance(inputs: Tensors) -> torch.Tensor:
    """The colour's variance ``(B, 1, H, W)`` from the split features: the diffuse branch's variance of
    the irradiance times the albedo squared, plus the specular branch's variance of log(1 + specular)
    times (1 + specular) squared (the delta method backwards); each an RGB mean, as the features keep them."""
    d, s, a = inputs["diffuse"], inputs["specular"], inputs["albedo"]
    var_d = d[:, COLOR_VAR] * ((a + EPS) ** 2).mean(1, keepdim=True)
    var_s = s[:, COLOR_VAR] * torch.exp(2.0 * s[:, 0:3].clamp_min(0.0)).mean(1, keepdim=True)
    return var_d + var_s


_AUX = ("albedo", "normal", "depth")


def _split_spec(name: str, variances: bool, description: str) -> InputSpec:
    branch_layers = {b: ls if variances else ls[:1] for b, ls in BRANCH_LAYERS.items()}
    layers = ("diffuse", "specular") + _AUX
    if variances:
        layers += tuple(f"{n}Variance" for n in layers)

    def build(buffers, depth_scale=None, branches=("diffuse", "specular")):
        return branch_features(buffers, depth_scale, branches, variances=variances)

    return InputSpec(
        name=name, description=description, layers=layers, branches=("diffuse", "specular"),
        channels=27 if variances else 23, branch_layers=branch_layers, halo=1, uses_depth_scale=True,
        target_layers=("diffuse", "specular"), build=build, targets=_split_targets, reconstruct=split_reconstruct,
        # channel order (kpcn.features): colour 3, [variance 1], d/dx of colour 3, normal 3, albedo 3, depth 1,
        # d/dy of the same 10, [variances of normal, albedo, depth]
        rgb_starts=(0, 4, 10, 14, 20) if variances else (0, 3, 9, 13, 19),
        grad_x=(4, 14) if variances else (3, 13), grad_y=(14, 24) if variances else (13, 23),
        variance_channels=(*range(COLOR_VAR.start, COLOR_VAR.stop), *range(FEATURE_VAR.start, FEATURE_VAR.stop))
        if variances else (),
        colour_variance=_split_colour_variance if variances else None, log_branches=("specular",),
    )


KPCN_SPLIT = register_input_spec(_split_spec(
    "kpcn_split", True, "diffuse/specular split with per-pixel variances (Bako et al. 2017; 27 channels a branch)"))
SPLIT_NOVAR = register_input_spec(_split_spec(
    "split_novar", False, "diffuse/specular split without variances (renderers with no variance pass; 23 channels a branch)"))


def _can_build(buffers, frame_value=None, branches=("color",), noise=False):
    name = "color_albedo_normal_noise" if noise else "color_albedo_normal"
    missing = [n for n in ("color", "albedo", "normal") if n not in buffers]
    if missing:
        raise KeyError(f"{name}: missing buffers {missing}; got {sorted(buffers)}")
    albedo = _clean(buffers["albedo"])
    out = {"albedo": albedo}
    if "color" in branches:
        normal = finite_copy(buffers["normal"])
        parts = [_clean(buffers["color"]), albedo, normal]
        if noise:
            if frame_value is None:  # a whole frame (training, or an untiled call): its own precision
                frame_value = noise_precision(buffers["color"], albedo, normal)
            b, _, h, w = albedo.shape
            parts.append(torch.as_tensor(frame_value, dtype=albedo.dtype, device=albedo.device)
                         .reshape(-1, 1, 1, 1).expand(b, 1, h, w))
        out["color"] = torch.cat(parts, dim=1)
    return out


def _frame_precision(frame) -> torch.Tensor:
    """:func:`kpcn.noise.noise_precision` of a whole :class:`~kpcn.io.Frame` (its selected layers), ``(1, 1, 1, 1)``."""
    t = frame_to_tensors(frame, ("color", "albedo", "normal"))
    return noise_precision(t["color"], t["albedo"], t["normal"])


def _can_targets(ref: Tensors, inputs: Tensors) -> Tensors:
    c = _clean(ref["color"])
    return {"y_color": c}


def _can_reconstruct(outputs: Tensors, inputs: Tensors) -> torch.Tensor:
    c = outputs.get("color")
    return finite_nonneg(c) if c is not None else torch.zeros_like(inputs["albedo"])


COLOR_ALBEDO_NORMAL = register_input_spec(InputSpec(
    name="color_albedo_normal",
    description="colour + albedo + normal, no split and no variances (what OIDN takes; 9 channels)",
    layers=("color", "albedo", "normal"), branches=("color",), channels=9, branch_layers={"color": ("color",)},
    halo=0, uses_depth_scale=False, target_layers=("color",), build=_can_build, targets=_can_targets,
    reconstruct=_can_reconstruct, rgb_starts=(0, 3),
    # OIDN's albedo where the renderer writes it (Cycles' Denoising Albedo follows mirrors and glass to the next
    # rough surface): without a split, the only guide for reflections; the split specs keep the diffuse albedo
    prefer=(("albedo", OIDN_ALBEDO),),
))
COLOR_ALBEDO_NORMAL_NOISE = register_input_spec(InputSpec(
    name="color_albedo_normal_noise",
    description="colour + albedo + normal and the frame's estimated noise precision (kpcn.noise; 10 channels)",
    layers=("color", "albedo", "normal"), branches=("color",), channels=10, branch_layers={"color": ("color",)},
    halo=0, uses_depth_scale=False, target_layers=("color",), build=partial(_can_build, noise=True),
    targets=_can_targets, reconstruct=_can_reconstruct, rgb_starts=(0, 3), prefer=(("albedo", OIDN_ALBEDO),),
    # a lone bright pixel is a highlight in a converged frame and a firefly in a 2-spp one: the frame's noise tells
    frame_stat=_frame_precision, revision=NOISE_REVISION,
))
