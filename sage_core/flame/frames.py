"""Per-triangle frames for binding Gaussians and surfels to a mesh (docs/formats.md §6)."""

from __future__ import annotations

import torch

_EPS2 = 1e-20


def _unit(x: torch.Tensor) -> torch.Tensor:
    """x / sqrt(max(x·x, 1e-20)) along the last axis."""
    return x / (x * x).sum(-1, keepdim=True).clamp_min(_EPS2).sqrt()


def triangle_frames(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """GaussianAvatars' per-face frames.

    vertices: (..., V, 3); faces: (F, 3) integer tensor or array, in the face table's winding order.
    Returns R: (..., F, 3, 3) with columns [a0 | a1 | a2], where a0 is the first edge direction,
    a1 the face normal (second column) and a2 = a0 × a1 (det +1); T: (..., F, 3) the centroid;
    k: (..., F) the mean of the first edge's length and the triangle's height over it.
    A point in face-local coordinates maps as μ = k·R·μ_loc + T.
    """
    faces = torch.as_tensor(faces, dtype=torch.long, device=vertices.device)
    tri = vertices[..., faces, :]  # (..., F, 3, 3): vertex, xyz
    v0, v1, v2 = tri.unbind(-2)
    e1 = v1 - v0
    e2 = v2 - v0
    a0 = _unit(e1)
    a1 = _unit(torch.linalg.cross(a0, e2, dim=-1))
    a2 = torch.linalg.cross(a0, a1, dim=-1)
    R = torch.stack([a0, a1, a2], dim=-1)
    T = (v0 + v1 + v2) / 3.0
    edge = (e1 * e1).sum(-1).clamp_min(_EPS2).sqrt()
    height = (a2 * e2).sum(-1).abs()
    k = 0.5 * (edge + height)
    return R, T, k


def surfel_frames(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-face frames in the surfel convention used by sage.

    Same as :func:`triangle_frames` but R' = [a0 | −a2 | a1]: the first two columns span the
    triangle's plane and the third column is the face normal, so a surfel with identity local
    rotation lies flat on its triangle (a 2D Gaussian's normal is its rotation's 3rd column).
    R' = R·Rx(−90°), still det +1. Bindings in this convention are not interchangeable with GA's.

    vertices: (..., V, 3); faces: (F, 3). Returns R': (..., F, 3, 3), T: (..., F, 3), k: (..., F).
    """
    R, T, k = triangle_frames(vertices, faces)
    a0, a1, a2 = R.unbind(-1)
    return torch.stack([a0, -a2, a1], dim=-1), T, k
