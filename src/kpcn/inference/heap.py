"""Heap reuse during a denoise call (glibc's ``malloc``): freed tensors' memory reused, not re-mapped.

A denoise call allocates and frees the same large tensors many times: a 1080p U-Net's half-resolution
feature maps are about 50 MB each, the row bands' features a few MB each. glibc serves every
allocation above its mmap threshold (at most 32 MiB, dynamic) with a fresh ``mmap`` and unmaps it on
``free``, and gives memory at the top of the heap back above its trim threshold; each such tensor
then costs the kernel a page fault and a zeroed page per 4 KiB when it is first written. On the 2-core
machine that was a quarter of a 1080p denoise (``python -m kpcn.bench denoise``: see ``docs/measured.md``).

:func:`reuse_heap` raises both thresholds (``mallopt``) for the duration of a call, so freed blocks
stay in the heap and are reused, and afterwards gives the free memory back (``malloc_trim``) and sets
the thresholds to the values glibc's own dynamic rule reaches once a process has freed a block of
32 MiB or more (mmap 32 MiB, trim 64 MiB), so the process keeps no more memory between calls than it
would have. Nested and concurrent calls share one setting (the outermost call restores it).

Nothing happens where the C library is not glibc (macOS, Windows, musl), or with the environment
variable ``KPCN_REUSE_HEAP=0``.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import threading

__all__ = ["reuse_heap", "heap_tuning_available"]

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: thresholds during a call: blocks up to 64 MiB come from (and return to) the heap. That covers a 1080p
#: frame's half-resolution maps (50 MB); larger blocks are still mapped afresh, because keeping them too
#: fragmented the heap: a 3840x2160 denoise peaked at 2597 MB with 1 GiB against 2113 MB untuned and
#: 2210 MB with 64 MiB, for no gain in time there (docs/measured.md)
_DURING = 64 << 20
#: thresholds after it: where glibc's dynamic rule settles once a 32 MiB block has been freed
_AFTER_MMAP, _AFTER_TRIM = 32 << 20, 64 << 20

_lock = threading.Lock()
_depth = 0
_libc = None


def _glibc():
    """glibc's handle, or None (another C library, or the tuning turned off)."""
    global _libc
    if os.environ.get("KPCN_REUSE_HEAP", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    if _libc is None:
        lib = False
        if sys.platform.startswith("linux"):
            try:
                c = ctypes.CDLL("libc.so.6")
                c.gnu_get_libc_version.restype = ctypes.c_char_p
                c.gnu_get_libc_version()  # only glibc has it
                c.mallopt.argtypes, c.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
                c.malloc_trim.argtypes, c.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
                lib = c
            except (OSError, AttributeError):
                lib = False
        _libc = lib
    return _libc or None


def heap_tuning_available() -> bool:
    """Whether :func:`reuse_heap` changes anything in this process (glibc, not turned off)."""
    return _glibc() is not None


@contextlib.contextmanager
def reuse_heap(enabled: bool = True):
    """Within the block, freed memory (blocks up to 64 MiB) is kept in the heap and reused; on leaving
    the outermost block the free memory is returned to the system. A no-op off glibc or if not ``enabled``."""
    global _depth
    libc = _glibc() if enabled else None
    if libc is None:
        yield
        return
    with _lock:
        if _depth == 0:
            libc.mallopt(_M_MMAP_THRESHOLD, _DURING)
            libc.mallopt(_M_TRIM_THRESHOLD, _DURING)
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                libc.mallopt(_M_MMAP_THRESHOLD, _AFTER_MMAP)
                libc.mallopt(_M_TRIM_THRESHOLD, _AFTER_TRIM)
                libc.malloc_trim(0)
