"""Rendering: the differentiable 2D Gaussian surfel rasterizer, the mesh rasterizer (triangle id +
barycentrics, ray warping to canonical space) and the NeuS volume renderer."""

from __future__ import annotations

from ._camera import RenderCamera
from ..geometry.sh import eval_sh_colors, num_sh_coeffs, sh_basis
from .mesh_raster import (
    MeshRaster,
    points_on_mesh,
    rasterize_mesh,
    ray_directions,
    warp_directions_to_canonical,
    warp_points_to_canonical,
    warp_rays_to_canonical,
)
from .surfels import (
    BACKENDS,
    SurfelRender,
    depth_to_normal,
    depth_to_points,
    rasterize_surfels,
    resolve_backend,
)
from .volume import NeuSOutput, SVariance, render_neus

__all__ = [
    "BACKENDS",
    "MeshRaster",
    "NeuSOutput",
    "SVariance",
    "points_on_mesh",
    "rasterize_mesh",
    "ray_directions",
    "render_neus",
    "warp_directions_to_canonical",
    "warp_points_to_canonical",
    "warp_rays_to_canonical",
    "RenderCamera",
    "SurfelRender",
    "depth_to_normal",
    "depth_to_points",
    "eval_sh_colors",
    "num_sh_coeffs",
    "rasterize_surfels",
    "resolve_backend",
    "sh_basis",
]
