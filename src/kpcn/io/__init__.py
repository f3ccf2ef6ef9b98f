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

The package's modules: :mod:`~kpcn.io.frame` (:class:`Frame`, the layer names,
the errors, the windows), :mod:`~kpcn.io.names` (EXR channel names ↔ layers),
:mod:`~kpcn.io.parts` (the parts of a file, multi-part and mip-mapped),
:mod:`~kpcn.io.read` (:func:`read_exr`), :mod:`~kpcn.io.sanitize` (NaN/Inf),
:mod:`~kpcn.io.write` (:func:`write_exr`) and :mod:`~kpcn.io.atomic`
(:func:`atomic_write`, stale temporaries). The public names, and the helpers
the tests reach here, are re-exported; the other helpers live in their modules.
"""
from __future__ import annotations

from .atomic import STALE_TEMP_AGE_S, _host_tag, atomic_write, remove_stale_temporaries
from .frame import (BASE_LAYERS, FEATURE_LAYERS, RGB_LAYERS, SAMPLE_COUNT, WINDOW_KEYS, ExrError, Frame,
                    MissingLayerError)
from .names import _channel_names
from .read import read_exr
from .sanitize import sanitize_layers
from .write import write_exr

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
    "SAMPLE_COUNT",
]

# Importable from kpcn.io without being in ``__all__``, as before the split: used by
# kpcn.inference (sanitize_layers) and by the tests (the helpers). Naming them here
# marks the imports as used.
_ALSO_EXPORTED = (RGB_LAYERS, WINDOW_KEYS, sanitize_layers, _channel_names, _host_tag)

# The errors keep the qualified name they had (tracebacks print kpcn.io.MissingLayerError).
ExrError.__module__ = MissingLayerError.__module__ = __name__
