"""Geometry metrics between meshes and point sets: Chamfer distance and normal error."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .mesh_sdf import face_normals_and_areas, sample_surface, signed_distance


def chamfer_distance(pa: np.ndarray, pb: np.ndarray) -> float:
    """Symmetric Chamfer distance: (mean_a min_b |a-b| + mean_b min_a |a-b|) / 2.

    pa: (N, 3), pb: (M, 3) -> float (same units as the points); inf if either set is empty.
    """
    a = np.asarray(pa, dtype=np.float64)
    b = np.asarray(pb, dtype=np.float64)
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return float(0.5 * (da.mean() + db.mean()))


def mesh_chamfer(
    v_a: np.ndarray, f_a: np.ndarray, v_b: np.ndarray, f_b: np.ndarray, n_samples: int = 50000, seed: int = 0
) -> float:
    """Chamfer distance between two meshes from ``n_samples`` area-weighted samples on each."""
    if len(f_a) == 0 or len(f_b) == 0:
        return float("inf")
    rng = np.random.default_rng(seed)
    pa, _ = sample_surface(v_a, f_a, n_samples, rng)
    pb, _ = sample_surface(v_b, f_b, n_samples, rng)
    return chamfer_distance(pa, pb)


def _oriented_angle(src_v, src_f, dst_v, dst_f, n: int, rng: np.random.Generator) -> np.ndarray:
    pts, nrm = sample_surface(src_v, src_f, n, rng)
    _, _, fid = signed_distance(pts, dst_v, dst_f)
    dst_n, _ = face_normals_and_areas(np.asarray(dst_v), np.asarray(dst_f))
    cos = np.clip((nrm * dst_n[fid]).sum(1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def normal_error(
    v_pred: np.ndarray,
    f_pred: np.ndarray,
    v_gt: np.ndarray,
    f_gt: np.ndarray,
    n_samples: int = 20000,
    seed: int = 0,
) -> float:
    """Mean angle in degrees between a mesh's face normals and those of the closest face on the other.

    Symmetric (both directions averaged), orientation-aware (flipped normals give ~180 degrees).
    v_*: (V, 3), f_*: (F, 3).
    """
    if len(f_pred) == 0 or len(f_gt) == 0:
        return float("nan")
    rng = np.random.default_rng(seed)
    a = _oriented_angle(v_pred, f_pred, v_gt, f_gt, n_samples, rng)
    b = _oriented_angle(v_gt, f_gt, v_pred, f_pred, n_samples, rng)
    return float(0.5 * (a.mean() + b.mean()))
