"""Heap reuse during a denoise call (glibc's ``malloc``): freed tensors' memory reused, not re-mapped.

A denoise call allocates and frees the same large tensors many times: a 1080p U-Net's half-resolution
feature maps are about 50 MB each, the row bands' features a few MB each. glibc serves every
allocation above its mmap threshold (at most 32 MiB, dynamic) with a fresh ``mmap`` and unmaps it on
``free``, and gives memory at the top of the heap back above its trim threshold; each such tensor
then costs the kernel a page fault and a zeroed page per 4 KiB when it is first written. On the 2-core
machine that was a quarter of a 1080p denoise (``python -m kpcn.bench denoise``: see ``docs/measured.md``).

:func:`reuse_heap` raises both thresholds (``mallopt``) for the duration of a call, so freed blocks
stay in the heap and are reused. When the last call ends, the free memory is kept a little longer,
:data:`KEEP_SECONDS` (a decay, as jemalloc's ``dirty_decay_ms``): a call that starts within it reuses the
pages the previous one faulted in. On a 1920x1080 frame those faults were 800 MB of 4 KiB pages, a
fifth of the CPU time of every call (``python -m kpcn.bench denoise`` repeats calls in one process, as a
renderer denoising frame after frame does; OIDN keeps its buffers between calls too). After that
idle time, or at once with ``KPCN_HEAP_KEEP_S=0``, the free memory is given back (``malloc_trim``) and
the thresholds set to the values glibc's own dynamic rule reaches once a process has freed a block of
32 MiB or more (mmap 32 MiB, trim 64 MiB), so an idle process keeps no more memory than it would have.
Nested and concurrent calls share one setting (the last to end schedules the release).

Nothing happens where the C library is not glibc (macOS, Windows, musl), or with the environment
variable ``KPCN_REUSE_HEAP=0``.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import threading

__all__ = ["reuse_heap", "heap_tuning_available", "release_heap", "KEEP_SECONDS"]

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: the mmap threshold during a call and the keep time: blocks up to 1 GiB come from (and return to) the heap. That
#: covers a 3840x2160 frame's half-resolution maps (200 MB; 50 MB at 1920x1080). With 64 MiB, every such map of a 4K
#: frame was mapped afresh and faulted in: 4 GB of 4 KiB pages per call, 6.6 s against 3.8 s (docs/measured.md)
_DURING = 1 << 30
#: the trim threshold over the same time: free memory at the top of the heap is kept up to this much
_TRIM_DURING = 1 << 30
#: thresholds after it: where glibc's dynamic rule settles once a 32 MiB block has been freed
_AFTER_MMAP, _AFTER_TRIM = 32 << 20, 64 << 20

#: seconds the free memory is kept after the last call ends (``KPCN_HEAP_KEEP_S``; 0: given back at once)
KEEP_SECONDS = 2.0

_lock = threading.Lock()
_depth = 0
_raised = False  # the thresholds are raised (during a call, and until the release after it)
_timer: threading.Timer | None = None
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


def _keep_seconds() -> float:
    text = os.environ.get("KPCN_HEAP_KEEP_S", "").strip()
    try:
        return max(0.0, float(text)) if text else KEEP_SECONDS
    except ValueError:
        raise ValueError(f"KPCN_HEAP_KEEP_S must be a number of seconds, got {text!r}") from None


@contextlib.contextmanager
def reuse_heap(enabled: bool = True):
    """Within the block, freed memory (blocks up to 1 GiB) is kept in the heap and reused; when the last
    block ends, the free memory is returned to the system after :data:`KEEP_SECONDS` of no new block
    (``KPCN_HEAP_KEEP_S``), or at once with 0. A no-op off glibc or if not ``enabled``."""
    global _depth, _raised, _timer
    libc = _glibc() if enabled else None
    if libc is None:
        yield
        return
    keep = _keep_seconds()
    with _lock:
        if _timer is not None:  # a release was waiting: this call reuses what the last one left
            _timer.cancel()
            _timer = None
        if not _raised:
            libc.mallopt(_M_MMAP_THRESHOLD, _DURING)
            libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_DURING)
            _raised = True
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                if keep > 0:
                    _timer = threading.Timer(keep, _release_if_idle)
                    _timer.daemon = True
                    _timer.start()
                else:
                    _release(libc)


def _release(libc) -> None:
    """Thresholds back to glibc's settled values, free memory returned (with :data:`_lock` held)."""
    global _raised
    libc.mallopt(_M_MMAP_THRESHOLD, _AFTER_MMAP)
    libc.mallopt(_M_TRIM_THRESHOLD, _AFTER_TRIM)
    libc.malloc_trim(0)
    _raised = False


def _release_if_idle() -> None:
    """The timer's release: skipped if a call started meanwhile (it cancelled or replaced this timer)."""
    global _timer
    with _lock:
        if _timer is not threading.current_thread():
            return
        _timer = None
        if _depth == 0 and _raised:
            _release(_glibc())


def _after_fork_in_child() -> None:
    """A child forked while memory was kept has no timer thread to give it back: give it back now."""
    global _lock, _timer, _depth
    _lock = threading.Lock()  # the parent's may have been held by another thread at the fork
    _timer, _depth = None, 0
    if _raised and _libc:
        _release(_libc)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def release_heap() -> None:
    """Give the memory kept after the last call back now (no waiting for :data:`KEEP_SECONDS`); a no-op during a
    call, off glibc, or when nothing is kept."""
    global _timer
    libc = _glibc()
    if libc is None:
        return
    with _lock:
        if _timer is not None:
            _timer.cancel()
            _timer = None
        if _depth == 0 and _raised:
            _release(libc)
