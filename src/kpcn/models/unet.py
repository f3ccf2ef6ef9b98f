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
  features of the same level, ``convs_per_level`` 3×3 convs + ReLU (at inference
  the first conv is computed without building the upsampled map or the
  concatenation: :class:`~kpcn.models.layers.UpCatConv`); with ``up_kernel: 1``
  that conv's taps over the upsampled level are one 1×1 at the coarse resolution
  (:class:`~kpcn.models.layers.UpAddConv`);
* head: a 1×1 conv to ``kernel_size²`` bounded logits (``s·tanh(z/s)``), a
  softmax, and the per-pixel kernel applied to the noisy branch colour with
  replicate padding — the output is a convex combination of input pixels, so a
  zero branch stays zero and a constant image stays constant.

The input is padded (replicate) at the bottom/right to a multiple of
``alignment = 2**(len(widths) - 1)`` and the output cropped back.

**Multi-scale kernels** (Vogels et al. 2018; ``kernel_scales = n > 1``): the
decoder predicts a kernel at each of the ``n`` finest levels, each applied to
the noisy colour average-pooled to that level, so a ``k``×``k`` kernel at
level ``l`` spans ``k·2**l`` pixels at the cost of a ``k``×``k`` one. Levels
``l < n - 1`` also predict a per-pixel weight ``α = sigmoid(z)`` and the
filtered levels are combined coarse to fine::

    o_l = f_l - α_l · U(D(f_l)) + α_l · U(o_{l+1})

(``D`` a 2×2 average pool, ``U`` bilinear 2× upsampling): ``α`` swaps the low
frequencies of the fine result for the coarse one. With ``band_gain`` a level
also predicts ``β = 2·sigmoid(z)`` and scales its high band ``f_l - U(D(f_l))``
by it (the blend alone keeps that band whole: the grain a small kernel leaves). A constant image stays
constant and a zero branch stays zero (each term is linear in the colour and
every kernel sums to one), but the output is no longer a convex combination of
input pixels. Light groups filtered with :meth:`UNetBranch.kernels` and
``apply_kernels`` still add up to the beauty, as the combination is linear in
the colour.

**Albedo kernel** (``albedo_kernel = k_a > 0``, the diffuse branch only): the full-resolution head also
predicts a ``k_a``×``k_a`` kernel ``K_a`` and a gate ``g = tanh(c·z)`` (``c``: ``albedo_gate_gain``), and the colour is remodulated with
``max(a + g·(K_a ⊛ a - a), 0)`` (:meth:`UNetBranch.filter_albedo`) instead of the noisy albedo ``a``;
:meth:`UNetKPCN.forward` returns it as ``"albedo"``. The branch itself still filters ``diffuse / (a + eps)``.

