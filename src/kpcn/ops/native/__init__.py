"""Native (C) inference kernels, compiled for this CPU on first use and cached.

The element-wise stages at full resolution are bounded by passes over memory, not arithmetic
(docs/measured.md, thirty-third session): a step that PyTorch runs as many passes, each reading and writing
a whole band of rows, runs here as one loop whose intermediates stay in the L1 cache. The C source lies
beside this module; :func:`library` compiles it with the system's C compiler (``cc``, or ``$CC``) for the
CPU it runs on (``-march=native``) into a cache folder, once per source, compiler and CPU, and loads it with
:mod:`ctypes`. Its loops are split between threads by OpenMP: the library needs ``libgomp.so.1``, which the
dynamic loader finds already loaded, torch's own, in a process that imported torch first (this module does), so
both share one thread pool (Python threads beside torch's spinning OpenMP threads made it slower, not faster).

Where there is no compiler, the build fails or ``KPCN_NATIVE=0`` is set, :func:`library` returns None and every
caller keeps its PyTorch path (the same function to float rounding; tests check both). The cache folder is
``$KPCN_CACHE_DIR/native``, else ``$XDG_CACHE_HOME/kpcn/native``, else ``~/.cache/kpcn/native``.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import torch  # noqa: F401  (loaded first: its libgomp.so.1 is the one the library links)

__all__ = ["library", "enabled", "status", "reset", "cache_dir", "SOURCES", "HEADERS", "FLAGS"]

#: the C sources compiled into the one library
SOURCES = ("softmax_apply.c", "upsample_guide.c", "feed_rows.c", "residual_regression.c", "branch_features.c",
           "guided_blend.c", "guided_softmax.c")
#: headers they include (part of the cache key)
HEADERS = ("kpcn_math.h", "rows.h")
#: compiler flags: vectorised for this CPU; the sources' sums and polynomials are written for float rounding,
#: no flag that changes a result beyond it (no -ffast-math)
FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-fno-trapping-math", "-fopenmp", "-fPIC", "-shared", "-std=c99")

_lock = threading.Lock()
_state: dict = {}


def enabled() -> bool:
    """False where ``KPCN_NATIVE`` is ``0``/``false``/``no``/``off`` (the PyTorch paths only)."""
    return os.environ.get("KPCN_NATIVE", "1").strip().lower() not in ("0", "false", "no", "off")


def cache_dir() -> Path:
    """Where compiled libraries are kept (see the module's docstring)."""
    root = os.environ.get("KPCN_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "kpcn")
    return Path(root) / "native"


def _cpu_identity() -> str:
    """What ``-march=native`` depends on: the machine, the CPU's model and its feature flags."""
    ident = [platform.machine()]
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if line.startswith(("model name", "flags", "Features", "CPU part")):
                    ident.append(line.strip())
                if line.strip() == "":  # the first processor's block is enough
                    break
    except OSError:
        ident.append(platform.processor())
    return "\n".join(ident)


def _compiler() -> str | None:
    cc = os.environ.get("CC") or "cc"
    return shutil.which(cc) or (shutil.which("gcc") if cc == "cc" else None)


def _build() -> tuple[ctypes.CDLL | None, str]:
    cc = _compiler()
    if cc is None:
        return None, "no C compiler (cc, gcc or $CC) on the PATH"
    here = Path(__file__).parent
    sources = [here / name for name in SOURCES]
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        return None, f"{cc} --version failed: {exc}"
    key = hashlib.sha256()
    for part in [version, " ".join(FLAGS), _cpu_identity()] + [(here / n).read_text() for n in SOURCES + HEADERS]:
        key.update(part.encode())
    folder = cache_dir()
    target = folder / f"kpcn_native_{key.hexdigest()[:20]}.so"
    if not target.exists():
        tmp = None
        try:
            folder.mkdir(parents=True, exist_ok=True)
            # compiled to a temporary name and renamed: a reader never finds a half-written library
            fd, tmp = tempfile.mkstemp(suffix=".so", dir=folder)
            os.close(fd)
            proc = subprocess.run([cc, *FLAGS, "-o", tmp, *map(str, sources)], capture_output=True, text=True,
                                  timeout=300)
            if proc.returncode != 0:
                return None, f"{cc} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}"
            os.replace(tmp, target)
        except (OSError, subprocess.SubprocessError) as exc:
            return None, f"building {target} failed: {exc}"
        finally:  # a failed or stopped build leaves nothing behind
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
    try:
        lib = ctypes.CDLL(str(target))
    except OSError as exc:
        return None, f"loading {target} failed: {exc}"
    i64, i32, ptr, f32 = ctypes.c_int64, ctypes.c_int, ctypes.c_void_p, ctypes.c_float
    lib.softmax_apply_rows.argtypes = [ptr, i64, i64, i32, f32, ptr, i64, i64, i32, ptr, i64, i64, i32, i32, i32]
    lib.softmax_apply_rows.restype = None
    lib.upsample_guide_rows.argtypes = [ptr, i64, i64, i32, i32, ptr, i64, i64, i32, i32, ptr, i32, ptr, i64, i64,
                                        ptr, i32]
    lib.upsample_guide_rows.restype = None
    # low + strides, rows, width; guide + strides, channels, bf16; weights, k, s; img + strides, channels; out +
    # strides; scratch; threads
    lib.guided_softmax_rows.argtypes = [ptr, i64, i64, i32, i32, ptr, i64, i64, i32, i32, ptr, i32, f32, ptr, i64, i64,
                                        i32, ptr, i64, i64, ptr, i32]
    lib.guided_softmax_rows.restype = None
    # f, its strides, rows, width, channels; coarse + strides; fine guide + strides; coarse guide + strides; guide
    # channels, sigma; alpha, its row stride; beta, its row stride; r0, n; out + strides; scratch; threads
    lib.guided_blend_rows.argtypes = [ptr, i64, i64, i32, i32, i32, ptr, i64, i64, ptr, i64, i64, ptr, i64, i64,
                                      i32, f32, ptr, i64, ptr, i64, i32, i32, ptr, i64, i64, ptr, i32]
    lib.guided_blend_rows.restype = None
    lib.feed_rows.argtypes = [ptr, i64, i64, i32, i32, i32, i32, ptr, ptr, i32, ptr, i64, i64, i32, ptr, i64, i64, i64,
                              i32, i32]
    lib.feed_rows.restype = None
    lib.residual_regression_s2.argtypes = [ptr, i64, i64, i64, ptr, i64, i64, i64, ptr, i64, i64, i64, ptr, i32, i32,
                                           i32, f32, f32, i32, ptr, i32]
    lib.residual_regression_s2.restype = None
    lib.branch_features_rows.argtypes = [ptr, ptr, ptr, i32, i32, f32, i32, i32, ptr, ptr, ptr, ptr, ptr, ptr, i32]
    lib.branch_features_rows.restype = None
    return lib, f"loaded {target}"


_UNSET = object()


def library() -> ctypes.CDLL | None:
    """The compiled library, built on the first call (None: not available; :func:`status` says why)."""
    if not enabled():
        return None
    lib = _state.get("lib", _UNSET)  # built (or failed) already: no lock on the hot path, one atomic read
    if lib is not _UNSET:
        return lib
    with _lock:
        if "lib" not in _state:
            lib, why = _build()
            _state["lib"], _state["why"] = lib, why
            if lib is None:
                warnings.warn(f"kpcn: native kernels unavailable, using the PyTorch paths ({why})", RuntimeWarning,
                              stacklevel=2)
        return _state["lib"]


def status() -> str:
    """One line: whether the native kernels are in use, and why not."""
    if not enabled():
        return "off (KPCN_NATIVE=0)"
    lib = library()
    return ("on: " if lib is not None else "unavailable: ") + _state["why"]


def reset() -> None:
    """Forget the loaded library (or the failure to build it): the next :func:`library` builds or finds it again,
    with the compiler (``$CC``) and cache folder (``$KPCN_CACHE_DIR``) set then. A library already loaded stays
    mapped in the process."""
    with _lock:
        _state.clear()
