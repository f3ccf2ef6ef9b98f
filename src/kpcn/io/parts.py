"""The parts of an EXR file as OpenEXR gives them, for :func:`kpcn.io.read_exr`.

Every part of a multi-part file is read (the parts OpenEXR drops are described,
not lost silently); a tiled mip- or rip-mapped file that OpenEXR refuses is
read at level 0 from a single-level copy made in memory; an unreadable file
gets an error that says what its header claims it is.
"""
from __future__ import annotations

import io as _io
import os
import struct
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .exr_threads import exr_threads
from .frame import ExrError


@dataclass
class _Part:
    """One part of an EXR file as read: its name, header and channel arrays."""

    index: int
    name: str
    header: dict
    channels: dict[str, np.ndarray]


def _storage(header: Mapping) -> str:
    t = header.get("type")
    if t is None:
        return "tiledimage" if "tiles" in header else "scanlineimage"
    if isinstance(t, bytes):
        return t.decode("ascii", "replace")
    return getattr(t, "name", str(t))


def _describe_file(path: str) -> str:
    """What the header of an unreadable file says (tiled, mip-mapped, parts), or ''."""
    import OpenEXR

    try:
        with OpenEXR.File(path, header_only=True) as f:
            headers = [dict(p.header) for p in f.parts] or [dict(f.header())]
    except Exception:
        return ""
    bits = []
    if len(headers) > 1:
        bits.append(f"a multi-part EXR ({len(headers)} parts)")
    for h in headers:
        tiles = h.get("tiles")
        if tiles is not None:
            bits.append(f"a tiled, {_level_mode_words(tiles)} EXR ({tiles.xSize}x{tiles.ySize} tiles)")
            break
    return " and ".join(bits)


def _level_mode_words(tiles) -> str:
    mode = getattr(getattr(tiles, "mode", None), "name", str(getattr(tiles, "mode", "")))
    return {"ONE_LEVEL": "single-level", "MIPMAP_LEVELS": "mip-mapped", "RIPMAP_LEVELS": "rip-mapped"}.get(mode, mode)


# flags of the EXR version field
_EXR_MAGIC = 20000630
_FLAG_DEEP, _FLAG_MULTIPART = 0x800, 0x1000


def _is_multipart(path: str) -> bool:
    try:
        with open(path, "rb") as fh:
            magic, version = struct.unpack("<ii", fh.read(8))
    except (OSError, struct.error):
        return False
    return magic == _EXR_MAGIC and bool(version & _FLAG_MULTIPART)


def _lost_parts(path: str, parts: list[_Part]) -> list[str]:
    """Parts of a multi-part file that OpenEXR dropped while reading (it only prints a warning)."""
    import OpenEXR

    try:
        with OpenEXR.File(path, header_only=True) as f:
            headers = [(getattr(p, "part_index", i), p.name() or "", dict(p.header)) for i, p in enumerate(f.parts)]
    except Exception:
        return []
    read = {p.index for p in parts}
    lost = []
    for i, name, header in headers:
        if i in read:
            continue
        kind = _storage(header)
        if "tiles" in header:
            kind = f"tiled, {_level_mode_words(header['tiles'])}"
        lost.append(f"{name or f'part {i}'!r} ({kind}; channels {', '.join(sorted(c.name for c in header.get('channels', [])))})")
    return lost


def _read_parts(path: str) -> tuple[list[_Part], list[str]]:
    """Every part of an EXR file, pixels included (tiled multi-level files at level 0),
    and the descriptions of the parts that could not be read."""
    import OpenEXR

    exr_threads()
    try:
        with OpenEXR.File(path, separate_channels=True) as f:
            parts = [
                _Part(getattr(p, "part_index", i), p.name() or "", dict(p.header),
                      {n: np.asarray(c.pixels) for n, c in p.channels.items()})
                for i, p in enumerate(f.parts)
            ]
        if not parts:
            raise ExrError("no readable part")
        return parts, (_lost_parts(path, parts) if _is_multipart(path) else [])
    except Exception as exc:  # OpenEXR raises RuntimeError/ValueError without the reason
        error = exc
    what = _describe_file(path)
    size = os.path.getsize(path)
    if "mapped" in what:
        try:
            return _read_level0(path), []
        except Exception as exc:
            raise ExrError(
                f"{path}: cannot read as OpenEXR ({error}); the header says it is {what}, and its "
                f"level 0 cannot be read either ({exc}); file size {size} bytes — is it truncated or "
                "still being written? (kpcn reads level 0 of tiled mip-/rip-mapped files)"
            ) from error
    said = f" the header says it is {what};" if what else ""
    raise ExrError(
        f"{path}: cannot read as OpenEXR ({error});{said} file size {size} bytes — "
        "is it truncated, still being written, or not an EXR?"
    ) from error


