"""The patch store (kpcn.store): crops equal the in-memory ones to float16 rounding, stale and half-written
entries are rebuilt, the data set is never modified, and batches are the same with and without workers."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pickle
import shutil

import numpy as np
import pytest
import torch

from kpcn import store as st
from kpcn.config import ConfigError, load_config
from kpcn.data import PatchDataset, read_manifest
from kpcn.distributed import Dist
from kpcn.inputs import get_input_spec
from kpcn.io import _host_tag
from kpcn.train_config import RunConfig

SPEC = get_input_spec("kpcn_split")


@pytest.fixture
def data(tiny_dataset, tmp_path):
    """A private copy of the tiny data set (the tests change its files)."""
    root = tmp_path / "data"
    shutil.copytree(tiny_dataset, root, ignore=shutil.ignore_patterns(".store"))
    return root


def snapshot(folder) -> dict:
    """Every file under ``folder`` but the store: content digest and mtime."""
    return {str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file() and ".store" not in p.relative_to(folder).parts}


def assert_items_match(mem: dict, sto: dict) -> None:
    """Same keys, order and shapes; float32 channels equal; float16 ones within the documented rounding."""
    assert list(mem) == list(sto)
    for k in mem:
        a, b = mem[k], sto[k]
        assert b.dtype == torch.float32 and a.shape == b.shape, (k, a.shape, b.shape)
        exact = st.float32_channels(SPEC, k, a.shape[0])
        np.testing.assert_array_equal(b[exact].numpy(), a[exact].numpy(), err_msg=k)
        np.testing.assert_allclose(b[~exact].numpy(), a[~exact].numpy(), rtol=st.HALF_RTOL, atol=st.HALF_ATOL,
                                   err_msg=k)


def test_store_crops_equal_in_memory_crops_to_float16_rounding(tiny_dataset, tmp_path):
    pairs = read_manifest(tiny_dataset)
    mem = PatchDataset(pairs, patch_size=20, patches_per_frame=6, seed=3)
    sto = PatchDataset(pairs, patch_size=20, patches_per_frame=6, seed=3, store=tmp_path / "store")
    rounded = 0
    for epoch in (0, 1):
        mem.resample(epoch)
        sto.resample(epoch)
        np.testing.assert_array_equal(mem.index, sto.index)  # the same patch positions
        for i in range(len(mem)):
            a, b = mem[i], sto[i]
            assert_items_match(a, b)
            rounded += int((a["diffuse"] != b["diffuse"]).sum())
    assert rounded > 0  # the float16 channels really are float16 on disk
    entry = next((tmp_path / "store").glob("*/entry.json"))
    meta = json.loads(entry.read_text())
    assert meta["groups"]["half"]["dtype"] == "float16" and meta["groups"]["full"]["dtype"] == "float32"
    # a patch larger than the 48x48 frame is clipped as in memory
    big_mem = PatchDataset(pairs[:2], patch_size=64, patches_per_frame=2, seed=0)
    big_sto = PatchDataset(pairs[:2], patch_size=64, patches_per_frame=2, seed=0, store=tmp_path / "store")
    assert big_sto[1]["diffuse"].shape == (27, 48, 48)
    assert_items_match(big_mem[1], big_sto[1])


def test_values_beyond_float16_are_stored_as_float32_not_clamped(data, tmp_path):
    from kpcn.io import read_exr, write_exr

    pair = read_manifest(data, spp=[4])[0]
    frame = read_exr(pair.input_path)
    layers = dict(frame.layers)
    layers["diffuse"] = layers["diffuse"] * 1e5  # the diffuse branch colour goes far beyond 65504
    write_exr(pair.input_path, layers, frame.meta)
    mem = PatchDataset([pair], patch_size=48, patches_per_frame=1, seed=0)
    assert float(mem[0]["diffuse"][:3].max()) > 65504
    sto = PatchDataset([pair], patch_size=48, patches_per_frame=1, seed=0, store=tmp_path / "store")
    assert sto.store.entries[0].groups["half"]["dtype"] == "float32"
    for k, v in mem[0].items():
        torch.testing.assert_close(sto[0][k], v, rtol=0, atol=0)


def test_the_data_set_is_never_modified(data):
    before = snapshot(data)
    ds = PatchDataset(read_manifest(data), patch_size=16, patches_per_frame=2, store=st.default_store_dir(data, SPEC))
    ds[0]
    assert snapshot(data) == before
    assert len(list((data / ".store" / "kpcn_split").glob("*/entry.json"))) == 6


def test_a_stale_frame_is_preprocessed_again_and_only_it(data, tmp_path):
    store = tmp_path / "store"
    pairs = read_manifest(data)
    assert st.prepare(pairs, SPEC, store).built == list(range(6))
    assert st.prepare(pairs, SPEC, store).built == []  # everything fresh: nothing is read again
    # re-render one frame: here, another frame's file replaces it (new content, size and mtime)
    target = next(i for i, p in enumerate(pairs) if p.spp == 8)
    other = next(p for p in pairs if p.scene != pairs[target].scene and p.spp == 8)
    shutil.copyfile(other.input_path, pairs[target].input_path)
    assert st.prepare(pairs, SPEC, store).built == [target]
    mem = PatchDataset([pairs[target]], patch_size=48, patches_per_frame=1, seed=0)
    sto = PatchDataset([pairs[target]], patch_size=48, patches_per_frame=1, seed=0, store=store)
    assert_items_match(mem[0], sto[0])
    # touching a reference makes both frames that use it stale
    ref = pairs[0].reference_path
    os.utime(ref, ns=(ref.stat().st_atime_ns, ref.stat().st_mtime_ns + 10**9))
    assert st.prepare(pairs, SPEC, store).built == [i for i, p in enumerate(pairs) if p.reference_path == ref]
    # another spec has its own entries: the kpcn_split ones stay trusted
    assert st.prepare(pairs, "split_novar", tmp_path / "novar").built == list(range(6))
    assert st.prepare(pairs, SPEC, store).built == []
    # a spec that reads another layer in place of one (InputSpec.prefer) does not trust entries built without it
    can = get_input_spec("color_albedo_normal")
    assert can.prefer and st.fingerprint(pairs[0], can, store) != \
        st.fingerprint(pairs[0], dataclasses.replace(can, prefer=()), store)
    # nor entries built by an earlier revision of the features' maths (the noise estimate)
    noise = get_input_spec("color_albedo_normal_noise")
    assert st.fingerprint(pairs[0], noise, store) != \
        st.fingerprint(pairs[0], dataclasses.replace(noise, revision=noise.revision - 1), store)


def test_half_written_entries_are_rebuilt_not_trusted(data, tmp_path, monkeypatch):
    store = tmp_path / "store"
    pairs = read_manifest(data)
    entries = st.prepare(pairs, SPEC, store).entries
    (entries[0].path / "entry.json").unlink()  # killed before the done marker
    with open(entries[1].path / "half.npy", "r+b") as f:  # a truncated array
        f.truncate(os.path.getsize(entries[1].path / "half.npy") - 100)
    (entries[2].path / "entry.json").write_text('{"format": 1, "fingerp')  # a torn marker
    np.save(entries[3].path / "importance.npy", np.zeros((48, 47), np.float32))  # wrong shape
    assert st.prepare(pairs, SPEC, store).built == [0, 1, 2, 3]
    # a rebuild killed between its arrays: the entry is not trusted, the next prepare finishes it
    os.utime(pairs[4].input_path)
    real = st._write_npy
    calls = []

    def killed(path, arr):  # the second array's writer dies mid-file, leaving its temporary
        calls.append(path.name)
        if len(calls) == 2:
            dead = 2**22 + 12345  # above Linux's largest pid: no such process
            (path.parent / f".{path.name}.{dead}-{_host_tag()}.abcd1234.tmp.npy").write_bytes(b"\x93NUMPY partial")
            raise KeyboardInterrupt("killed")
        real(path, arr)

    monkeypatch.setattr(st, "_write_npy", killed)
    with pytest.raises(KeyboardInterrupt):
        st.prepare(pairs, SPEC, store)
    monkeypatch.setattr(st, "_write_npy", real)
    assert calls == ["half.npy", "full.npy"] and not (entries[4].path / "entry.json").exists()
    assert st.prepare(pairs, SPEC, store).built == [4]
    assert not [p.name for p in entries[4].path.iterdir() if ".tmp" in p.name]  # the dead writer's temporary went
    mem = PatchDataset(pairs, patch_size=48, patches_per_frame=1, seed=0)
    sto = PatchDataset(pairs, patch_size=48, patches_per_frame=1, seed=0, store=store)
    for i in range(len(mem)):
        assert_items_match(mem[i], sto[i])


def test_the_dataset_pickles_without_its_memory_maps(tiny_dataset, tmp_path):
    ds = PatchDataset(read_manifest(tiny_dataset), patch_size=16, patches_per_frame=3, store=tmp_path / "store")
    first = ds[4]
    assert ds.store._open  # maps opened in this process
    blob = pickle.dumps(ds)
    assert len(blob) < 50_000  # positions and entry metadata only: not one frame's pixels
    again = pickle.loads(blob)
    assert not again.store._open
    for k, v in again[4].items():
        torch.testing.assert_close(v, first[k], rtol=0, atol=0)


def tiny_run_cfg(root, workers, store="auto") -> RunConfig:
    return load_config(RunConfig, None, [
        f"data.root={root}", "data.patch_size=16", "data.patches_per_frame=3", f"data.workers={workers}",
        f"data.store={store}", "train.batch_size=4", "train.stage1_steps=7", "train.stage2_steps=3"])


def test_batches_are_the_same_with_and_without_workers_and_on_resume(tiny_dataset, tmp_path):
    from kpcn.train_steps import batches

    pairs = read_manifest(tiny_dataset, spp=[4, 8])

    def run(workers, start=0, store=tmp_path / "store"):
        cfg = tiny_run_cfg(tiny_dataset, workers)
        ds = PatchDataset(pairs, 16, 3, seed=cfg.train.seed, store=store)
        return [(s, b) for s, b in batches(ds, cfg, Dist(), start)]

    plain, workers = run(0), run(2)
    assert [s for s, _ in plain] == list(range(10))  # 18 patches, batches of 4: 4 steps an epoch, 3 epochs
    for (s0, a), (s1, b) in zip(plain, workers, strict=True):
        assert s0 == s1 and list(a) == list(b)
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    resumed = run(2, start=5)  # mid-epoch
    for (s0, a), (s1, b) in zip(plain[5:], resumed, strict=True):
        assert s0 == s1
        torch.testing.assert_close(a["diffuse"], b["diffuse"], rtol=0, atol=0)
    in_memory = run(0, store=None)  # the same patches as the in-memory dataset, to float16 rounding
    for (_, a), (_, b) in zip(in_memory, plain, strict=True):
        assert_items_match({k: v[0] for k, v in a.items()}, {k: v[0] for k, v in b.items()})


def test_store_and_workers_config_keys(tiny_dataset, tmp_path):
    from kpcn.train_data import store_dir

    assert store_dir(tiny_run_cfg(tiny_dataset, 0), SPEC) == tiny_dataset / ".store" / "kpcn_split"
    assert store_dir(tiny_run_cfg(tiny_dataset, 0, "none"), SPEC) is None
    assert store_dir(tiny_run_cfg(tiny_dataset, 0, str(tmp_path / "s")), "split_novar") == tmp_path / "s" / "split_novar"
    with pytest.raises(ConfigError, match="data.workers: must be >= 0"):
        tiny_run_cfg(tiny_dataset, -1)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ConfigError, match="data.store: cannot create the patch store"):
        st.prepare(read_manifest(tiny_dataset)[:1], SPEC, blocker / "store")


def test_entries_built_by_worker_processes_equal_those_built_in_process(data, tmp_path):
    """``prepare(workers=2)`` (spawned processes) writes the same arrays and records as the serial build, and the
    result is trusted by a later serial call; a spec the registry cannot rebuild by name is built in process."""
    pairs = read_manifest(data)
    serial = st.prepare(pairs, SPEC, tmp_path / "one", workers=1)
    parallel = st.prepare(pairs, SPEC, tmp_path / "two", workers=2)
    assert parallel.built == serial.built == list(range(len(pairs)))
    for a, b in zip(serial.entries, parallel.entries, strict=True):
        assert a.path.name == b.path.name
        for name in ("half.npy", "full.npy", "importance.npy"):
            assert (a.path / name).read_bytes() == (b.path / name).read_bytes(), name
        ja, jb = (json.loads((e.path / "entry.json").read_text()) for e in (a, b))
        assert ja == jb
    assert st.prepare(pairs, SPEC, tmp_path / "two", workers=2).built == []
    assert st._prepare_workers(None, st.PARALLEL_MIN_FRAMES - 1, SPEC) == 1
    assert st._prepare_workers(8, 3, SPEC) == 3
    assert st._prepare_workers(8, 30, dataclasses.replace(SPEC)) == 1  # not the registered object
    with pytest.raises(ConfigError, match="data.prepare_workers: must be >= 1"):
        load_config(RunConfig, None, ["data.prepare_workers=0"])
