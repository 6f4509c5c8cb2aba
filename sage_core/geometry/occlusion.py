"""Ambient occlusion of points on or near a triangle mesh, with deterministic ray directions.

The cosine-weighted ambient visibility of a point x with normal n is

    A(x) = (1/π) ∫_{ω·n > 0} V(x, ω) (ω·n) dω,

the share of diffuse light from a uniform white sky that reaches x (V = 1 when the ray from x along
ω escapes the mesh). It is estimated with ``samples`` directions distributed over the hemisphere by
a Fibonacci spiral in the cosine-weighted measure (a direction at polar angle θ with sin²θ uniform on
(0, 1)), so that A is the plain fraction of rays that escape. The same directions are used for every
point (rotated into its normal's frame), so the result is a deterministic function of the input.
Ray casting uses libigl's AABB tree (``igl.AABB.intersect_ray_first``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ambient_visibility", "hemisphere_directions"]


def hemisphere_directions(samples: int) -> np.ndarray:
    """(S, 3) unit directions about +z, cosine-weighted Fibonacci spiral (float64)."""
    k = np.arange(samples, dtype=np.float64) + 0.5
    sin2 = k / samples  # sin²θ uniform: the cosine-weighted measure
    golden = np.pi * (3.0 - np.sqrt(5.0))
    phi = golden * k
    st = np.sqrt(sin2)
    ct = np.sqrt(np.clip(1.0 - sin2, 0.0, None))
    return np.stack([st * np.cos(phi), st * np.sin(phi), ct], -1)


def _frames(normals: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations whose third column is the unit normal."""
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], -1)


def ambient_visibility(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray, samples: int = 256, offset: float = 0.0,
    chunk: int = 1 << 18,
) -> np.ndarray:
    """Cosine-weighted ambient visibility in [0, 1] of every point (see the module doc).

    vertices: (V, 3); faces: (F, 3); points, normals: (M, 3) (normals need not be unit); samples: rays
    per point; offset: the rays start this far along the normal (avoids hitting the point's own
    triangle). Returns (M,) float64: 1 fully open, 0 fully occluded.
    """
    import igl

    V = np.ascontiguousarray(vertices, dtype=np.float64)
    Fc = np.ascontiguousarray(faces, dtype=np.int64)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    M = P.shape[0]
    if M == 0:
        return np.zeros(0)
    R = _frames(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    D_loc = hemisphere_directions(int(samples))
    tree = igl.AABB()
    tree.init(V, Fc)
    origins = P + offset * R[:, :, 2]
    dirs = np.einsum("mij,sj->msi", R, D_loc).reshape(-1, 3)
    orig = np.repeat(origins, D_loc.shape[0], axis=0)
    hit = np.empty(dirs.shape[0], dtype=bool)
    for s in range(0, dirs.shape[0], chunk):
        ids, _, _ = tree.intersect_ray_first(V, Fc, np.ascontiguousarray(orig[s : s + chunk]), np.ascontiguousarray(dirs[s : s + chunk]))
        hit[s : s + chunk] = np.asarray(ids) >= 0
    return 1.0 - hit.reshape(M, -1).mean(1)
