"""Multi-layer EXR buffers: read, validate and write the kpcn contract (DESIGN §2.1).

A render is a :class:`Frame`: a dict of named layers, each a float32 array of
shape ``(H, W, C)`` with ``C`` = 3 (colour-like) or 1 (depth, one-channel
variances), plus header metadata (``spp``, ``renderTimeSeconds``, ``seed``,
``scene``).

Canonical layer names are ``color``, ``diffuse``, ``specular``, ``albedo``,
``normal``, ``depth`` and ``<layer>Variance``. On reading, the aliases used by
other tools are accepted: ``R G B`` / ``color.*`` / ``default.*`` for the colour,
``.X .Y .Z`` for normals, ``depth.Z/.R/.V`` for depth, and the Tungsten layer
names of the original KPCN data set (which match ours).

Multi-part files are read whole (the channels of every part, see
:func:`read_exr`); tiled mip-mapped files are read at level 0; the data and
display windows are kept in ``frame.meta`` and written back by
:func:`write_exr`. Writes are atomic, and the temporaries a killed writer left
are removed by the next write to the same target (:func:`atomic_write`).
"""
from __future__ import annotations

import functools
import io as _io
import os
import re
import socket
import struct
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

__all__ = [
    "Frame",
    "ExrError",
    "MissingLayerError",
    "read_exr",
    "write_exr",
    "atomic_write",
    "remove_stale_temporaries",
    "STALE_TEMP_AGE_S",
    "BASE_LAYERS",
    "FEATURE_LAYERS",
]

#: Layers with three channels; everything else (depth) has one.
RGB_LAYERS = ("color", "diffuse", "specular", "albedo", "normal")
#: The layers a KPCN/DPCN model reads (variances are listed separately).
BASE_LAYERS = ("color", "diffuse", "specular", "albedo", "normal", "depth")
FEATURE_LAYERS = BASE_LAYERS + tuple(f"{n}Variance" for n in BASE_LAYERS)

_COLOR_ALIASES = {"", "color", "colour", "default", "rgb", "rgba"}
_CHANNEL_ORDER = {
    # suffix sets accepted for a three-channel layer, in output order
    3: (("R", "G", "B"), ("X", "Y", "Z"), ("r", "g", "b"), ("x", "y", "z")),
}
_SINGLE = ("Y", "Z", "R", "V", "A", "y", "z", "r", "v")
_HEADER_KEYS = ("spp", "renderTimeSeconds", "seed", "scene")
#: ``frame.meta`` keys of the EXR windows, each ``((xmin, ymin), (xmax, ymax))`` in pixels (inclusive)
WINDOW_KEYS = ("dataWindow", "displayWindow")


class ExrError(RuntimeError):
    """A file could not be read or written as a kpcn EXR."""


class MissingLayerError(ExrError, KeyError):
    """Layers a consumer needs are absent; the message names them and what was found."""

    def __init__(self, path, missing: Iterable[str], found: Iterable[str], note: str = ""):
        self.missing = sorted(missing)
        self.found = sorted(found)
        msg = (
            f"{path}: missing layer(s) {', '.join(self.missing)}; "
            f"found: {', '.join(self.found) if self.found else 'none'}"
        )
        if note:
            msg += f" ({note})"
        super().__init__(msg)

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return self.args[0]


@dataclass
class Frame:
    """One render: named ``(H, W, C)`` float32 layers and header metadata."""

    layers: dict[str, np.ndarray]
    meta: dict = field(default_factory=dict)
    path: str | None = None
    #: number of NaN/Inf values replaced per layer when the frame was read
    nonfinite: dict[str, int] = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.layers[name]
        except KeyError:
            raise MissingLayerError(self.path or "frame", [name], self.layers) from None

    def __contains__(self, name: str) -> bool:
        return name in self.layers

    def get(self, name: str, default=None):
        return self.layers.get(name, default)

    @property
    def shape(self) -> tuple[int, int]:
        h, w = next(iter(self.layers.values())).shape[:2]
        return h, w

    @property
    def spp(self) -> int | None:
        s = self.meta.get("spp")
        return int(s) if s is not None else None

    def require(self, names: Iterable[str]) -> None:
        """Raise :class:`MissingLayerError` unless every layer in ``names`` is present."""
        missing = [n for n in names if n not in self.layers]
        if missing:
            raise MissingLayerError(self.path or "frame", missing, self.layers)

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> "Frame":
        """Rows ``y0:y1`` and columns ``x0:x1``; a ``dataWindow`` in the metadata moves with the crop."""
        meta = dict(self.meta)
        if "dataWindow" in meta and self.layers:
            h, w = self.shape
            ys, ye, _ = slice(y0, y1).indices(h)
            xs, xe, _ = slice(x0, x1).indices(w)
            (wx, wy), _ = _window(meta["dataWindow"], "dataWindow")
            meta["dataWindow"] = ((wx + xs, wy + ys), (wx + max(xe, xs) - 1, wy + max(ye, ys) - 1))
        return Frame({k: v[y0:y1, x0:x1] for k, v in self.layers.items()}, meta, self.path)


