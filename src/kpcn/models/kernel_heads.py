"""The U-Net's kernel heads and how its kernels are applied (:mod:`kpcn.models.unet`).

* :func:`_bounded_softmax`: kernels ``softmax(s · tanh(z / s))`` from a head's logits;
* :class:`GuidedHead`: the ``stem: half`` head, a 1×1 conv of the upsampled finest decoder level and a
  full-resolution guide, computed without building either at full size;
* :class:`MultiScaleKernels` / :class:`MultiScaleApply` / :func:`combine_levels`: kernels at several
  resolutions, each applied to the colour pooled to its level, combined coarse to fine
  (Vogels et al. 2018).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..inputs import radiance_of
from ..ops.kernel_apply import KernelApply
from .guided import apply_guided, guided_weights
from .layers import conv1x1, pool2, pool2_radiance, upsample2

__all__ = ["GuidedHead", "MultiScaleKernels", "MultiScaleApply", "blend_weights", "combine_levels", "gate_of",
           "gated_albedo", "albedo_bound", "radiance_mixed"]

_LOG2_E = 1.4426950408889634


def _bounded_softmax(z: torch.Tensor, s: float) -> torch.Tensor:
    """``softmax(s * tanh(z / s))`` over channels, contiguous; in place where no gradient is needed."""
    if torch.is_grad_enabled() and z.requires_grad:
        # s tanh(z / s) = 2s sigmoid(2z / s) - s, and a softmax ignores the constant: the same function, with
        # PyTorch's CPU sigmoid ~10x faster than its tanh (tanh and this softmax: 6 % of a training step, py-spy)
        return torch.softmax(torch.sigmoid(z * (2.0 / s)) * (2.0 * s), dim=1).contiguous()
    w, norm = _softmax_weights(z, s)  # inference: in place (frames are large)
    return w.div_(norm).contiguous() if norm is not None else w


def _softmax_weights(z: torch.Tensor, s: float, inplace: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Inference: unnormalised kernel weights ``exp(s tanh(z / s))`` and their sum over channels (the bounded
    logits lie in ``[-s, s]``, so for ``s <= 80`` exp cannot overflow and no maximum need be subtracted: equal
    to ``torch.softmax`` to float rounding); a caller may divide after applying them (3 channels, not ``k*k``).
    For ``s > 80``: the normalised softmax and None. ``inplace``: ``z`` (a temporary) holds the weights."""
    t = z if inplace else z.clone()
    if s > 80:
        return torch.softmax(bounded_logits_(t, s), dim=1).contiguous(), None
    # exp(s tanh(z / s)) = 2 ** (log2(e) s tanh(z / s)): PyTorch's CPU exp2 is about 3x faster than its exp
    t = bounded_logits_(t, s, scale=_LOG2_E).exp2_()
    return t, t.sum(dim=1, keepdim=True)


def bounded_logits_(z: torch.Tensor, s: float, scale: float = 1.0) -> torch.Tensor:
    """``scale * s * tanh(z / s)`` in place, computed as ``scale * (2s * sigmoid(2z / s) - s)`` (the same function:
    ``tanh(x) = 2 sigmoid(2x) - 1``): PyTorch's CPU sigmoid is about 10x faster than its tanh, which was a fifth of
    a 1080p denoise (``python -m kpcn.bench denoise``; docs/measured.md). Inference only (no autograd)."""
    a = 2.0 * s * scale
    return z.mul_(2.0 / s).sigmoid_().mul_(a).sub_(0.5 * a)


