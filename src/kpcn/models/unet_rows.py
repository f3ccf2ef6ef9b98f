"""Row-band inference for the ``stem: half`` U-Net: its full-resolution work done a band of rows at a time.

A ``stem: half`` :class:`~kpcn.models.unet.UNetBranch` does three things at full resolution: it pools
(and transforms) the features, computes the 1×1 guide of them, and at the end turns the upsampled
head plus the guide into kernels, applies them and blends in the coarser levels. Each is a few
element-wise passes over up to 27 channels: on a 1920×1080 frame, hundreds of MB per pass, so the
whole-frame path is bounded by memory traffic, not arithmetic, and holds every pass's result at once.
:class:`RowStream` does those steps on bands of rows small enough to stay in the CPU's cache, and keeps
only what the later steps need (the guide, the colour, the pooled features):

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
from .layers import conv1x1, pool2, transform_input
from .unet import UNetBranch, _bounded_logits, _bounded_softmax, combine_levels

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


def _apply_softmax_kernels(padded: torch.Tensor, logits: torch.Tensor, s: float, k: int) -> torch.Tensor:
    """The kernels ``softmax(s tanh(logits / s))`` applied to ``padded`` (grown by ``k // 2``), normalised
    after the application (3 channels to divide, not ``k*k``); equal to normalising first to rounding."""
    if s > 80:  # exp of logits in [-s, s] could overflow: the ordinary softmax
        return kernel_apply_padded(padded, _bounded_softmax(logits, s), k)
    w = _bounded_logits(logits, s).exp_()
    return kernel_apply_padded(padded, w, k).div_(w.sum(dim=1, keepdim=True))


class RowStream:
    """One ``stem: half`` branch over one frame of ``height × width`` pixels, a band of rows at a time.

    Args:
        branch: the :class:`UNetBranch` (its config must have ``stem: half``).
        height, width: the frame's size (unpadded); the stream works on the frame padded (replicate) to
            the branch's alignment, ``padded_size``.
        device, dtype: of the buffers.

    ``feed`` every band of the padded frame in order (``rows`` ``[r0, r1)``, ``r0`` and ``r1`` even),
    then ``run`` once, then ask for output bands with ``rows``. Inference only (no autograd).
    """

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
        kw = dict(device=device, dtype=dtype)
        # channels_last, the layout the network runs in: each band is transposed while it is in cache
        self._pooled = torch.empty(1, c, hp // 2, wp // 2, **kw).contiguous(memory_format=torch.channels_last)
        self._guide = torch.empty(1, cfg.guide_channels, hp, wp, **kw)
        self._colour = torch.empty(1, 3, hp, wp, **kw)
        self._colour_half = torch.empty(1, 3, hp // 2, wp // 2, **kw)
        self._fed = 0
        self._low = self._coarse = None

    def feed(self, r0: int, x: torch.Tensor) -> None:
        """Features ``(1, C, r1 - r0, padded width)`` of rows ``[r0, r1)`` of the padded frame (bands in order)."""
        n = x.shape[-2]
        if r0 != self._fed or n % 2 or x.shape[-1] != self.padded_size[1]:
            raise ValueError(f"RowStream.feed: expected an even number of rows from row {self._fed}, "
                             f"{self.padded_size[1]} wide; got rows {r0}..{r0 + n}, {x.shape[-1]} wide")
        kind, g = self.cfg.input_transform, self.branch.guide
        self._guide[..., r0:r0 + n, :] = conv1x1(transform_input(x, kind), g.weight, g.bias).relu_()
        self._pooled[..., r0 // 2:(r0 + n) // 2, :] = transform_input(pool2(x), kind)
        self._colour[..., r0:r0 + n, :] = x[:, :3]
        self._colour_half[..., r0 // 2:(r0 + n) // 2, :] = pool2(x[:, :3])
        self._fed = r0 + n

    def run(self, summary: torch.Tensor | None = None) -> None:
        """The network at half resolution (all rows must have been fed); ``summary``: a given global summary."""
        if self._fed != self.padded_size[0]:
            raise ValueError(f"RowStream.run: rows 0..{self._fed} of {self.padded_size[0]} fed")
        net, cfg = self.branch, self.cfg
        h, decoded = net.decode(net.encode_from(self._release_pooled()), summary)
        c = h.shape[1]
        self._low = conv1x1(h, net.head.weight[:, :c], net.head.bias)  # the guided head's half-resolution part
        self._wg = net.head.weight[:, c:].reshape(net.head.out_channels, -1)
        if cfg.kernel_scales > 1:  # the coarser kernel levels, combined into one half-resolution result
            kk, s = cfg.kernel_size**2, cfg.logit_scale
            filtered, alphas, colour = [], [], self._colour_half
            for level in range(1, cfg.kernel_scales):
                if level > 1:
                    colour = pool2(colour)
                z = net.heads[level - 1](decoded[level - 1])
                alphas.append(torch.sigmoid(z[:, kk:]) if z.shape[1] > kk else None)
                r = cfg.kernel_size // 2
                padded = F.pad(colour, (r, r, r, r), mode="replicate") if r else colour
                filtered.append(_apply_softmax_kernels(padded, z[:, :kk], s, cfg.kernel_size))
            self._coarse = combine_levels(filtered, alphas)
        self._colour_half = None

    def _release_pooled(self) -> torch.Tensor:
        """The pooled features, no longer held here: the encoder frees them after its first conv."""
        pooled, self._pooled = self._pooled, None
        return pooled

    def rows(self, r0: int, r1: int) -> torch.Tensor:
        """Output rows ``[r0, r1)`` (even) of the padded frame, ``(1, 3, r1 - r0, padded width)``, branch space."""
        if self._low is None:
            raise ValueError("RowStream.rows: call run() first")
        cfg = self.cfg
        hp = self.padded_size[0]
        kk, r = cfg.kernel_size**2, cfg.kernel_size // 2
        m = 2 if cfg.kernel_scales > 1 else 0  # the blend's 2x2 pool and bilinear upsampling read 2 rows further
        e0, e1 = max(r0 - m, 0), min(r1 + m, hp)
        z = F.interpolate(clamped_rows(self._low, e0 // 2 - 1, e1 // 2 + 1), scale_factor=2, mode="bilinear",
                          align_corners=False)[..., 2:-2, :]
        gb = self._guide[0, :, e0:e1, :]
        z = z.add_(torch.mm(self._wg, gb.reshape(gb.shape[0], -1)).view(1, -1, e1 - e0, gb.shape[-1]))
        colour = F.pad(clamped_rows(self._colour, e0 - r, e1 + r), (r, r, 0, 0), mode="replicate") if r else \
            self._colour[..., e0:e1, :]
        f = _apply_softmax_kernels(colour, z[:, :kk], cfg.logit_scale, cfg.kernel_size)
        if cfg.kernel_scales == 1:
            return f
        alpha = torch.sigmoid(z[:, kk:])
        up = F.interpolate(clamped_rows(self._coarse, e0 // 2, e1 // 2) - pool2(f), scale_factor=2, mode="bilinear",
                           align_corners=False)
        i0, n = r0 - e0, r1 - r0
        return f[..., i0:i0 + n, :] + alpha[..., i0:i0 + n, :] * up[..., i0:i0 + n, :]
