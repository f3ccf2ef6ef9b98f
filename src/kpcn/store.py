"""The patch store: every frame's training tensors preprocessed once, on disk, read through memory maps.

:class:`kpcn.data.PatchDataset` built with ``store=<folder>`` crops its patches
from here instead of holding every frame in memory, so the training set may be
larger than the RAM. :func:`prepare` builds the entries that are missing or
stale (and only those); :class:`kpcn.store_frames.StoreFrames` reads crops
(:func:`kpcn.store_frames.open_store` does both).

Layout (default folder ``<data root>/.store/<spec name>/``, :func:`default_store_dir`)::

    <store>/
      .lock                            # serialises preparing processes (flock)
      <scene>-<spp>spp-<hash>/         # one entry per (input, reference) pair
        half.npy       (H, W, Ch)      # float16 channels (float32 when the frame overflows float16)
        full.npy       (H, W, Cf)      # float32 channels
        importance.npy (H, W)          # the importance map of patch sampling, as kpcn.data computes it
        entry.json                     # written last: the "done" marker (see below)

Channels are stored last, so a patch is one contiguous run per row. Which
channels are float16 (:func:`float32_channels`): the branch colours and their
gradients, the albedo and the normal (``noisy_normal``), are float16 — their relative rounding error is at
most ``2**-11`` (``|x| >= 2**-14``), absolute ``2**-25`` below
(:data:`HALF_RTOL`, :data:`HALF_ATOL`). Float32 are the variance channels
(they span 1e-40..1e5: a frame of the 30-scene training set has colour
variances above float16's 65504, and the ``logvar`` input transform resolves
them down to 1e-6, where float16's step is 3 %), the targets ``y_*`` (the loss
compares against them: exact) and ``noisy_color`` (unbounded radiance). A frame
with any float16-bound value above 65504 stores its ``half.npy`` as float32 —
never clamped, never infinite; ``entry.json`` records the dtype.

An entry is trusted only when ``entry.json`` parses, carries this
:data:`STORE_FORMAT` and the frame's current :func:`fingerprint` (spec, the two
files' paths relative to the store, their sizes and ``st_mtime_ns``, and the
manifest's render records), and every array file has the header and the exact
byte size it records. Anything else (a killed build, a truncated file, a
re-rendered or touched frame, another spec) rebuilds the entry: its
``entry.json`` is removed first, the arrays are written under temporary names
and renamed, and ``entry.json`` is written last. The data set itself is only
read.
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import hashlib
import json
import logging
import multiprocessing as mp
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .config import ConfigError
from .inputs import InputSpec, get_input_spec
from .io import atomic_write

log = logging.getLogger("kpcn.store")

__all__ = ["STORE_FORMAT", "HALF_RTOL", "HALF_ATOL", "StoreError", "Entry", "Prepared", "default_store_dir",
           "float32_channels", "fingerprint", "entry_name", "load_entry", "build_entry", "prepare"]

#: Version of the layout and of the preprocessing; entries of another version are rebuilt.
#: Bump it when the features an input spec builds change.
STORE_FORMAT = 2  # 2: the noisy frame's normal (``noisy_normal``) is stored
#: float16's largest finite value: a frame with a larger float16-bound value stores it as float32
HALF_MAX = 65504.0
#: the float16 round trip: |stored - x| <= HALF_RTOL * |x| + HALF_ATOL (round to nearest, 11-bit significand)
HALF_RTOL = 2.0 ** -11
HALF_ATOL = 2.0 ** -25
ENTRY = "entry.json"


class StoreError(ConfigError):
    """The patch store cannot be created where ``data.store`` says (a user's error: one line)."""


def default_store_dir(root: str | os.PathLike, spec: InputSpec | str) -> Path:
    """``<root>/.store/<spec name>``: where training keeps the store of a data set by default."""
    return Path(root) / ".store" / get_input_spec(spec).name


def float32_channels(spec: InputSpec, key: str, channels: int) -> np.ndarray:
    """Boolean mask over the ``channels`` of tensor ``key``: True where the store keeps float32.

    Branch tensors: float32 only for the spec's ``variance_channels``; the albedo and
    ``noisy_normal`` (in [-1, 1]): none; targets, ``noisy_color`` and any other key: all.
    """
    mask = np.ones(channels, bool)
    if key in spec.branches:
        mask[:] = False
        mask[list(spec.variance_channels)] = True
    elif key in ("albedo", "noisy_normal"):
        mask[:] = False
    return mask


def _rel(path, store_dir) -> str:
    return os.path.relpath(os.path.abspath(path), os.path.abspath(store_dir))


def entry_name(pair, store_dir: str | os.PathLike) -> str:
    """``<scene>-<spp>spp-<hash>``: the entry folder of ``pair`` (the hash is of the two paths relative to the store)."""
    rel = "\n".join(_rel(p, store_dir) for p in (pair.input_path, pair.reference_path))
    scene = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(pair.scene))[:60] or "frame"
    return f"{scene}-{pair.spp}spp-{hashlib.sha256(rel.encode()).hexdigest()[:12]}"