def blend_weights(z: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """A kernel level's channels after its logits ``(B, 0..2, h, w)``: the blending weight ``α = sigmoid(z_0)`` and
    the high-band gain ``β = 2 sigmoid(z_1)`` (``UNetConfig.band_gain``), each None where the level has none."""
    n = z.shape[1]
    alpha = torch.sigmoid(z[:, :1]) if n > 0 else None
    gain = torch.sigmoid(z[:, 1:2]).mul(2.0) if n > 1 else None
    return alpha, gain


def gate_of(z: torch.Tensor, gain: float = 1.0) -> torch.Tensor:
    """The albedo gate ``g = tanh(gain · z)`` of its logit ``(B, 1, H, W)`` (0: the noisy albedo as it is)."""
    return torch.tanh(z * gain) if gain != 1.0 else torch.tanh(z)


def gated_albedo(albedo: torch.Tensor, filtered: torch.Tensor, gate: torch.Tensor,
                 bound: torch.Tensor | None = None) -> torch.Tensor:
    """``max(a + g · (K_a ⊛ a - a), 0)``: the albedo the colour is remodulated with (``UNetConfig.albedo_kernel``);
    ``albedo`` and ``filtered`` ``(B, 3, H, W)``, ``gate`` ``(B, 1, H, W)`` in ``[-1, 1]``; ``bound`` ``(B, 1, H, W)``
    (``UNetConfig.albedo_clamp``): the correction ``K_a ⊛ a - a`` clamped to ``[-bound, bound]`` first."""
    if bound is None:
        return torch.lerp(albedo, filtered, gate.to(filtered.dtype)).clamp_min(0.0)
    delta = filtered - albedo
    delta = torch.minimum(torch.maximum(delta, -bound), bound)
    return albedo.addcmul(gate.to(delta.dtype), delta).clamp_min(0.0)


def albedo_bound(variance: torch.Tensor, c: float) -> torch.Tensor:
    """``c · sqrt(max(variance, 0))``: the most an albedo may move (``UNetConfig.albedo_clamp``), of the variance of its
    pixel mean ``(B, 1, H, W)``."""
    return variance.clamp_min(0.0).sqrt().mul_(c)


def radiance_mixed(apply, colour: torch.Tensor, weights, gamma: torch.Tensor) -> torch.Tensor:
    """``lerp(K ⊛ c, log1p(K ⊛ expm1(c)), γ)`` (``UNetConfig.radiance_mix``) of a ``log1p``-encoded colour
    ``(B, C, H, W)`` with a per-pixel weight ``γ`` ``(B, 1, H, W)`` in ``[0, 1]``: ``apply(x, weights)`` is the
    kernel's application (called once, on the colour and its radiance side by side; the radiance
    :func:`~kpcn.inputs.radiance_of`, ``c`` clamped). Both filters keep a constant and a zero, so the mix does."""
    c = colour.shape[1]
    both = apply(torch.cat([colour, radiance_of(colour)], dim=1), weights)
    return torch.lerp(both[:, :c], torch.log1p(both[:, c:].clamp_min(0.0)), gamma.to(both.dtype))


@dataclass(frozen=True)
class MultiScaleKernels:
    """Per-level kernels ``(B, k*k, H/2**l, W/2**l)``, blending weights ``(B, 1, ...)`` (None at the coarsest) and
    high-band gains (:attr:`gains`), at the size padded to the alignment; ``size`` is the unpadded ``(H, W)``."""

    kernels: tuple[torch.Tensor, ...]
    alphas: tuple[torch.Tensor | None, ...]
    size: tuple[int, int]
    #: per-level high-band gains ``(B, 1, ...)`` (``UNetConfig.band_gain``; None: every gain 1)
    gains: tuple[torch.Tensor | None, ...] | None = None
    #: ``UNetConfig.albedo_kernel``: the albedo's full-resolution kernels ``(B, k_a², H, W)`` (softmax-normalised)
    #: and gates ``(B, 1, H, W)`` (and with ``albedo_clamp`` the bounds ``(B, 1, H, W)``, else None), for
    #: :func:`gated_albedo`; None: the albedo as it is
    albedo: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None] | None = None
    #: ``UNetConfig.radiance_mix``: per-level weights ``γ`` ``(B, 1, ...)`` of the radiance-space filter
    #: (:func:`radiance_mixed`); None: the kernels applied to the colour as it is
    mixes: tuple[torch.Tensor, ...] | None = None
    #: ``UNetConfig.edge_upsample``: the guide of every level ``(B, G, H/2**l, W/2**l)`` at the padded size (the
    #: frame's normal and its :func:`pool2` pyramid) and the σ of the joint bilateral upsampling; None: bilinear
    guides: tuple[torch.Tensor, ...] | None = None
    guide_sigma: float = 0.0


class MultiScaleApply(nn.Module):
    """Apply :class:`MultiScaleKernels` to a colour ``(B, 3, H, W)``: filter each level, combine coarse to fine.
    ``radiance``: the colour is ``log1p`` of a radiance, pooled to the coarser levels as radiance
    (:func:`~kpcn.models.layers.pool2_radiance`; ``UNetConfig.radiance_pool``). Kernels with ``mixes``
    (``UNetConfig.radiance_mix``) filter each level with :func:`radiance_mixed`."""

    def __init__(self, kernel_size: int, alignment: int, radiance: bool = False,
                 coarse_kernel: int | None = None) -> None:
        super().__init__()
        self.kernel_size, self.alignment = kernel_size, alignment
        self.apply_one = KernelApply(kernel_size, "replicate")
        #: the coarser levels' kernels (``UNetConfig.coarse_kernel``), where they differ from the finest level's
        same = not coarse_kernel or coarse_kernel == kernel_size
        self.apply_coarse = self.apply_one if same else KernelApply(coarse_kernel, "replicate")
        self.pool = pool2_radiance if radiance else pool2

    def forward(self, colour: torch.Tensor, ks: MultiScaleKernels) -> torch.Tensor:
        h, w = ks.size
        a = self.alignment
        colour = F.pad(colour, (0, (-w) % a, 0, (-h) % a), mode="replicate") if (h % a or w % a) else colour
        filtered = []
        level_colour = colour
        for level, k in enumerate(ks.kernels):
            if level:
                level_colour = self.pool(level_colour)
            apply = self.apply_coarse if level else self.apply_one
            if ks.mixes is not None:
                filtered.append(radiance_mixed(apply, level_colour.contiguous(), k, ks.mixes[level]))
            else:
                filtered.append(apply(level_colour.contiguous(), k))
        return combine_levels(filtered, ks.alphas, ks.gains, ks.guides, ks.guide_sigma)[..., :h, :w]


