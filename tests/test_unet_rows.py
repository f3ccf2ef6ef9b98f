"""Row-band inference of the ``stem: half`` U-Net (:mod:`kpcn.models.unet_rows`, :mod:`kpcn.inference.rows`)
and the layers written for it (:func:`pool2`, :func:`upsample2`, :func:`conv1x1`, :func:`kernel_apply_padded`,
the kernel weights and the guided head's accumulating product).

The frame is a real render (Mitsuba, tiny) whose size is not a multiple of the U-Net's alignment; the
models are random-init with sharp kernels, so a band that read a wrong row shows up as a large error.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from kpcn import inference
from kpcn.features import frame_to_tensors
from kpcn.io import Frame
from kpcn.inference.rows import denoise_rows, supports_rows
from kpcn.models import create_model
from kpcn.models import unet_rows
from kpcn.models.kernel_heads import GuidedHead, _bounded_softmax, _softmax_weights
from kpcn.models.guided import upsample2_guided
from kpcn.models.layers import conv1x1, pool2, upsample2
from kpcn.models.unet_branch import FullResLevel
from kpcn.ops.kernel_apply import kernel_apply, kernel_apply_padded

FRAME_RES = (150, 117)  # width, height: neither a multiple of the alignment (16)


@pytest.fixture(autouse=True)
def bands_for_small_frames(monkeypatch):
    """The test frames are small: take them in row bands all the same (the default is 600x600 and larger)."""
    from kpcn.inference import rows

    monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", 0)


@pytest.fixture(scope="module")
def frame(render):
    return render("test:glossy", spp=4, seed=1, resolution=FRAME_RES)


def _model(**kw):
    torch.manual_seed(0)
    cfg = dict(widths=[8, 8, 12, 12], stem="half", kernel_scales=3, out_init_gain=5.0)
    cfg.update(kw)
    model = create_model("unet_kpcn", **cfg).eval()
    for m in model.modules():  # a full-resolution level starts at zero (the file's output): give it a say
        if isinstance(m, FullResLevel):
            torch.nn.init.normal_(m.out.weight, std=0.5)
    return model


def _rel(a, b) -> float:
    return float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-12))


@pytest.mark.parametrize("kw", [{}, {"kernel_scales": 1}, {"kernel_scales": 4}, {"kernel_scales": 2, "kernel_size": 3},
                                {"guide_kernel": 3}, {"guide_kernel": 5, "kernel_scales": 1}, {"band_gain": True},
                                {"band_gain": True, "kernel_scales": 4}, {"up_kernel": 1, "band_gain": True},
                                {"albedo_kernel": 3, "band_gain": True}, {"albedo_kernel": 5, "kernel_scales": 2, "albedo_gate_gain": 4.0},
                                {"albedo_kernel": 3, "albedo_clamp": 2.0, "albedo_gate_gain": 8.0},
                                {"albedo_kernel": 3, "up_kernel": 1, "specular_widths": [4, 6, 8, 10]},
                                {"radiance_pool": True, "band_gain": True},
                                {"radiance_pool": True, "input_spec": "split_novar"},
                                {"radiance_mix": True, "albedo_kernel": 3, "band_gain": True},
                                {"radiance_mix": True, "radiance_pool": True, "kernel_scales": 4},
                                {"input_spec": "color_albedo_normal"}, {"input_spec": "split_novar"},
                                {"input_spec": "color_albedo_normal_noise"},
                                {"kernel_size": 3, "coarse_kernel": 5, "albedo_kernel": 3, "band_gain": True},
                                {"coarse_kernel": 3, "radiance_mix": True, "radiance_pool": True},
                                {"deep_blocks": 1, "band_gain": True},
                                {"edge_upsample": 0.5, "band_gain": True, "albedo_kernel": 3},
                                {"edge_upsample": 0.3, "kernel_scales": 4, "radiance_pool": True},
                                {"fullres_channels": 4, "edge_upsample": 0.5, "band_gain": True, "albedo_kernel": 3},
                                {"fullres_channels": 6, "kernel_scales": 1, "guide_kernel": 3}],
                         ids=lambda kw: ",".join(f"{k}={v}" for k, v in kw.items()) or "default")
@pytest.mark.parametrize("band", [32, 6])
def test_row_bands_equal_the_whole_frame(frame, monkeypatch, kw, band):
    monkeypatch.setattr(unet_rows, "BAND_ROWS", band)
    model = _model(**kw)
    whole = inference.denoise_result(frame, model, tile=0, device="cpu", skip=False, rows=False)
    res = inference.denoise_result(frame, model, tile=0, device="cpu", skip=False)
    assert whole.stats.row_bands == 0 and res.stats.row_bands == -(-128 // band), "the default must take the row path"
    assert res.color.shape == whole.color.shape and np.isfinite(res.color).all()
    # 3e-5: the native feed's log1p is not torch's to the last float bit, and the stream keeps the features in
    # bfloat16, where such a difference flips the rounding of about one value in 10^4 (PyTorch paths: below 2e-6;
    # a band that reads a wrong row: above 1e-3, test_row_bands_read_the_rows_around_them)
    assert _rel(whole.color, res.color) < 3e-5, f"{kw} band {band}: {_rel(whole.color, res.color):.3g}"


def test_row_bands_read_the_rows_around_them(frame):
    """Negative control: a band that does not read the row below it (the forward differences) differs."""
    model = _model()
    spec = model.input_spec
    # float32, as the bands below run the model as it is (denoise would pick bfloat16 on a CPU with AMX)
    whole = inference.denoise(frame, model, tile=0, device="cpu", skip=False, rows=False, precision="float32")
    frame_value = spec.frame_value(frame)
    with torch.inference_mode():
        right, _, bands = denoise_rows(frame, model, spec, frame_value, spec.branches, torch.device("cpu"), band=8)
        wrong, _, _ = denoise_rows(frame, model, dataclasses.replace(spec, halo=0), frame_value, spec.branches,
                                   torch.device("cpu"), band=8)
    assert bands == 16 and _rel(whole, right) < 1e-5  # 117 rows padded to 128, in bands of 8
    assert _rel(whole, wrong) > 1e-3


def test_row_stream_refuses_misuse():
    model = _model()
    s = model.row_stream("diffuse", 40, 40)
    assert s.padded_size == (48, 48)
    with pytest.raises(ValueError, match="run\\(\\) first"):
        s.rows(0, 8)
    with torch.inference_mode():
        with pytest.raises(ValueError, match="from row 0"):
            s.feed(8, torch.zeros(1, 27, 8, 48))
        with pytest.raises(ValueError, match="even number of rows"):
            s.feed(0, torch.zeros(1, 27, 7, 48))
        with pytest.raises(ValueError, match="rows 0..0 of 48 fed"):
            s.run()
    with pytest.raises(ValueError, match="stem: half"):
        _model(stem="full").row_stream("diffuse", 40, 40)
    assert not _model(stem="full").streams_rows
    kpcn = create_model("kpcn", layers=2, width=4)  # no row streams: the contract's default
    assert not kpcn.streams_rows and not supports_rows(kpcn) and supports_rows(_model())
    with pytest.raises(NotImplementedError, match="no row streams"):
        kpcn.row_stream("diffuse", 40, 40)


def test_branch_streams_share_one_normal(frame, monkeypatch):
    """``edge_upsample``: the second branch's stream reads the first's normal buffer (fed once) instead of a copy;
    the denoised frame is the whole frame's all the same (and the rows == whole tests with the option above)."""
    model = _model(edge_upsample=0.5, band_gain=True)
    a, b = model.row_stream("diffuse", 40, 40), model.row_stream("specular", 40, 40)
    assert a._normal.data_ptr() != b._normal.data_ptr()
    b.share_normal(a)
    assert a._normal.data_ptr() == b._normal.data_ptr()
    plain = _model()
    c, d = plain.row_stream("diffuse", 40, 40), plain.row_stream("specular", 40, 40)
    d.share_normal(c)  # no normal read: nothing to share
    assert c._normal is None and d._normal is None
    seen, pyramids = [], []
    real = unet_rows.RowStream.share_normal
    monkeypatch.setattr(unet_rows.RowStream, "share_normal", lambda s, o: seen.append(s is o) or real(s, o))
    real_pyr = unet_rows.guide_pyramid
    monkeypatch.setattr(unet_rows, "guide_pyramid", lambda *a: pyramids.append(1) or real_pyr(*a))
    whole = inference.denoise(frame, model, tile=0, device="cpu", skip=False, rows=False, precision="float32")
    rows = inference.denoise(frame, model, tile=0, device="cpu", skip=False, precision="float32")
    assert seen == [True, False] and _rel(whole, rows) < 3e-5
    assert len(pyramids) == 1  # the normal's half-resolution pyramid too: once for both streams
    # a normal beyond [-1, 1] (unnormalised): the bands clamp the blend's guide as the whole frame's path does
    big = Frame({**frame.layers, "normal": frame["normal"] * np.float32(3.0)}, dict(frame.meta))
    whole = inference.denoise(big, model, tile=0, device="cpu", skip=False, rows=False, precision="float32")
    assert _rel(whole, inference.denoise(big, model, tile=0, device="cpu", skip=False, precision="float32")) < 3e-5
    with torch.inference_mode():
        e = model.row_stream("diffuse", 40, 40)
        e.feed(0, torch.zeros(1, 27, 8, 48), albedo=None, normal=torch.zeros(1, 3, 8, 48))
        with pytest.raises(ValueError, match="before the first feed"):
            e.share_normal(a)


