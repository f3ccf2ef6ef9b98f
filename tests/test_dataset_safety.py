"""Data sets know whether they are complete and what each frame was rendered with; the render CLI
refuses bad options in one line before it renders or writes anything. Tiny real renders (8x8-12x12)."""
import json
import logging
import os
import subprocess
import sys

import numpy as np
import pytest

from kpcn.data import read_manifest
from kpcn.integrator import ALBEDO_REVISION, NORMAL_REVISION
from kpcn.io import read_exr, write_exr
from kpcn.render import dataset as dataset_mod
from kpcn.render import render_dataset

SMALL = dict(spp_list=(2,), ref_spp=4, resolution=(8, 8), first_seed=0, progress=False)


def frame_files(root):
    return sorted(p for p in root.rglob("*.exr") if not p.name.startswith("."))


def mtimes(paths):
    return [p.stat().st_mtime_ns for p in paths]


class Interrupt(KeyboardInterrupt):
    pass


def counting_render(monkeypatch, fail_at=None):
    """Count the frames render_dataset writes; raise (as Ctrl-C would) at call number ``fail_at``."""
    real = dataset_mod.render_to_exr
    calls = []

    def wrapper(scene, out, spp, *a, **kw):
        calls.append((str(scene), os.fspath(out), spp))
        if fail_at is not None and len(calls) == fail_at:
            raise Interrupt("simulated kill")
        return real(scene, out, spp, *a, **kw)

    monkeypatch.setattr(dataset_mod, "render_to_exr", wrapper)
    return calls


# ----------------------------------------------------------------------------- 1. completeness


@pytest.fixture
def interrupted(mi, tmp_path, monkeypatch):
    """A 2-scene data set killed while rendering its second scene (after scene 0's two frames)."""
    root = tmp_path / "data"
    counting_render(monkeypatch, fail_at=3)
    with pytest.raises(Interrupt):
        render_dataset(root, 2, **SMALL)
    monkeypatch.undo()
    return root


def test_interrupted_dataset_is_refused_by_read_manifest(interrupted):
    manifest = json.loads((interrupted / "manifest.json").read_text())
    assert manifest.get("complete") is False
    with pytest.raises(ValueError) as err:
        read_manifest(interrupted)
    msg = str(err.value)
    assert str(interrupted) in msg and "1 of 2 scenes rendered" in msg
    assert f"python -m kpcn.render dataset --out {interrupted}" in msg and "--scenes 2" in msg


def test_ensure_dataset_resumes_an_interrupted_dataset(interrupted, monkeypatch):
    from kpcn.render import DatasetError, ensure_dataset

    args = (interrupted, 2, [2], 4, (8, 8), 0)
    with pytest.raises(DatasetError) as err:
        ensure_dataset(*args, render_if_missing=False, progress=False)
    assert isinstance(err.value, ValueError)
    assert str(interrupted) in str(err.value) and "1 of 2 scenes rendered" in str(err.value)

    done = frame_files(interrupted)
    assert len(done) == 2  # scene 0: input and reference
    before = mtimes(done)
    calls = counting_render(monkeypatch)
    assert ensure_dataset(*args, progress=False) == interrupted
    assert [c[1] for c in calls] == [str(interrupted / "random_1" / n) for n in ("input_2spp.exr", "reference.exr")]
    assert mtimes(done) == before, "finished frames must be kept"
    manifest = json.loads((interrupted / "manifest.json").read_text())
    assert manifest["complete"] is True and len(manifest["scenes"]) == 2
    assert len(read_manifest(interrupted)) == 2

    calls.clear()  # complete and matching: returns without rendering
    assert ensure_dataset(*args, render_if_missing=False, progress=False) == interrupted
    assert ensure_dataset(*args, progress=False) == interrupted
    assert calls == []


def test_ensure_dataset_renders_a_missing_one_and_refuses_other_settings(mi, tmp_path, monkeypatch):
    from kpcn.render import DatasetError, ensure_dataset

    root = tmp_path / "d"
    with pytest.raises(DatasetError, match="no data set"):
        ensure_dataset(root, 1, [2], 4, (8, 8), 0, render_if_missing=False, progress=False)
    assert not (root / "manifest.json").exists()
    assert ensure_dataset(root, 1, [2], 4, (8, 8), 0, progress=False) == root
    assert len(read_manifest(root)) == 1
    calls = counting_render(monkeypatch)
    # a complete data set with other settings is neither trained on nor silently overwritten
    for flag in (False, True):
        with pytest.raises(DatasetError) as err:
            ensure_dataset(root, 1, [2], 4, (12, 12), 0, render_if_missing=flag, progress=False)
        assert str(root) in str(err.value) and "resolution" in str(err.value) and "12x12" in str(err.value)
    with pytest.raises(DatasetError, match="scenes"):
        ensure_dataset(root, 3, [2], 4, (8, 8), 0, render_if_missing=False, progress=False)
    assert calls == []


