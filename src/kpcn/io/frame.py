"""The in-memory render: :class:`Frame`, its layer names and EXR windows, and the I/O errors."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

import numpy as np

#: Layers with three channels; everything else (depth) has one.
RGB_LAYERS = ("color", "diffuse", "specular", "albedo", "normal")
#: The layers a KPCN/DPCN model reads (variances are listed separately).
BASE_LAYERS = ("color", "diffuse", "specular", "albedo", "normal", "depth")
FEATURE_LAYERS = BASE_LAYERS + tuple(f"{n}Variance" for n in BASE_LAYERS)
#: The per-pixel sample count (one channel): a frame whose spp varies from pixel to pixel (an adaptive sampler's,
#: or :func:`kpcn.render.mix_frames`'s) says how many samples each pixel's mean and variances are of.
SAMPLE_COUNT = "sampleCount"
#: ``frame.meta`` keys of the EXR windows, each ``((xmin, ymin), (xmax, ymax))`` in pixels (inclusive)
WINDOW_KEYS = ("dataWindow", "displayWindow")


class ExrError(RuntimeError):
    """A file could not be read or written as a kpcn EXR."""


class MissingLayerError(ExrError, KeyError):
    """Layers a consumer needs are absent; the message names them and what was found."""

    def __init__(self, path, missing: Iterable[str], found: Iterable[str], note: str = ""):
        self.missing = sorted(map(str, missing))
        self.found = sorted(map(str, found))
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

    def keys(self):
        """The layer names (so ``dict(frame)`` is its layers)."""
        return self.layers.keys()

    def __iter__(self):
        return iter(self.layers)

    def __len__(self) -> int:
        return len(self.layers)

    def __bool__(self) -> bool:  # a frame is a frame even without layers (`if frame:` tests for None)
        return True

    def get(self, name: str, default=None):
        return self.layers.get(name, default)

    def preferring(self, sources: Mapping[str, str]) -> "Frame":
        """This frame with layer ``k`` read from layer ``sources[k]`` where the frame has that one.

        A shallow copy (arrays shared) when anything is replaced, with ``meta["layers_from"]``
        saying what was; ``self`` itself when nothing is.
        """
        swaps = {k: v for k, v in sources.items() if v in self.layers}
        if not swaps:
            return self
        layers = dict(self.layers)
        for k, v in swaps.items():
            layers[k] = self.layers[v]
        meta = {**self.meta, "layers_from": {**self.meta.get("layers_from", {}), **swaps}}
        return Frame(layers, meta, self.path, dict(self.nonfinite))

    def region(self, name: str, crop=None) -> np.ndarray:
        """Layer ``name`` over ``crop`` (a ``(rows, columns)`` pair of slices; None: all of it). For layers computed
        when read (:class:`kpcn.exposure.ScaledLayers`) only that region is computed."""
        if name not in self.layers:
            raise MissingLayerError(self.path or "frame", [name], self.layers)
        region = getattr(self.layers, "region", None)
        if region is not None:
            return region(name, crop)
        a = self.layers[name]
        return a if crop is None else a[crop]

    @property
    def shape(self) -> tuple[int, int]:
        arrays = getattr(self.layers, "raw", self.layers)  # a computed layer's shape is its source's
        h, w = next(iter(arrays.values())).shape[:2]
        return h, w

    @property
    def spp(self) -> int | None:
        s = self.meta.get("spp")
        return int(s) if s is not None else None

    def sample_count(self) -> np.ndarray | None:
        """``(H, W)`` float64: the samples of each pixel, from the :data:`SAMPLE_COUNT` layer, else the header's
        ``spp`` everywhere; None where the frame says neither."""
        if SAMPLE_COUNT in self.layers:
            return self.layers[SAMPLE_COUNT][..., 0].astype(np.float64)
        return None if self.spp is None else np.full(self.shape, float(self.spp))

    def beauty(self) -> np.ndarray:
        """The noisy colour ``(H, W, 3)``: the ``color`` layer, or ``diffuse + specular`` where the frame has only
        the split (a missing one is named by :class:`MissingLayerError`)."""
        if "color" in self.layers:
            color = self.layers["color"]
            if color.shape[2] == 3:
                return color
        return self["diffuse"] + self["specular"]

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
