"""Files that other tools (or a killed kpcn) leave behind, and inputs that used to be lost or blacked out.

* stale temporary files of :func:`kpcn.io.atomic_write` are removed on the next write to the same target;
* multi-part EXRs are read whole (every part's channels);
* the data window and the display window survive a read/write round trip;
* tiled mip-mapped EXRs are read (level 0);
* a variance near the float maximum neither blacks out the denoised neighbourhood nor passes silently.

Renders are real (Mitsuba); the special files are written with the OpenEXR Python package.
"""
from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

from kpcn import io as kio
from kpcn.io import BASE_LAYERS, FEATURE_LAYERS, ExrError, MissingLayerError, atomic_write, read_exr, write_exr

OpenEXR = pytest.importorskip("OpenEXR")


def _box(x0, y0, x1, y1):
    return (np.array([x0, y0], dtype=np.int32), np.array([x1, y1], dtype=np.int32))


def _exr_channels(frame, layers=None) -> dict[str, np.ndarray]:
    """A frame's layers as EXR channel arrays, named the way kpcn writes them."""
    out = {}
    for name, arr in frame.layers.items():
        if layers is not None and name not in layers:
            continue
        names = kio._channel_names(name, arr.shape[2])
        for c, cname in enumerate(names):
            out[cname] = np.ascontiguousarray(arr[..., c], dtype=np.float32).copy()
    return out


# ----------------------------------------------------------------------------- 1. stale temporary files


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()  # reaped: the pid names no process now
    return p.pid


@pytest.fixture
def live_pid():
    p = subprocess.Popen(["sleep", "60"])
    try:
        yield p.pid
    finally:
        p.kill()
        p.wait()


def test_temporary_name_carries_the_writers_pid(tmp_path):
    seen = []
    atomic_write(tmp_path / "x.exr", lambda tmp: (seen.append(os.path.basename(tmp)), open(tmp, "wb").close()))
    (name,) = seen
    assert name.startswith(f".x.exr.{os.getpid()}-") and name.endswith(".tmp.exr"), name
    assert os.listdir(tmp_path) == ["x.exr"]


def test_stale_temporaries_of_the_same_target_are_removed(render, tmp_path, live_pid):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    host = kio._host_tag()
    dead = _dead_pid()
    old = time.time() - 2 * kio.STALE_TEMP_AGE_S
    files = {
        # removed: writers on this machine that are gone (with and without the host tag)
        "dead": f".x.exr.{dead}-{host}.k2j4h6g8.tmp.exr",
        "dead_nohost": f".x.exr.{dead}.a1b2c3d4.tmp.exr",
        # removed: older than the safe age, whoever wrote them (kpcn's earlier name format, another machine)
        "old_legacy": ".x.exr.q9w8e7r6.tmp.exr",
        "old_other_host": f".x.exr.{dead}-elsewhere.z1x2c3v4.tmp.exr",
        # kept: live writers (a running process, this test's parent and this process itself)
        "live": f".x.exr.{live_pid}-{host}.m1n2b3v4.tmp.exr",
        "parent": f".x.exr.{os.getppid()}-{host}.p0o9i8u7.tmp.exr",
        "self": f".x.exr.{os.getpid()}-{host}.l5k6j7h8.tmp.exr",
        # kept: young files whose writer cannot be checked (earlier format, another machine)
        "young_legacy": ".x.exr.t5r4e3w2.tmp.exr",
        "young_other_host": f".x.exr.{dead}-elsewhere.y6t5r4e3.tmp.exr",
        # kept: another target's temporary, and files that only look alike
        "other_target": f".y.exr.{dead}-{host}.g7f6d5s4.tmp.exr",
        "longer_target": f".x.exr.1.exr.{dead}-{host}.h8g7f6d5.tmp.exr",
        "not_tmp": f".x.exr.{dead}-{host}.j9h8g7f6.exr",
        "user_file": "x.exr.bak",
    }
    for key, name in files.items():
        (tmp_path / name).write_bytes(b"half a file")
        if key.startswith("old_"):
            os.utime(tmp_path / name, (old, old))
    write_exr(tmp_path / "x.exr", frame.layers, frame.meta)
    left = set(os.listdir(tmp_path))
    removed = {"dead", "dead_nohost", "old_legacy", "old_other_host"}
    for key, name in files.items():
        assert (name in left) == (key not in removed), (key, name)
    assert "x.exr" in left
    np.testing.assert_array_equal(read_exr(tmp_path / "x.exr")["color"], frame["color"])


