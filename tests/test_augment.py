"""Augmentation of built features equals building the features of the transformed frame.

The frame is a real (tiny) Mitsuba render; the transformed frame is made from
its raw layers (mirrored, transposed, RGB permuted), and its features are
built by the input spec as training would build them.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from kpcn.augment import PERMUTATIONS, Augmentation, augment_batch, augment_patch, undo_flips
from kpcn.features import frame_to_tensors
from kpcn.inputs import get_input_spec

RES = (40, 40)
NOT_COLOURS = ("normal", "normalVariance", "depth", "depthVariance")


@pytest.fixture(scope="module")
def frame(render):
    return render("test:textured", spp=4, seed=2, resolution=RES)


def _raw(frame, layers, aug: Augmentation) -> dict[str, torch.Tensor]:
    """The frame's layers ``(1, C, H, W)`` with the transform applied to the raw pixels."""
    out = {}
    for n, t in frame_to_tensors(frame, layers).items():
        if aug.transpose:
            t = t.transpose(-1, -2)
        if aug.flip_x:
            t = t.flip(-1)
        if aug.flip_y:
            t = t.flip(-2)
        if aug.perm and n not in NOT_COLOURS and t.shape[1] == 3:
            t = t[:, list(PERMUTATIONS[aug.perm])]
        out[n] = t.contiguous()
    return out


CASES = [Augmentation(transpose=True), Augmentation(flip_x=True), Augmentation(flip_y=True),
         Augmentation(perm=3), Augmentation(True, True, True, 5)]


@pytest.mark.parametrize("spec_name", ["kpcn_split", "split_novar", "color_albedo_normal"])
@pytest.mark.parametrize("aug", CASES, ids=lambda a: f"fx{a.flip_x:d}fy{a.flip_y:d}t{a.transpose:d}p{a.perm}")
def test_augmented_features_are_the_features_of_the_transformed_frame(frame, spec_name, aug):
    spec = get_input_spec(spec_name)
    ident = Augmentation()
    built = spec.build(_raw(frame, spec.layers, ident))
    want = spec.build(_raw(frame, spec.layers, aug))
    for key in (*spec.branches, "albedo"):
        got = augment_patch(built[key][0], aug, spec if key in spec.branches else None)
        expect = want[key][0]
        # a mirrored patch cannot know the difference across its last column / row: compare inside it
        h = slice(0, -1) if aug.flip_y else slice(None)
        w = slice(0, -1) if aug.flip_x else slice(None)
        torch.testing.assert_close(got[:, h, w], expect[:, h, w], rtol=1e-5, atol=1e-5)
        assert not torch.equal(got, built[key][0]), f"{key}: the transform changed nothing"


def test_a_wrong_layout_is_caught(frame):
    """Negative control: permuting without the spec's layout (RGB of the first triplet only) does not match."""
    spec = get_input_spec("kpcn_split")
    aug = Augmentation(perm=3)
    built = spec.build(_raw(frame, spec.layers, Augmentation()))["diffuse"][0]
    want = spec.build(_raw(frame, spec.layers, aug))["diffuse"][0]
    assert not torch.allclose(augment_patch(built, aug, _first_triplet_only(spec)), want, atol=1e-5)


def _first_triplet_only(spec):
    from dataclasses import replace

    return replace(spec, rgb_starts=(0,))


def test_batch_augmentation_is_per_patch_and_reproducible(frame):
    spec = get_input_spec("kpcn_split")
    built = spec.build(_raw(frame, spec.layers, Augmentation()))
    batch = {k: v.expand(8, -1, -1, -1).clone() for k, v in built.items()}
    a = augment_batch(batch, spec, torch.Generator().manual_seed(7))
    b = augment_batch(batch, spec, torch.Generator().manual_seed(7))
    for k in a:
        assert torch.equal(a[k], b[k])
    distinct = {tuple(np.round(a["albedo"][i].flatten()[:64].numpy(), 6)) for i in range(8)}
    assert len(distinct) > 1, "every patch of the batch got the same transform"
    with pytest.raises(ValueError, match="only branches"):
        augment_batch({"depth": torch.zeros(2, 1, 4, 4)}, spec, torch.Generator())


