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
``forward`` returns it as ``"albedo"`` (:meth:`UNetKPCN.run_branches`). The branch itself still filters ``diffuse / (a + eps)``.

Receptive radius (full-resolution pixels): a 3×3 conv at level ``l`` adds
``2**l``; an average pool adds nothing beyond the pooled block; a nearest
upsample into level ``l`` adds ``2**l``; the kernel reaches ``kernel_size // 2``
(at level ``l``: ``(kernel_size // 2 + 2) · 2**l``, a bound that also covers the
pooling block and the bilinear upsampling, summed over the kernel levels).
"""
from __future__ import annotations

import torch

from .base import DETAIL_STAGE, DenoiserModel, check_inputs
from .kernel_heads import MultiScaleApply, MultiScaleKernels
from .registry import register_model, register_weights
from .unet_branch import UNetBranch
from .unet_config import UNetConfig

__all__ = ["UNetConfig", "UNetBranch", "UNetKPCN", "MultiScaleKernels", "MultiScaleApply"]


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
            self.add_module(b, UNetBranch(config.branch_config(b), config.albedo_kernel if b == "diffuse" else 0))

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

    def run_branches(self, inputs: dict[str, torch.Tensor], context=None):
        """:meth:`DenoiserModel.run_branches`; with ``albedo_kernel`` the diffuse branch's kernels also filter the
        albedo (:meth:`UNetBranch.filter_albedo`), which the colour is remodulated with and ``forward`` returns as
        ``"albedo"``."""
        if not self.config.albedo_kernel or inputs.get("diffuse") is None:
            return super().run_branches(inputs, context)
        net, x = self.diffuse, inputs["diffuse"]
        normal = inputs.get("normal") if self.reads_normal else None
        ks = net.kernels(x, (context or {}).get("diffuse"), normal)
        out = {"diffuse": net.apply_kernels(x[:, :3].contiguous(), ks)}
        albedo = net.filter_albedo(inputs["albedo"], ks)
        del ks
        guide = (normal,) if self.reads_normal else ()  # the normal only where read (an override may not take it)
        out.update((b, self.run_branch(b, inputs[b], context, *guide)) for b in self.branches
                   if b != "diffuse" and inputs.get(b) is not None)
        return out, albedo

    def run_branch(self, name: str, x: torch.Tensor, context=None, normal=None) -> torch.Tensor:
        """One branch, with its whole-frame summary from ``context`` when given (else its own)."""
        return getattr(self, name)(x, (context or {}).get(name), normal)

    def branch_kernels(self, name: str, x: torch.Tensor, context=None, normal=None) -> torch.Tensor:
        return getattr(self, name).kernels(x, (context or {}).get(name), normal)

    @property
    def reads_normal(self) -> bool:
        """``edge_upsample``: the blend's upsampling is guided by the frame's normal."""
        return bool(self.config.edge_upsample)


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
                             "wide64u at 4 spp, 1.0-1.1x its 1080p time (where wide64s starts)")
register_weights("unet_kpcn", "wide64s", "unet_wide64s.safetensors",
                 description="unet_kpcn:wide64a with its specular branch narrowed to 48/64/96/128 channels "
                             "(specular_widths), 98 k multiply-adds per pixel, convolutions in bfloat16 where the CPU "
                             "has it (configs/unet_wide64s.yaml): pruned from wide64a (train.init_prune: each channel "
                             "group keeps its first channels) and trained 9000 steps (batch 4) on the CPU on 87 + 24 "
                             "scenes; 0.9-1.0x OIDN's 1080p time, 0.89x wide64a's")
register_weights("unet_kpcn", "wide64b", "unet_wide64b.safetensors",
                 description="unet_kpcn:wide64s (the same network, 98 k multiply-adds per pixel) trained 4000 more "
                             "steps of batch 16 on the CPU (configs/unet_wide64b.yaml) on the 87 + 24 scenes at every "
                             "spp and 229 fresh CPU scenes at 2-16 spp only (data.spp_by_root), each spp's pairs "
                             "listed equally often (data.balance_spp); ahead of OIDN on 17 of the 21 report figures at "
                             "4-256 spp (wide64s 16)")
register_weights("unet_kpcn", "wide64c", "unet_wide64c.safetensors",
                 description="unet_kpcn:wide64b (the same network, 98 k multiply-adds per pixel) with its specular "
                             "branch's level-1 blending weight reopened (train.init_reopen: dead since unet_kpcn:fast, "
                             "so the specular 1/4 and 1/8 kernel levels were never used) and its colour pooled to the "
                             "coarse levels as radiance (radiance_pool), trained 3000 steps of batch 16 on the CPU "
                             "(configs/unet_wide64c.yaml) with 268 fresh scenes at 2-8 spp")
register_weights("unet_kpcn", "wide64h", "unet_wide64h.safetensors",
                 description="unet_kpcn:wide64c (the same network, 98 k multiply-adds per pixel) trained about 2800 "
                             "steps of batch 32 of 128² on one GPU on 85 procedural 256x256 scenes rendered there "
                             "(2-512 spp, 2048-spp references; log_msssim with tone_l2_weight 100), then blended "
                             "0.7 / 0.3 with wide64c in weight space (python -m kpcn.soup; configs/unet_wide64h.yaml)")
register_weights("unet_kpcn", "wide64u", "unet_wide64u.safetensors",
                 description="unet_kpcn:wide64g with up_kernel 1 (each decoder level's first conv reads the coarser "
                             "level through a 1x1 at its own resolution), 126 k multiply-adds per pixel, its convolutions "
                             "in bfloat16 where the CPU has it (configs/unet_wide64u.yaml): wide64g trained about 2400 "
                             "steps (batch 32 of 128²) on one GPU on 65 procedural 256x256 scenes rendered there, then "
                             "turned into up_kernel 1 and trained 7000 steps (batch 4) on the CPU on 87 + 24 scenes")
# wide64neg's inference settings over wide64n's file, kept by its fine-tuned successors wide64q and wide64v
WIDE64NEG_SETTINGS = dict(DETAIL_STAGE, detail_eps=0.001, edge_upsample=0.5, exposure_gain=1.5)
register_weights("unet_kpcn", "wide64v", "unet_wide64v.safetensors", default=True,
                 config=WIDE64NEG_SETTINGS,
                 description="unet_kpcn:wide64neg (the same network and settings, 98 k multiply-adds per pixel) "
                             "fine-tuned on the CPU on up to 581 fresh procedural 256x256 scenes "
                             "(configs/unet_wide64v.yaml): wide64q's two runs of 600 steps on 432 scenes and two of "
                             "1800 steps on 581, each from wide64ne, without and with the converged pairs, blended "
                             "1/8 each + 1/2 wide64neg (python -m kpcn.soup); chosen on the validation scenes "
                             "random:950001-950010 (docs/measured.md, forty-sixth session)")
register_weights("unet_kpcn", "wide64q", "unet_wide64q.safetensors",
                 config=WIDE64NEG_SETTINGS,
                 description="unet_kpcn:wide64neg (the same network and settings, 98 k multiply-adds per pixel) "
                             "fine-tuned on the CPU on 432 fresh procedural 256x256 scenes (configs/unet_wide64q.yaml): "
                             "two runs of 600 steps from wide64ne, without and with the converged pairs, blended "
                             "1/4 + 1/4 + 1/2 with wide64neg (python -m kpcn.soup); chosen on the validation scenes "
                             "random:950001-950010 (docs/measured.md, forty-fifth session)")
register_weights("unet_kpcn", "wide64neg", "unet_wide64n.safetensors",
                 config=WIDE64NEG_SETTINGS,
                 description="unet_kpcn:wide64ne (wide64n's file, its detail stage and normal-guided blend) with every "
                             "frame denoised at 1.5x its exposure (exposure_gain 1.5, no weights): the network is not "
                             "exposure-invariant, and at 1.5x it does better on unseen scenes at every spp; chosen on "
                             "the validation scenes random:920001-920010, 930001-930010 and 940001-940010 "
                             "(docs/measured.md, forty-first session)")
register_weights("unet_kpcn", "wide64ne", "unet_wide64n.safetensors",
                 config=dict(DETAIL_STAGE, detail_eps=0.001, edge_upsample=0.5),
                 description="unet_kpcn:wide64n's file and detail stage with the coarse-to-fine blend's upsampling "
                             "guided by the frame's normal (edge_upsample 0.5, no weights): a coarse level's value "
                             "no longer bleeds across an edge of the geometry, where the default's 4-spp error "
                             "against OIDN lies; measured on the report's and the validation scenes "
                             "(docs/measured.md, fortieth session)")
register_weights("unet_kpcn", "wide64n", "unet_wide64n.safetensors",
                 config=dict(DETAIL_STAGE, detail_eps=0.001),
                 description="unet_kpcn:wide64e (the same network, 98 k multiply-adds per pixel, and its detail stage) "
                             "fine-tuned in two runs of 600 steps on the CPU on 89 fresh procedural 256x256 scenes "
                             "with the references as targets at every spp (no distillation from itself above 32 spp, "
                             "which kept fireflies in 256-spp inputs), blended 1/4 + 1/4 + 1/2 with wide64e "
                             "(python -m kpcn.soup; configs/unet_wide64n.yaml); chosen on validation scenes "
                             "random:920001-920010, 930001-930010 and 940001-940010 pooled")
register_weights("unet_kpcn", "wide64e", "unet_wide64f.safetensors",
                 config=dict(DETAIL_STAGE, detail_eps=0.001),
                 description="unet_kpcn:wide64f's weights (the same network, 98 k multiply-adds per pixel) with its "
                             "detail stage's ridge detail_eps 0.001 instead of 0.01 (radius 6 and clip 0.15 as "
                             "before): more of the shading detail the normal explains is added back; chosen on "
                             "validation scenes random:920001-920010 and random:930001-930010 pooled")
register_weights("unet_kpcn", "wide64f", "unet_wide64f.safetensors",
                 config=dict(DETAIL_STAGE),
                 description="unet_kpcn:wide64m (the same network, 98 k multiply-adds per pixel, and its detail stage) "
                             "fine-tuned in two runs of 600 steps on the CPU on 59 fresh procedural 256x256 scenes it "
                             "had not seen (2-256 spp, 1024-spp references), then blended in weight space "
                             "(python -m kpcn.soup; configs/unet_wide64f.yaml); chosen on validation scenes "
                             "random:920001-920010")
register_weights("unet_kpcn", "wide64m", "unet_wide64m.safetensors",
                 config=dict(DETAIL_STAGE),
                 description="unet_kpcn:wide64r (the same network, 98 k multiply-adds per pixel, and its detail stage) "
                             "fine-tuned for the colour after the stage in three runs of 600 steps on the CPU with a "
                             "relMSE term in the loss and the converged pairs' identity lesson narrowed or dropped, "
                             "then blended in weight space (python -m kpcn.soup; configs/unet_wide64m.yaml); chosen on "
                             "validation scenes random:920001-920018")
register_weights("unet_kpcn", "wide64r", "unet_wide64h.safetensors",
                 config=dict(DETAIL_STAGE),
                 description="unet_kpcn:wide64h's weights (the same network, 98 k multiply-adds per pixel) with the "
                             "detail stage after it (detail_radius 6, detail_eps 0.01, detail_clip 0.15; "
                             "kpcn.inference.detail): the part of the colour's log residual that the normal explains "
                             "in each 14x14 window is added back, no channel moved further than its noisy value (the "
                             "shading of bump-mapped surfaces); settings chosen on validation scenes "
                             "random:920001-920018")