def test_checkpoint_style_temporaries_are_cleaned_too(tmp_path, live_pid):
    host = kio._host_tag()
    dead = _dead_pid()
    stale = tmp_path / f".latest.pt.{dead}-{host}.a8s7d6f5.tmp.pt"
    alive = tmp_path / f".latest.pt.{live_pid}-{host}.q2w3e4r5.tmp.pt"
    stale.write_bytes(b"x")
    alive.write_bytes(b"x")
    atomic_write(tmp_path / "latest.pt", lambda tmp: open(tmp, "wb").write(b"state"))
    assert not stale.exists() and alive.exists()
    assert (tmp_path / "latest.pt").read_bytes() == b"state"


def test_a_failing_cleanup_never_fails_the_write(tmp_path, monkeypatch):
    dead = _dead_pid()
    (tmp_path / f".x.exr.{dead}-{kio._host_tag()}.a1a1a1a1.tmp.exr").write_bytes(b"x")

    def refuse(path, *a, **k):
        raise PermissionError(f"no: {path}")

    monkeypatch.setattr(os, "unlink", refuse)  # the os module atomic_write uses
    atomic_write(tmp_path / "x.exr", lambda tmp: open(tmp, "wb").write(b"ok"))
    assert (tmp_path / "x.exr").read_bytes() == b"ok"


# ----------------------------------------------------------------------------- 2. multi-part files


@pytest.mark.parametrize("qualified", [False, True], ids=["bare-channels-in-named-part", "qualified-channels"])
def test_multi_part_file_is_read_whole(render, tmp_path, qualified):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    main = _exr_channels(frame, [n for n in frame.layers if n != "diffuse"])
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "spp": 4, "scene": "test:glossy", "seed": 1}
    if qualified:  # OpenEXR's own convention: full channel names, the part name only labels the part
        diffuse = {f"diffuse.{c}": np.ascontiguousarray(frame["diffuse"][..., i]).copy() for i, c in enumerate("RGB")}
    else:  # a part named after its layer, holding bare R, G, B
        diffuse = {c: np.ascontiguousarray(frame["diffuse"][..., i]).copy() for i, c in enumerate("RGB")}
    parts = [OpenEXR.Part(header, main, "rgba"), OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION}, diffuse, "diffuse")]
    path = tmp_path / "mp.exr"
    OpenEXR.File(parts).write(str(path))
    back = read_exr(path, require=FEATURE_LAYERS)
    assert set(back.layers) == set(frame.layers)
    for name, arr in frame.layers.items():
        np.testing.assert_array_equal(back[name], arr, err_msg=name)
    assert back.meta["spp"] == 4 and back.meta["scene"] == "test:glossy"


