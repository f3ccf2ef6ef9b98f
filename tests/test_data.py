"""Patch sampling and datasets over a rendered folder."""
import numpy as np
import pytest
import torch

from kpcn.data import FrameDataset, PatchDataset, importance_map, patch_count, read_manifest, sample_patches


def test_patch_count_scales_with_area():
    assert patch_count(720, 1280) == 400
    assert patch_count(360, 640) == 100
    assert patch_count(8, 8) == 1


def test_importance_sampling_prefers_high_variance_regions(render):
    f = render("test:glass", spp=4, resolution=(96, 96))
    imp = importance_map(f["colorVariance"], f["normalVariance"])
    assert imp.min() >= 0 and imp.max() <= 1
    size, n = 16, 400
    rng = np.random.default_rng(0)
    cv = f["colorVariance"].mean(-1)

    def mean_var(corners):
        return np.mean([cv[y:y + size, x:x + size].mean() for y, x in corners])

    uni = sample_patches(96, 96, n, size, None, rng)
    imp_c = sample_patches(96, 96, n, size, imp, rng)
    assert ((imp_c >= 0) & (imp_c <= 96 - size)).all()
    assert mean_var(imp_c) > 1.3 * mean_var(uni)


def test_patch_dataset_over_rendered_folder(tiny_dataset):
    pairs = read_manifest(tiny_dataset)
    assert len(pairs) == 6 and {p.spp for p in pairs} == {4, 8}
    ds = PatchDataset(read_manifest(tiny_dataset, spp=[8]), patch_size=32, patches_per_frame=5, seed=1)
    assert len(ds) == 15
    item = ds[7]
    assert item["diffuse"].shape == (27, 32, 32) and item["specular"].shape == (27, 32, 32)
    for k in ("albedo", "y_diffuse", "y_specular", "y_color", "noisy_color"):
        assert item[k].shape == (3, 32, 32)
    first = ds.index.copy()
    ds.resample(1)
    assert not np.array_equal(first, ds.index)
    ds.resample(0)
    np.testing.assert_array_equal(first, ds.index)  # reproducible per epoch
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=4)))
    assert batch["diffuse"].shape == (4, 27, 32, 32)


def test_frame_dataset(tiny_dataset):
    ds = FrameDataset(read_manifest(tiny_dataset, spp=[4]))
    item = ds[0]
    assert item["diffuse"].shape == (27, 48, 48)
    assert torch.isfinite(item["y_color"]).all()


def test_missing_manifest_says_how_to_make_one(tmp_path):
    with pytest.raises(FileNotFoundError, match="kpcn.render dataset"):
        read_manifest(tmp_path)


def test_spp_mix_takes_each_pixel_from_one_of_two_inputs_of_the_scene(tiny_dataset):
    """With spp_mix = 1 every patch is made of its own input and an input of the same scene at the other spp (a
    frame whose spp varies per pixel); a converged pair is never mixed; the same seed gives the same patches."""
    from kpcn.data import CONVERGED_SPP, FramePair

    pairs = read_manifest(tiny_dataset)
    pairs.append(FramePair(pairs[0].scene, CONVERGED_SPP, pairs[0].reference_path, pairs[0].reference_path))
    kw = dict(patch_size=32, patches_per_frame=4, seed=3, sampling="uniform", label_spp=True)
    plain, mixed = PatchDataset(pairs, **kw), PatchDataset(pairs, spp_mix=1.0, **kw)
    for i, p in enumerate(pairs):
        partners = [pairs[j] for j in mixed.partners[i]]
        if p.spp == CONVERGED_SPP:
            assert partners == []
        else:
            assert len(partners) == 1 and partners[0].reference_path == p.reference_path
            assert partners[0].spp != p.spp
    assert np.array_equal(plain.index, mixed.index)
    both = 0
    for idx, (f, _, _) in enumerate(mixed.index):
        own, got = plain[idx], mixed[idx]
        assert int(got["spp"]) == pairs[f].spp  # the label stays the first input's
        if pairs[f].spp == CONVERGED_SPP:
            assert all(torch.equal(got[k], own[k]) for k in own)
            continue
        theirs = plain._crop(mixed.partners[f][0], *mixed.index[idx][1:])  # the partner's pixels at the same place
        from_own = (got["noisy_color"] == own["noisy_color"]).all(0)
        from_other = (got["noisy_color"] == theirs["noisy_color"]).all(0)
        assert bool((from_own | from_other).all())
        both += bool((from_own & ~from_other).any() and (from_other & ~from_own).any())
        assert torch.equal(got["y_color"], own["y_color"])  # the same reference
    assert both >= len(mixed) // 2
    again = PatchDataset(pairs, spp_mix=1.0, **kw)
    assert all(torch.equal(again[5][k], mixed[5][k]) for k in mixed[5])
    with pytest.raises(ValueError, match="spp_mix"):
        PatchDataset(pairs, spp_mix=1.5, **kw)
