"""Writing named layers as one multi-layer EXR, atomically: :func:`write_exr`."""
from __future__ import annotations

import os
from typing import Mapping

import numpy as np

from .atomic import atomic_write
from .exr_threads import exr_threads
from .frame import WINDOW_KEYS, _window
from .names import _channel_names


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

    exr_threads()

    atomic_write(path, _write)