# ----------------------------------------------------------------------------- reading


def _split_name(channel: str) -> tuple[str, str]:
    if "." in channel:
        layer, suffix = channel.rsplit(".", 1)
    else:
        layer, suffix = "", channel
    return layer, suffix


def _canonical_layer(layer: str) -> str:
    low = layer.lower()
    if low in _COLOR_ALIASES:
        return "color"
    for alias in ("color", "colour", "default"):
        if low == alias + "variance":
            return "colorVariance"
    if low == "variance":
        return "colorVariance"
    return layer


def _group_channels(names: Iterable[str]) -> dict[str, dict[str, str]]:
    groups: dict[str, dict[str, str]] = {}
    for name in names:
        layer, suffix = _split_name(name)
        groups.setdefault(_canonical_layer(layer), {})[suffix] = name
    return groups


def _pick_channels(layer: str, suffixes: Mapping[str, str]) -> list[str] | None:
    base = layer[: -len("Variance")] if layer.endswith("Variance") else layer
    if base in RGB_LAYERS:
        for order in _CHANNEL_ORDER[3]:
            if all(s in suffixes for s in order):
                return [suffixes[s] for s in order]
        if not layer.endswith("Variance"):
            return None
    # one-channel layer (depth, or a variance stored as one channel)
    for s in _SINGLE:
        if s in suffixes:
            return [suffixes[s]]
    if len(suffixes) == 1:
        return list(suffixes.values())
    # a three-channel layer we do not know: keep RGB if present
    for order in _CHANNEL_ORDER[3]:
        if all(s in suffixes for s in order):
            return [suffixes[s] for s in order]
    return None


def _header_meta(header: Mapping) -> dict:
    meta = {}
    for key in _HEADER_KEYS:
        if key in header:
            value = header[key]
            if isinstance(value, bytes):
                value = value.decode("utf-8", "replace")
            meta[key] = value
    for key in WINDOW_KEYS:
        if key in header:
            try:
                meta[key] = _window(header[key], key)
            except ValueError:
                pass
    return meta


def _window(value, key: str = "window") -> tuple[tuple[int, int], tuple[int, int]]:
    """``((xmin, ymin), (xmax, ymax))`` from a box given as two pairs or four numbers."""
    try:
        a = np.asarray([np.asarray(v).ravel() for v in value] if len(value) == 2 else value).ravel()
        if a.size != 4 or not np.all(np.isfinite(a.astype(np.float64))) or np.any(a != np.round(a)):
            raise ValueError
        x0, y0, x1, y1 = (int(v) for v in a)
    except (TypeError, ValueError):
        raise ValueError(
            f"{key}: expected ((xmin, ymin), (xmax, ymax)) in integer pixels, got {value!r}"
        ) from None
    if x1 < x0 - 1 or y1 < y0 - 1:
        raise ValueError(f"{key}: max corner {(x1, y1)} is left of / above min corner {(x0, y0)}")
    return (x0, y0), (x1, y1)


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


def _part_summary(parts: list[_Part], limit: int = 8) -> str:
    out = []
    for p in parts:
        names = sorted(p.channels)
        shown = ", ".join(names[:limit]) + (f", … {len(names) - limit} more" if len(names) > limit else "")
        out.append(f"{p.name or f'part {p.index}'!r}: {shown or 'no channels'}")
    return "; ".join(out)


