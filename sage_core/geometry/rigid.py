"""The rigid head map between canonical space and a frame's world (docs/method.md §2).

A frame that differs from canonical only in FLAME's global rotation R0 (axis-angle ``rotation``) and
``translation`` t moves every canonical point rigidly about the root joint J0 (FLAME turns the whole
head about it):

    x_world = R0·(x_c − J0) + J0 + t              (:func:`canonical_to_world`)
    x_c     = R0ᵀ·(x_world − t − J0) + J0         (:func:`world_to_canonical`)

Rays map the same way (origins as points, directions by R0 or R0ᵀ alone); distances along a ray are
preserved. This module is the one implementation of that map: the avatar, the canonical warps of
training and the exports all call it.

Shapes: points and ray origins/directions ``(..., 3)`` (any leading dimensions); R0 ``(3, 3)``;
t and J0 ``(3,)``. The functions are differentiable and keep the inputs' dtype and device.
"""

from __future__ import annotations

import torch

from .rotations import axis_angle_to_matrix

__all__ = [
    "canonical_to_world",
    "rays_canonical_to_world",
    "rays_world_to_canonical",
    "rigid_from_flame",
    "world_from_canonical_matrix",
    "world_to_canonical",
]


def canonical_to_world(x: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor) -> torch.Tensor:
    """Canonical → world points: x_w = R0·(x_c − J0) + J0 + t. x: (..., 3) -> (..., 3)."""
    return (x - J0) @ R0.T + J0 + t


def world_to_canonical(x: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor) -> torch.Tensor:
    """World → canonical points (inverse of :func:`canonical_to_world`): x_c = R0ᵀ·(x_w − t − J0) + J0.
    x: (..., 3) -> (..., 3)."""
    return (x - t - J0) @ R0 + J0


def rays_world_to_canonical(
    origins: torch.Tensor, dirs: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays to canonical space: o_c = R0ᵀ·(o_w − t − J0) + J0, d_c = R0ᵀ·d_w.

    origins, dirs: (..., 3) -> (o_c (..., 3), d_c (..., 3)); unit directions stay unit and a point
    o + s·d maps to o_c + s·d_c.
    """
    return world_to_canonical(origins, R0, t, J0), dirs @ R0


def rays_canonical_to_world(
    origins: torch.Tensor, dirs: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Canonical rays to the world (inverse of :func:`rays_world_to_canonical`): o_w = R0·(o_c − J0) + J0 + t,
    d_w = R0·d_c. origins, dirs: (..., 3) -> (o_w (..., 3), d_w (..., 3))."""
    return canonical_to_world(origins, R0, t, J0), dirs @ R0.T


def rigid_from_flame(rotation: torch.Tensor, translation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R0 (3, 3), t (3,)) of one frame's FLAME global ``rotation`` (axis-angle, 3 numbers in any
    shape such as (1, 3)) and ``translation`` (3 numbers), in their dtype and device."""
    R0 = axis_angle_to_matrix(rotation.reshape(1, 3))[0]
    return R0, translation.reshape(3).to(R0)


def world_from_canonical_matrix(R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor) -> torch.Tensor:
    """(4, 4) homogeneous matrix M of :func:`canonical_to_world`: M·[x_c, 1] = [x_w, 1], i.e.
    M[:3, :3] = R0 and M[:3, 3] = J0 − R0·J0 + t (in the dtype of R0)."""
    J0 = J0.to(R0)
    M = torch.eye(4, dtype=R0.dtype, device=R0.device)
    M[:3, :3] = R0
    M[:3, 3] = J0 - R0 @ J0 + t.to(R0)
    return M
