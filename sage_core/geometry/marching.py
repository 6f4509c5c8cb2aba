"""Mesh extraction from a signed distance function by marching cubes (scikit-image)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from skimage.measure import marching_cubes


def extract_mesh(
    sdf_fn: Callable[[torch.Tensor], torch.Tensor],
    bbox_min: Sequence[float] | np.ndarray | torch.Tensor,
    bbox_max: Sequence[float] | np.ndarray | torch.Tensor,
    resolution: int | Sequence[int] = 256,
    chunk: int = 262144,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of ``sdf_fn`` over a box, with outward faces for an SDF that is negative inside.

    sdf_fn: (M, 3) world points -> (M,) signed distances; queried in chunks under ``no_grad``.
    resolution: samples per axis (int or (rx, ry, rz)), grid spacing ``(bbox_max - bbox_min)/(res - 1)``.
    Returns vertices (V, 3) float32 in world units and faces (F, 3) int64; both empty (0, 3) when the
    field has no zero crossing in the box.
    """
    lo = np.asarray(torch.as_tensor(bbox_min).detach().cpu(), dtype=np.float64).reshape(3)
    hi = np.asarray(torch.as_tensor(bbox_max).detach().cpu(), dtype=np.float64).reshape(3)
    res = np.array([resolution] * 3 if isinstance(resolution, int) else list(resolution), dtype=np.int64)
    if res.shape != (3,) or (res < 2).any():
        raise ValueError("resolution must be >= 2 per axis")
    axes = [torch.linspace(float(lo[k]), float(hi[k]), int(res[k]), dtype=dtype, device=device) for k in range(3)]
    values = np.empty(int(res.prod()), dtype=np.float32)
    ny_nz = int(res[1] * res[2])
    # Process whole x-slabs so each chunk is a contiguous block of the (x, y, z) C-ordered volume.
    slabs = max(1, chunk // ny_nz)
    gy, gz = torch.meshgrid(axes[1], axes[2], indexing="ij")
    yz = torch.stack([gy.reshape(-1), gz.reshape(-1)], -1)
    with torch.no_grad():
        for start in range(0, int(res[0]), slabs):
            xs = axes[0][start : start + slabs]
            pts = torch.cat(
                [xs[:, None, None].expand(-1, ny_nz, 1), yz[None].expand(xs.shape[0], -1, -1)], -1
            ).reshape(-1, 3)
            vals = sdf_fn(pts).reshape(-1).float().cpu().numpy()
            values[start * ny_nz : start * ny_nz + vals.shape[0]] = vals
    volume = values.reshape(tuple(int(r) for r in res))
    empty = (np.zeros((0, 3), dtype=np.float32), np.zeros((0, 3), dtype=np.int64))
    if not np.isfinite(volume).all() or volume.min() >= 0.0 or volume.max() <= 0.0:
        return empty
    spacing = tuple(float(s) for s in (hi - lo) / (res - 1))
    verts, faces, _, _ = marching_cubes(volume, level=0.0, spacing=spacing, gradient_direction="descent")
    verts = (verts + lo[None]).astype(np.float32)
    return verts, faces.astype(np.int64)
