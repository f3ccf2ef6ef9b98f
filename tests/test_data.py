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
