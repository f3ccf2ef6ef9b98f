"""kpcn.ops.regression: the residual's first-order regression on guide features (pure maths on synthetic arrays)."""
import pytest
import torch

from kpcn.ops.regression import box_mean, regression_reach, residual_regression, residual_regression_rows


def _pair(seed=0, h=20, w=24):
    g = torch.Generator().manual_seed(seed)
    denoised = torch.rand(1, 3, h, w, generator=g, dtype=torch.float64) + 0.1
    guide = torch.randn(1, 3, h, w, generator=g, dtype=torch.float64)
    return denoised, guide, g


def test_box_mean_is_the_window_mean():
    x = torch.arange(7 * 9, dtype=torch.float64).reshape(1, 1, 7, 9)
    m = box_mean(x, 1)
    assert m.shape == x.shape
    assert m[0, 0, 3, 4] == pytest.approx(x[0, 0, 2:5, 3:6].mean().item())


def test_a_flat_guide_or_a_converged_input_leaves_the_output_as_it_is():
    denoised, guide, g = _pair()
    noisy = denoised * torch.exp(0.3 * torch.randn(denoised.shape, generator=g, dtype=torch.float64))
    flat = torch.ones_like(guide) * torch.tensor([0.2, -0.5, 0.8], dtype=torch.float64)[None, :, None, None]
    torch.testing.assert_close(residual_regression(denoised, noisy, flat, radius=2, eps=0.01), denoised)
    torch.testing.assert_close(residual_regression(denoised, denoised.clone(), guide, radius=2, eps=0.01), denoised)


def test_a_residual_linear_in_the_guide_is_recovered_and_noise_is_not():
    """log1p(noisy) - log1p(denoised) = a·guide: the regression restores the part that varies with the guide
    around its window mean, (guide - mean(guide))·a (the window mean of the residual stays the denoiser's); a
    pure-noise residual is mostly not returned."""
    denoised, guide, g = _pair(1, 40, 40)
    denoised = denoised + 2.0  # log1p(denoised) > 1.09 > |a·guide|: the noisy colour stays positive
    a = torch.tensor([0.1, -0.08, 0.05], dtype=torch.float64)[None, :, None, None]
    truth = torch.expm1(torch.log1p(denoised) + (guide * a).sum(1, keepdim=True))
    out = residual_regression(denoised, truth, guide, radius=3, eps=1e-6, bound=False)
    expected = torch.expm1(torch.log1p(denoised) + ((guide - box_mean(box_mean(guide, 3), 3)) * a).sum(1, keepdim=True))
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-4)
    assert (out - denoised).abs().mean() > 0.1 * (truth - denoised).abs().mean()
    noise = 0.5 * torch.randn(denoised.shape, generator=g, dtype=torch.float64)
    noisy = torch.expm1(torch.log1p(denoised) + noise)
    kept = (torch.log1p(residual_regression(denoised, noisy, guide, radius=3, eps=1e-6, bound=False))
            - torch.log1p(denoised))
    assert kept.pow(2).mean() < 0.1 * noise.pow(2).mean()


def test_gradcheck():
    denoised, guide, g = _pair(2, 6, 7)
    noisy = denoised * torch.exp(0.2 * torch.randn(denoised.shape, generator=g, dtype=torch.float64))
    denoised.requires_grad_(True)
    guide.requires_grad_(True)
    for bound in (False, True):
        assert torch.autograd.gradcheck(lambda d, gd: residual_regression(d, noisy, gd, radius=1, eps=0.05,
                                                                          bound=bound), (denoised, guide))


