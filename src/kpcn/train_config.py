"""The training run's configuration: ``model``, ``data`` and ``train`` sections.

Loaded with :func:`kpcn.config.load_config` from ``configs/*.yaml``::

    name: small
    model: {name: kpcn, layers: 5, width: 32, conv_size: 5, kernel_size: 11, input_transform: log}
    data: {root: data/train, patch_size: 65}
    train: {stage1_steps: 1500, lr: 1.0e-3}

``model`` is the registry name plus that model's own keys (checked against
its config dataclass, e.g. :class:`kpcn.models.BranchConfig`: an unknown key
names the nearest valid one).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePath

from .config import ConfigError, from_dict
from .constants import PRECISIONS
from .exposure import check_exposure_range
from .schedule import SCHEDULES

__all__ = ["RunConfig", "DataConfig", "TrainConfig", "check_model_section"]


def _at_least(section: str, obj, key: str, low: int) -> None:
    v = getattr(obj, key)
    if v is not None and v < low:
        raise ConfigError(f"{section}.{key}: must be >= {low}, got {v!r}")


def _positive(section: str, obj, key: str) -> None:
    v = getattr(obj, key)
    if v is not None and not (math.isfinite(v) and v > 0):
        raise ConfigError(f"{section}.{key}: must be a number > 0, got {v!r}")


@dataclass
class DataConfig:
    root: str = "data/train"  #: folder written by `python -m kpcn.render dataset`
    #: more rendered data sets trained on with root (scene names must differ: render with another --first-seed)
    extra_roots: list[str] = field(default_factory=list)
    val_root: str | None = None  #: held-out frames; None: the last `val_scenes` scenes of root
    val_scenes: int = 2
    spp: list[int] | None = None  #: input spp to train on (None: all)
    #: input spp per folder, overriding ``spp`` for the data sets (root, extra_roots, val_root) at or under each
    #: folder; the longest matching folder wins. E.g. ``{data/r3: [2, 4, 8, 16]}``: a set of scenes that helps
    #: the low spp but not the high ones lends only its low-spp inputs (its converged pairs still follow
    #: ``converged_inputs``)
    spp_by_root: dict[str, list[int]] = field(default_factory=dict)
    #: also train on each training scene's reference as its own input (target = itself): the
    #: converged end of the spp range, so the model learns to leave a clean frame alone
    converged_inputs: bool = False
    #: how many times each converged pair is listed (its share of the patches drawn): a model without
    #: variance layers must learn from data alone to leave a clean frame as it is
    converged_weight: int = 1
    #: list each input spp's training pairs that many times that every spp (and the converged pairs, as one more
    #: level) has about as many as the most common one (whole repeats, rounded): scenes lent only at some spp
    #: (``spp_by_root``) then add variety at those spp without taking patches from the others.
    #: ``converged_weight`` multiplies the converged pairs after it
    balance_spp: bool = False
    #: the fraction of training patches made of two inputs of one scene at different spp, one's pixels inside a
    #: random smooth region and the other's outside (:class:`kpcn.data.PatchDataset`): a frame from an adaptive
    #: sampler, whose spp varies from pixel to pixel (measured: a model trained on uniform frames only denoised
    #: such composites 6-11 % worse per region than the uniform frames; docs/measured.md, thirty-ninth session)
    spp_mix: float = 0.0
    #: converged pairs only from data sets whose references have at least this many spp (0: all). A
    #: reference close to the inputs' spp is still noisy: listed as its own target, it teaches the model to
    #: keep the noise of a high-spp input (measured: 1024-spp references against 128-256-spp inputs)
    converged_min_ref_spp: int = 0
    #: converged pairs count only the pixels whose reference is converged: relative noise (the standard
    #: deviation of the pixel mean, over sqrt(colour^2 + 0.01) as relMSE weighs it) at most this. A 2048-spp
    #: reference still has 5-10 % noise on rough metals and under hard lights (a third of the pixels of the
    #: training data above 2 %); taught as their own target there, the model keeps that much noise, and
    #: fireflies, in a 256-spp input. None: every pixel (needs an input spec with variances)
    converged_max_noise: float | None = None
    patch_size: int = 65
    patches_per_frame: int | None = None  #: None: the paper's 400 per 1280×720, scaled by area
    sampling: str = "importance"
    #: the patch store (kpcn.store): "auto" = <root>/.store/<spec>, a folder (<folder>/<spec> is used),
    #: or "none" to keep every frame in memory as float32 tensors (no preprocessing on disk)
    store: str = "auto"
    #: DataLoader worker processes that crop the patches (0: the training process itself); None: 2 when
    #: training on CUDA, 0 on the CPU (there workers measured slower: `python -m kpcn.bench data`)
    workers: int | None = None
    #: processes that build the patch store's missing entries (one torch thread each); None: one per core, at most
    #: 16, when 16 or more frames are missing (fewer are built in the training process)
    prepare_workers: int | None = None
    # the built-in default data set, rendered when `root` has no manifest and `render_if_missing`
    render_if_missing: bool = True
    render_scenes: int = 24
    render_spp: list[int] = field(default_factory=lambda: [2, 4, 8, 16, 32])
    render_ref_spp: int = 1024
    render_resolution: list[int] = field(default_factory=lambda: [128, 128])
    render_first_seed: int = 0

    def __post_init__(self) -> None:
        if self.sampling not in ("importance", "uniform"):
            raise ConfigError(f"data.sampling: expected 'importance' or 'uniform', got {self.sampling!r}")
        for key in ("patch_size", "patches_per_frame", "render_scenes", "converged_weight", "prepare_workers"):
            _at_least("data", self, key, 1)
        for key in ("val_scenes", "render_first_seed", "workers", "converged_min_ref_spp"):
            _at_least("data", self, key, 0)
        _positive("data", self, "converged_max_noise")
        if isinstance(self.spp_mix, bool) or not isinstance(self.spp_mix, (int, float)) or not 0 <= self.spp_mix <= 1:
            raise ConfigError(f"data.spp_mix: expected a fraction in [0, 1], got {self.spp_mix!r}")
        if not isinstance(self.store, str) or not self.store.strip():
            raise ConfigError(f"data.store: expected auto, none or a folder, got {self.store!r}")
        _at_least("data", self, "render_ref_spp", 2)
        if self.spp is not None:
            if not self.spp:
                raise ConfigError("data.spp: must list at least one sample count (null: all)")
            if min(self.spp) < 1:
                raise ConfigError(f"data.spp: every sample count must be >= 1, got {self.spp!r}")
        if not isinstance(self.spp_by_root, dict):
            raise ConfigError(f"data.spp_by_root: expected a mapping of folder -> sample counts, got "
                              f"{self.spp_by_root!r}")
        for folder, counts in self.spp_by_root.items():
            if not isinstance(counts, list) or not counts or any(
                    isinstance(c, bool) or not isinstance(c, int) or c < 1 for c in counts):
                raise ConfigError(f"data.spp_by_root[{folder!r}]: expected a list of sample counts >= 1, got "
                                  f"{counts!r}")
        if not self.render_spp or min(self.render_spp) < 2:
            raise ConfigError(f"data.render_spp: every sample count must be >= 2, got {self.render_spp!r}")
        res = self.render_resolution
        if len(res) != 2 or min(res) < 1:
            raise ConfigError(f"data.render_resolution: expected [width, height] >= 1, got {res!r}")


@dataclass
class TrainConfig:
    stage1_steps: int = 1000  #: every branch on its own target
    stage2_steps: int = 500  #: joint fine-tuning on the final colour
    batch_size: int = 4
    lr: float = 1e-5
    stage2_lr: float | None = None  #: None: same as lr
    loss: str = "l1"
    stage2_loss: str | None = None  #: None: same as loss
    #: keyword parameters of the loss (e.g. ``{ssim_weight: 2}`` for log_msssim); stage2_loss_params those of
    #: stage 2's loss (None: loss_params when stage 2 uses the same loss, else its defaults)
    loss_params: dict = field(default_factory=dict)
    stage2_loss_params: dict | None = None
    schedule: str = "constant"  #: constant, or onecycle (per stage: warm-up to lr, cosine down; see kpcn.schedule)
    warmup: float = 0.15  #: onecycle: the fraction of each stage spent warming up
    augment: bool = True  #: flips, transposes and RGB permutations of every patch (kpcn.augment)
    #: the fraction of patches shown at another exposure, their key drawn log-uniform in ``exposure_range``
    #: (kpcn.augment.exposure_batch; split input specs); 0: every patch at its own
    exposure_augment: float = 0.0
    #: the keys exposure_augment draws from; None: the model config's exposure_range
    exposure_range: tuple[float, float] | None = None
    grad_clip: float = 1.0
    val_every: int = 250
    ckpt_every: int = 100  #: also writes checkpoints/step_<N>.pt
    keep_checkpoints: int = 3  #: the last K checkpoints/step_<N>.pt kept beside latest.pt (0: latest.pt only)
    log_every: int = 10
    seed: int = 0
    threads: int | None = None  #: torch CPU threads (None: PyTorch's default)
    device: str = "auto"  #: auto, cpu or cuda
    #: weights to start from (fine-tuning): a kpcn ``.safetensors`` file or a shipped ``model:tag``;
    #: its model and hyper-parameters must be the config's. None: random initialisation. A resumed
    #: run continues from its checkpoint instead.
    init: str | None = None
    #: the config's model may extend the ``init`` model: read more input channels (another input spec whose
    #: channels start with the file's, e.g. color_albedo_normal -> color_albedo_normal_noise; the added
    #: channels' weights start at zero) and add the precision gate (starting nearly open), so training starts
    #: from the file's outputs (exactly, or within the gate's 0.25 %)
    init_extend: bool = False
    #: with init_extend: U-Net channel groups may also be narrower than the file's (``specular_widths`` below its
    #: widths): each group keeps the file's first channels. Unlike extending, the narrowed model does not compute
    #: the file's function: it is a start for training, not a conversion. U-Net kernels may be smaller than the
    #: file's (``kernel_size``, ``coarse_kernel``): each level starts from the centre taps of the file's logits
    #: (init_extend alone lets them be larger: the file's logits as the centre taps, new ones copied from their
    #: nearest, a little lower)
    init_prune: bool = False
    #: U-Net blending weights to restart, each ``"<branch>:<level>"``: the weight ``α`` with which kernel level
    #: ``level`` (0: full resolution) takes in the next coarser one restarts at ``sigmoid(-1) ≈ 0.27`` at every
    #: pixel (its logit's weights zeroed, its bias -1), the rest of the ``init`` file as it was. A gate whose logits
    #: sank far below 0 has no gradient left to come back with (the specular branch's level 1 in every shipped
    #: U-Net: logits -25 to -60, so its 1/4 and 1/8 levels were never used)
    init_reopen: list[str] = field(default_factory=list)
    #: learning-rate factors by parameter name, ``{glob: factor}`` (the first matching glob counts; others train at
    #: the schedule's rate): e.g. ``{"*.fullres.*": 20}`` for a part added at zero to a trained file, which Adam
    #: would move by about the rate a step, and so hardly at a fine-tune's (docs/measured.md, forty-eighth session)
    lr_mult: dict = field(default_factory=dict)
    #: parameter names to train, as glob patterns (``fnmatch``; e.g. ``"specular.head*"``): every other parameter is
    #: frozen (no gradient, left out of the optimiser, and the frozen part of the network runs without autograd).
    #: Empty: all of them. A pattern that names no parameter is refused
    train_only: list[str] = field(default_factory=list)
    #: patches whose input has at least this many samples per pixel (converged pairs excepted) are taught the
    #: ``init`` file's own outputs on them instead of their references (every ``y_<output>`` the file's model
    #: gives): training on low-spp data and a new loss keeps what the file does at high spp, with no references
    #: fine enough for high-spp inputs (a 512-spp reference has half a 256-spp input's noise). Needs ``init``;
    #: the file's model must read the config's input spec. None: off
    distill_min_spp: int | None = None
    #: the teacher's outputs (``distill_min_spp``) are the mean of its outputs on this many flips and transposes of
    #: each patch (1: the patch as it is; at most 8): a target with less of the network's own variance, at that many
    #: teacher passes a step
    distill_tta: int = 1
    #: dtype of the model's hidden layers (``DenoiserModel.set_compute_dtype``): float32, or bfloat16 (autocast
    #: around the conv stack of models that can; weights, optimiser, heads and loss stay float32). On CPUs with
    #: AMX, bfloat16 steps of the U-Net take half the time of float32 ones at twice the width.
    precision: str = "float32"
    #: pass the colour through the model's detail stage (its ``detail_regression``: the config's ``detail_*``
    #: fields) before the stage-2 loss, in validation and on the teacher's outputs, as :func:`kpcn.denoise` applies
    #: it after the network: the network is trained for the output the pipeline gives. Needs a model with the stage
    #: and a data set whose frames have a normal layer (``noisy_normal``)
    detail_stage: bool = False

    def __post_init__(self) -> None:
        from .losses import create_loss, list_losses

        for key in ("loss", "stage2_loss"):
            v = getattr(self, key)
            if v is not None and v not in list_losses():
                raise ConfigError(f"train.{key}: unknown loss {v!r}; known: {', '.join(list_losses())}")
        for stage in (1, 2):
            try:
                create_loss(*self.loss_of(stage))
            except ValueError as e:
                raise ConfigError(f"train.{'stage2_' if stage == 2 else ''}loss_params: {e}") from None
        for key in ("stage1_steps", "stage2_steps", "keep_checkpoints", "seed"):
            _at_least("train", self, key, 0)
        for key in ("batch_size", "val_every", "ckpt_every", "log_every", "threads"):
            _at_least("train", self, key, 1)
        if self.stage1_steps + self.stage2_steps < 1:
            raise ConfigError("train.stage1_steps + train.stage2_steps: must be >= 1, got 0")
        for key in ("lr", "stage2_lr"):
            _positive("train", self, key)
        if not 0.0 <= float(self.exposure_augment) <= 1.0:
            raise ConfigError(f"train.exposure_augment: must be a fraction in [0, 1], got {self.exposure_augment!r}")
        try:
            check_exposure_range(self.exposure_range, "train.exposure_range")
        except ValueError as e:
            raise ConfigError(str(e)) from None
        if self.schedule not in SCHEDULES:
            raise ConfigError(f"train.schedule: expected one of {', '.join(SCHEDULES)}, got {self.schedule!r}")
        if not (0.0 <= self.warmup < 1.0):
            raise ConfigError(f"train.warmup: must be in [0, 1), got {self.warmup!r}")
        if not (math.isfinite(self.grad_clip) and self.grad_clip >= 0):
            raise ConfigError(f"train.grad_clip: must be >= 0 (0: off), got {self.grad_clip!r}")
        if self.init_reopen and not self.init:
            raise ConfigError("train.init_reopen: needs train.init (it restarts blending weights of the init file)")
        for entry in self.init_reopen:
            if not (isinstance(entry, str) and re.fullmatch(r"[A-Za-z_]\w*:\d+", entry)):
                raise ConfigError(f"train.init_reopen: entries are '<branch>:<level>' (e.g. 'specular:1'), "
                                  f"got {entry!r}")
        if not all(isinstance(k, str) and k and isinstance(v, (int, float)) and not isinstance(v, bool)
                   and math.isfinite(v) and v > 0 for k, v in self.lr_mult.items()):
            raise ConfigError(f"train.lr_mult: expected {{parameter-name pattern: factor > 0}}, got {self.lr_mult!r}")
        if not all(isinstance(p, str) and p for p in self.train_only):
            raise ConfigError(f"train.train_only: expected a list of parameter-name patterns, got {self.train_only!r}")
        if self.distill_min_spp is not None:
            if not self.init:
                raise ConfigError("train.distill_min_spp: needs train.init (its model is the teacher)")
            _at_least("train", self, "distill_min_spp", 1)
        if not (isinstance(self.distill_tta, int) and 1 <= self.distill_tta <= 8):
            raise ConfigError(f"train.distill_tta: the number of flips and transposes, 1 to 8, got "
                              f"{self.distill_tta!r}")
        if self.init_prune and not self.init_extend:
            raise ConfigError("train.init_prune: needs train.init_extend (it narrows what extending maps)")
        if self.precision not in PRECISIONS:
            raise ConfigError(f"train.precision: expected {' or '.join(PRECISIONS)}, got {self.precision!r}")
        if not (self.device in ("auto", "cpu") or re.fullmatch(r"cuda(:\d+)?", self.device)):
            raise ConfigError(f"train.device: expected auto, cpu, cuda or cuda:<index>, got {self.device!r}")

    def loss_of(self, stage: int) -> tuple[str, dict]:
        """The loss name and its parameters in ``stage`` (1: each branch on its target; 2: the colour)."""
        if stage == 1 or self.stage2_loss in (None, self.loss):
            params = self.loss_params if stage == 1 or self.stage2_loss_params is None else self.stage2_loss_params
            return self.loss, params
        return self.stage2_loss, self.stage2_loss_params or {}


def check_model_section(model: dict) -> dict:
    """``model`` with older layouts flattened (``extra:``), checked against the model's config dataclass."""
    from .models import is_model, list_models, model_config_class

    model = dict(model)
    model.update(model.pop("extra", None) or {})
    name = model.get("name")
    if not is_model(name):
        raise ConfigError(f"model.name: unknown model {name!r}; known: {', '.join(list_models())}")
    params = {k: v for k, v in model.items() if k != "name"}
    from_dict(model_config_class(name), params, where="model")  # raises on an unknown key or a wrong type
    return model


@dataclass
class RunConfig:
    name: str = "default"
    results_dir: str = "results"
    model: dict = field(default_factory=lambda: {"name": "kpcn"})
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        name = PurePath(self.name)
        if not name.parts or name.is_absolute() or ".." in name.parts or self.name.strip() != self.name:
            raise ConfigError(f"name: must be a folder name under results_dir (not empty, not absolute, "
                              f"no '.' or '..'), got {self.name!r}")
        if not self.results_dir:
            raise ConfigError("results_dir: must not be empty (use '.' for the current folder)")
        self.model = check_model_section(self.model)

    @property
    def run_dir(self) -> Path:
        return Path(self.results_dir) / self.name

