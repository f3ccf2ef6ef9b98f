"""A kernel-predicting U-Net with a global summary (after Salehi et al. 2022).

Each branch of the input spec (diffuse and specular for the split specs, one
``color`` branch for ``color_albedo_normal``) has its own U-Net:

* encoder: ``len(widths)`` levels of ``convs_per_level`` 3×3 convs + ReLU, a
  2×2 average pool between levels (so most of the work happens at 1/2 … 1/2^n
  resolution: fewer multiply-adds per pixel than a full-resolution stack);
* **global summary** (``summary_channels > 0``): the per-channel mean and
  standard deviation of the bottleneck over the whole frame, a 1×1 conv to
  ``summary_channels``, broadcast back and concatenated to the bottleneck. It
  gives every pixel the frame's statistics whatever its receptive field. When a
  frame is denoised in tiles, :meth:`UNetKPCN.frame_context` computes it once
  over the whole frame and every tile uses that value, so tiled equals untiled;
* decoder: nearest-neighbour 2× upsampling, concatenation with the encoder
  features of the same level, ``convs_per_level`` 3×3 convs + ReLU;
* head: a 1×1 conv to ``kernel_size²`` bounded logits (``s·tanh(z/s)``), a
  softmax, and the per-pixel kernel applied to the noisy branch colour with
  replicate padding — the output is a convex combination of input pixels, so a
  zero branch stays zero and a constant image stays constant.

The input is padded (replicate) at the bottom/right to a multiple of
``alignment = 2**(len(widths) - 1)`` and the output cropped back.

Receptive radius (full-resolution pixels): a 3×3 conv at level ``l`` adds
``2**l``; an average pool adds nothing beyond the pooled block; a nearest
upsample into level ``l`` adds ``2**l``; the kernel reaches ``kernel_size // 2``.
Multi-scale kernels (Vogels et al. 2018) are not in this first version.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from ..inputs import get_input_spec
from ..ops.kernel_apply import KernelApply
from .base import DenoiserModel, check_inputs
from .kpcn import INPUT_TRANSFORMS, kernel_prior_bias, transform_input
from .registry import register_model

__all__ = ["UNetConfig", "UNetBranch", "UNetKPCN"]


@dataclass
class UNetConfig:
    """Architecture of :class:`UNetKPCN` (every branch shares it).

    Attributes:
        input_spec: the :mod:`kpcn.inputs` spec (``kpcn_split``, ``split_novar``, ``color_albedo_normal``).
        widths: channels of each level, finest first; ``len(widths) - 1`` poolings.
        convs_per_level: 3×3 convs per level in the encoder and in the decoder.
        kernel_size: odd size ``k`` of the predicted full-resolution kernels.
        summary_channels: width of the global summary (0: no summary, a purely local model).
        logit_scale: bound of the kernel logits, ``s * tanh(z / s)``.
        init_sigma: std (pixels) of the Gaussian the kernels start as.
        out_init_gain: scale of the head's initial weights.
        input_transform: ``log`` (signed log1p of the features), ``logvar`` or ``none``.
    """

    input_spec: str = "kpcn_split"
    widths: list[int] = field(default_factory=lambda: [16, 24, 32, 48])
    convs_per_level: int = 2
    kernel_size: int = 5
    summary_channels: int = 8
    logit_scale: float = 16.0
    init_sigma: float = 1.0
    out_init_gain: float = 0.1
    input_transform: str = "log"

    def __post_init__(self) -> None:
        spec = get_input_spec(self.input_spec)
        if not self.widths or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in self.widths):
            raise ValueError(f"UNetConfig.widths must be a non-empty list of positive integers, got {self.widths!r}")
        if self.convs_per_level < 1:
            raise ValueError(f"UNetConfig.convs_per_level must be >= 1, got {self.convs_per_level}")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ValueError(f"UNetConfig.kernel_size must be a positive odd integer, got {self.kernel_size}")
        if self.summary_channels < 0:
            raise ValueError(f"UNetConfig.summary_channels must be >= 0, got {self.summary_channels}")
        if not self.logit_scale > 0 or not self.init_sigma > 0:
            raise ValueError("UNetConfig.logit_scale and init_sigma must be positive")
        if self.input_transform not in INPUT_TRANSFORMS:
            raise ValueError(f"UNetConfig.input_transform must be one of {INPUT_TRANSFORMS}, got {self.input_transform!r}")
        if self.input_transform == "logvar" and spec.name != "kpcn_split":
            raise ValueError("UNetConfig.input_transform 'logvar' needs the kpcn_split input spec")

    @property
    def alignment(self) -> int:
        return 2 ** (len(self.widths) - 1)

    @property
    def network_radius(self) -> int:
        c = self.convs_per_level
        scales = [2**level for level in range(len(self.widths))]
        encoder = c * sum(scales)
        decoder = sum(s * (1 + c) for s in scales[:-1])
        return encoder + decoder


def _convs(c_in: int, c_out: int, n: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    for i in range(n):
        conv = nn.Conv2d(c_in if i == 0 else c_out, c_out, 3, padding=1)
        nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")
        nn.init.zeros_(conv.bias)
        mods += [conv, nn.ReLU(inplace=True)]
    return nn.Sequential(*mods)


class UNetBranch(nn.Module):
    """One branch: ``(B, C, H, W)`` features -> ``(B, 3, H, W)`` filtered colour (channels 0..2)."""

    def __init__(self, cfg: UNetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c_in = get_input_spec(cfg.input_spec).channels
        w = list(cfg.widths)
        self.enc = nn.ModuleList()
        for level, width in enumerate(w):
            self.enc.append(_convs(c_in if level == 0 else w[level - 1], width, cfg.convs_per_level))
        s = cfg.summary_channels
        self.summary = nn.Conv2d(2 * w[-1], s, 1) if s else None
        self.dec = nn.ModuleList()
        below = w[-1] + s
        for level in range(len(w) - 2, -1, -1):
            self.dec.append(_convs(below + w[level], w[level], cfg.convs_per_level))
            below = w[level]
        k = cfg.kernel_size
        self.head = nn.Conv2d(w[0], k * k, 1)
        self.apply_kernels = KernelApply(k, "replicate")
        nn.init.kaiming_normal_(self.head.weight, nonlinearity="linear")
        with torch.no_grad():
            self.head.weight.mul_(cfg.out_init_gain)
            self.head.bias.copy_(kernel_prior_bias(k, cfg.init_sigma, cfg.logit_scale))

    def _pad(self, x: torch.Tensor) -> torch.Tensor:
        a = self.cfg.alignment
        ph, pw = (-x.shape[-2]) % a, (-x.shape[-1]) % a
        return F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Encoder features of every level, finest first (input padded to the alignment)."""
        h = self._pad(transform_input(x, self.cfg.input_transform))
        feats = []
        for level, block in enumerate(self.enc):
            if level:
                h = F.avg_pool2d(h, 2)
            h = block(h)
            feats.append(h)
        return feats

    def summarize(self, bottleneck: torch.Tensor) -> torch.Tensor | None:
        """The global summary ``(B, summary_channels, 1, 1)`` of a bottleneck (None without one)."""
        if self.summary is None:
            return None
        mean = bottleneck.mean(dim=(2, 3), keepdim=True)
        std = torch.sqrt(bottleneck.var(dim=(2, 3), keepdim=True, unbiased=False) + 1e-8)
        return self.summary(torch.cat([mean, std], dim=1))

    def forward(self, x: torch.Tensor, summary: torch.Tensor | None = None) -> torch.Tensor:
        return self.apply_kernels(x[:, :3].contiguous(), self.kernels(x, summary))

    def kernels(self, x: torch.Tensor, summary: torch.Tensor | None = None) -> torch.Tensor:
        """Softmax-normalised per-pixel kernels ``(B, k*k, H, W)`` (contiguous)."""
        h_in, w_in = x.shape[-2:]
        feats = self.encode(x)
        h = feats[-1]
        if self.summary is not None:
            if summary is None:
                summary = self.summarize(h)
            h = torch.cat([h, summary.expand(-1, -1, h.shape[-2], h.shape[-1])], dim=1)
        for block, skip in zip(self.dec, reversed(feats[:-1])):
            h = block(torch.cat([F.interpolate(h, scale_factor=2, mode="nearest"), skip], dim=1))
        s = self.cfg.logit_scale
        logits = torch.tanh(self.head(h)[..., :h_in, :w_in] / s) * s
        return torch.softmax(logits, dim=1).contiguous()


