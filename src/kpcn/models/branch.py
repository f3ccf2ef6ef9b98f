"""The configuration and conv stack that KPCN's and DPCN's branches share (:mod:`kpcn.models.kpcn`).

* :class:`BranchConfig`: one branch's architecture and options (both registered models, ``kpcn`` and
  ``dpcn``, take it);
* :func:`_conv_stack`: the branch's stack of convs (ReLU between, none after the last);
* :func:`_check_branch_input`: the shape check of a branch's input.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from ..exposure import check_exposure_range
from ..inputs import get_input_spec
from ..ops.kernel_apply import PADDING_MODES
from .base import check_detail_config
from .layers import INPUT_TRANSFORMS

__all__ = ["BranchConfig"]


@dataclass
class BranchConfig:
    """Architecture of one branch (both branches share it).

    Attributes:
        layers: number of conv layers (>= 1), the last one included.
        width: channels of the hidden layers.
        conv_size: odd spatial size of every conv.
        kernel_size: odd size ``k`` of the predicted per-pixel kernels (KPCN only).
        input_spec: the :mod:`kpcn.inputs` spec the model reads: ``kpcn_split``
            (27 channels a branch, the paper), ``split_novar`` (23) or
            ``color_albedo_normal`` (one 9-channel branch).
        in_channels: channels of the branch input; ``None``: the spec's.
        logit_scale: bound of the kernel logits, ``s * tanh(z / s)``; ``None``
            leaves them unbounded (KPCN only).
        padding_mode: ``"replicate"`` or ``"zeros"`` for the kernel application (KPCN only).
        init_sigma: std in pixels of the initial Gaussian kernel; ``None`` for a
            near-uniform initial kernel (KPCN only).
        out_init_gain: scale of the last conv's initial weights.
        dilations: one dilation per conv layer (``None``: all 1). Growing
            dilations (1, 2, 4, 8, ...) give a wide context at the cost of a
            plain conv: the "dilated" configs use them.
        precision_gate: KPCN on an input spec with a noise precision channel
            (``color_albedo_normal_noise``): blend each kernel with the identity by a
            gate of the frame's precision ``p``, ``g = sigmoid(10 (a + c p))`` (two learnt
            scalars): ``k' = g k + (1 - g) delta``. Still a convex kernel (constant stays
            constant, zero stays zero, light groups still sum), and a direct path by which
            a converged frame is left as it is. Starts nearly open (``g = 0.9975``).
        demodulate: KPCN on a colour + albedo + normal spec: the last conv predicts one
            more channel, a per-pixel weight ``beta = sigmoid(z)``, and the kernel ``w`` is
            applied as ``(1 - beta) sum_q w_q c_q + beta (a_p + e) sum_q w_q c_q / (a_q + e)``
            (``a``: mean albedo, ``e``: :data:`~kpcn.models.layers.DEMOD_EPS`): a blend of
            filtering the colour and filtering the albedo-demodulated colour, which the
            split specs' diffuse branch does and a colour-only input cannot. A bright
            neighbour of another albedo (an emitter's edge) then lends its shading, not
            its radiance. Still linear in the colour (light groups sum, zero stays zero,
            a constant with a constant albedo stays constant), but no longer convex.
        input_transform: ``"log"`` feeds the conv stack ``sign(x) log1p(|x|)`` of
            the features (the kernels are still applied to the raw colour), so
            the network sees the same range whether the scene is dim or 1e8
            bright; ``"none"`` feeds the raw features (the paper).
        detail_radius, detail_eps, detail_clip: the detail stage after the network (KPCN only; 0: off), as
            :class:`~kpcn.models.UNetConfig`'s.
        exposure_range: None, or ``[lo, hi]``: the exposure keys of the training frames, as
            :class:`~kpcn.models.UNetConfig`'s (an inference setting).
    """

    layers: int = 9
    width: int = 100
    conv_size: int = 5
    kernel_size: int = 21
    input_spec: str = "kpcn_split"
    in_channels: int | None = None
    logit_scale: float | None = 16.0
    padding_mode: str = "replicate"
    init_sigma: float | None = 1.5
    out_init_gain: float = 0.1
    dilations: list[int] | None = None
    input_transform: str = "log"
    precision_gate: bool = False
    demodulate: bool = False
    detail_radius: int = 0
    detail_eps: float = 0.01
    detail_clip: float = 0.0
    exposure_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        spec = get_input_spec(self.input_spec)
        check_detail_config(self, spec, "BranchConfig")
        check_exposure_range(self.exposure_range, "BranchConfig.exposure_range")
        if self.in_channels is None:
            self.in_channels = spec.channels
        if self.in_channels != spec.channels:
            raise ValueError(f"BranchConfig.in_channels is {self.in_channels} but input spec {spec.name!r} "
                             f"gives {spec.channels} channels a branch")
        if self.precision_gate and spec.frame_stat is None:
            raise ValueError(f"BranchConfig.precision_gate needs an input spec with a noise precision channel "
                             f"(color_albedo_normal_noise), not {spec.name!r}")
        if self.demodulate and spec.branches != ("color",):
            raise ValueError(f"BranchConfig.demodulate needs a colour + albedo + normal input spec (one 'color' "
                             f"branch, albedo in channels 3..5), not {spec.name!r}")
        if self.input_transform == "logvar" and spec.name != "kpcn_split":
            raise ValueError(f"BranchConfig.input_transform 'logvar' needs the kpcn_split input spec, not {spec.name!r}")
        for name in ("layers", "width", "conv_size", "kernel_size", "in_channels"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"BranchConfig.{name} must be a positive integer, got {v!r}")
        for name in ("conv_size", "kernel_size"):
            if getattr(self, name) % 2 == 0:
                raise ValueError(f"BranchConfig.{name} must be odd, got {getattr(self, name)}")
        if self.in_channels < 3:
            raise ValueError(f"BranchConfig.in_channels must be >= 3 (colour first), got {self.in_channels}")
        if self.logit_scale is not None and not (self.logit_scale > 0 and math.isfinite(self.logit_scale)):
            raise ValueError(f"BranchConfig.logit_scale must be a positive number or None, got {self.logit_scale!r}")
        if self.padding_mode not in PADDING_MODES:
            raise ValueError(f"BranchConfig.padding_mode must be one of {PADDING_MODES}, got {self.padding_mode!r}")
        if self.init_sigma is not None and not self.init_sigma > 0:
            raise ValueError(f"BranchConfig.init_sigma must be positive or None, got {self.init_sigma!r}")
        if self.dilations is not None:
            self.dilations = [int(d) for d in self.dilations]
            if len(self.dilations) != self.layers or min(self.dilations) < 1:
                raise ValueError(
                    f"BranchConfig.dilations must list {self.layers} positive integers (one per layer), got {self.dilations!r}"
                )
        if self.input_transform not in INPUT_TRANSFORMS:
            raise ValueError(f"BranchConfig.input_transform must be one of {INPUT_TRANSFORMS}, got {self.input_transform!r}")
        if not self.out_init_gain >= 0:
            raise ValueError(f"BranchConfig.out_init_gain must be >= 0, got {self.out_init_gain!r}")

    @property
    def network_radius(self) -> int:
        """Receptive radius of the conv stack: ``sum(dilation) * (conv_size // 2)``."""
        return sum(self.layer_dilations) * (self.conv_size // 2)

    @property
    def layer_dilations(self) -> list[int]:
        return list(self.dilations) if self.dilations is not None else [1] * self.layers


def _conv_stack(cfg: BranchConfig, out_channels: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    c_in = cfg.in_channels
    for layer, dil in enumerate(cfg.layer_dilations):
        last = layer == cfg.layers - 1
        c_out = out_channels if last else cfg.width
        conv = nn.Conv2d(c_in, c_out, cfg.conv_size, padding=dil * (cfg.conv_size // 2), dilation=dil)
        nn.init.kaiming_normal_(conv.weight, nonlinearity="relu" if not last else "linear")
        if last:
            with torch.no_grad():
                conv.weight.mul_(cfg.out_init_gain)
        nn.init.zeros_(conv.bias)
        mods.append(conv)
        if not last:
            mods.append(nn.ReLU(inplace=True))
        c_in = c_out
    return nn.Sequential(*mods)


def _check_branch_input(x: torch.Tensor, cfg: BranchConfig, who: str) -> None:
    if not isinstance(x, torch.Tensor) or x.dim() != 4:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"{who}: input must be a (B, {cfg.in_channels}, H, W) tensor, got {shape}")
    if x.shape[1] != cfg.in_channels:
        raise ValueError(f"{who}: input must have {cfg.in_channels} channels, got {x.shape[1]} ({tuple(x.shape)})")