Receptive radius (full-resolution pixels): a 3×3 conv at level ``l`` adds
``2**l``; an average pool adds nothing beyond the pooled block; a nearest
upsample into level ``l`` adds ``2**l``; the kernel reaches ``kernel_size // 2``
(at level ``l``: ``(kernel_size // 2 + 2) · 2**l``, a bound that also covers the
pooling block and the bilinear upsampling, summed over the kernel levels).
"""
from __future__ import annotations

import contextlib
import functools

import torch
import torch.nn.functional as F
from torch import nn

from ..inputs import get_input_spec
from ..ops.kernel_apply import KernelApply
from .base import DenoiserModel, check_inputs
from .kernel_heads import (GuidedHead, MultiScaleApply, MultiScaleKernels, _bounded_softmax, albedo_bound,
                           blend_weights, gate_of, gated_albedo)
from .layers import Conv1x1, ReLU, UpAddConv, UpCatConv, kernel_prior_bias, pool2, relu_, transform_input
from .registry import register_model, register_weights
from .unet_config import UNetConfig

__all__ = ["UNetConfig", "UNetBranch", "UNetKPCN", "MultiScaleKernels", "MultiScaleApply"]

#: the kpcn_split features' albedo-variance channel (kpcn.features: variances of normal, albedo, depth from 24)
ALBEDO_VARIANCE = 25


def _up_add(coarse: int, c_in: int, c_out: int, k: int, padding: int) -> UpAddConv:
    """:class:`UpAddConv` in :func:`_convs`' place of the decoder's first conv over ``c_in = coarse + skip`` inputs."""
    return UpAddConv(coarse, c_in - coarse, c_out)


def _convs(c_in: int, c_out: int, n: int, first=nn.Conv2d) -> nn.Sequential:
    mods: list[nn.Module] = []
    for i in range(n):
        conv = (first if i == 0 else nn.Conv2d)(c_in if i == 0 else c_out, c_out, 3, padding=1)
        nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")
        nn.init.zeros_(conv.bias)
        mods += [conv, ReLU()]
    return nn.Sequential(*mods)


class UNetBranch(nn.Module):
    """One branch: ``(B, C, H, W)`` features -> ``(B, 3, H, W)`` filtered colour (channels 0..2).

    ``albedo_kernel``: ``k_a`` of the albedo kernels this branch's full-resolution head also predicts (0: none;
    :class:`UNetKPCN` gives the diffuse branch ``UNetConfig.albedo_kernel``).
    """

    def __init__(self, cfg: UNetConfig, albedo_kernel: int = 0) -> None:
        super().__init__()
        self.cfg = cfg
        self.albedo_kernel = int(albedo_kernel)
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
            first = UpCatConv if cfg.up_kernel == 3 else functools.partial(_up_add, below)
            self.dec.append(_convs(below + w[level], w[level], cfg.convs_per_level, first))
            below = w[level]
        k, n = cfg.kernel_size, cfg.kernel_scales
        # level 0's head is `head` (the single-scale model's name); coarser levels' are `heads.<l-1>`;
        # every level but the coarsest adds one blending-weight channel
        off = cfg.offset
        self.guide = None
        if off:
            gk = cfg.guide_kernel
            self.guide = Conv1x1(c_in, cfg.guide_channels, 1) if gk == 1 else nn.Conv2d(c_in, cfg.guide_channels, gk)
        blend = 2 if cfg.band_gain else 1  # channels after the logits of a level that blends: α (and β)
        ka = self.albedo_kernel
        #: channels of the full-resolution head: the kernel logits, the blend (α, β), the albedo logits and gate
        self.head_layout = (k * k, blend if n > 1 else 0, ka * ka + 1 if ka else 0)
        self.head = self._make_head(w[0] + (cfg.guide_channels if off else 0), sum(self.head_layout),
                                    GuidedHead if off else Conv1x1)
        if ka:
            with torch.no_grad():  # the albedo kernels start as the colour's do (a Gaussian), gated shut (g = 0)
                self.head.bias[k * k + self.head_layout[1]:][: ka * ka].copy_(
                    kernel_prior_bias(ka, cfg.init_sigma, cfg.logit_scale))
        self.apply_albedo = KernelApply(ka, "replicate") if ka else None
        # kernel level lv (resolution 1/2**lv) reads the decoder level lv - off
        self.heads = nn.ModuleList(self._make_head(w[lv - off], k * k + (blend if lv < n - 1 else 0))
                                   for lv in range(1, n))
        self.apply_kernels = KernelApply(k, "replicate") if n == 1 else MultiScaleApply(k, cfg.alignment)
        #: the conv stack's dtype (None: float32); see :meth:`UNetKPCN.set_compute_dtype`
        self.compute_dtype: torch.dtype | None = None

    def _lowp(self, t: torch.Tensor):
        """Autocast to :attr:`compute_dtype` around the encoder and decoder convs (a no-op in float32)."""
        if self.compute_dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(t.device.type, dtype=self.compute_dtype)

    def channel_groups(self) -> dict[str, tuple[tuple[int, ...] | None, tuple[int, ...]]]:
        """:meth:`DenoiserModel.channel_groups` of this branch (names relative to it)."""
        cfg, w = self.cfg, list(self.cfg.widths)
        n, s = cfg.convs_per_level, cfg.summary_channels
        groups: dict[str, tuple[tuple[int, ...] | None, tuple[int, ...]]] = {}
        c_prev = get_input_spec(cfg.input_spec).channels
        for level, width in enumerate(w):
            for i in range(n):  # Sequential: conv, ReLU, conv, ReLU, ...
                groups[f"enc.{level}.{2 * i}"] = ((width,), (c_prev if i == 0 else width,))
            c_prev = width
        if s:
            groups["summary"] = ((s,), (w[-1], w[-1]))  # [mean, std] of the bottleneck
        below = (w[-1], s) if s else (w[-1],)
        for j, level in enumerate(range(len(w) - 2, -1, -1)):
            cat = cfg.up_kernel == 3  # UpCatConv reads [upsampled, skip]; UpAddConv the skip, its child the coarse level
            for i in range(n):
                groups[f"dec.{j}.{2 * i}"] = ((w[level],), below + (w[level],) if i == 0 and cat else (w[level],))
            if not cat:
                groups[f"dec.{j}.0.coarse"] = ((w[level],), below)
            below = (w[level],)
        off = cfg.offset
        if off:
            groups["guide"] = ((cfg.guide_channels,), (get_input_spec(cfg.input_spec).channels,))
        groups["head"] = (None, (w[0], cfg.guide_channels) if off else (w[0],))
        for lv in range(1, cfg.kernel_scales):
            groups[f"heads.{lv - 1}"] = (None, (w[lv - off],))
        return groups

    def _make_head(self, width: int, out: int, kind=None) -> nn.Conv2d:
        k, cfg = self.cfg.kernel_size, self.cfg
        head = (kind or Conv1x1)(width, out, 1)
        nn.init.kaiming_normal_(head.weight, nonlinearity="linear")
        with torch.no_grad():
            head.weight.mul_(cfg.out_init_gain)
            head.bias.zero_()
            head.bias[: k * k].copy_(kernel_prior_bias(k, cfg.init_sigma, cfg.logit_scale))
        return head

    def guide_of(self, t: torch.Tensor, pad_rows: bool = True) -> torch.Tensor:
        """``stem: half``: the guide float32 of transformed full-resolution features ``(B, C, H, W)``:
        ``relu(conv(t))``, ``t`` replicate-padded by ``r = guide_kernel // 2`` (a 3x3 guide runs in
        :attr:`compute_dtype`): ``(B, guide_channels, H, W)``; with ``pad_rows=False`` only the columns are
        padded (a row band that brings ``r`` rows each side, :mod:`kpcn.models.unet_rows`), ``H - 2r`` rows."""
        r = self.cfg.guide_kernel // 2
        if not r:
            return F.relu(self.guide(t))
        with self._lowp(t):
            g = self.guide(F.pad(t, (r, r, r, r) if pad_rows else (r, r, 0, 0), mode="replicate"))
        return relu_(g).float()

    def _pad(self, x: torch.Tensor) -> torch.Tensor:
        a = self.cfg.alignment
        ph, pw = (-x.shape[-2]) % a, (-x.shape[-1]) % a
        return F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Encoder features of every level, finest first (input padded to the alignment)."""
        if self.cfg.offset:  # pool the linear features, then transform them
            h = transform_input(pool2(self._pad(x)), self.cfg.input_transform)
        else:
            h = self._pad(transform_input(x, self.cfg.input_transform))
        return self.encode_from(h)

    def encode_from(self, h: torch.Tensor) -> list[torch.Tensor]:
        """The encoder on the first level's input ``(B, C, H', W')`` (transformed, padded, pooled with ``stem: half``).

        Without autograd the levels run ``channels_last`` (on the CPU, oneDNN's convolutions take half
        the time in that layout: no reordering around each call).
        """
        if not torch.is_grad_enabled():
            h = h.contiguous(memory_format=torch.channels_last)
        feats = []
        with self._lowp(h):
            for level, block in enumerate(self.enc):
                if level:
                    h = pool2(h)
                h = block(h)
                feats.append(h)
        return feats

    def decode(self, feats: list[torch.Tensor], summary: torch.Tensor | None = None):
        """The global summary and the decoder: ``(finest decoder level, {level: decoder output})``: float32
        with autograd, else in :attr:`compute_dtype` (the heads' :func:`~kpcn.models.layers.conv1x1` takes either)."""
        h = feats[-1]
        if self.summary is not None:
            if summary is None:
                summary = self.summarize(h)
            h = torch.cat([h, summary.to(h.dtype).expand(-1, -1, h.shape[-2], h.shape[-1])], dim=1)
            if feats[-1].is_contiguous(memory_format=torch.channels_last) and not feats[-1].is_contiguous():
                h = h.contiguous(memory_format=torch.channels_last)  # the expanded summary made it NCHW
        decoded = {}
        with self._lowp(h):
            for level, block, skip in zip(range(len(feats) - 2, -1, -1), self.dec, reversed(feats[:-1])):
                h = block((h, skip))  # its first conv (UpCatConv) upsamples h and concatenates the skip
                decoded[level] = h
        if h.dtype != torch.float32 and torch.is_grad_enabled():  # the heads, softmax and kernels run in float32
            # (without autograd the heads read the reduced-precision maps directly: kpcn.models.layers.conv1x1)
            decoded = {level: d.float() for level, d in decoded.items()}
            h = decoded[0] if decoded else h.float()
        return h, decoded

    def summarize(self, bottleneck: torch.Tensor) -> torch.Tensor | None:
        """The global summary ``(B, summary_channels, 1, 1)`` of a bottleneck (None without one)."""
        if self.summary is None:
            return None
        bottleneck = bottleneck.float()  # statistics in float32 whatever the compute dtype
        mean = bottleneck.mean(dim=(2, 3), keepdim=True)
        std = torch.sqrt(bottleneck.var(dim=(2, 3), keepdim=True, unbiased=False) + 1e-8)
        return self.summary(torch.cat([mean, std], dim=1))

    def forward(self, x: torch.Tensor, summary: torch.Tensor | None = None) -> torch.Tensor:
        return self.apply_kernels(x[:, :3].contiguous(), self.kernels(x, summary))

    def kernels(self, x: torch.Tensor, summary: torch.Tensor | None = None):
        """Softmax-normalised per-pixel kernels ``(B, k*k, H, W)`` (contiguous).

        With ``kernel_scales > 1``: a :class:`MultiScaleKernels` (kernels and blending
        weights of every level, at the padded size), which ``apply_kernels`` takes the same way.
        """
        h_in, w_in = x.shape[-2:]
        h, decoded = self.decode(self.encode(x), summary)
        s, kk, off = self.cfg.logit_scale, self.cfg.kernel_size**2, self.cfg.offset
        if off:  # full resolution: the finest level upsampled, beside the guide of the full-resolution features
            # a 1x1 conv and a ReLU are per pixel, so they commute with replicate padding: pad the
            # guide's few channels rather than the full-resolution features
            t = transform_input(x, self.cfg.input_transform)
            guide = self._pad(self.guide_of(t)) if self.cfg.guide_kernel == 1 else self.guide_of(self._pad(t))
            if self.compute_dtype is not None and not torch.is_grad_enabled():
                guide = guide.to(self.compute_dtype)  # rounded as the row streams keep it (kpcn.models.unet_rows)
            h = (h, guide)  # GuidedHead: the 1x1 conv of [upsample(h), guide] without building either at full size
        if self.cfg.kernel_scales == 1:
            return _bounded_softmax(self.head(h)[..., :h_in, :w_in], s)
        kernels, alphas, gains, albedo = [], [], [], None
        for level in range(self.cfg.kernel_scales):
            z = self.head(h) if level == 0 else self.heads[level - 1](decoded[level - off])
            nb = self.head_layout[1] if level == 0 else z.shape[1] - kk
            alpha, gain = blend_weights(z[:, kk:kk + nb])
            alphas.append(alpha)
            gains.append(gain)
            kernels.append(_bounded_softmax(z[:, :kk], s))
            if level == 0 and self.albedo_kernel:
                za = z[:, kk + nb:].float()
                bound = albedo_bound(self._pad(x[:, ALBEDO_VARIANCE:ALBEDO_VARIANCE + 1].float()), self.cfg.albedo_clamp) \
                    if self.cfg.albedo_clamp else None
                albedo = (_bounded_softmax(za[:, :-1], s), gate_of(za[:, -1:], self.cfg.albedo_gate_gain), bound)
            del z
        return MultiScaleKernels(tuple(kernels), tuple(alphas), (h_in, w_in),
                                 tuple(gains) if self.cfg.band_gain else None, albedo)

    def filter_albedo(self, albedo: torch.Tensor, ks: MultiScaleKernels) -> torch.Tensor:
        """The albedo ``(B, 3, H, W)`` the colour is remodulated with: ``max(a + g·(K_a ⊛ a - a), 0)`` with the
        albedo kernels and gates of ``ks`` (:meth:`kernels`), at the frame padded to the alignment (replicate) as
        the colour is filtered; ``albedo`` itself where ``ks`` has none."""
        if not isinstance(ks, MultiScaleKernels) or ks.albedo is None:
            return albedo
        (h, w), a = ks.size, self.cfg.alignment
        padded = F.pad(albedo, (0, (-w) % a, 0, (-h) % a), mode="replicate") if (h % a or w % a) else albedo
        weights, gate, bound = ks.albedo
        filtered = self.apply_albedo(padded.contiguous(), weights)
        return gated_albedo(padded, filtered, gate, bound)[..., :h, :w]


