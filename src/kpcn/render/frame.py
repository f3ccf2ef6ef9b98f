"""Rendering one frame: ``kpcn_split`` passes combined into a :class:`~kpcn.io.Frame`."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..constants import OIDN_ALBEDO, OIDN_NORMAL
from ..integrator import ALBEDO_REVISION, DENOISING_REVISION, MOMENT2, NORMAL_REVISION, aov_layout
from ..io import SAMPLE_COUNT, Frame, write_exr
from .scene import ensure_variant, load_scene


def pass_seed(seed: int, role: int, index: int) -> int:
    """Seed for pass ``index`` of a render; ``role`` keeps inputs and references independent."""
    return int(np.random.SeedSequence([int(seed), int(role), int(index)]).generate_state(1)[0] & 0x7FFFFFFF)


@dataclass
class RenderStats:
    seconds: float
    spp: int
    passes: int


def render_frame(
    scene: Any,
    spp: int,
    seed: int = 0,
    resolution: tuple[int, int] | None = None,
    *,
    max_depth: int = 8,
    pass_spp: int = 256,
    role: int = 0,
    loaded=None,
    params: Mapping[str, Any] | None = None,
    albedo_only: bool = False,
    first_pass: int = 0,
) -> Frame:
    """Render ``scene`` at ``spp`` samples per pixel into a :class:`~kpcn.io.Frame`.

    Args:
        scene: XML path, Mitsuba dict, ``"test:<name>"`` or ``"random:<seed>"``.
        spp: samples per pixel (>= 2, needed for variances).
        seed: base seed; the same seed gives the same image.
        resolution: ``(width, height)``; default: the scene's own film size.
        max_depth: longest path (Mitsuba's convention: 1 = emitters seen directly).
        pass_spp: samples per pass; larger renders are split into passes.
        role: 0 for noisy inputs, 1 for references — different roles never
            share seeds, so inputs and references have independent noise.
        loaded: a ``(mi.Scene, name, notes)`` from :func:`load_scene` to reuse.
        params: the XML file's ``$name`` parameters (see :func:`load_scene`).
        albedo_only: trace only the first hit: ``albedo``, ``normal`` and ``depth`` (and their
            variances) as a full render with the same arguments writes them, the radiance layers 0
            (:mod:`kpcn.render.albedo`).
        first_pass: index of the first pass's seed. A frame of passes ``0 … k-1`` and one of the same seed and role
            from ``first_pass=k`` have independent samples (:func:`extend_frame` merges them).

    Returns:
        Frame with ``color``, ``diffuse``, ``specular``, ``albedo``, ``normal``,
        ``depth`` and ``<layer>Variance`` (variance of the pixel mean), ``denoisingAlbedo`` and
        ``denoisingNormal`` (OIDN's guides, :mod:`kpcn.integrator`), and meta
        ``spp``, ``renderTimeSeconds`` (wall time of the passes), ``seed``, ``scene``,
        ``albedoRevision``, ``normalRevision`` and ``denoisingRevision`` (:data:`kpcn.integrator.ALBEDO_REVISION`,
        :data:`kpcn.integrator.NORMAL_REVISION`, :data:`kpcn.integrator.DENOISING_REVISION`).
    """
    if spp < 2:
        raise ValueError(f"spp must be >= 2 to estimate variances, got {spp}")
    mi, mi_scene, name, integrator = _setup(scene, resolution, params, loaded, max_depth, albedo_only)
    acc, seconds = None, 0.0
    for n, arr, dt in _passes(mi, mi_scene, integrator, _pass_sizes(spp, pass_spp), seed, role, first_pass):
        acc = arr * n if acc is None else acc + arr * n
        seconds += dt
    return Frame(_layers(acc / spp, spp), _meta(spp, seconds, seed, name))


def render_sample_map(
    scene: Any,
    counts: np.ndarray,
    seed: int = 0,
    resolution: tuple[int, int] | None = None,
    *,
    max_depth: int = 8,
    pass_spp: int = 256,
    role: int = 0,
    loaded=None,
    params: Mapping[str, Any] | None = None,
    first_pass: int = 0,
) -> Frame:
    """Render ``scene`` with each pixel's own number of samples, ``counts`` ``(H, W)`` (integers >= 2): what an
    adaptive sampler asks of the renderer.

    The distinct counts ``c_1 < c_2 < …`` are rendered as passes of ``c_1``, ``c_2 - c_1``, … samples (split at
    ``pass_spp``, seeded as :func:`render_frame`'s passes from ``first_pass`` on), and a pixel adds up the passes up
    to its own count: so a pixel of count ``c`` is exactly that pixel of :func:`render_frame` with the same passes
    (``render_frame(scene, c, seed, pass_spp=...)`` where the counts are multiples of ``pass_spp``), its mean and
    the variances of its mean. Mitsuba renders whole frames, so the wall time is that of ``counts.max()`` samples
    everywhere (``renderTimeSeconds``). The frame has the :data:`~kpcn.io.SAMPLE_COUNT` layer; its ``spp`` is the
    mean count, rounded. Other arguments as :func:`render_frame`.

    Raises:
        ValueError: ``counts`` is not 2-D integers >= 2, or not the film's size.
    """
    n = np.asarray(counts)
    if n.ndim != 2 or n.size == 0 or not np.all(np.isfinite(n)) or np.any(n != np.round(n)) or n.min() < 2:
        raise ValueError(f"render_sample_map: counts must be a 2-D map of integers >= 2 (variances need two "
                         f"samples), got shape {n.shape}" + (f", least {n.min()}" if n.size else ""))
    n = n.astype(np.int64)
    mi, mi_scene, name, integrator = _setup(scene, resolution, params, loaded, max_depth, False)
    film = tuple(int(v) for v in mi_scene.sensors()[0].film().crop_size())[::-1]
    if film != n.shape:
        raise ValueError(f"render_sample_map: counts are {n.shape[0]}x{n.shape[1]} (rows x columns), the film "
                         f"{film[0]}x{film[1]}")
    acc, seconds, done, index = None, 0.0, 0, first_pass
    for level in np.unique(n):
        take = (n >= level)[..., None]
        for k, arr, dt in _passes(mi, mi_scene, integrator, _pass_sizes(int(level) - done, pass_spp), seed, role,
                                  index):
            acc = np.where(take, arr * k, 0.0) if acc is None else acc + np.where(take, arr * k, 0.0)
            seconds += dt
            index += 1
        done = int(level)
    layers = _layers(acc / n[..., None], n[..., None].astype(np.float64))
    layers[SAMPLE_COUNT] = n[..., None].astype(np.float32)
    meta = _meta(int(max(round(float(n.mean())), 1)), seconds, seed, name)
    return Frame(layers, meta)


def _setup(scene, resolution, params, loaded, max_depth: int, albedo_only: bool):
    mi = ensure_variant()
    mi_scene, name, _ = loaded or load_scene(scene, resolution, params)
    integrator = mi.load_dict({"type": "kpcn_split", "max_depth": int(max_depth), "albedo_only": bool(albedo_only)})
    return mi, mi_scene, name, integrator


def _pass_sizes(spp: int, pass_spp: int) -> list[int]:
    sizes, left = [], int(spp)
    while left > 0:
        sizes.append(min(int(pass_spp), left))
        left -= sizes[-1]
    return sizes


def _passes(mi, mi_scene, integrator, sizes, seed: int, role: int, first_pass: int):
    """Each pass ``(samples, film (H, W, C) float64: the mean and second-moment channels, seconds)``."""
    n_ch = 3 + sum(c for _, c in aov_layout())
    for i, n in enumerate(sizes):
        t0 = time.perf_counter()
        img = mi.render(mi_scene, integrator=integrator, spp=n, seed=pass_seed(seed, role, first_pass + i))
        arr = np.array(img, dtype=np.float64)
        if arr.shape[-1] != n_ch:
            raise RuntimeError(f"film returned {arr.shape[-1]} channels, expected {n_ch}")
        yield n, arr, time.perf_counter() - t0


def _layers(acc: np.ndarray, n) -> dict[str, np.ndarray]:
    """The layers and their variances of the mean from the per-sample means ``acc`` of ``n`` samples (a number or
    ``(H, W, 1)``)."""
    raw: dict[str, np.ndarray] = {}
    c0 = 0
    layout = [("color", 3)] + aov_layout()
    for layer, c in layout:
        raw[layer] = acc[..., c0 : c0 + c]
        c0 += c
    layers = {layer: raw[layer].astype(np.float32) for layer, _ in layout if not layer.endswith("_m2")}
    for layer, _ in MOMENT2:
        var = (raw[f"{layer}_m2"] - raw[layer] ** 2) / (n - 1)
        layers[f"{layer}Variance"] = np.maximum(var, 0.0).astype(np.float32)
    return layers


def _meta(spp: int, seconds: float, seed: int, name) -> dict:
    return {"spp": int(spp), "renderTimeSeconds": float(seconds), "seed": int(seed), "scene": str(name),
            "albedoRevision": ALBEDO_REVISION, "normalRevision": NORMAL_REVISION,
            "denoisingRevision": DENOISING_REVISION}


def render_to_exr(scene: Any, out: str | os.PathLike, spp: int, seed: int = 0, *,
                  meta: Mapping[str, Any] | None = None, **kw) -> Frame:
    """Render and write one EXR (atomically). Returns the frame.

    ``meta``: extra header attributes (int, float or str), added to ``frame.meta``.
    """
    frame = render_frame(scene, spp, seed, **kw)
    frame.meta.update(meta or {})
    write_exr(out, frame.layers, frame.meta)
    frame.path = os.fspath(out)
    return frame


def n_passes(spp: int, pass_spp: int = 256) -> int:
    """How many passes :func:`render_frame` splits ``spp`` samples into."""
    return -(-int(spp) // int(pass_spp))


def _counts(frame: Frame, who: str) -> np.ndarray:
    n = frame.sample_count()
    if n is None:
        raise ValueError(f"{who}: a frame gives neither a {SAMPLE_COUNT} layer nor an spp in its header")
    return n[..., None]


def _same_view(a: Frame, b: Frame, who: str) -> list[str]:
    names = sorted(set(a.layers) - {SAMPLE_COUNT})
    if names != sorted(set(b.layers) - {SAMPLE_COUNT}):
        raise ValueError(f"frames to {who} have different layers: {sorted(a.layers)} and {sorted(b.layers)}")
    if a.shape != b.shape:
        raise ValueError(f"frames to {who} have different sizes: {a.shape} and {b.shape}")
    return names


def _mean_spp_meta(meta: dict, n: np.ndarray, **more) -> dict:
    """``meta`` with ``spp`` the mean samples per pixel (rounded) of the counts ``n``."""
    return {**meta, "spp": int(max(round(float(n.mean())), 1)), **more}


def merge_frames(a: Frame, b: Frame) -> Frame:
    """One frame from two renders of the same view with independent samples.

    Every layer is the sample-weighted mean; each ``<layer>Variance`` (variance of the pixel mean) is recomputed from
    the two parts' per-sample second moments, as :func:`render_frame` computes it from the passes it adds up, so a
    frame of passes ``0 … k-1`` merged with passes ``k … n-1`` is the frame of passes ``0 … n-1`` (to float32
    rounding). The weights are each pixel's samples (:meth:`~kpcn.io.Frame.sample_count`: a frame's
    :data:`~kpcn.io.SAMPLE_COUNT` layer, else its ``spp``), so frames whose spp varies per pixel merge pixel by
    pixel; the result has a :data:`~kpcn.io.SAMPLE_COUNT` layer where either part had one. Meta: ``a``'s, with
    ``spp`` the sum (the mean per pixel, rounded, with a count layer) and ``renderTimeSeconds`` the sum of both.

    Raises:
        ValueError: the frames' layers or sizes differ, or a frame gives no sample count.
    """
    names = _same_view(a, b, "merge")
    na, nb = _counts(a, "merge_frames"), _counts(b, "merge_frames")
    n = na + nb
    out: dict[str, np.ndarray] = {}
    for name in names:
        if name.endswith("Variance"):
            continue
        ma, mb = a[name].astype(np.float64), b[name].astype(np.float64)
        m = (na * ma + nb * mb) / n
        out[name] = m.astype(np.float32)
        vname = f"{name}Variance"
        if vname in a.layers:
            # per-sample second moments back from each part's variance of the mean: var = (m2 - m^2) / (n - 1)
            m2 = (na * (a[vname].astype(np.float64) * (na - 1) + ma**2)
                  + nb * (b[vname].astype(np.float64) * (nb - 1) + mb**2)) / n
            out[vname] = np.maximum((m2 - m**2) / np.maximum(n - 1, 1), 0.0).astype(np.float32)
    seconds = float(a.meta.get("renderTimeSeconds", 0.0)) + float(b.meta.get("renderTimeSeconds", 0.0))
    if SAMPLE_COUNT in a.layers or SAMPLE_COUNT in b.layers:
        out[SAMPLE_COUNT] = n.astype(np.float32)
        return Frame(out, _mean_spp_meta(a.meta, n, renderTimeSeconds=seconds))
    return Frame(out, {**a.meta, "spp": int(a.spp) + int(b.spp), "renderTimeSeconds": seconds})


def mix_frames(a: Frame, b: Frame, mask: np.ndarray) -> Frame:
    """A frame whose spp varies per pixel: ``a``'s pixels where ``mask`` is True, ``b``'s elsewhere.

    ``a`` and ``b`` are renders of one view (say at 4 and 64 spp); each pixel of the result is still the mean of
    its own samples, with the variances of that mean, and its :data:`~kpcn.io.SAMPLE_COUNT` layer says how many
    (what an adaptive sampler writes, made from renders at uniform spp). Meta: ``a``'s, ``spp`` the mean samples per
    pixel (rounded), ``renderTimeSeconds`` dropped (the samples' time is not known per pixel).

    Raises:
        ValueError: the frames' layers or sizes differ, ``mask`` is not ``(H, W)``, or a frame gives no count.
    """
    names = _same_view(a, b, "mix")
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != a.shape:
        raise ValueError(f"mix_frames: the mask is {mask.shape}, the frames {a.shape}")
    m = mask[..., None]
    out = {k: np.where(m, a[k], b[k]) for k in names}
    n = np.where(m, _counts(a, "mix_frames"), _counts(b, "mix_frames"))
    out[SAMPLE_COUNT] = n.astype(np.float32)
    meta = {k: v for k, v in a.meta.items() if k != "renderTimeSeconds"}
    return Frame(out, _mean_spp_meta(meta, n))


def extend_frame(frame: Frame, scene: Any, spp: int, seed: int = 0, *, role: int = 0, pass_spp: int = 256,
                 **kw) -> Frame:
    """``frame`` (a :func:`render_frame` of ``seed`` and ``role``) with more samples: ``spp`` in all.

    The added samples are the passes after ``frame``'s own (:func:`n_passes`), so they are independent of it, and
    when ``frame.spp`` is a multiple of ``pass_spp`` the result is the direct render of ``spp`` samples. ``kw`` goes
    to :func:`render_frame` (``resolution``, ``max_depth``, ``loaded``, ...).

    A frame rendered before the denoising guides (no ``denoisingAlbedo``/``denoisingNormal``) is extended without
    them, as its header says (:func:`kpcn.render.albedo.update_first_hit` adds them).

    Raises:
        ValueError: ``spp`` is not above ``frame.spp``, or fewer than 2 samples would be added.
    """
    more = int(spp) - int(frame.spp)
    if more < 2:
        raise ValueError(f"extend_frame: {spp} spp is not at least 2 above the frame's {frame.spp}")
    extra = render_frame(scene, more, seed, role=role, pass_spp=pass_spp, first_pass=n_passes(frame.spp, pass_spp),
                         **kw)
    for name in (OIDN_ALBEDO, OIDN_NORMAL):  # a frame from before the denoising guides stays without them
        if name not in frame.layers:
            extra.layers.pop(name, None)
    return merge_frames(frame, extra)
