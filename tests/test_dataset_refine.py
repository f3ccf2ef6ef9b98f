"""Data set references refined to a noise floor (``render_dataset(..., ref_floor_target=...)``): tiny real
renders (8x8), as in tests/test_dataset_safety.py."""
import json

import numpy as np
import pytest

from kpcn.io import read_exr
from kpcn.render import DatasetError, ensure_dataset, merge_frames, render_dataset, render_frame
from kpcn.render.record import read_record
from kpcn.render.refine import reference_floor, refined_spp

from test_dataset_safety import SMALL, counting_render, mtimes


def test_a_noisy_reference_is_refined_and_kept(mi, tmp_path, monkeypatch):
    """A reference whose own noise adds more relMSE than the target keeps its samples and gets the passes that
    follow, as many as refined_spp predicts (up to ref_spp_max); inputs are untouched, the record and manifest say
    its spp and the target, a second run changes nothing, and ensure_dataset compares the target."""
    root = tmp_path / "data"
    render_dataset(root, 1, **SMALL)
    inp, ref = root / "random_0" / "input_2spp.exr", root / "random_0" / "reference.exr"
    old, before = read_exr(ref), mtimes([inp])
    floor = reference_floor(old)
    assert floor > 0
    target = floor / 3  # 4 spp: the floor predicted at 8 is floor / 2 > target, at 16 floor / 4 <= target
    assert refined_spp(4, floor, target, 16) == 16
    calls = counting_render(monkeypatch)
    render_dataset(root, 1, **SMALL, ref_floor_target=target, ref_spp_max=16)
    assert calls == [] and mtimes([inp]) == before
    new = read_exr(ref)
    assert new.spp == 16 and read_record(ref)[0]["spp"] == 16
    want = merge_frames(old, render_frame("random:0", 12, 0, (8, 8), role=1, first_pass=1))
    np.testing.assert_allclose(new["color"], want["color"], rtol=1e-5, atol=1e-7)
    assert reference_floor(new) < floor
    m = json.loads((root / "manifest.json").read_text())
    assert m["complete"] is True and m["ref_spp"] == 4 and m["ref_floor_target"] == target and m["ref_spp_max"] == 16
    assert m["scenes"][0]["frames"]["random_0/reference.exr"]["spp"] == 16

    stamp = mtimes([ref, inp])
    render_dataset(root, 1, **SMALL, ref_floor_target=target, ref_spp_max=16)  # up to date: kept as it is
    assert calls == [] and mtimes([ref, inp]) == stamp
    settings = dict(n_scenes=1, spp=[2], ref_spp=4, resolution=(8, 8), first_seed=0, render_if_missing=False)
    assert ensure_dataset(root, **settings, ref_floor_target=target, ref_spp_max=16) == root
    with pytest.raises(DatasetError, match=r"ref_floor_target [0-9.e-]+ \(requested none\)"):
        ensure_dataset(root, **settings)
    with pytest.raises(DatasetError, match="--ref-floor-target 0.5 --ref-spp-max 64"):
        ensure_dataset(tmp_path / "none", **settings, ref_floor_target=0.5, ref_spp_max=64)


def test_a_clean_enough_reference_is_left_alone(mi, tmp_path, monkeypatch):
    """A reference already at or below the target, or without room to double under ref_spp_max, is not touched;
    a target without room is refused before anything is rendered."""
    root = tmp_path / "data"
    render_dataset(root, 1, **SMALL)
    ref = root / "random_0" / "reference.exr"
    floor, stamp = reference_floor(read_exr(ref)), mtimes([ref])
    render_dataset(root, 1, **SMALL, ref_floor_target=floor * 2)
    render_dataset(root, 1, **SMALL, ref_floor_target=floor / 100, ref_spp_max=7)  # 8 would be above the cap
    assert mtimes([ref]) == stamp and read_exr(ref).spp == 4
    with pytest.raises(ValueError, match="ref_spp_max"):
        render_dataset(tmp_path / "other", 1, **SMALL, ref_floor_target=0.1, ref_spp_max=2)
    with pytest.raises(ValueError, match="ref_floor_target"):
        render_dataset(tmp_path / "other", 1, **SMALL, ref_floor_target=0.0)
    assert not (tmp_path / "other").exists()
