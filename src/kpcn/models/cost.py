"""Multiply-adds per pixel of a model: what its speed on a CPU follows.

Counted by running the model once on a random input of its input spec with
forward hooks on every ``nn.Conv2d`` (``output pixels × C_in / groups × kh ×
kw`` per output channel, the usual count; "same" padding counted as full
windows) and every :class:`~kpcn.ops.KernelApply` (``k² × C`` per pixel).
Element-wise work (activations, pooling, softmax) is left out, as in the usual
count. A whole-frame summary is counted on the same frame, divided by its
pixels like everything else.
"""
from __future__ import annotations

import torch
from torch import nn

from ..ops.kernel_apply import KernelApply

__all__ = ["macs_per_pixel"]


def macs_per_pixel(model: nn.Module, height: int = 64, width: int = 64) -> float:
    """Multiply-adds per output pixel of ``model`` on a ``height × width`` frame (every branch run)."""
    spec = model.input_spec
    g = torch.Generator().manual_seed(0)
    inputs = {b: torch.rand(1, spec.channels, height, width, generator=g) for b in spec.branches}
    inputs["albedo"] = torch.rand(1, 3, height, width, generator=g)
    if getattr(model, "reads_normal", False):  # a guide beside the features (its element-wise use is not counted)
        inputs["normal"] = torch.rand(1, 3, height, width, generator=g) * 2 - 1
    total = [0]

    def conv_hook(mod: nn.Conv2d, args, out):
        if hasattr(mod, "macs"):  # a conv that counts its own work (e.g. one that runs partly at low resolution)
            total[0] += mod.macs(*args, out)
            return
        kh, kw = mod.kernel_size
        total[0] += out.numel() // out.shape[0] * (mod.in_channels // mod.groups) * kh * kw

    def kernel_hook(mod: KernelApply, args, out):
        total[0] += out.numel() // out.shape[0] * mod.kernel_size**2

    handles = []
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            handles.append(m.register_forward_hook(conv_hook))
        elif isinstance(m, KernelApply):
            handles.append(m.register_forward_hook(kernel_hook))
    try:
        with torch.no_grad():
            model(inputs)
    finally:
        for h in handles:
            h.remove()
    return total[0] / (height * width)
