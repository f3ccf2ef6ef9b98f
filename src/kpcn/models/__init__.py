"""Denoising networks, their contract (:class:`DenoiserModel`) and the model registry.

Adding a model is one file here (a config dataclass, a :class:`DenoiserModel`
subclass, a ``@register_model`` factory and, when weights ship, a
``register_weights`` line) plus its import in :func:`registry._ensure_builtin_models`.
"""

from ..inputs import SPECULAR_LOG_MAX
from .base import DenoiserModel, check_inputs
from .cost import macs_per_pixel
from .kpcn import EPS, BranchConfig, Denoiser, DPCNBranch, KPCNBranch, reconstruct
from .registry import (
    WEIGHTS_DIR,
    create_model,
    is_model,
    list_models,
    list_weights,
    model_config_class,
    register_model,
    register_weights,
    weights_entry,
)
from .mskpcn import MSKPCN, MSKPCNConfig
from .unet import UNetConfig, UNetKPCN

__all__ = [
    "EPS",
    "SPECULAR_LOG_MAX",
    "BranchConfig",
    "Denoiser",
    "DenoiserModel",
    "DPCNBranch",
    "KPCNBranch",
    "MSKPCN",
    "MSKPCNConfig",
    "UNetConfig",
    "UNetKPCN",
    "WEIGHTS_DIR",
    "check_inputs",
    "macs_per_pixel",
    "reconstruct",
    "create_model",
    "is_model",
    "list_models",
    "list_weights",
    "model_config_class",
    "register_model",
    "register_weights",
    "weights_entry",
]
