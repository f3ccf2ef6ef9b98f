"""Per-pixel kernel application (the "kernel-apply" step of KPCN).

Every output pixel is a weighted sum of the ``k x k`` neighbourhood of the same
pixel in the input image, with its own weights::

    out[b, c, y, x] = sum_{i, j} w[b, i*k + j, y, x] * pad(image)[b, c, y + i - r, x + j - r]

with ``r = k // 2``. Taps are ordered row-major over the window, exactly like the
channel ordering of :func:`torch.nn.functional.unfold`, so
:func:`kernel_apply` equals :func:`kernel_apply_unfold`.

Two implementations are provided:

* :func:`kernel_apply` -- a custom :class:`torch.autograd.Function` whose forward
  loops over the ``k*k`` shifts and accumulates ``w_t * shift_t(image)`` into one
  accumulator with ``addcmul_``; its backward is a hand-written shift loop too.
  Extra memory is O(B*C*H*W) whatever ``k`` is.
* :func:`kernel_apply_unfold` -- the plain reference built on ``F.unfold``. It
  materialises a ``(B, C*k*k, H*W)`` tensor (about 5.5 GB for a 1024x1024 RGB
  image with k = 21) and is only meant for tests and benchmarks.

Padding: ``"zeros"`` (default; pixels outside the image contribute 0, so near
the border the weights of the real pixels sum to less than one and the output
is darkened unless the weights avoid the outside taps) or ``"replicate"``
(outside pixels repeat the nearest border pixel, so a convex combination stays
inside the range of real pixel values and a constant image stays constant).
The weights are used as given: callers normalise them (KPCN uses a softmax over
the tap dimension).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["kernel_apply", "kernel_apply_padded", "kernel_apply_unfold", "KernelApply", "PADDING_MODES"]

PADDING_MODES = ("zeros", "replicate")


def _check_inputs(image: torch.Tensor, weights: torch.Tensor, kernel_size: int, padding_mode: str) -> None:
    if not isinstance(image, torch.Tensor) or not isinstance(weights, torch.Tensor):
        raise ValueError(
            f"kernel_apply: image and weights must be tensors, got {type(image).__name__} "
            f"and {type(weights).__name__}"
        )
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, int):
        raise ValueError(f"kernel_apply: kernel_size must be an int, got {kernel_size!r}")
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_apply: kernel_size must be a positive odd integer, got {kernel_size}")
    if image.dim() != 4:
        raise ValueError(f"kernel_apply: image must have shape (B, C, H, W), got {tuple(image.shape)}")
    if weights.dim() != 4:
        raise ValueError(
            f"kernel_apply: weights must have shape (B, k*k, H, W), got {tuple(weights.shape)}"
        )
    taps = kernel_size * kernel_size
    if weights.shape[1] != taps:
        raise ValueError(
            f"kernel_apply: weights must have k*k = {taps} channels for kernel_size {kernel_size}, "
            f"got {weights.shape[1]} (weights shape {tuple(weights.shape)})"
        )
    b, _, h, w = image.shape
    if (weights.shape[0], weights.shape[2], weights.shape[3]) != (b, h, w):
        raise ValueError(
            "kernel_apply: image and weights must agree in batch size and spatial size: "
            f"image {tuple(image.shape)} (B, C, H, W) vs weights {tuple(weights.shape)} (B, k*k, H, W)"
        )
    if image.dtype != weights.dtype:
        raise ValueError(f"kernel_apply: image dtype {image.dtype} differs from weights dtype {weights.dtype}")
    if not image.is_floating_point():
        raise ValueError(f"kernel_apply: image must be a floating-point tensor, got {image.dtype}")
    if image.device != weights.device:
        raise ValueError(f"kernel_apply: image on {image.device} but weights on {weights.device}")
    if padding_mode not in PADDING_MODES:
        raise ValueError(f"kernel_apply: padding_mode must be one of {PADDING_MODES}, got {padding_mode!r}")


class _ShiftLoopKernelApply(torch.autograd.Function):
    """Kernel application on an already padded image ("valid" mode).

    forward(padded (B, C, H+2r, W+2r), weights (B, k*k, H, W), k) -> (B, C, H, W)

    Gradients are returned for the padded image; the padding itself (zeros or
    replicate) is done outside with ``F.pad`` whose autograd folds the border
    gradient back.
    """

    @staticmethod
    def forward(ctx, padded: torch.Tensor, weights: torch.Tensor, kernel_size: int) -> torch.Tensor:
        padded = padded.contiguous()
        weights = weights.contiguous()
        k = kernel_size
        b, c, hp, wp = padded.shape
        h, w = hp - (k - 1), wp - (k - 1)
        out = padded.new_zeros((b, c, h, w))
        for i in range(k):
            for j in range(k):
                t = i * k + j
                # (B, 1, H, W) * (B, C, H, W) broadcast into the accumulator; views only.
                out.addcmul_(weights[:, t : t + 1], padded[:, :, i : i + h, j : j + w])
        ctx.save_for_backward(padded, weights)
        ctx.kernel_size = k
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        padded, weights = ctx.saved_tensors
        k = ctx.kernel_size
        grad_out = grad_out.contiguous()
        b, c, h, w = grad_out.shape
        need_image, need_weights = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_padded = torch.zeros_like(padded) if need_image else None
        grad_weights = torch.empty_like(weights) if need_weights else None
        for i in range(k):
            for j in range(k):
                t = i * k + j
                if need_image:
                    # d out / d padded[.., y+i, x+j] = w_t[y, x]
                    grad_padded[:, :, i : i + h, j : j + w].addcmul_(weights[:, t : t + 1], grad_out)
                if need_weights:
                    # grad_w[:, t] = sum_c grad_out * shift_t(image), written in place (no temporaries)
                    shifted = padded[:, :, i : i + h, j : j + w]
                    g = grad_weights[:, t]
                    torch.mul(grad_out[:, 0], shifted[:, 0], out=g)
                    for ch in range(1, c):
                        g.addcmul_(grad_out[:, ch], shifted[:, ch])
        return grad_padded, grad_weights, None


def _pad(image: torch.Tensor, r: int, padding_mode: str) -> torch.Tensor:
    if r == 0:
        return image
    if padding_mode == "zeros":
        return F.pad(image, (r, r, r, r), mode="constant", value=0.0)
    # "replicate": F.pad's replicate mode needs the pad to fit; it handles r >= H too.
    return F.pad(image, (r, r, r, r), mode="replicate")


def kernel_apply(
    image: torch.Tensor, weights: torch.Tensor, kernel_size: int, padding_mode: str = "zeros"
) -> torch.Tensor:
    """Apply a different ``k x k`` kernel at every pixel (shift-loop implementation).

    Args:
        image: ``(B, C, H, W)`` floating-point tensor (any memory format).
        weights: ``(B, k*k, H, W)`` per-pixel kernels, tap ``t = i*k + j`` weighting
            the pixel at offset ``(i - r, j - r)``, ``r = k // 2`` (``F.unfold`` order).
            Not normalised here; pass softmax-normalised weights for a convex combination.
        kernel_size: odd ``k >= 1``.
        padding_mode: ``"zeros"`` (default) or ``"replicate"``; see the module docstring.

    Returns:
        ``(B, C, H, W)`` tensor, same dtype as the inputs, contiguous (NCHW).

    Raises:
        ValueError: on wrong ranks, a weights channel count other than ``k*k``,
            mismatched batch/spatial sizes, even or non-positive ``k``, mixed dtypes/devices.

    Memory: O(B*C*H*W) extra for forward and backward, independent of ``k``
    (besides the ``(B, k*k, H, W)`` weights gradient that autograd needs anyway).
    """
    _check_inputs(image, weights, kernel_size, padding_mode)
    padded = _pad(image, kernel_size // 2, padding_mode)
    return _ShiftLoopKernelApply.apply(padded, weights, kernel_size)


def kernel_apply_padded(padded: torch.Tensor, weights: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """:func:`kernel_apply` on an image the caller has already padded by ``r = k // 2`` on every side.

    ``padded`` ``(B, C, H + 2r, W + 2r)``, ``weights`` ``(B, k*k, H, W)`` -> ``(B, C, H, W)``. For a
    caller that pads with real neighbours (a band of rows of a larger image) rather than a border rule.
    """
    r = kernel_size // 2
    if padded.dim() != 4 or weights.dim() != 4 or padded.shape[-2] != weights.shape[-2] + 2 * r \
            or padded.shape[-1] != weights.shape[-1] + 2 * r:
        raise ValueError(f"kernel_apply_padded: padded {tuple(padded.shape)} must be weights {tuple(weights.shape)} "
                         f"grown by {r} on every side")
    _check_inputs(padded[..., r:padded.shape[-2] - r, r:padded.shape[-1] - r], weights, kernel_size, "zeros")
    return _ShiftLoopKernelApply.apply(padded, weights, kernel_size)


def kernel_apply_unfold(
    image: torch.Tensor, weights: torch.Tensor, kernel_size: int, padding_mode: str = "zeros"
) -> torch.Tensor:
    """Reference implementation of :func:`kernel_apply` with ``F.unfold``.

    Same arguments, result and checks as :func:`kernel_apply`. Materialises a
    ``(B, C*k*k, H*W)`` tensor plus an equally large product, so it needs about
    ``2 * B*C*k*k*H*W * itemsize`` bytes; use it only for tests and benchmarks.
    """
    _check_inputs(image, weights, kernel_size, padding_mode)
    b, c, h, w = image.shape
    k = kernel_size
    padded = _pad(image, k // 2, padding_mode)
    cols = F.unfold(padded, kernel_size=k)  # (B, C*k*k, H*W), channel-major then row-major taps
    cols = cols.view(b, c, k * k, h, w)
    return (cols * weights.unsqueeze(1)).sum(dim=2)


class KernelApply(nn.Module):
    """Module wrapper around :func:`kernel_apply`.

    Args:
        kernel_size: odd ``k``.
        padding_mode: ``"zeros"`` or ``"replicate"``.

    Shape:
        - image: ``(B, C, H, W)``
        - weights: ``(B, k*k, H, W)``
        - output: ``(B, C, H, W)``
    """

    def __init__(self, kernel_size: int, padding_mode: str = "zeros") -> None:
        super().__init__()
        if isinstance(kernel_size, bool) or not isinstance(kernel_size, int) or kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"KernelApply: kernel_size must be a positive odd integer, got {kernel_size!r}")
        if padding_mode not in PADDING_MODES:
            raise ValueError(f"KernelApply: padding_mode must be one of {PADDING_MODES}, got {padding_mode!r}")
        self.kernel_size = kernel_size
        self.padding_mode = padding_mode

    def forward(self, image: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        return kernel_apply(image, weights, self.kernel_size, self.padding_mode)

    def extra_repr(self) -> str:
        return f"kernel_size={self.kernel_size}, padding_mode={self.padding_mode!r}"
