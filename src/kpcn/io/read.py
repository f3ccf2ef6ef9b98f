"""Reading a multi-layer EXR into a :class:`~kpcn.io.Frame`: :func:`read_exr`.

The parts of the file (:mod:`kpcn.io.parts`) are merged under one channel
namespace, the channels grouped into layers (:mod:`kpcn.io.names`), the header
metadata and windows kept in ``frame.meta``, and non-finite values replaced
(:mod:`kpcn.io.sanitize`).
"""
from __future__ import annotations

import os
import warnings
from typing import Iterable, Mapping

import numpy as np

from .cycles import convert_cycles
from .frame import WINDOW_KEYS, ExrError, Frame, MissingLayerError, _window
from .names import _canonical_layer, _group_channels, _pick_channels
from .parts import _Part, _read_parts, _storage
from .sanitize import sanitize_layers

_HEADER_KEYS = ("spp", "renderTimeSeconds", "seed", "scene", "albedoRevision", "normalRevision",
                "denoisingRevision")


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

    A Blender Cycles render (``<view layer>.<pass>`` layers, no ``diffuse`` /
    ``specular``) gets the contract layers derived from its passes, and
    ``frame.meta["source_layout"] == "cycles"`` (see :mod:`kpcn.io.cycles`); a
    missing-layer error then names the Cycles passes to enable.

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

    # a Blender Cycles render: the contract layers from its passes (kpcn.io.cycles)
    cycles = convert_cycles(layers, channels, meta, parts[0].header if parts else None, path=path)
    frame = Frame(layers, meta, path)
    missing = [n for n in require if n not in layers]
    if missing:
        note = ""
        if cycles is not None:
            note = cycles.explain(missing)
        elif len(parts) > 1 or lost:
            note = f"multi-part file; parts {_part_summary(parts)}"
            if lost:
                note += f"; unreadable part(s) {'; '.join(lost)}"
        raise MissingLayerError(path, missing, layers, note)
    frame.nonfinite = sanitize_layers(frame.layers)
    if warn and frame.nonfinite:
        counts = ", ".join(f"{k}: {v}" for k, v in frame.nonfinite.items())
        warnings.warn(f"{path}: replaced non-finite values ({counts})", RuntimeWarning, stacklevel=2)
    return frame
