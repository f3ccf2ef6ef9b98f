import pytest
import torch
import torch.nn.functional as F

from kpcn.config import ConfigError
from kpcn.constants import EPS, N_FEATURES
from kpcn.models import (
    BranchConfig,
    Denoiser,
    KPCNBranch,
    create_model,
    list_models,
    reconstruct,
    register_model,
)

TINY = dict(layers=3, width=8, conv_size=3, kernel_size=5)


def _inputs(b=2, h=12, w=13, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    xd = torch.rand(b, N_FEATURES, h, w, generator=g, dtype=dtype)
    xs = torch.rand(b, N_FEATURES, h, w, generator=g, dtype=dtype)
    albedo = torch.rand(b, 3, h, w, generator=g, dtype=dtype)
    return xd, xs, albedo


def _d(xd, xs, albedo):
    """The model's input dict (the ``kpcn_split`` spec): a branch given as None is absent."""
    return {"diffuse": xd, "specular": xs, "albedo": albedo}


def _neighbourhood_range(colour, k):
    r = k // 2
    b, c, h, w = colour.shape
    cols = F.unfold(F.pad(colour, (r, r, r, r), mode="replicate"), k).view(b, c, k * k, h, w)
    return cols.min(dim=2).values, cols.max(dim=2).values


def test_registry_lists_and_creates():
    assert {"kpcn", "dpcn"} <= set(list_models())
    for name in ("kpcn", "dpcn"):
        m = create_model(name, **TINY)
        assert isinstance(m, Denoiser) and m.kind == name
        assert m.config == BranchConfig(**TINY)
    # rebuild from hparams
    m = create_model("kpcn", **TINY)
    m2 = create_model(**m.hparams())
    m2.load_state_dict(m.state_dict())


def test_registry_errors():
    with pytest.raises(ValueError, match="known models: .*dpcn.*kpcn"):
        create_model("unet9000")
    with pytest.raises(ConfigError, match=r"model kpcn\.layerz: unknown key; did you mean 'layers'\? valid keys: "):
        create_model("kpcn", layerz=3)
    with pytest.raises(ConfigError, match=r"model kpcn\.layers: expected an integer, got 'abc'"):
        create_model("kpcn", layers="abc")
    with pytest.raises(ValueError, match="odd"):
        create_model("kpcn", kernel_size=4)
    with pytest.raises(ValueError, match="already registered"):

        @register_model("kpcn", config=BranchConfig)
        def other(config):  # pragma: no cover
            return None


@pytest.mark.parametrize("name", ["kpcn", "dpcn"])
def test_output_shapes_and_channels_last(name):
    torch.manual_seed(0)
    m = create_model(name, **TINY)
    xd, xs, albedo = _inputs()
    out = m(_d(xd, xs, albedo))
    assert set(out) == {"diffuse", "specular", "color"}
    for v in out.values():
        assert v.shape == albedo.shape
    cl = lambda t: t.to(memory_format=torch.channels_last)  # noqa: E731
    out_cl = m(_d(cl(xd), cl(xs), cl(albedo)))
    for key in out:
        torch.testing.assert_close(out_cl[key], out[key], rtol=1e-5, atol=1e-5)


def test_kpcn_output_in_convex_hull():
    torch.manual_seed(1)
    # a large output gain gives sharp, irregular kernels
    m = create_model("kpcn", **TINY, out_init_gain=5.0)
    xd, xs, albedo = _inputs(seed=1)
    xd[:, :3] = torch.randn_like(xd[:, :3]) * 10  # signed colours too
    out = m(_d(xd, xs, albedo))
    for key, x in (("diffuse", xd), ("specular", xs)):
        lo, hi = _neighbourhood_range(x[:, :3], 5)
        y = out[key]
        assert (y >= lo - 1e-4).all() and (y <= hi + 1e-4).all()
        assert not torch.allclose(y, x[:, :3])  # it did filter


def test_kpcn_kernels_are_normalised_and_bounded():
    torch.manual_seed(2)
    branch = KPCNBranch(BranchConfig(**TINY, logit_scale=4.0, out_init_gain=100.0))
    x = torch.rand(1, N_FEATURES, 9, 9) * 100
    w = branch.kernels(x)
    torch.testing.assert_close(w.sum(dim=1), torch.ones(1, 9, 9))
    logits = branch.logits(x)
    assert logits.abs().max() <= 4.0
    # ratio of any two taps is bounded by exp(2 * logit_scale)
    assert (w.max(dim=1).values / w.min(dim=1).values).max() <= torch.exp(torch.tensor(8.0)) * 1.001


def test_demodulated_kernels_filter_the_albedo_demodulated_colour():
    """``demodulate``: the output is ``(1 - beta) K*c + beta (a + e) K*(c / (a + e))`` with the softmax kernel ``K``,
    ``beta`` the extra logit's sigmoid and ``a`` the mean albedo (float64, replicated borders included)."""
    from kpcn.models.layers import DEMOD_EPS
    from kpcn.ops.kernel_apply import kernel_apply

    torch.manual_seed(4)
    cfg = BranchConfig(**TINY, input_spec="color_albedo_normal", demodulate=True, out_init_gain=5.0)
    branch = KPCNBranch(cfg).double()
    with torch.no_grad():
        branch.net[-1].bias[25] = 0.0  # beta around 0.5 instead of its initial 0.018
    g = torch.Generator().manual_seed(4)
    x = torch.rand(2, 9, 10, 11, generator=g, dtype=torch.float64)
    x[:, :3] *= 5.0
    x[:, 3:6] = torch.rand(2, 3, 10, 11, generator=g, dtype=torch.float64) ** 3  # dark and bright albedo
    z = branch.logits(x)
    w, beta = torch.softmax(z[:, :25], dim=1), torch.sigmoid(z[:, 25:])
    assert beta.std() > 0.05  # the blend weight varies: both terms count
    a = x[:, 3:6].mean(dim=1, keepdim=True) + DEMOD_EPS
    c = x[:, :3]
    want = (1 - beta) * kernel_apply(c, w, 5, "replicate") + beta * a * kernel_apply(c / a, w, 5, "replicate")
    torch.testing.assert_close(branch(x), want, rtol=1e-10, atol=1e-12)
    # and it differs from the plain kernel (the demodulated term moved the output)
    assert (branch(x) - kernel_apply(c, w, 5, "replicate")).abs().max() > 1e-3
    # a constant colour over a constant albedo stays constant; zero stays zero
    x2 = x.clone()
    x2[:, :3], x2[:, 3:6] = 0.7, 0.3
    torch.testing.assert_close(branch(x2), torch.full_like(c, 0.7))
    x2[:, :3] = 0.0
    assert torch.equal(branch(x2), torch.zeros_like(c))


def test_demodulate_needs_a_colour_spec_and_kernels():
    with pytest.raises(ValueError, match="demodulate needs a colour"):
        BranchConfig(**TINY, demodulate=True)  # the split spec: its diffuse branch is demodulated already
    with pytest.raises(ValueError, match="demodulate weights kernels"):
        create_model("dpcn", **TINY, input_spec="color_albedo_normal", demodulate=True)
    m = create_model("kpcn", **TINY, input_spec="color_albedo_normal", demodulate=True)
    assert not m.convex_kernels and m.zero_preserving


def test_fresh_kpcn_is_mild_blur_and_dpcn_near_identity():
    torch.manual_seed(3)
    k = 5
    m = create_model("kpcn", **TINY)
    xd, _, _ = _inputs(seed=3)
    w = m.diffuse.kernels(xd).mean(dim=(0, 2, 3)).view(k, k)
    assert w.argmax() == (k // 2) * k + k // 2  # centre tap dominates
    d = create_model("dpcn", **TINY)
    y = d.diffuse(xd)
    assert (y - xd[:, :3]).abs().mean() < 0.5 * xd[:, :3].abs().mean()


def test_reconstruction_formula():
    torch.manual_seed(4)
    m = create_model("kpcn", **TINY)
    xd, xs, albedo = _inputs(seed=4)
    out = m(_d(xd, xs, albedo))
    expected = (albedo + EPS) * out["diffuse"] + torch.expm1(out["specular"])
    torch.testing.assert_close(out["color"], expected)
    assert (out["diffuse"] >= 0).all() and (out["specular"] >= 0).all()


@pytest.mark.parametrize("name", ["kpcn", "dpcn"])
@pytest.mark.parametrize("scale", [1.0, 1e3, 1e8, 1e30])
def test_colour_finite_and_non_negative(name, scale):
    torch.manual_seed(5)
    m = create_model(name, **TINY)
    xd, xs, albedo = _inputs(seed=5)
    xd = (xd - 0.3) * scale  # includes negative values
    xs = (xs - 0.3) * scale
    out = m(_d(xd, xs, albedo * scale))
    assert torch.isfinite(out["color"]).all()
    assert (out["color"] >= 0).all()


def test_reconstruct_clamps():
    d = torch.tensor([-1.0, 2.0, float("inf"), 1.0]).view(1, 1, 1, 4).expand(1, 3, 1, 4)
    s = torch.tensor([-5.0, 0.5, 1.0, 1e4]).view(1, 1, 1, 4).expand(1, 3, 1, 4)
    a = torch.full((1, 3, 1, 4), 0.5)
    c = reconstruct(d, s, a)
    assert torch.isfinite(c).all() and (c >= 0).all()
    torch.testing.assert_close(c[0, 0, 0, 0], torch.tensor(0.0))
    torch.testing.assert_close(c[0, 0, 0, 1], (0.5 + EPS) * 2.0 + torch.expm1(torch.tensor(0.5)))


@pytest.mark.parametrize("name", ["kpcn", "dpcn"])
def test_branch_skipping(name):
    torch.manual_seed(6)
    m = create_model(name, **TINY)
    xd, xs, albedo = _inputs(seed=6)
    full = m(_d(xd, xs, albedo))
    only_d = m(_d(xd, None, albedo))
    only_s = m(_d(None, xs, albedo))
    assert torch.equal(only_d["specular"], torch.zeros_like(albedo))
    assert torch.equal(only_s["diffuse"], torch.zeros_like(albedo))
    torch.testing.assert_close(only_d["diffuse"], full["diffuse"])
    torch.testing.assert_close(only_s["specular"], full["specular"])
    # DPCN outputs may be negative: the reconstruction clamps them
    torch.testing.assert_close(only_d["color"], (albedo + EPS) * full["diffuse"].clamp(min=0))
    torch.testing.assert_close(only_s["color"], torch.expm1(full["specular"].clamp(min=0)))
    both_none = m(_d(None, None, albedo))
    assert torch.equal(both_none["color"], torch.zeros_like(albedo))


def test_kpcn_constant_colour_stays_constant():
    torch.manual_seed(7)
    m = create_model("kpcn", **TINY, out_init_gain=3.0)  # replicate padding by default
    xd, xs, albedo = _inputs(seed=7)
    xd[:, :3] = torch.tensor([0.2, 1.5, 7.0]).view(1, 3, 1, 1)
    y = m.diffuse(xd)
    torch.testing.assert_close(y, xd[:, :3].expand_as(y).contiguous(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    "name,cfg,radius",
    [
        ("kpcn", dict(layers=3, width=6, conv_size=3, kernel_size=5), 3),  # network wider than kernel
        ("kpcn", dict(layers=2, width=6, conv_size=3, kernel_size=9), 4),  # kernel wider than network
        ("dpcn", dict(layers=2, width=6, conv_size=5, kernel_size=5), 4),
        ("kpcn", dict(layers=4, width=6, conv_size=3, kernel_size=5, dilations=[1, 2, 4, 1]), 8),
        ("dpcn", dict(layers=3, width=6, conv_size=3, dilations=[1, 3, 2], input_transform="none"), 6),
    ],
)
def test_receptive_radius_impulse_response(name, cfg, radius):
    torch.manual_seed(8)
    m = create_model(name, **cfg, out_init_gain=1.0).double()
    assert m.receptive_radius == radius
    h = w = 2 * radius + 9
    g = torch.Generator().manual_seed(8)
    x = torch.rand(1, N_FEATURES, h, w, generator=g, dtype=torch.float64)
    cy, cx = h // 2, w // 2
    x2 = x.clone()
    x2[:, :, cy, cx] += torch.rand(N_FEATURES, generator=g, dtype=torch.float64) + 0.5
    with torch.no_grad():
        diff = (m.diffuse(x2) - m.diffuse(x)).abs().amax(dim=(0, 1))
    ys, xs = torch.nonzero(diff > 1e-12, as_tuple=True)
    dist = torch.maximum((ys - cy).abs(), (xs - cx).abs())
    assert dist.max().item() == radius  # changes reach exactly the radius, not further


def test_receptive_radius_formula():
    assert create_model("kpcn").receptive_radius == max(9 * 2, 10)
    assert create_model("kpcn", layers=2, conv_size=3, kernel_size=21).receptive_radius == 10
    assert create_model("dpcn", layers=9, conv_size=5).receptive_radius == 18


def test_backward_gives_finite_gradients():
    torch.manual_seed(9)
    m = create_model("kpcn", **TINY)
    xd, xs, albedo = _inputs(b=1, h=10, w=10, seed=9)
    out = m(_d(xd, xs, albedo))
    out["color"].abs().mean().backward()
    grads = [p.grad for p in m.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_input_checks():
    m = create_model("kpcn", **TINY)
    xd, xs, albedo = _inputs()
    with pytest.raises(ValueError, match=r"inputs\['diffuse'\] must be a \(B, 27, H, W\) tensor, got \(2, 20, 12, 13\)"):
        m(_d(xd[:, :20], xs, albedo))
    with pytest.raises(ValueError, match="27 channels"):  # a branch module called on its own checks too
        m.diffuse(xd[:, :20])
    with pytest.raises(ValueError, match="albedo"):
        m(_d(xd, xs, albedo[:, :2]))
    with pytest.raises(ValueError, match="batch and spatial"):
        m(_d(xd[:, :, :10], xs, albedo))
    with pytest.raises(ValueError, match="layers"):
        BranchConfig(layers=0)
    with pytest.raises(ValueError, match="padding_mode"):
        BranchConfig(padding_mode="reflect")


def test_log_input_transform_makes_network_input_scale_robust():
    from kpcn.models.layers import transform_input

    x = torch.tensor([-1e8, -1.0, 0.0, 1.0, 1e8])
    y = transform_input(x, "log")
    assert torch.all(torch.sign(y) == torch.sign(x)) and y.abs().max() < 20
    assert torch.equal(transform_input(x, "none"), x)
    with pytest.raises(ValueError, match="input_transform"):
        BranchConfig(input_transform="sqrt")
    with pytest.raises(ValueError, match="dilations"):
        BranchConfig(layers=3, dilations=[1, 2])


def test_logvar_transform_resolves_small_variances():
    from kpcn.models.layers import VARIANCE_CHANNELS, transform_input

    x = torch.zeros(2, N_FEATURES, 1, 1)
    x[0, list(VARIANCE_CHANNELS)] = 1e-5  # a converged render
    x[1, list(VARIANCE_CHANNELS)] = 1e-3  # a noisy one
    log1p_gap = (transform_input(x, "log")[1] - transform_input(x, "log")[0]).abs().max()
    logvar_gap = (transform_input(x, "logvar")[1] - transform_input(x, "logvar")[0]).abs().max()
    assert log1p_gap < 1e-2 < 4.0 < logvar_gap  # log(1e-3 / 1e-5) ~ 4.6 apart
    other = [c for c in range(N_FEATURES) if c not in VARIANCE_CHANNELS]
    assert torch.equal(transform_input(x, "logvar")[:, other], transform_input(x, "log")[:, other])


def test_up_cat_conv_equals_upsample_concatenate_convolve():
    # the decoder's fused first conv (a transposed conv of the coarse map + a conv of the skip) against the
    # plain nearest upsampling, concatenation and 3x3 conv, in float64, borders included, both memory formats
    from kpcn.models.layers import UpCatConv, up_cat_conv3x3

    g = torch.Generator().manual_seed(0)
    for b, cc, cs, o, h, w in [(2, 5, 3, 4, 3, 7), (1, 8, 6, 5, 1, 1), (1, 2, 3, 6, 9, 4)]:
        coarse = torch.randn(b, cc, h, w, generator=g, dtype=torch.float64)
        skip = torch.randn(b, cs, 2 * h, 2 * w, generator=g, dtype=torch.float64)
        weight = torch.randn(o, cc + cs, 3, 3, generator=g, dtype=torch.float64)
        bias = torch.randn(o, generator=g, dtype=torch.float64)
        want = F.conv2d(torch.cat([F.interpolate(coarse, scale_factor=2, mode="nearest"), skip], 1), weight, bias,
                        padding=1)
        for fmt in (torch.contiguous_format, torch.channels_last):
            got = up_cat_conv3x3(coarse.contiguous(memory_format=fmt), skip.contiguous(memory_format=fmt), weight, bias)
            torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
        # the module: the plain path with autograd, the fused one without; the same parameters
        mod = UpCatConv(cc + cs, o, 3, padding=1).double()
        with torch.no_grad():
            mod.weight.copy_(weight), mod.bias.copy_(bias)
            torch.testing.assert_close(mod((coarse, skip)), want, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(mod((coarse, skip)), want, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="not twice coarse"):
        up_cat_conv3x3(torch.zeros(1, 2, 3, 3), torch.zeros(1, 1, 5, 6), torch.zeros(1, 3, 3, 3))
    with pytest.raises(ValueError, match="3x3 kernel over 2 \\+ 1"):
        up_cat_conv3x3(torch.zeros(1, 2, 3, 3), torch.zeros(1, 1, 6, 6), torch.zeros(1, 4, 3, 3))


def test_up_add_conv_is_the_up_cat_conv_with_centre_coarse_taps():
    """UpAddConv (``up_kernel: 1``) computes the decoder's ``conv3x3([nearest_up2(coarse), skip])`` whose taps over the
    coarse channels are zero off the centre: float64, with and without autograd, both memory formats; the in-place
    broadcast add of a bfloat16 channels_last map against the plain upsampling; a float64 gradcheck."""
    from kpcn.models.layers import UpAddConv

    g = torch.Generator().manual_seed(0)
    for b, cc, cs, o, h, w in [(2, 5, 3, 4, 3, 7), (1, 8, 6, 5, 1, 1)]:
        coarse = torch.randn(b, cc, h, w, generator=g, dtype=torch.float64)
        skip = torch.randn(b, cs, 2 * h, 2 * w, generator=g, dtype=torch.float64)
        mod = UpAddConv(cc, cs, o).double()
        with torch.no_grad():
            mod.bias.copy_(torch.randn(o, generator=g, dtype=torch.float64))
        full = torch.zeros(o, cc + cs, 3, 3, dtype=torch.float64)
        full[:, :cc, 1, 1] = mod.coarse.weight[:, :, 0, 0].detach()
        full[:, cc:] = mod.weight.detach()
        want = F.conv2d(torch.cat([F.interpolate(coarse, scale_factor=2, mode="nearest"), skip], 1), full, mod.bias,
                        padding=1)
        torch.testing.assert_close(mod((coarse, skip)), want, rtol=1e-12, atol=1e-12)
        with torch.no_grad():
            for fmt in (torch.contiguous_format, torch.channels_last):
                got = mod((coarse.contiguous(memory_format=fmt), skip.contiguous(memory_format=fmt)))
                torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
        assert torch.autograd.gradcheck(lambda c, s: mod((c, s)), (coarse.clone().requires_grad_(),
                                                                  skip.clone().requires_grad_()))
    # bfloat16 channels_last without autograd (the in-place 2x2 broadcast) against the plain path on the same values
    mod = UpAddConv(6, 4, 8)
    coarse = torch.randn(1, 6, 5, 9, generator=g).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
    skip = torch.randn(1, 4, 10, 18, generator=g).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        got = mod((coarse, skip))
        plain = F.conv2d(skip, mod.weight, mod.bias, padding=1) + F.interpolate(mod.coarse(coarse), scale_factor=2)
    assert got.dtype == torch.bfloat16 and got.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(got.float(), plain.float(), rtol=0, atol=0)
    with pytest.raises(ValueError, match="not twice coarse"):
        mod((torch.zeros(1, 6, 3, 3), torch.zeros(1, 4, 5, 6)))
    with pytest.raises(ValueError, match="up_kernel must be 1 or 3"):
        create_model("unet_kpcn", up_kernel=2)


@pytest.mark.parametrize("kw,msg", [({"albedo_kernel": 2}, "albedo_kernel must be 0"),
                                    ({"albedo_kernel": -1}, "albedo_kernel must be 0"),
                                    ({"albedo_kernel": True}, "albedo_kernel: expected an integer"),
                                    ({"albedo_kernel": 3}, "needs kernel_scales >= 2"),
                                    ({"albedo_gate_gain": 0.0}, "albedo_gate_gain must be positive"),
                                    ({"albedo_clamp": 1.0, "input_spec": "split_novar"}, "needs the kpcn_split input spec"),
                                    ({"albedo_clamp": -1.0}, "albedo_clamp must be >= 0"),
                                    ({"albedo_kernel": 3, "kernel_scales": 2, "input_spec": "color_albedo_normal"},
                                     "needs an input spec with a diffuse branch")])
def test_albedo_kernel_config_is_checked(kw, msg):
    with pytest.raises(ValueError, match=msg):
        create_model("unet_kpcn", **kw)


@pytest.mark.parametrize("kw,msg", [({"specular_widths": [8, 12, 16]}, "specular_widths must be None or 4"),
                                    ({"specular_widths": [8, 12, 0, 24]}, "specular_widths must be None or 4"),
                                    ({"specular_widths": [8, 12, 16, 24], "input_spec": "color_albedo_normal"},
                                     "needs an input spec with a specular branch")])
def test_specular_widths_config_is_checked(kw, msg):
    with pytest.raises(ValueError, match=msg):
        create_model("unet_kpcn", **kw)


def test_specular_widths_narrow_the_specular_branch_alone():
    """``specular_widths`` builds the specular branch at its own widths and leaves the diffuse branch as ``widths``
    builds it: the same parameters, and the same output on the same input, as in a model without it."""
    torch.manual_seed(0)
    base = create_model("unet_kpcn", widths=[8, 12, 16], stem="half", kernel_scales=2).eval()
    torch.manual_seed(0)
    narrow = create_model("unet_kpcn", widths=[8, 12, 16], stem="half", kernel_scales=2,
                          specular_widths=[4, 6, 10]).eval()
    assert [b[0].out_channels for b in narrow.specular.enc] == [4, 6, 10]
    assert [b[0].out_channels for b in narrow.diffuse.enc] == [8, 12, 16]
    for (k, a), (_, b) in zip(base.diffuse.state_dict().items(), narrow.diffuse.state_dict().items()):
        assert torch.equal(a, b), k
    x = torch.rand(1, base.input_spec.channels, 24, 24)
    with torch.no_grad():
        torch.testing.assert_close(narrow.diffuse(x), base.diffuse(x), rtol=0, atol=0)
        assert narrow.specular(x).shape == base.specular(x).shape


def test_relu_on_bfloat16_is_the_relu_bit_for_bit():
    """kpcn.models.layers.relu_ clamps a bfloat16 tensor through its int16 view: the same bits as relu, but
    for -0, which becomes +0 (relu keeps -0; the two are equal values)."""
    from kpcn.models.layers import ReLU, relu_

    g = torch.Generator().manual_seed(0)
    x = (torch.randn(2, 7, 9, 11, generator=g) * torch.logspace(-30, 30, 11)).to(torch.bfloat16)
    x[0, 0, 0, :4] = torch.tensor([-0.0, 0.0, -1e-40, float("inf")], dtype=torch.bfloat16)
    x[0, 0, 1, :2] = torch.tensor([float("-inf"), -torch.finfo(torch.bfloat16).max], dtype=torch.bfloat16)
    want = torch.relu(x)
    want[want == 0] = 0.0  # +0 where relu kept -0
    for t in (x.clone(), x.clone().contiguous(memory_format=torch.channels_last), x.clone()[..., ::2]):
        w = want if t.shape == want.shape else want[..., ::2]
        with torch.no_grad():
            got = relu_(t)
        assert got.data_ptr() == t.data_ptr() and torch.equal(got.view(torch.int16), w.view(torch.int16))
    assert (x < 0).any() and (want == 0).sum() > (x == 0).sum()  # the case has negatives to clamp
    # with autograd, the plain ReLU (and its gradient)
    y = x.float().requires_grad_()
    ReLU()(y * 1).sum().backward()
    assert torch.equal(y.grad, (x.float() > 0).float())


def test_unet_guide_kernel_must_be_odd_and_reaches_no_further_than_the_radius_says():
    """An even guide kernel is refused; a guide reaching past the half-resolution stem's 3 full-resolution pixels
    widens the receptive radius the tiling overlaps by (a 3x3 guide does not)."""
    with pytest.raises(ValueError, match="guide_kernel must be a positive odd integer, got 2"):
        create_model("unet_kpcn", stem="half", guide_kernel=2)
    radius = {gk: create_model("unet_kpcn", stem="half", kernel_scales=2, guide_kernel=gk).receptive_radius
              for gk in (1, 3, 9)}
    assert radius[1] == radius[3] and radius[9] == radius[1] + 1


def test_unet_coarse_kernel_and_deep_blocks_settings():
    """``coarse_kernel`` sizes the coarser levels' kernels only (their heads' logits, the reach the radius counts) and
    is refused where there are no coarser levels or it is even; ``deep_blocks`` widens the radius by its convs'
    reach at the coarsest level and is refused below 0."""
    base = create_model("unet_kpcn", stem="half", kernel_scales=3, kernel_size=3)
    mixed = create_model("unet_kpcn", stem="half", kernel_scales=3, kernel_size=3, coarse_kernel=5)
    assert mixed.diffuse.head.out_channels == base.diffuse.head.out_channels == 9 + 1
    assert [h.out_channels for h in mixed.diffuse.heads] == [25 + 1, 25]
    # levels 1 and 2 reach (5 // 2 + 2) · 2**l instead of (3 // 2 + 2) · 2**l: 2 + 4 more pixels
    assert mixed.receptive_radius == base.receptive_radius + 6
    with pytest.raises(ValueError, match="coarse_kernel must be 0 .* or a positive odd integer, got 4"):
        create_model("unet_kpcn", stem="half", kernel_scales=3, coarse_kernel=4)
    with pytest.raises(ValueError, match="coarse_kernel needs kernel_scales >= 2"):
        create_model("unet_kpcn", coarse_kernel=3)
    deep = create_model("unet_kpcn", stem="half", kernel_scales=3, kernel_size=3, deep_blocks=2)
    assert deep.receptive_radius == base.receptive_radius + 2 * 2 * 16  # two blocks of two 3x3 convs at 1/16
    with pytest.raises(ValueError, match="deep_blocks must be an integer >= 0, got -1"):
        create_model("unet_kpcn", deep_blocks=-1)


def test_band_gain_scales_the_high_band_of_each_blended_level():
    """``combine_levels`` with gains: β = 1 is the blend without them; β = 0 at the finest level leaves only the
    blend of its low band with the coarse result (so the output is smooth at the 2x2 scale: it equals
    ``U(D(o))``'s neighbourhood average there); a constant stays constant for any gains; float64 gradcheck."""
    from kpcn.models.kernel_heads import blend_weights, combine_levels
    from kpcn.models.layers import pool2, upsample2

    g = torch.Generator().manual_seed(3)
    f = [torch.rand(1, 3, 16 >> lv, 16 >> lv, generator=g, dtype=torch.float64) for lv in range(3)]
    alphas = [torch.rand(1, 1, 16 >> lv, 16 >> lv, generator=g, dtype=torch.float64) for lv in range(2)] + [None]
    ones = [torch.ones_like(a) for a in alphas[:2]] + [None]
    torch.testing.assert_close(combine_levels(f, alphas, ones), combine_levels(f, alphas), rtol=0, atol=1e-12)
    zero0 = [torch.zeros_like(alphas[0]), ones[1], None]
    out = combine_levels(f, alphas, zero0)
    coarse = combine_levels(f[1:], alphas[1:])
    expect = (1 - alphas[0]) * upsample2(pool2(f[0])) + alphas[0] * upsample2(coarse)
    torch.testing.assert_close(out, expect, rtol=0, atol=1e-12)
    assert (out - combine_levels(f, alphas)).abs().max() > 1e-3
    const = [torch.full_like(x, 0.7) for x in f]
    gains = [2 * torch.rand(a.shape, generator=g, dtype=torch.float64) for a in alphas[:2]] + [None]
    torch.testing.assert_close(combine_levels(const, alphas, gains), const[0], rtol=0, atol=1e-12)
    a, b = blend_weights(torch.zeros(1, 2, 4, 4))
    assert torch.equal(a, torch.full_like(a, 0.5)) and torch.equal(b, torch.ones_like(b))
    assert blend_weights(torch.zeros(1, 1, 4, 4))[1] is None and blend_weights(torch.zeros(1, 0, 4, 4)) == (None, None)
    ins = [x.clone().requires_grad_(True) for x in f + gains[:2]]
    assert torch.autograd.gradcheck(lambda f0, f1, f2, b0, b1: combine_levels([f0, f1, f2], alphas, [b0, b1, None]),
                                    ins)
    with pytest.raises(ValueError, match="band_gain needs kernel_scales >= 2"):
        create_model("unet_kpcn", band_gain=True)


def test_pool2_radiance_is_the_log_of_the_mean_radiance():
    """``pool2_radiance`` of a log1p-encoded colour is ``log1p`` of the 2x2 mean radiance (float64), twice the 4x4
    mean's; above the mean of the logarithms wherever a block varies, equal to it on a constant; gradcheck."""
    from kpcn.models.layers import pool2, pool2_radiance

    g = torch.Generator().manual_seed(5)
    x = torch.log1p(torch.rand(2, 3, 8, 12, generator=g, dtype=torch.float64) * 20)
    torch.testing.assert_close(pool2_radiance(x), torch.log1p(F.avg_pool2d(torch.expm1(x), 2)), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(pool2_radiance(pool2_radiance(x)), torch.log1p(F.avg_pool2d(torch.expm1(x), 4)),
                               rtol=1e-12, atol=1e-12)
    assert (pool2_radiance(x) > pool2(x) + 1e-6).all()  # every random block varies: Jensen's gap
    const = torch.full((1, 3, 4, 4), 2.5, dtype=torch.float64)
    torch.testing.assert_close(pool2_radiance(const), const[..., :2, :2], rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(pool2_radiance, [x[:1, :1, :4, :4].clone().requires_grad_(True)])


def test_radiance_pool_brightens_only_the_specular_coarse_levels(render):
    """``radiance_pool`` on a real 4-spp render of a glossy scene, the same weights with and without it: the diffuse
    branch is the same, the specular output is at least as bright at every pixel (its coarse levels filter brighter
    pooled colours with the same kernels, and the blend weights are non-negative) and brighter somewhere, in the
    whole-frame call and in row bands alike; a spec without a log-encoded branch is refused."""
    from kpcn import inference
    from kpcn.features import frame_to_tensors

    frame = render("test:glossy", spp=4, seed=1, resolution=(48, 48))
    kw = dict(widths=[8, 8, 12], stem="half", kernel_scales=3, band_gain=True, out_init_gain=5.0)
    torch.manual_seed(0)
    rad = create_model("unet_kpcn", radiance_pool=True, **kw).eval()
    log = create_model("unet_kpcn", **kw).eval()
    log.load_state_dict(rad.state_dict())
    assert rad.specular.cfg.radiance_pool and not rad.diffuse.cfg.radiance_pool
    spec = rad.input_spec
    inputs = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    with torch.no_grad():
        a, b = rad.run_branches(inputs)[0], log.run_branches(inputs)[0]
    assert torch.equal(a["diffuse"], b["diffuse"])
    assert (a["specular"] >= b["specular"] - 1e-6).all() and (a["specular"] - b["specular"]).max() > 1e-3
    rows = [inference.denoise(frame, m, tile=0, device="cpu", skip=False, precision="float32") for m in (rad, log)]
    assert (rows[0] >= rows[1] - 1e-5).all() and (rows[0] - rows[1]).max() > 1e-3
    with pytest.raises(ValueError, match="radiance_pool needs"):
        create_model("unet_kpcn", input_spec="color_albedo_normal", kernel_scales=2, radiance_pool=True)
    with pytest.raises(ValueError, match="radiance_pool needs"):
        create_model("unet_kpcn", radiance_pool=True)


def test_radiance_mixed_lies_between_the_log_and_the_radiance_filter():
    """``radiance_mixed`` (float64): at γ = 0 the kernel applied to the logarithms, at γ = 1 ``log1p`` of the kernel
    applied to the radiance; in between, at least the first (Jensen's gap, softmax kernels) and at most the second at
    every pixel, strictly above where the taps differ; a constant and a zero stay as they are; gradcheck in both the
    colour and γ."""
    from kpcn.models.kernel_heads import radiance_mixed
    from kpcn.ops.kernel_apply import kernel_apply

    def apply(x, w):
        return kernel_apply(x, w, 3, "replicate")

    g = torch.Generator().manual_seed(7)
    c = torch.log1p(torch.rand(2, 3, 6, 7, generator=g, dtype=torch.float64) * 30)
    w = torch.softmax(torch.randn(2, 9, 6, 7, generator=g, dtype=torch.float64), dim=1)
    low, high = apply(c, w), torch.log1p(apply(torch.expm1(c), w))
    torch.testing.assert_close(radiance_mixed(apply, c, w, torch.zeros(2, 1, 6, 7, dtype=torch.float64)), low)
    torch.testing.assert_close(radiance_mixed(apply, c, w, torch.ones(2, 1, 6, 7, dtype=torch.float64)), high)
    gamma = torch.rand(2, 1, 6, 7, generator=g, dtype=torch.float64) * 0.9 + 0.05
    mixed = radiance_mixed(apply, c, w, gamma)
    assert (mixed > low + 1e-9).all() and (mixed < high - 1e-9).all()
    for value in (0.0, 2.5):
        const = torch.full((1, 3, 6, 7), value, dtype=torch.float64)
        out = radiance_mixed(apply, const, w[:1], gamma[:1])
        torch.testing.assert_close(out, const, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(lambda x, t: radiance_mixed(apply, x, w[:1, :, :4, :4], t),
                                    [c[:1, :, :4, :4].clone().requires_grad_(True),
                                     gamma[:1, :, :4, :4].clone().requires_grad_(True)])


def test_radiance_mix_moves_only_the_specular_between_its_filters(render):
    """``radiance_mix`` on a real 4-spp glossy render, the same kernels with the mixing logits' weights zeroed: with
    every γ = 0 the model is the one without the option (diffuse and specular), with every γ = 1 the diffuse is the
    same and the specular output brighter on average, whole frame and row bands alike (the row path agrees with the
    whole-frame one); an input spec without a log-encoded branch is refused."""
    from kpcn import inference
    from kpcn.features import frame_to_tensors

    frame = render("test:glossy", spp=4, seed=1, resolution=(48, 48))
    kw = dict(widths=[8, 8, 12], stem="half", kernel_scales=3, band_gain=True, radiance_pool=True, out_init_gain=5.0)
    torch.manual_seed(0)
    base = create_model("unet_kpcn", **kw).eval()
    mix = create_model("unet_kpcn", radiance_mix=True, **kw).eval()
    assert mix.specular.mix and not mix.diffuse.mix
    state = mix.state_dict()
    for k, v in base.state_dict().items():  # the file's rows first, the mixing logits' rows zeroed
        state[k] = v if v.shape == state[k].shape else torch.cat([v, torch.zeros_like(state[k][v.shape[0]:])])
    spec = mix.input_spec
    inputs = spec.build(frame_to_tensors(spec.select(frame), spec.layers))

    def outputs(bias):
        for name in ["head"] + [f"heads.{i}" for i in range(2)]:
            state[f"specular.{name}.bias"][-1] = bias
        mix.load_state_dict(state)
        with torch.no_grad():
            return mix.run_branches(inputs)[0], inference.denoise(frame, mix, tile=0, device="cpu", skip=False,
                                                                  precision="float32")

    with torch.no_grad():
        ref = base.run_branches(inputs)[0]
    ref_rows = inference.denoise(frame, base, tile=0, device="cpu", skip=False, precision="float32")
    shut, shut_rows = outputs(-60.0)
    for b in ("diffuse", "specular"):
        torch.testing.assert_close(shut[b], ref[b], rtol=1e-5, atol=1e-6)
    assert abs(shut_rows - ref_rows).max() < 1e-4
    wide, wide_rows = outputs(60.0)
    assert torch.equal(wide["diffuse"], ref["diffuse"])
    assert float(torch.expm1(wide["specular"]).mean()) > float(torch.expm1(ref["specular"]).mean()) * 1.01
    assert wide_rows.mean() > ref_rows.mean() + 1e-4
    whole = inference.denoise(frame, mix, tile=0, device="cpu", skip=False, precision="float32", rows=False)
    assert abs(whole - wide_rows).max() < 1e-4 * max(float(whole.max()), 1.0)
    with pytest.raises(ValueError, match="radiance_mix needs"):
        create_model("unet_kpcn", input_spec="color_albedo_normal", kernel_scales=2, radiance_mix=True)


def test_the_default_uses_every_kernel_level(render):
    """The shipped default's blending weights on a real 4-spp glossy render: every kernel level that blends in a
    coarser one does so somewhere (max α > 1e-3), in both branches. The check can fail: in ``unet_kpcn:wide64b``
    (and every default before it) the specular branch's level-1 weight is below 1e-6 at every pixel (logits -25 to
    -60), so its 1/4 and 1/8 kernel levels were never used."""
    from kpcn.features import frame_to_tensors
    from kpcn.inference import load_model
    from kpcn.inference.frames import with_normal

    frame = render("test:glossy", spp=4, seed=1, resolution=(48, 48))

    def alphas(model):
        spec = model.input_spec
        x = with_normal(model, spec.build(frame_to_tensors(spec.select(frame), spec.layers)), frame, None, "cpu")
        with torch.no_grad():
            return {b: [a for a in getattr(model, b).kernels(x[b], None, x.get("normal")).alphas if a is not None]
                    for b in model.branches}

    for branch, levels in alphas(load_model(None, device="cpu")).items():
        assert levels and all(float(a.max()) > 1e-3 for a in levels), \
            f"{branch}: max blending weight per level {[float(a.max()) for a in levels]}"
    assert float(alphas(load_model("unet_kpcn:wide64b", device="cpu"))["specular"][1].max()) < 1e-6


def test_albedo_clamp_keeps_the_albedo_within_its_noise(render):
    """``albedo_clamp: c`` on a real 4-spp render of a textured scene, the gates open (a sharp random init): every pixel's
    remodulation albedo lies within ``c`` standard deviations of its noisy mean, so a pixel whose albedo has no noise
    keeps it; without the clamp the same model moves some pixels further (the clamp is what holds it). The clamped
    combination passes a float64 gradcheck."""
    from kpcn.features import frame_to_tensors
    from kpcn.models.kernel_heads import gated_albedo

    frame = render("test:textured", spp=4, seed=1, resolution=(40, 40))
    kw = dict(widths=[8, 8, 12], stem="half", kernel_scales=3, band_gain=True, albedo_kernel=3, out_init_gain=5.0,
              albedo_gate_gain=8.0)
    torch.manual_seed(0)
    clamped = create_model("unet_kpcn", albedo_clamp=1.0, **kw).eval()
    free = create_model("unet_kpcn", **kw).eval()
    free.load_state_dict(clamped.state_dict())
    spec = clamped.input_spec
    inputs = spec.build(frame_to_tensors(spec.select(frame), spec.layers))
    sigma = inputs["diffuse"][:, 25:26].clamp_min(0).sqrt()  # the features' albedo variance (of the pixel mean)
    assert float((sigma == 0).float().mean()) > 0.05 and float(sigma.max()) > 0.05  # flat texels and noisy edges
    with torch.no_grad():
        a, moved, unbounded = inputs["albedo"], clamped(inputs)["albedo"], free(inputs)["albedo"]
    assert ((moved - a).abs() <= sigma + 1e-6).all()
    assert ((unbounded - a).abs() > sigma + 1e-3).any()
    assert torch.equal(moved[(sigma == 0).expand_as(a)], a[(sigma == 0).expand_as(a)])
    g = torch.Generator().manual_seed(1)
    args = [torch.rand(1, 3, 5, 6, generator=g, dtype=torch.float64) + 0.5,
            torch.rand(1, 3, 5, 6, generator=g, dtype=torch.float64) + 0.5,
            torch.rand(1, 1, 5, 6, generator=g, dtype=torch.float64) * 2 - 1]
    bound = torch.rand(1, 1, 5, 6, generator=g, dtype=torch.float64) * 0.4 + 0.05
    assert torch.autograd.gradcheck(lambda x, f, gt: gated_albedo(x, f, gt, bound),
                                    [t.requires_grad_() for t in args])