def _merge_parts(path: str, parts: list[_Part], multi: bool) -> tuple[dict[str, np.ndarray], dict]:
    """The channels of all parts under one namespace, and the metadata (first part's first).

    In a multi-part file a channel keeps its name when it names its layer
    (``diffuse.R``: OpenEXR's convention, the part name only labels the part);
    a bare channel (``R``) in a part named after a layer (``diffuse``) becomes
    ``diffuse.R``, except in a part named like the colour (``rgba``, ``rgb``,
    ``color``, ``default``…). Parts whose data window differs from the first
    image part's, and deep parts, are left out with a warning; so is a channel
    name that an earlier part already gave.
    """
    image = [p for p in parts if "deep" not in _storage(p.header)]
    skipped = [p for p in parts if p not in image]
    if not image:
        raise ExrError(f"{path}: only deep parts ({_part_summary(parts)}); kpcn reads flat images")
    base = image[0]
    base_window = _window(base.header["dataWindow"], "dataWindow") if "dataWindow" in base.header else None
    channels: dict[str, np.ndarray] = {}
    origin: dict[str, str] = {}
    clashes = []
    meta: dict = {}
    for p in image:
        if p is not base and "dataWindow" in p.header and _window(p.header["dataWindow"]) != base_window:
            skipped.append(p)
            continue
        for key, value in _header_meta(p.header).items():
            meta.setdefault(key, value)
        label = p.name or f"part {p.index}"
        prefix = "" if not multi or _canonical_layer(p.name) == "color" else p.name
        for cname, arr in p.channels.items():
            full = cname if ("." in cname or not prefix) else f"{prefix}.{cname}"
            if full in channels:
                clashes.append(f"{full} (in {origin[full]!r} and {label!r})")
                continue
            channels[full] = arr
            origin[full] = label
    if skipped:
        desc = ", ".join(
            f"{p.name or f'part {p.index}'!r} ({_storage(p.header)}, dataWindow {_window(p.header['dataWindow']) if 'dataWindow' in p.header else '?'})"
            for p in skipped
        )
        warnings.warn(
            f"{path}: multi-part file: left out part(s) {desc}: kpcn reads flat parts with the data window "
            f"{base_window} of part {base.name or base.index!r}",
            RuntimeWarning,
            stacklevel=3,
        )
    if clashes:
        warnings.warn(
            f"{path}: multi-part file: channel name(s) given by two parts, the first kept: {', '.join(clashes)}",
            RuntimeWarning,
            stacklevel=3,
        )
    return channels, meta