class UNetKPCN(DenoiserModel):
    """Kernel-predicting U-Net, one per branch of the input spec (see the module docstring)."""

    zero_preserving = True
    kernel_padding = "replicate"  # every level's kernels, and the padding to the alignment
    #: the encoder and decoder convs can run in bfloat16 (autocast; CPUs with AMX or AVX-512 BF16 run
    #: them 3-5x faster than float32): heads, softmax and kernels stay float32
    compute_dtypes = (torch.float32, torch.bfloat16)

    def __init__(self, config: UNetConfig) -> None:
        super().__init__(config)
        self.uses_frame_context = config.summary_channels > 0
        for b in self.branches:
            self.add_module(b, UNetBranch(config, config.albedo_kernel if b == "diffuse" else 0))

    def _on_compute_dtype(self, dtype: torch.dtype) -> None:
        for b in self.branches:
            getattr(self, b).compute_dtype = None if dtype == torch.float32 else dtype

    @property
    def receptive_radius(self) -> int:
        if self.config.kernel_scales == 1:
            return max(self.config.network_radius, self.config.kernel_radius)
        return self.config.network_radius + self.config.kernel_radius

    @property
    def alignment(self) -> int:
        return self.config.alignment

    @property
    def convex_kernels(self) -> bool:
        """One full-resolution kernel: convex; the multi-scale combination ``f + α·U(o - D f)`` is not."""
        return self.config.kernel_scales == 1

    @property
    def streams_rows(self) -> bool:
        """``stem: half``: a frame can be run a band of rows at a time (:meth:`row_stream`)."""
        return self.config.offset == 1

    def channel_groups(self) -> dict[str, tuple[tuple[int, ...] | None, tuple[int, ...]]]:
        return {f"{b}.{k}": v for b in self.branches for k, v in getattr(self, b).channel_groups().items()}

    def row_stream(self, name: str, height: int, width: int, device=None):
        """A :class:`~kpcn.models.unet_rows.RowStream` of branch ``name`` for a ``height × width`` frame."""
        from .unet_rows import RowStream

        return RowStream(getattr(self, name), height, width, device)

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

    def forward(self, inputs: dict[str, torch.Tensor], context=None) -> dict[str, torch.Tensor]:
        """:meth:`DenoiserModel.forward`; with ``albedo_kernel`` the diffuse branch's kernels also filter the
        albedo, the colour is remodulated with that (:meth:`UNetBranch.filter_albedo`) and it is returned as
        ``"albedo"``."""
        if not self.config.albedo_kernel or inputs.get("diffuse") is None:
            return super().forward(inputs, context)
        check_inputs(self, inputs)
        net, x = self.diffuse, inputs["diffuse"]
        ks = net.kernels(x, (context or {}).get("diffuse"))
        out = {"diffuse": net.apply_kernels(x[:, :3].contiguous(), ks)}
        albedo = net.filter_albedo(inputs["albedo"], ks)
        del ks
        for b in self.branches:
            if b != "diffuse":
                out[b] = self.run_branch(b, inputs[b], context) if inputs.get(b) is not None else None
        color = self.input_spec.reconstruct({b: v for b, v in out.items() if v is not None}, {**inputs, "albedo": albedo})
        for b in self.branches:
            if out.get(b) is None:
                out[b] = torch.zeros_like(color)
        out["color"], out["albedo"] = color, albedo
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


