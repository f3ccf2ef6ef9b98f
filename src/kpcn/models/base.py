"""The model contract every kpcn denoiser follows.

A model is an ``nn.Module`` subclass of :class:`DenoiserModel`, built from a
config dataclass by the registry (:mod:`kpcn.models.registry`). What the rest
of the library (training, denoising, tiling, report, bench) knows about a
model is only what it declares here:

* ``input_spec`` — the :class:`~kpcn.inputs.InputSpec` its inputs follow (which
  EXR layers it reads, its branches, how they add up to the colour);
* ``receptive_radius`` — how many pixels on each side an output pixel depends
  on through local operations (the halo a tile needs);
* ``uses_frame_context`` — whether it also uses a summary of the whole frame
  (then :meth:`frame_context` computes it once and tiles share it);
* ``alignment`` — tiles (and crops) must start at multiples of it (a U-Net
  with ``n`` 2× downsamplings needs ``2**n``); the model pads its own input
  at the bottom/right to a multiple of it;
* ``zero_preserving`` — a branch whose noisy colour is zero over the
  receptive radius gives exactly zero (kernel predictors: a convex
  combination of zeros is zero), so tiles or frames where it is zero may skip
  it without changing the result.
* ``kernel_padding`` — kernel predictors: how their kernels (weights summing
  to one) see beyond the frame border, ``"replicate"`` (border pixels
  repeated, so a constant image comes back unchanged) or ``"zeros"``; ``None``
  for a model that predicts no kernels;
* ``convex_kernels`` — each branch's output pixel is a convex combination of
  the branch's noisy colour over its ``kernel_size x kernel_size``
  neighbourhood, padded as ``kernel_padding`` says, so it lies in that
  neighbourhood's per-channel range (single-scale kernel predictors; not a
  multi-scale reconstruction, which adds coarse-minus-fine corrections).
* ``detail_regression`` — ``(radius, eps, clip)`` or None: the inference pipeline refines the assembled colour
  with the frame's normal (:func:`kpcn.ops.residual_regression`, an output pixel reads ``2 radius`` pixels further)
  after the network, outside ``forward``; a stage without weights, which training applies only with
  ``train.detail_stage`` (:func:`kpcn.train_steps.with_detail`).
* ``exposure_range`` — ``(lo, hi)`` or None: the exposure keys of the frames the weights were trained on; the
  inference pipeline denoises a frame outside them at the range's centre and scales the result back
  (:mod:`kpcn.exposure`).

``forward(inputs, context=None)`` takes the dict an input spec builds
(``(B, C, H, W)`` tensors: one per branch, plus ``albedo``; a branch that is
absent is zero and not run) and returns ``{branch: (B, 3, H, W), ...,
"color": (B, 3, H, W)}``: each branch in its own (feature) space and the
final radiance, finite and non-negative. A model that remodulates with an albedo of its own (the U-Net's
``albedo_kernel``) also returns it as ``"albedo"`` ``(B, 3, H, W)``; layers remodulated beside the colour
(light groups) use that one.
"""
from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch
from torch import nn

from ..exposure import check_exposure_gain, check_exposure_range
from ..inputs import InputSpec, get_input_spec

__all__ = ["DenoiserModel", "check_inputs", "check_detail_config", "DETAIL_STAGE"]

#: the detail stage's settings in the shipped ``*_r`` tags (chosen on the validation scenes random:920001-920018 for
#: the default U-Net; docs/measured.md, twenty-eighth session)
DETAIL_STAGE = {"detail_radius": 6, "detail_eps": 0.01, "detail_clip": 0.15}
#: config fields that change how a model runs but add no parameter (the detail stage, the U-Net's normal-guided
#: blend, the exposure range and gain): weights trained with or without them are the same network (training's
#: ``train.init``, :mod:`kpcn.soup`)
NO_WEIGHT_SETTINGS = frozenset({*DETAIL_STAGE, "edge_upsample", "exposure_range", "exposure_gain"})


