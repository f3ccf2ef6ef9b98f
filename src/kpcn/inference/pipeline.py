"""Denoise one frame: read, build the model's inputs tile by tile, run it, write.

How a frame is processed
------------------------
* The file is read with :func:`kpcn.io.read_exr`, requiring the layers of the
  model's input spec (a missing layer is named, with the layers found).
  NaN/Inf are replaced and counted by the reader; a :class:`Frame` given in
  memory is sanitised the same way (on a copy).
* **Tiles with a halo** (:mod:`.tiling`): ``halo = model.receptive_radius +
  spec.halo`` (the features read ``spec.halo`` pixels further: forward
  differences), crop corners on multiples of ``model.alignment``. Each tile's
  inputs are built from its crop (with whole-frame values where the spec needs
  them: the depth normaliser); only the interior is kept. A model with
  whole-frame context gets it computed once, over the whole frame
  (:meth:`~kpcn.models.DenoiserModel.frame_context`), and every tile uses it.
  So tiled equals untiled, to float rounding.
* **Row bands**: a frame run whole (one tile) by a model with row streams (the
  ``stem: half`` U-Net) goes through :mod:`.rows` instead: features built a band
  of rows at a time, the network once at half resolution, the output assembled
  band by band (same result to float rounding; ``rows=False`` turns it off).
* **Exposure**: a model that declares ``exposure_range`` (the default U-Net) denoises a frame whose exposure key
  lies outside it at the range's centre (:func:`kpcn.exposure.exposure_scale`: continuous in the key) — its
  radiance layers scaled, the result scaled back; a frame inside is denoised as it is. A model with an
  ``exposure_gain`` ``g`` scales every frame by ``g`` first (the range then applies to the key ``g`` times the
  frame's). The radiance is scaled as it is read, a band's or a tile's rows at a time
  (:class:`kpcn.exposure.ScaledLayers`, ``Frame.region``; the detail stage's noisy colour too): no scaled copy of
  the frame is held.
* **What a frame does not need is left out** (``skip=True``, the default):

  - a branch with no positive radiance anywhere in the frame is not run and
    its inputs are not built (for a ``zero_preserving`` model — a kernel
    predictor — this is exact; for DPCN the skipped component is 0, which is
    the correct radiance there, where the network would add a small residual);
  - ``zero_preserving`` models only, per tile: a branch that is zero on the
    tile's crop is not run on that tile (exact);
  - a tile whose crop has no geometry (depth <= 0) and converged colour
    (variance of the mean <= ``(PASSTHROUGH_REL_STD * colour)^2``) is passed
    through (needs depth and a colour variance in the file).
"""
from __future__ import annotations

import contextlib
import os
import time
import warnings

import numpy as np
import torch

from ..exposure import ScaledLayers, exposure_scale, frame_key, scale_array
from ..features import frame_to_tensors
from ..io import SAMPLE_COUNT, Frame
from .aovs import denoise_aovs, noisy_aov, plan_aovs
from .detail import refine_detail
from .ensemble import check_views, ensemble_result
from .frames import as_frame, check_output, color_variance, default_model, validate, with_normal, write_output
from .heap import reuse_heap
from .precision import compute_dtype, resolve_precision
from .results import DenoiseResult, DenoiseStats, peak_rss_mb
from .rows import denoise_rows, supports_rows
from .tiling import auto_tile, plan_tiles, tile_size
from .weights import describe, load_model, resolve_device

__all__ = ["denoise", "denoise_result", "DenoiseResult", "DenoiseStats", "PASSTHROUGH_REL_STD", "peak_rss_mb"]

#: a no-hit tile is passed through when every pixel's standard error is at most this fraction of its colour
PASSTHROUGH_REL_STD = 1e-3


def _autocast(half: bool):
    return torch.autocast("cuda", dtype=torch.float16) if half else contextlib.nullcontext()


