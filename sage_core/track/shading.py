"""Shaded renders of a mesh through the project's mesh rasterizer: the untextured heads the landmark
calibration looks at, and the fitted meshes drawn over the images in the tracking report."""

from __future__ import annotations

import numpy as np
import torch

from ..data.cameras import Camera
from ..render.mesh_raster import MeshRaster, rasterize_mesh

SKIN = np.array([0.82, 0.66, 0.56])


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals. vertices: (..., V, 3); faces: (F, 3) -> (..., V, 3)."""
    tri = vertices[..., faces, :]  # (..., F, 3, 3)
    fn = torch.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)
    n = torch.zeros_like(vertices)
    for k in range(3):
        n = n.index_add(-2, faces[:, k], fn)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)


def camera_tensors(cam: Camera, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """(K (3, 3), w2c (4, 4)) tensors of a camera."""
    return (torch.as_tensor(cam.K, dtype=dtype, device=device), torch.as_tensor(cam.w2c, dtype=dtype, device=device))


LIGHT = (-0.35, -0.45, -0.82)
"""Default light direction in camera axes (x right, y down, z forward): from the upper left, towards the scene."""


def shade(vertices: torch.Tensor, faces: torch.Tensor, cam: Camera, supersample: int = 2,
          color: np.ndarray = SKIN, ambient: float = 0.3, light: tuple[float, float, float] = LIGHT
          ) -> tuple[np.ndarray, np.ndarray, MeshRaster]:
    """A Lambert-shaded render of a mesh.

    vertices: (V, 3) world; faces: (F, 3); cam: the view; light: the light's travel direction in
    camera axes. Returns (image (H, W, 3) float32 on white, coverage (H, W) float32 in [0, 1], the
    raster at the camera's resolution).
    """
    s = int(supersample)
    with torch.no_grad():
        K, w2c = camera_tensors(cam, vertices.dtype, vertices.device)
        Ks = K.clone()
        Ks[:2] *= s
        W, H = cam.width * s, cam.height * s
        r = rasterize_mesh(vertices, faces, Ks, w2c, W, H)
        n = vertex_normals(vertices, faces)
        fid = r.face_id[0]
        fg = fid >= 0
        tri = faces[fid[fg]]
        nn = (r.bary[0][fg][..., None] * n[tri]).sum(-2)
        nn = nn / nn.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        R = w2c[:3, :3]
        light = R.T @ torch.tensor(light, dtype=vertices.dtype)
        light = light / light.norm()
        lam = (nn @ -light).abs().clamp(0, 1)  # both sides lit (open meshes)
        img = torch.ones(H, W, 3, dtype=vertices.dtype)
        img[fg] = (ambient + (1 - ambient) * lam)[:, None] * torch.as_tensor(color, dtype=vertices.dtype)
        cov = fg.to(vertices.dtype)
        img = img.reshape(cam.height, s, cam.width, s, 3).mean((1, 3))
        cov = cov.reshape(cam.height, s, cam.width, s).mean((1, 3))
        low = rasterize_mesh(vertices, faces, K, w2c, cam.width, cam.height) if s > 1 else r
    return img.float().numpy(), cov.float().numpy(), low
