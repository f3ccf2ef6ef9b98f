"""A training run's folder is safe: a new run never destroys an earlier one, ``--resume`` checks before it
writes and survives a damaged ``latest.pt``, and every user mistake is one line and exit code 2."""
from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from kpcn.checkpoint import CheckpointError, load_train_state, read_weights
from kpcn.config import ConfigError, load_config
from kpcn.train import train
from kpcn.train_config import RunConfig

TINY = ["data.patch_size=24", "data.patches_per_frame=8", "data.val_scenes=1", "model.layers=3", "model.width=8",
        "model.kernel_size=5", "train.batch_size=4", "train.lr=3e-3", "train.log_every=1", "train.val_every=1000",
        "train.threads=1"]
PROG = "python -m kpcn.train: "


def make_cfg(root, tmp_path, name, *sets) -> RunConfig:
    return load_config(RunConfig, None, [f"data.root={root}", f"name={name}", f"results_dir={tmp_path}", *TINY, *sets])


def cli(root, tmp_path, name, *args, sets=(), timeout=180):
    cmd = [sys.executable, "-m", "kpcn.train", "--no-progress", "--name", name, "--results-dir", str(tmp_path),
           "--set", f"data.root={root}"]
    for s in (*TINY, *sets):
        cmd += ["--set", s]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    return subprocess.run(cmd + list(args), env=env, capture_output=True, text=True, timeout=timeout)


def one_line_error(r) -> str:
    """The single error line of a failed command (exit code 2, no traceback)."""
    assert r.returncode == 2, (r.returncode, r.stdout[-2000:], r.stderr[-3000:])
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith(PROG)]
    assert len(errors) == 1, r.stderr[-3000:]
    return errors[0]