register_weights("unet_kpcn", "fast", "unet_fast.safetensors",
                 description="U-Net at half resolution, multi-scale 5x5 kernels, 22 k multiply-adds per pixel "
                             "(configs/unet_fast.yaml): 28 procedural 128x128 scenes on the CPU, then fine-tuned on a GPU on "
                             "72 procedural 256x256 scenes, each with its converged reference as an input")
register_weights("unet_kpcn", "fast4", "unet_fast4.safetensors",
                 description="unet_kpcn:fast with a fourth kernel level at 1/8 resolution (footprint up to 40 px), "
                             "22 k multiply-adds per pixel (configs/unet_fast4.yaml): fine-tuned from unet_kpcn:fast on the "
                             "CPU on 24 + 38 procedural 256x256 scenes, converged inputs from the 2048-spp references (four runs)")
register_weights("unet_kpcn", "wide", "unet_wide.safetensors",
                 description="unet_kpcn:fast4 twice as wide at every level (48/64/96/128), 79 k multiply-adds per pixel, "
                             "its convolutions in bfloat16 where the CPU has it (configs/unet_wide.yaml): widened from "
                             "unet_kpcn:fast4 and trained 76000 steps on the CPU on 87 + 24 procedural 256x256 scenes, "
                             "the last 48000 with the log_msssim loss, the last 20000 on albedo revision 2, the last "
                             "12000 with converged pairs counting only their converged pixels")
