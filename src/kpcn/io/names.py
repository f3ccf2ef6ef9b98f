"""EXR channel names ↔ kpcn layers: the aliases accepted on reading, the names written.

Reading groups channels ``<layer>.<suffix>`` by canonical layer (the colour's
aliases ``R G B`` / ``color.*`` / ``default.*``… become ``color``) and picks the
channels of each layer in output order; writing names a layer's channels
``<layer>.R/G/B`` or ``<layer>.Y`` (the colour as bare ``R G B``).
"""
from __future__ import annotations

from typing import Iterable, Mapping

from .frame import RGB_LAYERS

_COLOR_ALIASES = {"", "color", "colour", "default", "rgb", "rgba"}
_CHANNEL_ORDER = {
    # suffix sets accepted for a three-channel layer, in output order
    3: (("R", "G", "B"), ("X", "Y", "Z"), ("r", "g", "b"), ("x", "y", "z")),
}
_SINGLE = ("Y", "Z", "R", "V", "A", "y", "z", "r", "v")


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
    if base != "depth":  # another tool's three-channel layer (a light group, an AOV): keep it whole
        for order in _CHANNEL_ORDER[3]:
            if all(s in suffixes for s in order):
                return [suffixes[s] for s in order]
    # one-channel layer (depth, or a variance stored as one channel)
    for s in _SINGLE:
        if s in suffixes:
            return [suffixes[s]]
    if len(suffixes) == 1:
        return list(suffixes.values())
    return None


def _channel_names(layer: str, n: int) -> list[str]:
    if layer == "color":
        return ["R", "G", "B"] if n == 3 else ["Y"]
    if n == 1:
        return [f"{layer}.Y"]
    if n == 3:
        return [f"{layer}.{s}" for s in "RGB"]
    raise ValueError(f"layer {layer!r}: expected 1 or 3 channels, got {n}")
