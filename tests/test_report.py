"""The error-against-time report (kpcn.report) and the OIDN baseline, on real tiny renders.

The report runs once in --quick mode (two 24x24 scenes, spp 2 and 4, 64-spp
reference) through the Python API with a tiny untrained stand-in model saved as
a checkpoint (so nothing depends on shipped weights), then again through
``python -m kpcn.report`` into the same folder, which must reuse the renders.
"""
from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kpcn.baselines import oidn_available, oidn_denoise
from kpcn.report import (
    MC,
    METRICS,
    ReportConfig,
    mc_spp_for_error,
    nearest_spp,
    parse_model_spec,
    render_time_model,
    run_report,
)

HAS_OIDN = oidn_available()


@pytest.fixture(scope="module")
def stand_in(tmp_path_factory):
    """A tiny KPCN (3 layers x 8, 5x5 kernels) saved as a weights file."""
    from kpcn.checkpoint import save_weights
    from kpcn.models import create_model

    path = tmp_path_factory.mktemp("ckpt") / "tiny.safetensors"
    save_weights(path, create_model("kpcn", layers=3, width=8, kernel_size=5))
    return path


@pytest.fixture(scope="module")
def report(tmp_path_factory, stand_in, mi):
    out = tmp_path_factory.mktemp("report")
    cfg = ReportConfig.quick(out=str(out), models=[f"kpcn={stand_in}"])
    return cfg, run_report(cfg)


def _csv_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _exr_mtimes(folder: Path) -> dict[str, int]:
    return {str(p): p.stat().st_mtime_ns for p in sorted(folder.rglob("*.exr"))}


# ----------------------------------------------------------------------------- the quick report


def test_csv_has_one_row_per_scene_spp_method(report):
    cfg, res = report
    rows = _csv_rows(res.paths["csv"])
    methods = [MC, "kpcn"] + (["oidn"] if HAS_OIDN else [])
    keys = [(r["scene"], int(r["spp"]), r["method"]) for r in rows]
    assert sorted(keys) == sorted((s, p, m) for s in cfg.scenes for p in cfg.spp for m in methods)
    for r in rows:
        for k in METRICS:
            assert math.isfinite(float(r[k])), (k, r)
        assert float(r["render_s"]) > 0 and float(r["total_s"]) > 0
        if r["method"] == MC:
            assert float(r["denoise_s"]) == 0
        else:
            assert float(r["denoise_s"]) > 0
            assert float(r["total_s"]) == pytest.approx(float(r["render_s"]) + float(r["denoise_s"]), rel=1e-4)
        assert int(r["ref_spp"]) == cfg.ref_spp and (int(r["width"]), int(r["height"])) == tuple(cfg.resolution)


def test_markdown_pngs_and_summary(report):
    from PIL import Image

    cfg, res = report
    md = res.paths["markdown"].read_text()
    for heading in ("## Mean over scenes", "## Equal time", "## Per scene"):
        assert heading in md
    if not HAS_OIDN:
        assert "OIDN was not installed" in md
    for key in ("plot", "contact_sheet"):
        with Image.open(res.paths[key]) as im:
            im.verify()
        with Image.open(res.paths[key]) as im:
            assert im.format == "PNG" and im.width >= 300 and im.height >= 150
    summary = json.loads(res.paths["summary"].read_text())
    assert set(summary["mean"]) >= {MC, "kpcn"}
    # the stand-in's cost, counted by hand: per branch 27->8 and 8->8 and 8->25 (5x5 convs), 5x5 kernels on RGB
    per_branch = 27 * 8 * 25 + 8 * 8 * 25 + 8 * 25 * 25 + 3 * 25
    assert summary["method_macs_per_px"]["kpcn"] == 2 * per_branch
    assert f"kpcn ({2 * per_branch / 1e3:.1f} k multiply-adds per pixel)" in md
    assert set(summary["mean"][MC]) == {str(s) for s in cfg.spp}
    eq = summary["equal_time"]
    assert [e["scene"] for e in eq] == list(cfg.scenes)
    for e in eq:
        assert e["model"] == "kpcn" and e["model_spp"] == 4  # 8 is off the quick ladder: nearest
        assert e["mc_spp"] > 0 and e["time_ratio"] > 0 and isinstance(e["extrapolated"], bool)
    assert summary["equal_time_geomean"]["time_ratio"] > 0
    assert "time ratio" in md


def test_raw_mc_error_falls_with_spp(report):
    _, res = report
    mean = {s: np.mean([r["relmse"] for r in res.rows if r["method"] == MC and r["spp"] == s]) for s in (2, 4)}
    assert mean[4] < mean[2]


