"""The frame noise estimate (kpcn.noise) and the input spec that feeds it to a model.

The estimate is checked against the true error of real renders (Mitsuba, tiny
scenes at several spp against a high-spp reference); the pure-maths properties
(constant frames, exposure, non-finite values) on synthetic arrays.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from kpcn import inference
from kpcn.inputs import InputSpec, get_input_spec
from kpcn.models import create_model
from kpcn.noise import PRECISION_MAX, noise_level, noise_precision

RES = (64, 64)
SPEC = get_input_spec("color_albedo_normal_noise")


def _t(frame, name):
    return torch.from_numpy(np.ascontiguousarray(frame[name].transpose(2, 0, 1)))[None].float()


def _cgn(frame):
    return _t(frame, "color"), _t(frame, "albedo"), _t(frame, "normal")


@pytest.mark.parametrize("scene", ["test:glossy", "test:textured"])
def test_estimate_follows_the_true_error_as_spp_grows(render, scene):
    """On real renders the estimated level falls with spp as the true relative error does (about sqrt(2) a doubling)."""
    ref = render(scene, spp=1024, seed=9, resolution=RES)
    spps = (2, 8, 32)
    prec = [float(noise_precision(*_cgn(render(scene, spp=s, seed=1, resolution=RES)))) for s in spps]
    assert prec[0] < prec[1] < prec[2], prec
    for (s0, p0), (s1, p1) in zip(zip(spps, prec), zip(spps[1:], prec[1:])):
        est = 2.0 ** (p1 - p0)  # how much the estimated level fell
        err = [np.sqrt(np.mean((render(scene, spp=s, seed=1, resolution=RES)["color"] - ref["color"]) ** 2)) for s in (s0, s1)]
        true = err[0] / err[1]  # how much the true error fell (about 2 for 4x the samples)
        assert true / 2.0 < est < true * 1.5, (scene, s0, s1, est, true)


def test_estimate_is_exposure_invariant(render):
    c, a, n = _cgn(render("test:glossy", spp=4, seed=1, resolution=RES))
    p = noise_precision(c, a, n)
    for k in (1e-3, 37.0, 1e5):
        assert torch.allclose(noise_precision(c * k, a, n), p, atol=1e-3)


def test_constant_and_black_frames_have_no_noise():
    a = torch.full((2, 3, 16, 16), 0.5)
    n = torch.zeros(2, 3, 16, 16)
    n[:, 2] = 1.0
    c = torch.stack([torch.full((3, 16, 16), 2.0), torch.zeros(3, 16, 16)])
    assert noise_level(c, a, n).flatten().tolist() == [0.0, 0.0]
    assert noise_precision(c, a, n).flatten().tolist() == [PRECISION_MAX, PRECISION_MAX]
    # frames too small for a Laplacian: defined, and no noise measured
    assert noise_level(c[..., :2, :], a[..., :2, :], n[..., :2, :]).flatten().tolist() == [0.0, 0.0]


def test_fireflies_and_non_finite_pixels_move_it_little(render):
    """Each pixel counts at most 1: a few huge fireflies or NaN/Inf do not make a converged frame look noisy."""
    c, a, n = _cgn(render("test:glossy", spp=256, seed=1, resolution=RES))
    p = float(noise_precision(c, a, n))
    g = torch.Generator().manual_seed(0)
    bad = c.clone()
    idx = torch.randperm(RES[0] * RES[1], generator=g)[:4]  # 0.1 % of the pixels
    bad.view(1, 3, -1)[..., idx] = 1e6
    assert abs(float(noise_precision(bad, a, n)) - p) < 0.5
    bad.view(1, 3, -1)[..., idx[:2]] = float("nan")
    bad.view(1, 3, -1)[..., idx[2:]] = float("inf")
    q = noise_precision(bad, a, n)
    assert torch.isfinite(q).all() and abs(float(q) - p) < 0.5
    noisy = float(noise_precision(*_cgn(render("test:glossy", spp=2, seed=1, resolution=RES))))
    assert p - noisy > 2.0  # and the fireflies do not bring it anywhere near a 2-spp frame


def test_bad_shapes_are_refused_with_their_shapes():
    with pytest.raises(ValueError, match=r"albedo is \(1, 3, 8, 9\)"):
        noise_level(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 9), torch.zeros(1, 3, 8, 8))
    with pytest.raises(ValueError, match="color must be a"):
        noise_level(torch.zeros(3, 8, 8), torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8))


def test_spec_channel_is_the_whole_frames_precision(render):
    frame = render("test:glossy", spp=4, seed=1, resolution=RES)
    c, a, n = _cgn(frame)
    built = SPEC.build({"color": c, "albedo": a, "normal": n})["color"]
    assert built.shape == (1, 10, *RES)
    want = noise_precision(c, a, n)
    assert torch.equal(built[:, 9], want[:, 0].expand(1, *RES))
    assert torch.equal(SPEC.frame_value(frame), want)
    # a crop given the frame's value carries it, not its own
    crop = {k: v[..., :20, :20] for k, v in (("color", c), ("albedo", a), ("normal", n))}
    assert torch.equal(SPEC.build(crop, want)["color"][:, 9], want[:, 0].expand(1, 20, 20))
    assert not torch.equal(SPEC.build(crop)["color"][:, 9], want[:, 0].expand(1, 20, 20))


def test_tiles_need_the_whole_frames_value(render, monkeypatch):
    """Negative control of the contract's tiled == untiled for this spec: tiles that measure their own noise differ."""
    frame = render("test:glossy", spp=4, seed=1, resolution=(90, 77))
    torch.manual_seed(0)
    model = create_model("kpcn", input_spec=SPEC.name, layers=3, width=8, kernel_size=5, out_init_gain=5.0).eval()
    res = inference.denoise_result(frame, model, tile=0, device="cpu", skip=False)
    whole = res.color
    assert res.stats.noise_precision == pytest.approx(float(SPEC.frame_value(frame)))  # and the stats say it
    assert "noise precision" in res.stats.summary()
    tiled = inference.denoise(frame, model, tile=24, device="cpu", skip=False)
    assert np.abs(whole - tiled).max() <= 1e-5 * np.abs(whole).max()
    monkeypatch.setattr(InputSpec, "frame_value", lambda self, frame: None)
    own = inference.denoise(frame, model, tile=24, device="cpu", skip=False)
    assert np.abs(whole - own).max() > 1e-3 * np.abs(whole).max()


