"""Rendered data sets, patch sampling and torch ``Dataset`` s.

A data set folder is what ``python -m kpcn.render dataset`` writes: one folder
per scene with ``input_<spp>spp.exr`` files and a ``reference.exr``, and a
``manifest.json`` listing them. Each (input, reference) pair is a *frame*.

Patches follow the paper: 65×65 by default, their number scaled to the frame
area (400 per 1280×720 frame), drawn uniformly or by importance — dart throwing
over a pdf built from the colour variance and the normal variance, each mapped
to [0, 1] (Bako et al. 2017 §5; CN113947547A claim 4).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from .augment import check_mix_spec, mix_patches
from .features import frame_to_tensors
from .inputs import InputSpec, get_input_spec
from .io import Frame, read_exr
from .sample_maps import region_mask

PAPER_PATCHES_PER_PIXEL = 400 / (1280 * 720)

#: the ``spp`` label of a converged pair (its input is the reference render itself)
CONVERGED_SPP = 0


@dataclass
class FramePair:
    scene: str
    spp: int
    input_path: Path
    reference_path: Path
    #: the manifest's render records of the input and the reference (None: not recorded); part of
    #: the patch store's fingerprint of the frame (:mod:`kpcn.store`)
    records: dict | None = field(default=None, compare=False, repr=False)


def read_manifest(root: str | Path, spp: Sequence[int] | None = None) -> list[FramePair]:
    """The (input, reference) pairs of a rendered data set, optionally only some spp.

    Only a usable data set is read: its manifest must say ``"complete": true``
    (written after the last scene of ``python -m kpcn.render dataset``) and
    every frame it lists must exist. A manifest written before kpcn recorded
    completeness (no ``"format"`` key) cannot tell an interrupted render from
    a smaller complete one: it is read with a ``UserWarning`` when all its
    files exist (see :mod:`kpcn.render.manifest`).

    Raises:
        FileNotFoundError: ``root`` has no manifest.json.
        DatasetError: (a ``ValueError``) an incomplete data set ("N of M scenes
            rendered", with the command that finishes it), missing frames, a
            damaged manifest, or requested ``spp`` the data set does not have.
    """
    from .render.manifest import DatasetError, check_usable, dataset_status

    root = Path(root)
    status = dataset_status(root)
    if status.manifest is None:
        raise FileNotFoundError(f"{root}: no manifest.json — render one with `python -m kpcn.render dataset --out {root}`")
    check_usable(status)
    if spp is not None:
        absent = sorted(set(int(s) for s in spp) - set(status.settings["spp"]))
        if absent:
            raise DatasetError(f"{root}: no inputs at {' '.join(map(str, absent))} spp; the data set has "
                               f"{' '.join(map(str, status.settings['spp']))} spp")
    pairs = []
    for sc in status.manifest["scenes"]:
        frames = sc.get("frames") or {}
        for s, rel in sc["inputs"].items():
            if spp is None or int(s) in spp:
                records = {"input": frames.get(rel), "reference": frames.get(sc["reference"])} if frames else None
                pairs.append(FramePair(sc["name"], int(s), root / rel, root / sc["reference"], records))
    return pairs


DEFAULT_SPEC = "kpcn_split"


def read_pair(pair: FramePair, spec: InputSpec | str = DEFAULT_SPEC) -> tuple[Frame, Frame]:
    """The noisy and the reference frame of a pair, checked for the layers ``spec`` needs."""
    spec = get_input_spec(spec)
    noisy = read_exr(pair.input_path, require=tuple(dict.fromkeys(spec.layers + ("color",))))
    ref = read_exr(pair.reference_path, require=spec.target_layers)
    return spec.select(noisy), ref


def load_pair(pair: FramePair, spec: InputSpec | str = DEFAULT_SPEC) -> dict[str, torch.Tensor]:
    """Inputs and targets of one whole frame, ``(1, C, H, W)`` tensors."""
    return pair_tensors(*read_pair(pair, spec), spec=spec)


def pair_tensors(noisy: Frame, ref: Frame, spec: InputSpec | str = DEFAULT_SPEC) -> dict[str, torch.Tensor]:
    """The model inputs of ``noisy`` (as ``spec`` builds them), targets from ``ref``, ``noisy_color`` and
    ``noisy_normal``.

    All ``(1, C, H, W)``: one entry per branch plus ``albedo``, ``y_<branch>``,
    ``y_color``, ``noisy_color`` and, where the spec reads the normal, ``noisy_normal`` (the guide of a model's
    detail stage, which training's ``train.detail_stage`` applies as the pipeline does).
    """
    spec = get_input_spec(spec)
    inputs = spec.build(frame_to_tensors(noisy, spec.layers))
    targets = spec.targets(frame_to_tensors(ref, spec.target_layers), inputs)
    out = {**inputs, **targets}
    out["noisy_color"] = frame_to_tensors(noisy, ("color",))["color"]
    if "normal" in spec.layers:
        out["noisy_normal"] = frame_to_tensors(noisy, ("normal",))["normal"]
    return out


def model_inputs(net, tensors: dict) -> dict:
    """The entries of ``tensors`` (:func:`pair_tensors`' dict, or a batch of such) that ``net`` reads: its spec's
    branches and the albedo, and the noisy frame's normal as ``"normal"`` for a model that reads it
    (:attr:`~kpcn.models.DenoiserModel.reads_normal`)."""
    out = {k: tensors[k] for k in (*net.branches, "albedo")}
    if net.reads_normal:
        if "noisy_normal" not in tensors:
            raise ValueError(f"{net.name or type(net).__name__} reads the frame's normal; the batch has none")
        out["normal"] = tensors["noisy_normal"]
    return out


# ----------------------------------------------------------------------------- patch sampling


def patch_count(height: int, width: int, per_pixel: float = PAPER_PATCHES_PER_PIXEL) -> int:
    """Number of patches for a frame: the paper's 400 per 1280×720, at least one."""
    return max(1, int(round(height * width * per_pixel)))


def _to01(x: np.ndarray) -> np.ndarray:
    """Map a non-negative map to [0, 1] robustly (divide by its 99th percentile, clip)."""
    x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)
    top = np.percentile(x, 99.0)
    if top <= 0:
        top = x.max()
    return np.clip(x / top, 0.0, 1.0) if top > 0 else np.zeros_like(x)


def importance_map(color_variance: np.ndarray, normal_variance: np.ndarray) -> np.ndarray:
    """Per-pixel importance ``(H, W)`` in [0, 1] from colour and normal variance ``(H, W[, C])``."""
    cv = color_variance.mean(-1) if color_variance.ndim == 3 else color_variance
    nv = normal_variance.mean(-1) if normal_variance.ndim == 3 else normal_variance
    return 0.5 * (_to01(cv) + _to01(nv))


def _window_means(m: np.ndarray, size: int) -> np.ndarray:
    """Mean of ``m`` over every ``size``×``size`` window (top-left anchored), via an integral image."""
    ii = np.pad(m, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    s = ii[size:, size:] - ii[:-size, size:] - ii[size:, :-size] + ii[:-size, :-size]
    return s / (size * size)


def sample_patches(
    height: int,
    width: int,
    n: int,
    size: int = 65,
    importance: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
    candidates: int = 8,
    uniform_mix: float = 0.2,
) -> np.ndarray:
    """Top-left corners ``(n, 2)`` of ``size``×``size`` patches inside an ``height``×``width`` frame.

    Without ``importance`` the corners are uniform. With it, dart throwing:
    ``candidates * n`` uniform darts, each scored by the mean importance of its
    patch, then ``n`` kept without replacement with probability proportional to
    ``score + uniform_mix * mean(score)`` (the floor keeps easy regions in the
    training set so the model learns not to blur what is already clean).
    Frames smaller than ``size`` give patches clipped to the frame (corner 0).
    """
    rng = rng or np.random.default_rng()
    hy, hx = max(height - size, 0) + 1, max(width - size, 0) + 1
    if importance is None:
        return np.stack([rng.integers(0, hy, n), rng.integers(0, hx, n)], axis=1)
    k = max(n, candidates * n)
    darts = np.stack([rng.integers(0, hy, k), rng.integers(0, hx, k)], axis=1)
    sz = min(size, height, width)
    win = _window_means(importance.astype(np.float64), sz)
    score = win[np.minimum(darts[:, 0], win.shape[0] - 1), np.minimum(darts[:, 1], win.shape[1] - 1)]
    p = score + uniform_mix * max(score.mean(), 1e-12)
    p = p / p.sum()
    keep = rng.choice(k, size=n, replace=False, p=p)
    return darts[keep]


# ----------------------------------------------------------------------------- datasets


class PatchDataset(Dataset):
    """Training patches over a rendered data set.

    Without ``store`` the frames are loaded once and kept in memory as the
    float32 tensors ``spec`` builds. With ``store`` (a folder, see
    :mod:`kpcn.store`) each frame is preprocessed once into that folder (only
    frames missing there or stale are) and patches are cropped from memory
    maps, opened lazily in each process (DataLoader workers open their own):
    memory does not grow with the data set. Both give the same patch positions
    for the same ``(seed, epoch)`` and the same items, to the store's float16
    rounding (:data:`kpcn.store.HALF_RTOL`) on the channels it keeps in float16.

    :meth:`resample` draws a new set of patch positions (call it at each epoch).
    Items are dicts of float32 ``(C, size, size)`` tensors: one per branch of the spec
    (``diffuse``, ``specular`` for the split specs), ``albedo``, ``y_<branch>``,
    ``y_color`` and ``noisy_color``; where ``pairs`` hold converged pairs (spp
    :data:`CONVERGED_SPP`), also ``converged``: a 0-d bool tensor, True on their patches; with
    ``label_spp``, also ``spp``: a 0-d int64 tensor, the input's samples per pixel (``CONVERGED_SPP`` for a
    converged pair).

    With ``spp_mix`` > 0 that fraction of the patches (drawn per patch, seeded by the seed, the epoch and the
    index) are made of two inputs of the same scene at different spp: one's pixels inside a random smooth region
    (:func:`kpcn.sample_maps.region_mask`), the other's outside (:func:`kpcn.augment.mix_patches`), as a frame
    from an adaptive sampler has more samples in some regions than in others. Converged pairs are never mixed; ``spp``
    labels stay the first input's.
    """

    def __init__(
        self,
        pairs: Sequence[FramePair],
        patch_size: int = 65,
        patches_per_frame: int | None = None,
        sampling: str = "importance",
        seed: int = 0,
        spec: InputSpec | str = DEFAULT_SPEC,
        store: str | Path | None = None,
        progress: bool = False,
        store_workers: int | None = None,
        label_spp: bool = False,
        spp_mix: float = 0.0,
    ):
        if sampling not in ("importance", "uniform"):
            raise ValueError(f"sampling must be 'importance' or 'uniform', got {sampling!r}")
        if not pairs:
            raise ValueError("PatchDataset: no frames")
        self.pairs = list(pairs)
        self._flag_converged = any(p.spp == CONVERGED_SPP for p in self.pairs)
        self.label_spp = label_spp
        self.patch_size = patch_size
        self.sampling = sampling
        self.frames, self.importance = [], []
        self.spec = get_input_spec(spec)
        self.store = None
        if store is not None:
            from .store_frames import open_store

            self.store = open_store(self.pairs, self.spec, store, importance=sampling == "importance", progress=progress,
                                    workers=store_workers)
            self.sizes = list(self.store.sizes)
        else:
            for p in self.pairs:
                noisy, ref = read_pair(p, self.spec)
                self.frames.append({k: v[0] for k, v in pair_tensors(noisy, ref, self.spec).items()})
                imp = None
                if sampling == "importance":
                    noisy.require(("colorVariance", "normalVariance"))
                    imp = importance_map(noisy["colorVariance"], noisy["normalVariance"])
                self.importance.append(imp)
            self.sizes = [tuple(fr["albedo"].shape[-2:]) for fr in self.frames]
        self.patches_per_frame = patches_per_frame
        self.seed = seed
        if not 0.0 <= float(spp_mix) <= 1.0:
            raise ValueError(f"spp_mix must be a fraction in [0, 1], got {spp_mix!r}")
        self.spp_mix = float(spp_mix)
        self.partners = self._mix_partners() if self.spp_mix > 0 else [[] for _ in self.pairs]
        if self.spp_mix > 0:
            check_mix_spec(self.spec)
        self.epoch = 0
        self.index: np.ndarray = np.zeros((0, 3), dtype=np.int64)
        self.resample(0)

    def _mix_partners(self) -> list[list[int]]:
        """For each frame, the frames it can be mixed with (:meth:`__getitem__`): inputs of the same scene and
        reference at another spp, the same size, neither a converged pair (each listed input once)."""
        by_ref: dict = {}
        for i, p in enumerate(self.pairs):
            if p.spp != CONVERGED_SPP:
                by_ref.setdefault((str(p.reference_path), self.sizes[i]), {}).setdefault(str(p.input_path), (i, p.spp))
        out = []
        for i, p in enumerate(self.pairs):
            group = by_ref.get((str(p.reference_path), self.sizes[i]), {}) if p.spp != CONVERGED_SPP else {}
            out.append(sorted(j for j, spp in group.values() if spp != p.spp))
        return out

    def resample(self, epoch: int) -> None:
        self.epoch = int(epoch)
        rng = np.random.default_rng([self.seed, epoch])
        rows = []
        for i, (h, w) in enumerate(self.sizes):
            n = self.patches_per_frame or patch_count(h, w)
            imp = None
            if self.sampling == "importance":
                imp = self.store.importance(i) if self.store is not None else self.importance[i]
            corners = sample_patches(h, w, n, self.patch_size, imp, rng)
            rows.append(np.concatenate([np.full((n, 1), i), corners], axis=1))
        self.index = np.concatenate(rows).astype(np.int64)

    def __getstate__(self) -> dict:
        # for DataLoader workers started by spawn: the spec (it holds functions) travels by its registered
        # name, the store without its memory maps (kpcn.store_frames.StoreFrames reopens them in the worker)
        state = dict(self.__dict__)
        state["spec"] = self.spec.name
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.spec = get_input_spec(state["spec"])

    def __len__(self) -> int:
        return len(self.index)

    def _crop(self, f: int, y: int, x: int) -> dict[str, torch.Tensor]:
        s = self.patch_size
        if self.store is not None:
            return self.store.crop(f, y, x, s)
        return {k: v[:, y : y + s, x : x + s] for k, v in self.frames[f].items()}

    def __getitem__(self, idx: int) -> dict[str, torch.Tensor]:
        f, y, x = (int(v) for v in self.index[idx])
        item = self._crop(f, y, x)
        if self.partners[f]:
            rng = np.random.default_rng([self.seed, self.epoch, idx, 0x5199])
            if rng.random() < self.spp_mix:
                other = self._crop(self.partners[f][int(rng.integers(len(self.partners[f])))], y, x)
                mask = torch.from_numpy(region_mask(item["albedo"].shape[-2:], rng))[None]
                item = mix_patches(item, other, mask, self.spec)
        if self._flag_converged:
            item["converged"] = torch.tensor(self.pairs[f].spp == CONVERGED_SPP)
        if self.label_spp:
            item["spp"] = torch.tensor(int(self.pairs[f].spp))
        return item


class FrameDataset(Dataset):
    """Whole frames (inputs, targets, noisy colour) for validation; items are ``(C, H, W)``."""

    def __init__(self, pairs: Sequence[FramePair], spec: InputSpec | str = DEFAULT_SPEC):
        self.pairs = list(pairs)
        self.spec = get_input_spec(spec)
        self._cache: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, idx: int) -> dict[str, torch.Tensor]:
        if idx not in self._cache:
            self._cache[idx] = {k: v[0] for k, v in load_pair(self.pairs[idx], self.spec).items()}
        return self._cache[idx]
