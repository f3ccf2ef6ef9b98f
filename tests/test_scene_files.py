"""The Mitsuba XML scene files shipped for evaluation (kpcn/scenes/files/): names, loading, tiny real renders."""
from __future__ import annotations

import numpy as np
import pytest

from kpcn import scenes

RES = (16, 16)


def test_names_paths_and_unknown_name():
    names = scenes.list_scene_files()
    assert len(names) >= 3
    for n in names:
        p = scenes.scene_file(n)
        assert p.is_file() and p.suffix == ".xml" and p.stem == n
        assert scenes.scene_file(f"file:{n}") == p
    for bad in ("file:no_such_scene", "../named", "file:", "files/cbox_glossy"):
        with pytest.raises(ValueError, match="file:" + names[0]):
            scenes.scene_file(bad)


def test_files_use_only_built_in_parts():
    """No external meshes or textures (nothing to download), no participating media."""
    import xml.etree.ElementTree as ET

    allowed_shapes = {"rectangle", "cube", "sphere", "disk", "cylinder"}
    for n in scenes.list_scene_files():
        root = ET.parse(scenes.scene_file(n)).getroot()
        assert root.tag == "scene"
        shapes = {e.get("type") for e in root.iter("shape")}
        assert shapes and shapes <= allowed_shapes, (n, shapes)
        assert not list(root.iter("medium")) and not list(root.iter("include")), n
        assert not [e for e in root.iter("string") if e.get("name") == "filename"], n
        assert list(root.iter("emitter")), n


@pytest.mark.parametrize("name", scenes.list_scene_files())
def test_file_renders_split_with_kpcn_overrides(name):
    """Each file loads through kpcn.render (film replaced, kpcn_split) and gives a finite, lit, split image."""
    from kpcn.render import load_scene, render_frame

    loaded = load_scene(scenes.scene_file(name), RES)
    fr = render_frame(scenes.scene_file(name), 4, seed=0, resolution=RES, loaded=loaded)
    assert fr["color"].shape == (RES[1], RES[0], 3)
    for layer in ("color", "diffuse", "specular", "albedo", "normal", "colorVariance"):
        assert np.isfinite(fr[layer]).all(), layer
    assert fr["color"].mean() > 1e-3  # lit
    np.testing.assert_allclose(fr["diffuse"] + fr["specular"], fr["color"], atol=1e-4)
    assert (fr["albedo"].max(axis=-1) > 0).mean() > 0.3  # most pixels see a surface