@pytest.mark.skipif(not HAS_OIDN, reason="pyoidn not installed")
def test_oidn_rows_beat_raw_mc(report):
    _, res = report
    err = {m: np.mean([r["relmse"] for r in res.rows if r["method"] == m and r["spp"] == 2]) for m in (MC, "oidn")}
    assert err["oidn"] < err[MC]


def test_cli_reuses_cached_renders(report, stand_in):
    cfg, res = report
    renders = cfg.folder / "renders"
    before = _exr_mtimes(renders)
    assert len(before) == len(cfg.scenes) * (len(cfg.spp) + 1)
    assert res.rendered, "the first run rendered everything"
    cmd = [sys.executable, "-m", "kpcn.report", "--quick", "--out", cfg.out, "--models", f"kpcn={stand_in}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "## Equal time" in proc.stdout and "| mc | 2 |" in proc.stdout
    assert "rendered" not in proc.stderr
    assert _exr_mtimes(renders) == before, "a second run must reuse the cached renders"
    rows = _csv_rows(res.paths["csv"])
    assert len(rows) == len(res.rows)
    # renders are identical, so raw MC metrics are too
    mc_old = {(r["scene"], r["spp"]): r["relmse"] for r in res.rows if r["method"] == MC}
    for r in rows:
        if r["method"] == MC:
            assert float(r["relmse"]) == pytest.approx(mc_old[(r["scene"], int(r["spp"]))], rel=1e-5)


# ----------------------------------------------------------------------------- pieces


def test_mc_spp_for_error_interpolates_and_extrapolates():
    spp = [2, 4, 8, 16]
    err = [1.0, 0.5, 0.25, 0.125]  # exact 1/spp
    s, ext, slope = mc_spp_for_error(spp, err, 0.35355339)  # sqrt(0.5 * 0.25): halfway in log
    assert not ext and s == pytest.approx(math.sqrt(32), rel=1e-6) and slope == pytest.approx(-1)
    s, ext, _ = mc_spp_for_error(spp, err, 0.125 / 8)
    assert ext and s == pytest.approx(128, rel=1e-6)
    s, ext, _ = mc_spp_for_error(spp, err, 2.0)
    assert ext and s == pytest.approx(1, rel=1e-6)
    # a ladder that does not fall (noise): extrapolation uses the MC slope -1
    s, ext, slope = mc_spp_for_error([2, 4], [1.0, 1.1], 0.5)
    assert ext and slope == -1.0 and s == pytest.approx(4 * 1.1 / 0.5, rel=1e-6)


def test_render_time_model():
    a, b = render_time_model([2, 4, 8, 1024], [0.1 + 0.01 * s for s in (2, 4, 8, 1024)])
    assert a == pytest.approx(0.1) and b == pytest.approx(0.01)
    a, b = render_time_model([2, 4], [0.5, 0.4])  # time that does not grow: seconds per sample over all
    assert a == 0 and b == pytest.approx(0.9 / 6)


def test_model_specs_and_ladder():
    assert parse_model_spec("kpcn") == ("kpcn", "kpcn")
    assert parse_model_spec("runs/a/latest.pt") == ("latest", "runs/a/latest.pt")
    assert parse_model_spec("mine=runs/a/latest.pt") == ("mine", "runs/a/latest.pt")
    assert nearest_spp([2, 4, 16, 64], 8) == 4 and nearest_spp([2, 4, 8], 8) == 8
    with pytest.raises(ValueError, match="spp"):
        ReportConfig(spp=[1, 2]).validate()


@pytest.mark.skipif(not HAS_OIDN, reason="pyoidn not installed")
def test_oidn_wrapper_handles_pyoidn_input_rules():
    rng = np.random.default_rng(0)
    color = rng.random((16, 20, 3))  # float64: pyoidn itself refuses it
    color[0, 0] = np.nan
    color[1, 1] = np.inf
    color[2, 2] = -1.0
    albedo = rng.random((16, 20, 3)) * 1.2  # conductors: above 1
    normal = rng.random((16, 20, 3)) * 2 - 1
    out = oidn_denoise(color, albedo, normal)
    assert out.shape == (16, 20, 3) and out.dtype == np.float32 and np.isfinite(out).all()
    assert oidn_denoise(color[..., :1].repeat(3, -1)).shape == (16, 20, 3)
    with pytest.raises(ValueError, match="shape"):
        oidn_denoise(color, albedo[:8])
