"""Triangle neighbour sets for surfel correction: a ball query around each triangle's centroid.

Computed once, in canonical space. A surfel's neighbour set is the set of its bound triangle
(``idx[binding]``).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def _to_numpy(x: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def triangle_centroids(vertices: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray) -> np.ndarray:
    """Centroids (F, 3) float64 of the faces (F, 3) of a mesh with vertices (V, 3)."""
    v = _to_numpy(vertices).astype(np.float64)
    f = _to_numpy(faces).astype(np.int64)
    return v[f].mean(axis=1)


def triangle_neighbours(
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    radius: float,
    max_neighbours: int,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ball query around every triangle.

    Triangle j is a neighbour of triangle q when their centroids are at most ``radius`` apart
    (Euclidean, in the vertices' units) and j ≠ q. Of those, the ``max_neighbours`` nearest are
    kept, sorted by increasing distance.

    vertices: (V, 3); faces: (F, 3). Returns idx: (F, max_neighbours) int64 padded with −1 and
    count: (F,) int64 valid entries per row, on ``device`` (default: the vertices' device when
    they are a tensor, else CPU).
    """
    if radius < 0 or max_neighbours < 0:
        raise ValueError("radius and max_neighbours must be non-negative")
    if device is None:
        device = vertices.device if isinstance(vertices, torch.Tensor) else "cpu"
    c = triangle_centroids(vertices, faces)
    F = c.shape[0]
    K = int(max_neighbours)
    if F == 0 or K == 0:
        return torch.full((F, K), -1, dtype=torch.long, device=device), torch.zeros(F, dtype=torch.long, device=device)
    k_query = min(K + 1, F)
    dist, idx = cKDTree(c).query(c, k=k_query, distance_upper_bound=radius)
    dist = np.asarray(dist).reshape(F, k_query)
    idx = np.asarray(idx).reshape(F, k_query)
    ok = np.isfinite(dist) & (idx != np.arange(F)[:, None]) & (idx < F)
    # stable compaction of the valid entries of each row to the front, keeping the distance order
    order = np.argsort(~ok, axis=1, kind="stable")
    idx = np.take_along_axis(np.where(ok, idx, -1), order, axis=1)[:, :K]
    count = ok.sum(axis=1).clip(max=K)
    if idx.shape[1] < K:
        idx = np.pad(idx, ((0, 0), (0, K - idx.shape[1])), constant_values=-1)
    return torch.as_tensor(idx, dtype=torch.long, device=device), torch.as_tensor(count, dtype=torch.long, device=device)


def surfel_neighbours(idx: torch.Tensor, count: torch.Tensor, binding: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A surfel's neighbour set is its bound triangle's.

    idx: (F, K), count: (F,) from :func:`triangle_neighbours`; binding: (N,) face ids.
    Returns (idx (N, K), count (N,)).
    """
    b = binding.to(device=idx.device, dtype=torch.long)
    return idx[b], count[b]
