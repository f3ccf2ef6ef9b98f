"""kpcn-denoise and kpcn.denoise never write over an input, never lose an output silently,
and turn every mistake about inputs and outputs into one line (and exit code 2 on the command line).

Renders are real (Mitsuba, 16x16); the model is a tiny random-init KPCN (or the shipped default).
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from kpcn import inference as dn
from kpcn.checkpoint import save_weights
from kpcn.inference.cli import main as cli_main
from kpcn.io import read_exr, write_exr
from kpcn.models import create_model


def _tiny():
    torch.manual_seed(0)
    return create_model("kpcn", layers=2, width=4, kernel_size=3).eval()


@pytest.fixture(scope="module")
def frame(render):
    return render("test:glossy", spp=4, seed=1, resolution=(16, 16))


@pytest.fixture()
def exr(tmp_path, frame):
    """``make(path)`` writes the tiny render to ``path`` (creating folders) and returns the path."""

    def make(path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_exr(path, frame.layers, frame.meta)
        return path

    return make


@pytest.fixture()
def weights(tmp_path):
    path = tmp_path / "tiny.safetensors"
    save_weights(path, _tiny())
    return str(path)


def _never_run():
    """A tiny model whose network must not run: the call has to be refused before any denoising."""
    model = _tiny()

    def boom(*a, **k):
        raise AssertionError("denoised although the call should have been refused first")

    model.forward = boom
    return model


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one error line, got:\n{err}"
    assert "Traceback" not in err
    return lines[0]


# ----------------------------------------------------------------------------- the Python API


_VARIANTS = ["same", "dot_relative", "out_relative", "dotdot", "out_symlink_to_input", "input_symlink_to_out",
             "hardlink", "folder_symlink"]


def _aliases(variant: str, tmp_path: Path, exr, monkeypatch) -> tuple[str, str, Path]:
    """(input, out_path, the file whose bytes must survive) for one way of naming the input as the output."""
    data = tmp_path / "data"
    real = exr(data / "x.exr")
    if variant == "same":
        return str(real), str(real), real
    if variant == "dot_relative":  # ./x.exr vs the absolute path
        monkeypatch.chdir(data)
        return "./x.exr", str(real), real
    if variant == "out_relative":
        monkeypatch.chdir(data)
        return str(real), "x.exr", real
    if variant == "dotdot":
        (data / "sub").mkdir()
        return str(real), str(data / "sub" / ".." / "x.exr"), real
    if variant == "out_symlink_to_input":
        link = tmp_path / "link.exr"
        link.symlink_to(real)
        return str(real), str(link), real
    if variant == "input_symlink_to_out":
        link = tmp_path / "link.exr"
        link.symlink_to(real)
        return str(link), str(real), real
    if variant == "hardlink":
        other = tmp_path / "hard.exr"
        os.link(real, other)
        return str(real), str(other), real
    if variant == "folder_symlink":
        alias = tmp_path / "alias"
        alias.symlink_to(data, target_is_directory=True)
        return str(real), str(alias / "x.exr"), real
    raise AssertionError(variant)


@pytest.mark.parametrize("fn", ["denoise_result", "denoise"])
@pytest.mark.parametrize("variant", _VARIANTS)
def test_api_refuses_to_write_over_its_input(tmp_path, exr, monkeypatch, variant, fn):
    src, out, keep = _aliases(variant, tmp_path, exr, monkeypatch)
    before = keep.read_bytes()
    links = {p: os.readlink(p) for p in tmp_path.rglob("*") if p.is_symlink()}
    with pytest.raises(ValueError) as info:
        getattr(dn, fn)(src, _never_run(), out_path=out, tile=8, device="cpu")
    msg = str(info.value)
    assert src in msg and out in msg, msg  # names both, as the caller spelled them
    assert keep.read_bytes() == before
    assert {p: os.readlink(p) for p in tmp_path.rglob("*") if p.is_symlink()} == links  # no link replaced either
    if variant == "hardlink":
        assert os.path.samefile(src, out)  # the other name still is the input


def test_api_refuses_the_shipped_model_too(tmp_path, exr):
    # model=None (the shipped default) goes through the same check
    src = exr(tmp_path / "x.exr")
    before = src.read_bytes()
    with pytest.raises(ValueError, match="x.exr"):
        dn.denoise(src, out_path=src, device="cpu")
    assert src.read_bytes() == before


def test_api_refuses_writing_over_the_file_a_frame_was_read_from(tmp_path, exr):
    src = exr(tmp_path / "x.exr")
    before = src.read_bytes()
    with pytest.raises(ValueError, match="x.exr"):
        dn.denoise(read_exr(src), _never_run(), out_path=tmp_path / "." / "x.exr", device="cpu")
    assert src.read_bytes() == before


def test_api_refuses_an_output_that_cannot_be_a_file_before_denoising(tmp_path, exr):
    src = exr(tmp_path / "x.exr")
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(IsADirectoryError, match="folder"):
        dn.denoise(src, _never_run(), out_path=folder, device="cpu")
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder")
    with pytest.raises(NotADirectoryError, match="afile"):
        dn.denoise(src, _never_run(), out_path=blocker / "out.exr", device="cpu")
    assert _files(tmp_path) == ["afile", "folder", "x.exr"]


def test_api_still_writes_a_distinct_output_and_creates_its_folder(tmp_path, exr):
    src = exr(tmp_path / "x.exr")
    out = tmp_path / "new" / "deeper" / "x.exr"  # same name, another folder: fine
    color = dn.denoise(src, _tiny(), out_path=out, tile=8, device="cpu")
    assert (read_exr(out)["color"] == color).all()


def test_failed_denoising_leaves_no_output(tmp_path, exr):
    src = exr(tmp_path / "x.exr")
    model = _tiny()
    calls = []

    def fail_on_second_tile(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("out of memory (simulated)")
        return type(model).forward(model, *a, **k)

    model.forward = fail_on_second_tile
    with pytest.raises(RuntimeError, match="simulated"):
        dn.denoise(src, model, out_path=tmp_path / "out" / "clean.exr", tile=8, device="cpu")
    assert len(calls) == 2
    assert not (tmp_path / "out" / "clean.exr").exists()
    assert [f for f in _files(tmp_path) if f.startswith("out/")] == []  # no temporary file left either


# ----------------------------------------------------------------------------- the command line


def test_cli_refuses_two_inputs_that_would_share_one_output(tmp_path, exr, weights):
    # the reported case, as a user runs it: a/x.exr b/x.exr --out-dir OUT
    a, b = exr(tmp_path / "a" / "x.exr"), exr(tmp_path / "b" / "x.exr")
    out_dir = tmp_path / "OUT"
    r = subprocess.run([sys.executable, "-m", "kpcn.inference", str(a), str(b), "--out-dir", str(out_dir),
                        "--model", weights, "--device", "cpu"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    line = _one_line_error(r.stderr)
    assert str(a) in line and str(b) in line and str(out_dir / "x_denoised.exr") in line
    assert not out_dir.exists() or _files(out_dir) == []  # nothing denoised, nothing written
    assert r.stdout == ""


def test_cli_refuses_an_output_that_is_another_input(tmp_path, exr, weights, capsys):
    # next to the inputs: x.exr -> x_denoised.exr, which is the second input
    first, second = exr(tmp_path / "x.exr"), exr(tmp_path / "x_denoised.exr")
    before = second.read_bytes()
    assert cli_main([str(first), str(second), "--model", weights, "--device", "cpu"]) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert str(first) in line and str(second) in line
    assert second.read_bytes() == before
    assert _files(tmp_path) == ["tiny.safetensors", "x.exr", "x_denoised.exr"]
    # with --out-dir: d/y.exr -> OUT/y_denoised.exr, which is given as an input too
    y = exr(tmp_path / "d" / "y.exr")
    other = exr(tmp_path / "OUT" / "y_denoised.exr")
    before = other.read_bytes()
    assert cli_main([str(y), str(other), "--out-dir", str(tmp_path / "OUT"), "--model", weights,
                     "--device", "cpu"]) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert str(y) in line and str(other) in line
    assert other.read_bytes() == before and _files(tmp_path / "OUT") == ["y_denoised.exr"]


@pytest.mark.parametrize("spelling", ["same", "dot_relative", "symlink", "hardlink"])
def test_cli_refuses_the_same_input_twice(tmp_path, exr, weights, capsys, monkeypatch, spelling):
    src = exr(tmp_path / "x.exr")
    again = str(src)
    if spelling == "dot_relative":
        monkeypatch.chdir(tmp_path)
        again = "./x.exr"
    elif spelling == "symlink":
        (tmp_path / "link.exr").symlink_to(src)
        again = str(tmp_path / "link.exr")
    elif spelling == "hardlink":
        os.link(src, tmp_path / "hard.exr")
        again = str(tmp_path / "hard.exr")
    out_dir = tmp_path / "OUT"
    assert cli_main([str(src), again, "--out-dir", str(out_dir), "--model", weights, "--device", "cpu"]) == 2
    cap = capsys.readouterr()
    line = _one_line_error(cap.err)
    assert "twice" in line and str(src) in line and again in line
    assert cap.out == "" and not out_dir.exists()


@pytest.mark.parametrize("variant", ["same", "dot_relative", "out_symlink_to_input", "input_symlink_to_out",
                                     "hardlink"])
def test_cli_refuses_output_equal_to_its_input_with_the_api_check(tmp_path, exr, weights, capsys, monkeypatch,
                                                                   variant):
    src, out, keep = _aliases(variant, tmp_path, exr, monkeypatch)
    before = keep.read_bytes()
    with pytest.raises(ValueError) as api:
        dn.denoise(src, _never_run(), out_path=out, device="cpu")
    assert cli_main([src, "-o", out, "--model", weights, "--device", "cpu"]) == 2  # a usage error, before any work
    cap = capsys.readouterr()
    line = _one_line_error(cap.err)
    assert str(api.value) in line  # the same check, the same words
    assert cap.out == ""  # refused before the model was even loaded
    assert keep.read_bytes() == before


def _mistake(kind: str, tmp_path: Path, exr) -> tuple[list[str], str]:
    """CLI arguments (before --model) for one user mistake, and a word the error line must contain."""
    good = str(exr(tmp_path / "x.exr"))
    if kind == "missing_input":
        return [good, str(tmp_path / "nope.exr"), "--out-dir", str(tmp_path / "OUT")], "nope.exr"
    if kind == "input_is_a_folder":
        (tmp_path / "dir.exr").mkdir()
        return [good, str(tmp_path / "dir.exr"), "--out-dir", str(tmp_path / "OUT")], "dir.exr"
    if kind == "out_dir_is_a_file":
        (tmp_path / "OUT").write_text("a file")
        return [good, "--out-dir", str(tmp_path / "OUT")], "OUT"
    if kind == "out_is_a_folder":
        (tmp_path / "OUT").mkdir()
        return [good, "-o", str(tmp_path / "OUT")], "OUT"
    if kind == "out_parent_is_a_file":
        (tmp_path / "OUT").write_text("a file")
        return [good, "-o", str(tmp_path / "OUT" / "clean.exr")], "OUT"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["missing_input", "input_is_a_folder", "out_dir_is_a_file", "out_is_a_folder",
                                  "out_parent_is_a_file"])
def test_cli_input_output_mistakes_are_one_line_and_exit_2(tmp_path, exr, weights, capsys, kind):
    args, word = _mistake(kind, tmp_path, exr)
    before = _files(tmp_path)
    assert cli_main(args + ["--model", weights, "--device", "cpu"]) == 2
    cap = capsys.readouterr()
    line = _one_line_error(cap.err)
    assert line.startswith("kpcn-denoise: ") and word in line
    assert cap.out == ""  # nothing denoised, the model not even loaded
    assert _files(tmp_path) == before  # nothing written, nothing created


def test_cli_mistakes_without_a_traceback_in_a_real_process(tmp_path, exr, weights):
    args, _ = _mistake("out_dir_is_a_file", tmp_path, exr)
    r = subprocess.run([sys.executable, "-m", "kpcn.inference", *args, "--model", weights, "--device", "cpu"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "is a file" in _one_line_error(r.stderr)


def test_cli_creates_a_missing_output_folder(tmp_path, exr, weights, capsys):
    a, b = exr(tmp_path / "a" / "x.exr"), exr(tmp_path / "b" / "y.exr")
    out_dir = tmp_path / "new" / "OUT"
    assert cli_main([str(a), str(b), "--out-dir", str(out_dir), "--model", weights, "--device", "cpu",
                     "--tile", "8"]) == 0
    assert _files(out_dir) == ["x_denoised.exr", "y_denoised.exr"]
    assert cli_main([str(a), "-o", str(tmp_path / "other" / "clean.exr"), "--model", weights,
                     "--device", "cpu"]) == 0
    assert (tmp_path / "other" / "clean.exr").is_file()
    capsys.readouterr()
