"""Exposure keys and the exposure range (kpcn.exposure), and the pipeline's use of them on real renders."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from kpcn.exposure import (SCALE_LIMIT, TRAINED_KEYS, TRANSITION, check_exposure_gain, check_exposure_range,
                           ScaledLayers, exposure_scale, frame_key, scale_layers)
from kpcn.inference import denoise, denoise_result, load_model
from kpcn.io import Frame
from kpcn.metrics import all_metrics

RES = (48, 48)


def _scaled(frame, s, extra=()):
    return Frame(scale_layers(frame.layers, s, extra), dict(frame.meta))


@pytest.fixture(scope="module")
def models():
    """The shipped default, and the same weights with no exposure range nor gain (every frame at its own exposure)."""
    net = load_model("unet_kpcn", "cpu")
    raw = copy.deepcopy(net)
    raw.config.exposure_range, raw.config.exposure_gain = None, 1.0
    return net, raw


# ---------------------------------------------------------------------------------------------- the key (maths)
def test_the_key_is_the_geometric_mean_of_block_luminances():
    rng = np.random.default_rng(0)
    c = (rng.random((37, 50, 3)) ** 3).astype(np.float32)
    c[:16, :16] = 0  # a black block: left out, not a zero in the mean
    c[20, 30] = (-5.0, 0.5, 0.5)  # a negative luminance counts as 0
    lum = np.maximum(c @ np.array([0.2126, 0.7152, 0.0722]), 0)
    blocks = [lum[y:y + 16, x:x + 16].mean() for y in range(0, 37, 16) for x in range(0, 50, 16)]
    blocks = np.array([b for b in blocks if b > 1e-8])
    assert len(blocks) == 11  # 3 x 4 blocks (the last row and column partial), one black
    assert frame_key(c) == pytest.approx(float(np.exp(np.log(blocks).mean())), rel=1e-6)
    for s in (1e-3, 1e-12, 1e12):  # at any scale: the black-block threshold is relative
        assert frame_key(c * np.float32(s)) == pytest.approx(frame_key(c) * s, rel=1e-5)
    assert frame_key(np.zeros((5, 7, 3), np.float32)) == 0.0
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        frame_key(np.zeros((5, 7), np.float32))


def test_exposure_scale_takes_keys_far_outside_to_the_centre_continuously():
    rng, centre = (0.1, 1.0), 0.1 ** 0.5
    assert exposure_scale(0.5, rng) == 1.0 and exposure_scale(0.1, rng) == 1.0 and exposure_scale(1.0, rng) == 1.0
    for key in (0.1 / TRANSITION, 0.01, 1e-9, 1.0 * TRANSITION, 20.0, 1e9):  # TRANSITION x beyond a bound, or more
        assert key * exposure_scale(key, rng) == pytest.approx(centre, rel=1e-9)
    for bound, step in ((0.1, 1 - 1e-7), (1.0, 1 + 1e-7)):  # no jump at a bound
        assert bound * step * exposure_scale(bound * step, rng) == pytest.approx(bound, rel=1e-5)
    keys = np.geomspace(0.1 / TRANSITION, 0.1, 50)  # between: from the centre to the bound, in order
    targets = [k * exposure_scale(k, rng) for k in keys]
    assert all(a >= b for a, b in zip(targets, targets[1:])) and targets[0] > targets[-1]
    assert exposure_scale(0.0, rng) == 1.0  # a black frame is left as it is
    assert exposure_scale(1e-40, rng) == SCALE_LIMIT and exposure_scale(1e40, rng) == 1 / SCALE_LIMIT
    assert exposure_scale(0.001, None) == 1.0
    for bad in ((0.0, 1.0), (1.0, 0.5), (float("nan"), 1.0), (0.1,), "ab"):
        with pytest.raises(ValueError, match="exposure_range"):
            check_exposure_range(bad)


def test_an_exposure_gain_scales_the_frame_before_the_range():
    rng = (0.1, 1.0)
    for key in (0.05, 0.2, 0.8, 3.0, 1e-9):
        assert exposure_scale(key, rng, 1.5) == pytest.approx(1.5 * exposure_scale(1.5 * key, rng), rel=1e-12)
    assert exposure_scale(0.5, rng, 1.5) == 1.5 and exposure_scale(0.9, rng, 1.5) != 1.5  # 1.35: beyond the range
    assert exposure_scale(0.5, None, 2.0) == 2.0 and exposure_scale(0.5, rng, 1.0) == 1.0
    for bad in (0.0, -1.0, 100.0, float("nan"), "x", True):
        with pytest.raises(ValueError, match="exposure_gain"):
            check_exposure_gain(bad)


def test_scale_layers_scales_radiance_and_its_variance_only():
    a = {n: np.full((2, 2, 3), 2.0, np.float32) for n in ("color", "colorVariance", "albedo", "normal",
                                                          "g.diffuse", "g.diffuseVariance", "other")}
    out = scale_layers(a, 3.0, extra=["g.diffuse"])
    assert out["color"][0, 0, 0] == 6.0 and out["colorVariance"][0, 0, 0] == 18.0
    assert out["g.diffuse"][0, 0, 0] == 6.0 and out["g.diffuseVariance"][0, 0, 0] == 18.0
    for n in ("albedo", "normal", "other"):
        assert out[n] is a[n]
    assert a["color"][0, 0, 0] == 2.0  # the input is not changed


def test_scaled_layers_read_as_scale_layers_and_scale_only_the_region_asked_for():
    rng = np.random.default_rng(1)
    a = {n: rng.random((6, 5, 3), dtype=np.float32) for n in ("color", "colorVariance", "albedo", "g.diffuse",
                                                               "g.diffuseVariance", "otherVariance")}
    lazy, eager = ScaledLayers(a, 2.5, extra=["g.diffuse"]), scale_layers(a, 2.5, extra=["g.diffuse"])
    assert sorted(lazy) == sorted(eager) and len(lazy) == len(a) and "albedo" in lazy and "x" not in lazy
    crop = (slice(1, 4), slice(2, 5))
    for n in a:
        np.testing.assert_array_equal(lazy[n], eager[n])
        np.testing.assert_array_equal(lazy.region(n, crop), eager[n][crop])
    assert lazy["albedo"] is a["albedo"] and lazy["otherVariance"] is a["otherVariance"]  # not radiance: as they are
    assert lazy.region("color", crop).shape == (3, 3, 3)
    frame = Frame(lazy)
    assert frame.shape == (6, 5) and frame.region("colorVariance", crop)[0, 0, 0] == eager["colorVariance"][1, 2, 0]
    np.testing.assert_array_equal(frame.beauty(), eager["color"])
    with pytest.raises(KeyError, match="nope"):
        frame.region("nope")


# ------------------------------------------------------------------------------------- on real renders
def test_the_key_of_a_render_hardly_depends_on_its_sample_count(render):
    keys = [frame_key(render("random:5", spp=spp, resolution=(64, 64))["color"]) for spp in (4, 64)]
    assert keys[0] > 0 and abs(keys[0] / keys[1] - 1) < 0.25, keys


def test_a_frame_inside_the_range_is_denoised_at_the_gain(render, models):
    """The default's ``exposure_gain`` (1.5): a frame whose key times the gain lies inside the range is denoised at
    the gain's exposure, and at its own without one."""
    net, raw = models
    frame = render("test:glossy", spp=4, resolution=RES)
    lo, hi = net.exposure_range
    g = net.exposure_gain
    assert g == 1.5 and raw.exposure_gain == 1.0
    res = denoise_result(frame, net, device="cpu", precision="float32")
    assert lo <= g * res.stats.exposure_key <= hi and res.stats.exposure_scale == g
    at_gain = denoise(_scaled(frame, g), raw, device="cpu", precision="float32") / g
    np.testing.assert_allclose(res.color, at_gain, rtol=1e-5, atol=1e-6 * at_gain.max())
    assert np.abs(res.color - denoise(frame, raw, device="cpu", precision="float32")).max() > 1e-4 * at_gain.max()
    no_gain = copy.deepcopy(raw)
    no_gain.config.exposure_range = net.exposure_range
    res = denoise_result(frame, no_gain, device="cpu")
    assert res.stats.exposure_scale == 1.0
    np.testing.assert_array_equal(res.color, denoise(frame, raw, device="cpu"))


