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

import torch
from torch import nn

from ..constants import EPS
from ..inputs import SPECULAR_LOG_MAX, radiance_of, split_reconstruct
from ..ops.kernel_apply import KernelApply
from .base import DETAIL_STAGE, DenoiserModel
from .branch import BranchConfig, _check_branch_input, _conv_stack
from .layers import albedo_ratio, kernel_prior_bias, transform_input
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


#: the precision gate: ``sigmoid(GATE_SCALE * (a + c * p))``, (a, c) starting at (GATE_INIT, 0)
GATE_SCALE = 10.0
GATE_INIT = 0.6
#: initial bias of the demodulation weight's logit (``demodulate``): ``beta = sigmoid(-4) = 0.018``
DEMOD_INIT = -4.0


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
        return radiance_of(y)


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
for _base, _gain, _files in (
        ("can_small", "+0.1-0.23 dB and +0.003-0.005 SSIM", "colour, albedo and normal only"),
        ("novar_small", "+0.2-0.3 dB and +0.005 SSIM at 16-64 spp", "the split but no variances")):
    register_weights("kpcn", f"{_base}_r", f"kpcn_{_base}.safetensors", config=dict(DETAIL_STAGE),
                     description=f"kpcn:{_base}'s weights with the default U-Net's detail stage after the network "
                                 f"(kpcn.inference.detail, its settings): on the 18 validation scenes {_gain} over "
                                 f"{_base}, every figure better at 2-256 spp; denoise(path)'s model for files with "
                                 f"{_files}")
register_weights("dpcn", "small", "dpcn_small.safetensors",
                 description="DPCN 5x32, 5x5 convs (configs/small_dpcn.yaml), 44 procedural scenes")
