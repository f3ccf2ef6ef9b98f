"""Inference: denoise multi-layer EXR renders with any registered kpcn model.

Python::

    from kpcn import denoise
    color = denoise("noisy.exr")                                   # shipped default weights
    color = denoise("noisy.exr", "results/small/model.safetensors", out_path="clean.exr")
    result = denoise_result(frame, model)                          # colour + DenoiseStats

Command line: ``kpcn-denoise in.exr -o out.exr`` (or ``python -m kpcn.inference``).

Modules: :mod:`.weights` (which model a call means), :mod:`.tiling` (aligned
tiles with a halo), :mod:`.pipeline` (one frame, end to end), :mod:`.paths`
(which file a path names: no output ever replaces an input, for the API and the
CLI alike), :mod:`.heap` (memory reused within and between calls; :func:`release_heap` gives it back
at once), :mod:`.ensemble` (``views=N``: the mean of mirrored denoisings), :mod:`.cli`.
"""
from .heap import release_heap
from .pipeline import PASSTHROUGH_REL_STD, denoise, denoise_result
from .results import DenoiseResult, DenoiseStats, peak_rss_mb
from .tiling import Tile, plan_tiles, tile_size
from .weights import DEFAULT_MODEL, DefaultWeightsMissing, describe, load_model, resolve_device, resolve_weights

__all__ = [
    "denoise",
    "denoise_result",
    "load_model",
    "resolve_weights",
    "resolve_device",
    "describe",
    "DenoiseResult",
    "DenoiseStats",
    "DefaultWeightsMissing",
    "DEFAULT_MODEL",
    "PASSTHROUGH_REL_STD",
    "Tile",
    "plan_tiles",
    "tile_size",
    "peak_rss_mb",
    "release_heap",
]
