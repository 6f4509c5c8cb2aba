"""Canonical fields: hash grid, SDF network (gradient, Hessian, curvature), appearance and shape networks,
and SDF pretraining on a mesh."""

from .appearance import AppearanceNetwork, sh_basis
from .hashgrid import HashGrid
from .pretrain import PretrainConfig, SDFPretrainer
from .sdf import SDFNetwork, hessian_fd, principal_curvatures, tangent_basis
from .shape import ShapeNetwork, frame_from_symmetric, safe_eigh, symmetric_from_tril

__all__ = [
    "AppearanceNetwork",
    "HashGrid",
    "PretrainConfig",
    "SDFNetwork",
    "SDFPretrainer",
    "ShapeNetwork",
    "frame_from_symmetric",
    "hessian_fd",
    "principal_curvatures",
    "safe_eigh",
    "sh_basis",
    "symmetric_from_tril",
    "tangent_basis",
]
