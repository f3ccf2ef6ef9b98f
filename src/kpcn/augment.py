"""Training augmentation: flips, transposes and colour-channel permutations of built patches; other exposures;
patches whose spp varies from pixel to pixel.

OIDN's training flips, transposes and permutes the colour channels of every
patch; kpcn does the same, but on the tensors the input spec has already
built (:mod:`kpcn.inputs`), so the data set is preprocessed once. The spec
says which channels are RGB triplets (``rgb_starts``: colour, and the
gradients of colour and albedo) and which are forward differences in x and y
(``grad_x``, ``grad_y``); every other key of a batch (``albedo``, targets
``y_*``, ``noisy_color``) is one RGB triplet.

What each transform does to a patch ``(C, H, W)``:

* **transpose** (swap x and y): the image is transposed and the ``grad_x`` and
  ``grad_y`` channel blocks trade places — exactly the features of the
  transposed frame;
* **flip in x**: the image is mirrored, and the x-differences become the
  negated differences one pixel over (a forward difference of the mirrored
  image is minus the backward difference of the original). The last column's
  difference would read the pixel outside the patch: it is set to 0, which is
  what the features hold on a frame's last column anyway. Flip in y alike;
* **channel permutation**: the same permutation of R, G, B in every triplet of
  every key. Normals, depth and variances are not colours and are not permuted
  (variances are means over the channels).

Normals stay as they are under the spatial transforms: they are world-space
vectors, unrelated to the image axes (OIDN does the same).

Every transform is chosen per patch from a generator seeded by the training
seed and the step, so a resumed run sees the same augmented batches.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .exposure import frame_key
from .inputs import InputSpec, get_input_spec

__all__ = ["Augmentation", "augment_patch", "undo_flips", "augment_batch", "batch_at_exposure", "exposure_batch",
           "check_exposure_spec", "mix_patches", "check_mix_spec"]

PERMUTATIONS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))


@dataclass(frozen=True)
class Augmentation:
    """One patch's transform: flips (in x, in y), transpose, and an RGB permutation (index into ``PERMUTATIONS``)."""

    flip_x: bool = False
    flip_y: bool = False
    transpose: bool = False
    perm: int = 0

    @classmethod
    def draw(cls, g: torch.Generator, flips: bool = True, channels: bool = True) -> "Augmentation":
        r = torch.randint(0, 2, (3,), generator=g).tolist()
        p = int(torch.randint(0, len(PERMUTATIONS), (1,), generator=g))
        return cls(bool(r[0]) and flips, bool(r[1]) and flips, bool(r[2]) and flips, p if channels else 0)


def _flip_differences(x: torch.Tensor, block: tuple[int, int] | None, dim: int) -> torch.Tensor:
    """``x`` mirrored along ``dim`` (-1: x, -2: y), with the forward differences of ``block`` corrected."""
    x = x.flip(dim)
    if block is None:
        return x
    a, b = block
    d = x[..., a:b, :, :]
    fixed = torch.zeros_like(d)
    if dim == -1:  # mirrored x' = x[W-1-j]: x'[j+1] - x'[j] = -(x[W-1-j] - x[W-2-j]) = -d[j+1]
        fixed[..., :-1] = -d[..., 1:]
    else:
        fixed[..., :-1, :] = -d[..., 1:, :]
    return torch.cat([x[..., :a, :, :], fixed, x[..., b:, :, :]], dim=-3)


def _permute_rgb(x: torch.Tensor, starts, perm: tuple[int, int, int]) -> torch.Tensor:
    idx = list(range(x.shape[-3]))
    for s in starts:
        for i, j in enumerate(perm):
            idx[s + i] = s + j
    return x[..., idx, :, :]


def augment_patch(x: torch.Tensor, aug: Augmentation, spec: InputSpec | None = None) -> torch.Tensor:
    """``x`` ``(..., C, H, W)`` transformed by ``aug``: a branch tensor of ``spec``, or (``spec=None``) an RGB triplet."""
    gx, gy = (spec.grad_x, spec.grad_y) if spec is not None else (None, None)
    starts = spec.rgb_starts if spec is not None else (0,)
    if aug.transpose:
        x = x.transpose(-1, -2)
        if gx is not None:
            (a, b), (c, d) = gx, gy
            if b - a != d - c:
                raise ValueError(f"{spec.name}: grad_x {gx} and grad_y {gy} must have as many channels")
            idx = list(range(x.shape[-3]))
            idx[a:b], idx[c:d] = list(range(c, d)), list(range(a, b))
            x = x[..., idx, :, :]
    if aug.flip_x:
        x = _flip_differences(x, gx, -1)
    if aug.flip_y:
        x = _flip_differences(x, gy, -2)
    if aug.perm:
        x = _permute_rgb(x, starts, PERMUTATIONS[aug.perm])
    return x.contiguous()


