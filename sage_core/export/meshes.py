"""Meshes of an avatar: the zero level set of its canonical SDF and its posed FLAME mesh, as PLY/OBJ.

The SDF lives in canonical space (the canonical timestep's mesh with zero global rotation and
translation), so its zero level set is written there. The FLAME mesh is posed by any frame's FLAME
inputs (for the canonical pose it lies in the same space as the SDF mesh).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..workspace import atomic_write_bytes

if TYPE_CHECKING:
    from ..avatar.model import Avatar

MESH_FORMATS: tuple[str, ...] = ("ply", "obj")


def sdf_mesh(avatar: Avatar, resolution: int = 256, device: str | torch.device | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the avatar's SDF over its box: vertices (V, 3) float32, faces (F, 3) int64
    (both (0, 3) when the field has no zero crossing)."""
    from ..geometry.marching import extract_mesh

    net = avatar.sdf
    dev = avatar.device if device is None else device
    return extract_mesh(net.sdf, net.bbox_min, net.bbox_max, int(resolution), device=dev)


def posed_mesh(avatar: Avatar, flame_inputs: dict[str, torch.Tensor]) -> tuple[np.ndarray, np.ndarray]:
    """The avatar's FLAME mesh (mouth interior included) for one frame: (V, 3) float32, (F, 3) int64."""
    with torch.no_grad():
        verts = avatar.pose_mesh(flame_inputs)
    return verts.detach().cpu().numpy().astype(np.float32), avatar.faces.detach().cpu().numpy().astype(np.int64)


def mesh_bytes(vertices: np.ndarray, faces: np.ndarray, fmt: str) -> bytes:
    """Encode a triangle mesh as binary PLY (``fmt="ply"``) or OBJ (``fmt="obj"``), vertices in order."""
    import trimesh

    if fmt not in MESH_FORMATS:
        raise ValueError(f"mesh format must be one of {', '.join(MESH_FORMATS)}, got {fmt!r}")
    m = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int64), process=False)
    data = m.export(file_type=fmt)
    return data.encode("utf-8") if isinstance(data, str) else bytes(data)


def write_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a mesh atomically; the format follows the suffix (.ply or .obj)."""
    p = Path(path)
    atomic_write_bytes(p, mesh_bytes(vertices, faces, p.suffix.lower().lstrip(".")))
    return p