def test_frames_far_outside_the_range_are_denoised_at_its_centre(render, models):
    net, raw = models
    frame = render("test:glossy", spp=4, resolution=RES)
    lo, hi = net.exposure_range
    centre, key = (lo * hi) ** 0.5, frame_key(frame["color"])
    # float32: in bfloat16 a last-bit difference of a scaled input can round a hidden value the other way; the frame
    # at the centre as it is (raw: the gain would take it to 1.5x the centre)
    at_centre = denoise(_scaled(frame, centre / key), raw, device="cpu", precision="float32") / (centre / key)
    for e in (1e-3, 1e-12, 1e3, 1e12):
        res = denoise_result(_scaled(frame, e), net, device="cpu", precision="float32")
        assert res.stats.exposure_key * res.stats.exposure_scale == pytest.approx(centre, rel=1e-4)
        assert "exposure key" in res.stats.summary()
        np.testing.assert_allclose(res.color / e, at_centre, rtol=1e-4, atol=1e-4 * at_centre.max())


def test_every_shipped_tag_carries_the_training_keys():
    from kpcn.models import list_weights, weights_entry

    tags = list_weights()
    assert len(tags) > 20
    for name in tags:
        assert dict(weights_entry(*name.split(":")).config)["exposure_range"] == TRAINED_KEYS, name


