"""A frame's exposure key, and the scale that brings it into the range a model was trained on.

A learned denoiser is not exposure-invariant: the same render in other radiance units (a scene lit 100× brighter
with every surface 100× darker, a renderer in physical units, an exposure change before saving) gives another
result, and far outside the brightness of the training frames a worse one (the default at 16 spp, 16 report
scenes: PSNR 38.87 dB at their own exposure, 33.00 with every radiance layer × 0.01; docs/measured.md,
thirty-eighth session). The key measures a frame's brightness robustly:

* the luminance (Rec. 709 weights) of the noisy colour, a negative one as 0;
* averaged over blocks of :data:`BLOCK` × :data:`BLOCK` pixels (partial blocks at the right and bottom over the
  pixels they have), so that a sparse low-spp frame — a few bright samples on black — has the key of its mean;
* the geometric mean of the blocks' luminances above :data:`KEY_EPS` times the brightest block's (black blocks,
  the sky of an empty background, do not pull it to zero; relative, so that the key of a frame × s is s times
  its key at any s); 0 for a black frame.

It hardly depends on the sample count (procedural scenes: 2 spp and 256 spp within a few per cent). A model declares
``exposure_range = (lo, hi)``, the keys of the frames it was trained on. Inside the range nothing is scaled: the
result is what the model gives the frame as it is. A frame whose key lies outside is denoised at the key
:func:`exposure_scale` gives — every radiance layer × ``s``, its variance × ``s²`` (:func:`scale_layers`, or
:class:`ScaledLayers` as it is read) — and
the result divided by ``s`` (:func:`kpcn.inference.denoise`): the range's centre ``sqrt(lo hi)`` for a frame more than
:data:`TRANSITION` × beyond a bound, and between the bound and the centre (log-linear in the key) in that last
factor, so that the result changes continuously with the exposure. The centre rather than the nearer bound: at a
bound the network works in one end of its input transform, and the report's 16 scenes at × 0.01 of their
exposure, denoised at the bound, lost 0.47 dB at 4 spp against their own exposure; at the centre they lost none.

``python -m kpcn.exposure ROOT...`` prints the keys of a data set's input frames (where a range comes from).
"""
from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["BLOCK", "KEY_EPS", "TRANSITION", "TRAINED_KEYS", "LUMINANCE", "SCALE_LIMIT", "frame_key", "exposure_scale",
           "scale_layers", "ScaledLayers", "scale_array", "RADIANCE_LAYERS", "check_exposure_range", "check_exposure_gain"]

#: side of the blocks whose mean luminances the key averages (pixels)
BLOCK = 16
#: blocks at or below this fraction of the brightest block's luminance are left out of the key
KEY_EPS = 1e-8
#: the factors exposure_scale returns stay within [1 / SCALE_LIMIT, SCALE_LIMIT] (float32 radiance, and its
#: variance times the factor squared, stay finite; a frame dimmer than that is black to float32's precision)
SCALE_LIMIT = 1e18
#: Rec. 709 luminance weights of R, G, B
LUMINANCE = (0.2126, 0.7152, 0.0722)
#: beyond a bound, the factor of exposure over which the key a frame is denoised at moves from the bound to the centre
TRANSITION = 2.0
#: the keys of kpcn's procedural training frames, their 2nd and 98th percentiles rounded (data/f1 and data/f2: 1392
#: frames at 2-256 spp, 0.032 and 0.997; ``python -m kpcn.exposure data/f1 data/f2``); Blender Cycles' generated
#: scenes lie inside (0.12-0.41 at 4 spp): the range the shipped defaults carry
TRAINED_KEYS = (0.03, 1.0)
#: the layers that are radiance (scaled by ``s``; a ``<name>Variance`` layer beside one by ``s²``)
RADIANCE_LAYERS = ("color", "diffuse", "specular")


def frame_key(color: np.ndarray | torch.Tensor) -> float:
    """The exposure key of a colour ``(H, W, 3)``: the geometric mean of its :data:`BLOCK`-pixel blocks' mean
    luminances above :data:`KEY_EPS` times the brightest's (module docstring); 0.0 for a black frame."""
    c = torch.as_tensor(color)
    if c.ndim != 3 or c.shape[-1] != 3:
        raise ValueError(f"frame_key: expected a colour (H, W, 3), got shape {tuple(c.shape)}")
    lum = (c.float() @ torch.tensor(LUMINANCE, dtype=torch.float32)).clamp_min_(0.0)  # one pass (a matrix product)
    # partial blocks are averaged over the pixels they have (ceil_mode leaves the missing ones out of the divisor)
    blocks = F.avg_pool2d(lum[None, None], BLOCK, ceil_mode=True).reshape(-1).double()
    blocks = blocks[blocks > KEY_EPS * float(blocks.max())] if blocks.numel() else blocks
    blocks = blocks[blocks > 0]
    return float(torch.exp(torch.log(blocks).mean())) if blocks.numel() else 0.0