def test_pool2_is_the_2x2_average():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 6, 10, generator=g, dtype=torch.float64)
    assert torch.allclose(pool2(x), F.avg_pool2d(x, 2), atol=1e-15)
    cl = x.contiguous(memory_format=torch.channels_last)
    assert torch.allclose(pool2(cl), F.avg_pool2d(x, 2), atol=1e-15)
    assert torch.autograd.gradcheck(pool2, (x[:1, :2].clone().requires_grad_(),))


@pytest.mark.parametrize("shape", [(2, 5, 6, 10), (1, 3, 7, 5), (1, 2, 1, 4), (1, 3, 4, 1), (1, 1, 1, 1)])
def test_upsample2_is_bilinear_interpolation(shape):
    g = torch.Generator().manual_seed(3)
    x = torch.randn(*shape, generator=g, dtype=torch.float64)
    want = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    strided = torch.zeros(*shape[:-1], 2 * shape[-1], dtype=torch.float64)[..., ::2]  # every other column
    strided.copy_(x)
    for layout in (x, x.contiguous(memory_format=torch.channels_last), strided):
        out = upsample2(layout)
        assert out.shape == want.shape and out.is_contiguous()
        assert torch.allclose(out, want, atol=1e-12)
    if shape[-2] >= 3:  # a band whose first and last rows are context: the inner rows of the whole map's upsampling
        assert torch.allclose(upsample2(x, context_rows=True), want[..., 2:-2, :], atol=1e-12)
    with torch.enable_grad():  # with autograd, F.interpolate's own (differentiable) result
        xs = x.clone().requires_grad_()
        upsample2(xs).sum().backward()
        assert xs.grad is not None and torch.allclose(xs.grad, torch.full_like(x, 4.0))


