"""Multi-scale residual KPCN (after Chinese patent CN113947547A).

A KPCN whose branches (diffuse and specular for the split specs; same
architecture, separate weights) are deeper and built from multi-scale residual
blocks:

    conv 5×5 (in → width) + ReLU
    → ``blocks`` × multi-scale residual block (width → width)
    → ``tail_layers`` × conv 5×5 (ReLU between; the last gives k² kernel logits)
    → bounded softmax kernels applied to the noisy branch colour (as in KPCN)

The inside of the block is in a part of the patent we do not have; we use the
usual multi-scale residual block (MSRN, Li et al. 2018): two parallel paths,
3×3 and 5×5 convs (width → width each, ReLU), concatenated (2·width), a
second pair of 3×3 / 5×5 convs (2·width → 2·width each, ReLU), concatenated
(4·width), a 1×1 conv back to ``width``, and the block input added.

Receptive radius: the head conv 2, each block 4 (two 5×5 stages), each tail
conv 2; the kernel reaches ``kernel_size // 2``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..exposure import check_exposure_range
from ..inputs import get_input_spec
from ..ops.kernel_apply import KernelApply
from .base import DenoiserModel
from .layers import INPUT_TRANSFORMS, kernel_prior_bias, transform_input
from .registry import register_model, register_weights

__all__ = ["MSKPCNConfig", "MSResBlock", "MSKPCNBranch", "MSKPCN"]


@dataclass
class MSKPCNConfig:
    """Architecture of :class:`MSKPCN` (every branch shares it).

    Attributes:
        input_spec: the :mod:`kpcn.inputs` spec (``kpcn_split``, ``split_novar``, ``color_albedo_normal``).
        width: channels of the head, the blocks and the tail.
        blocks: multi-scale residual blocks (the patent: 8).
        tail_layers: 5×5 convs after the blocks, the last one giving the kernel logits (the patent: 8).
        kernel_size: odd size ``k`` of the predicted kernels.
        logit_scale: bound of the kernel logits, ``s * tanh(z / s)``.
        init_sigma: std (pixels) of the Gaussian the kernels start as.
        out_init_gain: scale of the last conv's initial weights.
        input_transform: ``log`` (signed log1p of the features), ``logvar`` or ``none``.
        exposure_range: None, or ``[lo, hi]``: the exposure keys of the training frames, as
            :class:`~kpcn.models.UNetConfig`'s (an inference setting).
    """

    input_spec: str = "kpcn_split"
    width: int = 64
    blocks: int = 8
    tail_layers: int = 8
    kernel_size: int = 21
    logit_scale: float = 16.0
    init_sigma: float = 1.5
    out_init_gain: float = 0.1
    input_transform: str = "log"
    exposure_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        spec = get_input_spec(self.input_spec)
        check_exposure_range(self.exposure_range, "MSKPCNConfig.exposure_range")
        for name in ("width", "tail_layers", "kernel_size"):
            v = getattr(self, name)
            if v < 1:
                raise ValueError(f"MSKPCNConfig.{name} must be >= 1, got {v}")
        if self.blocks < 0:
            raise ValueError(f"MSKPCNConfig.blocks must be >= 0, got {self.blocks}")
        if self.kernel_size % 2 == 0:
            raise ValueError(f"MSKPCNConfig.kernel_size must be odd, got {self.kernel_size}")
        if not self.logit_scale > 0 or not self.init_sigma > 0:
            raise ValueError("MSKPCNConfig.logit_scale and init_sigma must be positive")
        if self.input_transform not in INPUT_TRANSFORMS:
            raise ValueError(f"MSKPCNConfig.input_transform must be one of {INPUT_TRANSFORMS}, got {self.input_transform!r}")
        if self.input_transform == "logvar" and spec.name != "kpcn_split":
            raise ValueError("MSKPCNConfig.input_transform 'logvar' needs the kpcn_split input spec")

    @property
    def network_radius(self) -> int:
        return 2 + 4 * self.blocks + 2 * self.tail_layers


def _conv(c_in: int, c_out: int, size: int, gain: str = "relu") -> nn.Conv2d:
    conv = nn.Conv2d(c_in, c_out, size, padding=size // 2)
    nn.init.kaiming_normal_(conv.weight, nonlinearity=gain)
    nn.init.zeros_(conv.bias)
    return conv


class MSResBlock(nn.Module):
    """Multi-scale residual block ``(B, C, H, W) -> (B, C, H, W)`` (MSRN-style, see the module docstring)."""

    def __init__(self, width: int) -> None:
        super().__init__()
        c = width
        self.a3, self.a5 = _conv(c, c, 3), _conv(c, c, 5)
        self.b3, self.b5 = _conv(2 * c, 2 * c, 3), _conv(2 * c, 2 * c, 5)
        self.fuse = _conv(4 * c, c, 1, gain="linear")
        with torch.no_grad():  # start close to the identity, so a deep stack of blocks trains
            self.fuse.weight.mul_(0.1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = torch.relu(torch.cat([self.a3(x), self.a5(x)], dim=1))
        b = torch.relu(torch.cat([self.b3(a), self.b5(a)], dim=1))
        return x + self.fuse(b)


class MSKPCNBranch(nn.Module):
    """One branch: ``(B, C, H, W)`` features -> ``(B, 3, H, W)`` filtered colour (channels 0..2)."""

    def __init__(self, cfg: MSKPCNConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c_in, w, k = get_input_spec(cfg.input_spec).channels, cfg.width, cfg.kernel_size
        self.head = _conv(c_in, w, 5)
        self.blocks = nn.Sequential(*[MSResBlock(w) for _ in range(cfg.blocks)])
        tail: list[nn.Module] = []
        for i in range(cfg.tail_layers):
            last = i == cfg.tail_layers - 1
            tail.append(_conv(w, k * k if last else w, 5, gain="linear" if last else "relu"))
            if not last:
                tail.append(nn.ReLU(inplace=True))
        self.tail = nn.Sequential(*tail)
        with torch.no_grad():
            self.tail[-1].weight.mul_(cfg.out_init_gain)
            self.tail[-1].bias.copy_(kernel_prior_bias(k, cfg.init_sigma, cfg.logit_scale))
        self.apply_kernels = KernelApply(k, MSKPCN.kernel_padding)

    def kernels(self, x: torch.Tensor) -> torch.Tensor:
        """Softmax-normalised per-pixel kernels ``(B, k*k, H, W)`` (contiguous)."""
        h = torch.relu(self.head(transform_input(x, self.cfg.input_transform)))
        z = self.tail(self.blocks(h))
        s = self.cfg.logit_scale
        return torch.softmax(torch.tanh(z / s) * s, dim=1).contiguous()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.apply_kernels(x[:, :3].contiguous(), self.kernels(x))


class MSKPCN(DenoiserModel):
    """Multi-scale residual KPCN, one branch per branch of the input spec (see the module docstring)."""

    zero_preserving = True  # kernels only average the branch colour (replicate padding)
    convex_kernels = True  # one softmax kernel a pixel, applied to the noisy branch colour
    kernel_padding = "replicate"

    def __init__(self, config: MSKPCNConfig) -> None:
        super().__init__(config)
        for b in self.branches:
            self.add_module(b, MSKPCNBranch(config))

    @property
    def receptive_radius(self) -> int:
        return max(self.config.network_radius, self.config.kernel_size // 2)


@register_model("mskpcn", config=MSKPCNConfig)
def mskpcn(config: MSKPCNConfig) -> MSKPCN:
    """Multi-scale residual KPCN (CN113947547A); fields of :class:`MSKPCNConfig`."""
    return MSKPCN(config)


register_weights("mskpcn", "small", "mskpcn_small.safetensors", default=True,
                 description="multi-scale residual KPCN 16 wide, 3 blocks, 11x11 kernels (configs/small_mskpcn.yaml), "
                             "trained on a GPU on 72 procedural 256x256 scenes + their converged references")
