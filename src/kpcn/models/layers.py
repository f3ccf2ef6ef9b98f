"""Building blocks shared by the kernel-predicting models (KPCN, the multi-scale KPCN, the U-Net).

* :func:`transform_input`: what a network sees of its input features (``log``:
  signed ``log1p``, so a dim scene and a 1e8-bright one have the same range;
  ``logvar``: variances as ``log(var + 1e-6)``);
* :func:`kernel_prior_bias`: the bias of a kernel head so that a fresh model's
  kernels are a Gaussian;
* :func:`albedo_ratio`: the per-tap factor that turns a kernel applied to the
  colour into one applied to the albedo-demodulated colour (KPCN's ``demodulate``);
* :func:`pool2`, :func:`upsample2` and :func:`conv1x1` (:class:`Conv1x1`): a 2×2 average pool, a bilinear 2×
  upsampling and a 1×1 convolution written for the CPU's memory traffic (what the U-Net does at full resolution;
  :mod:`kpcn.models.guided`: the upsampling guided by the frame's normal);
* :func:`relu_` (:class:`ReLU`): an in-place ReLU that is fast on bfloat16 tensors too;
* :func:`up_cat_conv3x3`: a U-Net decoder's first convolution of ``[nearest_up2(coarse), skip]``
  without building either (a transposed convolution of the coarse input plus a convolution of the skip).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..inputs import get_input_spec, radiance_of

__all__ = ["INPUT_TRANSFORMS", "VARIANCE_CHANNELS", "VARIANCE_FLOOR", "DEMOD_EPS", "transform_input",
           "kernel_prior_bias", "albedo_ratio", "pool2", "pool2_radiance", "upsample2", "conv1x1",
           "conv1x1_lowp", "Conv1x1",
           "up_cat_conv3x3", "UpCatConv", "UpAddConv", "relu_", "ReLU"]

INPUT_TRANSFORMS = ("logvar", "log", "none")
#: feature channels holding variances (DESIGN 2.2 layout: colour variance, then normal/albedo/depth)
VARIANCE_CHANNELS = get_input_spec("kpcn_split").variance_channels  # (3, 24, 25, 26)
VARIANCE_FLOOR = 1e-6
#: added to the mean albedo before demodulating by it (a black surface would divide by ~0; with 0.003, the
#: split specs' EPS, demodulating the whole colour lost 4 dB on glossy black surfaces)
DEMOD_EPS = 0.1


def transform_input(x: torch.Tensor, kind: str) -> torch.Tensor:
    """What the conv stack sees.

    ``"none"``: the raw features. ``"log"``: ``sign(x) log1p(|x|)``. ``"logvar"``:
    the same, but the variance channels become ``log(var + 1e-6)``: a signed
    log1p maps a 1024-spp variance and a 32-spp one to the same ~0, so the net
    could not tell a converged input from a noisy one and blurred both.
    """
    if kind == "none":
        return x
    y = x.abs().log1p_().copysign_(x)  # sign(x) log1p(|x|) with one temporary (frames are large)
    if kind == "logvar" and x.shape[1] > max(VARIANCE_CHANNELS):
        idx = list(VARIANCE_CHANNELS)
        y = y.clone()
        y[:, idx] = torch.log(x[:, idx].clamp_min(0.0) + VARIANCE_FLOOR)
    return y


def kernel_prior_bias(k: int, sigma: float, logit_scale: float | None) -> torch.Tensor:
    """Bias ``(k*k,)`` of a kernel head so that a fresh model's kernels are a Gaussian of std ``sigma`` pixels.

    The log-prior ``-d^2 / (2 sigma^2)`` over the tap offset ``d``, clipped to
    ``-logit_scale / 2`` (no tap starts in the flat part of the tanh bound) and
    mapped through ``atanh`` so that ``s * tanh(bias / s)`` equals it.
    """
    r = k // 2
    off = torch.arange(k, dtype=torch.float64) - r
    d2 = (off[:, None] ** 2 + off[None, :] ** 2).reshape(-1)
    prior = -d2 / (2.0 * sigma**2)
    s = logit_scale
    if s is None:
        return prior.clamp(min=-30.0).float()
    prior = prior.clamp(min=-0.5 * s)
    return (s * torch.atanh(prior / s)).float()


def albedo_ratio(albedo: torch.Tensor, kernel_size: int, eps: float = DEMOD_EPS) -> torch.Tensor:
    """``(a_p + eps) / (a_q + eps)`` for every pixel ``p`` and tap ``q`` of its ``k x k`` neighbourhood.

    ``a`` is the channel mean of the albedo (clamped at 0); taps are in
    ``F.unfold`` order, and the border is replicated as
    :func:`kpcn.ops.kernel_apply` replicates the colour. A kernel ``w`` times
    this ratio, applied to the colour ``c``, equals ``(a_p + eps) * sum_q w_q
    c_q / (a_q + eps)``: the kernel applied to the albedo-demodulated colour and
    remodulated, so texture is kept where the kernel averages shading.

    Args:
        albedo: ``(B, 3, H, W)`` (or ``(B, 1, H, W)``).
        kernel_size: odd ``k``.

    Returns:
        ``(B, k*k, H, W)``, positive and finite; 1 at the centre tap.
    """
    b, _, h, w = albedo.shape
    r = kernel_size // 2
    a = albedo.clamp_min(0.0).mean(dim=1, keepdim=True) + eps
    taps = F.unfold(F.pad(a, (r, r, r, r), mode="replicate"), kernel_size).view(b, kernel_size * kernel_size, h, w)
    return a / taps


def pool2(x: torch.Tensor) -> torch.Tensor:
    """2×2 average pool of ``(B, C, H, W)`` with even ``H`` and ``W``: ``F.avg_pool2d(x, 2)`` to float
    rounding, several times faster on the CPU (two strided adds; any memory format)."""
    y = x[..., 0::2, :] + x[..., 1::2, :]
    return (y[..., 0::2] + y[..., 1::2]).mul_(0.25)


def pool2_radiance(x: torch.Tensor) -> torch.Tensor:
    """:func:`pool2` of a ``log1p``-encoded colour ``(B, C, H, W)`` as radiance: ``log1p(pool2(expm1(x)))``, the
    logarithm of the block's mean radiance rather than the mean of its logarithms (below it by Jensen's
    inequality: darker wherever a block's pixels differ). Applied twice it is the 4×4 mean's; a constant stays
    as it is. ``x`` is clamped to ``[0, SPECULAR_LOG_MAX]`` first (``log1p`` of a radiance ≥ 0; finite sums)."""
    return torch.log1p(pool2(radiance_of(x)))


def upsample2(x: torch.Tensor, context_rows: bool = False) -> torch.Tensor:
    """Bilinear 2× upsampling of ``(B, C, H, W)``: ``F.interpolate(x, scale_factor=2, mode="bilinear",
    align_corners=False)`` to float rounding, about 2.5× faster on the CPU without autograd (four
    ``lerp`` passes with the fixed weights 3/4 and 1/4, where PyTorch's kernel computes source indices and
    weights for every output element); with autograd, ``F.interpolate`` itself.

    Output row ``2i`` is ``3/4 x[i] + 1/4 x[i - 1]`` and row ``2i + 1`` is ``3/4 x[i] + 1/4 x[i + 1]``, the
    same for columns, with the edge rows and columns repeated (what ``align_corners=False`` does).

    Args:
        x: ``(B, C, H, W)``, NCHW or ``channels_last``.
        context_rows: ``x``'s first and last rows are only read, as the neighbours of the rows between
            (a band of rows of a larger map): the result is ``(B, C, 2H - 4, 2W)``, rows ``2 .. 2H - 3`` of
            the upsampled band, which are those of the upsampled larger map.

    Returns:
        ``(B, C, 2H, 2W)`` (``2H - 4`` rows with ``context_rows``), contiguous NCHW.
    """
    if torch.is_grad_enabled() and x.requires_grad:
        up = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
        return up[..., 2:-2, :] if context_rows else up
    b, c, h, w = x.shape
    if context_rows:
        if h < 3:
            raise ValueError(f"upsample2: context_rows needs at least 3 rows, got {h}")
        mid, above, below = x[..., 1:-1, :], x[..., :-2, :], x[..., 2:, :]
    else:
        mid = x
        above = torch.cat([x[..., :1, :], x[..., :-1, :]], dim=-2) if h > 1 else x
        below = torch.cat([x[..., 1:, :], x[..., -1:, :]], dim=-2) if h > 1 else x
    n = mid.shape[-2]
    v = torch.empty(b, c, 2 * n, w, dtype=x.dtype, device=x.device)
    torch.lerp(mid, above, 0.25, out=v[..., 0::2, :])
    torch.lerp(mid, below, 0.25, out=v[..., 1::2, :])
    out = torch.empty(b, c, 2 * n, 2 * w, dtype=x.dtype, device=x.device)
    even, odd = out[..., 0::2], out[..., 1::2]
    even[..., :1].copy_(v[..., :1])  # the first column's left neighbour is itself
    odd[..., -1:].copy_(v[..., -1:])
    if w > 1:
        torch.lerp(v[..., 1:], v[..., :-1], 0.25, out=even[..., 1:])
        torch.lerp(v[..., :-1], v[..., 1:], 0.25, out=odd[..., :-1])
    return out


def conv1x1(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """A 1×1 convolution ``(B, C, H, W) -> (B, O, H, W)`` as a matrix product (``weight`` ``(O, C[, 1, 1])``).

    The output is contiguous NCHW whether ``x`` is NCHW (or a band of rows of an NCHW tensor) or
    ``channels_last``: oneDNN's 1×1 convolution
    on NCHW frames spends most of its time reordering, and a channels-last result would have to be
    copied back before the element-wise work that follows.
    """
    b, c, h, w = x.shape
    wm = weight.reshape(weight.shape[0], c)
    if x.dtype != weight.dtype and not torch.is_grad_enabled():
        return _conv1x1_low(x, wm, bias)
    if x.stride(-1) == 1 and (h == 1 or x.stride(-2) == w):  # each channel's rows follow on (NCHW, or a band of it)
        xm = x.reshape(b, c, h * w)  # a view
    elif x.is_contiguous(memory_format=torch.channels_last):
        xm = x.permute(0, 2, 3, 1).reshape(b, h * w, c).transpose(1, 2)  # a view: (B, C, HW) strided
    else:
        return F.conv2d(x, weight.reshape(-1, c, 1, 1), bias).contiguous()
    if b == 1:
        out = torch.addmm(bias[:, None], wm, xm[0]) if bias is not None else torch.mm(wm, xm[0])
        return out.view(1, -1, h, w)
    out = torch.matmul(wm, xm)
    if bias is not None:
        out = out + bias[:, None]
    return out.view(b, -1, h, w)


def _conv1x1_low(x: torch.Tensor, wm: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """:func:`conv1x1` of reduced-precision features (bfloat16 hidden layers, inference): the product in
    ``x``'s dtype (float32 accumulation, the result rounded to ``x``'s dtype), then the result and the bias in
    the weights' dtype, NCHW contiguous. A matrix product writes NCHW directly, where a convolution of a
    channels-last map would write channels-last and need a transposing copy (twice the time at 1080p)."""
    out = conv1x1_lowp(x, wm).to(wm.dtype, memory_format=torch.contiguous_format)
    return out.add_(bias.view(1, -1, 1, 1)) if bias is not None else out


def conv1x1_lowp(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """The product ``weight · x`` of a 1×1 convolution without bias, in ``x``'s (reduced) precision: ``(B, O, H, W)``
    NCHW in ``x``'s dtype (float32 accumulation, rounded once), ``weight`` ``(O, C[, 1, 1])`` of any float dtype.
    Inference; :func:`conv1x1` converts it to the weights' dtype and adds the bias, a caller that keeps a large map
    can keep it in ``x``'s dtype and convert it a band at a time (:mod:`kpcn.models.unet_rows`)."""
    b, c, h, w = x.shape
    wl = weight.reshape(weight.shape[0], c).to(x.dtype)
    if b == 1 and x.is_contiguous(memory_format=torch.channels_last):
        return torch.mm(wl, x.permute(0, 2, 3, 1).reshape(h * w, c).t()).view(1, -1, h, w)
    if b == 1 and x.is_contiguous():
        return torch.mm(wl, x.view(c, h * w)).view(1, -1, h, w)
    return F.conv2d(x, wl.reshape(-1, c, 1, 1)).contiguous()


