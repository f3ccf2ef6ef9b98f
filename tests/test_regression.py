"""kpcn.ops.regression: the residual's first-order regression on guide features (pure maths on synthetic arrays)."""
import pytest
import torch

from kpcn.ops.regression import box_mean, residual_regression


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
    out = residual_regression(denoised, truth, guide, radius=3, eps=1e-6)
    expected = torch.expm1(torch.log1p(denoised) + ((guide - box_mean(guide, 3)) * a).sum(1, keepdim=True))
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-4)
    assert (out - denoised).abs().mean() > 0.1 * (truth - denoised).abs().mean()
    noise = 0.5 * torch.randn(denoised.shape, generator=g, dtype=torch.float64)
    noisy = torch.expm1(torch.log1p(denoised) + noise)
    kept = torch.log1p(residual_regression(denoised, noisy, guide, radius=3, eps=1e-6)) - torch.log1p(denoised)
    assert kept.pow(2).mean() < 0.1 * noise.pow(2).mean()


def test_gradcheck():
    denoised, guide, g = _pair(2, 6, 7)
    noisy = denoised * torch.exp(0.2 * torch.randn(denoised.shape, generator=g, dtype=torch.float64))
    denoised.requires_grad_(True)
    guide.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d, gd: residual_regression(d, noisy, gd, radius=1, eps=0.05),
                                    (denoised, guide))


def test_shapes_are_checked():
    denoised, guide, _ = _pair()
    with pytest.raises(ValueError, match="must be"):
        residual_regression(denoised, denoised[:, :, :-1], guide)
