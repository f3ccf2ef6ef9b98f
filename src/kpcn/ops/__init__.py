"""Low-level operators."""

from .kernel_apply import PADDING_MODES, KernelApply, kernel_apply, kernel_apply_unfold

__all__ = ["kernel_apply", "kernel_apply_unfold", "KernelApply", "PADDING_MODES"]