def combine_levels(filtered, alphas, gains=None, guides=None, sigma: float = 0.0) -> torch.Tensor:
    """Coarse to fine, ``o_l = f_l + α_l · U(o_{l+1} - D(f_l))`` over filtered levels ``(B, 3, H/2**l, W/2**l)``;
    with a level's gain ``β_l`` (``gains``, None: 1) also ``- (1 - β_l) · (f_l - U(D(f_l)))``, its high band scaled.
    ``U`` is :func:`upsample2`; with ``guides`` (a guide ``(B, G, H/2**l, W/2**l)`` per level, e.g. the frame's
    normal and its :func:`pool2` pyramid) and ``sigma`` > 0, :func:`~kpcn.models.guided.upsample2_guided` (joint
    bilateral), both ``U``s, so that a coarse level's value does not bleed across an edge of the guide."""
    out = filtered[-1]
    guided = guides is not None and sigma > 0
    for level in range(len(filtered) - 2, -1, -1):
        f, alpha = filtered[level], alphas[level]
        beta = gains[level] if gains is not None else None
        df = pool2(f)
        if guided:  # the tap weights once for the level, both maps upsampled in one pass
            wts = guided_weights(guides[level].to(f.dtype), guides[level + 1], sigma)
            both = apply_guided(torch.cat([df, out - df], 1), wts)
            u_df, u_corr = both[:, :df.shape[1]], both[:, df.shape[1]:]
        else:
            u_df, u_corr = (upsample2(df) if beta is not None else None), upsample2(out - df)
        if beta is not None:  # f - (1 - β)(f - U D f) = lerp(U D f, f, β)
            f = torch.lerp(u_df, f, beta)
        out = f.addcmul(alpha, u_corr)
    return out


class GuidedHead(nn.Conv2d):
    """The ``stem: half`` head: a 1×1 conv of ``[bilinear_up2(coarse), guide]``, computed as
    ``bilinear_up2(W_c · coarse + b) + W_g · guide``.

    The same function (a 1×1 conv is per-pixel affine, and bilinear weights sum to one, so the
    two commute) and the same parameters as an ``nn.Conv2d`` on the concatenation, but the
    coarse part runs at half resolution and no full-resolution concatenation is built.
    ``forward`` takes the pair ``(coarse (B, Cc, h, w), guide (B, Cg, 2h, 2w))``.
    """

    def forward(self, pair):  # type: ignore[override]
        coarse, guide = pair
        return self.add_guide_part_(upsample2(self.coarse_part(coarse)), guide)  # in place: one full-size tensor fewer

    def add_guide_part_(self, z: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
        """``z += W_g · guide`` in place and ``z``: ``z`` ``(B, O, H, W)``, ``guide`` ``(B, Cg, H, W)``. Without autograd,
        for one NCHW ``z`` and a ``guide`` whose channels' rows follow on (NCHW, or a band of rows of it), one matrix
        product that accumulates into ``z`` (no temporary of ``O`` full-resolution channels to add)."""
        b, o, h, w = z.shape
        guide = guide.to(z.dtype)  # a guide kept in reduced precision (row streams), in z's for the product
        flat = guide.stride(-1) == 1 and (h == 1 or guide.stride(-2) == w)
        if b != 1 or torch.is_grad_enabled() or not z.is_contiguous() or not flat:
            return z.add_(self.guide_part(guide))
        wg = self.weight[:, self.in_channels - guide.shape[1]:].reshape(o, -1)
        z.view(o, h * w).addmm_(wg, guide[0].reshape(guide.shape[1], h * w))
        return z

    def coarse_part(self, coarse: torch.Tensor) -> torch.Tensor:
        """``W_c · coarse + b`` at the coarse resolution (before the upsampling)."""
        return conv1x1(coarse, self.weight[:, : coarse.shape[1]], self.bias)

    def guide_part(self, guide: torch.Tensor) -> torch.Tensor:
        """``W_g · guide`` (the guide's channels are the last inputs)."""
        return conv1x1(guide, self.weight[:, self.in_channels - guide.shape[1]:])

    def macs(self, pair, out) -> int:
        """Multiply-adds of one call per image (for :func:`kpcn.models.cost.macs_per_pixel`)."""
        coarse, guide = pair
        n_out = self.out_channels
        return (coarse[0, 0].numel() * coarse.shape[1] + guide[0, 0].numel() * guide.shape[1]) * n_out