def test_multi_part_file_missing_a_layer_names_its_parts(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    parts = [
        OpenEXR.Part({}, _exr_channels(frame, ["color"]), "rgba"),
        OpenEXR.Part({}, _exr_channels(frame, ["albedo"]), "albedo"),
    ]
    path = tmp_path / "mp2.exr"
    OpenEXR.File(parts).write(str(path))
    with pytest.raises(MissingLayerError) as err:
        read_exr(path, require=BASE_LAYERS)
    msg = str(err.value)
    assert "diffuse" in msg and "multi-part" in msg and "rgba" in msg and "albedo" in msg


def test_multi_part_file_with_a_part_of_another_size_warns(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    small = {"Z": np.zeros((4, 4), np.float32)}
    # parts share the display window (OpenEXR requires it); the data windows differ
    thumb = {"displayWindow": _box(0, 0, 15, 15), "dataWindow": _box(0, 0, 3, 3)}
    parts = [OpenEXR.Part({}, _exr_channels(frame), "rgba"), OpenEXR.Part(thumb, small, "thumbnail")]
    path = tmp_path / "mp3.exr"
    OpenEXR.File(parts).write(str(path))
    with pytest.warns(RuntimeWarning, match="thumbnail"):
        back = read_exr(path, require=FEATURE_LAYERS)
    assert "thumbnail" not in back.layers


def test_multi_part_file_with_an_unreadable_part_says_which(render, tmp_path):
    # OpenEXR drops a part it cannot read (here a mip-mapped part without its smaller levels) and
    # only prints a line: the reader must say so, and the missing-layer error must name that part
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    diffuse = {f"diffuse.{c}": np.ascontiguousarray(frame["diffuse"][..., i]).copy() for i, c in enumerate("RGB")}
    parts = [
        OpenEXR.Part({}, _exr_channels(frame, [n for n in frame.layers if n != "diffuse"]), "rgba"),
        OpenEXR.Part({"type": OpenEXR.tiledimage, "tiles": _tiles(OpenEXR.MIPMAP_LEVELS)}, diffuse, "diffuse"),
    ]
    path = tmp_path / "mp4.exr"
    OpenEXR.File(parts).write(str(path))
    with pytest.warns(RuntimeWarning, match=r"'diffuse' \(tiled, mip-mapped"):
        with pytest.raises(MissingLayerError, match=r"unreadable part\(s\) 'diffuse'"):
            read_exr(path, require=BASE_LAYERS)


# ----------------------------------------------------------------------------- 3. data and display windows


def test_data_window_offset_from_display_window_round_trips(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "dataWindow": _box(4, 2, 19, 17),
        "displayWindow": _box(0, 0, 31, 31),
        "spp": 4,
    }
    src = tmp_path / "offset.exr"
    OpenEXR.File(header, _exr_channels(frame)).write(str(src))
    fr = read_exr(src, require=FEATURE_LAYERS)
    assert fr.meta["dataWindow"] == ((4, 2), (19, 17))
    assert fr.meta["displayWindow"] == ((0, 0), (31, 31))
    out = tmp_path / "out.exr"
    write_exr(out, fr.layers, fr.meta)
    with OpenEXR.File(str(out), header_only=True) as f:
        h = f.header()
        assert [list(map(int, v)) for v in h["dataWindow"]] == [[4, 2], [19, 17]]
        assert [list(map(int, v)) for v in h["displayWindow"]] == [[0, 0], [31, 31]]
    back = read_exr(out)
    assert back.meta["dataWindow"] == ((4, 2), (19, 17)) and back.meta["displayWindow"] == ((0, 0), (31, 31))
    for name, arr in frame.layers.items():
        np.testing.assert_array_equal(back[name], arr, err_msg=name)


def test_plain_file_records_its_windows_and_writes_them_back(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    write_exr(tmp_path / "a.exr", frame.layers, frame.meta)
    fr = read_exr(tmp_path / "a.exr")
    assert fr.meta["dataWindow"] == fr.meta["displayWindow"] == ((0, 0), (15, 15))


def test_window_that_does_not_fit_the_layers_is_refused(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    with pytest.raises(ValueError, match="dataWindow"):
        write_exr(tmp_path / "b.exr", frame.layers, {"dataWindow": ((0, 0), (7, 7))})
    assert not os.listdir(tmp_path)


def test_crop_moves_the_data_window(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1, resolution=(16, 16))
    fr = kio.Frame(dict(frame.layers), {"dataWindow": ((4, 2), (19, 17)), "displayWindow": ((0, 0), (31, 31))})
    c = fr.crop(3, 10, 5, 16)
    assert c.meta["dataWindow"] == ((9, 5), (19, 11)) and c.meta["displayWindow"] == ((0, 0), (31, 31))
    write_exr(tmp_path / "c.exr", c.layers, c.meta)  # consistent with the cropped size
    assert read_exr(tmp_path / "c.exr").meta["dataWindow"] == ((9, 5), (19, 11))


# ----------------------------------------------------------------------------- 4. tiled, mip-mapped files


def _tiles(mode):
    t = OpenEXR.TileDescription()
    t.xSize, t.ySize, t.mode, t.roundingMode = 8, 8, mode, OpenEXR.ROUND_DOWN
    return t


@pytest.mark.parametrize("mode", ["MIPMAP_LEVELS", "RIPMAP_LEVELS"])
def test_mip_mapped_tiled_file_is_read_at_level_0(render, tmp_path, mode):
    # the OpenEXR Python package writes level 0 only: the other levels' chunk table entries stay empty
    frame = render("test:glossy", spp=4, seed=1)  # 32 x 32: 4 x 4 tiles of 8 x 8
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.tiledimage,
              "tiles": _tiles(getattr(OpenEXR, mode)), "spp": 4}
    path = tmp_path / "mip.exr"
    OpenEXR.File(header, _exr_channels(frame)).write(str(path))
    fr = read_exr(path, require=FEATURE_LAYERS)
    for name, arr in frame.layers.items():
        np.testing.assert_array_equal(fr[name], arr, err_msg=name)
    assert fr.meta["spp"] == 4


def _write_full_mipmap(path, chans):
    """A complete mip-mapped file: OpenEXR writes level 0, the smaller levels are appended by hand."""
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.tiledimage,
                  "tiles": _tiles(OpenEXR.MIPMAP_LEVELS)}, {k: v.copy() for k, v in chans.items()}).write(str(path))
    data = bytearray(path.read_bytes())
    i = 8
    while data[i]:
        i = data.index(b"\0", data.index(b"\0", i) + 1) + 1
        i += 4 + struct.unpack_from("<i", data, i)[0]
    table = i + 1
    h, w = next(iter(chans.values())).shape
    levels = [(max(w >> k, 1), max(h >> k, 1)) for k in range(max(w, h).bit_length())]
    counts = [-(-lw // 8) * -(-lh // 8) for lw, lh in levels]
    offsets = list(struct.unpack_from(f"<{sum(counts)}Q", data, table))
    k = counts[0]
    for lv, (lw, lh) in enumerate(levels[1:], 1):
        img = {n: np.ascontiguousarray(chans[n][:: 1 << lv, :: 1 << lv][:lh, :lw]) for n in sorted(chans)}
        for ty in range(-(-lh // 8)):
            for tx in range(-(-lw // 8)):
                rows = [img[n][y, tx * 8: tx * 8 + 8].astype("<f4").tobytes()
                        for y in range(ty * 8, min(ty * 8 + 8, lh)) for n in sorted(img)]
                block = b"".join(rows)
                offsets[k], k = len(data), k + 1
                data += struct.pack("<5i", tx, ty, lv, lv, len(block)) + block
    struct.pack_into(f"<{len(offsets)}Q", data, table, *offsets)
    path.write_bytes(bytes(data))


def test_complete_mip_mapped_file_is_read_at_level_0(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1)
    path = tmp_path / "full.exr"
    _write_full_mipmap(path, _exr_channels(frame))
    fr = read_exr(path, require=FEATURE_LAYERS)
    for name, arr in frame.layers.items():
        np.testing.assert_array_equal(fr[name], arr, err_msg=name)


def test_unreadable_mip_mapped_file_error_says_so(render, tmp_path):
    frame = render("test:glossy", spp=4, seed=1)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.tiledimage, "tiles": _tiles(OpenEXR.MIPMAP_LEVELS)}
    good = tmp_path / "mip.exr"
    OpenEXR.File(header, _exr_channels(frame)).write(str(good))
    data = good.read_bytes()
    bad = tmp_path / "cut.exr"
    bad.write_bytes(data[: len(data) * 2 // 3])  # level-0 tiles missing too
    with pytest.raises(ExrError) as err:
        read_exr(bad)
    msg = str(err.value)
    assert "cut.exr" in msg and "mip-mapped" in msg and "tiled" in msg


# ----------------------------------------------------------------------------- 5. huge variances


def _spike_pixel(frame):
    """A pixel well inside the frame where both diffuse and specular carry light."""
    h, w = frame.shape
    d = frame["diffuse"].mean(-1)
    s = frame["specular"].mean(-1)
    ok = (d > 0) & (s > 0)
    ok[:8, :] = ok[-8:, :] = False
    ok[:, :8] = ok[:, -8:] = False
    ys, xs = np.nonzero(ok)
    i = np.argmin((ys - h / 2) ** 2 + (xs - w / 2) ** 2)
    return int(ys[i]), int(xs[i])


@pytest.mark.parametrize("layer", ["diffuseVariance", "specularVariance"])
def test_huge_variance_does_not_black_out_the_neighbourhood(render, layer):
    from kpcn.inference import denoise

    frame = render("test:glossy", spp=4, seed=1)  # 32 x 32
    y, x = _spike_pixel(frame)
    clean = denoise(frame, model=None, device="cpu")
    layers = {k: v.copy() for k, v in frame.layers.items()}
    layers[layer][y, x] = 3e38
    layers["colorVariance"][y, x] = 3e38
    spiked = kio.Frame(layers, dict(frame.meta))
    with pytest.warns(RuntimeWarning, match=layer):
        out = denoise(spiked, model=None, device="cpu")
    assert np.isfinite(out).all()
    nb = (slice(y - 10, y + 11), slice(x - 10, x + 11))  # the 21 x 21 block around the spike
    lit = clean[nb].max(-1) > 0
    assert lit.mean() > 0.5
    assert np.all(out[nb].max(-1)[lit] > 0), "pixels turned black around the spike"
    rel = np.abs(out[nb] - clean[nb]).mean() / np.abs(clean[nb]).mean()
    assert rel < 0.02, rel


def test_features_bound_variances_and_count_them(render):
    import torch

    from kpcn.features import frame_features, frame_to_tensors, make_features

    frame = render("test:glossy", spp=4, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a real render's variances are all within bounds: no warning
        plain = frame_features(frame)
    b = frame_to_tensors(frame)
    b["diffuseVariance"][0, :, 3, 4] = 3e38
    b["specularVariance"][0, 1, 5, 6] = 3e38
    b["depthVariance"][0, 0, 7, 8] = 3e38
    with pytest.warns(RuntimeWarning) as rec:
        feats = make_features(b)
    msg = " ".join(str(r.message) for r in rec)
    assert re.search(r"diffuseVariance: 3\b", msg) and re.search(r"specularVariance: 1\b", msg)
    assert re.search(r"depthVariance: 1\b", msg)
    for t in feats.as_dict().values():
        assert torch.isfinite(t).all()
    # only the spiked pixels change, and their variance stays below the physical bound
    for got, want in ((feats.x_diffuse, plain.x_diffuse), (feats.x_specular, plain.x_specular)):
        diff = (got != want).any(dim=1)[0]
        assert set(map(tuple, torch.nonzero(diff).tolist())) <= {(3, 4), (5, 6), (7, 8)}
    assert float(feats.x_specular[0, 3, 5, 6]) <= 1.02 # delta-method variance of log1p: var / (1 + s)^2 <= 1