def test_upsample2_band_needs_context():
    with pytest.raises(ValueError, match="at least 3 rows"):
        upsample2(torch.zeros(1, 1, 2, 4), context_rows=True)


@pytest.mark.parametrize("s", [4.0, 16.0, 100.0])
def test_kernel_weights_are_the_bounded_softmax(s):
    """The inference weights (sigmoid and exp2, unnormalised) are ``softmax(s tanh(z / s))`` once divided by
    their sum, for logits from small to far into the bound, and the input is left alone unless in place; the
    training path (sigmoid, autograd) is the same function with the right gradient."""
    g = torch.Generator().manual_seed(4)
    z = torch.randn(2, 25, 6, 7, generator=g, dtype=torch.float64) * torch.tensor([0.1, 3.0, 40.0, 400.0]
                                                                                   ).repeat(7)[:25].view(1, 25, 1, 1)
    want = torch.softmax(s * torch.tanh(z / s), dim=1)
    before = z.clone()
    w, norm = _softmax_weights(z, s)
    assert torch.equal(z, before)
    got = w / norm if norm is not None else w
    assert torch.allclose(got, want, rtol=1e-10, atol=1e-14)
    zg = z.clone().requires_grad_()  # the training path: the same function, and its gradient
    assert torch.allclose(_bounded_softmax(zg, s), want, rtol=1e-10, atol=1e-14)
    small = z[:1, :, :2, :2].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda t: _bounded_softmax(t, s), (small,))
    w2, norm2 = _softmax_weights(z, s, inplace=True)
    assert w2.data_ptr() == z.data_ptr() or norm2 is None
    assert torch.allclose(w2 / norm2 if norm2 is not None else w2, want, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("band", [False, True])
def test_guided_head_accumulates_its_guide_part(band):
    g = torch.Generator().manual_seed(5)
    head = GuidedHead(6 + 4, 5, 1).double()
    guide = torch.randn(1, 4, 9, 8, generator=g, dtype=torch.float64)
    if band:  # rows of a taller NCHW guide, as the row streams pass it
        guide = torch.randn(1, 4, 15, 8, generator=g, dtype=torch.float64)[..., 3:12, :]
    z = torch.randn(1, 5, 9, 8, generator=g, dtype=torch.float64)
    want = z + F.conv2d(guide, head.weight[:, 6:])
    with torch.no_grad():
        out = head.add_guide_part_(z, guide)
    assert out.data_ptr() == z.data_ptr() and torch.allclose(out, want, atol=1e-12)


@pytest.mark.parametrize("layout", ["nchw", "channels_last", "band", "strided"])
@pytest.mark.parametrize("batch", [1, 3])
def test_conv1x1_is_the_1x1_convolution(layout, batch):
    g = torch.Generator().manual_seed(1)
    x = torch.randn(batch, 6, 5, 7, generator=g, dtype=torch.float64)
    w = torch.randn(4, 6, 1, 1, generator=g, dtype=torch.float64)
    b = torch.randn(4, generator=g, dtype=torch.float64)
    if layout == "channels_last":
        x = x.contiguous(memory_format=torch.channels_last)
    elif layout == "band":  # rows of a taller NCHW tensor (what the row streams pass)
        x = torch.randn(batch, 6, 11, 7, generator=g, dtype=torch.float64)[..., 3:8, :]
    elif layout == "strided":
        x = torch.randn(batch, 6, 5, 14, generator=g, dtype=torch.float64)[..., ::2]
    for bias in (b, None):
        out = conv1x1(x, w, bias)
        assert out.is_contiguous() and torch.allclose(out, F.conv2d(x, w, bias), atol=1e-12)
    xs = x.detach().clone().requires_grad_()
    ws, bs = w.clone().requires_grad_(), b.clone().requires_grad_()
    assert torch.autograd.gradcheck(conv1x1, (xs, ws, bs))


def test_kernel_apply_padded_takes_real_neighbours():
    g = torch.Generator().manual_seed(2)
    image = torch.randn(1, 3, 20, 9, generator=g, dtype=torch.float64)
    weights = torch.softmax(torch.randn(1, 25, 20, 9, generator=g, dtype=torch.float64), dim=1)
    full = kernel_apply(image, weights, 5, "replicate")
    # rows 6..14 from a band padded with its real neighbour rows and replicated columns
    band = F.pad(image[..., 4:16, :], (2, 2, 0, 0), mode="replicate")
    assert torch.allclose(kernel_apply_padded(band, weights[..., 6:14, :], 5), full[..., 6:14, :], atol=1e-12)
    with pytest.raises(ValueError, match="grown by 2"):
        kernel_apply_padded(image, weights, 5)


def test_auto_tiles_only_beyond_what_row_bands_hold(frame, monkeypatch):
    """``tile="auto"``: a model with row streams takes frames whole up to 4096², others up to ~1080p."""
    from kpcn.inference import tiling

    assert tiling.auto_tile(1080, 1920, 134, 16) is None and tiling.auto_tile(2160, 3840, 134, 16) == 544
    assert tiling.auto_tile(2160, 3840, 134, 16, rows=True) is None
    assert tiling.auto_tile(4112, 4096, 134, 16, rows=True) == 544
    # the pipeline asks for the row limit exactly when it will use row bands
    monkeypatch.setattr(tiling, "WHOLE_FRAME_PIXELS", 100)  # this frame is "large" for the tile path
    rows = inference.denoise_result(frame, _model(), device="cpu")
    tiled = inference.denoise_result(frame, _model(), device="cpu", rows=False)
    assert rows.stats.tile == max(FRAME_RES) and rows.stats.row_bands > 0  # the whole frame
    assert tiled.stats.tile >= 512 and tiled.stats.row_bands == 0  # auto tiles (this frame fits in one)


@pytest.fixture(scope="module")
def groups(mi):
    from kpcn.render.groups import render_light_groups

    return render_light_groups("test:textured", spp=8, seed=1, resolution=(50, 38))


@pytest.mark.parametrize("kw", [{}, {"input_spec": "color_albedo_normal", "kernel_scales": 2},
                                {"edge_upsample": 0.5, "band_gain": True}], ids=["split", "colour", "edge"])
def test_row_bands_denoise_light_groups_and_other_layers_as_the_whole_frame(groups, monkeypatch, kw):
    """Light groups (and a layer filtered directly) in row bands equal the whole-frame result; they sum to the beauty."""
    monkeypatch.setattr(unet_rows, "BAND_ROWS", 6)
    model = _model(**kw)
    names = groups.meta["lightGroups"].split(",")
    layers = names + ["albedo"]  # albedo: not a group, filtered with the first branch's kernels
    whole = inference.denoise_result(groups, model, tile=0, device="cpu", layers=layers, rows=False)
    res = inference.denoise_result(groups, model, tile=0, device="cpu", layers=layers)
    assert res.stats.row_bands > 0 and whole.stats.row_bands == 0
    for name in layers:
        assert _rel(whole.layers[name], res.layers[name]) < 1e-5, name
    total = sum(res.layers[n] for n in names)
    assert _rel(res.color, total) < 1e-5
    assert all(res.layers[n].mean() > 0 for n in names)


def test_light_groups_add_up_where_the_blend_dips_below_zero(mi):
    """The multi-scale blend is not convex: beside fireflies the diffuse output dips below 0 (the beauty clamps
    it) and the filtered specular can vanish while the log-space branch does not; the groups follow the beauty."""
    from kpcn.render.groups import render_light_groups

    frame = render_light_groups("random:5", spp=2, seed=1, resolution=(96, 64))  # (random:1 dipped before albedo revision 2)
    names = frame.meta["lightGroups"].split(",")
    model = _model()
    spec = model.input_spec
    with torch.inference_mode():  # the control: this frame's diffuse output really dips below 0
        x = spec.build(frame_to_tensors(frame, spec.layers), spec.frame_value(frame), spec.branches)
        assert model.run_branch("diffuse", x["diffuse"]).min() < 0
    for rows in (True, False):
        res = inference.denoise_result(frame, model, device="cpu", layers=names, rows=rows)
        total = sum(res.layers[n] for n in names)
        assert _rel(res.color, total) < 1e-5, rows


def test_the_kernels_in_use_choose_the_smallest_banded_frame(frame, monkeypatch):
    """Without a fixed threshold, bands start at 128² with the native kernels (their bands beat the whole frame from
    there) and at 600² on the PyTorch paths; this 150 × 117 frame goes in bands only with the native kernels."""
    from kpcn.inference import rows
    from kpcn.ops import native

    monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", None)
    have = native.library() is not None
    assert rows.rows_min_pixels() == (rows.ROWS_MIN_PIXELS_NATIVE if have else rows.ROWS_MIN_PIXELS_PYTORCH)
    assert (inference.denoise_result(frame, _model(), device="cpu").stats.row_bands > 0) == have
    monkeypatch.setenv("KPCN_NATIVE", "0")
    assert rows.rows_min_pixels() == rows.ROWS_MIN_PIXELS_PYTORCH == 600 * 600
    assert inference.denoise_result(frame, _model(), device="cpu").stats.row_bands == 0


def test_small_frames_go_whole(frame, monkeypatch):
    """Below ``ROWS_MIN_PIXELS`` the bands' overhead outweighs what they save: the frame goes whole."""
    from kpcn.inference import rows

    w, h = FRAME_RES
    monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", w * h + 1)
    assert inference.denoise_result(frame, _model(), device="cpu").stats.row_bands == 0
    monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", w * h)
    assert inference.denoise_result(frame, _model(), device="cpu").stats.row_bands > 0


def test_guided_upsampling_keeps_an_edge_and_is_bilinear_on_a_flat_guide():
    """:func:`upsample2_guided`: with a constant guide the bilinear upsampling, whatever sigma; a value map with a
    step where its guide (a normal turning 90°) steps keeps the step sharp, where bilinear upsampling spreads it
    over two pixels; the weights are renormalised, so a constant stays constant; float64 gradcheck."""
    g = torch.Generator().manual_seed(5)
    x = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    flat = torch.zeros(2, 3, 10, 12, dtype=torch.float64)
    flat[:, 1] = 1
    want = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    for sigma in (0.05, 1.0):
        torch.testing.assert_close(upsample2_guided(x, flat, pool2(flat), sigma), want, rtol=0, atol=1e-12)
    # a floor (normal +y) left of coarse column 3, a wall (+z) from it on; the value 0 on the floor, 1 on the wall
    n = torch.zeros(1, 3, 8, 12, dtype=torch.float64)
    n[:, 1, :, :6] = 1
    n[:, 2, :, 6:] = 1
    v = torch.zeros(1, 1, 4, 6, dtype=torch.float64)
    v[..., 3:] = 1
    sharp = upsample2_guided(v, n, pool2(n), 0.2)
    blurred = upsample2(v)
    assert torch.all(sharp[..., :6] < 1e-6) and torch.all(sharp[..., 6:] > 1 - 1e-6)
    assert blurred[0, 0, 0, 5] == pytest.approx(0.25) and blurred[0, 0, 0, 6] == pytest.approx(0.75)
    ones = torch.ones(1, 2, 4, 6, dtype=torch.float64)
    rough = torch.randn(1, 3, 8, 12, generator=g, dtype=torch.float64)
    torch.testing.assert_close(upsample2_guided(ones, rough, pool2(rough), 0.3), torch.ones(1, 2, 8, 12,
                                                                                       dtype=torch.float64))
    xs = x[:1, :2].clone().requires_grad_()
    gf = torch.randn(1, 3, 10, 12, generator=g, dtype=torch.float64).requires_grad_()
    gc = torch.randn(1, 3, 5, 6, generator=g, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c: upsample2_guided(a, b, c, 0.7), (xs, gf, gc))
    # with and without autograd (training and inference) the same
    guide = torch.randn(2, 3, 10, 12, generator=g, dtype=torch.float64)
    with torch.no_grad():
        fast = upsample2_guided(x, guide, pool2(guide), 0.4)
    with torch.enable_grad():
        slow = upsample2_guided(x.clone().requires_grad_(), guide, pool2(guide), 0.4).detach()
    torch.testing.assert_close(slow, fast, rtol=0, atol=1e-12)
    assert (fast - want).abs().max() > 1e-3  # a rough guide does move the result
    with pytest.raises(ValueError, match="sigma"):
        upsample2_guided(x, flat, pool2(flat), 0.0)
    with pytest.raises(ValueError, match="must be"):
        upsample2_guided(x, flat[..., :8, :], pool2(flat), 0.5)


def test_combine_levels_guided_is_the_bilinear_blend_on_a_flat_guide():
    """``combine_levels(..., guides, sigma)`` with a constant guide pyramid is the blend without one (both
    upsamplings guided), and with a guide that has an edge it differs from it."""
    from kpcn.models.kernel_heads import combine_levels

    g = torch.Generator().manual_seed(6)
    sizes = [(16, 24), (8, 12), (4, 6)]
    f = [torch.rand(1, 3, h, w, generator=g, dtype=torch.float64) for h, w in sizes]
    alphas = [torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) for h, w in sizes[:-1]] + [None]
    gains = [torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) for h, w in sizes[:-1]] + [None]
    flat = [torch.full((1, 3, h, w), 0.5, dtype=torch.float64) for h, w in sizes]
    plain = combine_levels(f, alphas, gains)
    torch.testing.assert_close(combine_levels(f, alphas, gains, flat, 0.3), plain, rtol=0, atol=1e-12)
    edge = torch.zeros(1, 3, 16, 24, dtype=torch.float64)
    edge[:, 1, :, :11] = 1
    edge[:, 2, :, 11:] = 1
    pyramid = [edge, pool2(edge), pool2(pool2(edge))]
    assert (combine_levels(f, alphas, gains, pyramid, 0.3) - plain).abs().max() > 1e-3


def test_edge_upsampling_reads_the_frames_normal(frame):
    """``edge_upsample``: the model reads the frame's normal (``reads_normal``), refuses inputs without it with a
    message that names it, and its result differs from the bilinear blend's where the geometry has edges (the same
    weights; test:glossy has a sphere's and the floor's silhouettes)."""
    plain, edged = _model(band_gain=True), _model(band_gain=True, edge_upsample=0.5)
    edged.load_state_dict(plain.state_dict())
    assert edged.reads_normal and not plain.reads_normal
    spec = edged.input_spec
    inputs = spec.build(frame_to_tensors(frame, spec.layers_for(spec.branches)), spec.frame_value(frame))
    with torch.inference_mode(), pytest.raises(ValueError, match="normal"):
        edged(inputs)
    a = inference.denoise(frame, plain, tile=0, device="cpu", rows=False)
    b = inference.denoise(frame, edged, tile=0, device="cpu", rows=False)
    assert _rel(a, b) > 1e-3
    with pytest.raises(ValueError, match="edge_upsample"):
        _model(edge_upsample=0.5, kernel_scales=1)
    with pytest.raises(ValueError, match="edge_upsample"):
        _model(edge_upsample=-1.0)