class Conv1x1(nn.Conv2d):
    """An ``nn.Conv2d`` with a 1×1 kernel computed by :func:`conv1x1` (same parameters and state-dict keys)."""

    def forward(self, x):  # type: ignore[override]
        return conv1x1(x, self.weight, self.bias)


#: for each tap k of a stride-2 transposed convolution's 4-tap kernel (padding 1), which taps of a 3-tap
#: kernel applied after a nearest 2× upsampling it gathers: output row 2m reads input m (taps 1, 2) and
#: m - 1 (tap 0); row 2m + 1 reads m (taps 0, 1) and m + 1 (tap 2)
_UP_TAPS = ((0, 0, 1), (0, 1, 1), (1, 1, 0), (1, 0, 0))


def up_cat_conv3x3(coarse: torch.Tensor, skip: torch.Tensor, weight: torch.Tensor,
                   bias: torch.Tensor | None = None) -> torch.Tensor:
    """``conv2d(cat([nearest_up2(coarse), skip]), weight, bias, padding=1)`` without the upsampling or the cat.

    A 3×3 convolution (zero padding) of a nearest-upsampled map is a stride-2 transposed convolution of
    the map itself with a 4×4 kernel whose taps are sums of the 3×3 taps (:data:`_UP_TAPS`): 4 rather than
    9 multiply-adds per output pixel and channel, and neither the upsampled map nor the concatenation is
    written. Same result to float rounding (``tests/test_models.py``). Inference path of the U-Net's decoder.

    Args:
        coarse: ``(B, Cc, h, w)``.
        skip: ``(B, Cs, 2h, 2w)``.
        weight: ``(O, Cc + Cs, 3, 3)`` (the coarse input's channels first); bias ``(O,)``.

    Returns:
        ``(B, O, 2h, 2w)``, in ``skip``'s memory format.
    """
    cc = coarse.shape[1]
    if weight.shape[-2:] != (3, 3) or weight.shape[1] != cc + skip.shape[1]:
        raise ValueError(f"up_cat_conv3x3: weight {tuple(weight.shape)} is not a 3x3 kernel over "
                         f"{cc} + {skip.shape[1]} input channels")
    if skip.shape[-2:] != (2 * coarse.shape[-2], 2 * coarse.shape[-1]):
        raise ValueError(f"up_cat_conv3x3: skip {tuple(skip.shape)} is not twice coarse {tuple(coarse.shape)}")
    taps = torch.tensor(_UP_TAPS, dtype=weight.dtype, device=weight.device)
    wt = torch.einsum("ky,lx,ocyx->cokl", taps, taps, weight[:, :cc])  # (Cc, O, 4, 4)
    out = F.conv2d(skip, weight[:, cc:], bias, padding=1)
    return out.add_(F.conv_transpose2d(coarse, wt.contiguous(), stride=2, padding=1))