def test_a_fresh_data_set_renders_without_openexr_errors(mi, tmp_path, capfd):
    # the reuse checks of frames not yet rendered had OpenEXR print "Unable to open file for read" (at file
    # descriptor level, past Python's sys.stderr) twice for each frame of a new data set
    render_dataset(tmp_path / "d", 1, **SMALL)
    assert len(frame_files(tmp_path / "d")) == 2
    err = capfd.readouterr().err
    assert "EXR_ERR" not in err and "Unable to open" not in err, err


def test_legacy_manifest_readable_only_when_its_files_exist(mi, tmp_path):
    root = tmp_path / "old"
    render_dataset(root, 1, **SMALL)
    m = json.loads((root / "manifest.json").read_text())
    legacy = {"ref_spp": m["ref_spp"], "spp": m["spp"], "resolution": m["resolution"],
              "scenes": [{k: sc[k] for k in ("name", "source", "seed", "inputs", "reference")} for sc in m["scenes"]]}
    (root / "manifest.json").write_text(json.dumps(legacy))
    with pytest.warns(UserWarning, match="complete"):
        assert len(read_manifest(root)) == 1
    (root / legacy["scenes"][0]["reference"]).unlink()
    with pytest.raises(ValueError, match="reference.exr"):
        read_manifest(root)


def test_ensure_dataset_resumes_a_legacy_manifest_of_fewer_scenes(mi, tmp_path, monkeypatch):
    from kpcn.render import DatasetError, ensure_dataset

    root = tmp_path / "old"
    render_dataset(root, 1, **SMALL)
    m = json.loads((root / "manifest.json").read_text())
    legacy = {k: m[k] for k in ("ref_spp", "spp", "resolution")}
    legacy["scenes"] = [{k: sc[k] for k in ("name", "source", "seed", "inputs", "reference")} for sc in m["scenes"]]
    (root / "manifest.json").write_text(json.dumps(legacy))
    with pytest.raises(DatasetError, match="1 of 2 scenes rendered"):  # an old interrupted render
        ensure_dataset(root, 2, [2], 4, (8, 8), 0, render_if_missing=False, progress=False)
    calls = counting_render(monkeypatch)
    ensure_dataset(root, 2, [2], 4, (8, 8), 0, progress=False)
    # only scene 1: scene 0's frames carry matching render records
    assert [c[1] for c in calls] == [str(root / "random_1" / n) for n in ("input_2spp.exr", "reference.exr")]
    assert json.loads((root / "manifest.json").read_text())["complete"] is True


# ----------------------------------------------------------------------------- 2. stale frames


def test_new_settings_rerender_every_stale_frame(mi, tmp_path, caplog):
    root = tmp_path / "data"
    render_dataset(root, 1, spp_list=(2,), ref_spp=4, resolution=(8, 8), first_seed=0, progress=False)
    with caplog.at_level(logging.INFO, logger="kpcn.render"):
        render_dataset(root, 1, spp_list=(2,), ref_spp=8, resolution=(12, 12), first_seed=0, progress=False)
    files = frame_files(root)
    assert len(files) == 2
    for p in files:
        f = read_exr(p)
        assert f.shape == (12, 12), p
        assert f.meta["spp"] == (8 if p.name == "reference.exr" else 2)
    m = json.loads((root / "manifest.json").read_text())
    assert m["complete"] is True and m["resolution"] == [12, 12] and m["ref_spp"] == 8
    frames = m["scenes"][0]["frames"]
    assert {r["resolution"][0] for r in frames.values()} == {12}
    assert frames["random_0/reference.exr"]["spp"] == 8
    rerendered = [r.getMessage() for r in caplog.records if "re-render" in r.getMessage()]
    assert len(rerendered) == 2 and any("8x8" in m and "12x12" in m for m in rerendered)