register_weights("unet_kpcn", "wide64", "unet_wide64.safetensors",
                 description="unet_kpcn:wide widened to 64/96/128/160 channels, 146 k multiply-adds per pixel, its "
                             "convolutions in bfloat16 where the CPU has it (configs/unet_wide64.yaml): widened from "
                             "unet_kpcn:wide, trained about 3800 steps (batch 32 of 128²) on one GPU on 78 procedural "
                             "256x256 scenes rendered there, then 13000 steps (batch 4) on the CPU on 87 + 24 scenes")
register_weights("unet_kpcn", "wide64g", "unet_wide64g.safetensors",
                 description="unet_kpcn:wide64 with band_gain (a per-pixel gain of each blending level's high band), "
                             "146 k multiply-adds per pixel, its convolutions in bfloat16 where the CPU has it "
                             "(configs/unet_wide64g.yaml): the gains added to unet_kpcn:wide64 at 1 and trained "
                             "12000 steps (batch 4 of 128²) on the CPU on 87 + 24 procedural 256x256 scenes")
register_weights("unet_kpcn", "wide64a", "unet_wide64a.safetensors",
                 description="unet_kpcn:wide64u with albedo_kernel 3 (the diffuse branch also predicts a 3x3 kernel and a "
                             "gate per pixel, and the colour is remodulated with that filtered albedo instead of the "
                             "noisy one), 126 k multiply-adds per pixel (configs/unet_wide64a.yaml): added to wide64u at "
                             "gate 0 and trained 9000 steps (batch 4) on the CPU on 87 + 24 scenes; +0.25 dB over "
                             "wide64u at 4 spp, 1.0-1.1x its 1080p time")
register_weights("unet_kpcn", "wide64u", "unet_wide64u.safetensors", default=True,
                 description="unet_kpcn:wide64g with up_kernel 1 (each decoder level's first conv reads the coarser "
                             "level through a 1x1 at its own resolution), 126 k multiply-adds per pixel, its convolutions "
                             "in bfloat16 where the CPU has it (configs/unet_wide64u.yaml): wide64g trained about 2400 "
                             "steps (batch 32 of 128²) on one GPU on 65 procedural 256x256 scenes rendered there, then "
                             "turned into up_kernel 1 and trained 7000 steps (batch 4) on the CPU on 87 + 24 scenes")
