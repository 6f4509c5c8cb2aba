"""Warping camera rays of a deformed frame back into canonical space (SAGE §4, docs/method.md §2).

A pixel's world ray o + t·d hits the frame's posed FLAME mesh at x_h on triangle j. Triangle j's
canonical → posed transform is the similarity of docs/formats.md §6,

    x_p = k_p·R_p·R_cᵀ·(x_c − T_c)/k_c + T_p,

so its inverse maps the hit point to x_h^c = T_c + k_c·R_c·R_pᵀ·(x_h − T_p)/k_p and the ray direction
to d_c ∝ R_c·R_pᵀ·d. A world distance s along the ray becomes s·k_c/k_p in canonical space, so the
warped ray starts at o_c = x_h^c − t_h·(k_c/k_p)·d_c (t_h the world distance from the camera to the
hit) and passes through x_h^c at canonical distance t_h·k_c/k_p: the whole ray is moved rigidly (up
to the uniform scale) by the one triangle it hits. Rays that miss the mesh are flagged invalid.

For a frame that differs from canonical only by its global rotation R0 and translation t (FLAME
turns about the root joint J0), :func:`rigid_rays_to_canonical` gives the exact map
x_c = R0ᵀ·(x − t − J0) + J0 for every ray, hit or not.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..flame.frames import surfel_frames
from ..geometry.rigid import rays_world_to_canonical
from ..render.mesh_raster import MeshRaster, points_on_mesh, rasterize_mesh

Frames = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


@dataclass
class CanonicalRays:
    """Rays mapped into canonical space.

    Attributes:
        origins: (R, 3) canonical ray origins.
        dirs: (R, 3) unit canonical directions.
        scale: (R,) canonical length per world length along the ray (k_c / k_p; 1 when rigid).
        rotation: (R, 3, 3) world → canonical rotation (apply to world normals / view directions).
        face_id: (R,) int64 hit triangle of the posed mesh, −1 where the ray misses it.
        valid: (R,) bool, rays that were warped (hit the mesh, or every ray when rigid).
        hit_distance: (R,) world distance from the camera to the mesh hit (inf where missed).
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    scale: torch.Tensor
    rotation: torch.Tensor
    face_id: torch.Tensor
    valid: torch.Tensor
    hit_distance: torch.Tensor


def warp_hits_to_canonical(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    hit_points: torch.Tensor,
    face_id: torch.Tensor,
    frames_posed: Frames,
    frames_canonical: Frames,
) -> CanonicalRays:
    """Warp world rays through the triangles they hit.

    origins, dirs: (R, 3) world rays (dirs unit); hit_points: (R, 3) points on the rays on the posed
    mesh; face_id: (R,) hit triangle, −1 for a miss (then the ray is returned invalid, with the
    triangle-0 transform); frames_*: per-face (R (F, 3, 3), T (F, 3), k (F,)) of the posed and the
    canonical mesh, in the same convention.
    """
    valid = face_id >= 0
    f = torch.where(valid, face_id, torch.zeros_like(face_id)).long()
    Rp, Tp, kp = (a[f] for a in frames_posed)
    Rc, Tc, kc = (a[f] for a in frames_canonical)
    rot = Rc @ Rp.transpose(-1, -2)  # (R, 3, 3) world → canonical rotation of the hit triangle
    scale = kc / kp.clamp_min(1e-30)
    hit_c = Tc + scale[:, None] * (rot @ (hit_points - Tp)[..., None]).squeeze(-1)
    d_c = (rot @ dirs[..., None]).squeeze(-1)
    d_c = d_c / d_c.norm(dim=-1, keepdim=True).clamp_min(1e-20)
    t_hit = ((hit_points - origins) * dirs).sum(-1)
    o_c = hit_c - (t_hit * scale)[:, None] * d_c
    t_hit = torch.where(valid, t_hit, torch.full_like(t_hit, float("inf")))
    return CanonicalRays(o_c, d_c, scale, rot, face_id.long(), valid, t_hit)


def rigid_rays_to_canonical(
    origins: torch.Tensor, dirs: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, root_joint: torch.Tensor
) -> CanonicalRays:
    """Exact canonical rays of a rigidly moved frame: x_c = R0ᵀ·(x − t − J0) + J0, d_c = R0ᵀ·d.

    origins, dirs: (R, 3); R0: (3, 3); t, root_joint: (3,). Every ray is valid; face_id is −1.
    """
    R = origins.shape[0]
    o_c, d_c = rays_world_to_canonical(origins, dirs, R0, t, root_joint)
    ones = torch.ones(R, dtype=origins.dtype, device=origins.device)
    return CanonicalRays(
        o_c, d_c, ones, R0.T.expand(R, 3, 3), torch.full((R,), -1, dtype=torch.long, device=origins.device),
        torch.ones(R, dtype=torch.bool, device=origins.device), torch.full_like(ones, float("inf")),
    )  # fmt: skip


def pixel_rays(K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays of flat pixel ids. K: (3, 3); w2c: (4, 4); pix: (R,) -> origins (R, 3), unit dirs (R, 3).

    The rays of :func:`~sage_core.render.mesh_raster.ray_directions` through the centres
    (j + 0.5, i + 0.5) of those pixels (pix = i·width + j), computed for them only, in K's dtype."""
    w2c = w2c.to(K)
    pix = pix.to(device=K.device, dtype=torch.long)
    width = int(width)
    col = (pix % width).to(K.dtype) + 0.5
    row = torch.div(pix, width, rounding_mode="floor").to(K.dtype) + 0.5
    d_cam = torch.stack([col, row, torch.ones_like(col)], -1) @ torch.linalg.inv(K).T  # K⁻¹·(u, v, 1)
    R, t = w2c[:3, :3], w2c[:3, 3]
    d_world = d_cam @ R  # Rᵀ·d for row vectors
    dirs = d_world / d_world.norm(dim=-1, keepdim=True)
    centre = -(R.T @ t)
    return centre.expand(pix.shape[0], 3).contiguous(), dirs


def warp_pixels_to_canonical(
    posed_vertices: torch.Tensor,
    faces: torch.Tensor,
    frames_canonical: Frames,
    K: torch.Tensor,
    w2c: torch.Tensor,
    width: int,
    height: int,
    pix: torch.Tensor,
    raster: MeshRaster | None = None,
) -> CanonicalRays:
    """Canonical rays of the pixels ``pix`` of one camera through the posed mesh's hit triangles.

    posed_vertices: (V, 3) the frame's posed mesh; faces: (F, 3); frames_canonical: the canonical
    per-face frames (surfel convention, e.g. an Avatar's (R_c, T_c, k_c)); K: (3, 3); w2c: (4, 4);
    pix: (R,) flat pixel ids (row·width + column); raster: a precomputed :func:`rasterize_mesh` of
    the same mesh and camera (batch 1). Runs without gradients (the result is a fixed target).
    """
    with torch.no_grad():
        verts = posed_vertices.detach()
        if raster is None:
            raster = rasterize_mesh(verts, faces, K, w2c, width, height)
        fid = raster.face_id.reshape(-1)[pix]
        bary = raster.bary.reshape(-1, 3)[pix]
        o_w, d_w = pixel_rays(K.to(verts), w2c.to(verts), width, height, pix)
        ok = fid >= 0
        f_safe = torch.where(ok, fid, torch.zeros_like(fid))
        hit = points_on_mesh(verts, faces, f_safe, bary)
        hit = torch.where(ok[:, None], hit, o_w)
        frames_posed = surfel_frames(verts, faces)
        return warp_hits_to_canonical(o_w, d_w, hit, fid, frames_posed, frames_canonical)
