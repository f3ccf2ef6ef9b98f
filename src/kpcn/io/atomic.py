"""Atomic file writes (:func:`atomic_write`) and the removal of temporaries a killed writer left."""
from __future__ import annotations

import functools
import os
import re
import socket
import tempfile
import time
from pathlib import Path


#: Age (seconds since the last change) after which a temporary of :func:`atomic_write` whose writer
#: cannot be checked — from another machine, or named before the writer's pid was — counts as stale.
STALE_TEMP_AGE_S = 24 * 3600.0

# the middle of a temporary's name: "<pid>-<host>.<8 random>" (the host is optional), or "<8 random>"
# (kpcn before it put the writer's pid there); mkstemp's random part is 8 of [a-z0-9_]
_TEMP_MIDDLE = re.compile(r"(?:(?P<pid>[0-9]+)(?:-(?P<host>[A-Za-z0-9-]+))?\.)?(?P<rand>[a-z0-9_]{8})")


@functools.lru_cache(maxsize=1)
def _host_tag() -> str:
    """This machine's name as it goes into temporary names (letters, digits and '-')."""
    try:
        host = socket.gethostname()
    except OSError:
        host = ""
    host = re.sub(r"[^A-Za-z0-9-]+", "-", host).strip("-")[:40]
    return host or "localhost"


def _pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (True when that cannot be told)."""
    if os.name != "posix" or pid <= 0:
        return True  # os.kill(pid, 0) would end the process on Windows
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: it exists, as another user's
        return True
    return True


def _temp_affixes(path: Path) -> tuple[str, str]:
    return f".{path.name}.", ".tmp" + path.suffix


def remove_stale_temporaries(path: str | os.PathLike) -> list[str]:
    """Remove temporaries that :func:`atomic_write` left for ``path`` when its writer was killed.

    Only the temporaries of this target (``.<name>.<pid>-<host>.<random>.tmp<suffix>`` in
    its folder) are considered. One goes when its writer ran on this machine and its
    pid names no process now, or — when the writer cannot be checked (another
    machine, or a name without a pid) — when it has not changed for
    :data:`STALE_TEMP_AGE_S`. A live process's temporary is never removed. Errors
    (a file already gone, no permission) are ignored.

    Returns:
        The paths removed.
    """
    path = Path(path)
    prefix, suffix = _temp_affixes(path)
    host = _host_tag()
    now = time.time()
    removed = []
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return removed
    for entry in entries:
        name = entry.name
        if not (name.startswith(prefix) and name.endswith(suffix)) or len(name) <= len(prefix) + len(suffix):
            continue
        m = _TEMP_MIDDLE.fullmatch(name[len(prefix): len(name) - len(suffix)])
        if m is None:
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            if m["pid"] is not None and m["host"] in (None, host):
                stale = not _pid_alive(int(m["pid"]))
            else:
                stale = now - entry.stat(follow_symlinks=False).st_mtime > STALE_TEMP_AGE_S
            if stale:
                os.unlink(entry.path)
                removed.append(entry.path)
        except (OSError, ValueError):
            continue
    return removed


def atomic_write(path: str | os.PathLike, write_fn) -> None:
    """Call ``write_fn(tmp_path)`` on a temporary name in the target folder, then rename.

    A crash mid-write leaves the previous file (if any) untouched and no
    half-written file under ``path``. The temporary is
    ``.<name>.<pid>-<host>.<random>.tmp<suffix>``; before writing, the
    temporaries of the same target whose writer is gone are removed
    (:func:`remove_stale_temporaries`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        remove_stale_temporaries(path)
    except Exception:  # cleaning up is a courtesy: it never fails a write
        pass
    prefix, suffix = _temp_affixes(path)
    fd, tmp = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}-{_host_tag()}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        write_fn(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
