"""Appearance at rest, looked up through the mesh correspondence: a sharp teacher for phase 2.

Phase 2 compares the rasterized colour of a deformed frame with the avatar's canonical appearance
at the same surface point (SAGE §4). The canonical appearance can be volume-rendered from the SDF
and the appearance network (the ``neus`` teacher of :mod:`sage_core.train.phase2`), but a NeuS
render of a field trained for a few thousand steps is blurrier than the surfels it is meant to
teach. This module provides the ``rest`` teacher instead: the avatar's own rasterized appearance at
rest, transferred through the triangle correspondence of the FLAME mesh. No image of the capture is
used.

Built once from the phase-1 avatar. For every training view v (camera c_v, timestep t_v) it keeps

* the surfel render at rest ``I_v`` (H, W, 3): the avatar posed with the timestep's own FLAME
  parameters, seen by the view's camera (the state phase 1 fitted);
* the raster of the posed mesh ``V_v``: visible triangle and depth per pixel;
* the interior of the rendered foreground (the raster's mask eroded by one pixel), so that colours
  blended with the background at the silhouette never teach.

A deformed pixel whose ray hits triangle f at barycentrics b is the surface point
x_v = Σ_i b_i V_v[f_i] at rest. It is projected into every view; a view *sees* it when the point is in
front of the camera, lands on the interior of that view's foreground, and the view's raster depth at
that pixel is not nearer than the point by more than ``depth_tol`` (relative to the distance). Among
the views that see it, the one whose viewing direction, expressed in the triangle's own frame,
is closest to the deformed ray's (so view-dependent effects transfer with the surface) gives the
teacher colour, bilinearly interpolated from ``I_v``. Points no view sees (the mouth interior when the
jaw opens, the underside of the chin) have no teacher and are left out of the loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..flame.frames import surfel_frames
from ..render.mesh_raster import rasterize_mesh

Frames = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


@dataclass
class RestView:
    """One training view at rest.

    Attributes:
        K: (3, 3) intrinsics; w2c: (4, 4) world-to-camera; width, height: image size.
        color: (3, H, W) rest render of the avatar.
        interior: (1, 1, H, W) float, 1 on the foreground eroded by one pixel.
        depth: (H, W) camera depth of the rest mesh (+inf on the background).
        vertices: (V, 3) the posed mesh at rest.
        frames: per-face surfel frames (R (F, 3, 3), T (F, 3), k (F,)) of ``vertices``.
    """

    K: torch.Tensor
    w2c: torch.Tensor
    width: int
    height: int
    color: torch.Tensor
    interior: torch.Tensor
    depth: torch.Tensor
    vertices: torch.Tensor
    frames: Frames


@dataclass
class TeacherLookup:
    """Teacher colours of R deformed pixels.

    Attributes:
        color: (R, 3) colour at rest (zeros where invalid).
        valid: (R,) bool, True where at least one view sees the surface point.
        view: (R,) int64 index of the view used (−1 where invalid).
    """

    color: torch.Tensor
    valid: torch.Tensor
    view: torch.Tensor


def erode_mask(mask: torch.Tensor) -> torch.Tensor:
    """(H, W) bool -> (1, 1, H, W) float: 1 where the pixel and its 8 neighbours are foreground."""
    m = mask.to(torch.float32)[None, None]
    return (-F.max_pool2d(-m, 3, stride=1, padding=1)).clamp_min(0)


def _sample(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Bilinear samples of img (1, C, H, W) at continuous pixel coordinates u, v (R,) (pixel j covers
    [j, j + 1)). Returns (R, C)."""
    gx = u / width * 2.0 - 1.0
    gy = v / height * 2.0 - 1.0
    grid = torch.stack([gx, gy], -1).to(img.dtype)[None, None]  # (1, 1, R, 2)
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T