def check_exposure_range(key_range, who: str = "exposure_range") -> tuple[float, float] | None:
    """``key_range`` as ``(lo, hi)`` floats with ``0 < lo <= hi`` (finite), or None; a clear error otherwise."""
    if key_range is None:
        return None
    try:
        lo, hi = (float(v) for v in key_range)
    except (TypeError, ValueError):
        raise ValueError(f"{who} must be None or two numbers (lo, hi), got {key_range!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(f"{who} must satisfy 0 < lo <= hi (finite), got {key_range!r}")
    return lo, hi


def check_exposure_gain(gain, who: str = "exposure_gain") -> float:
    """``gain`` as a float in ``[1 / 16, 16]``; a clear error otherwise."""
    try:
        g = float(gain)
    except (TypeError, ValueError):
        raise ValueError(f"{who} must be a number, got {gain!r}") from None
    if isinstance(gain, bool) or not 1 / 16 <= g <= 16:
        raise ValueError(f"{who} must be a number in [1/16, 16] (1: the frame's own exposure), got {gain!r}")
    return g


def exposure_scale(key: float, key_range: Sequence[float] | None, gain: float = 1.0) -> float:
    """The factor a frame of exposure ``key`` is denoised at, for a model trained on keys ``key_range``
    ``(lo, hi)``: 1.0 inside the range (and for no range, or a black frame, ``key`` 0). Outside, the factor that
    takes ``key`` to ``bound · (centre / bound)^t``, with ``bound`` the nearer bound, ``centre = sqrt(lo hi)`` and
    ``t = min(1, |log(key / bound)| / log(TRANSITION))``: the centre once the frame is :data:`TRANSITION` × beyond
    the bound, and continuous in ``key`` everywhere.

    ``gain`` (a model's ``exposure_gain``): the frame is first scaled by it, then as above: ``gain ·
    exposure_scale(gain · key, key_range)``."""
    if gain != 1.0:
        check_exposure_gain(gain)
        return gain * exposure_scale(gain * key, key_range)
    rng = check_exposure_range(key_range)
    if rng is None or not key > 0:
        return 1.0
    lo, hi = rng
    if lo <= key <= hi:
        return 1.0
    bound = lo if key < lo else hi
    centre = math.sqrt(lo * hi)
    t = min(1.0, abs(math.log(key / bound)) / math.log(TRANSITION))
    return min(max(bound * (centre / bound) ** t / key, 1.0 / SCALE_LIMIT), SCALE_LIMIT)


def scale_layers(layers: Mapping[str, np.ndarray], s: float, extra: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """A copy of ``layers`` with every radiance layer (:data:`RADIANCE_LAYERS` and ``extra``, e.g. light groups)
    × ``s`` and its ``<name>Variance`` × ``s²``; other layers (albedo, normal, depth) are the same arrays."""
    return dict(ScaledLayers(layers, s, extra))


class ScaledLayers(Mapping):
    """``layers`` as :func:`scale_layers` gives them, each scaled when it is read rather than all copied at once.

    A :class:`~kpcn.io.Frame` over these (``Frame(ScaledLayers(frame.layers, s), ...)``) reads as the scaled frame,
    and :meth:`region` scales only the rows and columns asked for: :func:`kpcn.inference.denoise` denoises a frame
    at another exposure a band of rows at a time without holding a scaled copy of every radiance layer and variance
    (up to 150 MB at 1920×1080). Reading a whole layer returns a new scaled array each time (the other layers are
    the same arrays, unscaled); :attr:`raw` is the mapping underneath.
    """

    def __init__(self, layers: Mapping[str, np.ndarray], s: float, extra: Sequence[str] = ()) -> None:
        names = set(RADIANCE_LAYERS) | set(extra)
        self.raw, self.scale = layers, float(s)
        #: how many factors ``s`` each scaled layer takes: 1 for radiance, 2 for its variance (× s twice: s² may
        #: overflow where s does not)
        self.powers = {n: 1 if n in names else 2 for n in layers
                       if n in names or (n.endswith("Variance") and n[: -len("Variance")] in names)}

    def region(self, name: str, crop=None) -> np.ndarray:
        """Layer ``name`` over ``crop`` (a ``(rows, columns)`` pair of slices; None: all of it), scaled."""
        a = self.raw[name]
        if crop is not None:
            a = a[crop]
        for _ in range(self.powers.get(name, 0)):
            a = scale_array(a, self.scale)
        return a

    def __getitem__(self, name: str) -> np.ndarray:
        return self.region(name)

    def __contains__(self, name) -> bool:
        return name in self.raw

    def __iter__(self):
        return iter(self.raw)

    def __len__(self) -> int:
        return len(self.raw)


def scale_array(a: np.ndarray, s: float) -> np.ndarray:
    """``a × s`` in float32, values beyond float32's range held at its largest (a huge variance stays a huge finite
    one, which the features bound and report, rather than turning into an infinity)."""
    with np.errstate(over="ignore"):
        out = (a * np.float32(s)).astype(np.float32, copy=False)
    big = np.finfo(np.float32).max
    return np.clip(out, -big, big, out=out) if s > 1 else out


def _dataset_keys(roots: Sequence[str]) -> None:
    """Print the keys of the input frames under ``roots`` (EXR files named ``input*.exr``): percentiles per spp."""
    from pathlib import Path

    from .io import read_exr

    keys: dict[int, list[float]] = {}
    for root in roots:
        for path in sorted(Path(root).rglob("input*.exr")):
            frame = read_exr(path, require=())
            keys.setdefault(int(frame.meta.get("spp", 0) or 0), []).append(frame_key(frame.beauty()))
    if not keys:
        raise SystemExit(f"no input*.exr frames under {', '.join(roots)}")
    pct = (0, 2, 10, 50, 90, 98, 100)
    allk = np.concatenate([np.asarray(v) for v in keys.values()])
    print(f"{allk.size} frames; key percentiles {pct}: {' '.join(f'{v:.4g}' for v in np.percentile(allk, pct))}")
    for spp in sorted(keys):
        v = np.percentile(keys[spp], pct)
        print(f"  {spp:>5} spp ({len(keys[spp])} frames): {' '.join(f'{x:.4g}' for x in v)}")


if __name__ == "__main__":
    import sys

    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        print("usage: python -m kpcn.exposure ROOT [ROOT ...]  (the exposure keys of the input frames under ROOT)")
        raise SystemExit(0 if len(sys.argv) >= 2 else 2)
    _dataset_keys(sys.argv[1:])
