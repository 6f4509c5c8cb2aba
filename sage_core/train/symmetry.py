"""Soft left–right symmetry of the canonical head (regularizer for SV-HR and one-shot).

A head seen from one side only leaves the other side to the priors. The FLAME template is
mirror-symmetric about its sagittal plane x = 0 (:func:`sage_core.flame.mirror.model_mirror` finds the vertex
pairs and :func:`plane_from_pairs` checks the plane); canonical space is the template after the
canonical timestep's shape, expression, jaw, eyes and neck pose, so the plane there is fitted to the
same vertex pairs on the canonical mesh. With S the reflection across that plane,

    x' = S(x) = x − 2·(n·x − d)·n,

the regularizer compares the SDF at x and S(x) (|f(x) − f(S x)| in units of the SDF box half extent)
and the appearance colour at x and S(x) (L1), at the surfel centres and at random points of the SDF
box. Both sides receive gradients: the term pulls the field towards symmetry, softly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch


@dataclass
class MirrorPlane:
    """The plane n·x = d (n unit, (3,)) and its fit residual (mean distance, metres, between a
    vertex's reflection and its partner)."""

    normal: torch.Tensor
    offset: torch.Tensor
    residual: float

    def reflect(self, x: torch.Tensor) -> torch.Tensor:
        """x: (..., 3) -> (..., 3) mirrored points."""
        n = self.normal.to(x)
        return x - 2.0 * ((x * n).sum(-1, keepdim=True) - self.offset.to(x)) * n

    def reflect_directions(self, v: torch.Tensor) -> torch.Tensor:
        """v: (..., 3) -> (..., 3) mirrored directions (the linear part of the reflection)."""
        n = self.normal.to(v)
        return v - 2.0 * (v * n).sum(-1, keepdim=True) * n


def plane_from_pairs(vertices: torch.Tensor, mirror_index: torch.Tensor) -> MirrorPlane:
    """Least-squares mirror plane of a mesh whose vertex i should mirror onto vertex m(i).

    vertices: (V, 3); mirror_index: (V,). The normal is the dominant direction of v_i − v_m(i)
    (sign: +x), the offset the mean of n·(v_i + v_m(i))/2 over pairs that are not on the plane.
    """
    v = vertices.detach().double()
    m = mirror_index.to(v.device).long()
    diff = v - v[m]
    mid = 0.5 * (v + v[m])
    off_plane = diff.norm(dim=-1) > 1e-9 * float((v.max(0).values - v.min(0).values).norm())
    if not bool(off_plane.any()):
        raise ValueError("every vertex is its own mirror partner; no plane to fit")
    d = diff[off_plane]
    # principal direction of the (sign-free) differences
    _, _, vh = torch.linalg.svd(d, full_matrices=False)
    n = vh[0]
    if n[0] < 0:
        n = -n
    offset = (mid[off_plane] @ n).mean()
    plane = MirrorPlane(n.to(vertices.dtype), offset.to(vertices.dtype), 0.0)
    res = (plane.reflect(v) - v[m]).norm(dim=-1).mean()
    plane.residual = float(res)
    return plane


def sdf_symmetry_loss(sdf_fn: Callable[[torch.Tensor], torch.Tensor], points: torch.Tensor, plane: MirrorPlane,
                      length_unit: float = 1.0) -> torch.Tensor:
    """mean |f(x) − f(S x)| / length_unit. sdf_fn: (M, 3) -> (M,); points: (M, 3)."""
    both = torch.cat([points, plane.reflect(points)], 0)
    f = sdf_fn(both)
    a, b = f.split(points.shape[0], 0)
    return (a - b).abs().mean() / length_unit


def color_symmetry_loss(color_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], points: torch.Tensor,
                        view_dirs: torch.Tensor, plane: MirrorPlane) -> torch.Tensor:
    """mean |c(x, v) − c(S x, S v)| over points and channels.

    color_fn: (points (M, 3), view directions (M, 3)) -> colours (M, C); points, view_dirs: (M, 3).
    """
    both = torch.cat([points, plane.reflect(points)], 0)
    dirs = torch.cat([view_dirs, plane.reflect_directions(view_dirs)], 0)
    c = color_fn(both, dirs)
    a, b = c.split(points.shape[0], 0)
    return (a - b).abs().mean()