def denoise_result(
    exr_path_or_frame,
    model=None,
    out_path: str | os.PathLike | None = None,
    *,
    tile: int | str | None = "auto",
    device: str | torch.device = "auto",
    half: bool = False,
    skip: bool = True,
    trust_pickle: bool = False,
    layers=None,
    aov_branch: str | None = None,
    rows: bool = True,
    precision: str = "auto",
    views: int = 1,
) -> DenoiseResult:
    """Like :func:`denoise`, but returns a :class:`DenoiseResult` (colour, ``layers`` and :class:`DenoiseStats`)."""
    if check_views(views) > 1:  # the mean of mirrored denoisings, each one an ordinary call
        return ensemble_result(exr_path_or_frame, model, out_path, views=views, tile=tile, device=device, half=half,
                               skip=skip, trust_pickle=trust_pickle, layers=layers, aov_branch=aov_branch, rows=rows,
                               precision=precision)
    if tile != "auto" and tile is not None and (isinstance(tile, (bool, str)) or int(tile) != tile):
        raise ValueError(f"denoise: tile must be an integer (<= 0 or None: whole frame) or 'auto', got {tile!r}")
    check_output(out_path, exr_path_or_frame)  # refused before any work, not after it
    dev = resolve_device(device)
    read_s = 0.0
    frame = None
    if model is None:  # the shipped model for the layers this file has
        frame, read_s = as_frame(exr_path_or_frame, ())
        model = default_model(frame, stacklevel=2)
    net = load_model(model, dev, trust_pickle=trust_pickle)
    dtype = resolve_precision(precision, net, dev)
    spec = net.input_spec
    if frame is None:
        frame, read_s = as_frame(exr_path_or_frame, spec.layers)
    else:  # already read and sanitised above (our own copy): only the layers to check
        frame.require(spec.layers)
    frame = spec.select(frame)  # e.g. OIDN's albedo for a colour + albedo + normal model, where the file has it
    h, w = validate(frame, spec.layers)
    plans = plan_aovs(frame, list(layers), spec, aov_branch) if layers else []
    if plans and not net.zero_preserving:
        raise ValueError(f"denoise: layers=... needs a kernel-predicting model; {describe(net)} predicts no kernels")
    aov_out = {p.name: np.zeros((h, w, 3), dtype=np.float32) for p in plans}
    halo = int(net.receptive_radius) + spec.halo
    align = int(net.alignment)
    use_half = bool(half) and dev.type == "cuda"
    use_rows = rows and dev.type == "cpu" and supports_rows(net, h, w)  # bands are for CPU caches; a GPU takes it whole
    if tile == "auto":
        tile = auto_tile(h, w, halo, align, rows=use_rows)
    if half and not use_half:
        warnings.warn("denoise: half=True is only used on CUDA; running float32 on the CPU", RuntimeWarning, stacklevel=2)

    stats = DenoiseStats(size=(h, w), tile=tile_size(tile, align) or max(h, w), halo=halo, alignment=align,
                         device=str(dev), read_seconds=read_s, nonfinite=dict(frame.nonfinite),
                         branch_tiles_run={b: 0 for b in spec.branches},
                         branch_tiles_skipped={b: 0 for b in spec.branches})
    if SAMPLE_COUNT in frame:  # a frame whose spp varies per pixel (it is denoised from its variances)
        stats.sample_count = (float(frame[SAMPLE_COUNT].min()), float(frame[SAMPLE_COUNT].max()))
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    t0 = time.perf_counter()
    # a frame far brighter or darker than the model's training frames is denoised at its range's centre; a model with
    # an exposure gain denoises every frame at that many times its exposure first
    gain = net.exposure_gain
    key = frame_key(frame.beauty()) if net.exposure_range is not None or gain != 1.0 else None
    scale = exposure_scale(key, net.exposure_range, gain) if key is not None else 1.0
    # the frame at its own exposure: what a scale does not change (which branches and tiles are zero, the no-hit
    # tiles' noise test) is read from it, with no scaled copy made
    own = frame
    if scale != 1.0:
        # scaled when read: a band's or a tile's rows at a time, no scaled copy of every radiance layer held
        frame = Frame(ScaledLayers(frame.layers, scale, [v for p in plans for v in p.parts.values()]),
                      frame.meta, frame.path, frame.nonfinite)
    stats.exposure_key, stats.exposure_scale = key, scale

    # branches whose kernels filter plain layers run everywhere (on a zero branch a kernel predictor's output is 0)
    needed = {b for p in plans if not p.group for b in p.parts}
    active = [b for b in spec.branches if b in needed or not (skip and spec.branch_is_zero(own, b))]
    stats.branches_skipped = tuple(b for b in spec.branches if b not in active)
    frame_value = spec.frame_value(frame)  # the depth scale or noise precision of the whole frame, given to each tile
    frame_value = frame_value.to(dev) if frame_value is not None else None
    if spec.frame_stat is not None and frame_value is not None:
        stats.noise_precision = float(frame_value.reshape(-1)[0])
    color_in = own.beauty()  # the noisy colour at its own exposure (× scale where it is used with the denoised)
    var_in = color_variance(own) if skip and "depth" in frame else None

    out = np.empty((h, w, 3), dtype=np.float32)
    stats.precision = str(dtype).removeprefix("torch.")
    # freed tensors' pages reused, not re-faulted; the hidden layers in the resolved precision
    with reuse_heap(dev.type == "cpu"), torch.inference_mode(), compute_dtype(net, dtype):
        context = None
        tiles = list(plan_tiles(h, w, tile, halo, align))
        # one tile that is the whole frame: each branch's own summary is the frame's (no separate pass)
        if net.uses_frame_context and active and not (len(tiles) == 1 and tiles[0].crop == (slice(0, h), slice(0, w))):
            tc = time.perf_counter()
            whole = (slice(None), slice(None))
            full = spec.build(frame_to_tensors(frame, spec.layers_for(active), whole, dev), frame_value, active)
            with_normal(net, full, frame, whole, dev)
            with _autocast(use_half):
                context = net.frame_context(full)
            del full
            stats.frame_context_seconds = time.perf_counter() - tc
        for t in tiles:
            stats.tiles += 1
            crop = t.crop
            if var_in is not None and not np.any(frame["depth"][crop] > 0):
                if np.all(var_in[crop] <= np.square(PASSTHROUGH_REL_STD * color_in[crop])):
                    out[t.interior] = np.maximum(scale_array(color_in[t.interior], scale), 0.0)
                    for p in plans:
                        aov_out[p.name][t.interior] = noisy_aov(frame, p, t.interior)
                    stats.tiles_passed_through += 1
                    for b in spec.branches:
                        stats.branch_tiles_skipped[b] += 1
                    continue
            run = list(active)
            if skip and net.zero_preserving:
                run = [b for b in active if b in needed or not spec.branch_is_zero(own, b, crop)]
            for b in spec.branches:
                stats.branch_tiles_run[b] += b in run
                stats.branch_tiles_skipped[b] += b not in run
            if not run:  # every component is zero
                out[t.interior] = 0.0
                stats.tiles_zero += 1
                continue
            if use_rows and crop == (slice(0, h), slice(0, w)):  # the whole frame, a band of rows at a time
                out[...], denoised, stats.row_bands = denoise_rows(frame, net, spec, frame_value, run, dev, plans)
                for name, v in denoised.items():
                    aov_out[name][...] = v
                stats.tiles_run += 1
                continue
            inputs = spec.build(frame_to_tensors(frame, spec.layers_for(run), crop, dev), frame_value, run)
            with_normal(net, inputs, frame, crop, dev)
            with _autocast(use_half):
                res = net(inputs, context)
            if use_half and not torch.isfinite(res["color"]).all():
                res = net(inputs, context)  # float16 overflowed: this tile again in float32
                stats.tiles_fp32_fallback += 1
            iy, ix = t.interior_in_crop
            out[t.interior] = res["color"][0, :, iy, ix].float().permute(1, 2, 0).cpu().numpy()
            if plans:
                for name, v in denoise_aovs(net, inputs, res, context, frame, crop, run, plans, dev).items():
                    aov_out[name][t.interior] = v[0, :, iy, ix].float().permute(1, 2, 0).cpu().numpy()
            stats.tiles_run += 1
            del inputs, res
        detail = net.detail_regression
        if detail is not None and stats.tiles_run:  # after the network, on the assembled frame (tiled == untiled)
            td = time.perf_counter()
            groups = {p.name: aov_out[p.name] for p in plans if p.group}  # parts of the beauty: they keep adding up
            out, refined = refine_detail(out, color_in, frame["normal"], *detail, layers=groups, noisy_scale=scale)
            aov_out.update(refined)
            stats.detail_radius, stats.detail_seconds = detail[0], time.perf_counter() - td
    if scale != 1.0:  # back to the frame's own exposure
        out *= np.float32(1.0 / scale)
        for v in aov_out.values():
            v *= np.float32(1.0 / scale)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
        stats.peak_cuda_mb = torch.cuda.max_memory_allocated(dev) / 2**20
    stats.seconds = time.perf_counter() - t0
    stats.peak_rss_mb = peak_rss_mb()

    result = DenoiseResult(out, stats, describe(net), layers=aov_out)
    if out_path is not None:
        t1 = time.perf_counter()
        write_output(out_path, out, frame, result)
        stats.write_seconds = time.perf_counter() - t1
        result.out_path = os.fspath(out_path)
    return result


