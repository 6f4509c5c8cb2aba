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

A lookup treats all views at once: :class:`RestTeacher` stacks the views of one image size (their
renders, masks, depths, rest meshes, triangle frames and cameras) into batched tensors, and the
views' own fields become slices of those stacks (no copy is kept twice). The choice is the same as
visiting the views in order and keeping a view only when its score beats the best so far: the first
view with the highest score among those that see the point.
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


@dataclass
class _ViewStack:
    """The views of one image size, stacked (B views).

    index: (B,) int64 positions of the views in ``RestTeacher.views``; width, height: image size;
    color: (B, 3, H, W); interior: (B, 1, H, W); depth: (B, H, W); vertices: (B, V, 3); rotations:
    (B, F, 3, 3) the rest triangle frames' R; w2c_r: (B, 3, 3) and w2c_t: (B, 3) the world-to-camera
    rotation and translation; K: (B, 3, 3); centre: (B, 3) camera centres.
    """

    index: torch.Tensor
    width: int
    height: int
    color: torch.Tensor
    interior: torch.Tensor
    depth: torch.Tensor
    vertices: torch.Tensor
    rotations: torch.Tensor
    w2c_r: torch.Tensor
    w2c_t: torch.Tensor
    K: torch.Tensor
    centre: torch.Tensor


