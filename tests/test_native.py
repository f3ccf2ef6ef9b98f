"""The native (C) inference kernels (:mod:`kpcn.ops.native`, :func:`kpcn.ops.fused.softmax_apply_native`):
built here, the same function as the PyTorch path they replace, refused where they do not apply, and a
missing compiler costs nothing but the speed."""
from __future__ import annotations

import shutil
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from kpcn import inference
from kpcn.models import create_model, unet_rows
from kpcn.models.kernel_heads import _softmax_weights
from kpcn.ops import native
from kpcn.ops.kernel_apply import kernel_apply_padded
from kpcn.models.kernel_heads import GuidedHead
from kpcn.models.guided import upsample2_guided
from kpcn.models.layers import conv1x1, pool2, transform_input, upsample2
from kpcn.features import branch_features, depth_scale_of, frame_to_tensors
from kpcn.ops.fused import (MAX_NATIVE_SCALE, branch_features_native, feed_native, guided_blend_native,
                            guided_softmax_native, residual_regression_native, softmax_apply_native,
                            upsample_guide_native)
from kpcn.ops.regression import residual_regression

HAVE_CC = native._compiler() is not None


@pytest.fixture
def fresh_native(monkeypatch, tmp_path):
    """A cache folder of this test's own, the library forgotten before and after."""
    monkeypatch.setenv("KPCN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("KPCN_NATIVE", raising=False)
    native.reset()
    yield tmp_path / "cache" / "native"
    native.reset()


def _pytorch_path(logits, padded, k, s):
    w, norm = _softmax_weights(logits.clone(), s)
    out = kernel_apply_padded(padded, w, k)
    return out.div_(norm) if norm is not None else out


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
def test_the_library_builds_and_loads_here(fresh_native):
    assert native.library() is not None
    assert native.status().startswith("on: loaded ")
    built = list(fresh_native.glob("kpcn_native_*.so"))
    assert len(built) == 1, built
    stamp = built[0].stat().st_mtime_ns
    native.reset()
    assert native.library() is not None  # found in the cache, not built again
    assert [p.stat().st_mtime_ns for p in fresh_native.glob("kpcn_native_*.so")] == [stamp]
    assert [p.name for p in fresh_native.iterdir()] == [built[0].name]  # the library alone: no half-written file


def test_a_failing_compiler_leaves_nothing_behind(fresh_native, monkeypatch):
    """``$CC`` that fails (``false``): a warning naming it, None, and no half-written file in the cache folder."""
    false = shutil.which("false")
    if false is None:
        pytest.skip("no `false` command here")
    monkeypatch.setenv("CC", false)
    native.reset()
    with pytest.warns(RuntimeWarning, match="native kernels unavailable"):
        assert native.library() is None
    assert "failed (1)" in native.status()
    assert fresh_native.is_dir() and not list(fresh_native.iterdir())


def test_a_cache_folder_that_cannot_be_made_costs_only_the_speed(fresh_native, monkeypatch, tmp_path):
    """``KPCN_CACHE_DIR`` under a file (no folder can be made there): a warning that says where, and None."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("KPCN_CACHE_DIR", str(blocker / "cache"))
    native.reset()
    with pytest.warns(RuntimeWarning, match="native kernels unavailable"):
        assert native.library() is None
    assert native.status().startswith("unavailable: ") and ("a-file" in native.status() or not HAVE_CC)
    assert softmax_apply_native(torch.zeros(1, 9, 4, 4), torch.zeros(1, 3, 6, 6), 3, 16.0) is None


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
@pytest.mark.parametrize("k,channels,batch,width,s", [(1, 3, 1, 70, 16.0), (3, 3, 1, 131, 16.0), (5, 3, 2, 64, 16.0),
                                                       (5, 9, 1, 200, 4.0), (7, 6, 1, 65, 80.0), (9, 3, 1, 33, 1.0)])
def test_softmax_apply_is_the_pytorch_path(k, channels, batch, width, s):
    """Random logits (a slice of a larger tensor, as the heads give them; some far beyond the bound) and images:
    the one native pass equals the softmax weights and the shift-loop application, widths off the 64-pixel blocks."""
    g = torch.Generator().manual_seed(k * 100 + channels)
    h = 19
    big = torch.randn(batch, k * k + 3, h, width, generator=g) * 6.0
    big[:, :, 0, :5] = torch.tensor([1e4, -1e4, 0.0, 300.0, -300.0])[:, None].expand(5, k * k + 3).T[None]
    logits = big[:, 1:1 + k * k]
    padded = torch.rand(batch, channels, h + k - 1, width + k - 1, generator=g) * 10.0
    got = softmax_apply_native(logits, padded, k, s)
    assert got is not None and got.shape == (batch, channels, h, width)
    want = _pytorch_path(logits, padded, k, s)
    assert torch.allclose(got, want, rtol=2e-5, atol=1e-6), float((got - want).abs().max())


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
def test_softmax_apply_keeps_a_constant_and_reads_the_right_taps():
    """A constant image stays constant whatever the kernels; one-hot kernels (one logit far above the rest) copy
    the pixel at their tap's offset."""
    k, h, w = 5, 12, 77
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(1, k * k, h, w, generator=g) * 20.0
    const = torch.full((1, 3, h + k - 1, w + k - 1), 0.7)
    assert torch.allclose(softmax_apply_native(logits, const, k, 16.0), torch.full((1, 3, h, w), 0.7), atol=1e-6)
    image = torch.rand(1, 3, h + k - 1, w + k - 1, generator=g)
    for t in (0, 7, 24):
        onehot = torch.full((1, k * k, h, w), -1e4)
        onehot[:, t] = 1e4  # weight 1 against e^-32 for the rest (s = 16)
        i, j = divmod(t, k)
        got = softmax_apply_native(onehot, image, k, 16.0)
        assert torch.allclose(got, image[..., i:i + h, j:j + w], atol=1e-6), t


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
@pytest.mark.parametrize("guide_dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("rows,width", [(3, 1), (5, 37), (10, 64)])
def test_upsample_guide_is_the_guided_heads_band(guide_dtype, rows, width):
    """The band of the guided head's output: bilinear upsampling with context rows, then the guide's product (in
    bfloat16 the guide is kept so), as :func:`upsample2` and :meth:`GuidedHead.add_guide_part_` make it."""
    g = torch.Generator().manual_seed(rows * 7 + width)
    o, cg, cc = 11, 5, 6
    head = GuidedHead(cc + cg, o, 1)
    with torch.no_grad():
        head.weight.normal_(generator=g)
    big = torch.randn(1, o + 2, rows + 4, width, generator=g)
    low = big[:, 1:1 + o, 1:rows + 3]  # a slice, as the stream's clamped rows are
    guide = torch.randn(1, cg, 2 * rows + 9, 2 * width, generator=g).to(guide_dtype)[..., 3:3 + 2 * rows, :]
    with torch.no_grad():
        want = head.add_guide_part_(upsample2(low, context_rows=True), guide)
        got = upsample_guide_native(low, guide, head.weight[:, cc:, 0, 0])
    assert got is not None and got.shape == want.shape == (1, o, 2 * rows, 2 * width)
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-5), float((got - want).abs().max())
    with pytest.raises(ValueError, match="do not fit"):
        upsample_guide_native(low, guide[..., 1:, :], head.weight[:, cc:, 0, 0].detach())


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
@pytest.mark.parametrize("guide_dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("k,rows,width,channels", [(3, 3, 1, 3), (5, 5, 37, 6), (5, 10, 70, 3), (7, 4, 33, 9)])
def test_guided_softmax_is_the_band_made_then_applied(guide_dtype, k, rows, width, channels):
    """The guided head's kernels made and applied at once: the PyTorch path's band (upsampled, the guide's product
    added) made softmax kernels and applied to the padded colour, reading only the head's first k² channels (the
    others, the blend's weights, set far off here, must not leak in)."""
    g = torch.Generator().manual_seed(k * 100 + rows * 7 + width)
    kk, cg, cc = k * k, 5, 6
    o = kk + 4
    head = GuidedHead(cc + cg, o, 1)
    with torch.no_grad():
        head.weight.normal_(generator=g)
        head.weight[kk:] *= 100.0
    big = torch.randn(1, o + 2, rows + 4, width, generator=g) * 2.0
    low = big[:, 1:1 + o, 1:rows + 3]  # a slice, as the stream's clamped rows are
    guide = torch.randn(1, cg, 2 * rows + 9, 2 * width, generator=g).to(guide_dtype)[..., 3:3 + 2 * rows, :]
    padded = torch.rand(1, channels, 2 * rows + k - 1, 2 * width + k - 1, generator=g)
    with torch.no_grad():
        z = head.add_guide_part_(upsample2(low, context_rows=True), guide)
        want = _pytorch_path(z[:, :kk], padded, k, 16.0)
        got = guided_softmax_native(low, guide, head.weight[:, cc:, 0, 0], padded, k, 16.0)
    assert got is not None and got.shape == want.shape == (1, channels, 2 * rows, 2 * width)
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-5), float((got - want).abs().max())
    with pytest.raises(ValueError, match="do not fit"):
        guided_softmax_native(low, guide, head.weight[:, cc:, 0, 0].detach(), padded[..., 1:, :], k, 16.0)
    with pytest.raises(ValueError, match="do not fit"):  # fewer head channels than taps
        guided_softmax_native(low[:, :kk - 1], guide, head.weight[:kk - 1, cc:, 0, 0].detach(), padded, k, 16.0)


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
@pytest.mark.parametrize("rows,width,r0,n", [(2, 2, 0, 2), (8, 38, 2, 4), (12, 64, 0, 12), (20, 30, 3, 13)])
def test_guided_blend_is_the_row_streams_blend(rows, width, r0, n):
    """A band's blend with the normal-guided upsampling and the high-band gain, ``lerp(U D f, f, β) + α U(c - D f)``,
    as :func:`upsample2_guided` and :func:`pool2` make it, on slices (the streams pass views of larger maps); a
    step in the guide keeps its edge (the weights matter: the bilinear blend differs there)."""
    g = torch.Generator().manual_seed(rows * 31 + width)
    c = 6  # two signals side by side
    f = torch.rand(1, c + 1, rows, width + 3, generator=g)[:, 1:, :, 2:2 + width]
    coarse = torch.rand(1, c, rows // 2, width // 2, generator=g)
    normal = torch.randn(1, 3, rows + 2, width, generator=g).clamp(-1, 1)[:, :, 1:1 + rows]
    normal[..., width // 2:] = -normal[..., width // 2:]  # an edge
    normal_half = pool2(normal.contiguous())
    alpha = torch.rand(1, 1, rows, width, generator=g)
    beta = 2 * torch.rand(1, 1, rows, width, generator=g)
    df = pool2(f)
    both = upsample2_guided(torch.cat([df, coarse - df], 1), normal, normal_half, 0.5)
    want = (torch.lerp(both[:, :c], f, beta) + alpha * both[:, c:])[..., r0:r0 + n, :]
    got = guided_blend_native(f, coarse, normal, normal_half, 0.5, alpha, beta, r0, n)
    assert got is not None and got.shape == want.shape == (1, c, n, width)
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-6), float((got - want).abs().max())
    bilinear = (torch.lerp(upsample2(df), f, beta) + alpha * upsample2(coarse - df))[..., r0:r0 + n, :]
    if rows >= 4 and width >= 4:  # (a 1x1 coarse map has one tap: nothing to weigh)
        assert not torch.allclose(got, bilinear, rtol=1e-3, atol=1e-4)
    with pytest.raises(ValueError, match="do not fit"):
        guided_blend_native(f, coarse[..., 1:, :], normal, normal_half, 0.5, alpha, beta, r0, n)


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
@pytest.mark.parametrize("kind", ["log", "none"])
@pytest.mark.parametrize("dtype,layout", [(torch.float32, torch.contiguous_format),
                                          (torch.bfloat16, torch.channels_last), (torch.float32, torch.channels_last)])
def test_feed_is_the_transformed_guide_and_pooled_features(kind, dtype, layout):
    """A band of feature rows (values from 1e-6 to 1e5, both signs; a slice, as the stream's bands are): the guide
    ``relu(W T(x) + b)`` and the pooled ``T(pool2(x))`` as :func:`transform_input`, :func:`pool2` and
    :func:`conv1x1` make them, written into views of larger maps (bfloat16 rounded as torch rounds it)."""
    g = torch.Generator().manual_seed(5)
    c, n, w, cg = 13, 6, 2 * 75, 4
    scale = torch.logspace(-6, 5, c)[None, :, None, None]
    x = (torch.randn(1, c + 2, n + 2, w, generator=g) * scale.new_ones(1, c + 2, 1, 1))[:, 1:1 + c, 1:1 + n] * scale
    weight, bias = torch.randn(cg, c, 1, 1, generator=g) * 0.3, torch.randn(cg, generator=g)
    guide_map = torch.zeros(1, cg, n + 4, w, dtype=dtype)
    pooled_map = torch.empty(1, c, n // 2 + 3, w // 2, dtype=dtype, memory_format=layout).zero_()
    guide, pooled = guide_map[..., 2:2 + n, :], pooled_map[..., 1:1 + n // 2, :]
    assert feed_native(x, kind, weight, bias, guide, pooled)
    t = transform_input(x, kind)
    want_guide = torch.relu(conv1x1(t, weight, bias)).to(dtype)
    want_pooled = transform_input(pool2(x), kind).to(dtype)
    ulp = 2.0**-7 if dtype == torch.bfloat16 else 1e-6  # one rounding step of the stored type, relative
    assert torch.allclose(pooled.float(), want_pooled.float(), rtol=ulp, atol=1e-6)
    assert torch.allclose(guide.float(), want_guide.float(), rtol=ulp, atol=1e-4 * float(want_guide.abs().max()))
    if dtype == torch.bfloat16:  # rounded as torch rounds: the same bfloat16 for nearly every value
        assert (pooled.float() == want_pooled.float()).float().mean() > 0.99
    assert not guide_map[..., :2, :].any() and not pooled_map[..., :1, :].any()  # nothing outside the views
    assert feed_native(x, kind, None, None, None, pooled)  # no guide (a wider guide trails the bands)
    with pytest.raises(ValueError, match="n and W even"):
        feed_native(x[..., 1:, :], kind, weight, bias, guide[..., 1:, :], pooled)


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
@pytest.mark.parametrize("h,w", [(37, 51), (64, 64), (20, 9), (2, 3)])
@pytest.mark.parametrize("clip,bound", [(None, True), (0.15, True), (0.15, False)])
def test_residual_regression_is_the_pytorch_paths(monkeypatch, h, w, clip, bound):
    """The detail stage's regression at stride 2 (pixel-major views, as the stage passes them; odd sizes; a
    firefly): the native pass against the PyTorch path (``KPCN_NATIVE=0``) of the same function."""
    g = torch.Generator().manual_seed(h * w)
    d = torch.rand(1, 3, h, w, generator=g) * 2
    n = d * torch.exp(torch.randn(1, 3, h, w, generator=g) * 0.5)
    n[0, :, h // 2, w // 2] = 500.0
    guide = torch.randn(1, 3, h, w, generator=g)
    d, n, guide = (t[0].permute(1, 2, 0).contiguous().permute(2, 0, 1)[None] for t in (d, n, guide))
    got = residual_regression_native(d, n, guide, 6, 1e-3, bound, clip)
    monkeypatch.setenv("KPCN_NATIVE", "0")
    want = residual_regression(d, n, guide, radius=6, eps=1e-3, stride=2, clip=clip, bound=bound)
    assert got is not None and got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=2e-5, atol=2e-6)


def _extreme_buffers(render, contiguous, one_channel):
    """A real render's layers with NaN, ±Inf, huge and negative values planted, as views or copies."""
    f = render("test:glossy", spp=4, seed=3, resolution=(37, 29))
    b = frame_to_tensors(f, contiguous=contiguous)
    b = {k: v.clone() if contiguous else v for k, v in b.items()}
    for k in ("diffuse", "specular", "diffuseVariance", "normalVariance", "depth"):
        if not contiguous:
            b[k] = b[k].permute(0, 2, 3, 1).clone().permute(0, 3, 1, 2)  # a writable pixel-major copy
    b["specular"][0, :, 3, 4] = 1e38
    b["diffuse"][0, 1, 5, 5] = float("nan")
    b["diffuse"][0, 2, 6, 7] = float("-inf")
    b["diffuseVariance"][0, :, 2, 2] = float("inf")
    b["diffuseVariance"][0, 0, 9, 9] = 1e20  # above its bound: clamped and counted
    b["diffuseVariance"][0, 1, 9, 10] = -3.0
    b["normalVariance"][0, :, 4, 4] = 7.0
    b["depth"][0, :, 0, 0] = float("inf")
    if one_channel:  # renderers that write one variance channel
        for k in ("specularVariance", "albedoVariance", "depthVariance"):
            b[k] = b[k][:, :1].clone()
        b["specularVariance"][0, 0, 1, 1] = 1e30
    return b


@pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine: the PyTorch paths run instead")
@pytest.mark.parametrize("contiguous", [True, False])
@pytest.mark.parametrize("one_channel", [False, True])
@pytest.mark.parametrize("branches", [("diffuse", "specular"), ("specular",)])
def test_branch_features_are_the_pytorch_paths(render, monkeypatch, contiguous, one_channel, branches):
    """A real render with extreme values planted (layers as copies or as views of the frame's arrays, variances of
    one channel or three, one branch or both): the native features, albedo and clamp warnings equal the PyTorch
    path's (``KPCN_NATIVE=0``)."""
    b = _extreme_buffers(render, contiguous, one_channel)
    if branches == ("specular",):
        del b["diffuse"], b["diffuseVariance"]  # an unlisted branch's layers need not be there
    scale = depth_scale_of(torch.nan_to_num(b["depth"][:, :1], posinf=0.0).clamp_min(0.0))

    def run():
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = branch_features(b, scale, branches)
        return out, [str(w.message) for w in caught]

    assert branch_features_native(b, scale, branches) is not None
    got, got_warn = run()
    monkeypatch.setenv("KPCN_NATIVE", "0")
    want, want_warn = run()
    assert set(got) == set(want) == {"albedo", *branches}
    for k in want:
        assert torch.isfinite(got[k]).all(), k
        torch.testing.assert_close(got[k], want[k], rtol=1e-5, atol=1e-6, msg=k)
    assert got_warn == want_warn and len(want_warn) == 1  # the same values clamped, named in the same order
    assert ("diffuseVariance: " in want_warn[0]) == ("diffuse" in branches) and "normalVariance: 3" in want_warn[0]


def test_softmax_apply_refuses_what_it_does_not_do(monkeypatch):
    k = 3
    logits, padded = torch.zeros(1, 9, 6, 8), torch.zeros(1, 3, 8, 10)
    assert softmax_apply_native(logits.double(), padded.double(), k, 16.0) is None
    assert softmax_apply_native(logits, padded, k, MAX_NATIVE_SCALE * 2) is None
    assert softmax_apply_native(logits.requires_grad_(), padded, k, 16.0) is None
    assert softmax_apply_native(torch.zeros(1, 9, 8, 6).transpose(-1, -2), padded, k, 16.0) is None  # columns strided
    if HAVE_CC:
        with pytest.raises(ValueError, match="does not fit"):
            softmax_apply_native(torch.zeros(1, 9, 6, 8), torch.zeros(1, 3, 6, 10), k, 16.0)
    img = torch.zeros(1, 3, 6, 8)
    assert residual_regression_native(img.double(), img.double(), img.double(), 4, 0.01, True, None) is None
    assert residual_regression_native(img.requires_grad_(), img, img, 4, 0.01, True, None) is None
    assert residual_regression_native(torch.zeros(2, 3, 6, 8), torch.zeros(2, 3, 6, 8), torch.zeros(2, 3, 6, 8),
                                      4, 0.01, True, None) is None
    low, guide, wg = torch.zeros(1, 4, 5, 8), torch.zeros(1, 2, 6, 16), torch.zeros(4, 2)
    assert upsample_guide_native(low.double(), guide, wg) is None
    assert upsample_guide_native(low.requires_grad_(), guide, wg) is None
    assert upsample_guide_native(torch.zeros(2, 4, 5, 8), torch.zeros(2, 2, 6, 16), wg) is None
    pad9 = torch.zeros(1, 3, 8, 18)
    assert guided_softmax_native(torch.zeros(1, 9, 5, 8), guide, torch.zeros(9, 2), pad9, k, 16.0) is not None \
        or not HAVE_CC
    assert guided_softmax_native(torch.zeros(1, 9, 5, 8), guide, torch.zeros(9, 2), pad9, k, MAX_NATIVE_SCALE * 2) \
        is None
    assert guided_softmax_native(torch.zeros(1, 9, 5, 8), guide, torch.zeros(9, 2), pad9, 4, 16.0) is None  # even k
    assert guided_softmax_native(torch.zeros(1, 9, 5, 8), guide, torch.zeros(9, 2), pad9.double(), k, 16.0) is None
    x, pooled = torch.zeros(1, 4, 6, 8), torch.zeros(1, 4, 3, 4)
    assert not feed_native(x, "logvar", None, None, None, pooled)  # not a transform it computes
    assert not feed_native(x.double(), "log", None, None, None, pooled)
    assert not feed_native(torch.zeros(1, 65, 6, 8), "log", None, None, None, torch.zeros(1, 65, 3, 4))
    assert not feed_native(x, "log", None, None, None, pooled.half())
    monkeypatch.setenv("KPCN_NATIVE", "0")
    assert native.library() is None and native.status() == "off (KPCN_NATIVE=0)"
    assert not feed_native(x, "log", None, None, None, pooled)
    assert softmax_apply_native(torch.zeros(1, 9, 6, 8), padded, k, 16.0) is None
    assert upsample_guide_native(torch.zeros(1, 4, 5, 8), guide, wg) is None
    assert guided_softmax_native(torch.zeros(1, 9, 5, 8), guide, torch.zeros(9, 2), pad9, k, 16.0) is None


def _default_like_model():
    torch.manual_seed(0)
    cfg = dict(widths=[8, 8, 12, 12], stem="half", kernel_scales=4, out_init_gain=5.0, band_gain=True, albedo_kernel=3,
               up_kernel=1, radiance_pool=True)
    return create_model("unet_kpcn", **cfg).eval()


@pytest.fixture
def rows_for_small_frames(monkeypatch):
    from kpcn.inference import rows

    monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", 0)


def test_a_real_frame_denoises_the_same_without_the_library(render, fresh_native, monkeypatch, rows_for_small_frames):
    """A real render through the row bands (the default's options): with the native kernels (each call counted),
    without a compiler (a clear warning, nothing lost) and with ``KPCN_NATIVE=0``, the same image."""
    frame = render("test:glossy", spp=4, seed=2, resolution=(96, 80))
    model = _default_like_model()
    calls = []

    def counted(real):
        def call(*a):
            out = real(*a)
            calls.append((real.__name__, out is not None and out is not False))
            return out
        return call

    names = {"softmax_apply_native", "upsample_guide_native", "guided_softmax_native", "feed_native"}
    for name in names:
        monkeypatch.setattr(unet_rows, name, counted(getattr(unet_rows, name)))
    def run():
        return inference.denoise_result(frame, model, tile=0, device="cpu", skip=False, precision="float32")
    with_lib = run()
    assert with_lib.stats.row_bands > 0
    assert {name for name, _ in calls} == names
    if HAVE_CC:
        assert all(ok for _, ok in calls), "the row bands must take the native path where the library builds"
    monkeypatch.setenv("CC", str(fresh_native / "no-such-compiler"))
    native.reset()
    calls.clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        without = run()
    assert calls and not any(ok for _, ok in calls)
    assert any("native kernels unavailable" in str(w.message) and "no C compiler" in str(w.message) for w in caught)
    assert "unavailable: no C compiler" in native.status()
    monkeypatch.setenv("KPCN_NATIVE", "0")
    off = run()
    scale = float(np.abs(without.color).max())
    assert float(np.abs(with_lib.color - without.color).max()) < 2e-5 * scale
    np.testing.assert_array_equal(without.color, off.color)
