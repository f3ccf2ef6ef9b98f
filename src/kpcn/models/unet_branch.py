"""One branch of :class:`~kpcn.models.unet.UNetKPCN`: :class:`UNetBranch`, the encoder, global summary, decoder
and kernel heads that turn a branch's ``(B, C, H, W)`` features into its filtered colour (the architecture is
described in :mod:`kpcn.models.unet`; its row-band inference is :mod:`kpcn.models.unet_rows`)."""
from __future__ import annotations

import contextlib
import functools

import torch
import torch.nn.functional as F
from torch import nn

from ..features import FEATURE_VAR
from ..inputs import get_input_spec
from ..ops.kernel_apply import KernelApply
from .kernel_heads import (GuidedHead, MultiScaleApply, MultiScaleKernels, _bounded_softmax, albedo_bound,
                           blend_weights, gate_of, gated_albedo)
from .guided import guide_pyramid
from .layers import Conv1x1, ReLU, UpAddConv, UpCatConv, kernel_prior_bias, pool2, relu_, transform_input
from .unet_config import RADIANCE_MIX_INIT, UNetConfig

__all__ = ["UNetBranch", "ALBEDO_VARIANCE"]

#: the kpcn_split features' albedo-variance channel (kpcn.features: the variances of normal, albedo and depth)
ALBEDO_VARIANCE = FEATURE_VAR.start + 1


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


