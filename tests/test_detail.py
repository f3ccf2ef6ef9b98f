"""The detail stage after the network (kpcn.inference.detail): bump shading the normal shows, on real renders."""
import numpy as np
import pytest

from kpcn.inference import denoise_result, load_model
from kpcn.metrics import relmse
from kpcn.models import register_weights, weights_entry
from kpcn.render import render_frame


def _scene(mi, scale, bsdf):
    """A plane under a small sphere light, seen at a slant; bump-mapped (random heights) where ``scale`` > 0."""
    heights = np.random.default_rng(0).random((24, 24, 1)).astype(np.float32)
    bumped = {"type": "bumpmap", "arbitrary": {"type": "bitmap", "bitmap": mi.Bitmap(heights), "raw": True},
              "scale": scale, "bsdf": bsdf}
    look = mi.ScalarTransform4f().look_at(origin=[0, -1.5, 3], target=[0, 0, 0], up=[0, 1, 0])
    return {"type": "scene",
            "sensor": {"type": "perspective", "fov": 40, "to_world": look,
                       "film": {"type": "hdrfilm", "width": 64, "height": 64, "rfilter": {"type": "box"}}},
            "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([3, 3, 1]),
                      "bsdf": bumped if scale else bsdf},
            "light": {"type": "sphere", "center": [2.5, 2, 1.2], "radius": 0.3,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 30.0}}},
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.05}}}


@pytest.fixture(scope="module")
def bumpy(mi):
    out = {}
    for name, bsdf in (("diffuse", {"type": "diffuse"}), ("rough metal", {"type": "roughconductor", "alpha": 0.2})):
        scene = _scene(mi, 0.05, bsdf)
        out[name] = (render_frame(scene, 4, 1, (64, 64)), render_frame(scene, 1024, 2, (64, 64), role=1))
    return out


def test_the_stage_brings_a_bump_mapped_surface_closer_to_its_reference(bumpy):
    """At 4 spp the network blurs the shading of the bumps; the stage adds back what the normal explains. On a
    diffuse and a rough metal bump-mapped plane wide64r (wide64h's weights with the stage, as the default has it) is
    at least 3 % closer to the 1024-spp reference than the same weights without it."""
    for name, (noisy, ref) in bumpy.items():
        plain = denoise_result(noisy, "unet_kpcn:wide64h", device="cpu").color
        res = denoise_result(noisy, "unet_kpcn:wide64r", device="cpu")
        assert res.stats.detail_radius == 6 and 0 < res.stats.detail_seconds < res.stats.seconds, name
        assert "detail stage" in res.stats.summary()
        e_plain, e_stage = relmse(plain, ref["color"]), relmse(res.color, ref["color"])
        assert e_stage < 0.97 * e_plain < relmse(noisy["color"], ref["color"]), (name, e_stage, e_plain)


def test_a_surface_without_bumps_is_left_as_the_network_made_it(mi):
    """A flat normal explains nothing: the stage leaves the network's colour (to float rounding)."""
    noisy = render_frame(_scene(mi, 0.0, {"type": "diffuse"}), 4, 1, (64, 64))
    plain = denoise_result(noisy, "unet_kpcn:wide64h", device="cpu").color
    staged = denoise_result(noisy, "unet_kpcn:wide64r", device="cpu").color
    np.testing.assert_allclose(staged, plain, rtol=1e-5, atol=1e-7)


def _plain(noisy):
    return denoise_result(noisy, "unet_kpcn:wide64h", tile=None, rows=False, device="cpu").color


def test_tiles_and_row_bands_give_the_whole_frame_result(bumpy, monkeypatch):
    import kpcn.inference.rows as rows

    noisy = bumpy["rough metal"][0]
    whole = denoise_result(noisy, "unet_kpcn:wide64r", tile=None, rows=False, device="cpu")
    tiled = denoise_result(noisy, "unet_kpcn:wide64r", tile=16, device="cpu")
    monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", 1)
    banded = denoise_result(noisy, "unet_kpcn:wide64r", tile=None, device="cpu")
    assert tiled.stats.tiles > 1 and banded.stats.row_bands > 1
    assert np.abs(whole.color - _plain(noisy)).max() > 1e-3  # the stage did something here
    for other in (tiled, banded):
        np.testing.assert_allclose(other.color, whole.color, rtol=2e-5, atol=1e-6)


def test_a_tag_sets_config_over_its_file():
    """wide64r is wide64h's file with the stage switched on: one file, two configs, each named by describe."""
    r, h = weights_entry("unet_kpcn", "wide64r"), weights_entry("unet_kpcn", "wide64h")
    keys = {"exposure_range": (0.03, 1.0)}  # every shipped tag: the procedural training frames' exposure keys
    assert r.path == h.path and dict(r.config) == {**keys, "detail_radius": 6, "detail_eps": 0.01, "detail_clip": 0.15}
    default = weights_entry("unet_kpcn")
    # the default has the stage too, with the smaller ridge that wide64e (wide64f's file) set over its file
    f, e = weights_entry("unet_kpcn", "wide64f"), weights_entry("unet_kpcn", "wide64e")
    n = weights_entry("unet_kpcn", "wide64n")
    assert default.tag == "wide64v" and e.path == f.path and dict(f.config) == dict(r.config)
    assert dict(n.config) == dict(e.config) == {**dict(r.config), "detail_eps": 0.001}
    # wide64neg is wide64n's file and settings with the normal-guided blend and the exposure gain on top; the
    # default, wide64v, is its own file (wide64neg fine-tuned), as is wide64q before it, with wide64neg's settings
    ne, neg = weights_entry("unet_kpcn", "wide64ne"), weights_entry("unet_kpcn", "wide64neg")
    assert ne.path == n.path and dict(ne.config) == {**dict(n.config), "edge_upsample": 0.5}
    assert neg.path == n.path and dict(neg.config) == {**dict(ne.config), "exposure_gain": 1.5}
    q = weights_entry("unet_kpcn", "wide64q")
    assert len({default.path, q.path, n.path}) == 3 and dict(default.config) == dict(q.config) == dict(neg.config)
    assert dict(h.config) == keys
    assert load_model("unet_kpcn", "cpu").detail_regression == (6, 0.001, 0.15)
    staged, plain = load_model("unet_kpcn:wide64r", "cpu"), load_model("unet_kpcn:wide64h", "cpu")
    assert staged.detail_regression == (6, 0.01, 0.15) and plain.detail_regression is None
    from kpcn.inference import describe

    assert "detail_radius=6" in describe(staged) and "detail" not in describe(plain)
    with pytest.raises(ValueError, match="detail_radiu"):
        register_weights("unet_kpcn", "bad", "unet_wide64h.safetensors", config={"detail_radiu": 5})


def test_a_file_without_variances_gets_the_stage_too(bumpy):
    """``denoise(path)`` on a split without variance layers picks kpcn:novar_small_r (novar_small's weights with
    the stage), says so, and on the bump-mapped planes comes closer to the reference than novar_small alone."""
    from kpcn.io import Frame

    for name, (noisy, ref) in bumpy.items():
        bare = Frame({k: v for k, v in noisy.layers.items() if not k.endswith("Variance")}, dict(noisy.meta))
        plain = denoise_result(bare, "kpcn:novar_small", device="cpu").color
        with pytest.warns(UserWarning, match="kpcn:novar_small_r"):
            res = denoise_result(bare, None, device="cpu")
        assert res.stats.detail_radius == 6 and "novar" in res.model_name, name
        assert relmse(res.color, ref["color"]) < relmse(plain, ref["color"]), name