def undo_flips(x: torch.Tensor, aug: Augmentation) -> torch.Tensor:
    """An image ``(..., C, H, W)`` made from a patch :func:`augment_patch` transformed, with ``aug``'s flips and
    transpose undone (in the reverse order); its channel permutation is not undone."""
    if aug.flip_y:
        x = x.flip(-2)
    if aug.flip_x:
        x = x.flip(-1)
    return x.transpose(-1, -2) if aug.transpose else x


def augment_batch(batch: dict[str, torch.Tensor], spec: InputSpec | str, g: torch.Generator,
                  flips: bool = True, channels: bool = True) -> dict[str, torch.Tensor]:
    """Each patch of ``batch`` (``(B, C, H, W)`` tensors) under its own random :class:`Augmentation`.

    Keys that are branches of ``spec`` are transformed as its features; ``(B,)`` entries (per-patch
    labels such as ``converged``) pass through; every other key is an RGB triplet.
    Patches must be square when transposes are on (the batch is stacked again).
    """
    spec = get_input_spec(spec)
    n = next(iter(batch.values())).shape[0]
    augs = [Augmentation.draw(g, flips, channels) for _ in range(n)]
    out = {}
    for k, v in batch.items():
        if v.dim() == 1:
            out[k] = v
            continue
        s = spec if k in spec.branches else None
        if s is None and v.shape[-3] != 3:
            raise ValueError(f"augment_batch: {k!r} has {v.shape[-3]} channels; only branches of {spec.name} "
                             f"and RGB (3-channel) entries can be augmented")
        out[k] = torch.stack([augment_patch(v[i], a, s) for i, a in enumerate(augs)])
    return out


# ------------------------------------------------------------------------------------------------ exposure
#: batch entries that are radiance (× s); ``y_<log branch>`` entries are log1p of radiance
_RADIANCE_KEYS = ("noisy_color", "y_color")