class RestTeacher:
    """The ``rest`` appearance teacher (see the module doc).

    views: the training views at rest (:meth:`build` makes them from an avatar); depth_tol: relative
    depth slack of the visibility test.
    """

    def __init__(self, views: list[RestView], depth_tol: float = 0.01) -> None:
        if not views:
            raise ValueError("the rest teacher needs at least one view")
        self.views = views
        self.depth_tol = float(depth_tol)

    @classmethod
    @torch.no_grad()
    def build(
        cls,
        render_fn,
        pose_fn,
        faces: torch.Tensor,
        cameras: list[tuple[torch.Tensor, torch.Tensor, int, int]],
        inputs: list[dict[str, torch.Tensor]],
        depth_tol: float = 0.01,
    ) -> RestTeacher:
        """Render every training view at rest.

        render_fn(camera_index, flame_inputs) -> (H, W, 3) colour of the avatar; pose_fn(flame_inputs)
        -> (V, 3) posed mesh; faces: (F, 3); cameras: per view (K (3, 3), w2c (4, 4), width, height);
        inputs: per view the FLAME inputs of its timestep.
        """
        views: list[RestView] = []
        for i, ((K, w2c, width, height), inp) in enumerate(zip(cameras, inputs)):
            color = render_fn(i, inp).detach().clamp(0, 1)
            verts = pose_fn(inp).detach()
            ras = rasterize_mesh(verts, faces, K, w2c, width, height)
            views.append(RestView(
                K=K, w2c=w2c, width=int(width), height=int(height), color=color.permute(2, 0, 1)[None].contiguous(),
                interior=erode_mask(ras.mask[0]), depth=ras.depth[0], vertices=verts, frames=surfel_frames(verts, faces),
            ))  # fmt: skip
        return cls(views, depth_tol)

    @torch.no_grad()
    def lookup(
        self, faces: torch.Tensor, face_id: torch.Tensor, bary: torch.Tensor, ray_dirs: torch.Tensor, frames_deformed: Frames
    ) -> TeacherLookup:
        """Teacher colours of deformed pixels.

        faces: (F, 3); face_id: (R,) hit triangle of each pixel (all >= 0); bary: (R, 3) its
        barycentrics; ray_dirs: (R, 3) unit world directions of the deformed rays; frames_deformed:
        per-face surfel frames of the deformed mesh.
        """
        R = face_id.shape[0]
        dev, dt = ray_dirs.device, ray_dirs.dtype
        Rd = frames_deformed[0][face_id]  # (R, 3, 3) local -> world of the deformed triangle
        d_loc = (Rd.transpose(-1, -2) @ ray_dirs[..., None]).squeeze(-1)  # ray direction in the triangle frame
        best = torch.full((R,), -2.0, device=dev, dtype=dt)
        color = torch.zeros(R, 3, device=dev, dtype=dt)
        view = torch.full((R,), -1, device=dev, dtype=torch.long)
        tri = faces[face_id]  # (R, 3)
        for vi, v in enumerate(self.views):
            x = (bary[..., None] * v.vertices[tri]).sum(1)  # (R, 3) surface point at rest
            xc = x @ v.w2c[:3, :3].T + v.w2c[:3, 3]
            z = xc[:, 2]
            front = z > 1e-6
            zs = torch.where(front, z, torch.ones_like(z))
            uvw = xc @ v.K.T
            u = uvw[:, 0] / zs
            w_ = uvw[:, 1] / zs
            inside = front & (u >= 0) & (u < v.width) & (w_ >= 0) & (w_ < v.height)
            ui = u.clamp(0, v.width - 1).long()
            wi = w_.clamp(0, v.height - 1).long()
            surf = v.depth[wi, ui]
            visible = inside & (z <= surf * (1.0 + self.depth_tol))
            visible &= _sample(v.interior, u, w_, v.width, v.height)[:, 0] > 0.999
            # viewing direction of the rest camera at x, in the rest triangle's frame
            centre = -(v.w2c[:3, :3].T @ v.w2c[:3, 3])
            dv = x - centre
            dv = dv / dv.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            Rv = v.frames[0][face_id]
            dv_loc = (Rv.transpose(-1, -2) @ dv[..., None]).squeeze(-1)
            score = (dv_loc * d_loc).sum(-1)
            take = visible & (score > best)
            if bool(take.any()):
                c = _sample(v.color, u, w_, v.width, v.height).to(dt)
                color = torch.where(take[:, None], c, color)
                best = torch.where(take, score, best)
                view = torch.where(take, torch.full_like(view, vi), view)
        return TeacherLookup(color, view >= 0, view)