def _level0_bytes(data: bytes) -> bytes:
    """A single-part tiled mip-/rip-mapped EXR rewritten as a single-level one holding its level 0.

    The OpenEXR Python package writes only level 0 of such files (the other
    levels' chunk table entries stay 0), which the OpenEXR library then refuses
    as a corrupt chunk table. Level 0's chunks are self-contained, so they are
    copied as they are (compressed) behind a header whose tile description says
    ONE_LEVEL, and the copy is read from memory.
    """
    magic, version = struct.unpack_from("<ii", data, 0)
    if magic != _EXR_MAGIC:
        raise ValueError("not an OpenEXR file")
    if version & (_FLAG_DEEP | _FLAG_MULTIPART):
        raise ValueError("level 0 is recovered only from single-part, non-deep files")
    pos, attrs = 8, {}
    while True:
        if pos >= len(data):
            raise ValueError("header ends early")
        if data[pos] == 0:
            pos += 1
            break
        end = data.index(b"\0", pos)
        name = data[pos:end].decode("latin-1")
        end2 = data.index(b"\0", end + 1)
        (size,) = struct.unpack_from("<i", data, end2 + 1)
        attrs[name] = (end2 + 5, size)
        pos = end2 + 5 + size
    header_end = pos
    if "tiles" not in attrs or "dataWindow" not in attrs:
        raise ValueError("no tile description or data window in the header")
    t_at, _ = attrs["tiles"]
    tx_size, ty_size, mode = struct.unpack_from("<IIB", data, t_at)
    x0, y0, x1, y1 = struct.unpack_from("<4i", data, attrs["dataWindow"][0])
    if tx_size <= 0 or ty_size <= 0 or x1 < x0 or y1 < y0:
        raise ValueError("bad tile size or data window")
    nx = -(-(x1 - x0 + 1) // tx_size)
    ny = -(-(y1 - y0 + 1) // ty_size)
    n = nx * ny
    if header_end + 8 * n > len(data):
        raise ValueError("chunk table cut short")
    offsets = struct.unpack_from(f"<{n}Q", data, header_end)
    chunks = []
    for i, off in enumerate(offsets):
        want = (i % nx, i // nx, 0, 0)
        if off == 0 or off + 20 > len(data):
            raise ValueError(f"level-0 tile {want[:2]} is missing (offset {off}, file size {len(data)})")
        tile = struct.unpack_from("<4i", data, off)
        (size,) = struct.unpack_from("<i", data, off + 16)
        if tile != want or size < 0 or off + 20 + size > len(data):
            raise ValueError(f"level-0 tile {want[:2]} is damaged or cut short")
        chunks.append(data[off: off + 20 + size])
    head = bytearray(data[:header_end])
    head[t_at + 8] = mode & 0xF0  # ONE_LEVEL, same rounding mode
    if "chunkCount" in attrs:
        struct.pack_into("<i", head, attrs["chunkCount"][0], n)
    out = bytearray(head)
    at = len(out) + 8 * n
    table = []
    for c in chunks:
        table.append(at)
        at += len(c)
    out += struct.pack(f"<{n}Q", *table)
    for c in chunks:
        out += c
    return bytes(out)


def _read_level0(path: str) -> list[_Part]:
    import OpenEXR

    with open(path, "rb") as fh:
        data = _level0_bytes(fh.read())
    with OpenEXR.File(_io.BytesIO(data), separate_channels=True) as f:
        parts = [
            _Part(i, p.name() or "", dict(p.header), {n: np.asarray(c.pixels) for n, c in p.channels.items()})
            for i, p in enumerate(f.parts)
        ]
    if not parts:
        raise ValueError("OpenEXR cannot read the level-0 copy either")
    return parts
