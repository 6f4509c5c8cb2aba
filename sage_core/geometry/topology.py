"""Mesh topology: edges, the open boundary, and distances to it."""

from __future__ import annotations

import numpy as np

__all__ = ["boundary_edges", "distance_to_segments", "edges"]


def _half_edges(faces: np.ndarray) -> np.ndarray:
    """(3F, 2) the faces' edges as sorted vertex pairs, one row per face side."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.sort(e, axis=1)


def edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges (sorted pairs) of a face table (F, 3)."""
    return np.unique(_half_edges(faces), axis=0)


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """(B, 2) the edges of the open boundary (sorted pairs): those only one face of (F, 3) uses.
    A closed mesh has none (shape (0, 2))."""
    key, counts = np.unique(_half_edges(faces), axis=0, return_counts=True)
    return key[counts == 1].reshape(-1, 2)


def distance_to_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int | None = None) -> np.ndarray:
    """(N,) Euclidean distance of each point (N, 3) to the nearest of the segments a[j]–b[j]
    ((S, 3) each; S ≥ 1), exact (the foot of the perpendicular clamped to the segment), in chunks
    of ``chunk`` points (default: about four million point-segment pairs per chunk), so that memory
    stays chunk × S."""
    p = np.asarray(points, dtype=np.float64)
    a = np.asarray(a, dtype=np.float64)
    d = np.asarray(b, dtype=np.float64) - a
    dd = np.maximum((d * d).sum(-1), 1e-300)
    chunk = max(1, int(chunk) if chunk is not None else (1 << 22) // max(int(a.shape[0]), 1))
    out = np.empty(p.shape[0])
    for s in range(0, p.shape[0], chunk):
        q = p[s : s + chunk, None, :] - a[None]  # (n, S, 3)
        t = np.clip((q * d[None]).sum(-1) / dd[None], 0.0, 1.0)
        r = q - t[..., None] * d[None]
        out[s : s + chunk] = np.sqrt((r * r).sum(-1).min(axis=1))
    return out