class UpCatConv(nn.Conv2d):
    """A U-Net decoder's first 3×3 conv (padding 1) of ``[nearest_up2(coarse), skip]``, taking the pair
    ``(coarse (B, Cc, h, w), skip (B, Cs, 2h, 2w))``: the same parameters and state-dict keys as an
    ``nn.Conv2d`` on the concatenation. Without autograd it runs :func:`up_cat_conv3x3` (no upsampled
    map or concatenation written, 4 rather than 9 multiply-adds per pixel for the coarse input); with
    autograd, the plain upsample, concatenation and convolution."""

    def forward(self, pair):  # type: ignore[override]
        coarse, skip = pair
        if torch.is_grad_enabled():
            up = F.interpolate(coarse, scale_factor=2, mode="nearest")
            return F.conv2d(torch.cat([up, skip], dim=1), self.weight, self.bias, padding=1)
        return up_cat_conv3x3(coarse, skip, self.weight, self.bias)

    def macs(self, pair, out) -> int:
        """Multiply-adds of one call per image (for :func:`kpcn.models.cost.macs_per_pixel`): the path run."""
        coarse, skip = pair
        fine = out[0, 0].numel() * self.out_channels
        if torch.is_grad_enabled():
            return fine * self.in_channels * 9
        return fine * (9 * skip.shape[1] + 4 * coarse.shape[1])