@pytest.mark.parametrize("name", ["unet_kpcn", "kpcn:can_small_r", "kpcn:novar_small_r", "dpcn", "mskpcn"])
def test_a_dark_or_bright_render_is_not_made_worse_than_its_input(render, name):
    """Every shipped model (the defaults: the U-Net, and those for files without variances or with colour, albedo
    and normal only; DPCN went from 30.0 to 13.7 dB on the report's scenes at x 0.01) carries the procedural
    training keys. Without the range the U-Net returns test:glossy at 1/1000 of its
    exposure further from the reference than the noisy input (relMSE 0.43 against 0.17, 4 spp); with it, close
    to its result at the frame's own exposure (within 1.25x its relMSE; measured 0.99-1.07x)."""
    net = load_model(name, "cpu")
    assert net.exposure_range == TRAINED_KEYS
    raw = copy.deepcopy(net)
    raw.config.exposure_range = None
    frame = render("test:glossy", spp=4, resolution=RES)
    ref = render("test:glossy", spp=256, seed=2, role=1, resolution=RES)["color"]
    noisy = all_metrics(frame["color"], ref)["relmse"]
    own = all_metrics(denoise(frame, net, device="cpu"), ref)["relmse"]
    for e in (1e-3, 1e3):
        with_range = all_metrics(denoise(_scaled(frame, e), net, device="cpu") / e, ref)["relmse"]
        without = all_metrics(denoise(_scaled(frame, e), raw, device="cpu") / e, ref)["relmse"]
        assert with_range < 1.25 * own < noisy, (e, with_range, own, noisy)
        if e < 1:  # without the range a dark frame came back far from the reference (the U-Net: worse than noisy)
            assert with_range < 0.75 * without, (e, with_range, without)


def test_light_groups_follow_the_beauty_at_another_exposure(models):
    from kpcn.render.groups import render_light_groups

    net, _ = models
    frame = render_light_groups("test:textured", spp=8, seed=1, resolution=(48, 40))
    names = frame.meta["lightGroups"].split(",")
    parts = [f"{n}.{b}" for n in names for b in ("diffuse", "specular")]
    out = {}
    for e in (1e-4, 1e-6):
        res = denoise_result(_scaled(frame, e, parts), net, device="cpu", layers=names, precision="float32")
        assert res.stats.exposure_scale > 1
        out[e] = {k: v / e for k, v in {"color": res.color, **res.layers}.items()}
    for k, v in out[1e-4].items():  # the same frame at two exposures below the range: the same result
        np.testing.assert_allclose(out[1e-6][k], v, rtol=1e-4, atol=1e-4 * v.max())
    np.testing.assert_allclose(sum(out[1e-4][n] for n in names), out[1e-4]["color"], rtol=1e-4,
                               atol=1e-4 * out[1e-4]["color"].max())


@pytest.mark.parametrize("how", ["rows", "tiles"])
def test_the_gain_scales_bands_and_tiles_as_it_would_the_whole_frame(mi, models, how):
    """The pipeline scales a frame's radiance as it reads it (:class:`~kpcn.exposure.ScaledLayers`): a frame large
    enough for row bands, and the same in tiles, with two light groups denoised beside the beauty, equals the same
    weights without the gain on the frame scaled beforehand; the caller's arrays are left as they were."""
    from kpcn.render.groups import render_light_groups

    net, raw = models
    # wide enough that a 48-pixel tile's crop (its halo of 166 either side) is not the whole frame
    frame = render_light_groups("test:textured", spp=4, seed=2, resolution=(416, 64))
    before = {n: a.copy() for n, a in frame.layers.items()}
    names = frame.meta["lightGroups"].split(",")
    g = net.exposure_gain
    kw = dict(device="cpu", precision="float32", layers=names, **({"tile": 48, "rows": False} if how == "tiles" else {}))
    res = denoise_result(frame, net, **kw)
    assert res.stats.exposure_scale == g and (res.stats.row_bands > 0) == (how == "rows")
    assert res.stats.tiles == (1 if how == "rows" else 2 * 9)
    want = denoise(_scaled(frame, g, [f"{n}.{p}" for n in names for p in ("diffuse", "specular")]), raw, **kw)
    for name, v in (("color", res.color), *res.layers.items()):
        np.testing.assert_allclose(v, want[name] / g, rtol=1e-5, atol=1e-6 * want["color"].max() / g, err_msg=name)
    for n, a in frame.layers.items():
        np.testing.assert_array_equal(a, before[n], err_msg=n)
