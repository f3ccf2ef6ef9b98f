"""The mirrored-views ensemble (``denoise(..., views=N)``, kpcn.inference.ensemble) on real renders."""
from __future__ import annotations

import numpy as np
import pytest

from kpcn.inference import denoise, denoise_result
from kpcn.inference.cli import main as cli_main
from kpcn.inference.ensemble import unview, view
from kpcn.io import Frame, read_exr, write_exr
from kpcn.report.methods import split_views

SIZE = (48, 40)  # not square: a transposed view has another shape, which the way back must undo


@pytest.fixture(scope="module")
def frame(render):
    return render("test:glossy", spp=4, seed=3, resolution=SIZE)


def _viewed(frame, k):
    return Frame({n: view(a, k) for n, a in frame.layers.items()}, dict(frame.meta))


def _gap(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_views_round_trip_every_element_of_the_group():
    a = np.arange(5 * 7 * 3, dtype=np.float32).reshape(5, 7, 3)
    seen = set()
    for k in range(8):
        v = view(a, k)
        np.testing.assert_array_equal(unview(v, k), a)
        seen.add(v.tobytes() + bytes(v.shape))
    assert len(seen) == 8  # eight different views


@pytest.mark.parametrize("views, mirrors", [(8, (1, 2, 4, 5, 7)), (4, (1, 2, 3))])
def test_the_ensemble_is_invariant_to_the_mirrors_it_averages(frame, views, mirrors):
    """With all 8 views the result does not depend on how the frame is mirrored or transposed; with 4, on how it
    is flipped. A single view does depend on it (the network is not equivariant), so the property is the
    ensemble's, not the denoiser's."""
    base = denoise(frame, views=views)
    single = denoise(frame)
    for k in mirrors:
        mirrored = unview(denoise(_viewed(frame, k), views=views), k)
        assert _gap(mirrored, base) < 1e-5, k
        assert _gap(unview(denoise(_viewed(frame, k)), k), single) > 1e-3, k


def test_tiled_equals_untiled_with_views(frame):
    whole = denoise(frame, views=2, tile=None)
    tiled = denoise(frame, views=2, tile=16)
    assert _gap(tiled, whole) < 1e-5


def test_light_groups_still_add_up_to_the_colour(mi):
    from kpcn.render.groups import render_light_groups

    groups = render_light_groups("test:textured", spp=8, seed=1, resolution=SIZE)
    names = groups.meta["lightGroups"].split(",")
    out = denoise(groups, layers=names, views=4)
    total = sum(out[n] for n in names)
    np.testing.assert_allclose(total, out["color"], rtol=1e-4, atol=1e-5)


def test_the_output_file_holds_the_mean_and_the_stats_count_the_views(frame, tmp_path, monkeypatch):
    import kpcn.inference.pipeline as pipeline

    inner, calls = pipeline.denoise_result, []

    def spy(*a, **kw):  # every view's own call, and the seconds it reports
        out = inner(*a, **kw)
        calls.append(out.stats.seconds)
        return out

    monkeypatch.setattr(pipeline, "denoise_result", spy)
    src = tmp_path / "noisy.exr"
    write_exr(src, frame.layers, {"spp": 4})
    res = denoise_result(src, out_path=tmp_path / "clean.exr", views=2)
    assert res.stats.views == 2 and "mean of 2 mirrored views" in res.stats.summary()
    assert len(calls) == 2 and res.stats.seconds == pytest.approx(sum(calls))  # both views' times, summed
    np.testing.assert_allclose(read_exr(tmp_path / "clean.exr")["color"], res.color, rtol=0, atol=0)
    one = denoise_result(src)
    assert _gap(res.color, one.color) > 1e-4  # the second view changed the result


def test_bad_views_and_an_output_over_the_input_are_refused(frame, tmp_path):
    for bad in (0, 3, 16, True):
        with pytest.raises(ValueError, match="1, 2, 4, 8"):
            denoise(frame, views=bad)
    src = tmp_path / "noisy.exr"
    write_exr(src, frame.layers, {})
    before = src.read_bytes()
    with pytest.raises(ValueError):
        denoise(src, out_path=src, views=2)
    assert src.read_bytes() == before
    with pytest.raises(SystemExit):
        cli_main([str(src), "-o", str(tmp_path / "out.exr"), "--views", "3"])
    assert not (tmp_path / "out.exr").exists()


def test_report_model_specs_take_views():
    assert split_views("unet_kpcn@8") == ("unet_kpcn", 8)
    assert split_views("results/a@b/model.safetensors") == ("results/a@b/model.safetensors", 1)
    assert split_views("unet_kpcn:wide64e") == ("unet_kpcn:wide64e", 1)
    with pytest.raises(ValueError, match="1, 2, 4 or 8"):
        split_views("unet_kpcn@3")