def snapshot(folder) -> dict:
    """Every file under ``folder``: its content digest and modification time."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(folder))] = (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
    return out


def metric_steps(run) -> list[int]:
    return [json.loads(x)["step"] for x in (run / "metrics.jsonl").read_text().splitlines()]


# ----------------------------------------------------------------------------- 1. a new run never destroys an old one


def test_new_run_refuses_an_existing_run_folder_and_overwrite_replaces_it(tiny_dataset, tmp_path):
    first = ["train.stage1_steps=4", "train.stage2_steps=2", "train.ckpt_every=3", "train.val_every=3"]
    train(make_cfg(tiny_dataset, tmp_path, "r", *first), progress=False)
    run = tmp_path / "r"
    assert metric_steps(run) == [3, 6]
    before = snapshot(run)

    second = ["train.stage1_steps=2", "train.stage2_steps=0", "train.ckpt_every=1", "train.val_every=1"]
    with pytest.raises(ValueError) as err:
        train(make_cfg(tiny_dataset, tmp_path, "r", *second), progress=False)
    msg = str(err.value)
    assert str(run) in msg and "--resume" in msg and "--overwrite" in msg and "--name" in msg, msg
    assert snapshot(run) == before, "a refused run must not touch the earlier run's files"
    # --resume and --overwrite contradict each other
    with pytest.raises(ValueError, match="--overwrite"):
        train(make_cfg(tiny_dataset, tmp_path, "r", *second), progress=False, resume=True, overwrite=True)
    assert snapshot(run) == before

    # the command line: one line, exit code 2, nothing touched
    line = one_line_error(cli(tiny_dataset, tmp_path, "r", sets=second))
    assert str(run) in line and "--resume" in line and "--overwrite" in line and "--name" in line, line
    assert snapshot(run) == before

    # --overwrite replaces the run: nothing of the old one is left to mix with the new one
    r = cli(tiny_dataset, tmp_path, "r", "--overwrite", sets=second)
    assert r.returncode == 0, r.stderr[-3000:]
    assert metric_steps(run) == [1, 2]
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["latest.pt", "step_1.pt", "step_2.pt"]
    assert read_weights(run / "model.safetensors")[0]["step"] == 2
    assert load_config(RunConfig, run / "config.yaml").train.stage1_steps == 2
    assert len([p for p in (run / "tb").iterdir() if p.name.startswith("events")]) == 1


def test_overwrite_through_the_python_api(tiny_dataset, tmp_path):
    cfg = make_cfg(tiny_dataset, tmp_path, "o", "train.stage1_steps=3", "train.stage2_steps=0", "train.ckpt_every=3",
                   "train.val_every=3")
    train(cfg, progress=False)
    (tmp_path / "o" / "notes.txt").write_text("mine")  # not kpcn's: left alone
    out = train(cfg, progress=False, overwrite=True)
    assert out["step"] == 3 and metric_steps(tmp_path / "o") == [3]
    assert (tmp_path / "o" / "notes.txt").read_text() == "mine"


# ----------------------------------------------------------------------------- 2. --resume checks before it writes


def test_resume_with_another_model_is_refused_before_anything_is_written(tiny_dataset, tmp_path, caplog):
    sets = ["train.stage1_steps=3", "train.stage2_steps=0", "train.ckpt_every=3"]
    train(make_cfg(tiny_dataset, tmp_path, "a", *sets), progress=False)
    run = tmp_path / "a"
    before = snapshot(run)
    for change, words in [("model.width=16", "model.width: 8 in the checkpoint, 16"),
                          ("model.padding_mode=zeros", "model.padding_mode: 'replicate' in the checkpoint, 'zeros'")]:
        with pytest.raises(ValueError) as err:
            train(make_cfg(tiny_dataset, tmp_path, "a", *sets, change), resume=True, progress=False)
        assert words in str(err.value) and "latest.pt" in str(err.value), str(err.value)
        assert snapshot(run) == before, f"{change}: a refused resume must write nothing"
    line = one_line_error(cli(tiny_dataset, tmp_path, "a", "--resume", sets=[*sets, "model.width=16"]))
    assert "model.width: 8 in the checkpoint, 16" in line, line
    assert snapshot(run) == before
    # other settings may change; the changes are logged
    caplog.set_level(logging.INFO, logger="kpcn.train")
    out = train(make_cfg(tiny_dataset, tmp_path, "a", "train.stage1_steps=3", "train.stage2_steps=2",
                         "train.ckpt_every=3"), resume=True, progress=False)
    assert out["step"] == 5 and len(out["losses"]) == 2
    assert any("train.stage2_steps: 0 -> 2" in r.getMessage() for r in caplog.records), caplog.text


# ----------------------------------------------------------------------------- 3. damaged checkpoints


def test_resume_falls_back_to_the_newest_readable_step_checkpoint(tiny_dataset, tmp_path, caplog):
    sets = ["train.stage1_steps=4", "train.ckpt_every=2", "train.val_every=2", "train.keep_checkpoints=2"]
    full = train(make_cfg(tiny_dataset, tmp_path, "full", *sets, "train.stage2_steps=4"), progress=False)
    train(make_cfg(tiny_dataset, tmp_path, "part", *sets, "train.stage2_steps=2"), progress=False)
    ck = tmp_path / "part" / "checkpoints"
    # the last K step checkpoints are kept, next to latest.pt
    assert sorted(p.name for p in ck.iterdir()) == ["latest.pt", "step_4.pt", "step_6.pt"]
    assert load_train_state(ck / "step_4.pt")["step"] == 4
    assert load_train_state(ck / "step_6.pt")["step"] == load_train_state(ck / "latest.pt")["step"] == 6
    (ck / "latest.pt").write_bytes(b"")  # an interrupted copy
    data = (ck / "step_6.pt").read_bytes()
    (ck / "step_6.pt").write_bytes(data[: len(data) // 3])  # truncated
    caplog.set_level(logging.INFO, logger="kpcn.train")
    resumed = train(make_cfg(tiny_dataset, tmp_path, "part", *sets, "train.stage2_steps=4"), resume=True,
                    progress=False)
    text = caplog.text
    assert "step_4.pt" in text and "latest.pt" in text and "empty" in text, text
    np.testing.assert_allclose(resumed["losses"], full["losses"][4:], rtol=1e-5)
    a = read_weights(tmp_path / "full" / "model.safetensors")[1]
    b = read_weights(tmp_path / "part" / "model.safetensors")[1]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)
    # the validation lines of the abandoned steps are gone: one line per step
    assert metric_steps(tmp_path / "part") == [2, 4, 6, 8]
    assert load_train_state(ck / "latest.pt")["step"] == 8


def test_resume_with_no_readable_checkpoint_is_one_line_naming_them(tiny_dataset, tmp_path):
    sets = ["train.stage1_steps=4", "train.stage2_steps=0", "train.ckpt_every=2"]
    train(make_cfg(tiny_dataset, tmp_path, "b", *sets), progress=False)
    ck = tmp_path / "b" / "checkpoints"
    assert sorted(p.name for p in ck.iterdir()) == ["latest.pt", "step_2.pt", "step_4.pt"]
    for p in ck.iterdir():
        p.write_bytes(b"\x00not a checkpoint" * 4)
    (ck / "latest.pt").write_bytes(b"")
    before = snapshot(tmp_path / "b")
    with pytest.raises(CheckpointError) as err:
        train(make_cfg(tiny_dataset, tmp_path, "b", *sets), resume=True, progress=False)
    msg = str(err.value)
    assert "\n" not in msg and all(n in msg for n in ("latest.pt", "step_2.pt", "step_4.pt")), msg
    line = one_line_error(cli(tiny_dataset, tmp_path, "b", "--resume", sets=sets))
    assert all(n in line for n in ("latest.pt", "step_2.pt", "step_4.pt")), line
    assert snapshot(tmp_path / "b") == before


# ----------------------------------------------------------------------------- 4. user mistakes: one line, exit code 2


@pytest.mark.parametrize("assignment, message", [
    ("train.ckpt_every=0", "train.ckpt_every: must be >= 1, got 0"),
    ("train.val_every=0", "train.val_every: must be >= 1, got 0"),
    ("train.log_every=-1", "train.log_every: must be >= 1, got -1"),
    ("train.batch_size=0", "train.batch_size: must be >= 1, got 0"),
    ("train.stage1_steps=-1", "train.stage1_steps: must be >= 0, got -1"),
    ("train.stage2_steps=-10", "train.stage2_steps: must be >= 0, got -10"),
    ("train.lr=-1e-3", "train.lr: must be a number > 0, got -0.001"),
    ("train.lr=.nan", "train.lr: must be a number > 0, got nan"),
    ("train.stage2_lr=0", "train.stage2_lr: must be a number > 0, got 0.0"),
    ("train.grad_clip=-1", "train.grad_clip: must be >= 0 (0: off), got -1.0"),
    ("train.keep_checkpoints=-1", "train.keep_checkpoints: must be >= 0, got -1"),
    ("train.threads=0", "train.threads: must be >= 1, got 0"),
    ("train.seed=-3", "train.seed: must be >= 0, got -3"),
    ("train.device=gpu", "train.device: expected auto, cpu, cuda or cuda:<index>, got 'gpu'"),
    ("data.patch_size=0", "data.patch_size: must be >= 1, got 0"),
    ("data.patches_per_frame=0", "data.patches_per_frame: must be >= 1, got 0"),
    ("data.val_scenes=-1", "data.val_scenes: must be >= 0, got -1"),
    ("data.spp=[]", "data.spp: must list at least one sample count (null: all)"),
    ("data.spp=[0, 4]", "data.spp: every sample count must be >= 1, got [0, 4]"),
    ("data.converged_max_noise=0", "data.converged_max_noise: must be a number > 0, got 0"),
    ("data.render_scenes=0", "data.render_scenes: must be >= 1, got 0"),
    ("data.render_spp=[1, 4]", "data.render_spp: every sample count must be >= 2, got [1, 4]"),
    ("data.render_ref_spp=1", "data.render_ref_spp: must be >= 2, got 1"),
    ("data.render_resolution=[0, 64]", "data.render_resolution: expected [width, height] >= 1, got [0, 64]"),
    ("name=..", "name: must be a folder name under results_dir"),
])
def test_bad_values_are_config_errors_naming_the_key(assignment, message):
    with pytest.raises(ConfigError) as err:
        load_config(RunConfig, None, [assignment])
    assert message in str(err.value), str(err.value)


def test_no_steps_at_all_is_an_error():
    with pytest.raises(ConfigError, match=r"train.stage1_steps \+ train.stage2_steps: must be >= 1"):
        load_config(RunConfig, None, ["train.stage1_steps=0", "train.stage2_steps=0"])


def test_values_set_after_loading_are_checked_by_train(tiny_dataset, tmp_path):
    cfg = make_cfg(tiny_dataset, tmp_path, "late")
    cfg.train.ckpt_every = 0  # bypasses __post_init__
    with pytest.raises(ConfigError, match="train.ckpt_every: must be >= 1, got 0"):
        train(cfg, progress=False)
    assert not (tmp_path / "late").exists()


@pytest.mark.parametrize("sets, words", [
    (["train.ckpt_every=0"], "train.ckpt_every: must be >= 1, got 0"),
    (["train.batch_size=0"], "train.batch_size: must be >= 1, got 0"),
    (["train.stage1_steps=ten"], "train.stage1_steps: expected an integer, got 'ten'"),
    (["train.stage1_steps=2", "train.stage2_steps=0", "train.batch_size=1000"], "train.batch_size: 1000"),
    (["train.stage1_steps=2", "train.stage2_steps=0", "data.spp=[3]"], "3 spp"),
    (["train.stage1_steps=2", "train.stage2_steps=0", "data.val_root=/nonexistent/val"], "/nonexistent/val"),
])
def test_cli_user_mistakes_are_one_line_and_write_nothing(tiny_dataset, tmp_path, sets, words):
    line = one_line_error(cli(tiny_dataset, tmp_path, "m", sets=sets, timeout=120))
    assert words in line, line
    assert not (tmp_path / "m").exists(), "nothing may be written for a mistake"


def test_missing_data_set_is_rendered_once_and_an_empty_run_folder_is_fine(tmp_path):
    """data.root without a data set: kpcn.render.ensure_dataset renders the data.render_* one, once."""
    root = tmp_path / "rendered"
    sets = [f"data.root={root}", "data.render_scenes=2", "data.render_spp=[2]", "data.render_ref_spp=4",
            "data.render_resolution=[24, 24]", "data.render_first_seed=5", "data.patch_size=16",
            "data.patches_per_frame=4", "data.val_scenes=1", "model.layers=2", "model.width=4",
            "model.kernel_size=3", "train.batch_size=2", "train.stage1_steps=1", "train.stage2_steps=0",
            "train.threads=1", f"results_dir={tmp_path}"]
    (tmp_path / "one").mkdir()  # an empty run folder holds no run
    train(load_config(RunConfig, None, [*sets, "name=one"]), progress=False)
    manifest = json.loads((root / "manifest.json").read_text())
    assert manifest["complete"] is True and len(manifest["scenes"]) == 2
    frames = {p: p.stat().st_mtime_ns for p in root.rglob("*.exr")}
    train(load_config(RunConfig, None, [*sets, "name=two"]), progress=False)
    assert {p: p.stat().st_mtime_ns for p in root.rglob("*.exr")} == frames, "the data set was rendered again"


def test_cli_missing_data_set_is_one_line(tmp_path):
    missing = tmp_path / "no_data"
    line = one_line_error(cli(missing, tmp_path, "m", sets=["data.render_if_missing=false"], timeout=120))
    assert str(missing) in line, line
    assert not (tmp_path / "m").exists()


def test_cli_debug_shows_the_traceback(tiny_dataset, tmp_path):
    r = cli(tiny_dataset, tmp_path, "m", "--debug", sets=["train.ckpt_every=0"])
    assert r.returncode != 0 and "Traceback" in r.stderr and "train.ckpt_every: must be >= 1" in r.stderr


# ----------------------------------------------------------------------------- 5. untrusted pickles


class _Evil:
    """Unpickling this runs code: it writes a marker file."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (exec, (f"open({self.marker!r}, 'w').write('pwned')",))


