"""A small timm-style model registry.

Usage::

    @register_model("kpcn")
    def kpcn(**cfg) -> nn.Module: ...

    model = create_model("kpcn", layers=5, width=32, kernel_size=11)
    list_models()  # ['dpcn', 'kpcn']
"""

from __future__ import annotations

from typing import Callable

from torch import nn

__all__ = ["register_model", "create_model", "list_models", "is_model"]

_MODEL_ENTRYPOINTS: dict[str, Callable[..., nn.Module]] = {}


def register_model(name: str) -> Callable[[Callable[..., nn.Module]], Callable[..., nn.Module]]:
    """Decorator registering a factory ``fn(**cfg) -> nn.Module`` under ``name``.

    Raises:
        ValueError: if ``name`` is empty or already registered to a different factory.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"register_model: name must be a non-empty string, got {name!r}")

    def decorator(fn: Callable[..., nn.Module]) -> Callable[..., nn.Module]:
        existing = _MODEL_ENTRYPOINTS.get(name)
        if existing is not None and existing is not fn and (
            existing.__module__, existing.__qualname__
        ) != (fn.__module__, fn.__qualname__):
            raise ValueError(f"register_model: a model named {name!r} is already registered ({existing!r})")
        _MODEL_ENTRYPOINTS[name] = fn
        return fn

    return decorator


def list_models() -> list[str]:
    """Sorted names of all registered models."""
    _ensure_builtin_models()
    return sorted(_MODEL_ENTRYPOINTS)


def is_model(name: str) -> bool:
    """Whether ``name`` is a registered model."""
    _ensure_builtin_models()
    return name in _MODEL_ENTRYPOINTS


def create_model(name: str, **cfg) -> nn.Module:
    """Build the model registered under ``name`` with keyword configuration ``cfg``.

    Raises:
        ValueError: for an unknown name (the message lists the known ones) or an
            unknown/invalid configuration field.
    """
    _ensure_builtin_models()
    try:
        fn = _MODEL_ENTRYPOINTS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown model {name!r}; known models: {', '.join(sorted(_MODEL_ENTRYPOINTS))}") from None
    return fn(**cfg)


def _ensure_builtin_models() -> None:
    # Importing the module registers the built-in models; harmless if already imported.
    from . import kpcn  # noqa: F401