def fingerprint(pair, spec: InputSpec, store_dir: str | os.PathLike) -> dict:
    """What an entry must match to be trusted: format, spec (which layers it reads in place of others, and
    the revision of its maths), each file's relative path, size and mtime, records."""
    files = {}
    for role, p in (("input", pair.input_path), ("reference", pair.reference_path)):
        st = os.stat(p)
        files[role] = [_rel(p, store_dir), int(st.st_size), int(st.st_mtime_ns)]
    return {"format": STORE_FORMAT, "spec": spec.name, "channels": spec.channels, "prefer": list(spec.prefer),
            "revision": spec.revision, "files": files, "records": getattr(pair, "records", None)}


def _canon(obj) -> str:
    return json.dumps(obj, sort_keys=True)


@dataclass
class Entry:
    """One trusted frame of the store (the contents of its ``entry.json``)."""

    path: Path
    shape: tuple[int, int]
    groups: dict  #: "half"/"full" -> {"file", "dtype", "channels"}
    keys: dict  #: tensor name -> runs [group, first source channel, end, first channel of the tensor]
    channels: dict  #: tensor name -> its number of channels
    importance: str | None  #: file of the importance map (None: the frame has no colour/normal variance)
    importance_dtype: str | None = None


def _npy_ok(path: Path, dtype: str, shape: tuple) -> bool:
    """Whether ``path`` is a complete C-order ``.npy`` of ``dtype`` and ``shape`` (header and byte size)."""
    fmt = np.lib.format
    try:
        with open(path, "rb") as f:
            version = fmt.read_magic(f)
            read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shp, fortran, dt = read(f)
            offset = f.tell()
        size = os.path.getsize(path)
    except (OSError, ValueError, EOFError):
        return False
    return (tuple(shp) == tuple(shape) and not fortran and dt == np.dtype(dtype)
            and size == offset + int(np.prod(shape)) * dt.itemsize)


def load_entry(folder: Path, fp: dict) -> Entry | None:
    """The entry in ``folder`` if it is complete and matches ``fp``, else None (it is then rebuilt)."""
    try:
        meta = json.loads((folder / ENTRY).read_text())
        if meta.get("format") != STORE_FORMAT or _canon(meta.get("fingerprint")) != _canon(fp):
            return None
        h, w = (int(v) for v in meta["shape"])
        for info in meta["groups"].values():
            if not _npy_ok(folder / info["file"], info["dtype"], (h, w, int(info["channels"]))):
                return None
        imp = meta.get("importance")
        if imp and not _npy_ok(folder / imp, meta["importance_dtype"], (h, w)):
            return None
        return Entry(folder, (h, w), meta["groups"], meta["keys"], meta["channels"], imp, meta.get("importance_dtype"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _layout(spec: InputSpec, tensors: dict[str, np.ndarray]) -> tuple[dict[str, int], dict[str, list]]:
    """Channels per group and, per tensor, its runs ``[group, src, src_end, dst]`` (contiguous in both)."""
    counts = {"half": 0, "full": 0}
    runs: dict[str, list] = {}
    for key, t in tensors.items():
        mask = float32_channels(spec, key, t.shape[0])
        rk: list = []
        for c in range(t.shape[0]):
            g = "full" if mask[c] else "half"
            src = counts[g]
            counts[g] += 1
            if rk and rk[-1][0] == g and rk[-1][2] == src and rk[-1][3] + (rk[-1][2] - rk[-1][1]) == c:
                rk[-1][2] += 1
            else:
                rk.append([g, src, src + 1, c])
        runs[key] = rk
    return {g: n for g, n in counts.items() if n}, runs


def _write_npy(path: Path, arr: np.ndarray) -> None:
    def write(tmp: str) -> None:
        mm = np.lib.format.open_memmap(tmp, mode="w+", dtype=arr.dtype, shape=arr.shape)
        mm[...] = arr
        mm.flush()
        del mm

    atomic_write(path, write)


def build_entry(pair, spec: InputSpec, folder: Path, fp: dict) -> Entry:
    """Preprocess ``pair`` into ``folder`` (atomically: ``entry.json`` is removed first and written last)."""
    from .data import importance_map, pair_tensors, read_pair

    noisy, ref = read_pair(pair, spec)
    tensors = {k: v[0].numpy() for k, v in pair_tensors(noisy, ref, spec).items()}
    imp = None
    if "colorVariance" in noisy and "normalVariance" in noisy:
        imp = importance_map(noisy["colorVariance"], noisy["normalVariance"])
    counts, runs = _layout(spec, tensors)
    h, w = tensors["albedo"].shape[-2:]
    arrays = {g: np.empty((h, w, n), np.float32) for g, n in counts.items()}
    for key, rk in runs.items():
        for g, a, b, d in rk:
            arrays[g][..., a:b] = tensors[key][d : d + b - a].transpose(1, 2, 0)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / ENTRY).unlink(missing_ok=True)  # untrusted from here until entry.json is written again
    groups = {}
    for g, arr in arrays.items():
        dtype = "float32"
        if g == "half":
            if np.abs(arr).max(initial=0.0) <= HALF_MAX:
                dtype = "float16"
            else:
                log.info("%s: values beyond float16's range (%.3g): its half.npy is float32",
                         pair.input_path, float(np.abs(arr).max()))
        _write_npy(folder / f"{g}.npy", arr.astype(dtype, copy=False))
        groups[g] = {"file": f"{g}.npy", "dtype": dtype, "channels": int(arr.shape[-1])}
    if imp is not None:
        _write_npy(folder / "importance.npy", np.ascontiguousarray(imp))
    else:
        (folder / "importance.npy").unlink(missing_ok=True)
    meta = {"format": STORE_FORMAT, "fingerprint": fp, "shape": [int(h), int(w)], "groups": groups, "keys": runs,
            "channels": {k: int(v.shape[0]) for k, v in tensors.items()},
            "importance": "importance.npy" if imp is not None else None,
            "importance_dtype": str(imp.dtype) if imp is not None else None,
            "source": {"input": str(pair.input_path), "reference": str(pair.reference_path)}}
    atomic_write(folder / ENTRY, lambda tmp: Path(tmp).write_text(json.dumps(meta, indent=1)))
    return Entry(folder, (int(h), int(w)), groups, runs, meta["channels"], meta["importance"], meta["importance_dtype"])


@contextlib.contextmanager
def _locked(store_dir: Path):
    """An exclusive ``flock`` on ``<store>/.lock`` (none where flock is unavailable)."""
    try:
        import fcntl

        fh = open(store_dir / ".lock", "a")
    except (ImportError, OSError):
        yield
        return
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX)
        except OSError:
            pass
        yield
    finally:
        fh.close()  # releases the lock