@pytest.mark.parametrize("t,fx,fy", [(t, fx, fy) for t in (0, 1) for fx in (0, 1) for fy in (0, 1)])
def test_undo_flips_returns_an_rgb_patch_to_where_it_was(t, fx, fy):
    """Every flip and transpose undone (a non-square patch, so a wrong order or a missed transpose shows)."""
    x = torch.arange(3 * 4 * 6, dtype=torch.float32).view(1, 3, 4, 6)
    aug = Augmentation(flip_x=bool(fx), flip_y=bool(fy), transpose=bool(t))
    y = augment_patch(x, aug)
    assert torch.equal(undo_flips(y, aug), x)


# ------------------------------------------------------------------------------------------------ exposure
def _split_batch(frame, ref, spec):
    x = spec.build(frame_to_tensors(frame, spec.layers), None, spec.branches)
    x.update(spec.targets(frame_to_tensors(ref, spec.target_layers), x))
    x["noisy_color"] = frame_to_tensors(frame, ("color",))["color"]
    return x


@pytest.mark.parametrize("s", [0.01, 7.0])
@pytest.mark.parametrize("spec_name", ["kpcn_split", "split_novar"])
def test_a_batch_at_another_exposure_is_the_batch_of_the_rescaled_frame(render, s, spec_name):
    """Features, targets and colours of a real render whose radiance layers are × s, against the same entries
    rescaled by batch_at_exposure; exact but for the specular delta-method variance (an RGB mean, rescaled as if
    each channel's variance were proportional to its radiance squared)."""
    from kpcn.augment import batch_at_exposure
    from kpcn.exposure import scale_layers
    from kpcn.io import Frame

    spec = get_input_spec(spec_name)
    noisy, ref = render("test:glossy", spp=4, resolution=RES), render("test:glossy", spp=64, seed=2, role=1,
                                                                        resolution=RES)
    want = _split_batch(Frame(scale_layers(noisy.layers, s), noisy.meta), Frame(scale_layers(ref.layers, s)), spec)
    got = batch_at_exposure(_split_batch(noisy, ref, spec), spec, torch.tensor([s]))
    assert set(got) == set(want)
    for k, w in want.items():
        g = got[k]
        if k == "specular" and 3 in spec.variance_channels:
            var = w[:, 3]
            assert (g[:, 3] - var).abs().max() <= 0.1 * var.max() and var.max() > 0
            g, w = torch.cat([g[:, :3], g[:, 4:]], 1), torch.cat([w[:, :3], w[:, 4:]], 1)
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-5 * float(w.abs().max()), msg=k)


def test_exposure_batch_moves_chosen_patches_into_the_range(render):
    from kpcn.augment import exposure_batch
    from kpcn.exposure import frame_key

    spec = get_input_spec("kpcn_split")
    frames = [render(sc, spp=4, resolution=RES) for sc in ("test:glossy", "test:textured", "random:5")]
    ref = render("test:glossy", spp=64, seed=2, role=1, resolution=RES)
    parts = [_split_batch(f, ref, spec) for f in frames]
    batch = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    batch["noisy_color"][0].mul_(1e-5)  # one patch far below the range
    lo, hi = 0.2, 0.3  # narrower than the three patches' own keys
    out = exposure_batch(batch, spec, torch.Generator().manual_seed(0), 1.0, (lo, hi))
    keys = [frame_key(c.permute(1, 2, 0)) for c in out["noisy_color"]]
    assert all(lo * 0.999 <= k <= hi * 1.001 for k in keys), keys
    again = exposure_batch(batch, spec, torch.Generator().manual_seed(0), 1.0, (lo, hi))
    torch.testing.assert_close(again["diffuse"], out["diffuse"])  # reproducible from the generator
    kept = exposure_batch(batch, spec, torch.Generator().manual_seed(0), 0.0, (lo, hi))
    assert all(kept[k] is batch[k] for k in batch)
    with pytest.raises(ValueError, match="split input spec"):
        exposure_batch({"color": batch["noisy_color"], "noisy_color": batch["noisy_color"]}, "color_albedo_normal",
                       torch.Generator().manual_seed(0), 1.0, (lo, hi))


