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
"""
from __future__ import annotations

import os
import tempfile
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


class ExrError(RuntimeError):
    """A file could not be read or written as a kpcn EXR."""


class MissingLayerError(ExrError, KeyError):
    """Layers a consumer needs are absent; the message names them and what was found."""

    def __init__(self, path, missing: Iterable[str], found: Iterable[str]):
        self.missing = sorted(missing)
        self.found = sorted(found)
        msg = (
            f"{path}: missing layer(s) {', '.join(self.missing)}; "
            f"found: {', '.join(self.found) if self.found else 'none'}"
        )
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
        return Frame({k: v[y0:y1, x0:x1] for k, v in self.layers.items()}, dict(self.meta), self.path)


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
    return meta


def read_exr(path: str | os.PathLike, require: Iterable[str] = (), *, warn: bool = True) -> Frame:
    """Read a multi-layer EXR into a :class:`Frame`.

    Args:
        path: the EXR file.
        require: layer names that must be present (e.g. :data:`BASE_LAYERS`);
            if any is absent a :class:`MissingLayerError` names the missing and
            the found layers.
        warn: emit a warning that counts replaced NaN/Inf values.

    Returns:
        A frame whose layers are float32 ``(H, W, C)`` arrays. NaN and -Inf are
        replaced by 0 and +Inf by the layer's largest finite value (0 if none);
        the counts are in ``frame.nonfinite``.

    Raises:
        FileNotFoundError: the path does not exist.
        ExrError: the file is not a readable EXR (truncated, corrupt, not EXR).
    """
    import OpenEXR

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(path, separate_channels=True) as f:
            header = dict(f.header())
            channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises RuntimeError without the reason
        size = os.path.getsize(path)
        raise ExrError(
            f"{path}: cannot read as OpenEXR ({exc}); file size {size} bytes — "
            "is it truncated, still being written, or not an EXR?"
        ) from exc

    layers: dict[str, np.ndarray] = {}
    for layer, suffixes in _group_channels(channels).items():
        picked = _pick_channels(layer, suffixes)
        if picked is None:
            continue
        arr = np.stack([channels[c].astype(np.float32, copy=False) for c in picked], axis=-1)
        layers[layer] = np.ascontiguousarray(arr)

    frame = Frame(layers, _header_meta(header), path)
    frame.require(require)
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


def atomic_write(path: str | os.PathLike, write_fn) -> None:
    """Call ``write_fn(tmp_path)`` on a temporary name in the target folder, then rename.

    A crash mid-write leaves the previous file (if any) untouched and no
    half-written file under ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
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
    are int, float or str. ``half=True`` stores float16.
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
    for key, value in (meta or {}).items():
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
