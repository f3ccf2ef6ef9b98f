"""``kpcn.report.compare``: one method's means against another's on the same frames, read from results.csv."""
from __future__ import annotations

import pytest

from kpcn.report.compare import compare, load_side, main, markdown
from kpcn.report.tables import write_csv


def _row(scene, spp, method, psnr, relmse, ssim, ref_floor=0.0002):
    return dict(scene=scene, spp=spp, method=method, psnr=psnr, relmse=relmse, ssim=ssim, smape=0.0,
                render_s=0.1, denoise_s=0.1, total_s=0.2, width=64, height=64, ref_spp=2048, ref_floor=ref_floor,
                ref_limited=False)


def _report(tmp_path, name, rows):
    d = tmp_path / name
    d.mkdir()
    write_csv(d / "results.csv", rows)
    return d


@pytest.fixture
def two(tmp_path):
    # base: two scenes at 4 and 64 spp. The candidate gains a little on scene a everywhere and loses 3 dB on scene b
    # at 64 spp, so its 64-spp PSNR mean is lower although it wins on most frames
    base = [_row("a", 4, "base", 30.0, 0.010, 0.90), _row("b", 4, "base", 32.0, 0.008, 0.92),
            _row("a", 64, "base", 40.0, 0.002, 0.97), _row("b", 64, "base", 41.0, 0.001, 0.98),
            _row("a", 4, "mc", 20.0, 0.5, 0.3)]
    cand = [_row("a", 4, "new", 30.5, 0.009, 0.91), _row("b", 4, "new", 32.1, 0.008, 0.92),
            _row("a", 64, "new", 40.2, 0.0019, 0.971), _row("b", 64, "new", 38.0, 0.003, 0.975),
            _row("a", 4, "other", 1.0, 1.0, 0.0)]
    return _report(tmp_path, "base", base), _report(tmp_path, "cand", cand)


def test_means_wins_and_worst_scene(two):
    b, c = two
    cmp = compare(load_side(f"{b}"), load_side(f"{c}:new"))
    assert cmp.spps == [4, 64]
    assert cmp.means["base"][4]["psnr"] == pytest.approx(31.0)
    assert cmp.means["new"][64]["psnr"] == pytest.approx(39.1)
    # 4 spp: PSNR and SSIM up, relMSE down (better); 64 spp: all three worse, driven by scene b
    assert sorted(cmp.wins) == [(4, "psnr"), (4, "relmse"), (4, "ssim")]
    assert sorted(cmp.losses) == [(64, "psnr"), (64, "relmse"), (64, "ssim")]
    assert cmp.moves[64]["psnr"][0][0] == "b" and cmp.moves[64]["psnr"][0][1] == pytest.approx(-3.0)
    # relMSE is signed so that worse is negative, as for the others
    assert cmp.moves[64]["relmse"][0][0] == "b" and cmp.moves[64]["relmse"][0][1] < 0
    text = markdown(cmp)
    assert "new wins 3 of 6 figures and loses 3" in text
    assert "b -3" in text and "relmse: b +2" in text  # the rise as a fraction of b's own relMSE: 0.003 / 0.001 - 1


def test_one_method_needed_when_a_report_has_several(two):
    _, c = two
    with pytest.raises(ValueError, match="name one method.*new, other"):
        load_side(f"{c}")
    with pytest.raises(ValueError, match="no method 'nope'"):
        load_side(f"{c}:nope")


def test_different_references_are_refused(tmp_path, two):
    b, _ = two
    moved = _report(tmp_path, "moved", [_row("a", 4, "new", 30.0, 0.01, 0.9, ref_floor=0.0009),
                                        _row("b", 4, "new", 32.0, 0.008, 0.92)])
    with pytest.raises(ValueError, match="different references.*on a:"):
        compare(load_side(f"{b}"), load_side(f"{moved}"))
    elsewhere = _report(tmp_path, "elsewhere", [_row("z", 4, "new", 30.0, 0.01, 0.9)])
    with pytest.raises(ValueError, match="share no"):
        compare(load_side(f"{b}"), load_side(f"{elsewhere}"))


def test_one_method_in_two_reports_is_named_by_its_report(tmp_path, two):
    b, _ = two
    again = _report(tmp_path, "again", [_row("a", 4, "base", 31.0, 0.009, 0.91),
                                        _row("b", 4, "base", 32.0, 0.008, 0.92)])
    cmp = compare(load_side(f"{b}"), load_side(f"{again}"))
    assert cmp.base == "base (base)" and cmp.candidate == "base (again)"
    assert cmp.means["base (again)"][4]["psnr"] == pytest.approx(31.5) and (4, "psnr") in cmp.wins
    with pytest.raises(ValueError, match="against itself"):
        compare(load_side(f"{b}"), load_side(f"{b}"))


def test_cli(two, tmp_path, capsys):
    b, c = two
    assert main([str(b), f"{c}:new", "--worst", "1"]) == 0
    out = capsys.readouterr().out
    assert "| 64 | 40.50 / 0.001500 / 0.97500 | 39.10 / 0.002450 / 0.97300 | none |" in out
    assert main([str(tmp_path / "missing"), f"{c}:new"]) == 2
    assert "no results.csv" in capsys.readouterr().err


def test_reports_pooled(tmp_path, two):
    # a second validation set of other scenes: pooled, each side's means are over all four scenes
    b, c = two
    b2 = _report(tmp_path, "base2", [_row("x", 4, "ref", 20.0, 0.02, 0.80), _row("y", 4, "ref", 22.0, 0.02, 0.82)])
    c2 = _report(tmp_path, "cand2", [_row("x", 4, "new", 19.0, 0.03, 0.79), _row("y", 4, "new", 22.0, 0.02, 0.82)])
    base, cand = load_side(f"{b}+{b2}:ref"), load_side(f"{c}:new+{c2}")
    assert base.label == "base+ref" and cand.label == "new" and len(base.rows) == 6
    cmp = compare(base, cand)
    assert cmp.means["base+ref"][4]["psnr"] == pytest.approx((30.0 + 32.0 + 20.0 + 22.0) / 4)
    assert cmp.means["new"][4]["psnr"] == pytest.approx((30.5 + 32.1 + 19.0 + 22.0) / 4)
    # scene x's 1 dB loss outweighs a and b's gains at 4 spp: pooled, PSNR is lost where the first set alone won it
    assert (4, "psnr") in cmp.losses and (4, "psnr") in compare(load_side(f"{b}"), load_side(f"{c}:new")).wins
    assert cmp.moves[4]["psnr"][0][0] == "x"
    with pytest.raises(ValueError, match="a at 4 spp.*more than one"):
        load_side(f"{b}+{b}")
    assert main([f"{b}+{b2}:ref", f"{c}:new+{c2}", "--worst", "0"]) == 0
