"""Which file a path names, and the checks that keep denoising from writing over its inputs.

One set of checks for :func:`kpcn.denoise` / :func:`~kpcn.inference.denoise_result`
(:func:`check_not_input`, :func:`check_output_path`) and for ``kpcn-denoise``
(:func:`check_jobs`, which adds what only a batch can get wrong: the same input
twice, an output that is another input, two inputs sharing one output).

Two paths name the same file when they resolve to the same place (``./x.exr``
and ``/abs/x.exr``, ``d/../x.exr``, a symlink and its target, a folder reached
through a symlink) or, where both exist, when they are the same inode (a hard
link, a bind mount). A symlink or a hard link given as the output counts as the
input: the atomic write would replace that name, so the user's other name of
the input would silently stop being one.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

__all__ = ["file_key", "same_file", "check_not_input", "check_output_path", "check_input_path", "check_jobs"]


def file_key(path: str | os.PathLike) -> tuple:
    """A key equal for two paths exactly when they name the same file (existing or not)."""
    p = os.fspath(path)
    try:
        st = os.stat(p)  # follows symlinks
    except OSError:
        return ("path", os.path.normcase(os.path.realpath(p)))
    return ("inode", st.st_dev, st.st_ino)


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether ``a`` and ``b`` name the same file: the same resolved path, or (both existing) the same inode."""
    if os.path.normcase(os.path.realpath(os.fspath(a))) == os.path.normcase(os.path.realpath(os.fspath(b))):
        return True
    return file_key(a) == file_key(b)


def check_not_input(out_path: str | os.PathLike, in_path: str | os.PathLike) -> None:
    """Raise ``ValueError`` (naming both) if writing ``out_path`` would replace the input ``in_path``."""
    if same_file(out_path, in_path):
        out, src = os.fspath(out_path), os.fspath(in_path)
        how = "is" if out == src else "names the same file as"
        raise ValueError(f"output {out} {how} the input {src}; writing it would replace the input: "
                         f"choose another output path")


def check_output_path(out_path: str | os.PathLike) -> None:
    """Raise if ``out_path`` cannot become a file: it is a folder, or a parent of it is a file.

    Missing parent folders are fine (the writer creates them). Raises
    ``IsADirectoryError`` / ``NotADirectoryError`` with a one-line message.
    """
    p = Path(out_path)
    if p.is_dir():
        raise IsADirectoryError(f"output {os.fspath(out_path)} is a folder, not a file")
    for parent in p.parents:
        if parent.is_dir():
            return
        if os.path.lexists(parent):  # a file, or a dangling symlink, where a folder must be
            raise NotADirectoryError(f"cannot write {os.fspath(out_path)}: {os.fspath(parent)} is a file, "
                                     f"not a folder")


def check_input_path(in_path: str | os.PathLike) -> None:
    """Raise ``FileNotFoundError`` / ``IsADirectoryError`` unless ``in_path`` is an existing file."""
    p = os.fspath(in_path)
    if not os.path.exists(p):
        raise FileNotFoundError(f"input not found: {p}")
    if os.path.isdir(p):
        raise IsADirectoryError(f"input {p} is a folder, not an EXR file")


def check_jobs(pairs: Sequence[tuple[str, str]]) -> list[str]:
    """Every problem with a batch of ``(input, output)`` pairs, one line each; empty when it is safe to run.

    Checks each input exists and is a file, each output can be a file, no input
    is given twice, no output is one of the inputs (its own or another's), and
    no two inputs share an output (so no result is lost by being overwritten).
    """
    problems: list[str] = []
    for src, _ in pairs:
        try:
            check_input_path(src)
        except OSError as exc:
            problems.append(str(exc))
    seen_out: set[str] = set()
    for _, dst in pairs:
        if dst in seen_out:
            continue
        seen_out.add(dst)
        try:
            check_output_path(dst)
        except OSError as exc:
            problems.append(str(exc))
    if problems:
        return problems

    inputs: dict[tuple, str] = {}  # file -> the first spelling of it
    for src, _ in pairs:
        key = file_key(src)
        if key in inputs:
            problems.append(f"input {src} is given twice (also as {inputs[key]})")
        inputs.setdefault(key, src)
    if problems:
        return problems  # the clashing outputs that follow from it would only repeat it

    outputs: dict[tuple, str] = {}  # file -> the input written there
    for src, dst in pairs:
        key = file_key(dst)
        other = inputs.get(key)
        if other is not None:
            if same_file(other, src):
                try:
                    check_not_input(dst, src)
                except ValueError as exc:
                    problems.append(str(exc))
            else:
                what = "also an input" if dst == other else f"the same file as the input {other}"
                problems.append(f"the output of {src} would be {dst}, {what}; writing it would replace that "
                                f"input: choose another -o/--out-dir")
        elif key in outputs:
            problems.append(f"inputs {outputs[key]} and {src} would both be written to {dst}; "
                            f"denoise them in separate calls (with -o, or another --out-dir)")
        outputs.setdefault(key, src)
    return problems