def test_only_frames_whose_record_differs_are_rerendered(mi, tmp_path, monkeypatch):
    root = tmp_path / "data"
    render_dataset(root, 1, **SMALL)
    inp, ref = root / "random_0" / "input_2spp.exr", root / "random_0" / "reference.exr"
    before = mtimes([inp])
    calls = counting_render(monkeypatch)
    render_dataset(root, 1, **{**SMALL, "ref_spp": 3})  # fewer samples than it has: rendered again
    assert [c[1] for c in calls] == [str(ref)] and mtimes([inp]) == before
    assert read_exr(ref).meta["spp"] == 3

    # a frame without a record (another tool, an older kpcn) is not trusted
    f = read_exr(inp)
    write_exr(inp, f.layers, {k: f.meta[k] for k in ("spp", "seed", "scene")})
    calls.clear()
    render_dataset(root, 1, **{**SMALL, "ref_spp": 3})
    assert [c[1] for c in calls] == [str(inp)]


def test_a_reference_given_more_samples_keeps_its_own(mi, tmp_path, monkeypatch, caplog):
    """A larger ref_spp for a data set whose references differ only in spp: each reference keeps its samples and
    gets the following passes (kpcn.render.extend_frame), so an upgrade costs only the samples added; the inputs
    are untouched and the records and manifest say the new spp."""
    from kpcn.render import merge_frames, render_frame
    from kpcn.render.record import read_record

    root = tmp_path / "data"
    render_dataset(root, 1, **SMALL)
    inp, ref = root / "random_0" / "input_2spp.exr", root / "random_0" / "reference.exr"
    before, old = mtimes([inp]), read_exr(ref)
    calls = counting_render(monkeypatch)
    with caplog.at_level(logging.INFO, logger="kpcn.render"):
        render_dataset(root, 1, **{**SMALL, "ref_spp": 12})
    assert calls == [] and mtimes([inp]) == before
    assert any("adding 8 samples" in r.getMessage() and "4 -> 12 spp" in r.getMessage() for r in caplog.records)
    new = read_exr(ref)
    assert new.spp == 12 and read_record(ref)[0]["spp"] == 12
    # its first 4 samples are the old reference's: the mean of it and the next passes (seed 0, role 1, from pass 1)
    rest = render_frame("random:0", 8, 0, (8, 8), role=1, first_pass=1)
    want = merge_frames(old, rest)
    np.testing.assert_allclose(new["color"], want["color"], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(new["colorVariance"], want["colorVariance"], rtol=1e-3, atol=1e-8)
    assert not np.allclose(new["color"], old["color"])
    m = json.loads((root / "manifest.json").read_text())
    assert m["complete"] is True and m["ref_spp"] == 12
    assert m["scenes"][0]["frames"]["random_0/reference.exr"]["spp"] == 12
    calls.clear()
    render_dataset(root, 1, **{**SMALL, "ref_spp": 12})  # up to date: nothing rendered or extended
    assert calls == [] and read_exr(ref).meta["renderTimeSeconds"] == new.meta["renderTimeSeconds"]


def as_older_revision(root, key, value):
    """Rewrite every frame of the data set at ``root`` (and its manifest) as revision 1 of the ``key`` layer
    (``"albedo"`` or ``"normal"``) wrote it: no ``key`` in the records, no ``<key>Revision`` in the headers, the
    layer replaced by ``value(frame)``. Returns ``{path: the frame as it was}``."""
    from kpcn.render.record import HEADER_KEY, read_record

    fresh = {p: read_exr(p) for p in frame_files(root)}
    for p, f in fresh.items():
        rec = read_record(p)[0]
        del rec[key]
        meta = {k: v for k, v in f.meta.items() if k in ("spp", "renderTimeSeconds", "seed", "scene",
                                                           "albedoRevision", "normalRevision")}
        del meta[f"{key}Revision"]
        write_exr(p, {**f.layers, key: value(f)}, {**meta, HEADER_KEY: json.dumps(rec, sort_keys=True)})
    # the manifest's records too; training names the command that updates them
    m = json.loads((root / "manifest.json").read_text())
    for rec in m["scenes"][0]["frames"].values():
        del rec[key]
    (root / "manifest.json").write_text(json.dumps(m))
    return fresh


def test_frames_of_an_older_albedo_revision_get_their_albedo_only(mi, tmp_path, monkeypatch, caplog):
    """A data set rendered before albedo revision 2: its frames keep their radiance bit for bit, their albedo
    layers become what a fresh render writes, without a full render of any frame."""
    from kpcn.render.record import read_record
    from kpcn.train_data import warn_outdated_albedo

    root = tmp_path / "data"
    render_dataset(root, 1, **{**SMALL, "first_seed": 3})
    files = frame_files(root)
    fresh = as_older_revision(root, "albedo", lambda f: f["albedo"] * 7 + 0.5)

    with caplog.at_level(logging.WARNING, logger="kpcn.train"):
        assert warn_outdated_albedo([root]) == 2
    assert any("2 of 2 frames have albedo revision 1" in r.getMessage() and "kpcn.render dataset" in r.getMessage()
               for r in caplog.records)
    calls = counting_render(monkeypatch)
    with caplog.at_level(logging.INFO, logger="kpcn.render"):
        render_dataset(root, 1, **{**SMALL, "first_seed": 3})
    assert calls == [] and warn_outdated_albedo([root]) == 0  # no frame rendered in full
    assert sum("updating the albedo" in r.getMessage() for r in caplog.records) == len(files) == 2
    for p, f in fresh.items():
        g = read_exr(p)
        assert g.meta["albedoRevision"] == ALBEDO_REVISION and read_record(p)[0]["albedo"] == ALBEDO_REVISION
        for name in ("albedo", "albedoVariance", "color", "colorVariance", "diffuse", "specular", "normal", "depth"):
            assert np.array_equal(g[name], f[name]), (p.name, name)
    m = json.loads((root / "manifest.json").read_text())
    assert m["complete"] is True and all(r["albedo"] == 2 for r in m["scenes"][0]["frames"].values())
    # up to date now: nothing is touched
    before = mtimes(files)
    render_dataset(root, 1, **{**SMALL, "first_seed": 3})
    assert mtimes(files) == before and calls == []


def test_changed_scene_generator_rerenders(mi, tmp_path, monkeypatch):
    from kpcn import scenes

    root = tmp_path / "data"
    render_dataset(root, 1, **SMALL)
    real = scenes.random_scene

    def changed(seed, resolution=(128, 128)):
        d = real(seed, resolution)
        d["kpcn_test_extra_light"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.1, 0.2, 0.3]}}
        return d

    monkeypatch.setattr(scenes, "random_scene", changed)
    calls = counting_render(monkeypatch)
    render_dataset(root, 1, **SMALL)
    assert len(calls) == 2, "frames of a scene the generator now makes differently must be re-rendered"


