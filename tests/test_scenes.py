"""Procedural and named scenes: load, render tiny images with Mitsuba's `path`."""
from __future__ import annotations

import numpy as np
import pytest

from kpcn import scenes

RES = (16, 16)
SPP = 4
SEEDS = list(range(20))


@pytest.fixture(scope="module")
def mi():
    scenes._mi()  # selects llvm_ad_rgb if no variant is set
    import mitsuba

    return mitsuba


def _render(mi, scene_dict, spp=SPP, seed=0, integrator=None):
    d = scenes.copy_scene_dict(scene_dict)
    d["integrator"] = integrator or {"type": "path", "max_depth": 8}
    return np.array(mi.render(mi.load_dict(d), spp=spp, seed=seed))


@pytest.fixture(scope="module")
def random_images(mi):
    return {s: _render(mi, scenes.random_scene(s, RES)) for s in SEEDS}


def _flatten(d, prefix=""):
    """Comparable view of a scene dict: Bitmaps and transforms become arrays."""
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        elif isinstance(v, (bool, int, float, str, list, tuple)):
            out[key] = v
        elif hasattr(v, "matrix"):
            out[key] = np.array(v.matrix).round(12).tolist()
        else:
            out[key] = np.array(v).tolist()
    return out


def test_list_and_unknown_name():
    names = scenes.list_test_scenes()
    for n in ("diffuse_box", "glossy", "glass", "envmap_open", "no_hit", "textured"):
        assert n in names
    with pytest.raises(ValueError, match="diffuse_box"):
        scenes.test_scene("no_such_scene")


@pytest.mark.parametrize("name", scenes.list_test_scenes())
def test_named_scenes_render(mi, name):
    img = _render(mi, scenes.test_scene(name, RES))
    assert img.shape == (RES[1], RES[0], 3)
    assert np.all(np.isfinite(img)) and img.min() >= 0
    assert img.mean() > 1e-3


def test_random_scenes_render(random_images):
    means = []
    for s, img in random_images.items():
        assert img.shape == (RES[1], RES[0], 3), s
        assert np.all(np.isfinite(img)), s
        assert img.min() >= 0, s
        means.append(float(img.mean()))
    ok = sum(1e-3 <= m <= 50 for m in means)
    assert ok >= 18, f"mean radiances {np.round(means, 4)}"


def test_same_seed_same_scene(mi, random_images):
    a, b = scenes.random_scene(5, RES), scenes.random_scene(5, RES)
    assert _flatten(a) == _flatten(b)
    img = _render(mi, b)
    assert np.array_equal(img, random_images[5])
    # a different render seed gives different noise on the same scene
    assert not np.array_equal(_render(mi, b, seed=1), img)


def test_different_seeds_differ(random_images):
    flats = [_flatten(scenes.random_scene(s, (8, 8))) for s in range(6)]
    for i in range(len(flats)):
        for j in range(i + 1, len(flats)):
            assert flats[i] != flats[j]
    imgs = list(random_images.values())
    assert all(not np.array_equal(imgs[0], x) for x in imgs[1:])


def test_coverage_over_seeds():
    mats, lights, layouts, shapes, btypes = set(), set(), set(), set(), set()
    for s in range(40):
        _, meta = scenes.random_scene_with_meta(s, (8, 8))
        assert 3 <= len([o for o in meta["objects"] if o.get("placement") != "clutter"]) <= 10
        mats |= set(meta["material_classes"])
        lights |= set(meta["light_classes"])
        layouts.add(meta["layout"])
        shapes |= {o["shape"] for o in meta["objects"]}
        btypes |= {o["type"] for o in meta["objects"]}
    assert set(scenes.MATERIAL_CLASSES) <= mats
    assert {"area", "environment"} <= lights
    assert {"open", "closed"} <= layouts
    assert {"sphere", "cube", "cylinder", "disk", "rectangle"} <= shapes
    assert {"roughconductor", "plastic", "roughplastic", "dielectric"} <= btypes


def test_meta_is_plain_and_describe():
    import json

    _, meta = scenes.random_scene_with_meta(3, (8, 8))
    json.dumps(meta)  # serialisable for manifests
    text = scenes.describe_scene(3)
    assert meta["layout"] in text and "seed 3" in text


def test_no_hit_sees_nothing(mi):
    d = scenes.test_scene("no_hit", RES)
    depth = _render(mi, d, integrator={"type": "depth"})
    assert np.all(depth == 0)
    img = _render(mi, d)
    assert img.min() > 0  # the constant environment is seen everywhere


def test_diffuse_box_is_diffuse_only(mi):
    d = scenes.test_scene("diffuse_box", RES)
    sc = mi.load_dict(d)
    shapes = sc.shapes()
    assert len(shapes) > 0
    for sh in shapes:
        flags = sh.bsdf().flags()
        assert mi.has_flag(flags, mi.BSDFFlags.Diffuse)
        assert not mi.has_flag(flags, mi.BSDFFlags.Glossy)
        assert not mi.has_flag(flags, mi.BSDFFlags.Delta)
    emitters = sc.emitters()
    assert len(emitters) == 1 and mi.has_flag(emitters[0].flags(), mi.EmitterFlags.Surface)


def test_non_square_resolution(mi):
    img = _render(mi, scenes.random_scene(11, (24, 12)), spp=1)
    assert img.shape == (12, 24, 3)