class UpAddConv(nn.Conv2d):
    """A U-Net decoder's first conv with a 1×1 on the coarser level (``UNetConfig.up_kernel: 1``): ``conv3x3(skip) +
    nearest_up2(conv1x1(coarse))``, taking the pair ``(coarse (B, Cc, h, w), skip (B, Cs, 2h, 2w))``.

    The coarse part runs at the coarse resolution (``Cc`` rather than :class:`UpCatConv`'s ``4 Cc`` multiply-adds
    per output pixel and channel: the largest conv of the default U-Net's decoder, 96 + 64 -> 64 at half
    resolution, drops from 15.4 k to 9.6 k per full-resolution pixel); it is :class:`UpCatConv` with the coarse
    input's taps off the centre zero. The module is the ``nn.Conv2d`` of the skip (``weight`` ``(O, Cs, 3, 3)``,
    ``bias``) with the 1×1 as its child ``coarse`` (``(O, Cc, 1, 1)``, no bias). Without autograd the
    upsampled coarse part is added in place, a broadcast over each 2×2 block of a ``channels_last`` result.
    """

    def __init__(self, coarse_channels: int, skip_channels: int, out_channels: int) -> None:
        super().__init__(skip_channels, out_channels, 3, padding=1)
        self.coarse = nn.Conv2d(coarse_channels, out_channels, 1, bias=False)
        nn.init.kaiming_normal_(self.coarse.weight, nonlinearity="relu")

    def forward(self, pair):  # type: ignore[override]
        coarse, skip = pair
        if skip.shape[-2:] != (2 * coarse.shape[-2], 2 * coarse.shape[-1]):
            raise ValueError(f"UpAddConv: skip {tuple(skip.shape)} is not twice coarse {tuple(coarse.shape)}")
        out = super().forward(skip)
        c = self.coarse(coarse)
        cl = torch.channels_last
        if torch.is_grad_enabled() or c.dtype != out.dtype or not (
                out.is_contiguous(memory_format=cl) and c.is_contiguous(memory_format=cl)):
            return out + F.interpolate(c, scale_factor=2, mode="nearest")
        b, o, h, w = c.shape  # (B, 2h, 2w, O) in memory: each coarse pixel's O values added to a 2x2 block
        out.permute(0, 2, 3, 1).view(b, h, 2, w, 2, o).add_(c.permute(0, 2, 3, 1).view(b, h, 1, w, 1, o))
        return out

    def macs(self, pair, out) -> int:
        """Multiply-adds of the skip's 3×3 per image (for :func:`kpcn.models.cost.macs_per_pixel`; the child
        ``coarse`` is counted as the 1×1 conv it is, at the coarse resolution)."""
        return out[0, 0].numel() * self.out_channels * 9 * self.in_channels


def relu_(x: torch.Tensor) -> torch.Tensor:
    """``x.relu_()``; a bfloat16 ``x`` that needs no gradient is clamped through its ``int16`` view instead.

    A bfloat16 value is negative exactly when its sign bit, the int16 sign bit, is set, so clamping the
    int16 view at 0 maps every negative value to +0 and leaves the rest: the ReLU bit for bit (but -0, which
    becomes +0, an equal value), 4-8× faster on the CPU than PyTorch's bfloat16 clamp, which converts each
    value to float32 and back (``tests/test_models.py``). (A NaN with its sign bit set becomes 0, where
    ``relu_`` keeps it; the network's inputs are finite.)
    """
    if x.dtype == torch.bfloat16 and not (torch.is_grad_enabled() and x.requires_grad):
        x.view(torch.int16).clamp_min_(0)
        return x
    return x.relu_()


class ReLU(nn.ReLU):
    """An in-place ``nn.ReLU`` computed by :func:`relu_` (no parameters: a drop-in for ``nn.ReLU(inplace=True)``)."""

    def __init__(self) -> None:
        super().__init__(inplace=True)

    def forward(self, x):  # type: ignore[override]
        return relu_(x)
