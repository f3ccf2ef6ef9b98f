"""A timm-style model registry: models built by name from their config dataclass,
and the shipped weights registered beside them.

Usage::

    @register_model("kpcn", config=BranchConfig)
    def kpcn(config: BranchConfig) -> DenoiserModel: ...

    register_weights("kpcn", "small", "kpcn_small.safetensors", default=True)

    model = create_model("kpcn", layers=5, width=32, kernel_size=11)
    list_models()            # ['dpcn', 'kpcn', 'unet_kpcn']
    list_weights("kpcn")     # ['small']

Keyword configuration is checked by :mod:`kpcn.config` against the model's
config dataclass: an unknown key names the nearest valid one, a wrong type
names the key and the expected type.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from torch import nn

from ..config import ConfigError, from_dict
from ..exposure import TRAINED_KEYS

__all__ = [
    "register_model",
    "create_model",
    "list_models",
    "is_model",
    "model_config_class",
    "register_weights",
    "list_weights",
    "weights_entry",
    "WeightsEntry",
    "WEIGHTS_DIR",
]

#: folder of the shipped weights files
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"


@dataclass(frozen=True)
class _Entry:
    factory: Callable[..., nn.Module]
    config: type


@dataclass(frozen=True)
class WeightsEntry:
    """Shipped weights of a model: ``path`` (a weights-only file), a description, and ``config``: fields of the
    model's config that the tag sets over the file's own (stages without weights, such as the U-Net's
    ``detail_radius``), as ``((key, value), ...)``."""

    model: str
    tag: str
    path: Path
    description: str = ""
    config: tuple = ()


_MODELS: dict[str, _Entry] = {}
_WEIGHTS: dict[str, dict[str, WeightsEntry]] = {}
_DEFAULT_WEIGHTS: dict[str, str] = {}


def register_model(name: str, config: type | None = None) -> Callable:
    """Decorator registering ``fn(config) -> nn.Module`` under ``name``; ``config`` is its dataclass.

    Raises:
        ValueError: ``name`` is empty or already registered to a different factory.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"register_model: name must be a non-empty string, got {name!r}")
    if config is not None and not dataclasses.is_dataclass(config):
        raise ValueError(f"register_model({name!r}): config must be a dataclass, got {config!r}")

    def decorator(fn: Callable[..., nn.Module]) -> Callable[..., nn.Module]:
        existing = _MODELS.get(name)
        if existing is not None and (existing.factory.__module__, existing.factory.__qualname__) != (
            fn.__module__, fn.__qualname__
        ):
            raise ValueError(f"register_model: a model named {name!r} is already registered ({existing.factory!r})")
        _MODELS[name] = _Entry(fn, config)
        return fn

    return decorator


def register_weights(model: str, tag: str, filename: str, description: str = "", default: bool = False,
                     config: dict | None = None, exposure_range: tuple[float, float] | None = TRAINED_KEYS) -> None:
    """Register a shipped weights file (in :data:`WEIGHTS_DIR`) for ``model`` under ``tag``; ``config`` sets
    fields of the model's config over the file's (fields that add or remove no parameter: two tags can share a
    file, as timm's pretrained configs share weights with different inference settings).

    ``exposure_range``: the exposure keys of the frames the file was trained on, set as the config field of that
    name where the model's config has one and ``config`` does not set it (:mod:`kpcn.exposure`). Every shipped
    file was trained on kpcn's procedural frames (and Cycles' generated scenes, whose keys lie inside), hence the
    default :data:`kpcn.exposure.TRAINED_KEYS`; None: frames are denoised at their own exposure.

    Raises:
        ValueError: ``config`` names a field the model's config does not have.
    """
    entry_model = _MODELS.get(model)
    if entry_model is not None and entry_model.config is not None:
        known = {f.name for f in dataclasses.fields(entry_model.config)}
        if exposure_range is not None and "exposure_range" in known:
            config = {"exposure_range": tuple(exposure_range), **(config or {})}
        unknown = sorted(set(config or ()) - known)
        if unknown:
            raise ValueError(f"register_weights({model}:{tag}): config fields {unknown} are not fields of "
                             f"{entry_model.config.__name__}")
    entry = WeightsEntry(model, tag, WEIGHTS_DIR / filename, description, tuple(sorted((config or {}).items())))
    _WEIGHTS.setdefault(model, {})[tag] = entry
    if default or model not in _DEFAULT_WEIGHTS:
        _DEFAULT_WEIGHTS[model] = tag


def list_models() -> list[str]:
    """Sorted names of all registered models."""
    _ensure_builtin_models()
    return sorted(_MODELS)


def is_model(name) -> bool:
    _ensure_builtin_models()
    return isinstance(name, str) and name in _MODELS


def model_config_class(name: str) -> type:
    """The config dataclass of model ``name``."""
    return _entry(name).config


def list_weights(model: str | None = None) -> list[str]:
    """Tags of the shipped weights of ``model`` (or ``"model:tag"`` of all, when None)."""
    _ensure_builtin_models()
    if model is None:
        return sorted(f"{m}:{t}" for m, tags in _WEIGHTS.items() for t in tags)
    return sorted(_WEIGHTS.get(model, {}))


def weights_entry(model: str, tag: str | None = None) -> WeightsEntry:
    """The registered weights of ``model`` (its default tag when ``tag`` is None).

    Raises:
        KeyError: no such weights are registered (the message lists those that are).
    """
    _ensure_builtin_models()
    tags = _WEIGHTS.get(model, {})
    tag = tag or _DEFAULT_WEIGHTS.get(model)
    if tag is None or tag not in tags:
        shipped = ", ".join(list_weights()) or "none"
        raise KeyError(f"no shipped weights {model}:{tag or '<default>'}; shipped: {shipped}")
    return tags[tag]


def _entry(name: str) -> _Entry:
    _ensure_builtin_models()
    try:
        return _MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown model {name!r}; known models: {', '.join(sorted(_MODELS))}") from None


def create_model(name: str, **cfg) -> nn.Module:
    """Build the model registered under ``name`` from keyword configuration ``cfg``.

    ``config=`` may pass a ready config dataclass (or a dict) instead of keywords.

    Raises:
        ValueError: an unknown name (the message lists the known ones), or a
            :class:`~kpcn.config.ConfigError` for an unknown key (naming the nearest
            valid one) or a value of the wrong type.
    """
    entry = _entry(name)
    config = cfg.pop("config", None)
    if config is not None and cfg:
        raise ConfigError(f"model {name}: pass either config= or keyword fields, not both ({sorted(cfg)})")
    if config is None:
        config = cfg
    if entry.config is not None and not isinstance(config, entry.config):
        config = from_dict(entry.config, dict(config), where=f"model {name}")
    model = entry.factory(config)
    model.name = name
    return model


def _ensure_builtin_models() -> None:
    # importing the modules registers the built-in models and their weights
    from . import kpcn, mskpcn, unet  # noqa: F401