class RestTeacher:
    """The ``rest`` appearance teacher (see the module doc).

    views: the training views at rest (:meth:`build` makes them from an avatar); depth_tol: relative
    depth slack of the visibility test. The views' image, mask, depth, vertex and frame tensors are
    replaced by slices of the stacks the lookups use (same values).
    """

    def __init__(self, views: list[RestView], depth_tol: float = 0.01) -> None:
        if not views:
            raise ValueError("the rest teacher needs at least one view")
        self.views = views
        self.depth_tol = float(depth_tol)
        self._stacks: list[_ViewStack] = []
        self._stack_key: tuple = ()
        self._stack_refs: list = []
        self._stacked()

    def _view_key(self) -> tuple[tuple, list]:
        """The identity and version of every view's tensors (and its size), and the objects themselves
        (held with the stacks, so that the identities stay unique)."""
        refs = [(v, v.color, v.interior, v.depth, v.vertices, v.frames[0], v.K, v.w2c) for v in self.views]
        key = tuple((id(o), getattr(o, "_version", None)) for item in refs for o in item)
        return key + tuple((v.width, v.height) for v in self.views), refs

    def _stacked(self) -> list[_ViewStack]:
        """The views grouped by image size, dtype and device, each group stacked (see :class:`_ViewStack`);
        rebuilt when ``views`` changed (another list, other view objects, other or modified tensors)."""
        key, _ = self._view_key()
        if key == self._stack_key:
            return self._stacks
        groups: dict[tuple, list[int]] = {}
        for i, v in enumerate(self.views):
            groups.setdefault((v.width, v.height, v.color.dtype, v.color.device), []).append(i)
        stacks = []
        for (width, height, _, dev), members in groups.items():
            vs = [self.views[i] for i in members]
            w2c = torch.stack([v.w2c for v in vs])
            st = _ViewStack(
                index=torch.tensor(members, dtype=torch.long, device=dev), width=width, height=height,
                color=torch.cat([v.color for v in vs]), interior=torch.cat([v.interior for v in vs]),
                depth=torch.stack([v.depth for v in vs]), vertices=torch.stack([v.vertices for v in vs]),
                rotations=torch.stack([v.frames[0] for v in vs]), w2c_r=w2c[:, :3, :3], w2c_t=w2c[:, :3, 3],
                K=torch.stack([v.K for v in vs]), centre=torch.stack([-(v.w2c[:3, :3].T @ v.w2c[:3, 3]) for v in vs]),
            )  # fmt: skip
            for j, v in enumerate(vs):  # the views keep slices of the stacks, not copies
                v.color, v.interior, v.depth = st.color[j : j + 1], st.interior[j : j + 1], st.depth[j]
                v.vertices, v.frames = st.vertices[j], (st.rotations[j], v.frames[1], v.frames[2])
            stacks.append(st)
        self._stacks = stacks
        self._stack_key, self._stack_refs = self._view_key()
        return stacks

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
        self,
        faces: torch.Tensor,
        face_id: torch.Tensor,
        bary: torch.Tensor,
        ray_dirs: torch.Tensor,
        frames_deformed: Frames | None = None,
        deformed_rotations: torch.Tensor | None = None,
    ) -> TeacherLookup:
        """Teacher colours of deformed pixels.

        faces: (F, 3); face_id: (R,) hit triangle of each pixel (all >= 0); bary: (R, 3) its
        barycentrics; ray_dirs: (R, 3) unit world directions of the deformed rays; frames_deformed:
        per-face surfel frames of the deformed mesh, or deformed_rotations: (R, 3, 3) the rotation of
        each pixel's triangle frame alone (the same, ``frames_deformed[0][face_id]``).
        """
        if deformed_rotations is None:
            if frames_deformed is None:
                raise ValueError("RestTeacher.lookup needs frames_deformed or deformed_rotations")
            deformed_rotations = frames_deformed[0][face_id]
        R = face_id.shape[0]
        dev, dt = ray_dirs.device, ray_dirs.dtype
        Rd = deformed_rotations  # (R, 3, 3) local -> world of the deformed triangle
        d_loc = (Rd.transpose(-1, -2) @ ray_dirs[..., None]).squeeze(-1)  # ray direction in the triangle frame
        n_views = len(self.views)
        score = torch.full((n_views, R), -torch.inf, device=dev, dtype=dt)  # -inf where a view does not see
        colors = torch.zeros(n_views, R, 3, device=dev, dtype=dt)
        tri = faces[face_id]  # (R, 3)
        for st in self._stacked():
            corners = st.vertices.index_select(1, tri.reshape(-1)).reshape(-1, R, 3, 3)  # (B, R, 3, 3)
            x = (bary[None, :, :, None] * corners).sum(2)  # (B, R, 3) surface point at rest
            xc = x @ st.w2c_r.transpose(-1, -2) + st.w2c_t[:, None, :]
            z = xc[..., 2]
            front = z > 1e-6
            zs = torch.where(front, z, torch.ones_like(z))
            uvw = xc @ st.K.transpose(-1, -2)
            u = uvw[..., 0] / zs
            w_ = uvw[..., 1] / zs
            inside = front & (u >= 0) & (u < st.width) & (w_ >= 0) & (w_ < st.height)
            ui = u.clamp(0, st.width - 1).long()
            wi = w_.clamp(0, st.height - 1).long()
            surf = st.depth.flatten(1).gather(1, wi * st.width + ui)
            visible = inside & (z <= surf * (1.0 + self.depth_tol))
            visible &= _sample(st.interior, u, w_, st.width, st.height)[..., 0] > 0.999
            # viewing direction of the rest camera at x, in the rest triangle's frame
            dv = x - st.centre[:, None, :]
            dv = dv / dv.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            Rv = st.rotations.index_select(1, face_id)  # (B, R, 3, 3)
            dv_loc = (Rv.transpose(-1, -2) @ dv[..., None]).squeeze(-1)
            s = (dv_loc * d_loc).sum(-1)  # (B, R)
            ok = visible & (s > -2.0)  # -2: below any score (NaN scores never win)
            score[st.index] = torch.where(ok, s, torch.full_like(s, -torch.inf)).to(dt)
            colors[st.index] = _sample(st.color, u, w_, st.width, st.height).to(dt)
        best, view = score.max(0)  # the first of the highest scores, as a strict running maximum keeps
        valid = best > -torch.inf
        color = torch.where(valid[:, None], colors.gather(0, view[None, :, None].expand(1, R, 3))[0], torch.zeros_like(colors[0]))
        view = torch.where(valid, view, torch.full_like(view, -1))
        return TeacherLookup(color, valid, view)


def _sample(img: torch.Tensor, u: torch.Tensor, v: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Bilinear samples of B images img (B, C, H, W) at continuous pixel coordinates u, v (B, R) of
    their own image (pixel j covers [j, j + 1)). Returns (B, R, C)."""
    gx = u / width * 2.0 - 1.0
    gy = v / height * 2.0 - 1.0
    grid = torch.stack([gx, gy], -1).to(img.dtype)[:, None]  # (B, 1, R, 2)
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, :, 0].transpose(1, 2)
