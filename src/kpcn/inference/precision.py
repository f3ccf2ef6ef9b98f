"""The dtype a denoise call runs a model's hidden layers in (``denoise(..., precision=...)``).

``"auto"`` (the default) picks bfloat16 where it is both possible and fast: on the CPU, for a model that can
compute in it (:attr:`~kpcn.models.DenoiserModel.compute_dtypes`: the U-Net), on a processor with native
bfloat16 arithmetic (AMX tiles or AVX-512 BF16, where oneDNN's convolutions run 3-5× faster than in
float32: ``python -m kpcn.bench denoise`` prints both); float32 everywhere else. Only the convolution stack
changes dtype: the kernels, their softmax and their application to the colour stay float32, so a constant
image stays constant and a zero branch stays zero in either. ``KPCN_PRECISION=float32`` (or ``bfloat16``)
in the environment sets what ``"auto"`` means.
"""
from __future__ import annotations

import contextlib
import os

import torch

from ..constants import PRECISIONS as COMPUTE_PRECISIONS

__all__ = ["PRECISIONS", "native_bfloat16", "resolve_precision", "compute_dtype"]

PRECISIONS = ("auto", *COMPUTE_PRECISIONS)


def native_bfloat16(device: torch.device | str = "cpu") -> bool:
    """Whether ``device`` does bfloat16 arithmetic natively (CPU: AMX or AVX-512 BF16; CUDA: compute
    capability 8.0 or later)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    if device.type != "cpu" or not torch.backends.mkldnn.is_available():
        return False
    probe = [getattr(torch.cpu, n, None) for n in ("_is_amx_tile_supported", "_is_avx512_bf16_supported")]
    return any(bool(f()) for f in probe if f is not None)


def resolve_precision(precision: str, net, device: torch.device | str) -> torch.dtype:
    """The compute dtype for ``net`` on ``device`` (see the module docstring).

    Raises:
        ValueError: an unknown ``precision``, or one the model cannot run in.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"denoise: precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision == "auto":
        env = os.environ.get("KPCN_PRECISION", "").strip()
        if env:
            if env not in PRECISIONS:
                raise ValueError(f"KPCN_PRECISION must be one of {', '.join(PRECISIONS)}, got {env!r}")
            precision = env
    if precision == "auto":
        can = torch.bfloat16 in getattr(net, "compute_dtypes", (torch.float32,))
        fast = torch.device(device).type == "cpu" and native_bfloat16(device)
        return torch.bfloat16 if can and fast else torch.float32
    dtype = getattr(torch, precision)
    if dtype not in getattr(net, "compute_dtypes", (torch.float32,)):
        raise ValueError(f"denoise: {getattr(net, 'name', '') or type(net).__name__} cannot run in {precision} "
                         f"(it can in: {', '.join(str(d).removeprefix('torch.') for d in net.compute_dtypes)})")
    return dtype


@contextlib.contextmanager
def compute_dtype(net, dtype: torch.dtype):
    """``net`` computing in ``dtype`` inside the block, as it was after it."""
    if not hasattr(net, "set_compute_dtype"):
        yield net
        return
    before = net.compute_dtype
    net.set_compute_dtype(dtype)
    try:
        yield net
    finally:
        net.set_compute_dtype(before)