def read_exr(path: str | os.PathLike, require: Iterable[str] = (), *, warn: bool = True) -> Frame:
    """Read a multi-layer EXR into a :class:`Frame`.

    Args:
        path: the EXR file. A multi-part file is read whole: the channels of
            all its parts are merged (see :func:`_merge_parts` for the names).
            A tiled mip- or rip-mapped file is read at its full resolution
            (level 0).
        require: layer names that must be present (e.g. :data:`BASE_LAYERS`);
            if any is absent a :class:`MissingLayerError` names the missing and
            the found layers (and, for a multi-part file, its parts).
        warn: emit a warning that counts replaced NaN/Inf values.

    Returns:
        A frame whose layers are float32 ``(H, W, C)`` arrays. NaN and -Inf are
        replaced by 0 and +Inf by the layer's largest finite value (0 if none);
        the counts are in ``frame.nonfinite``. ``frame.meta`` holds the header's
        ``spp``, ``renderTimeSeconds``, ``seed`` and ``scene`` and the windows
        ``dataWindow`` and ``displayWindow`` as ``((xmin, ymin), (xmax, ymax))``
        (pass them to :func:`write_exr` to keep them).

    Raises:
        FileNotFoundError: the path does not exist.
        ExrError: the file is not a readable EXR (truncated, corrupt, not EXR).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"EXR file not found: {path}")
    parts, lost = _read_parts(path)
    if lost:
        warnings.warn(
            f"{path}: multi-part file: part(s) {'; '.join(lost)} could not be read and are left out",
            RuntimeWarning,
            stacklevel=2,
        )
    channels, meta = _merge_parts(path, parts, multi=len(parts) > 1 or bool(lost))

    if "dataWindow" in meta:
        (x0, y0), (x1, y1) = meta["dataWindow"]
        size = (y1 - y0 + 1, x1 - x0 + 1)
    else:
        size = next((a.shape for a in channels.values()), None)
    layers: dict[str, np.ndarray] = {}
    odd = []
    for layer, suffixes in _group_channels(channels).items():
        picked = _pick_channels(layer, suffixes)
        if picked is None:
            continue
        if any(channels[c].shape != size for c in picked):  # x/y-subsampled channels
            odd.append(f"{layer} ({', '.join(f'{c}: {channels[c].shape}' for c in picked)})")
            continue
        arr = np.stack([channels[c].astype(np.float32, copy=False) for c in picked], axis=-1)
        layers[layer] = np.ascontiguousarray(arr)
    if odd:
        warnings.warn(
            f"{path}: left out layer(s) whose channels are subsampled (not {size}): {', '.join(odd)}",
            RuntimeWarning,
            stacklevel=2,
        )

    frame = Frame(layers, meta, path)
    missing = [n for n in require if n not in layers]
    if missing:
        note = ""
        if len(parts) > 1 or lost:
            note = f"multi-part file; parts {_part_summary(parts)}"
            if lost:
                note += f"; unreadable part(s) {'; '.join(lost)}"
        raise MissingLayerError(path, missing, layers, note)
    frame.nonfinite = sanitize_layers(frame.layers)
    if warn and frame.nonfinite:
        counts = ", ".join(f"{k}: {v}" for k, v in frame.nonfinite.items())
        warnings.warn(f"{path}: replaced non-finite values ({counts})", RuntimeWarning, stacklevel=2)
    return frame


def sanitize_layers(layers: dict[str, np.ndarray]) -> dict[str, int]:
    """Replace NaN/-Inf by 0 and +Inf by the layer's largest finite value, in place.

    Returns the number of replaced values per layer (only layers with any).
    """
    counts = {}
    for name, arr in layers.items():
        bad = ~np.isfinite(arr)
        n = int(bad.sum())
        if not n:
            continue
        finite = arr[~bad]
        top = float(finite.max()) if finite.size else 0.0
        fixed = np.where(np.isposinf(arr), max(top, 0.0), arr)
        fixed = np.where(np.isnan(fixed) | np.isneginf(fixed), 0.0, fixed).astype(np.float32)
        layers[name] = fixed
        counts[name] = n
    return counts


# ----------------------------------------------------------------------------- writing


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


def _channel_names(layer: str, n: int) -> list[str]:
    if layer == "color":
        return ["R", "G", "B"] if n == 3 else ["Y"]
    if n == 1:
        return [f"{layer}.Y"]
    if n == 3:
        return [f"{layer}.{s}" for s in "RGB"]
    raise ValueError(f"layer {layer!r}: expected 1 or 3 channels, got {n}")


def write_exr(
    path: str | os.PathLike,
    layers: Mapping[str, np.ndarray],
    meta: Mapping | None = None,
    *,
    half: bool = False,
) -> None:
    """Write named ``(H, W, C)`` (or ``(H, W)``) layers as one multi-layer EXR, atomically.

    ``meta`` keys ``spp`` (int), ``renderTimeSeconds`` (float), ``seed`` (int)
    and ``scene`` (str) become header attributes; other keys are written if they
    are int, float or str. ``dataWindow`` and ``displayWindow`` (as
    :func:`read_exr` gives them, ``((xmin, ymin), (xmax, ymax))``) set the
    file's windows: the data window must have the layers' size (ValueError
    otherwise); without one it is ``(0, 0)-(W-1, H-1)``, and without a display
    window the display window is the data window. ``half=True`` stores float16.
    """
    import OpenEXR

    if not layers:
        raise ValueError("write_exr: no layers to write")
    dtype = np.float16 if half else np.float32
    channels: dict[str, np.ndarray] = {}
    shape = None
    for name, arr in layers.items():
        a = np.asarray(arr)
        if a.ndim == 2:
            a = a[..., None]
        if a.ndim != 3:
            raise ValueError(f"layer {name!r}: expected (H, W, C), got shape {a.shape}")
        if shape is None:
            shape = a.shape[:2]
        elif a.shape[:2] != shape:
            raise ValueError(f"layer {name!r}: size {a.shape[:2]} differs from {shape}")
        for c, cname in enumerate(_channel_names(name, a.shape[2])):
            # OpenEXR.File.write replaces the arrays it is given: always pass copies
            channels[cname] = np.ascontiguousarray(a[..., c], dtype=dtype).copy()

    header: dict = {"compression": OpenEXR.ZIP_COMPRESSION}
    meta = dict(meta or {})
    windows = {k: _window(meta.pop(k), k) for k in WINDOW_KEYS if meta.get(k) is not None}
    if windows:
        h, w = shape
        data = windows.get("dataWindow", ((0, 0), (w - 1, h - 1)))
        (x0, y0), (x1, y1) = data
        if (y1 - y0 + 1, x1 - x0 + 1) != (h, w):
            raise ValueError(
                f"write_exr: meta dataWindow {data} is {x1 - x0 + 1}x{y1 - y0 + 1} pixels, "
                f"but the layers are {w}x{h}"
            )
        display = windows.get("displayWindow", data)
        for key, ((a0, b0), (a1, b1)) in (("dataWindow", data), ("displayWindow", display)):
            header[key] = (np.array([a0, b0], dtype=np.int32), np.array([a1, b1], dtype=np.int32))
    for key, value in meta.items():
        if isinstance(value, (bool, np.bool_)):
            value = int(value)
        if isinstance(value, (int, np.integer)):
            header[key] = int(value)
        elif isinstance(value, (float, np.floating)):
            header[key] = float(value)
        elif isinstance(value, str):
            header[key] = value

    def _write(tmp: str) -> None:
        OpenEXR.File(header, channels).write(tmp)

    atomic_write(path, _write)
