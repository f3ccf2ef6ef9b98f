"""KPCN and DPCN denoisers (Bako et al. 2017), DESIGN.md sections 2.2 and 2.3.

Each model has two branches with the same architecture and separate weights:

* the **diffuse** branch works on ``diffuse / (albedo + EPS)`` (irradiance-like),
* the **specular** branch works on ``log1p(specular)``.

A branch is ``layers`` convolutions (``conv_size x conv_size``, ``width``
channels, zero "same" padding, ReLU between, none after the last) on the
``(B, 27, H, W)`` branch features, whose channels 0..2 are the noisy branch colour.

* KPCN branch: the last conv predicts ``k*k`` logits per pixel, bounded to
  ``logit_scale * tanh(z / logit_scale)`` (a softmax of logits around 1e4 is
  one-hot with a zero gradient, so training would stall), normalised by a
  softmax over the tap dimension and applied to the noisy branch colour with
  :func:`kpcn.ops.kernel_apply` (``padding_mode`` "replicate" by default, so a
  kernel at the frame border only mixes real pixel values and a constant image
  stays constant everywhere). Because the weights are a softmax and the
  padding replicates, each output pixel lies in the per-channel range (convex
  hull) of its ``k x k`` neighbourhood in the noisy colour. With ``demodulate``
  (colour + albedo + normal specs) a learnt per-pixel weight blends in the same
  kernel applied to the albedo-demodulated colour (no longer convex; still linear).
* DPCN branch: the last conv predicts 3 channels ``r``, a correction of the
  noisy branch colour ``c`` in log space: ``expm1(max(log1p(c) + r, 0))``
  (``c`` clamped at 0). In linear space the same net had to output residuals
  from 0.01 to 100 depending on scene brightness and did not learn at all in
  500 steps (validation error = the input's); in log space the correction is
  relative, like the kernels of KPCN.

Initialisation (so that a fresh model is sane):

* hidden convs: Kaiming-normal for ReLU, zero bias (keeps activations at the
  scale of the input over 9 layers);
* last conv: Kaiming-normal scaled by ``out_init_gain`` (0.1);
* KPCN last-conv bias: a Gaussian log-prior ``-d^2 / (2 init_sigma^2)`` over the
  tap offset ``d`` (clipped to ``-logit_scale / 2`` so no tap starts in the flat
  part of the tanh), i.e. a fresh KPCN is close to a Gaussian blur of std
  ``init_sigma`` pixels (``init_sigma=None``: zero bias, a near-uniform box);
* a fresh DPCN is close to the identity (small residual).

Reconstruction (:func:`reconstruct`)::

    color = (albedo + EPS) * max(diffuse, 0) + expm1(clamp(specular, 0, SPECULAR_LOG_MAX))

with NaN/Inf in the result mapped to 0 / the largest finite value, so the
colour is always finite and non-negative. The ``diffuse`` and ``specular``
outputs of :class:`Denoiser` are returned unclamped (so per-branch losses keep
their gradient); for KPCN with non-negative inputs they are non-negative anyway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from ..constants import EPS
from ..inputs import SPECULAR_LOG_MAX, get_input_spec, split_reconstruct
from ..ops.kernel_apply import PADDING_MODES, KernelApply
from .base import DenoiserModel
from .layers import INPUT_TRANSFORMS, albedo_ratio, kernel_prior_bias, transform_input
from .registry import register_model, register_weights

__all__ = [
    "EPS",
    "SPECULAR_LOG_MAX",
    "BranchConfig",
    "KPCNBranch",
    "DPCNBranch",
    "Denoiser",
    "reconstruct",
    "kpcn",
    "dpcn",
]


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

    def __post_init__(self) -> None:
        spec = get_input_spec(self.input_spec)
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


#: the precision gate: ``sigmoid(GATE_SCALE * (a + c * p))``, (a, c) starting at (GATE_INIT, 0)
GATE_SCALE = 10.0
GATE_INIT = 0.6
#: initial bias of the demodulation weight's logit (``demodulate``): ``beta = sigmoid(-4) = 0.018``
DEMOD_INIT = -4.0


def _check_branch_input(x: torch.Tensor, cfg: BranchConfig, who: str) -> None:
    if not isinstance(x, torch.Tensor) or x.dim() != 4:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"{who}: input must be a (B, {cfg.in_channels}, H, W) tensor, got {shape}")
    if x.shape[1] != cfg.in_channels:
        raise ValueError(f"{who}: input must have {cfg.in_channels} channels, got {x.shape[1]} ({tuple(x.shape)})")


class KPCNBranch(nn.Module):
    """Kernel-predicting branch.

    Shape:
        - input: ``(B, in_channels, H, W)``; channels 0..2 are the noisy branch colour
        - output: ``(B, 3, H, W)`` filtered branch colour
    """

    def __init__(self, config: BranchConfig) -> None:
        super().__init__()
        self.config = config
        k = config.kernel_size
        self.net = _conv_stack(config, k * k + int(config.demodulate))
        self.apply_kernels = KernelApply(k, config.padding_mode)  # no parameters: the state dict is unchanged
        with torch.no_grad():
            if config.init_sigma is not None:
                self.net[-1].bias[: k * k].copy_(self._prior_bias(config))
            if config.demodulate:
                self.net[-1].bias[k * k :] = DEMOD_INIT
        # (a, c) of the precision gate sigmoid(GATE_SCALE * (a + c * p)); the scale lets Adam move them at the
        # network's learning rate by whole units over a run
        self.gate = nn.Parameter(torch.tensor([GATE_INIT, 0.0])) if config.precision_gate else None

    @staticmethod
    def _prior_bias(cfg: BranchConfig) -> torch.Tensor:
        return kernel_prior_bias(cfg.kernel_size, cfg.init_sigma, cfg.logit_scale)

    @property
    def receptive_radius(self) -> int:
        """Pixels of input on each side that an output pixel depends on.

        The weights at a pixel see ``layers * (conv_size // 2)`` pixels, the
        kernel gathers the noisy colour ``kernel_size // 2`` pixels away, and the
        colour is the raw input, so the radius is the larger of the two.
        """
        return max(self.config.network_radius, self.config.kernel_size // 2)

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """Bounded kernel logits ``(B, k*k, H, W)`` (contiguous NCHW); with ``demodulate`` one more channel, the
        demodulation weight's logit."""
        z = self.net(transform_input(x, self.config.input_transform)).contiguous()
        s = self.config.logit_scale
        if s is None:
            return z
        return torch.tanh(z / s) * s

    def kernels(self, x: torch.Tensor) -> torch.Tensor:
        """Per-pixel kernels ``(B, k*k, H, W)`` for the colour, taps in ``F.unfold`` order: a softmax (blended with
        the identity by the precision gate), times the demodulation factor with ``demodulate``."""
        _check_branch_input(x, self.config, type(self).__name__)
        z = self.logits(x)
        kk = self.config.kernel_size**2
        k = torch.softmax(z[:, :kk], dim=1)
        if self.gate is not None:
            g = self.precision_gate(x)
            centre = torch.zeros_like(k[:1, :, :1, :1])
            centre[:, kk // 2] = 1.0
            k = g * k + (1.0 - g) * centre
        if self.config.demodulate:
            beta = torch.sigmoid(z[:, kk:])
            k = k * (1.0 - beta + beta * albedo_ratio(x[:, 3:6], self.config.kernel_size))
        return k

    def precision_gate(self, x: torch.Tensor) -> torch.Tensor:
        """The gate ``(B, 1, H, W)`` in (0, 1) from the precision channel (the last) of ``x``; 1: the kernels as predicted."""
        p = x[:, -1:]
        return torch.sigmoid(GATE_SCALE * (self.gate[0] + self.gate[1] * p))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weights = self.kernels(x)
        return self.apply_kernels(x[:, :3], weights)


class DPCNBranch(nn.Module):
    """Direct-prediction branch: ``expm1(max(log1p(colour) + conv_stack(x), 0))``.

    Shape:
        - input: ``(B, in_channels, H, W)``; channels 0..2 are the noisy branch colour
        - output: ``(B, 3, H, W)``
    """

    def __init__(self, config: BranchConfig) -> None:
        super().__init__()
        self.config = config
        self.net = _conv_stack(config, 3)

    @property
    def receptive_radius(self) -> int:
        """``layers * (conv_size // 2)``."""
        return self.config.network_radius

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _check_branch_input(x, self.config, type(self).__name__)
        base = torch.log1p(x[:, :3].clamp_min(0.0))
        y = base + self.net(transform_input(x, self.config.input_transform))
        return torch.expm1(y.clamp(0.0, SPECULAR_LOG_MAX))


_BRANCHES = {"kpcn": KPCNBranch, "dpcn": DPCNBranch}


def reconstruct(diffuse: torch.Tensor, specular: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """Final radiance from the split branch outputs (DESIGN.md 2.2), always finite and >= 0.

    ``color = (albedo + EPS) * max(diffuse, 0) + expm1(clamp(specular, 0, SPECULAR_LOG_MAX))``;
    NaN becomes 0 and +Inf the largest finite value of the dtype (:func:`kpcn.inputs.split_reconstruct`).

    Shapes: all ``(B, 3, H, W)``.
    """
    return split_reconstruct({"diffuse": diffuse, "specular": specular}, {"albedo": albedo})


class Denoiser(DenoiserModel):
    """Branch-per-component KPCN/DPCN denoiser: one conv stack per branch of the input spec.

    Args:
        kind: ``"kpcn"`` or ``"dpcn"``.
        config: :class:`BranchConfig` shared by every branch.

    With the split specs the branches are ``diffuse`` and ``specular``
    (separate weights; train them on their own by calling them directly on
    their ``(B, C, H, W)`` features); with ``color_albedo_normal`` a single
    ``color`` branch. ``forward(inputs)`` takes the dict the spec builds (a
    branch that is absent or ``None`` is zero and not run) and returns
    ``{branch: (B, 3, H, W) filtered branch colour (unclamped), "color": final radiance}``.
    """

    def __init__(self, kind: str, config: BranchConfig | None = None) -> None:
        if kind not in _BRANCHES:
            raise ValueError(f"Denoiser: kind must be one of {sorted(_BRANCHES)}, got {kind!r}")
        for option, what in (("precision_gate", "blends"), ("demodulate", "weights")):  # options of kernels
            if kind != "kpcn" and config is not None and getattr(config, option):
                raise ValueError(f"Denoiser: {option} {what} kernels; {kind} predicts none")
        super().__init__(config if config is not None else BranchConfig())
        self.kind = self.name = kind
        self.zero_preserving = kind == "kpcn"  # a convex combination of zeros is zero
        # softmax weights over the k x k neighbourhood (demodulated ones are not convex in the colour)
        self.convex_kernels = kind == "kpcn" and not self.config.demodulate
        self.kernel_padding = self.config.padding_mode if kind == "kpcn" else None
        cls = _BRANCHES[kind]
        for b in self.branches:
            self.add_module(b, cls(self.config))

    @property
    def receptive_radius(self) -> int:
        """Pixels a tile needs on each side so its interior equals full-frame inference (features excluded)."""
        return getattr(self, self.branches[0]).receptive_radius



def _build(kind: str, config: BranchConfig) -> Denoiser:
    return Denoiser(kind, config)


@register_model("kpcn", config=BranchConfig)
def kpcn(config: BranchConfig) -> Denoiser:
    """Kernel-predicting denoiser (Bako et al. 2017); fields of :class:`BranchConfig`."""
    return _build("kpcn", config)


@register_model("dpcn", config=BranchConfig)
def dpcn(config: BranchConfig) -> Denoiser:
    """Direct-prediction denoiser; fields of :class:`BranchConfig`.

    ``kernel_size``, ``logit_scale``, ``padding_mode`` and ``init_sigma`` are accepted and unused.
    """
    return _build("dpcn", config)


register_weights("kpcn", "small", "kpcn_small.safetensors", default=True,
                 description="KPCN 5x32, 5x5 convs, 11x11 kernels (configs/small.yaml), 44 procedural scenes")
register_weights("kpcn", "can_small", "kpcn_can_small.safetensors",
                 description="KPCN 5x32 on colour + albedo + normal only (configs/small_can.yaml, 30 procedural scenes), "
                             "fine-tuned on 32 Blender Cycles scenes (configs/small_can_cycles.yaml, _b, _c), then with "
                             "the frame's estimated noise precision as an input (configs/small_can_noise.yaml, _b), then "
                             "with kernels partly applied to the albedo-demodulated colour (configs/small_can_demod.yaml, _b, _c, _d); "
                             "reads OIDN's albedo (Cycles' Denoising Albedo) where a file has it")
register_weights("kpcn", "novar_small", "kpcn_novar_small.safetensors",
                 description="KPCN 5x32 on the diffuse/specular split without variances (configs/small_novar.yaml, "
                             "30 procedural scenes), fine-tuned on 32 Blender Cycles scenes "
                             "(configs/small_novar_cycles.yaml, _b, _c, _d)")
register_weights("dpcn", "small", "dpcn_small.safetensors",
                 description="DPCN 5x32, 5x5 convs (configs/small_dpcn.yaml), 44 procedural scenes")
