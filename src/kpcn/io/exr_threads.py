"""OpenEXR's own threads for (de)compressing files: on by default, and safe across ``fork``.

The OpenEXR library (de)compresses the blocks of a file on a global thread pool, which the Python package leaves
at 0 threads (all on the calling thread): a 1920×1080 render of kpcn's 32 channels (ZIP) took 0.50 s to read
single-threaded and 0.27 s with 2 threads (docs/measured.md, forty-second session; ``python -m kpcn.bench exr``).
:func:`exr_threads` gives the pool ``KPCN_EXR_THREADS`` threads (default: the CPUs this process may use, at most
8; ``0`` keeps OpenEXR's single thread), once per process, before kpcn's first read or write, unless the
application had set a count of its own (then its choice stands, and so does its care for ``fork``).

A process forked while the pool has threads inherits a pool whose threads do not exist: its first read of an EXR
waits for them forever. So when kpcn sets the count it also registers :func:`os.register_at_fork` handlers that
empty the pool before a fork (its threads joined) and restore it after, in the parent at once and in the child at
its first read or write (a worker that never touches an EXR starts no threads).
"""
from __future__ import annotations

import os
import threading

__all__ = ["ENV", "exr_threads"]

#: environment variable: OpenEXR threads for kpcn's reads and writes (0: OpenEXR's default, one thread)
ENV = "KPCN_EXR_THREADS"
#: the most threads the default gives the pool (decompression of one file gains little beyond)
MAX_DEFAULT = 8

_lock = threading.Lock()
_state = {"count": None, "registered": False}  # count: what this process set (0: left alone); None: not yet decided


def _wanted() -> int:
    raw = os.environ.get(ENV)
    if raw is not None and raw.strip():
        try:
            n = int(raw)
        except ValueError:
            raise ValueError(f"{ENV} must be a whole number of threads (0: OpenEXR's single thread), got {raw!r}") \
                from None
        if n < 0:
            raise ValueError(f"{ENV} must be >= 0, got {raw!r}")
        return n
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return min(cpus, MAX_DEFAULT)


def _set(n: int) -> None:
    import OpenEXR

    OpenEXR.set_global_thread_count(n)


def _before_fork() -> None:
    if _state["count"]:
        import OpenEXR

        _state["saved"] = OpenEXR.global_thread_count()  # kpcn's count, or one the application set since
        _set(0)  # join the pool's threads while they exist


def _after_fork_in_parent() -> None:
    if _state["count"] and _state.get("saved"):
        _set(_state["saved"])


def _after_fork_in_child() -> None:
    if _state["count"]:
        _state["count"] = None  # the pool is empty here (emptied before the fork): filled at the first read or write


def exr_threads() -> int:
    """Give OpenEXR's global thread pool its threads for this process (module docstring), once; returns the count
    kpcn set (0: none, where the application set its own, ``KPCN_EXR_THREADS`` is 0, or the OpenEXR package has no
    thread pool)."""
    count = _state["count"]
    if count is not None:
        return count
    with _lock:
        if _state["count"] is not None:
            return _state["count"]
        import OpenEXR

        n = _wanted()
        if not hasattr(OpenEXR, "set_global_thread_count") or OpenEXR.global_thread_count() != 0 \
                or not hasattr(os, "register_at_fork"):
            n = 0  # no pool to fill, the application's own count, or no fork guard on this platform
        if n:
            if not _state["registered"]:
                os.register_at_fork(before=_before_fork, after_in_parent=_after_fork_in_parent,
                                    after_in_child=_after_fork_in_child)
                _state["registered"] = True
            _set(n)
        _state["count"] = n
        return n