# ------------------------------------------------------------------------------------------------ varying spp
def test_region_mask_is_reproducible_and_splits_the_patch():
    from kpcn.sample_maps import region_mask

    fractions = []
    for seed in range(20):
        m = region_mask((64, 48), np.random.default_rng(seed))
        assert m.shape == (64, 48) and m.dtype == bool
        assert np.array_equal(m, region_mask((64, 48), np.random.default_rng(seed)))
        fractions.append(float(m.mean()))
    assert 0.15 <= min(fractions) and max(fractions) <= 0.85
    assert max(fractions) - min(fractions) > 0.2  # the share of the patch varies from mask to mask


@pytest.mark.parametrize("spec_name", ["kpcn_split", "split_novar"])
def test_a_mixed_patch_is_the_patch_of_the_mixed_render(render, spec_name):
    """Two real renders of one view at 4 and 64 spp, taken per pixel inside / outside a region mask: the mixed
    patch equals the features of that composite render everywhere but the gradients of normal, albedo and depth
    on the seam (they keep one render's) and the depth channels (each render's own depth scale, within 2 %); the
    colour gradients across the seam are the composite's."""
    from kpcn.augment import mix_patches
    from kpcn.features import FEATURE_VAR
    from kpcn.io import Frame
    from kpcn.sample_maps import region_mask

    spec = get_input_spec(spec_name)
    lo, hi = render("test:glossy", spp=4, resolution=RES), render("test:glossy", spp=64, seed=3, resolution=RES)
    ref = render("test:glossy", spp=64, seed=2, role=1, resolution=RES)
    h, w = lo.shape
    m = region_mask((h, w), np.random.default_rng(5))[..., None]
    mask = torch.from_numpy(m[..., 0])[None]
    mixed = Frame({k: np.where(m, lo[k], hi[k]) for k in lo.layers}, dict(lo.meta))
    want = {k: v[0] for k, v in _split_batch(mixed, ref, spec).items()}
    a = {k: v[0] for k, v in _split_batch(lo, ref, spec).items()}
    b = {k: v[0] for k, v in _split_batch(hi, ref, spec).items()}
    got = mix_patches(a, b, mask, spec)
    seam = torch.zeros(h, w, dtype=torch.bool)
    seam[:, :-1] |= mask[0, :, 1:] != mask[0, :, :-1]
    seam[:-1, :] |= mask[0, 1:, :] != mask[0, :-1, :]
    assert 0 < int(seam.sum()) < h * w // 2
    gbuf = [c for blk in (spec.grad_x, spec.grad_y) for c in range(blk[0] + 3, blk[1])]
    # depth is normalised by each frame's largest depth, which differs between renders by its anti-aliasing
    depth = [spec.grad_x[1] - 1, spec.grad_y[1] - 1]
    depth += [c for c in (FEATURE_VAR.start + 2,) if c in spec.variance_channels]
    for k, wv in want.items():
        g = got[k]
        if k in spec.branches:
            keep = torch.ones_like(g, dtype=torch.bool)
            keep[gbuf] = ~seam
            for c in depth:
                torch.testing.assert_close(g[c][~seam], wv[c][~seam], rtol=0, atol=0.02 * float(wv[c].abs().max()))
                keep[c] = False
            assert not torch.equal(g, a[k]) and not torch.equal(g, b[k])
            g, wv = g[keep], wv[keep]
            # the colour gradients across the seam are new values, not either render's
            c = spec.grad_x[0]
            assert torch.allclose(got[k][c:c + 3][:, seam], want[k][c:c + 3][:, seam], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(g, wv, rtol=1e-5, atol=1e-6, msg=k)


def test_a_spec_with_a_whole_frame_value_is_not_mixed():
    from kpcn.augment import check_mix_spec

    with pytest.raises(ValueError, match="whole-frame"):
        check_mix_spec("color_albedo_normal_noise")
    assert check_mix_spec("kpcn_split").name == "kpcn_split"