def test_bounded_detail_moves_no_channel_further_than_its_noisy_value():
    """A black pixel beside a guide-correlated residual stays black; elsewhere no channel moves further from the
    denoised value (in log1p) than its noisy value is; unbounded, some do (the bound is not idle)."""
    denoised, guide, g = _pair(3, 32, 32)
    noisy = torch.expm1(torch.log1p(denoised) + 0.3 * guide.sum(1, keepdim=True)
                        + 0.3 * torch.randn(denoised.shape, generator=g, dtype=torch.float64)).clamp_min(0)
    noisy[..., 10:14, 10:14] = 0.0
    denoised[..., 10:14, 10:14] = 0.0
    reach = (torch.log1p(noisy) - torch.log1p(denoised)).abs()
    out = residual_regression(denoised, noisy, guide, radius=2, eps=0.01)
    assert ((torch.log1p(out) - torch.log1p(denoised)).abs() <= reach + 1e-12).all()
    assert (out[..., 10:14, 10:14] == 0).all() and (out >= 0).all()
    free = residual_regression(denoised, noisy, guide, radius=2, eps=0.01, bound=False)
    assert ((torch.log1p(free.clamp_min(0)) - torch.log1p(denoised)).abs() > reach + 1e-6).any()
    assert (out - denoised).abs().sum() > 0


@pytest.mark.parametrize("stride", [1, 2])
def test_a_clip_keeps_a_firefly_from_steering_the_fit_or_coming_back(stride):
    """With ``clip`` no pixel's detail exceeds it; a firefly whose residual correlates with the guide brings back
    less of itself than without the clip, and its neighbours' detail moves less."""
    denoised, guide, g = _pair(8, 40, 40)
    logn = torch.log1p(denoised) + 0.2 * guide.sum(1, keepdim=True) + 0.1 * torch.randn(
        denoised.shape, generator=g, dtype=torch.float64)
    logn[..., 20, 20] += 5.0  # a firefly
    noisy = torch.expm1(logn)
    free = residual_regression(denoised, noisy, guide, radius=3, eps=0.01, stride=stride)
    clipped = residual_regression(denoised, noisy, guide, radius=3, eps=0.01, stride=stride, clip=0.15)
    detail = lambda out: torch.log1p(out) - torch.log1p(denoised)  # noqa: E731
    assert detail(clipped).abs().max() <= 0.15 + 1e-9 < detail(free).abs().max()
    assert detail(clipped)[..., 20, 20].abs().max() < detail(free)[..., 20, 20].abs().max()
    with pytest.raises(ValueError, match="clip must be None or > 0"):
        residual_regression(denoised, noisy, guide, clip=0.0)


@pytest.mark.parametrize("stride", [1, 2])
def test_the_three_channel_cofactor_solve_matches_lu(stride):
    """A fourth guide channel that is zero everywhere changes nothing (the ridge makes its system block-diagonal):
    the 3 x 3 cofactor path gives what the general solve gives with four channels; so does a one-channel guide
    padded the same way."""
    denoised, guide, g = _pair(7, 30, 26)
    noisy = denoised * torch.exp(0.3 * torch.randn(denoised.shape, generator=g, dtype=torch.float64))
    for gd in (guide, guide[:, :1]):
        padded = torch.cat([gd, torch.zeros_like(gd[:, :1])], 1)
        torch.testing.assert_close(residual_regression(denoised, noisy, padded, radius=2, eps=0.02, stride=stride),
                                   residual_regression(denoised, noisy, gd, radius=2, eps=0.02, stride=stride))


@pytest.mark.parametrize("stride", [1, 2])
def test_bands_of_rows_give_the_whole_frame_result(stride):
    denoised, guide, g = _pair(4, 151, 41)
    noisy = denoised * torch.exp(0.3 * torch.randn(denoised.shape, generator=g, dtype=torch.float64))
    whole = residual_regression(denoised, noisy, guide, radius=3, eps=0.02, stride=stride)
    for band in (16, 38):
        torch.testing.assert_close(residual_regression_rows(denoised, noisy, guide, radius=3, eps=0.02, band=band,
                                                            stride=stride), whole, rtol=1e-10, atol=1e-12)
    # the noisy colour given at another exposure and its scale (the pipeline's exposure gain): scaled a band at a time
    for band in (16, 1000):  # bands, and the whole frame at once
        torch.testing.assert_close(residual_regression_rows(denoised, noisy / 1.5, guide, radius=3, eps=0.02, band=band,
                                                            stride=stride, noisy_scale=1.5), whole, rtol=1e-10,
                                   atol=1e-12)


