"""kpcn: learned denoisers (KPCN, DPCN) for Monte Carlo renderings.

``kpcn.denoise("frame.exr")`` denoises a multi-layer EXR with the shipped
default model; see :mod:`kpcn.denoise`. Submodules follow the data:
:mod:`kpcn.io` → :mod:`kpcn.render` → :mod:`kpcn.features` / :mod:`kpcn.data`
→ :mod:`kpcn.models` and :mod:`kpcn.ops` → :mod:`kpcn.train` /
:mod:`kpcn.denoise` → :mod:`kpcn.report`.
"""
from importlib import import_module

__version__ = "0.1.0"

_LAZY = {
    "create_model": ("kpcn.models", "create_model"),
    "list_models": ("kpcn.models", "list_models"),
    "read_exr": ("kpcn.io", "read_exr"),
    "write_exr": ("kpcn.io", "write_exr"),
    "load_model": ("kpcn.denoise", "load_model"),
}


def __getattr__(name):
    # `kpcn.denoise` is the module, callable as the function (see kpcn/denoise.py);
    # the rest are imported on first use so `import kpcn` stays light.
    if name == "denoise":
        return import_module("kpcn.denoise")
    if name in _LAZY:
        module, attr = _LAZY[name]
        return getattr(import_module(module), attr)
    raise AttributeError(f"module 'kpcn' has no attribute {name!r}")


__all__ = ["denoise", "__version__", *_LAZY]