def test_precision_gate_leaves_a_clean_frame_as_it_is(render):
    """The KPCN precision gate: shut above a precision, a frame is returned as it is; below it, it is filtered.
    The gated kernels are still convex (sum to one), so a constant stays constant."""
    noisy = render("test:glossy", spp=2, seed=1, resolution=RES)
    clean = render("test:glossy", spp=1024, seed=3, resolution=RES)
    p_noisy, p_clean = (float(SPEC.frame_value(f)) for f in (noisy, clean))
    assert p_clean > p_noisy + 2
    torch.manual_seed(0)
    model = create_model("kpcn", input_spec=SPEC.name, layers=3, width=8, kernel_size=5, precision_gate=True).eval()
    with torch.no_grad():  # shut 10 steep units above the midpoint, open below it
        model.color.gate.copy_(torch.tensor([(p_noisy + p_clean) / 2, -1.0]))
    for frame, kept in ((clean, True), (noisy, False)):
        out = inference.denoise(frame, model, device="cpu", skip=False)
        change = np.abs(out - frame["color"]).max() / np.abs(frame["color"]).max()
        assert (change < 1e-4) if kept else (change > 1e-2), (kept, change)
        x = SPEC.build({n: _t(frame, n) for n in ("color", "albedo", "normal")})["color"]
        with torch.no_grad():
            k = model.color.kernels(x)
        assert torch.allclose(k.sum(dim=1), torch.ones(()), atol=1e-5) and (k >= 0).all()


def test_precision_gate_needs_the_precision_channel():
    with pytest.raises(ValueError, match="precision_gate needs an input spec"):
        create_model("kpcn", input_spec="color_albedo_normal", precision_gate=True)
    with pytest.raises(ValueError, match="predicts none"):
        create_model("dpcn", input_spec=SPEC.name, precision_gate=True)
