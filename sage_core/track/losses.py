"""The fitting's terms as plain functions of tensors: robust penalty, projection, landmark visibility,
silhouette distance sampling and the perspective-correct barycentrics of fixed pixels."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def charbonnier(r: torch.Tensor, scale: float) -> torch.Tensor:
    """sqrt(1 + (r/scale)²) − 1 elementwise: quadratic below ``scale``, linear above (in units of scale)."""
    return torch.sqrt(1.0 + (r / scale) ** 2) - 1.0


def project(points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """points: (B, N, 3) world; K: (B, 3, 3); w2c: (B, 4, 4) -> (uv (B, N, 2) pixels, z (B, N) view depth)."""
    pc = points @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]
    z = pc[..., 2]
    uvw = pc @ K.transpose(1, 2)
    uv = uvw[..., :2] / uvw[..., 2:3].clamp_min(1e-6)
    return uv, z


def triangle_normals(points: torch.Tensor) -> torch.Tensor:
    """Unit normals of triangles (..., 3, 3) -> (..., 3) (right-hand rule over the vertex order)."""
    n = torch.cross(points[..., 1, :] - points[..., 0, :], points[..., 2, :] - points[..., 0, :], dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)


def triangle_plane_frame(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """In-plane axes of triangles (..., 3, 3): (e1, e2), each (..., 3), e1 the unit first edge and
    e2 = normal × e1. The frame landmark offsets are measured in (calibration pose table, fitted
    offsets)."""
    e1 = points[..., 1, :] - points[..., 0, :]
    e1 = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return e1, torch.cross(triangle_normals(points), e1, dim=-1)


def facing(normals: torch.Tensor, points: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """Cosine between normals (B, N, 3) and the directions from points (B, N, 3) to the camera
    centres (B, 3): > 0 on the side that faces the camera."""
    d = centres[:, None, :] - points
    return (normals * d).sum(-1) / d.norm(dim=-1).clamp_min(1e-12)


def visibility_weight(cos: torch.Tensor, lo: float = 0.05, hi: float = 0.3) -> torch.Tensor:
    """Landmark weight from the facing cosine: 0 below ``lo`` (outline, far side), 1 above ``hi``."""
    return ((cos - lo) / (hi - lo)).clamp(0.0, 1.0)


def sample_map(maps: torch.Tensor, uv: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Bilinear samples of per-image maps at pixel positions.

    maps: (B, H, W) at the size (width, height) of pixel coordinates uv (B, N, 2) (continuous, pixel
    centres at +0.5); outside the map the border value is used. Returns (B, N), differentiable in uv.
    """
    gx = uv[..., 0] / width * 2 - 1
    gy = uv[..., 1] / height * 2 - 1
    grid = torch.stack([gx, gy], -1)[:, :, None, :]  # (B, N, 1, 2)
    out = F.grid_sample(maps[:, None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, 0, :, 0]


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance in pixels to the outline of a boolean mask (H, W): negative inside, positive outside."""
    from scipy.ndimage import distance_transform_edt

    m = np.asarray(mask, bool)
    if m.all() or not m.any():
        return np.zeros(m.shape, np.float32)
    outside = distance_transform_edt(~m)
    inside = distance_transform_edt(m)
    return (outside - inside + np.where(m, 0.5, -0.5)).astype(np.float32)


def pixel_barycentrics(tri_uv: torch.Tensor, tri_z: torch.Tensor, px: torch.Tensor) -> torch.Tensor:
    """Perspective-correct barycentrics of pixel centres inside fixed triangles.

    tri_uv: (P, 3, 2) projected vertices; tri_z: (P, 3) their view depths; px: (P, 2) pixel positions.
    Screen barycentrics λ come from the edge functions; with 1/z affine on screen, the 3D barycentrics
    are b_i = (λ_i / z_i) / Σ_j λ_j / z_j. Differentiable in the vertices. Returns (P, 3).
    """
    a, b, c = tri_uv[:, 0], tri_uv[:, 1], tri_uv[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    area = torch.where(area.abs() < 1e-9, torch.full_like(area, 1e-9), area)
    e0 = (b[:, 0] - px[:, 0]) * (c[:, 1] - px[:, 1]) - (c[:, 0] - px[:, 0]) * (b[:, 1] - px[:, 1])
    e1 = (c[:, 0] - px[:, 0]) * (a[:, 1] - px[:, 1]) - (a[:, 0] - px[:, 0]) * (c[:, 1] - px[:, 1])
    e2 = (a[:, 0] - px[:, 0]) * (b[:, 1] - px[:, 1]) - (b[:, 0] - px[:, 0]) * (a[:, 1] - px[:, 1])
    lam = torch.stack([e0, e1, e2], -1) / area[:, None]
    w = lam / tri_z.clamp_min(1e-6)
    return w / w.sum(-1, keepdim=True).clamp_min(1e-12)
