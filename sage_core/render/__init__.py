"""Surfel rendering: the differentiable 2D Gaussian surfel rasterizer and its helpers."""

from __future__ import annotations

from ._camera import RenderCamera
from ._sh import eval_sh_colors, num_sh_coeffs, sh_basis
from .surfels import BACKENDS, SurfelRender, depth_to_normal, depth_to_points, rasterize_surfels

__all__ = [
    "BACKENDS",
    "RenderCamera",
    "SurfelRender",
    "depth_to_normal",
    "depth_to_points",
    "eval_sh_colors",
    "num_sh_coeffs",
    "rasterize_surfels",
    "sh_basis",
]