@pytest.mark.parametrize("stride", [1, 2])
def test_an_output_pixel_reads_no_further_than_the_reach(stride):
    """Changing the inputs more than regression_reach rows away leaves a pixel as it is; changing them from
    regression_reach rows on moves it (the reach is the least; an even row, which reads furthest with stride 2)."""
    denoised, guide, g = _pair(5, 80, 24)
    noisy = denoised * torch.exp(0.3 * torch.randn(denoised.shape, generator=g, dtype=torch.float64))
    reach, y = regression_reach(3, stride), 40
    base = residual_regression(denoised, noisy, guide, radius=3, eps=0.02, stride=stride)
    far, near = guide.clone(), guide.clone()
    far[..., y + reach + 1:, :] = 0.5
    near[..., y + reach:, :] = 0.5
    torch.testing.assert_close(residual_regression(denoised, noisy, far, radius=3, eps=0.02, stride=stride)[..., y, :],
                               base[..., y, :], rtol=0, atol=0)
    assert not torch.equal(residual_regression(denoised, noisy, near, radius=3, eps=0.02, stride=stride)[..., y, :],
                           base[..., y, :])


def test_statistics_at_every_other_pixel_give_nearly_the_same_detail():
    """On a smooth bump field (the detail the regression is for), stride 2 keeps the stride-1 detail to within a
    few per cent."""
    denoised, _, g = _pair(6, 64, 64)
    yy, xx = torch.meshgrid(torch.arange(64.0, dtype=torch.float64), torch.arange(64.0, dtype=torch.float64),
                            indexing="ij")
    guide = torch.stack([torch.sin(xx / 3), torch.cos(yy / 4), torch.sin((xx + yy) / 5)])[None]
    a = torch.tensor([0.2, -0.1, 0.15], dtype=torch.float64)[None, :, None, None]
    noisy = torch.expm1(torch.log1p(denoised) + (guide * a).sum(1, keepdim=True)
                        + 0.05 * torch.randn(denoised.shape, generator=g, dtype=torch.float64))
    d1, d2 = (torch.log1p(residual_regression(denoised, noisy, guide, radius=4, eps=0.01, stride=s))
              - torch.log1p(denoised) for s in (1, 2))
    assert (d2 - d1).pow(2).mean() < 0.05 * d1.pow(2).mean()
    assert d1.pow(2).mean() > 1e-3


def test_shapes_are_checked():
    denoised, guide, _ = _pair()
    with pytest.raises(ValueError, match="must be"):
        residual_regression(denoised, denoised[:, :, :-1], guide)
    with pytest.raises(ValueError, match="eps must be > 0"):
        residual_regression(denoised, denoised, guide, eps=0.0)
    with pytest.raises(ValueError, match="stride must be 1 or 2"):
        residual_regression(denoised, denoised, guide, stride=3)


@pytest.mark.parametrize("path", ["native", "pytorch"])
def test_a_scaled_noisy_colour_beyond_float32_stays_finite(path, monkeypatch):
    """``noisy_scale`` holds a product beyond float32's range at its largest, as the exposure's scaled layers do: a
    3e38 pixel at 1.5× gives the result of the saturated colour, finite, not an infinity (the native pass and the
    PyTorch one)."""
    if path == "pytorch":
        import kpcn.ops.regression as regression

        monkeypatch.setattr(regression, "residual_regression_native", lambda *a, **k: None)
    denoised, guide, g = _pair(6, 40, 24)
    denoised, guide = denoised.float(), guide.float()
    noisy = denoised * torch.exp(0.3 * torch.randn(denoised.shape, generator=g)).float()
    noisy[0, :, 20, 12] = 3e38
    saturated = (noisy.double() * 1.5).clamp(max=torch.finfo(torch.float32).max).float()
    for band in (16, 1000):
        got = residual_regression_rows(denoised, noisy, guide, radius=3, eps=0.02, band=band, stride=2,
                                       noisy_scale=1.5)
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got, residual_regression_rows(denoised, saturated, guide, radius=3, eps=0.02,
                                                                 band=band, stride=2))
