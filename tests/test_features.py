"""27-channel features against a hand computation on a real render."""
import numpy as np
import pytest
import torch

from kpcn.constants import EPS
from kpcn.features import N_FEATURES, frame_features, frame_to_tensors, gradients, make_features, make_targets
from kpcn.models import reconstruct


def test_feature_channels_match_hand_computation(render):
    f = render("test:glossy", spp=8)
    feats = frame_features(f)
    xd, xs = feats.x_diffuse[0].numpy(), feats.x_specular[0].numpy()
    assert xd.shape[0] == xs.shape[0] == N_FEATURES == 27
    H, W = f.shape
    a = np.clip(f["albedo"], 0, None)
    dmax = f["depth"].max()
    for (y, x) in [(5, 7), (16, 16), (H - 1, 3), (9, W - 1), (H - 1, W - 1)]:
        irr = np.clip(f["diffuse"][y, x], 0, None) / (a[y, x] + EPS)
        np.testing.assert_allclose(xd[0:3, y, x], irr, rtol=1e-5)
        spec = np.clip(f["specular"][y, x], 0, None)
        np.testing.assert_allclose(xs[0:3, y, x], np.log1p(spec), rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(xd[3, y, x], (f["diffuseVariance"][y, x] / (a[y, x] + EPS) ** 2).mean(), rtol=1e-5)
        np.testing.assert_allclose(xs[3, y, x], (f["specularVariance"][y, x] / (1 + spec) ** 2).mean(), rtol=1e-5)
        # x gradient of the branch colour, of normal, albedo, depth; zero on the last column / row
        if x < W - 1:
            irr_r = np.clip(f["diffuse"][y, x + 1], 0, None) / (a[y, x + 1] + EPS)
            np.testing.assert_allclose(xd[4:7, y, x], irr_r - irr, rtol=1e-4, atol=1e-6)
            np.testing.assert_allclose(xd[7:10, y, x], f["normal"][y, x + 1] - f["normal"][y, x], atol=1e-6)
            np.testing.assert_allclose(xd[10:13, y, x], a[y, x + 1] - a[y, x], atol=1e-6)
            np.testing.assert_allclose(xd[13, y, x], (f["depth"][y, x + 1, 0] - f["depth"][y, x, 0]) / dmax, atol=1e-6)
        else:
            assert np.all(xd[4:14, y, x] == 0) and np.all(xs[4:14, y, x] == 0)
        if y < H - 1:
            np.testing.assert_allclose(xs[14:17, y, x], np.log1p(np.clip(f["specular"][y + 1, x], 0, None)) - np.log1p(spec), atol=1e-5)
            np.testing.assert_allclose(xs[17:20, y, x], f["normal"][y + 1, x] - f["normal"][y, x], atol=1e-6)
        else:
            assert np.all(xd[14:24, y, x] == 0)
        np.testing.assert_allclose(xd[24, y, x], f["normalVariance"][y, x].mean(), rtol=1e-5)
        np.testing.assert_allclose(xd[25, y, x], f["albedoVariance"][y, x].mean(), rtol=1e-5)
        np.testing.assert_allclose(xd[26, y, x], f["depthVariance"][y, x, 0] / dmax**2, rtol=1e-5)
    # shared auxiliary channels are identical in both branches
    np.testing.assert_array_equal(xd[7:14], xs[7:14])
    np.testing.assert_array_equal(xd[24:], xs[24:])


def test_targets_reconstruct_the_reference(render):
    noisy = render("test:glossy", spp=8)
    ref = render("test:glossy", spp=256, role=1)
    feats = frame_features(noisy)
    t = make_targets(frame_to_tensors(ref, ("diffuse", "specular")), feats.albedo)
    color = reconstruct(t["y_diffuse"], t["y_specular"], feats.albedo)[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(color, ref["color"], rtol=1e-4, atol=1e-5)


def test_constant_image_has_zero_gradients():
    x = torch.full((1, 4, 8, 9), 3.5)
    gx, gy = gradients(x)
    assert torch.all(gx == 0) and torch.all(gy == 0)
    ramp = torch.arange(9.0).expand(1, 1, 8, 9)
    gx, _ = gradients(ramp)
    assert torch.all(gx[..., :-1] == 1) and torch.all(gx[..., -1] == 0)


def test_features_finite_on_extreme_buffers(render):
    f = render("test:glossy", spp=8)
    b = frame_to_tensors(f)
    b["specular"] = b["specular"] * 1e8
    b["specular"][0, :, 0, 0] = -5.0
    b["diffuse"][0, 0, 1, 1] = float("nan")
    b["specularVariance"][0, :, 2, 2] = float("inf")
    feats = make_features(b)
    for t in feats.as_dict().values():
        assert torch.isfinite(t).all()
    assert torch.all(feats.x_specular[0, 0:3, 0, 0] == 0)


def test_missing_buffer_is_named():
    with pytest.raises(KeyError, match="albedo"):
        make_features({"diffuse": torch.zeros(1, 3, 2, 2)})


def test_input_specs_build_these_features(render):
    # the models read their inputs through kpcn.inputs specs: kpcn_split must give exactly these features
    from kpcn.inputs import get_input_spec

    noisy = render("test:glossy", spp=8)
    ref = render("test:glossy", spp=256, role=1)
    feats = frame_features(noisy)
    spec = get_input_spec("kpcn_split")
    assert spec.branches == ("diffuse", "specular") and spec.channels == N_FEATURES
    inputs = spec.build(frame_to_tensors(noisy, spec.layers))
    assert set(inputs) == {"diffuse", "specular", "albedo"}
    assert torch.equal(inputs["diffuse"], feats.x_diffuse)
    assert torch.equal(inputs["specular"], feats.x_specular)
    assert torch.equal(inputs["albedo"], feats.albedo)
    targets = spec.targets(frame_to_tensors(ref, spec.target_layers), inputs)
    want = make_targets(frame_to_tensors(ref, ("diffuse", "specular")), feats.albedo)
    assert set(targets) == set(want)
    for k in want:
        assert torch.equal(targets[k], want[k])
    # without variances: the same features less the variance channels (3 and 24..26), no variance layer read
    novar = get_input_spec("split_novar")
    assert not any(n.endswith("Variance") for n in novar.layers)
    inputs = novar.build(frame_to_tensors(noisy, novar.layers))
    keep = [c for c in range(N_FEATURES) if c not in (3, 24, 25, 26)]
    assert novar.channels == len(keep) == 23
    assert torch.equal(inputs["diffuse"], feats.x_diffuse[:, keep])
    assert torch.equal(inputs["specular"], feats.x_specular[:, keep])
