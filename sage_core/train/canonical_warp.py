"""Canonical warps: how a training frame's pixels become rays of the canonical SDF
(docs/method.md §2).

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

from ..geometry.rigid import canonical_to_world as rigid_head_map
from ..geometry.rigid import world_to_canonical as rigid_head_map_inverse
from .warp import CanonicalRays, pixel_rays, rigid_rays_to_canonical, warp_pixels_to_canonical

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
            o_w, d_w = pixel_rays(camera.K, camera.w2c, camera.width, camera.height, pix)
            return rigid_rays_to_canonical(o_w, d_w, R0, t, avatar.root_joint)


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
            verts = avatar.pose_mesh(flame_inputs)
            return warp_pixels_to_canonical(verts, avatar.faces, (avatar.R_c, avatar.T_c, avatar.k_c), camera.K, camera.w2c,
                                            camera.width, camera.height, pix)  # fmt: skip


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