class DenoiserModel(nn.Module):
    """Base class of registered denoisers (see the module docstring for the contract)."""

    #: registry name, set by :func:`~kpcn.models.registry.create_model`
    name: str = ""
    #: a zero branch colour gives an exactly zero branch output
    zero_preserving: bool = False
    #: the model uses a whole-frame summary (see :meth:`frame_context`)
    uses_frame_context: bool = False
    #: border padding of the kernels ("replicate" or "zeros"; None: the model predicts no kernels)
    kernel_padding: str | None = None
    #: each branch output is a convex combination of its noisy colour over the ``kernel_size``² neighbourhood
    convex_kernels: bool = False
    #: a whole frame can be run a band of rows at a time (:meth:`row_stream`, :mod:`kpcn.inference.rows`)
    streams_rows: bool = False
    #: dtypes the model's hidden layers can run in (:meth:`set_compute_dtype`); kernels, their softmax and
    #: their application stay float32 whatever the compute dtype
    compute_dtypes: tuple[torch.dtype, ...] = (torch.float32,)

    @property
    def detail_regression(self) -> tuple[int, float, float | None] | None:
        """``(radius, eps, clip)`` of the normal-guided residual regression the pipeline applies after the network
        (config fields ``detail_radius`` > 0, ``detail_eps`` and ``detail_clip``, 0 for None), or None."""
        radius = int(getattr(self.config, "detail_radius", 0) or 0)
        clip = float(getattr(self.config, "detail_clip", 0.0) or 0.0) or None
        return (radius, float(self.config.detail_eps), clip) if radius > 0 else None

    @property
    def exposure_range(self) -> tuple[float, float] | None:
        """``(lo, hi)``: the exposure keys (:func:`kpcn.exposure.frame_key`) the weights were trained on (config
        field ``exposure_range``), or None: every frame is denoised at its own exposure."""
        return check_exposure_range(getattr(self.config, "exposure_range", None))

    @property
    def exposure_gain(self) -> float:
        """The factor every frame is scaled by before :attr:`exposure_range` applies (config field
        ``exposure_gain``; 1.0: none): :func:`kpcn.exposure.exposure_scale`."""
        return check_exposure_gain(getattr(self.config, "exposure_gain", 1.0))

    def __init__(self, config: Any) -> None:
        super().__init__()
        self.config = config
        self._compute_dtype = torch.float32

    @property
    def compute_dtype(self) -> torch.dtype:
        """The dtype the hidden layers run in (float32 unless :meth:`set_compute_dtype` said otherwise)."""
        return self._compute_dtype

    def set_compute_dtype(self, dtype: torch.dtype | str) -> "DenoiserModel":
        """Run the hidden layers in ``dtype`` (``torch.bfloat16`` or ``"bfloat16"``: autocast around the
        convolution stack, weights kept float32; a run-time choice, not saved with the weights).

        Raises:
            ValueError: the model cannot run in ``dtype`` (:attr:`compute_dtypes` lists what it can).
        """
        dt = getattr(torch, dtype) if isinstance(dtype, str) and hasattr(torch, dtype) else dtype
        if dt not in self.compute_dtypes:
            names = ", ".join(str(d).removeprefix("torch.") for d in self.compute_dtypes)
            raise ValueError(f"{self.name or type(self).__name__}: cannot compute in {dtype!r}; it can in: {names}")
        self._compute_dtype = dt
        self._on_compute_dtype(dt)
        return self

    def _on_compute_dtype(self, dtype: torch.dtype) -> None:
        """Hook: a subclass passes the compute dtype to its parts."""

    # ------------------------------------------------------------------ declarations
    @property
    def input_spec(self) -> InputSpec:
        return get_input_spec(self.config.input_spec)

    @property
    def branches(self) -> tuple[str, ...]:
        return self.input_spec.branches

    @property
    def receptive_radius(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def alignment(self) -> int:
        return 1

    @property
    def reads_normal(self) -> bool:
        """Whether :meth:`forward` reads the frame's normal, ``inputs["normal"]`` ``(B, 3, H, W)`` in [-1, 1], beside
        the branches' features (a guide, e.g. the U-Net's ``edge_upsample``); the inference pipeline and training
        then give it (the noisy frame's own normal layer)."""
        return False

    def hparams(self) -> dict:
        """``{"name": ..., **config}``: ``create_model(**hparams())`` rebuilds the architecture."""
        return {"name": self.name, **asdict(self.config)}

    def extra_repr(self) -> str:
        return (f"name={self.name!r}, input_spec={self.input_spec.name!r}, receptive_radius={self.receptive_radius}, "
                f"alignment={self.alignment}, frame_context={self.uses_frame_context}")

    def channel_groups(self) -> dict[str, tuple[tuple[int, ...] | None, tuple[int, ...]]]:
        """How the convs' channels are grouped, for widening a trained model (``train.init_extend``).

        ``{module name: (output groups, input groups)}``, each a tuple of channel counts in the
        order the conv stacks them (a decoder conv reads ``(upsampled, skip)``). Output groups
        ``None``: the conv's outputs are results (kernel logits), not hidden channels. A model that
        lists no module (the default) can only gain channels at the end of a conv's inputs or outputs.
        """
        return {}

    # ------------------------------------------------------------------ computation
    def frame_context(self, inputs: dict[str, torch.Tensor]) -> Any:
        """Whole-frame context computed once per frame (``None`` for local models)."""
        return None

    def run_branch(self, name: str, x: torch.Tensor, context: Any = None,
                   normal: torch.Tensor | None = None) -> torch.Tensor:
        """Denoise one branch: ``(B, C, H, W)`` features -> ``(B, 3, H, W)`` in the branch's space; ``normal``: the
        frame's normal over the same pixels, for a model that :attr:`reads_normal`.

        The default runs the submodule registered under the branch's name.
        """
        return getattr(self, name)(x)

    def branch_kernels(self, name: str, x: torch.Tensor, context: Any = None,
                       normal: torch.Tensor | None = None) -> torch.Tensor:
        """The per-pixel kernels ``(B, k*k, H, W)`` a kernel predictor applies to branch ``name``.

        Only ``zero_preserving`` kernel predictors have them; the default uses
        the branch submodule's ``kernels(x)``. Others raise ``NotImplementedError``.
        """
        branch = getattr(self, name)
        if not self.zero_preserving or not hasattr(branch, "kernels"):
            raise NotImplementedError(f"{self.name or type(self).__name__} predicts no kernels: it cannot denoise "
                                      "other layers with the beauty's kernels")
        return branch.kernels(x)

    def row_stream(self, name: str, height: int, width: int, device=None):
        """A stream that runs branch ``name`` over a ``height × width`` frame a band of rows at a time
        (models with :attr:`streams_rows`; e.g. :class:`kpcn.models.unet_rows.RowStream`)."""
        raise NotImplementedError(f"{self.name or type(self).__name__} has no row streams")

    @property
    def kernel_size(self) -> int:
        """``k`` of the predicted ``k x k`` kernels (kernel predictors)."""
        return int(self.config.kernel_size)

    def forward(self, inputs: dict[str, torch.Tensor], context: Any = None) -> dict[str, torch.Tensor]:
        """Every present branch through :meth:`run_branch`, then the spec's reconstruction.

        A branch absent from ``inputs`` (or ``None``) is not run and is zero.
        """
        check_inputs(self, inputs)
        out, albedo = self.run_branches(inputs, context)
        color = self.input_spec.reconstruct(out, inputs if albedo is None else {**inputs, "albedo": albedo})
        for b in self.branches:  # a branch not run is zero in its own space
            if b not in out:
                out[b] = torch.zeros_like(color)
        out["color"] = color
        if albedo is not None:
            out["albedo"] = albedo
        return out

    def run_branches(self, inputs: dict[str, torch.Tensor], context: Any = None
                     ) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
        """Each present branch's output (:meth:`run_branch`), and the albedo the colour is remodulated with: None
        (the inputs' own) unless the model makes one (the U-Net's ``albedo_kernel``)."""
        guide = (inputs.get("normal"),) if self.reads_normal else ()  # the normal only to a model that reads it
        return {b: self.run_branch(b, inputs[b], context, *guide) for b in self.branches
                if inputs.get(b) is not None}, None


def check_inputs(model: DenoiserModel, inputs) -> tuple[int, int, int]:
    """Check ``inputs`` against the model's spec; returns ``(B, H, W)``.

    Raises ``ValueError`` naming the model, the key and the shapes.
    """
    who = f"{type(model).__name__} ({model.input_spec.name})"
    if not isinstance(inputs, dict):
        raise ValueError(f"{who}: inputs must be a dict of tensors (keys {list(model.branches) + ['albedo']}), "
                         f"got {type(inputs).__name__}")
    albedo = inputs.get("albedo")
    if not isinstance(albedo, torch.Tensor) or albedo.dim() != 4 or albedo.shape[1] != 3:
        shape = tuple(albedo.shape) if isinstance(albedo, torch.Tensor) else type(albedo).__name__
        raise ValueError(f"{who}: inputs['albedo'] must be a (B, 3, H, W) tensor, got {shape}")
    b, _, h, w = albedo.shape
    if model.reads_normal:
        normal = inputs.get("normal")
        if not isinstance(normal, torch.Tensor) or normal.dim() != 4 or tuple(normal.shape) != (b, 3, h, w):
            shape = tuple(normal.shape) if isinstance(normal, torch.Tensor) else type(normal).__name__
            raise ValueError(f"{who}: reads the frame's normal: inputs['normal'] must be a (B, 3, H, W) tensor the "
                             f"size of the albedo {tuple(albedo.shape)}, got {shape}")
    c = model.input_spec.channels
    for name in model.branches:
        x = inputs.get(name)
        if x is None:
            continue
        if not isinstance(x, torch.Tensor) or x.dim() != 4 or x.shape[1] != c:
            shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise ValueError(f"{who}: inputs[{name!r}] must be a (B, {c}, H, W) tensor, got {shape}")
        if (x.shape[0], x.shape[2], x.shape[3]) != (b, h, w):
            raise ValueError(f"{who}: inputs[{name!r}] {tuple(x.shape)} and albedo {tuple(albedo.shape)} "
                             "must agree in batch and spatial size")
    return b, h, w


def check_detail_config(cfg, spec, who: str) -> None:
    """Check a config's detail-stage fields (``detail_radius`` >= 0, ``detail_eps`` > 0, ``detail_clip`` >= 0; a
    radius > 0 needs an input spec that reads the normal). Raises ``ValueError`` naming ``who`` and the field."""
    radius, eps, clip = cfg.detail_radius, cfg.detail_eps, cfg.detail_clip
    if isinstance(radius, bool) or not isinstance(radius, int) or radius < 0 or not eps > 0 or not clip >= 0:
        raise ValueError(f"{who}.detail_radius (an integer) and detail_clip must be >= 0 and detail_eps > 0, got "
                         f"{radius!r}, {clip!r} and {eps!r}")
    if radius and "normal" not in spec.layers:
        raise ValueError(f"{who}.detail_radius needs an input spec that reads the normal; {spec.name!r} reads "
                         f"{spec.layers}")
