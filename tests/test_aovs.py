"""Light groups and AOVs denoised with the beauty's kernels (kpcn.inference.aovs), on real renders."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from kpcn.inference import denoise, denoise_result
from kpcn.io import Frame, MissingLayerError, read_exr
from kpcn.models import create_model


@pytest.fixture(scope="module")
def groups(mi):
    from kpcn.render.groups import render_light_groups

    return render_light_groups("test:textured", spp=8, seed=1, resolution=(48, 40))


def _names(frame):
    return frame.meta["lightGroups"].split(",")


def _rel(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_rendered_groups_add_up_to_the_beauty(groups):
    names = _names(groups)
    assert len(names) >= 2
    for part in ("color", "diffuse", "specular"):
        total = sum(groups[n if part == "color" else f"{n}.{part}"] for n in names)
        np.testing.assert_allclose(total, groups[part], rtol=1e-6, atol=1e-7)
    for n in names:  # each group lights the scene: its own image is not zero, and differs from the beauty
        assert groups[n].max() > 0 and _rel(groups[n], groups["color"]) > 0.05


@pytest.mark.parametrize("model", ["shipped", "unet_can", "kpcn_demod", "unet_albedo", "unet_albedo_rows"])
def test_denoised_light_groups_sum_to_the_denoised_beauty(groups, model, monkeypatch):
    frame = groups
    tile = 16
    if model.startswith("unet_albedo"):  # its own remodulation albedo: the groups must be remodulated with it too
        torch.manual_seed(0)
        net = create_model("unet_kpcn", widths=[8, 8, 12], stem="half", kernel_scales=3, band_gain=True,
                           albedo_kernel=3, out_init_gain=5.0).eval()
        if model.endswith("rows"):  # the whole frame a band of rows at a time
            import kpcn.inference.rows as rows
            monkeypatch.setattr(rows, "ROWS_MIN_PIXELS", 1)
            tile = None
    elif model == "unet_can":  # one colour branch: groups are colour layers
        torch.manual_seed(0)
        net = create_model("unet_kpcn", input_spec="color_albedo_normal", out_init_gain=5.0).eval()
    elif model == "kpcn_demod":  # kernels weighted by albedo ratios: the groups must get the same weighting
        torch.manual_seed(0)
        net = create_model("kpcn", input_spec="color_albedo_normal", layers=3, width=8, kernel_size=5,
                           demodulate=True, out_init_gain=5.0).eval()
    else:
        net = None
    names = _names(frame)
    res = denoise_result(frame, net, tile=tile, device="cpu", layers=names)
    assert res.stats.row_bands == (1 if model == "unet_albedo_rows" else 0) * 2  # 40 rows padded to 64: 2 bands
    assert set(res.layers) == set(names)
    total = sum(res.layers[n] for n in names)
    assert _rel(total, res.color) < 1e-5
    for n in names:
        assert np.isfinite(res.layers[n]).all() and res.layers[n].min() >= 0
        assert 0 < res.layers[n].mean() < 0.99 * res.color.mean()  # a group is a part of the beauty


def test_a_constant_layer_stays_constant_and_is_written(groups, tmp_path):
    frame = Frame(dict(groups.layers), dict(groups.meta))
    frame.layers["const"] = np.full(frame["color"].shape, 0.37, np.float32)
    for branch in ("diffuse", "specular"):
        out = denoise(frame, None, tile=16, device="cpu", layers=["const"], aov_branch=branch)
        np.testing.assert_allclose(out["const"], 0.37, rtol=1e-5)
    res = denoise_result(frame, None, tmp_path / "out.exr", tile=16, device="cpu", layers=["const", *_names(frame)])
    written = read_exr(tmp_path / "out.exr")
    for name in ["const", *_names(frame)]:
        np.testing.assert_array_equal(written[name], res.layers[name])


def test_aov_requests_that_cannot_work_are_refused(groups):
    with pytest.raises(MissingLayerError, match="nope"):
        denoise(groups, None, device="cpu", layers=["nope"])
    dpcn = create_model("dpcn", layers=2, width=4).eval()
    with pytest.raises(ValueError, match="predicts no kernels"):
        denoise(groups, dpcn, device="cpu", layers=_names(groups))
    with pytest.raises(ValueError, match="aov_branch 'color'"):
        denoise(groups, None, device="cpu", layers=_names(groups), aov_branch="color")


def test_a_file_with_only_colour_albedo_normal_gets_the_shipped_model_for_it(render, tmp_path):
    """No split, no variances: denoise(path) picks kpcn:can_small_r (can_small with the detail stage), says so, and
    cuts the error of a noisy render."""
    from kpcn.io import write_exr
    from kpcn.metrics import relmse

    noisy = render("test:glossy", spp=4, seed=2, resolution=(48, 48))
    ref = render("test:glossy", spp=512, seed=9, role=1, resolution=(48, 48))
    path = tmp_path / "can.exr"
    write_exr(path, {k: noisy[k] for k in ("color", "albedo", "normal")})
    with pytest.warns(UserWarning, match="no diffuse/specular split: denoising with kpcn:can_small_r"):
        res = denoise_result(path, None, device="cpu")
    assert "kpcn_can_small" in res.model_name and res.stats.detail_radius > 0
    assert relmse(res.color, ref["color"]) < 0.5 * relmse(noisy["color"], ref["color"])
    # a file with the full split still gets the default model, without a warning
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        full = denoise_result(noisy, None, device="cpu")
    from kpcn.inference import DEFAULT_MODEL
    from kpcn.models import weights_entry

    assert weights_entry(DEFAULT_MODEL).path.name in full.model_name