def _log_rescale(f: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """``log1p(s · expm1(f))``: a log1p-encoded radiance at ``s`` times the exposure."""
    return torch.log1p(s * torch.expm1(f.clamp_min(0.0)))


def _branch_at_exposure(x: torch.Tensor, s: torch.Tensor, spec: InputSpec, log: bool) -> torch.Tensor:
    """Branch features ``(B, C, H, W)`` of ``spec`` as they would be for the radiance × ``s`` ``(B, 1, 1, 1)``.

    Linear branch: colour and its gradients × s, its variance × s². log1p branch: colour f → log1p(s expm1 f),
    each gradient g (a forward difference, so f + g is the neighbour) → T(f + g) − T(f). The delta-method
    variance is an RGB mean of ``var_c / (1 + r_c)²`` (r the radiance) whose channels are not kept: it is rescaled
    as if each channel's variance were proportional to ``r_c²`` (test:glossy at 4 spp × 7: within 6 % of the
    channel's largest value; everything else exact). Normal, albedo and depth channels are unchanged."""
    x = x.clone()
    (gx, _), (gy, _) = spec.grad_x, spec.grad_y
    var = 3 if 3 in spec.variance_channels else None
    f = x[:, 0:3]
    if not log:
        for a in (0, gx, gy):
            x[:, a:a + 3] = x[:, a:a + 3] * s
        if var is not None:
            x[:, var:var + 1] = x[:, var:var + 1] * s * s
        return x
    t = _log_rescale(f, s)
    for a in (gx, gy):
        x[:, a:a + 3] = _log_rescale(f + x[:, a:a + 3], s) - t
    if var is not None:  # each channel's variance taken as proportional to its radiance squared
        r = torch.expm1(f.clamp_min(0.0))
        before = (r / (1 + r)).square().mean(1, keepdim=True)
        after = (s * r / (1 + s * r)).square().mean(1, keepdim=True)
        x[:, var:var + 1] = torch.where(before > 0, x[:, var:var + 1] * after / before.clamp_min(1e-30),
                                        x[:, var:var + 1] * s * s)
    x[:, 0:3] = t
    return x


def check_exposure_spec(spec: InputSpec | str) -> InputSpec:
    """``spec`` (resolved) if batches of it can be shown at another exposure (a diffuse/specular split); a
    ``ValueError`` naming it otherwise."""
    spec = get_input_spec(spec)
    if set(spec.branches) != {"diffuse", "specular"}:
        raise ValueError(f"exposure augmentation needs a diffuse/specular split input spec, not {spec.name!r}")
    return spec


def batch_at_exposure(batch: dict[str, torch.Tensor], spec: InputSpec | str, s: torch.Tensor
                      ) -> dict[str, torch.Tensor]:
    """A training batch of a split input spec as the same patches rendered at ``s`` ``(B,)`` times the exposure:
    the branches' features (:func:`_branch_at_exposure`), the targets in each branch's space, ``noisy_color`` and
    ``y_color``; albedo, normal and labels unchanged."""
    spec = check_exposure_spec(spec)
    s4 = s.to(torch.float32).reshape(-1, 1, 1, 1)
    out = dict(batch)
    for b in spec.branches:
        log = b in spec.log_branches
        if b in batch:
            out[b] = _branch_at_exposure(batch[b], s4, spec, log)
        y = f"y_{b}"
        if y in batch:
            out[y] = _log_rescale(batch[y], s4) if log else batch[y] * s4
    for k in _RADIANCE_KEYS:
        if k in batch:
            out[k] = batch[k] * s4
    return out


def exposure_batch(batch: dict[str, torch.Tensor], spec: InputSpec | str, g: torch.Generator, p: float,
                   key_range: tuple[float, float]) -> dict[str, torch.Tensor]:
    """Each patch, with probability ``p``, at another exposure: its key (:func:`kpcn.exposure.frame_key` of its
    noisy colour) moved to a log-uniform draw in ``key_range``, the range the model is to be used in
    (:attr:`kpcn.models.DenoiserModel.exposure_range`); the others, and black patches, as they are."""
    color = batch["noisy_color"]
    n = color.shape[0]
    pick = torch.rand(n, generator=g) < p
    u = torch.rand(n, generator=g, dtype=torch.float64)
    lo, hi = (float(v) for v in key_range)
    s = torch.ones(n, dtype=torch.float64)
    for i in torch.nonzero(pick).flatten().tolist():
        key = frame_key(color[i].permute(1, 2, 0))
        if key > 0:
            s[i] = lo * (hi / lo) ** float(u[i]) / key
    return batch_at_exposure(batch, spec, s) if bool((s != 1).any()) else batch


# ------------------------------------------------------------------------------------------------ varying spp
def check_mix_spec(spec: InputSpec | str) -> InputSpec:
    """``spec`` if its patches can be composited pixel by pixel (:func:`mix_patches`): no whole-frame value.

    Raises:
        ValueError: the spec feeds a whole frame's statistic (``frame_stat``) that a composite does not have.
    """
    spec = get_input_spec(spec)
    if spec.frame_stat is not None:
        raise ValueError(f"input spec {spec.name!r} feeds a whole-frame statistic; a patch made of two renders has "
                         f"none: its patches cannot be mixed across spp")
    return spec


def mix_patches(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], mask: torch.Tensor,
                spec: InputSpec | str) -> dict[str, torch.Tensor]:
    """One patch whose pixels come from two renders of the same view: ``a``'s where ``mask``, ``b``'s elsewhere.

    ``a`` and ``b`` are patch items (``(C, H, W)`` tensors, the same keys, crops of two inputs of one scene at
    different spp with the same reference); ``mask`` is ``(1, H, W)`` bool (:func:`kpcn.sample_maps.region_mask`).
    Every tensor is taken per pixel, which is exact for the pixel-wise channels (colour, variances, albedo,
    targets). A branch's colour gradients (the first three channels of its ``grad_x`` / ``grad_y`` blocks, forward
    differences of channels 0-2) are recomputed from the composite's colour where the two pixels they difference
    come from different renders; the gradients of normal, albedo and depth are kept from one render there (those
    layers differ between renders only by their anti-aliasing noise), and the depth channels keep each render's own
    depth scale (its largest depth, within about 1 % of the other's). Entries that are not ``(C, H, W)`` (labels)
    are ``a``'s.
    """
    spec = check_mix_spec(spec)
    out = {}
    for k, va in a.items():
        out[k] = torch.where(mask, va, b[k]) if va.dim() == 3 else va
    for name in spec.branches:
        if name not in out:
            continue
        x = out[name]
        for block, dim in ((spec.grad_x, -1), (spec.grad_y, -2)):
            if block is None:
                continue
            n = x.shape[dim] - 1
            g = x[block[0]:block[0] + 3].narrow(dim, 0, n)
            seam = mask.narrow(dim, 1, n) != mask.narrow(dim, 0, n)
            diff = x[0:3].narrow(dim, 1, n) - x[0:3].narrow(dim, 0, n)
            g.copy_(torch.where(seam, diff, g))
    return out
