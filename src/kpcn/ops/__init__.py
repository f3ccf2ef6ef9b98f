"""Low-level operators."""

from .kernel_apply import PADDING_MODES, KernelApply, kernel_apply, kernel_apply_unfold
from .regression import box_mean, residual_regression, residual_regression_rows

__all__ = ["kernel_apply", "kernel_apply_unfold", "KernelApply", "PADDING_MODES", "box_mean", "residual_regression",
           "residual_regression_rows"]
