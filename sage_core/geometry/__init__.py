"""Geometry utilities: rotations, mesh signed distance and sampling, marching cubes, mesh metrics."""

from .marching import extract_mesh
from .mesh_metrics import chamfer_distance, mesh_chamfer, normal_error
from .mesh_sdf import face_normals_and_areas, sample_surface, sign_confidence, signed_distance, vertex_normals, winding_number
from .rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
)

__all__ = [
    "axis_angle_to_matrix",
    "chamfer_distance",
    "extract_mesh",
    "face_normals_and_areas",
    "matrix_to_axis_angle",
    "matrix_to_quat",
    "mesh_chamfer",
    "normal_error",
    "quat_conjugate",
    "quat_multiply",
    "quat_normalize",
    "quat_to_matrix",
    "sample_surface",
    "sign_confidence",
    "signed_distance",
    "vertex_normals",
    "winding_number",
]
