import pytest
import torch
import torch.nn.functional as F

from kpcn.ops import KernelApply, kernel_apply, kernel_apply_unfold


def _rand(b, c, h, w, k, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    image = torch.randn(b, c, h, w, generator=g, dtype=dtype)
    weights = torch.rand(b, k * k, h, w, generator=g, dtype=dtype) + 0.1
    return image, weights


@pytest.mark.parametrize("k", [3, 5])
@pytest.mark.parametrize("padding_mode", ["zeros", "replicate"])
def test_gradcheck(k, padding_mode):
    image, weights = _rand(2, 3, 6, 6, k, dtype=torch.float64)
    image.requires_grad_(True)
    weights.requires_grad_(True)
    # full Jacobian check for zero padding; the cheaper random-projection check for replicate
    fast = padding_mode == "replicate"
    assert torch.autograd.gradcheck(
        lambda x, w: kernel_apply(x, w, k, padding_mode), (image, weights), fast_mode=fast
    )


def test_gradcheck_single_input_grad():
    image, weights = _rand(1, 2, 5, 4, 3, dtype=torch.float64)
    image.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: kernel_apply(x, weights, 3), (image,))
    image.requires_grad_(False)
    weights.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda w: kernel_apply(image, w, 3), (weights,))


@pytest.mark.parametrize(
    "shape,k",
    [((2, 3, 9, 7), 1), ((2, 3, 9, 7), 3), ((1, 3, 12, 10), 5), ((2, 1, 8, 8), 9), ((1, 3, 4, 4), 7), ((1, 2, 3, 5), 11)],
)
@pytest.mark.parametrize("padding_mode", ["zeros", "replicate"])
def test_matches_unfold_reference(shape, k, padding_mode):
    b, c, h, w = shape
    image, weights = _rand(b, c, h, w, k)
    image.requires_grad_(True)
    weights.requires_grad_(True)
    out = kernel_apply(image, weights, k, padding_mode)
    ref = kernel_apply_unfold(image, weights, k, padding_mode)
    assert out.shape == (b, c, h, w)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    g = torch.randn_like(out)
    gi, gw = torch.autograd.grad(out, (image, weights), g)
    ri, rw = torch.autograd.grad(ref, (image, weights), g)
    torch.testing.assert_close(gi, ri, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gw, rw, rtol=1e-5, atol=1e-5)


def test_unfold_reference_matches_explicit_sum():
    # Pin the tap convention independently of F.unfold: t = i*k + j weights offset (i-r, j-r).
    k, r = 3, 1
    image, weights = _rand(1, 2, 5, 6, k, dtype=torch.float64)
    padded = F.pad(image, (r, r, r, r))
    expected = torch.zeros_like(image)
    for i in range(k):
        for j in range(k):
            expected += weights[:, i * k + j : i * k + j + 1] * padded[:, :, i : i + 5, j : j + 6]
    torch.testing.assert_close(kernel_apply(image, weights, k), expected)
    torch.testing.assert_close(kernel_apply_unfold(image, weights, k), expected)


def test_one_hot_centre_is_identity_and_other_tap_shifts():
    k, r = 5, 2
    image, _ = _rand(2, 3, 8, 9, k)
    w = torch.zeros(2, k * k, 8, 9)
    w[:, r * k + r] = 1.0
    assert torch.equal(kernel_apply(image, w, k), image)

    # tap (i, j) = (r + 1, r - 2): out[y, x] = image[y + 1, x - 2] (zero outside)
    w = torch.zeros(2, k * k, 8, 9)
    w[:, (r + 1) * k + (r - 2)] = 1.0
    out = kernel_apply(image, w, k)
    expected = torch.zeros_like(image)
    expected[:, :, :-1, 2:] = image[:, :, 1:, :-2]
    assert torch.equal(out, expected)


@pytest.mark.parametrize("padding_mode", ["zeros", "replicate"])
def test_softmax_weights_stay_in_convex_hull(padding_mode):
    k, r = 5, 2
    g = torch.Generator().manual_seed(3)
    image = torch.randn(2, 3, 10, 11, generator=g) * 5
    weights = torch.softmax(torch.randn(2, k * k, 10, 11, generator=g) * 3, dim=1)
    out = kernel_apply(image, weights, k, padding_mode)
    if padding_mode == "zeros":
        padded = F.pad(image, (r, r, r, r))
    else:
        padded = F.pad(image, (r, r, r, r), mode="replicate")
    cols = F.unfold(padded, k).view(2, 3, k * k, 10, 11)
    lo, hi = cols.min(dim=2).values, cols.max(dim=2).values
    assert (out >= lo - 1e-5).all() and (out <= hi + 1e-5).all()


def test_replicate_keeps_constant_image_constant():
    k = 7
    image = torch.full((1, 3, 5, 6), 2.5)
    weights = torch.softmax(torch.randn(1, k * k, 5, 6), dim=1)
    torch.testing.assert_close(kernel_apply(image, weights, k, "replicate"), image)


def test_non_contiguous_and_channels_last_inputs():
    k = 3
    image, weights = _rand(2, 3, 7, 8, k)
    ref = kernel_apply_unfold(image, weights, k)
    out = kernel_apply(
        image.to(memory_format=torch.channels_last), weights.to(memory_format=torch.channels_last), k
    )
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    # a transposed (non-contiguous) view
    out_t = kernel_apply(image.transpose(2, 3).contiguous().transpose(2, 3), weights, k)
    torch.testing.assert_close(out_t, ref, rtol=1e-5, atol=1e-5)


def test_module_wrapper():
    k = 3
    image, weights = _rand(1, 3, 6, 6, k)
    mod = KernelApply(k, padding_mode="replicate")
    torch.testing.assert_close(mod(image, weights), kernel_apply(image, weights, k, "replicate"))
    assert "kernel_size=3" in repr(mod)
    with pytest.raises(ValueError, match="odd"):
        KernelApply(4)


def test_input_checks():
    image, weights = _rand(2, 3, 6, 6, 3)
    with pytest.raises(ValueError, match=r"k\*k = 9 channels"):
        kernel_apply(image, weights[:, :8], 3)
    with pytest.raises(ValueError, match="batch size and spatial size"):
        kernel_apply(image, weights[:1], 3)
    with pytest.raises(ValueError, match="batch size and spatial size"):
        kernel_apply(image, weights[:, :, :5], 3)
    with pytest.raises(ValueError, match="batch size and spatial size"):
        kernel_apply(image, weights[:, :, :, :5], 3)
    with pytest.raises(ValueError, match="odd"):
        kernel_apply(image, torch.rand(2, 16, 6, 6), 4)
    with pytest.raises(ValueError, match="odd"):
        kernel_apply(image, weights, 0)
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        kernel_apply(image[0], weights, 3)
    with pytest.raises(ValueError, match="dtype"):
        kernel_apply(image.double(), weights, 3)
    with pytest.raises(ValueError, match="padding_mode"):
        kernel_apply(image, weights, 3, "reflect")
    with pytest.raises(ValueError, match=r"k\*k = 9 channels"):
        kernel_apply_unfold(image, weights[:, :8], 3)
