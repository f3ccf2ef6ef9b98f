"""EXR contract: round trips, aliases, missing layers, non-finite values, broken files."""
import os

import numpy as np
import pytest

from kpcn.io import BASE_LAYERS, ExrError, MissingLayerError, read_exr, write_exr


def test_round_trip_of_a_render_is_exact(render, tmp_path):
    frame = render("test:glossy", spp=4)
    path = tmp_path / "f.exr"
    write_exr(path, frame.layers, frame.meta)
    back = read_exr(path, require=BASE_LAYERS)
    assert set(back.layers) == set(frame.layers)
    for name, arr in frame.layers.items():
        np.testing.assert_array_equal(back[name], arr, err_msg=name)
    assert back.meta["spp"] == 4 and back.meta["scene"] == frame.meta["scene"]
    assert back.meta["seed"] == frame.meta["seed"]
    assert back.meta["renderTimeSeconds"] == pytest.approx(frame.meta["renderTimeSeconds"])


def test_float16_round_trip(render, tmp_path):
    frame = render("test:glossy", spp=4)
    write_exr(tmp_path / "h.exr", frame.layers, frame.meta, half=True)
    back = read_exr(tmp_path / "h.exr")
    for name, arr in frame.layers.items():
        expect = arr.astype(np.float16).astype(np.float32)
        expect[~np.isfinite(expect)] = 0  # float16 overflow -> inf -> replaced
        np.testing.assert_array_equal(back[name], np.where(np.isfinite(arr.astype(np.float16)), expect, back[name]))


def test_missing_layer_names_missing_and_found(render, tmp_path):
    frame = render("test:glossy", spp=4)
    layers = {k: v for k, v in frame.layers.items() if k not in ("albedo", "normalVariance")}
    write_exr(tmp_path / "m.exr", layers, frame.meta)
    with pytest.raises(MissingLayerError) as err:
        read_exr(tmp_path / "m.exr", require=("albedo", "normal", "normalVariance"))
    msg = str(err.value)
    assert "albedo" in msg and "normalVariance" in msg
    assert "found:" in msg and "diffuse" in msg and "specular" in msg
    # a frame reads as a mapping of its layers; a key that is no layer name is still a clear MissingLayerError
    f = read_exr(tmp_path / "m.exr")
    assert dict(f).keys() == f.layers.keys() and len(f) == len(f.layers) and sorted(f) == sorted(f.layers)
    with pytest.raises(MissingLayerError, match="missing layer.s. 0; found: .*color"):
        f[0]


def test_nonfinite_values_are_replaced_and_counted(render, tmp_path):
    frame = render("test:glossy", spp=4)
    layers = {k: v.copy() for k, v in frame.layers.items()}
    layers["color"][0, 0, 0] = np.nan
    layers["color"][1, 1, 2] = np.inf
    layers["diffuse"][2, 3, 1] = -np.inf
    write_exr(tmp_path / "n.exr", layers)
    with pytest.warns(RuntimeWarning, match=r"color: 2.*diffuse: 1"):
        back = read_exr(tmp_path / "n.exr")
    assert back.nonfinite == {"color": 2, "diffuse": 1}
    for arr in back.layers.values():
        assert np.isfinite(arr).all()
    assert back["color"][0, 0, 0] == 0 and back["diffuse"][2, 3, 1] == 0
    finite = layers["color"][np.isfinite(layers["color"])]
    assert back["color"][1, 1, 2] == finite.max()  # +Inf saturates at the layer's largest finite value


def test_truncated_file_gives_clear_error(render, tmp_path):
    frame = render("test:glossy", spp=4)
    good = tmp_path / "g.exr"
    write_exr(good, frame.layers, frame.meta)
    data = good.read_bytes()
    bad = tmp_path / "t.exr"
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(ExrError, match="truncated"):
        read_exr(bad)
    (tmp_path / "x.exr").write_text("not an exr")
    with pytest.raises(ExrError, match="cannot read"):
        read_exr(tmp_path / "x.exr")
    with pytest.raises(FileNotFoundError, match="nope.exr"):
        read_exr(tmp_path / "nope.exr")


def test_tungsten_and_alias_channel_names(tmp_path):
    import OpenEXR

    h, w = 4, 5
    rng = np.random.default_rng(0)
    ch = {n: rng.random((h, w), dtype=np.float32) for n in (
        "color.R", "color.G", "color.B", "normal.X", "normal.Y", "normal.Z", "depth.Z",
        "colorVariance.Y", "diffuse.R", "diffuse.G", "diffuse.B", "diffuseVariance.Z")}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {k: v.copy() for k, v in ch.items()}).write(str(tmp_path / "t.exr"))
    fr = read_exr(tmp_path / "t.exr")
    np.testing.assert_array_equal(fr["color"][..., 1], ch["color.G"])
    np.testing.assert_array_equal(fr["normal"][..., 2], ch["normal.Z"])
    np.testing.assert_array_equal(fr["depth"][..., 0], ch["depth.Z"])
    assert fr["colorVariance"].shape == (h, w, 1) and fr["diffuseVariance"].shape == (h, w, 1)


def test_interrupted_write_keeps_previous_file(render, tmp_path, monkeypatch):
    import OpenEXR

    frame = render("test:glossy", spp=4)
    path = tmp_path / "out.exr"
    write_exr(path, frame.layers, frame.meta)
    before = path.read_bytes()

    class Dying:
        def __init__(self, header, channels):
            pass

        def write(self, tmp):
            with open(tmp, "wb") as f:
                f.write(b"half a file")
            raise OSError("disk full")

    monkeypatch.setattr(OpenEXR, "File", Dying)
    with pytest.raises(OSError, match="disk full"):
        write_exr(path, frame.layers, frame.meta)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["out.exr"]


def test_unknown_three_channel_layers_are_read_whole(tmp_path):
    """A light group or AOV written by another tool (``key.diffuse.R/G/B``) keeps its three channels."""
    rng = np.random.default_rng(0)
    layers = {"color": rng.random((5, 4, 3), dtype=np.float32), "key.diffuse": rng.random((5, 4, 3), dtype=np.float32),
              "fog": rng.random((5, 4, 3), dtype=np.float32), "depth": rng.random((5, 4, 1), dtype=np.float32)}
    write_exr(tmp_path / "a.exr", layers)
    fr = read_exr(tmp_path / "a.exr")
    for name, arr in layers.items():
        np.testing.assert_array_equal(fr[name], arr)
