"""Denoising networks and the model registry."""

from .kpcn import (
    EPS,
    SPECULAR_LOG_MAX,
    BranchConfig,
    Denoiser,
    DPCNBranch,
    KPCNBranch,
    reconstruct,
)
from .registry import create_model, is_model, list_models, register_model

__all__ = [
    "EPS",
    "SPECULAR_LOG_MAX",
    "BranchConfig",
    "Denoiser",
    "DPCNBranch",
    "KPCNBranch",
    "reconstruct",
    "create_model",
    "is_model",
    "list_models",
    "register_model",
]