class DeepBlock(nn.Module):
    """A residual block of two 3×3 convs at one level: ``relu(h + conv2(relu(conv1(h))))``, ``(B, C, H, W)`` ->
    ``(B, C, H, W)``. ``conv2`` starts at zero, so a new block passes a non-negative (post-ReLU) ``h`` unchanged."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        nn.init.kaiming_normal_(self.conv1.weight, nonlinearity="relu")
        for t in (self.conv1.bias, self.conv2.weight, self.conv2.bias):
            nn.init.zeros_(t)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return relu_(h + self.conv2(relu_(self.conv1(h))))


class FullResLevel(nn.Module):
    """``UNetConfig.fullres_channels``: a full-resolution decoder level whose output adds to the full-resolution
    head's logits, ``out(relu(conv3x3(relu(inp([bilinear_up2(coarse), guide])))))``: ``coarse`` ``(B, Cc, h, w)``
    (the finest decoder level), ``guide`` ``(B, Cg, 2h, 2w)`` -> ``(B, out, 2h, 2w)`` float32. ``inp`` is a
    :class:`GuidedHead` (its coarse part runs at half resolution), the 3×3 pads by replicating the edge, and
    ``out`` starts at zero: a level added to a trained file leaves its output as it was."""

    def __init__(self, coarse: int, guide: int, width: int, out: int) -> None:
        super().__init__()
        self.inp = GuidedHead(coarse + guide, width, 1)
        self.conv = nn.Conv2d(width, width, 3)
        self.out = Conv1x1(width, out, 1)
        for m in (self.inp, self.conv):
            nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
            nn.init.zeros_(m.bias)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, pair, lowp=contextlib.nullcontext) -> torch.Tensor:
        """``pair`` ``(coarse, guide)``; ``lowp()``: the context the 3×3 runs in (the branch's reduced precision)."""
        return self.tail(relu_(self.inp(pair)), lowp)

    def tail(self, f: torch.Tensor, lowp=contextlib.nullcontext, pad_rows: bool = True) -> torch.Tensor:
        """The 3×3 and the output of the first stage's ``relu`` ``f`` ``(B, width, H, W)``; with ``pad_rows=False``
        only the columns are padded (a band that brings a row each side: ``H - 2`` rows out)."""
        with lowp():
            f = relu_(self.conv(F.pad(f, (1, 1, 1, 1) if pad_rows else (1, 1, 0, 0), mode="replicate")))
        return self.out(f if f.dtype == torch.float32 or not torch.is_grad_enabled() else f.float()).float()


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
        #: UNetConfig.deep_blocks: residual blocks after the encoder's coarsest level
        self.deep = nn.ModuleList(DeepBlock(w[-1]) for _ in range(cfg.deep_blocks))
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
        ka = self.albedo_kernel
        #: ``radiance_mix``: every level's head ends in one more channel, the logit of its mixing weight γ
        self.mix = int(cfg.radiance_mix)
        #: channels of the full-resolution head: the kernel logits, the blend (α, β), the albedo logits and gate,
        #: the mixing weight's logit
        self.head_layout = self.head_segments(0)
        self.head = self._make_head(w[0] + (cfg.guide_channels if off else 0), sum(self.head_layout),
                                    GuidedHead if off else Conv1x1)
        if ka:
            with torch.no_grad():  # the albedo kernels start as the colour's do (a Gaussian), gated shut (g = 0)
                self.head.bias[k * k + self.head_layout[1]:][: ka * ka].copy_(
                    kernel_prior_bias(ka, cfg.init_sigma, cfg.logit_scale))
        self.apply_albedo = KernelApply(ka, "replicate") if ka else None
        #: UNetConfig.fullres_channels: the full-resolution level added to the head's logits (None: off)
        self.fullres = FullResLevel(w[0], cfg.guide_channels, cfg.fullres_channels, sum(self.head_layout)) \
            if off and cfg.fullres_channels else None
        # kernel level lv (resolution 1/2**lv) reads the decoder level lv - off
        kc = cfg.level_kernel(1)
        self.heads = nn.ModuleList(self._make_head(w[lv - off], sum(self.head_segments(lv)), k=kc)
                                   for lv in range(1, n))
        self.apply_kernels = KernelApply(k, "replicate") if n == 1 else \
            MultiScaleApply(k, cfg.alignment, radiance=cfg.radiance_pool, coarse_kernel=kc)
        #: the conv stack's dtype (None: float32); see :meth:`UNetKPCN.set_compute_dtype`
        self.compute_dtype: torch.dtype | None = None

    def head_segments(self, level: int) -> tuple[int, int, int, int]:
        """The output channels of kernel level ``level``'s head, in order: the kernel logits, the blend (α, and β
        with ``band_gain``; none on the coarsest level), the albedo kernel's logits and gate (level 0 only), the
        mixing weight's logit (``radiance_mix``)."""
        cfg, ka = self.cfg, self.albedo_kernel
        blend = (2 if cfg.band_gain else 1) if level < cfg.kernel_scales - 1 else 0
        albedo = ka * ka + 1 if ka and level == 0 else 0
        return (cfg.level_kernel(level) ** 2, blend, albedo, self.mix)

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
        for i in range(cfg.deep_blocks):
            groups[f"deep.{i}.conv1"] = groups[f"deep.{i}.conv2"] = ((w[-1],), (w[-1],))
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
        if self.fullres is not None:
            f = cfg.fullres_channels
            groups["fullres.inp"] = ((f,), (w[0], cfg.guide_channels))
            groups["fullres.conv"] = ((f,), (f,))
            groups["fullres.out"] = (None, (f,))
        for lv in range(1, cfg.kernel_scales):
            groups[f"heads.{lv - 1}"] = (None, (w[lv - off],))
        return groups

    def _make_head(self, width: int, out: int, kind=None, k: int | None = None) -> nn.Conv2d:
        k, cfg = k or self.cfg.kernel_size, self.cfg
        head = (kind or Conv1x1)(width, out, 1)
        nn.init.kaiming_normal_(head.weight, nonlinearity="linear")
        with torch.no_grad():
            head.weight.mul_(cfg.out_init_gain)
            head.bias.zero_()
            head.bias[: k * k].copy_(kernel_prior_bias(k, cfg.init_sigma, cfg.logit_scale))
            if self.mix:  # the mixing weight's logit is the last channel
                head.bias[-1:].fill_(RADIANCE_MIX_INIT)
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
            for block in self.deep:
                h = block(h)
            feats[-1] = h
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

    def forward(self, x: torch.Tensor, summary: torch.Tensor | None = None,
                normal: torch.Tensor | None = None) -> torch.Tensor:
        return self.apply_kernels(x[:, :3].contiguous(), self.kernels(x, summary, normal))

    def guide_pyramid(self, normal: torch.Tensor | None) -> tuple[torch.Tensor, ...] | None:
        """``edge_upsample``: the frame's normal ``(B, 3, H, W)`` padded to the alignment (replicate, as the colour
        is) and its :func:`pool2` pyramid, one per kernel level; None without ``edge_upsample``."""
        cfg = self.cfg
        if not cfg.edge_upsample:
            return None
        if normal is None:
            raise ValueError("UNetBranch: edge_upsample guides the blend with the frame's normal: give it "
                             "(inputs['normal'], (B, 3, H, W))")
        return tuple(guide_pyramid(self._pad(normal.float().clamp(-1.0, 1.0)), cfg.kernel_scales))

    def kernels(self, x: torch.Tensor, summary: torch.Tensor | None = None, normal: torch.Tensor | None = None):
        """Softmax-normalised per-pixel kernels ``(B, k*k, H, W)`` (contiguous).

        With ``kernel_scales > 1``: a :class:`MultiScaleKernels` (kernels and blending
        weights of every level, at the padded size), which ``apply_kernels`` takes the same way;
        with ``edge_upsample`` it carries the guide pyramid of ``normal`` (:meth:`guide_pyramid`).
        """
        h_in, w_in = x.shape[-2:]
        h, decoded = self.decode(self.encode(x), summary)
        s, off = self.cfg.logit_scale, self.cfg.offset
        if off:  # full resolution: the finest level upsampled, beside the guide of the full-resolution features
            # a 1x1 conv and a ReLU are per pixel, so they commute with replicate padding: pad the
            # guide's few channels rather than the full-resolution features
            t = transform_input(x, self.cfg.input_transform)
            guide = self._pad(self.guide_of(t)) if self.cfg.guide_kernel == 1 else self.guide_of(self._pad(t))
            if self.compute_dtype is not None and not torch.is_grad_enabled():
                guide = guide.to(self.compute_dtype)  # rounded as the row streams keep it (kpcn.models.unet_rows)
            h = (h, guide)  # GuidedHead: the 1x1 conv of [upsample(h), guide] without building either at full size
        if self.cfg.kernel_scales == 1:
            return _bounded_softmax(self._full_head(h)[..., :h_in, :w_in], s)
        kernels, alphas, gains, mixes, albedo = [], [], [], [], None
        for level in range(self.cfg.kernel_scales):
            z = self._full_head(h) if level == 0 else self.heads[level - 1](decoded[level - off])
            kk = self.cfg.level_kernel(level) ** 2
            nb = self.head_layout[1] if level == 0 else z.shape[1] - kk - self.mix
            alpha, gain = blend_weights(z[:, kk:kk + nb])
            if self.mix:
                mixes.append(torch.sigmoid(z[:, -1:]))
            alphas.append(alpha)
            gains.append(gain)
            kernels.append(_bounded_softmax(z[:, :kk], s))
            if level == 0 and self.albedo_kernel:
                za = z[:, kk + nb:kk + nb + self.head_layout[2]].float()
                bound = albedo_bound(self._pad(x[:, ALBEDO_VARIANCE:ALBEDO_VARIANCE + 1].float()), self.cfg.albedo_clamp) \
                    if self.cfg.albedo_clamp else None
                albedo = (_bounded_softmax(za[:, :-1], s), gate_of(za[:, -1:], self.cfg.albedo_gate_gain), bound)
            del z
        return MultiScaleKernels(tuple(kernels), tuple(alphas), (h_in, w_in),
                                 tuple(gains) if self.cfg.band_gain else None, albedo,
                                 tuple(mixes) if self.mix else None, self.guide_pyramid(normal),
                                 float(self.cfg.edge_upsample))

    def _full_head(self, h):
        """The full-resolution head's output for its input ``h`` (with ``stem: half`` the pair (finest level,
        guide)), the full-resolution level's (``fullres_channels``) added."""
        z = self.head(h)
        return z if self.fullres is None else z + self.fullres(h, functools.partial(self._lowp, z))

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
