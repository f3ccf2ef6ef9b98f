"""kpcn: learned kernel-predicting denoisers for Monte Carlo renderings.

``from kpcn import denoise``; ``denoise("frame.exr")`` denoises a multi-layer
EXR with the shipped default model (:mod:`kpcn.inference`). Submodules follow
the data: :mod:`kpcn.io` → :mod:`kpcn.render` → :mod:`kpcn.inputs` /
:mod:`kpcn.features` / :mod:`kpcn.data` → :mod:`kpcn.models` and
:mod:`kpcn.ops` → :mod:`kpcn.train` / :mod:`kpcn.inference` → :mod:`kpcn.report`.
"""
from importlib import import_module

__version__ = "0.2.0"

_LAZY = {
    "denoise": ("kpcn.inference", "denoise"),
    "denoise_result": ("kpcn.inference", "denoise_result"),
    "load_model": ("kpcn.inference", "load_model"),
    "create_model": ("kpcn.models", "create_model"),
    "list_models": ("kpcn.models", "list_models"),
    "read_exr": ("kpcn.io", "read_exr"),
    "write_exr": ("kpcn.io", "write_exr"),
}


def __getattr__(name):
    # imported on first use so `import kpcn` stays light (torch is not loaded by `import kpcn`)
    if name in _LAZY:
        module, attr = _LAZY[name]
        value = getattr(import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'kpcn' has no attribute {name!r}")


__all__ = ["__version__", *_LAZY]