def denoise(
    exr_path_or_frame,
    model=None,
    out_path: str | os.PathLike | None = None,
    *,
    tile: int | str | None = "auto",
    device: str | torch.device = "auto",
    half: bool = False,
    skip: bool = True,
    trust_pickle: bool = False,
    layers=None,
    aov_branch: str | None = None,
    rows: bool = True,
    precision: str = "auto",
    views: int = 1,
):
    """Denoise one render and return its colour ``(H, W, 3)`` float32 (finite, >= 0).

    With ``layers``, returns ``{"color": ..., name: ...}``: the colour and each
    listed layer denoised with the kernels predicted for the beauty (see
    :mod:`kpcn.inference.aovs`: light groups ``g.diffuse``/``g.specular`` add up to
    the denoised beauty; another layer is filtered with ``aov_branch``'s kernels).

    Args:
        exr_path_or_frame: a multi-layer EXR path, a :class:`~kpcn.io.Frame`, or a
            dict of ``(H, W, C)`` layers; it must have the layers of the model's input spec.
        model: ``None`` (shipped default), a model name (``"kpcn"``, ``"dpcn:small"``),
            a weights/checkpoint path, or a :class:`~kpcn.models.DenoiserModel`
            (see :func:`kpcn.inference.load_model`).
        out_path: if given, also write an EXR (atomically): the denoised colour as
            ``R G B``, the input's ``albedo``/``normal``/``depth``, and header
            attributes ``source``, ``denoiser``, ``denoiseSeconds`` (and the input's
            ``spp``, ``seed``, ``scene``). Missing folders are created. It must not
            be the input file (nor the file a :class:`~kpcn.io.Frame` was read from),
            under any spelling: relative, through a symlink, or a hard link of it.
        tile: interior tile size in pixels (rounded up to the model's alignment);
            ``None`` or ``0``: the whole frame at once; ``"auto"`` (default): the whole frame
            up to about 1920x1080 (fastest: nothing is computed twice; up to 4096x4096 for a
            model that runs whole frames in row bands), larger frames in tiles
            of ``max(512, 4 * halo)`` (:func:`kpcn.inference.tiling.auto_tile`).
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"``, ...
        half: float16 autocast on CUDA (ignored, with a warning, on the CPU).
        skip: leave out zero branches, zero tiles and no-hit converged tiles
            (see the module docstring); ``False`` runs the network everywhere.
        trust_pickle: allow a ``.pt`` checkpoint that needs full unpickling (runs its code).
        layers: names of light groups or other three-channel layers to denoise with
            the beauty's kernels (kernel predictors only); written to ``out_path`` too.
        aov_branch: the branch whose kernels filter layers that are not light groups
            (default: the spec's first branch).
        rows: on the CPU, a frame of at least 128x128 pixels (600x600 without the native kernels;
            :func:`kpcn.inference.rows.rows_min_pixels`) denoised whole by a model with row streams
            (the ``stem: half`` U-Net, the default) is run a band of rows at a time (:mod:`kpcn.inference.rows`: the same result to
            float rounding, in less time and memory); ``False``: the whole frame at once.
        precision: the dtype of the model's hidden layers: ``"float32"``, ``"bfloat16"``, or ``"auto"``
            (default): bfloat16 on a CPU with native bfloat16 arithmetic (AMX, AVX-512 BF16) for a model that
            can (the U-Net), float32 otherwise; kernels and their application are float32 in either
            (:mod:`kpcn.inference.precision`).
        views: 1 (default), or 2, 4 or 8: the mean of that many mirrored copies of the frame denoised
            (:mod:`kpcn.inference.ensemble`): a little closer to the reference at low spp, in ``views`` times the
            time.

    Raises:
        MissingLayerError: the input lacks layers the model needs (names them and those found).
        ExrError / FileNotFoundError: unreadable or missing file; CheckpointError: unusable weights.
        ValueError: ``out_path`` is the input (names both); raised before any denoising.
        IsADirectoryError / NotADirectoryError: ``out_path`` is a folder, or under a file; raised first too.
    """
    res = denoise_result(exr_path_or_frame, model, out_path, tile=tile, device=device, half=half, skip=skip,
                         trust_pickle=trust_pickle, layers=layers, aov_branch=aov_branch, rows=rows,
                         precision=precision, views=views)
    return {"color": res.color, **res.layers} if layers else res.color