# ----------------------------------------------------------------------------- 3. the command line


def run_cli(*args, cwd):
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "kpcn.render", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env)


BAD_FRAME = [
    (["--spp", "0"], "--spp"),
    (["--spp", "-4"], "--spp"),
    (["--spp", "1"], "--spp"),
    (["--resolution", "0", "0"], "--resolution"),
    (["--resolution", "8", "-1"], "--resolution"),
    (["--ref-spp", "1"], "--ref-spp"),
    (["--ref-spp", "-8"], "--ref-spp"),
    (["--max-depth", "0"], "--max-depth"),
    (["--seed", "-1"], "--seed"),
]


@pytest.mark.parametrize("extra,option", BAD_FRAME, ids=[" ".join(a) for a, _ in BAD_FRAME])
def test_cli_frame_bad_option_is_one_line_exit_2_and_writes_nothing(tmp_path, extra, option):
    # a repeated flag: argparse keeps the last value, so `extra` overrides the valid defaults
    args = ["frame", "test:glass", "--spp", "4", "--resolution", "8", "8", "--out", tmp_path / "n.exr"]
    r = run_cli(*args, *extra, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and option in lines[0], r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


BAD_SCENES = ["missing.xml", "broken.xml", "nomesh.xml", "test:nope", "random:abc"]


@pytest.mark.parametrize("scene", BAD_SCENES)
def test_cli_bad_scene_is_one_line(mi, tmp_path, scene):
    (tmp_path / "broken.xml").write_text('<scene version="3.0.0">\n  <shape type="sphere">\n</scene>\n')
    (tmp_path / "nomesh.xml").write_text(
        '<scene version="3.0.0"><sensor type="perspective"/>'
        '<shape type="ply"><string name="filename" value="meshes/gone.ply"/></shape></scene>')
    r = run_cli("frame", scene, "--spp", "4", "--resolution", "8", "8", "--out", "n.exr", "--ref-spp", "8", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1 and scene.split(".")[0] in errors[0], r.stderr
    assert not (tmp_path / "n.exr").exists() and not (tmp_path / "n_ref.exr").exists()


def test_cli_debug_shows_the_traceback(tmp_path):
    r = run_cli("frame", "test:glass", "--spp", "0", "--out", tmp_path / "n.exr", "--debug", cwd=tmp_path)
    assert r.returncode != 0 and "Traceback" in r.stderr and "--spp" in r.stderr


BAD_DATASET = [
    (["--spp", "1"], "spp"),
    (["--spp", "0", "4"], "spp"),
    (["--ref-spp", "1"], "ref-spp"),
    (["--ref-spp", "0"], "ref-spp"),
    (["--resolution", "0", "0"], "resolution"),
    (["--scenes", "0"], "scenes"),
]


@pytest.mark.parametrize("extra,option", BAD_DATASET, ids=[" ".join(a) for a, _ in BAD_DATASET])
def test_cli_dataset_bad_option_is_one_line_exit_2_and_writes_nothing(tmp_path, extra, option):
    r = run_cli("dataset", "--out", tmp_path / "ds", "--scenes", "1", "--spp", "2", "--ref-spp", "4",
                "--resolution", "8", "8", *extra, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and option in lines[0], r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_cli_dataset_renders_resumes_and_reports(mi, tmp_path):
    args = ("dataset", "--out", tmp_path / "ds", "--scenes", "1", "--spp", "2", "--ref-spp", "4",
            "--resolution", "8", "8")
    r = run_cli(*args, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert len(read_manifest(tmp_path / "ds")) == 1
    r = run_cli(*args[:-2], "12", "12", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stderr.count("re-render") == 2
    assert all(read_exr(p).shape == (12, 12) for p in frame_files(tmp_path / "ds"))
    assert np.isfinite(read_exr(tmp_path / "ds" / "random_0" / "reference.exr")["color"]).all()


def test_training_names_the_revision_a_data_set_has(mi, tmp_path, caplog):
    """Frames one revision behind are named by that revision and what it lacks; every older revision has its
    description (a new revision without one would name nothing)."""
    from kpcn.train_data import _ALBEDO_BEFORE, _NORMAL_BEFORE, warn_outdated_albedo

    assert set(_ALBEDO_BEFORE) == set(range(1, ALBEDO_REVISION))
    assert set(_NORMAL_BEFORE) == set(range(1, NORMAL_REVISION))
    root = tmp_path / "data"
    render_dataset(root, 1, **{**SMALL, "first_seed": 6})
    m = json.loads((root / "manifest.json").read_text())
    for rec in m["scenes"][0]["frames"].values():
        rec["albedo"], rec["normal"] = ALBEDO_REVISION - 1, NORMAL_REVISION - 1
    (root / "manifest.json").write_text(json.dumps(m))
    with caplog.at_level(logging.WARNING, logger="kpcn.train"):
        assert warn_outdated_albedo([root]) == 2
    said = " ".join(r.getMessage() for r in caplog.records)
    for kind, rev, what in (("albedo", ALBEDO_REVISION - 1, _ALBEDO_BEFORE), ("normal", NORMAL_REVISION - 1,
                                                                                 _NORMAL_BEFORE)):
        assert f"2 of 2 frames have {kind} revision {rev} ({what[rev]})" in said, said


def test_frames_of_an_older_normal_revision_get_their_normal_only(mi, tmp_path, monkeypatch, caplog):
    """A data set rendered before normal revision 2 (the unmapped normal): training names the command that updates
    it, which re-renders the normal layers alone, as a fresh render writes them (the current revision); every other
    layer stays bit for bit."""
    from kpcn.render.record import read_record
    from kpcn.train_data import warn_outdated_albedo

    root = tmp_path / "data"
    render_dataset(root, 1, **{**SMALL, "first_seed": 5})
    files = frame_files(root)
    fresh = as_older_revision(root, "normal",
                              lambda f: np.broadcast_to([0, 1, 0], f["normal"].shape).astype(np.float32))
    with caplog.at_level(logging.WARNING, logger="kpcn.train"):
        assert warn_outdated_albedo([root]) == 2
    assert any("2 of 2 frames have normal revision 1" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="kpcn.train"):  # many data sets: three named, the rest counted
        assert warn_outdated_albedo([root] * 5) == 10
    assert sum("frames have normal revision 1" in r.getMessage() for r in caplog.records) == 3
    assert sum("2 more data sets (4 frames" in r.getMessage() for r in caplog.records) == 1
    calls = counting_render(monkeypatch)
    with caplog.at_level(logging.INFO, logger="kpcn.render"):
        render_dataset(root, 1, **{**SMALL, "first_seed": 5})
    assert calls == [] and warn_outdated_albedo([root]) == 0  # no frame rendered in full
    assert sum("updating the normal of" in r.getMessage() for r in caplog.records) == len(files) == 2
    for p, f in fresh.items():
        g = read_exr(p)
        assert g.meta["normalRevision"] == NORMAL_REVISION and read_record(p)[0]["normal"] == NORMAL_REVISION
        for name in ("normal", "normalVariance", "albedo", "color", "colorVariance", "diffuse", "specular", "depth"):
            assert np.array_equal(g[name], f[name]), (p.name, name)
