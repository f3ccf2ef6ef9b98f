"""Training losses (pure maths on synthetic arrays)."""
from __future__ import annotations

import pytest
import torch

from kpcn.losses import create_loss, list_losses, ms_ssim
from kpcn.metrics import tonemap


def test_ms_ssim_is_one_for_equal_images_and_falls_with_noise():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 64, 64, generator=g)
    assert float(ms_ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    values = [float(ms_ssim(x, (x + s * torch.randn(x.shape, generator=g)).clamp(0, 1))) for s in (0.02, 0.1, 0.3)]
    assert values[0] > values[1] > values[2] and values[0] < 1
    with pytest.raises(ValueError, match="too small"):
        ms_ssim(x[..., :20, :20], x[..., :20, :20], scales=3)


def test_ms_ssim_sees_structure_that_l1_does_not():
    """A blur and a constant offset of the same mean absolute error: MS-SSIM penalises the blur more."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 1, 64, 64, generator=g) * 0.5 + 0.25
    blurred = torch.nn.functional.avg_pool2d(x, 5, 1, 2, count_include_pad=False)
    offset = x + (blurred - x).abs().mean()
    assert float(ms_ssim(x, blurred)) < float(ms_ssim(x, offset))


@pytest.mark.parametrize("name", list_losses())
def test_every_loss_is_zero_at_the_target_positive_elsewhere_and_differentiable(name):
    loss = create_loss(name)
    g = torch.Generator().manual_seed(2)
    y = torch.rand(2, 3, 32, 32, generator=g) * 4
    x = (y + 0.3 * torch.randn(y.shape, generator=g)).clamp_min(0).requires_grad_()
    assert float(loss(y, y)) == pytest.approx(0.0, abs=1e-6)
    value = loss(x, y)
    assert float(value.detach()) > 0
    value.backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_loss_params_weigh_the_ms_ssim_term_and_unknown_ones_are_refused():
    from kpcn.config import ConfigError
    from kpcn.losses import log_loss
    from kpcn.train_config import TrainConfig

    g = torch.Generator().manual_seed(3)
    y = torch.rand(2, 3, 32, 32, generator=g) * 4
    x = (y + 0.3 * torch.randn(y.shape, generator=g)).clamp_min(0)
    base, ssim_term = float(log_loss(x, y)), float(create_loss("log_msssim")(x, y)) - float(log_loss(x, y))
    assert ssim_term > 0
    weighted = float(create_loss("log_msssim", {"ssim_weight": 3.0})(x, y))
    assert weighted == pytest.approx(base + 3.0 * ssim_term, rel=1e-5)
    with pytest.raises(ValueError, match="no parameter 'ssim_wieght'.*ssim_weight"):
        create_loss("log_msssim", {"ssim_wieght": 3.0})
    # the config: stage 2's parameters follow its loss; a misspelt one is a ConfigError at load time
    t = TrainConfig(loss="log", stage2_loss="log_msssim", stage2_loss_params={"ssim_weight": 2.0})
    assert t.loss_of(1) == ("log", {}) and t.loss_of(2) == ("log_msssim", {"ssim_weight": 2.0})
    t = TrainConfig(loss="log_msssim", loss_params={"ssim_weight": 2.0})
    assert t.loss_of(2) == ("log_msssim", {"ssim_weight": 2.0})
    with pytest.raises(ConfigError, match="stage2_loss_params.*no parameter 'eps'"):
        TrainConfig(loss="log", stage2_loss="log_msssim", stage2_loss_params={"eps": 1.0})


def test_coarse_term_weighs_lost_energy_not_zero_mean_grain():
    """``coarse_weight``: a checkerboard of ±d around the target (grain that averages out over 4×4) costs the
    pooled term nothing though the per-pixel log loss sees it; a 3 % darkening costs it; 0 leaves the loss as it was."""
    from kpcn.losses import coarse_log_l1, log_l1
    g = torch.Generator().manual_seed(3)
    y = torch.rand(1, 3, 1, 1, generator=g).expand(1, 3, 32, 32) + 0.5  # constant per channel
    sign = (torch.arange(32)[:, None] + torch.arange(32)[None, :]) % 2 * 2 - 1
    grain = y + 0.2 * sign
    assert float(log_l1(grain, y)) > 0.05
    assert float(coarse_log_l1(grain, y)) == pytest.approx(0.0, abs=1e-6)
    assert float(coarse_log_l1(0.97 * y, y)) > 0.01
    # pools past the side: one pool of the whole side
    assert float(coarse_log_l1(0.97 * y[..., :8, :8], y[..., :8, :8], (16, 32))) > 0.01
    x = y * 0.9
    plain = float(create_loss("log_msssim")(x, y))
    assert float(create_loss("log_msssim", {"coarse_weight": 0.0})(x, y)) == plain
    assert float(create_loss("log_msssim", {"coarse_weight": 2.0})(x, y)) == pytest.approx(
        plain + 2.0 * float(coarse_log_l1(x, y)), rel=1e-6)
    # tone_l2_weight adds the mean squared error of the tone-mapped colours (the report's PSNR), 0 when equal
    tone = torch.from_numpy(tonemap(x.numpy())) - torch.from_numpy(tonemap(y.numpy()))
    assert float(create_loss("log_msssim", {"tone_l2_weight": 50.0})(x, y)) == pytest.approx(
        plain + 50.0 * float(tone.square().mean()), rel=1e-3)
    assert float(create_loss("log_msssim", {"tone_l2_weight": 50.0})(y, y)) == pytest.approx(
        float(create_loss("log_msssim")(y, y)), abs=1e-6)
    # relmse_weight adds the relMSE (the report's), 0 when equal
    want = plain + 10.0 * float(((x - y) ** 2 / (y**2 + 1e-2)).mean())
    assert float(create_loss("log_msssim", {"relmse_weight": 10.0})(x, y)) == pytest.approx(want, rel=1e-5)
    assert float(create_loss("log_msssim", {"relmse_weight": 10.0})(y, y)) == pytest.approx(
        float(create_loss("log_msssim")(y, y)), abs=1e-6)