@dataclass
class Prepared:
    entries: list[Entry]  #: one per pair, in order
    built: list[int]  #: indices of the pairs preprocessed by this call (missing, stale or damaged entries)


def prepare(pairs: Sequence, spec: InputSpec | str, store_dir: str | os.PathLike, progress: bool = False,
            workers: int | None = None) -> Prepared:
    """Make sure every pair has a trusted entry in ``store_dir``; (re)build only those that do not.

    ``workers``: processes that build the missing entries (each with one torch thread); None: one per core (at
    most 16) when at least :data:`PARALLEL_MIN_FRAMES` are missing, else this process alone.

    Raises:
        StoreError: ``store_dir`` cannot be created.
    """
    spec = get_input_spec(spec)
    store_dir = Path(store_dir)
    try:
        store_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StoreError(f"data.store: cannot create the patch store {store_dir} ({exc.strerror or exc}); set "
                         f"data.store to a writable folder, or to none to keep the frames in memory") from None
    with _locked(store_dir):
        entries: list = [None] * len(pairs)
        stale = []
        for i, p in enumerate(pairs):
            fp = fingerprint(p, spec, store_dir)
            entries[i] = load_entry(store_dir / entry_name(p, store_dir), fp)
            if entries[i] is None:
                stale.append((i, fp))
        if stale:
            log.info("patch store %s: preprocessing %d of %d frames", store_dir, len(stale), len(pairs))
        from tqdm import tqdm

        jobs = [(pairs[i], spec.name, store_dir / entry_name(pairs[i], store_dir), fp) for i, fp in stale]
        n = _prepare_workers(workers, len(stale), spec)
        # spawned (not forked) processes: the parent's OpenMP threads may not survive a fork
        with (cf.ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=_one_thread) if n > 1
              else contextlib.nullcontext()) as pool:
            done = pool.map(_build_named, jobs) if pool else (build_entry(p, spec, f, fp) for p, _, f, fp in jobs)
            for (i, _), entry in zip(stale, tqdm(done, total=len(stale), desc="patch store", disable=not progress,
                                                 dynamic_ncols=True)):
                entries[i] = entry
    return Prepared(entries, [i for i, _ in stale])


#: fewer missing entries than this are built in the calling process (starting workers costs seconds)
PARALLEL_MIN_FRAMES = 16


def _prepare_workers(workers: int | None, n_stale: int, spec: InputSpec) -> int:
    """How many processes build ``n_stale`` entries: ``workers``, or (None) one per core up to 16 when there are
    at least :data:`PARALLEL_MIN_FRAMES`; one for a spec the registry does not give back by name."""
    if workers is None:
        workers = min(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1, 16)
        workers = workers if n_stale >= PARALLEL_MIN_FRAMES else 1
    try:
        named = get_input_spec(spec.name) is spec
    except ValueError:  # an unregistered spec: a worker could not rebuild it from its name
        named = False
    return max(1, min(int(workers), n_stale)) if named else 1


def _one_thread() -> None:
    """A preparing worker's initializer: one torch thread and one OpenEXR thread (the workers share the CPUs)."""
    torch.set_num_threads(1)
    os.environ.setdefault("KPCN_EXR_THREADS", "1")


def _build_named(job) -> Entry:
    pair, spec_name, folder, fp = job
    return build_entry(pair, get_input_spec(spec_name), folder, fp)
