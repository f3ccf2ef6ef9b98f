"""The architecture of :class:`~kpcn.models.unet.UNetKPCN`: :class:`UNetConfig`, its checks, and the radii and
alignment that follow from it (see :mod:`kpcn.models.unet` for what each field means in the network)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ..exposure import check_exposure_gain, check_exposure_range
from ..inputs import get_input_spec
from .base import check_detail_config
from .layers import INPUT_TRANSFORMS

__all__ = ["UNetConfig", "RADIANCE_MIX_INIT"]

#: ``UNetConfig.radiance_mix``: the bias each mixing weight's logit starts from (``γ = sigmoid(-3) ≈ 0.05``)
RADIANCE_MIX_INIT = -3.0


@dataclass
class UNetConfig:
    """Architecture of :class:`UNetKPCN` (every branch shares it).

    Attributes:
        input_spec: the :mod:`kpcn.inputs` spec (``kpcn_split``, ``split_novar``, ``color_albedo_normal``).
        widths: channels of each level, finest first; ``len(widths) - 1`` poolings.
        convs_per_level: 3×3 convs per level in the encoder and in the decoder.
        deep_blocks: residual blocks ``h = relu(h + conv(relu(conv(h))))`` (3×3 convs, ``widths[-1]`` channels) after
            the encoder's coarsest level, before the global summary: context and capacity where a pixel costs
            1/256 of a full-resolution one (``stem: half``, 4 levels: 1.8 k multiply-adds per pixel a block at
            160 channels). Each block's second conv starts at zero, so ``train.init_extend`` adds blocks to a file
            without them at its output.
        kernel_size: odd size ``k`` of the predicted full-resolution kernels.
        coarse_kernel: ``kernel_scales > 1``: odd size of the coarser levels' kernels (0: ``kernel_size``). The
            full-resolution level is where the kernels' softmax, application and upsampled logits cost time (at
            1080p); the coarser levels reach far for a quarter of the pixels or fewer. ``kernel_size: 3`` with
            ``coarse_kernel: 5`` keeps their reach with 9 full-resolution taps instead of 25 (measured from the
            default: 0.91× its 1080p time, 0.2 dB less at 4 spp; docs/measured.md, thirty-sixth session).
        summary_channels: width of the global summary (0: no summary, a purely local model).
        logit_scale: bound of the kernel logits, ``s * tanh(z / s)``.
        init_sigma: std (pixels) of the Gaussian the kernels start as.
        out_init_gain: scale of the head's initial weights.
        input_transform: ``log`` (signed log1p of the features), ``logvar`` or ``none``.
        kernel_scales: levels with kernels, finest first (1: one full-resolution kernel;
            ``n > 1``: Vogels et al.'s multi-scale reconstruction over the ``n`` finest levels,
            at most ``len(widths) - 1``, or ``len(widths)`` with ``stem: half``).
        stem: ``full``: the first level runs at full resolution; ``half``: the network starts on
            the features average-pooled 2×2 (every level at half the resolution, a quarter of the
            multiply-adds), and the full-resolution kernels come from the finest decoder level
            upsampled (bilinear) beside a 1×1 ``guide`` of the full-resolution features.
        guide_channels: ``stem: half``: width of the full-resolution guide.
        guide_kernel: ``stem: half``: odd size of the guide's convolution (1: per pixel; 3: each pixel's
            guide also sees its 8 neighbours' features, so the full-resolution kernels can follow edges
            the half-resolution levels cannot place to the pixel), replicate padding at the frame's edges.
        fullres_channels: ``stem: half``: 0 (off) or ``F > 0``: a full-resolution decoder level of ``F`` channels,
            ``relu(conv3x3(relu(W · [bilinear_up2(finest decoder level), guide])))`` (the 1×1 of the finest level
            run at half resolution, as the head's), whose 1×1 output is added to the full-resolution head's
            logits. The finest level alone places an edge only to its half-resolution pixel; this level combines
            it with the full-resolution guide through two nonlinearities and a 3×3 neighbourhood. Its output
            conv starts at zero, so ``train.init_extend`` adds it to a file without it at the file's output.
        band_gain: ``kernel_scales > 1``: every level that blends in a coarser one also predicts a per-pixel
            gain ``β = 2·sigmoid(z)`` in ``[0, 2]`` of its own high band, ``o_l = f_l + α·U(o_{l+1} - D f_l)
            - (1 - β)·(f_l - U D f_l)``: the band a 2×2 pool drops, which the coarse-to-fine blend keeps whole
            (the grain a 5×5 kernel leaves at low spp; β > 1 sharpens). ``β = 1`` is the blend without it, and
            a model extended from one without it (``train.init_extend``: zero weights and bias) starts there.
        up_kernel: the taps of each decoder level's first conv over the coarser level it upsamples: 3 (a 3×3 conv
            of ``[nearest_up2(coarse), skip]``, :class:`~kpcn.models.layers.UpCatConv`) or 1 (a 1×1 of the
            coarse level at its own resolution, upsampled and added to the skip's 3×3,
            :class:`~kpcn.models.layers.UpAddConv`: 146 k -> 126 k multiply-adds per pixel for the
            64/96/128/160 U-Net, 0.92× its 1080p time in an in-process A/B). ``train.init_extend`` turns a file's 3×3 into it (the coarse taps summed).
        albedo_kernel: 0 (off) or an odd ``k_a``: the diffuse branch's full-resolution head also predicts a
            ``k_a × k_a`` kernel and a gate ``g = tanh(z)`` per pixel, and the colour is remodulated with
            ``a + g · (K_a ⊛ a - a)`` instead of the noisy albedo ``a`` (the diffuse branch still filters
            ``diffuse / (a + eps)``). At low spp a pixel's albedo is the mean of a few sub-pixel samples of the
            texture under it, and that noise reaches the output whole through the remodulation (remodulating
            the default's 4-spp output with the 2048-spp albedo instead: +0.8 dB on the report). Needs a split
            input spec (a ``diffuse`` branch). ``train.init_extend`` adds it to a file without it at ``g = 0``
            (the file's output).
        albedo_gate_gain: ``c`` in the albedo gate ``g = tanh(c·z)``: Adam moves a logit by about the learning rate
            a step whatever its gradient's scale, so a gate added at ``g = 0`` to a trained model opens ``c`` times
            faster (at 1, 2 200 steps at peak 7e-5 left it at a mean of 0.07).
        specular_widths: the specular branch's widths where they differ from ``widths`` (None: the same), as many
            levels. The specular branch is half a two-branch U-Net's multiply-adds; a narrower one buys time
            (``train.init_prune`` starts it from a file's wider one).
        albedo_clamp: 0 (off) or ``c > 0``: the albedo's correction ``K_a ⊛ a - a`` is clamped to ``± c·σ_a``,
            ``σ_a`` the standard deviation of the pixel's albedo mean (the ``kpcn_split`` features' albedo
            variance), so the filter moves an albedo only within its own noise: a converged albedo stays as it is.
        radiance_pool: ``kernel_scales > 1``: a branch whose colour is ``log1p`` of the radiance (the input spec's
            ``log_branches``: the split specs' specular) pools it to the coarser kernel levels as radiance,
            ``log1p(mean(expm1(c)))`` (:func:`~kpcn.models.layers.pool2_radiance`), instead of averaging its
            logarithms: a mean of logarithms is below the logarithm of the mean wherever a block's pixels differ,
            so at low spp the coarse levels of a log-space branch are darker than the radiance they stand for
            (the default's 4-spp specular output 4-19 % darker than the reference on the report's glossy scenes).
            The other branches pool as before. A function change, not a weights one: ``train.init_extend`` allows
            a file trained without it.
        radiance_mix: ``kernel_scales > 1``: every kernel level of a ``log1p``-encoded branch also predicts a
            per-pixel weight ``γ = sigmoid(z)`` and filters ``lerp(K ⊛ c, log1p(K ⊛ expm1(c)), γ)``: between the
            kernel applied to the logarithms (robust beside a firefly, but below the mean radiance by Jensen's
            inequality wherever the pixels it averages differ: at low spp a glossy surface comes out darker) and
            the kernel applied to the radiance (unbiased). Each ``γ`` starts near 0 (bias
            :data:`RADIANCE_MIX_INIT`), so ``train.init_extend`` from a file without it starts close to its output.
            A constant stays constant and a zero branch zero (both filters keep them).
        detail_radius: 0 (off) or ``r > 0``: after the network, :func:`kpcn.inference.denoise` adds back to the
            assembled colour the part of its log residual ``log1p(noisy) - log1p(denoised)`` that a local linear
            model of the frame's normal explains in each ``(2r + 1)²`` window, no channel moved further from
            the denoised value than its noisy value is (:func:`~kpcn.ops.residual_regression`): the shading
            detail of bump-mapped surfaces that the normal shows and a weighted mean of noisy neighbours blurs.
            An inference stage with no weights: a shipped file runs with or without it
            (``register_weights(..., config=...)``).
        detail_eps: the regression's ridge on the normal's window covariance (> 0): larger keeps less.
        detail_clip: 0 (none) or ``c > 0``: the fit sees the log residual clipped to ``± c`` and no pixel's detail
            exceeds ``c`` (fireflies neither steer the fit nor come back through it).
        edge_upsample: 0 (bilinear) or ``σ > 0``: every 2× upsampling of the coarse-to-fine blend (``kernel_scales``
            > 1) is joint bilateral on the frame's normal (:func:`kpcn.models.guided.upsample2_guided`, the normal
            and its 2×2-pooled pyramid as the guide, σ in the normal's units), so a coarse level's value does not
            bleed across an edge of the geometry. The model then reads the frame's normal (``inputs["normal"]``,
            ``(B, 3, H, W)``; :attr:`~kpcn.models.DenoiserModel.reads_normal`). An inference setting with no
            weights, like the detail stage (docs/measured.md, fortieth session).
        exposure_range: None, or ``[lo, hi]``: the exposure keys (:func:`kpcn.exposure.frame_key`) of the frames
            the weights were trained on; :func:`kpcn.inference.denoise` denoises a frame whose key lies outside at
            the range's centre and scales its result back (:func:`kpcn.exposure.exposure_scale`). An inference
            setting with no weights, like the detail stage.
        exposure_gain: ``g``: :func:`kpcn.inference.denoise` scales every frame by ``g`` before the exposure range
            applies (:func:`kpcn.exposure.exposure_scale`) and its result back. A calibration, measured: the network
            is not exposure-invariant inside its training range either (its input is ``log1p`` of the radiance),
            and the shipped weights do better on unseen frames at 1.5× their exposure (docs/measured.md,
            forty-first session). An inference setting with no weights, like the detail stage.
    """

    input_spec: str = "kpcn_split"
    widths: list[int] = field(default_factory=lambda: [16, 24, 32, 48])
    convs_per_level: int = 2
    deep_blocks: int = 0
    kernel_size: int = 5
    coarse_kernel: int = 0
    summary_channels: int = 8
    logit_scale: float = 16.0
    init_sigma: float = 1.0
    out_init_gain: float = 0.1
    input_transform: str = "log"
    kernel_scales: int = 1
    stem: str = "full"
    guide_channels: int = 8
    guide_kernel: int = 1
    fullres_channels: int = 0
    band_gain: bool = False
    up_kernel: int = 3
    albedo_kernel: int = 0
    albedo_gate_gain: float = 1.0
    albedo_clamp: float = 0.0
    specular_widths: list[int] | None = None
    radiance_pool: bool = False
    radiance_mix: bool = False
    detail_radius: int = 0
    detail_eps: float = 0.01
    detail_clip: float = 0.0
    edge_upsample: float = 0.0
    exposure_range: tuple[float, float] | None = None
    exposure_gain: float = 1.0

    def __post_init__(self) -> None:
        spec = get_input_spec(self.input_spec)
        check_exposure_range(self.exposure_range, "UNetConfig.exposure_range")
        check_exposure_gain(self.exposure_gain, "UNetConfig.exposure_gain")
        if not self.widths or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in self.widths):
            raise ValueError(f"UNetConfig.widths must be a non-empty list of positive integers, got {self.widths!r}")
        sw = self.specular_widths
        if sw is not None and (not isinstance(sw, (list, tuple)) or len(sw) != len(self.widths)
                               or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in sw)):
            raise ValueError(f"UNetConfig.specular_widths must be None or {len(self.widths)} positive integers (as many "
                             f"levels as widths {list(self.widths)}), got {sw!r}")
        if sw is not None and "specular" not in spec.branches:
            raise ValueError(f"UNetConfig.specular_widths needs an input spec with a specular branch; "
                             f"{spec.name!r} has {spec.branches}")
        if self.convs_per_level < 1:
            raise ValueError(f"UNetConfig.convs_per_level must be >= 1, got {self.convs_per_level}")
        if isinstance(self.deep_blocks, bool) or not isinstance(self.deep_blocks, int) or self.deep_blocks < 0:
            raise ValueError(f"UNetConfig.deep_blocks must be an integer >= 0, got {self.deep_blocks!r}")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ValueError(f"UNetConfig.kernel_size must be a positive odd integer, got {self.kernel_size}")
        if isinstance(self.coarse_kernel, bool) or not isinstance(self.coarse_kernel, int) or self.coarse_kernel < 0 \
                or (self.coarse_kernel and self.coarse_kernel % 2 == 0):
            raise ValueError(f"UNetConfig.coarse_kernel must be 0 (kernel_size) or a positive odd integer, got "
                             f"{self.coarse_kernel!r}")
        if self.stem not in ("full", "half"):
            raise ValueError(f"UNetConfig.stem must be 'full' or 'half', got {self.stem!r}")
        top = max(1, len(self.widths) - 1 + self.offset)
        if not 1 <= self.kernel_scales <= top:
            raise ValueError(f"UNetConfig.kernel_scales must be in 1..{top} (len(widths) - 1, or len(widths) "
                             f"with stem: half), got {self.kernel_scales}")
        if self.stem == "half" and self.guide_channels < 1:
            raise ValueError(f"UNetConfig.guide_channels must be >= 1 with stem: half, got {self.guide_channels}")
        if self.guide_kernel < 1 or self.guide_kernel % 2 == 0:
            raise ValueError(f"UNetConfig.guide_kernel must be a positive odd integer, got {self.guide_kernel}")
        if isinstance(self.fullres_channels, bool) or not isinstance(self.fullres_channels, int) \
                or self.fullres_channels < 0 or (self.fullres_channels and self.stem != "half"):
            raise ValueError(f"UNetConfig.fullres_channels must be an integer >= 0 and needs stem: half, got "
                             f"{self.fullres_channels!r} with stem {self.stem!r}")
        if self.up_kernel not in (1, 3) or isinstance(self.up_kernel, bool):
            raise ValueError(f"UNetConfig.up_kernel must be 1 or 3, got {self.up_kernel!r}")
        if isinstance(self.albedo_kernel, bool) or self.albedo_kernel < 0 or \
                (self.albedo_kernel and self.albedo_kernel % 2 == 0):
            raise ValueError(f"UNetConfig.albedo_kernel must be 0 (off) or a positive odd integer, got {self.albedo_kernel!r}")
        if not self.albedo_gate_gain > 0:
            raise ValueError(f"UNetConfig.albedo_gate_gain must be positive, got {self.albedo_gate_gain!r}")
        if self.albedo_clamp < 0 or (self.albedo_clamp and spec.name != "kpcn_split"):
            raise ValueError(f"UNetConfig.albedo_clamp must be >= 0 and needs the kpcn_split input spec (its albedo "
                             f"variance), got {self.albedo_clamp!r} with {spec.name!r}")
        if self.albedo_kernel and self.kernel_scales < 2:
            raise ValueError("UNetConfig.albedo_kernel needs kernel_scales >= 2 (its kernels travel with the "
                             "multi-scale ones)")
        if self.albedo_kernel and "diffuse" not in spec.branches:
            raise ValueError(f"UNetConfig.albedo_kernel needs an input spec with a diffuse branch (one that "
                             f"remodulates with the albedo); {spec.name!r} has {spec.branches}")
        if self.coarse_kernel and self.kernel_scales < 2:
            raise ValueError("UNetConfig.coarse_kernel needs kernel_scales >= 2 (the coarser kernel levels)")
        if self.band_gain and self.kernel_scales < 2:
            raise ValueError("UNetConfig.band_gain needs kernel_scales >= 2 (the gain is of the band a coarser "
                             "kernel level does not replace)")
        for key in ("radiance_pool", "radiance_mix"):
            if getattr(self, key) and (self.kernel_scales < 2 or not spec.log_branches):
                raise ValueError(f"UNetConfig.{key} needs kernel_scales >= 2 and an input spec with a log1p-encoded "
                                 f"branch (log_branches); got kernel_scales {self.kernel_scales} and {spec.name!r} "
                                 f"(log_branches {spec.log_branches})")
        check_detail_config(self, spec, "UNetConfig")
        if isinstance(self.edge_upsample, bool) or not self.edge_upsample >= 0 or \
                (self.edge_upsample and (self.kernel_scales < 2 or "normal" not in spec.layers)):
            raise ValueError(f"UNetConfig.edge_upsample must be 0 or > 0 and needs kernel_scales >= 2 and an input "
                             f"spec that reads the normal; got {self.edge_upsample!r}, kernel_scales "
                             f"{self.kernel_scales}, {spec.name!r}")
        if self.summary_channels < 0:
            raise ValueError(f"UNetConfig.summary_channels must be >= 0, got {self.summary_channels}")
        if not self.logit_scale > 0 or not self.init_sigma > 0:
            raise ValueError("UNetConfig.logit_scale and init_sigma must be positive")
        if self.input_transform not in INPUT_TRANSFORMS:
            raise ValueError(f"UNetConfig.input_transform must be one of {INPUT_TRANSFORMS}, got {self.input_transform!r}")
        if self.input_transform == "logvar" and spec.name != "kpcn_split":
            raise ValueError("UNetConfig.input_transform 'logvar' needs the kpcn_split input spec")

    def branch_config(self, branch: str) -> "UNetConfig":
        """The architecture of branch ``branch`` (``specular_widths`` applied to the specular branch; ``radiance_pool`` and
        ``radiance_mix`` only where the branch's colour is log-encoded)."""
        cfg = self
        if branch not in get_input_spec(self.input_spec).log_branches and (self.radiance_pool or self.radiance_mix):
            cfg = dataclasses.replace(cfg, radiance_pool=False, radiance_mix=False)
        if branch != "specular" or self.specular_widths is None:
            return cfg
        return dataclasses.replace(cfg, widths=list(self.specular_widths), specular_widths=None)

    @property
    def offset(self) -> int:
        """Resolution levels below full of the network's first level (``stem: half``: 1)."""
        return 1 if self.stem == "half" else 0

    @property
    def alignment(self) -> int:
        return 2 ** (len(self.widths) - 1 + self.offset)

    @property
    def network_radius(self) -> int:
        c = self.convs_per_level
        scales = [2 ** (level + self.offset) for level in range(len(self.widths))]
        encoder = c * sum(scales) + 2 * self.deep_blocks * scales[-1]
        decoder = sum(s * (1 + c) for s in scales[:-1])
        # stem half: the 2x2 pooling block and the bilinear upsampling back to full resolution (the guide's
        # reach at full resolution, guide_kernel // 2, counts where it exceeds that)
        # (fullres_channels: its 3x3 conv one pixel more)
        full = max(3, self.guide_kernel // 2) + (1 if self.fullres_channels else 0)
        return encoder + decoder + (full if self.offset else 0)

    @property
    def kernel_radius(self) -> int:
        """How far the kernels (and, with several scales, their pooling and upsampling) reach."""
        if self.kernel_scales == 1:
            return self.kernel_size // 2
        return sum((self.level_kernel(level) // 2 + 2) * 2**level for level in range(self.kernel_scales))

    def level_kernel(self, level: int) -> int:
        """The kernel size of kernel level ``level`` (0: full resolution): ``kernel_size``, or ``coarse_kernel``
        at the coarser levels where it is set."""
        return self.coarse_kernel if level and self.coarse_kernel else self.kernel_size