class UNetKPCN(DenoiserModel):
    """Kernel-predicting U-Net, one per branch of the input spec (see the module docstring)."""

    zero_preserving = True

    def __init__(self, config: UNetConfig) -> None:
        super().__init__(config)
        self.uses_frame_context = config.summary_channels > 0
        for b in self.branches:
            self.add_module(b, UNetBranch(config))

    @property
    def receptive_radius(self) -> int:
        return max(self.config.network_radius, self.config.kernel_size // 2)

    @property
    def alignment(self) -> int:
        return self.config.alignment

    def frame_context(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor] | None:
        """Each present branch's global summary over the whole frame ``{branch: (B, S, 1, 1)}``."""
        if not self.uses_frame_context:
            return None
        check_inputs(self, inputs)
        out = {}
        for b in self.branches:
            if inputs.get(b) is not None:
                net = getattr(self, b)
                out[b] = net.summarize(net.encode(inputs[b])[-1])
        return out

    def run_branch(self, name: str, x: torch.Tensor, context=None) -> torch.Tensor:
        """One branch, with its whole-frame summary from ``context`` when given (else its own)."""
        return getattr(self, name)(x, (context or {}).get(name))

    def branch_kernels(self, name: str, x: torch.Tensor, context=None) -> torch.Tensor:
        return getattr(self, name).kernels(x, (context or {}).get(name))


@register_model("unet_kpcn", config=UNetConfig)
def unet_kpcn(config: UNetConfig) -> UNetKPCN:
    """Kernel-predicting U-Net with a global summary; fields of :class:`UNetConfig`."""
    return UNetKPCN(config)
