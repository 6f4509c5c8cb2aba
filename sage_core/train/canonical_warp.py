"""Canonical warps: how a training frame's pixels become rays of the canonical SDF (design.md
"Canonical space").

A :class:`CanonicalWarp` maps flat pixel ids of one camera, for a frame posed by given FLAME inputs,
to canonical rays (:class:`sage_core.train.warp.CanonicalRays`: origins, unit directions, the ratio of
canonical to world distance along each ray, the world → canonical rotation for normals, and a
validity mask). Built-ins:

* :class:`RigidFlameWarp`: the rigid head map. A frame that differs from canonical only in its global
  rotation R0 and translation t (neck pose, expression, jaw and eyes as in canonical) maps exactly:
  x_c = R0ᵀ·(x − t − J0) + J0, d_c = R0ᵀ·d; every ray is valid, hit or not.
* :class:`TriangleFrameWarp`: any other frame (neck motion, new expressions): each ray is moved
  rigidly, up to the triangle's scale, by the similarity of the posed-mesh triangle it hits; rays
  that miss the mesh are invalid, which masks the SDF terms to the head.
* :class:`AutoWarp` (phase 1's default): the rigid map where it is exact, else the triangle warp.

A learned backward warp (e.g. a deformation network with weights the user supplies) plugs in by
implementing :meth:`CanonicalWarp.map`; nothing here downloads anything.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import torch

from ..flame.frames import surfel_frames
from ..render.mesh_raster import points_on_mesh, ray_directions, rasterize_mesh, warp_directions_to_canonical, warp_points_to_canonical
from .warp import CanonicalRays

if TYPE_CHECKING:
    from ..avatar.model import Avatar
    from ..render import RenderCamera

Rigid = tuple[torch.Tensor, torch.Tensor]
WARPS: tuple[str, ...] = ("auto", "rigid", "triangle")


@runtime_checkable
class CanonicalWarp(Protocol):
    """Maps a posed frame's pixels to canonical rays."""

    def map(
        self,
        avatar: Avatar,
        flame_inputs: dict[str, torch.Tensor],
        camera: RenderCamera,
        pix: torch.Tensor,
        rigid: Rigid | None = None,
    ) -> CanonicalRays:
        """flame_inputs: the frame's FLAME kwargs (batch 1); camera: the frame's camera; pix: (R,)
        flat pixel ids (row·width + column); rigid: the frame's (R0 (3, 3), t (3,)) when it is a
        rigid motion of canonical (:meth:`Avatar.rigid_transform`), else None. Returns the rays
        (R of them), computed without gradients."""
        ...


def _pixel_rays(camera: RenderCamera, pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    o_w, d_w = ray_directions(camera.K, camera.w2c, camera.width, camera.height)
    return o_w.reshape(-1, 3)[pix], d_w.reshape(-1, 3)[pix]


def rigid_head_map(x: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor) -> torch.Tensor:
    """Canonical → world of a rigidly moved frame: x_w = R0·(x_c − J0) + J0 + t. x: (M, 3)."""
    return (x - J0) @ R0.T + J0 + t


def rigid_head_map_inverse(x: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor) -> torch.Tensor:
    """World → canonical: x_c = R0ᵀ·(x_w − t − J0) + J0. x: (M, 3)."""
    return (x - t - J0) @ R0 + J0


class RigidFlameWarp:
    """The exact rigid head map (module doc); ``map`` raises ValueError for a non-rigid frame."""

    def map(
        self,
        avatar: Avatar,
        flame_inputs: dict[str, torch.Tensor],
        camera: RenderCamera,
        pix: torch.Tensor,
        rigid: Rigid | None = None,
    ) -> CanonicalRays:
        if rigid is None:
            rigid = avatar.rigid_transform(flame_inputs)
            if rigid is None:
                raise ValueError("the frame is not a rigid motion of canonical space (neck, jaw, eyes or expression differ)")
        R0, t = rigid
        with torch.no_grad():
            o_w, d_w = _pixel_rays(camera, pix)
            R = pix.shape[0]
            o_c = rigid_head_map_inverse(o_w, R0, t, avatar.root_joint)
            d_c = d_w @ R0
            ones = torch.ones(R, dtype=o_w.dtype, device=o_w.device)
            return CanonicalRays(
                o_c, d_c, ones, R0.T.expand(R, 3, 3), torch.full((R,), -1, dtype=torch.long, device=o_w.device),
                torch.ones(R, dtype=torch.bool, device=o_w.device), torch.full_like(ones, float("inf")),
            )  # fmt: skip


class TriangleFrameWarp:
    """The hit-triangle warp through the posed mesh (module doc); ignores ``rigid``."""

    def map(
        self,
        avatar: Avatar,
        flame_inputs: dict[str, torch.Tensor],
        camera: RenderCamera,
        pix: torch.Tensor,
        rigid: Rigid | None = None,
    ) -> CanonicalRays:
        with torch.no_grad():
            o_w, d_w = _pixel_rays(camera, pix)
            verts = avatar.pose_mesh(flame_inputs)
            ras = rasterize_mesh(verts, avatar.faces, camera.K, camera.w2c, camera.width, camera.height)
            fid = ras.face_id.reshape(-1)[pix]
            bary = ras.bary.reshape(-1, 3)[pix]
            ok = fid >= 0
            fid_s = torch.where(ok, fid, torch.zeros_like(fid))
            hit = points_on_mesh(verts, avatar.faces, fid_s, bary)
            fr_d = surfel_frames(verts, avatar.faces)
            fr_c = (avatar.R_c, avatar.T_c, avatar.k_c)
            hit_c = warp_points_to_canonical(hit, fid_s, fr_d, fr_c)
            d_c = warp_directions_to_canonical(d_w, fid_s, fr_d, fr_c)
            ratio = avatar.k_c[fid_s] / fr_d[2][fid_s]
            t_hit = ((hit - o_w) * d_w).sum(-1)
            o_c = hit_c - (t_hit * ratio)[:, None] * d_c
            rot = avatar.R_c[fid_s] @ fr_d[0][fid_s].transpose(-1, -2)
            t_hit = torch.where(ok, t_hit, torch.full_like(t_hit, float("inf")))
            return CanonicalRays(o_c, d_c, ratio, rot, fid.long(), ok, t_hit)


class AutoWarp:
    """Rigid map for rigid frames, triangle warp otherwise (phase 1's default)."""

    def __init__(self, rigid: CanonicalWarp | None = None, fallback: CanonicalWarp | None = None) -> None:
        self.rigid = rigid if rigid is not None else RigidFlameWarp()
        self.fallback = fallback if fallback is not None else TriangleFrameWarp()

    def map(
        self,
        avatar: Avatar,
        flame_inputs: dict[str, torch.Tensor],
        camera: RenderCamera,
        pix: torch.Tensor,
        rigid: Rigid | None = None,
    ) -> CanonicalRays:
        if rigid is not None:
            return self.rigid.map(avatar, flame_inputs, camera, pix, rigid)
        return self.fallback.map(avatar, flame_inputs, camera, pix, None)


def make_warp(name: str) -> CanonicalWarp:
    """A built-in warp by name: "auto" (:class:`AutoWarp`), "rigid" (:class:`RigidFlameWarp`; a
    non-rigid frame is an error) or "triangle" (:class:`TriangleFrameWarp` for every frame)."""
    if name == "auto":
        return AutoWarp()
    if name == "rigid":
        return RigidFlameWarp()
    if name == "triangle":
        return TriangleFrameWarp()
    raise ValueError(f"unknown canonical warp {name!r} (choose from {', '.join(WARPS)})")
