"""Shared fixtures: tiny scenes rendered for real with Mitsuba, once per test session."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest
import torch

torch.set_num_threads(min(2, os.cpu_count() or 1))

_SYSTEM_TMP = Path(tempfile.gettempdir())


@pytest.fixture(scope="session", autouse=True)
def no_temporary_files_left(tmp_path_factory):
    """Every temporary file of the run (subprocesses too: torchrun, tempfile) goes under pytest's own
    folder, which is removed after the run (tmp_path_retention_policy = "none"), and the run must add
    nothing to the system's temporary folder."""
    before = set(os.listdir(_SYSTEM_TMP))
    session_tmp = tmp_path_factory.mktemp("tmpdir")
    old = os.environ.get("TMPDIR")
    os.environ["TMPDIR"] = str(session_tmp)
    tempfile.tempdir = None  # re-read TMPDIR
    yield session_tmp
    if old is None:
        os.environ.pop("TMPDIR", None)
    else:
        os.environ["TMPDIR"] = old
    tempfile.tempdir = None
    basetemp = tmp_path_factory.getbasetemp()
    left = sorted(n for n in set(os.listdir(_SYSTEM_TMP)) - before
                  if not basetemp.is_relative_to(_SYSTEM_TMP / n))  # pytest's own folder is removed by pytest
    assert not left, f"the test run left files in {_SYSTEM_TMP}: {left}"

RES = (32, 32)


@pytest.fixture(scope="session")
def mi():
    from kpcn.render import ensure_variant

    return ensure_variant()


@pytest.fixture(scope="session")
def render(mi):
    """Cached ``render(scene, spp, seed, role=0, resolution=RES)`` -> Frame."""
    from kpcn.render import render_frame

    cache = {}

    def _render(scene="test:glossy", spp=8, seed=1, role=0, resolution=RES):
        key = (scene, spp, seed, role, resolution)
        if key not in cache:
            cache[key] = render_frame(scene, spp=spp, seed=seed, role=role, resolution=resolution)
        return cache[key]

    return _render


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory, mi):
    """A rendered data set: 3 procedural scenes at 48x48, inputs at 4 and 8 spp, 128-spp references."""
    from kpcn.render import render_dataset

    root = tmp_path_factory.mktemp("data")
    render_dataset(root, n_scenes=3, spp_list=(4, 8), ref_spp=128, resolution=(48, 48), first_seed=100, progress=False)
    return root
