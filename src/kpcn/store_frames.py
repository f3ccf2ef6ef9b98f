"""Crops of a prepared patch store (:mod:`kpcn.store`), read through memory maps: :func:`open_store` prepares
the store, then :class:`StoreFrames` reads the training patches from it."""
from __future__ import annotations

import os
from collections import OrderedDict
from typing import Sequence

import numpy as np
import torch

from .inputs import InputSpec, get_input_spec
from .store import Entry, prepare

__all__ = ["MAX_OPEN", "StoreFrames", "open_store"]

#: frames whose memory maps a process keeps open at most (each map holds a file descriptor);
#: None: an eighth of the process's file-descriptor limit (two maps a frame: a quarter of it)
MAX_OPEN: int | None = None


def _max_open() -> int:
    if MAX_OPEN is not None:
        return MAX_OPEN
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
        soft = 65536 if soft == resource.RLIM_INFINITY else soft
    except (ImportError, OSError, ValueError):
        soft = 1024
    return max(16, soft // 8)


class StoreFrames:
    """Crops of the frames of a store, read through memory maps.

    The maps are opened on first use in each process (a DataLoader worker opens
    its own; pickling drops them) and stay open, the least recently used frames
    closed beyond :data:`MAX_OPEN` (reopening costs the map and its page faults
    again: with the usual limit of 1024 descriptors, 128 frames stay open).
    """

    def __init__(self, entries: Sequence[Entry]):
        self.entries = list(entries)
        self.sizes = [e.shape for e in self.entries]
        self._open: OrderedDict = OrderedDict()
        self._pid: int | None = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_open"], state["_pid"] = OrderedDict(), None
        return state

    def _arrays(self, i: int) -> dict[str, np.ndarray]:
        if self._pid != os.getpid():  # a forked worker does not use its parent's maps
            self._open, self._pid = OrderedDict(), os.getpid()
        arrays = self._open.get(i)
        if arrays is None:
            e = self.entries[i]
            arrays = {g: np.load(e.path / info["file"], mmap_mode="r") for g, info in e.groups.items()}
            for g, info in e.groups.items():  # rebuilt by another process since this one checked it?
                if arrays[g].shape != (*e.shape, info["channels"]) or arrays[g].dtype != np.dtype(info["dtype"]):
                    raise RuntimeError(f"patch store entry {e.path} changed while in use ({g}.npy is now "
                                       f"{arrays[g].dtype}{arrays[g].shape}); start the run again")
            self._open[i] = arrays
            while len(self._open) > _max_open():
                self._open.popitem(last=False)
        else:
            self._open.move_to_end(i)
        return arrays

    def crop(self, i: int, y: int, x: int, size: int) -> dict[str, torch.Tensor]:
        """Float32 ``(C, h, w)`` tensors of frame ``i`` at rows ``y:y+size``, columns ``x:x+size`` (clipped)."""
        # each group's crop: rows copied out of the map, then converted and made channel-first in one pass
        crops = {g: torch.from_numpy(np.array(a[y : y + size, x : x + size], order="C")).permute(2, 0, 1)
                 .to(torch.float32, memory_format=torch.contiguous_format) for g, a in self._arrays(i).items()}
        out = {}
        for key, runs in self.entries[i].keys.items():
            if len(runs) == 1:  # one run: a view of the group's crop
                g, a, b, _ = runs[0]
                out[key] = crops[g][a:b]
            else:  # runs are in the tensor's channel order
                out[key] = torch.cat([crops[g][a:b] for g, a, b, _ in runs])
        return out

    def importance(self, i: int) -> np.ndarray | None:
        e = self.entries[i]
        return np.load(e.path / e.importance) if e.importance else None


def open_store(pairs: Sequence, spec: InputSpec | str, store_dir: str | os.PathLike, importance: bool = False,
               progress: bool = False, workers: int | None = None) -> StoreFrames:
    """:func:`prepare` the store, then a :class:`StoreFrames` over it.

    ``importance``: every frame must have an importance map (its noisy render has
    colour and normal variances); the error of a frame without is the reader's
    :class:`~kpcn.io.MissingLayerError`, as with the frames kept in memory.
    """
    from .data import read_pair

    spec = get_input_spec(spec)
    prepared = prepare(pairs, spec, store_dir, progress, workers)
    if importance:
        for p, e in zip(pairs, prepared.entries):
            if e.importance is None:
                read_pair(p, spec)[0].require(("colorVariance", "normalVariance"))
    return StoreFrames(prepared.entries)
