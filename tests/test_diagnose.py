"""``kpcn.report.diagnose`` on real tiny renders (Mitsuba) with the shipped default model."""
from __future__ import annotations

import math

import numpy as np
import pytest

from kpcn.io import write_exr
from kpcn.report.diagnose import diagnose_frame, find_renders, geometric_edges, main

RES = (48, 48)


@pytest.fixture(scope="module")
def net():
    from kpcn.inference.weights import load_model

    return load_model(None, device="cpu").eval()


def test_a_scene_without_specular_light_has_only_diffuse_error(net, render):
    """test:textured reflects no specular light: its specular part is zero in the reference and the output, so
    putting the reference's specular in changes nothing, the reference's diffuse leaves no error at all, and its
    specular ratio is undefined. Its albedo is a texture, so a 4-spp albedo is noisy: the reference's albedo in
    the remodulation lowers the error."""
    noisy = render("test:textured", spp=4, seed=1, resolution=RES)
    ref = render("test:textured", spp=256, seed=2, role=1, resolution=RES)
    assert float(np.abs(ref["specular"]).max()) == 0.0
    row = diagnose_frame(net, noisy, ref)["model"]
    assert row["relmse"] > 1e-4
    assert row["specular=ref"] == pytest.approx(row["relmse"], rel=1e-6)
    assert row["diffuse=ref"] < 1e-10
    assert math.isnan(row["specular ratio"]) and 0.5 < row["diffuse ratio"] < 1.5
    assert row["albedo=ref"] < row["relmse"] and row["psnr albedo=ref"] > row["psnr"]
    assert row["low band"] > 0 and row["high band"] > 0
    # the error split at the reference's geometric edges: both parts carry some, on a share of the frame
    assert 0 < row["edge share"] < 0.6 and row["edge band"] > 0 and row["off-edge band"] > 0


def test_the_reference_as_input_is_diagnosed_close_to_itself(net, render):
    """A converged frame against itself: the output barely moves, so every relMSE is small and the ratios are 1."""
    ref = render("test:glossy", spp=256, seed=2, role=1, resolution=RES)
    row = diagnose_frame(net, ref, ref)["model"]
    noisy_row = diagnose_frame(net, render("test:glossy", spp=2, seed=1, resolution=RES), ref)["model"]
    assert row["relmse"] < noisy_row["relmse"] / 3
    assert abs(row["ratio"] - 1) < 0.02 and abs(row["specular ratio"] - 1) < 0.05


def test_geometric_edges_mark_where_the_normal_turns_or_the_depth_jumps():
    """Pure geometry: a floor (normal +y) meeting a wall (normal +z) along column 5, and on the floor a step in
    depth along row 3 (a nearer object with the floor's normal): both pixels of each changing pair are marked,
    nothing else; a turn or a jump below the thresholds is not an edge."""
    n = np.zeros((8, 10, 3))
    n[:, :5, 1] = 1
    n[:, 5:, 2] = 1
    z = np.full((8, 10), 4.0)
    z[4:, :5] = 2.0
    e = geometric_edges(n, z)
    expect = np.zeros((8, 10), bool)
    expect[:, 4:6] = True
    expect[3:5, :5] = True
    assert np.array_equal(e, expect)
    tilt = n.copy()
    tilt[:, 5:] = [0, 0.95, 0.31]  # about 18 degrees from the floor's normal: sum of |differences| 0.36
    assert geometric_edges(tilt, np.full((8, 10), 4.0))[:, 4:6].all()
    assert not geometric_edges(tilt, np.full((8, 10), 4.0), turn=0.5).any()
    # one surface whose depth grows smoothly across the frame (a receding floor) has none
    ramp = np.broadcast_to(4.0 + 0.05 * np.arange(10), (8, 10))
    assert not geometric_edges(np.broadcast_to(n[:, :1], n.shape), ramp).any()


def test_cli_reads_a_renders_folder_and_refuses_an_empty_one(net, render, tmp_path, capsys):
    folder = tmp_path / "renders" / "test_textured" / "48x48-abc"
    folder.mkdir(parents=True)
    write_exr(folder / "input_4spp_seed0.exr", render("test:textured", spp=4, seed=1, resolution=RES).layers)
    write_exr(folder / "reference_256spp_seed0.exr",
              render("test:textured", spp=256, seed=2, role=1, resolution=RES).layers)
    assert [s.scene for s in find_renders(str(tmp_path / "renders"))] == ["test_textured"]
    # a refined reference beside the first is the one used: the most samples, not the first name in order
    for name in ("reference_1024spp_seed0.exr", "reference_512spp_seed0.exr"):
        (folder / name).write_bytes((folder / "reference_256spp_seed0.exr").read_bytes())
    assert find_renders(str(tmp_path / "renders"))[0].reference().endswith("reference_1024spp_seed0.exr")
    (folder / "reference_1024spp_seed0.exr").unlink()
    assert find_renders(str(tmp_path / "renders"))[0].reference().endswith("reference_512spp_seed0.exr")
    assert main(["--renders", str(tmp_path / "renders"), "--spp", "4", "8", "--no-oidn"]) == 0
    out = capsys.readouterr().out
    assert "| test_textured | 0.0" in out and "| mean |" in out and "no 8-spp input" in out
    with pytest.raises(FileNotFoundError, match="no renders with a reference"):
        find_renders(str(tmp_path / "nothing"))


def test_a_model_without_the_diffuse_specular_split_is_refused(render):
    from kpcn.inference.weights import load_model

    can = load_model("kpcn:can_small", device="cpu")
    frame = render("test:textured", spp=4, seed=1, resolution=RES)
    with pytest.raises(ValueError,
                       match="needs a model with the diffuse/specular split; 'color_albedo_normal_noise' has"):
        diagnose_frame(can, frame, frame)
