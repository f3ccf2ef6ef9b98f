"""Row-band inference for the ``stem: half`` U-Net: its full-resolution work done a band of rows at a time.

A ``stem: half`` :class:`~kpcn.models.unet_branch.UNetBranch` does three things at full resolution: it pools
(and transforms) the features, computes the guide of them (a 1×1 or a small conv), and at the end turns the upsampled
head plus the guide into kernels, applies them and blends in the coarser levels. Each is a few
element-wise passes over up to 27 channels: on a 1920×1080 frame, hundreds of MB per pass, so the
whole-frame path is bounded by memory traffic, not arithmetic, and holds every pass's result at once.
:class:`RowStream` does those steps on bands of rows small enough to stay in the CPU's cache, and keeps
only what the later steps need (the guide, the pooled features, the colour and any other layers to
filter with the same kernels):

1. :meth:`RowStream.feed`: the features of a band of rows of the padded frame -> pooled and
   transformed features (half resolution), the guide and the colour;
2. :meth:`RowStream.run`: the network at half resolution on the whole frame (so the global summary is
   the frame's), the coarse part of the head, and the coarser kernel levels filtered and combined;
3. :meth:`RowStream.rows`: the output rows of a band (the finest kernels, their application, the blend
   with the coarser levels).

The result equals :meth:`UNetBranch.forward` on the whole frame to float rounding (what the bands read
beyond their rows is clamped at the frame's edges exactly as the whole-frame ops clamp;
``tests/test_unet_rows.py``).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ..ops.kernel_apply import kernel_apply_padded
from ..ops.fused import (feed_native, guided_blend_native, guided_softmax_native, softmax_apply_native,
                         upsample_guide_native)
from .kernel_heads import (_softmax_weights, albedo_bound, blend_weights, combine_levels, gate_of, gated_albedo,
                           radiance_mixed)
from .guided import apply_guided, guide_pyramid, guided_weights
from .layers import conv1x1, conv1x1_lowp, pool2, transform_input, upsample2
from .unet_branch import ALBEDO_VARIANCE, UNetBranch

__all__ = ["RowStream", "BAND_ROWS", "clamped_rows"]

#: rows per band: 32 rows of a 1920-wide frame are about 7 MB per 27-channel tensor (the cache holds a few)
BAND_ROWS = 32


def clamped_rows(t: torch.Tensor, a: int, b: int) -> torch.Tensor:
    """Rows ``[a, b)`` of ``(B, C, H, W)``, indices clamped to ``[0, H)`` (edge rows repeated)."""
    h = t.shape[-2]
    if 0 <= a and b <= h:
        return t[..., a:b, :]
    idx = torch.arange(a, b, device=t.device).clamp_(0, h - 1)
    return t.index_select(-2, idx)


def _apply(padded: torch.Tensor, weights, k: int, mix: torch.Tensor | None = None) -> torch.Tensor:
    """The kernels ``weights = (unnormalised weights, their sum or None)`` applied to a ``padded`` signal; with a
    mixing weight ``mix`` (``UNetConfig.radiance_mix``) as :func:`~kpcn.models.kernel_heads.radiance_mixed` does."""
    if mix is not None:
        return radiance_mixed(lambda x, wt: _apply(x, wt, k), padded, weights, mix)
    w, norm = weights
    f = kernel_apply_padded(padded, w, k)
    return f.div_(norm) if norm is not None else f


def _softmax_apply(logits: torch.Tensor, padded: torch.Tensor, k: int, s: float,
                   mix: torch.Tensor | None = None) -> torch.Tensor:
    """The bounded-softmax kernels of ``logits`` ``(1, k², H, W)`` (a temporary: made weights in place on the PyTorch
    path) applied to ``padded`` ``(1, C, H + 2r, W + 2r)``: in one native pass where it applies
    (:func:`~kpcn.ops.fused.softmax_apply_native`), else :func:`_softmax_weights` and :func:`_apply`."""
    if mix is None:
        out = softmax_apply_native(logits, padded, k, s)
        if out is not None:
            return out
    return _apply(padded, _softmax_weights(logits, s, inplace=True), k, mix)


def _stacked(signals: dict[str, torch.Tensor]) -> torch.Tensor:
    """The signals ``{key: (1, 3, H, W)}`` side by side ``(1, 3 n, H, W)``: one application of shared kernels."""
    values = list(signals.values())
    return values[0] if len(values) == 1 else torch.cat(values, dim=1)


def _unstacked(keys, t: torch.Tensor) -> dict[str, torch.Tensor]:
    return dict(zip(keys, t.split(3, dim=1)))


class RowStream:
    """One ``stem: half`` branch over one frame of ``height × width`` pixels, a band of rows at a time.

    Args:
        branch: the :class:`UNetBranch` (its config must have ``stem: half``).
        height, width: the frame's size (unpadded); the stream works on the frame padded (replicate) to
            the branch's alignment, ``padded_size``.
        device, dtype: of the buffers.

    ``feed`` every band of the padded frame in order (``rows`` ``[r0, r1)``, ``r0`` and ``r1`` even),
    then ``run`` once, then ask for output bands with ``rows``. Besides the beauty (the branch colour,
    key :attr:`BEAUTY`), ``feed`` can take other three-channel layers in the branch's space (light
    groups, AOVs): ``rows`` returns each filtered with the same kernels and the same multi-scale
    blend. Inference only (no autograd). A branch with albedo kernels (``UNetConfig.albedo_kernel``) is also
    fed the albedo, and ``rows`` returns the albedo it remodulates with (key :attr:`ALBEDO`).
    """

    BEAUTY = "beauty"
    ALBEDO = "albedo"

    def __init__(self, branch: UNetBranch, height: int, width: int, device=None, dtype=torch.float32) -> None:
        cfg = branch.cfg
        if cfg.offset != 1:
            raise ValueError("RowStream needs a U-Net with stem: half")
        self.branch, self.cfg = branch, cfg
        a = cfg.alignment
        self.height, self.width = height, width
        self.padded_size = (-(-height // a) * a, -(-width // a) * a)
        hp, wp = self.padded_size
        c = branch.enc[0][0].in_channels
        self._kw = dict(device=device, dtype=dtype)
        # channels_last, the layout the network runs in: each band is transposed while it is in cache
        # in the conv stack's dtype (bfloat16: half the memory; its first conv would round them to it all the same)
        self._pooled = torch.empty(1, c, hp // 2, wp // 2, memory_format=torch.channels_last, device=device,
                                   dtype=branch.compute_dtype or dtype)
        # the guide in the conv stack's dtype too (bfloat16: half the memory, a quarter GB per branch at 3840x2160)
        self._guide = torch.empty(1, cfg.guide_channels, hp, wp, device=device, dtype=branch.compute_dtype or dtype)
        self._full: dict[str, torch.Tensor] = {}  # each signal at full resolution
        self._half: dict[str, torch.Tensor] = {}  # ... and pooled to half (the coarser kernel levels)
        # the colours' pooling to the coarser kernel levels: the whole-frame path's own (UNetConfig.radiance_pool)
        self._pool = getattr(branch.apply_kernels, "pool", pool2)
        self._fed = 0
        self._ctx, self._next = None, 0  # the guide's rows in waiting (guide_kernel > 1; _feed_guide)
        self._low, self._low_bias = None, None
        self._fr_low = None  # fullres_channels: the first stage's half-resolution part (run())
        #: the coarser kernel levels combined at half resolution, every signal side by side (:func:`_stacked` order)
        self._coarse: torch.Tensor | None = None
        #: the albedo at full resolution (a branch with albedo kernels), and with albedo_clamp its bound as a 4th channel
        clamp = bool(branch.albedo_kernel and cfg.albedo_clamp)
        self._albedo = torch.empty(1, 3 + clamp, hp, wp, **self._kw) if branch.albedo_kernel else None
        #: ``edge_upsample``: the frame's normal at full resolution (the blend's guide), and pooled to half in run()
        self._normal = torch.empty(1, 3, hp, wp, **self._kw) if cfg.edge_upsample else None
        self._normal_half = None
        self._normal_shared = False  # share_normal(): another stream's buffer, which that stream fills
        #: a dict that streams over the same frame share, holding the last band's guided tap weights (they follow from
        #: the normal alone): the second branch's stream reuses the first's (set by the caller; None: not shared)
        self.guide_weights_cache: dict | None = None

    def feed(self, r0: int, x: torch.Tensor, layers: dict[str, torch.Tensor] | None = None,
             albedo: torch.Tensor | None = None, normal: torch.Tensor | None = None) -> None:
        """Features ``(1, C, r1 - r0, padded width)`` of rows ``[r0, r1)`` of the padded frame (bands in order),
        ``layers``: other ``(1, 3, r1 - r0, padded width)`` signals to filter (the same keys every band),
        ``albedo`` ``(1, 3, r1 - r0, padded width)``: the same rows of the albedo (a branch with albedo kernels
        needs it), and ``normal``: the same rows of the frame's normal (a branch with ``edge_upsample`` needs it)."""
        n = x.shape[-2]
        if r0 != self._fed or n % 2 or x.shape[-1] != self.padded_size[1]:
            raise ValueError(f"RowStream.feed: expected an even number of rows from row {self._fed}, "
                             f"{self.padded_size[1]} wide; got rows {r0}..{r0 + n}, {x.shape[-1]} wide")
        if self._normal is not None:
            if normal is None:
                raise ValueError("RowStream.feed: this branch guides its blend by the normal (edge_upsample): give "
                                 "each band's normal")
            if not self._normal_shared:
                self._normal[..., r0:r0 + n, :].copy_(normal).clamp_(-1.0, 1.0)
        if self._albedo is not None:
            if albedo is None:
                raise ValueError("RowStream.feed: this branch filters the albedo (albedo_kernel): give each band's albedo")
            self._albedo[:, :3, r0:r0 + n, :] = albedo
            if self._albedo.shape[1] > 3:
                self._albedo[:, 3:, r0:r0 + n, :] = albedo_bound(x[:, ALBEDO_VARIANCE:ALBEDO_VARIANCE + 1].float(),
                                                                 self.cfg.albedo_clamp)
        signals = {self.BEAUTY: x[:, :3], **(layers or {})}
        if r0 == 0:
            hp, wp = self.padded_size
            self._full = {k: torch.empty(1, 3, hp, wp, **self._kw) for k in signals}
            self._half = {k: torch.empty(1, 3, hp // 2, wp // 2, **self._kw) for k in signals}
        elif signals.keys() != self._full.keys():
            raise ValueError(f"RowStream.feed: layers {sorted(signals)} differ from the first band's {sorted(self._full)}")
        kind = self.cfg.input_transform
        pooled = self._pooled[..., r0 // 2:(r0 + n) // 2, :]
        g = self.branch.guide if self.cfg.guide_kernel == 1 else None  # a wider guide trails the bands (_feed_guide)
        if g is None or not feed_native(x, kind, g.weight, g.bias, self._guide[..., r0:r0 + n, :], pooled):
            self._feed_guide(r0, transform_input(x, kind))
            pooled.copy_(transform_input(pool2(x), kind))
        for k, v in signals.items():
            self._full[k][..., r0:r0 + n, :] = v
            self._half[k][..., r0 // 2:(r0 + n) // 2, :] = self._pool(v)
        self._fed = r0 + n

    def share_normal(self, other: "RowStream") -> None:
        """Read the frame's normal from ``other``'s buffer (a stream of another branch over the same frame, fed every
        band too: it fills the buffer, this stream only reads it after :meth:`run`) instead of keeping a copy: 25 MB
        less a branch at 1920×1080. Before the first :meth:`feed`; a no-op where either stream reads no normal."""
        if self._fed:
            raise ValueError("RowStream.share_normal: call it before the first feed")
        if self._normal is not None and other._normal is not None and other._normal.shape == self._normal.shape \
                and other is not self:
            self._normal, self._normal_shared = other._normal, True

    def _feed_guide(self, r0: int, t: torch.Tensor) -> None:
        """The guide of the rows a band completes. A ``guide_kernel`` of ``2r + 1`` reads ``r`` rows each side, so
        the guide trails the bands by ``r`` rows: :attr:`_ctx` keeps the transformed rows the next band's first
        guide rows read (replicates of row 0 above the frame), and :meth:`run` finishes the last ``r`` rows."""
        r = self.cfg.guide_kernel // 2
        if not r:
            self._guide[..., r0:r0 + t.shape[-2], :] = self.branch.guide_of(t)
            return
        if r0 == 0:
            self._ctx, self._next = t[..., :1, :].expand(-1, -1, r, -1), 0
        ext = torch.cat([self._ctx, t], dim=-2)  # rows [next - r, r0 + n)
        self._guide_rows(ext)
        self._ctx = ext[..., -2 * r:, :]

    def _guide_rows(self, ext: torch.Tensor) -> None:
        """Guide rows ``[next, next + len(ext) - 2r)`` of transformed rows ``ext`` ``[next - r, ...)``."""
        r = self.cfg.guide_kernel // 2
        m = ext.shape[-2] - 2 * r
        if m <= 0:
            return
        self._guide[..., self._next:self._next + m, :] = self.branch.guide_of(ext, pad_rows=False)
        self._next += m

    def run(self, summary: torch.Tensor | None = None) -> None:
        """The network at half resolution (all rows must have been fed); ``summary``: a given global summary."""
        if self._fed != self.padded_size[0]:
            raise ValueError(f"RowStream.run: rows 0..{self._fed} of {self.padded_size[0]} fed")
        net, cfg = self.branch, self.cfg
        r = cfg.guide_kernel // 2
        if r:  # the last r guide rows read r replicates of the frame's last row below it
            self._guide_rows(torch.cat([self._ctx, self._ctx[..., -1:, :].expand(-1, -1, r, -1)], dim=-2))
            self._ctx = None
        h, decoded = net.decode(net.encode_from(self._release_pooled()), summary)
        # the guided head's half-resolution part; in reduced precision kept as the product in that dtype (half the
        # memory), converted and given its bias a band at a time in rows(): the same values
        head = net.head
        if h.dtype == torch.float32:
            self._low, self._low_bias = head.coarse_part(h), None
        else:
            self._low, self._low_bias = conv1x1_lowp(h, head.weight[:, :h.shape[1]]), head.bias
        if net.fullres is not None:
            self._fr_low = net.fullres.inp.coarse_part(h)
        if cfg.kernel_scales > 1:  # the coarser kernel levels, combined into one half-resolution result per signal
            kc = cfg.level_kernel(1)
            kk, r = kc**2, kc // 2
            colour = _stacked(self._half)  # every signal filtered with the same kernels at once
            filtered, alphas, gains = [], [], []
            for level in range(1, cfg.kernel_scales):
                hd, d = net.heads[level - 1], decoded[level - 1]
                # the kernel logits and the other channels as two products: the logits contiguous, made weights in place
                extra = conv1x1(d, hd.weight[kk:], hd.bias[kk:]) if hd.out_channels > kk else None
                nb = hd.out_channels - kk - net.mix
                alpha, gain = blend_weights(extra[:, :nb]) if nb else (None, None)
                alphas.append(alpha)
                gains.append(gain)
                mix = torch.sigmoid(extra[:, nb:]) if net.mix else None
                if level > 1:
                    colour = self._pool(colour)
                padded = F.pad(colour, (r, r, r, r), mode="replicate") if r else colour
                filtered.append(_softmax_apply(conv1x1(d, hd.weight[:kk], hd.bias[:kk]), padded, kc, cfg.logit_scale,
                                               mix))
            guides = None
            if self._normal is not None:  # the normal's pyramid from half resolution on (the levels combined here)
                guides = self._normal_pyramid(cfg.kernel_scales - 1)
                self._normal_half = guides[0]
            # gains: None each without band_gain
            self._coarse = combine_levels(filtered, alphas, gains, guides, float(cfg.edge_upsample))
        self._half = {}

    def _normal_pyramid(self, levels: int) -> tuple[torch.Tensor, ...]:
        """The normal pooled to half resolution and ``levels - 1`` coarser levels; computed once for the streams
        that share the normal buffer (:meth:`share_normal`) and the cache (:attr:`guide_weights_cache`)."""
        cache, key = self.guide_weights_cache, ("pyramid", levels, self._normal.data_ptr(), tuple(self._normal.shape))
        if cache is not None and key in cache:
            return cache[key]
        guides = tuple(guide_pyramid(pool2(self._normal), levels))
        if cache is not None:
            cache[key] = guides
        return guides

    @property
    def signals(self) -> dict[str, torch.Tensor]:
        """What was fed, ``{key: (1, 3, padded height, padded width)}``: the beauty and every layer."""
        return self._full

    def _release_pooled(self) -> torch.Tensor:
        """The pooled features, no longer held here: the encoder frees them after its first conv."""
        pooled, self._pooled = self._pooled, None
        return pooled

    def rows(self, r0: int, r1: int) -> dict[str, torch.Tensor]:
        """Output rows ``[r0, r1)`` (even) of the padded frame, ``{key: (1, 3, r1 - r0, padded width)}`` in the
        branch's space: the beauty (:attr:`BEAUTY`) and every layer fed."""
        if self._low is None:
            raise ValueError("RowStream.rows: call run() first")
        cfg = self.cfg
        hp = self.padded_size[0]
        kk, r = cfg.kernel_size**2, cfg.kernel_size // 2
        m = 2 if cfg.kernel_scales > 1 else 0  # the blend's 2x2 pool and bilinear upsampling read 2 rows further
        e0, e1 = max(r0 - m, 0), min(r1 + m, hp)
        low = clamped_rows(self._low, e0 // 2 - 1, e1 // 2 + 1)
        if self._low_bias is not None:
            low = low.float().add_(self._low_bias.view(1, -1, 1, 1))
        guide, head = self._guide[..., e0:e1, :], self.branch.head
        w_guide = head.weight[:, head.in_channels - guide.shape[1]:, 0, 0]
        _, nb, na, nm = self.branch.head_layout
        # every signal's rows, side by side: filtered with the same kernels at once
        colour = _stacked({key: F.pad(clamped_rows(full, e0 - r, e1 + r), (r, r, 0, 0), mode="replicate") if r else
                           full[..., e0:e1, :] for key, full in self._full.items()})
        # the kernels made and applied in one native pass where nothing else adds to their logits; then only the
        # head's other channels (the blend's weights, the albedo's logits) are made as a band
        filtered = guided_softmax_native(low, guide, w_guide, colour, cfg.kernel_size, cfg.logit_scale) \
            if self._fr_low is None and not nm else None
        if filtered is not None:  # the library that just ran takes the rest too (None only where there is none)
            tail = upsample_guide_native(low[:, kk:], guide, w_guide[kk:]) if low.shape[1] > kk else None
        else:
            z = upsample_guide_native(low, guide, w_guide)
            if z is None:  # the PyTorch path: the same, in passes
                z = head.add_guide_part_(upsample2(low, context_rows=True), guide)
            if self._fr_low is not None:
                z = z.add_(self._fullres_rows(e0, e1))
            tail = z[:, kk:]
        alpha, gain = blend_weights(tail[:, :nb]) if cfg.kernel_scales > 1 else (None, None)
        mix = torch.sigmoid(tail[:, nb + na:]) if nm else None
        i0, n = r0 - e0, r1 - r0
        out = {}
        if self._albedo is not None:  # its logits made weights in place (a slice of this band's own tail)
            out[self.ALBEDO] = self._albedo_rows(tail[:, nb:nb + na], e0, e1)[..., i0:i0 + n, :]
        if filtered is None:  # z is this band's own: its logits made weights in place on the PyTorch path
            filtered = _softmax_apply(z[:, :kk], colour, cfg.kernel_size, cfg.logit_scale, mix)
        coarse = clamped_rows(self._coarse, e0 // 2, e1 // 2) if alpha is not None else None
        if self._normal is not None and alpha is not None and gain is not None:  # the blend in one native pass
            blended = guided_blend_native(filtered, coarse, self._normal[..., e0:e1, :],
                                          self._normal_half[..., e0 // 2:e1 // 2, :], float(cfg.edge_upsample),
                                          alpha, gain, i0, n)
            if blended is not None:
                out.update(_unstacked(self._full, blended))
                return out
        # the blend's upsampling guided by the normal (edge_upsample), as in the whole frame (and where the native
        # library is missing): the tap weights once a band (and once for every stream that shares the cache)
        wts = None
        if self._normal is not None and alpha is not None:
            cache, key = self.guide_weights_cache, (e0, e1, self.padded_size, float(cfg.edge_upsample))
            if cache is not None and cache.get("key") == key:
                wts = cache["weights"]
            else:
                wts = guided_weights(self._normal[..., e0:e1, :], self._normal_half[..., e0 // 2:e1 // 2, :],
                                     float(cfg.edge_upsample))
                if cache is not None:
                    cache.update(key=key, weights=wts)
        coarse_of = _unstacked(self._full, coarse) if coarse is not None else {}
        for key, f in _unstacked(self._full, filtered).items():
            if alpha is None:
                out[key] = f
                continue
            df = pool2(f)
            corr = coarse_of[key] - df
            if wts is not None:
                both = apply_guided(torch.cat([df, corr], 1), wts)[..., i0:i0 + n, :]
                u_df, up = both[:, :3], both[:, 3:]
            else:
                u_df = upsample2(df)[..., i0:i0 + n, :] if gain is not None else None
                up = upsample2(corr)[..., i0:i0 + n, :]
            fi = f[..., i0:i0 + n, :]
            if gain is not None:  # the high band scaled by β: f - (1 - β)(f - U D f) = lerp(U D f, f, β)
                fi = torch.lerp(u_df, fi, gain[..., i0:i0 + n, :])
            out[key] = fi.addcmul(alpha[..., i0:i0 + n, :], up)
        return out

    def _fullres_rows(self, e0: int, e1: int) -> torch.Tensor:
        """Rows ``[e0, e1)`` (even) of the full-resolution level's logits (``fullres_channels``): its first stage on
        two more rows each side (edge rows repeated, as the whole frame's replicate padding repeats them), its 3×3
        on those."""
        fr = self.branch.fullres
        low = clamped_rows(self._fr_low, e0 // 2 - 2, e1 // 2 + 2)
        f = fr.inp.add_guide_part_(upsample2(low, context_rows=True), clamped_rows(self._guide, e0 - 2, e1 + 2))
        return fr.tail(f.relu_(), lambda: self.branch._lowp(f), pad_rows=False)[..., 1:-1, :]

    def _albedo_rows(self, za: torch.Tensor, e0: int, e1: int) -> torch.Tensor:
        """Rows ``[e0, e1)`` of the albedo the colour is remodulated with, from the head's albedo logits and gate
        ``za`` over those rows (:meth:`UNetBranch.filter_albedo`, a band at a time)."""
        ka = self.branch.albedo_kernel
        r = ka // 2
        albedo = self._albedo[:, :3]
        padded = F.pad(clamped_rows(albedo, e0 - r, e1 + r), (r, r, 0, 0), mode="replicate") if r else \
            albedo[..., e0:e1, :]
        gate = gate_of(za[:, -1:], self.cfg.albedo_gate_gain)
        # za is this band's own (a slice of z): its logits made weights in place
        filtered = _softmax_apply(za[:, :-1], padded, ka, self.cfg.logit_scale)
        bound = self._albedo[:, 3:, e0:e1, :] if self._albedo.shape[1] > 3 else None
        return gated_albedo(albedo[..., e0:e1, :], filtered, gate, bound)
