"""Tiles with a halo, aligned to a model's grid, so tiled inference equals untiled.

A frame is cut into ``tile x tile`` interiors. Each is computed on a crop:
the interior grown by ``halo`` pixels on every side (clamped to the frame),
with the crop's top-left corner moved down to a multiple of ``alignment`` so
a model that pools by ``alignment`` sees the same pixel grid in the crop as in
the whole frame. The interior tile size is rounded up to a multiple of the
alignment, so interiors start on the grid too. Only the interior of a crop's
result is kept: with ``halo`` at least the model's receptive radius (plus what
the features read), every kept pixel saw the same inputs as in the whole frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

__all__ = ["Tile", "plan_tiles", "tile_size", "auto_tile", "WHOLE_FRAME_PIXELS", "ROWS_WHOLE_FRAME_PIXELS"]

#: ``tile="auto"`` denoises frames up to this many pixels (1920x1080 and a little more) whole
WHOLE_FRAME_PIXELS = 2_100_000
#: ... and up to this many (4096x4096) with a model that runs whole frames in row bands
#: (:mod:`kpcn.inference.rows`: about 350 bytes a pixel, 2.9 GB at 3840x2160, and no halo computed twice)
ROWS_WHOLE_FRAME_PIXELS = 4096 * 4096


@dataclass(frozen=True)
class Tile:
    """An output interior ``[y0, y1) x [x0, x1)`` and the crop ``[cy0, cy1) x [cx0, cx1)`` it is computed on."""

    y0: int
    y1: int
    x0: int
    x1: int
    cy0: int
    cy1: int
    cx0: int
    cx1: int

    @property
    def crop(self) -> tuple[slice, slice]:
        return slice(self.cy0, self.cy1), slice(self.cx0, self.cx1)

    @property
    def interior(self) -> tuple[slice, slice]:
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    @property
    def interior_in_crop(self) -> tuple[slice, slice]:
        return slice(self.y0 - self.cy0, self.y1 - self.cy0), slice(self.x0 - self.cx0, self.x1 - self.cx0)


def tile_size(tile: int | None, alignment: int = 1) -> int | None:
    """The interior size used for ``tile`` (None or <= 0: whole frame), rounded up to the alignment."""
    if tile is None or tile <= 0:
        return None
    a = max(1, int(alignment))
    return -(-int(tile) // a) * a


def auto_tile(height: int, width: int, halo: int, alignment: int = 1, rows: bool = False) -> int | None:
    """The tile ``tile="auto"`` uses: None (the whole frame) up to :data:`WHOLE_FRAME_PIXELS`
    (:data:`ROWS_WHOLE_FRAME_PIXELS` when the model runs whole frames in row bands, ``rows``), else
    interiors of ``max(512, 4 * halo)`` pixels, so that the halo (computed twice) stays a small part."""
    if height * width <= (ROWS_WHOLE_FRAME_PIXELS if rows else WHOLE_FRAME_PIXELS):
        return None
    return tile_size(max(512, 4 * int(halo)), alignment)


def plan_tiles(height: int, width: int, tile: int | None, halo: int, alignment: int = 1) -> Iterator[Tile]:
    """Row-major tiles covering ``height x width``; ``tile`` None or <= 0: one tile, the whole frame.

    Crop corners lie on multiples of ``alignment``; see the module docstring.
    """
    a = max(1, int(alignment))
    size = tile_size(tile, a)
    th = height if size is None else size
    tw = width if size is None else size

    def start(v: int) -> int:
        return max(0, (v - halo) // a * a)

    for y0 in range(0, height, th):
        y1 = min(y0 + th, height)
        for x0 in range(0, width, tw):
            x1 = min(x0 + tw, width)
            yield Tile(y0, y1, x0, x1, start(y0), min(height, y1 + halo), start(x0), min(width, x1 + halo))