def test_resume_refuses_a_pickle_that_would_run_code(tiny_dataset, tmp_path):
    marker = tmp_path / "marker"
    latest = tmp_path / "evil" / "checkpoints" / "latest.pt"
    latest.parent.mkdir(parents=True)
    torch.save({"format": "kpcn-train-state/1", "model": {}, "optimizer": None, "step": 1, "rng": {},
                "config": {}, "payload": _Evil(marker)}, latest)
    line = one_line_error(cli(tiny_dataset, tmp_path, "evil", "--resume"))
    assert "latest.pt" in line and "--trust-checkpoint" in line, line
    assert not marker.exists(), "the checkpoint's code ran"
    # the file is a real threat: full unpickling runs it
    torch.load(latest, weights_only=False)
    assert marker.read_text() == "pwned"


# ----------------------------------------------------------------------------- torchrun


def test_torchrun_refuses_an_existing_run_folder_without_hanging(tiny_dataset, tmp_path):
    run = tmp_path / "ddp"
    run.mkdir()
    (run / "config.yaml").write_text("name: ddp\n")
    before = snapshot(run)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_port=29547",
           "-m", "kpcn.train", "--no-progress", "--name", "ddp", "--results-dir", str(tmp_path),
           "--set", f"data.root={tiny_dataset}", "--set", "train.stage1_steps=2", "--set", "train.stage2_steps=0"]
    for s in TINY:
        cmd += ["--set", s]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    assert r.returncode != 0
    assert f"{PROG}{run}" in r.stderr and "--overwrite" in r.stderr, r.stderr[-3000:]
    assert snapshot(run) == before
