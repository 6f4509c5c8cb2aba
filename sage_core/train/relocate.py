"""Surfel relocation in phase 1: a fixed budget moved to where the images need it.

SAGE spreads a fixed number of surfels over the FLAME triangles and never densifies. A real head has
surface the FLAME mesh lacks (hair hanging off the scalp, a fringe, a bun) and detail that is not
spread by triangle area. Relocation keeps the count and moves surfels that contribute nothing to
any training view onto the canonical SDF's surface where the renders are furthest from the images:

1. **Contribution** of every surfel to ``views`` training frames: the derivative of the rendered
   alpha summed over the image with respect to a per-surfel opacity multiplier (the surfel's
   visible weight in pixels, occlusion included). A surfel is a *source* when its summed
   contribution is below ``floor`` pixels, the outward normal of its triangle faces at least one of
   the scanned cameras (so the back of the head, which a multiview capture does not see, keeps its
   surfels), and it is not in the mouth or the eyes (hidden at rest by design).
2. **Targets**: foreground pixels drawn with probability proportional to the render's error there
   (colour L1 plus the part of the mask not yet covered), mapped to canonical rays as the NeuS
   terms map them, and placed on the SDF at NeuS's expected depth (rays whose accumulated weight
   stays below 0.5 are dropped).
3. **Move**: up to ``fraction`` of the surfels, the least contributing first, go to the targets:
   bound to the nearest canonical triangle with their position as its local offset, flat on the
   SDF's tangent plane, sized to the surfel spacing there; free attributes also take the colour of
   the nearest surfel that stays and a mid opacity (with attribute networks colour, opacity and
   shape follow from the new position). Their optimiser state restarts.

Everything happens in canonical space, so relocated surfels deform with their triangle like the
others (docs/method.md "Relocation").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from ..avatar.binding import nearest_triangles, world_to_local
from ..avatar.init import REGION_EYES, REGION_MOUTH
from ..geometry.knn import nearest_indices
from ..geometry.rotations import matrix_to_quat
from ..render import rasterize_surfels
from ..render.volume import render_neus

if TYPE_CHECKING:
    from .phase1 import Phase1Trainer

EXCLUDED_REGIONS = (REGION_MOUTH, REGION_EYES)
"""Regions whose surfels are never moved: hidden at rest by design (mouth interior, teeth, eyeballs)."""


@dataclass
class RelocationResult:
    """What one relocation did: surfels moved, sources found, targets found."""

    moved: int
    sources: int
    targets: int


def due(step: int, every: int, until: int) -> bool:
    """Whether relocation runs after ``step`` completed steps (every ``every`` steps, up to ``until``)."""
    return every > 0 and step > 0 and step % every == 0 and step <= until


@torch.no_grad()
def _facing(normals: torch.Tensor, means: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the outward normals (N, 3) at ``means`` (N, 3) face the camera centre (3,)."""
    return ((centre[None] - means) * normals).sum(-1) > 0


def scan(trainer: Phase1Trainer, frames: list[int]) -> tuple[torch.Tensor, torch.Tensor, list[tuple[int, torch.Tensor]]]:
    """Contribution (N,) in pixels of alpha summed over the training ``frames``, whether each surfel's
    triangle faces one of their cameras (N,) bool, and each frame's error map [(frame, (H, W))]
    (colour L1 plus the uncovered mask, 0 outside the foreground)."""
    av, c = trainer.avatar, trainer.cfg
    n = len(av.surfels)
    dev = trainer.device
    contrib = torch.zeros(n, device=dev)
    facing = torch.zeros(n, dtype=torch.bool, device=dev)
    errors: list[tuple[int, torch.Tensor]] = []
    with torch.no_grad():
        canon = av.canonical_state(with_sdf=av.attributes == "mlp")
    b = av.surfels.binding
    for i in frames:
        img, mask, cam = trainer._frame(i)
        ts = trainer.frames[i].timestep
        inputs = {k: v.detach() for k, v in trainer.inputs(ts).items()}
        centre = -(cam.w2c[:3, :3].T @ cam.w2c[:3, 3])
        with torch.no_grad():
            mesh = trainer.posed_mesh(ts, inputs, None)
            p = av.posed(inputs, centre, canonical=canon, mesh=mesh)
            tri_n = (mesh.R[b][..., 2] if mesh is not None else av.posed_mesh(inputs).R[b][..., 2])
            facing |= _facing(tri_n, p.means, centre)
        m = torch.ones(n, device=dev, requires_grad=True)
        out = rasterize_surfels(p.means, p.quats, p.scales, p.opacities * m, p.colors, cam, c.background,
                                near=c.near, far=c.far, return_statistics=False, backend=trainer.render_backend)  # fmt: skip
        (g,) = torch.autograd.grad(out.alpha.sum(), m)
        contrib += g.clamp_min(0)
        with torch.no_grad():
            err = (out.color - img).abs().mean(-1) + (mask - out.alpha).clamp_min(0)
            errors.append((i, torch.where(mask > 0.5, err, torch.zeros_like(err))))
    return contrib, facing, errors


def sources(avatar_regions: torch.Tensor, contrib: torch.Tensor, facing: torch.Tensor, floor: float, limit: int) -> torch.Tensor:
    """Ids of at most ``limit`` surfels to move: facing a camera, outside :data:`EXCLUDED_REGIONS`,
    contribution below ``floor``, the least contributing first. avatar_regions, contrib, facing: (N,)."""
    ok = facing & (contrib < floor)
    for r in EXCLUDED_REGIONS:
        ok &= avatar_regions != r
    idx = torch.nonzero(ok, as_tuple=False).reshape(-1)
    order = torch.argsort(contrib[idx])
    return idx[order[:limit]]


@torch.no_grad()
def targets(trainer: Phase1Trainer, errors: list[tuple[int, torch.Tensor]], count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to ``count`` canonical surface points (M, 3) and unit outward normals (M, 3) where the
    error maps are largest: pixels drawn in proportion to the error, canonical rays, NeuS depth."""
    av, c = trainer.avatar, trainer.cfg
    per = max(1, math.ceil(count / max(len(errors), 1)))
    pts, nrm = [], []
    for i, err in errors:
        w = err.reshape(-1)
        if float(w.sum()) <= 0:
            continue
        k = min(per, int((w > 0).sum()))
        pix = torch.multinomial(w, k, replacement=False, generator=trainer.generator)
        _, _, cam = trainer._frame(i)
        ts = trainer.frames[i].timestep
        inputs = {kk: v.detach() for kk, v in trainer.inputs(ts).items()}
        cr = trainer.warp.map(av, inputs, cam, pix, trainer.rigid(ts))
        out = render_neus(av.sdf, av.appearance, cr.origins, cr.dirs, av.variance, c.neus.samples, c.neus.importance,
                          c.neus.up_steps, 1.0, c.background, length_unit=trainer.length_unit)  # fmt: skip
        ok = cr.valid & (out.weights_sum > 0.5)
        t = out.depth / out.weights_sum.clamp_min(1e-6)
        x = cr.origins + t[:, None] * cr.dirs
        pts.append(x[ok])
    if not pts:
        z = torch.zeros(0, 3, device=trainer.device)
        return z, z
    x = torch.cat(pts)[:count]
    _, grad, _ = av.sdf.gradient(x)
    n = torch.nn.functional.normalize(grad, dim=-1)
    return x, n


@torch.no_grad()
def move(trainer: Phase1Trainer, ids: torch.Tensor, points: torch.Tensor, normals: torch.Tensor) -> int:
    """Move surfels ``ids`` (M,) to canonical ``points`` (M, 3) flat on ``normals`` (M, 3); returns M.

    Each is bound to its nearest canonical triangle; its size is the median distance to its
    4 nearest remaining surfels; free surfels take the nearest remaining surfel's colour and opacity
    0.5, an opacity offset (attribute networks) restarts at 0. The optimiser state of the moved rows
    restarts."""
    av = trainer.avatar
    s = av.surfels
    m = min(int(ids.numel()), int(points.shape[0]))
    if m == 0:
        return 0
    ids, points, normals = ids[:m], points[:m], normals[:m]
    keep = torch.ones(len(s), dtype=torch.bool, device=ids.device)
    keep[ids] = False
    kept = torch.nonzero(keep, as_tuple=False).reshape(-1)
    centres = s.canonical_positions(av.R_c, av.T_c, av.k_c)
    near = kept[nearest_indices(points, centres[kept], 4)]  # (M, 4)
    spacing = (centres[near] - points[:, None]).norm(dim=-1).median(dim=-1).values.clamp_min(1e-4)
    face, _ = nearest_triangles(points, av.canonical_vertices, av.faces)
    t1 = torch.nn.functional.normalize(torch.linalg.cross(normals, _any_perpendicular(normals)), dim=-1)
    t2 = torch.linalg.cross(normals, t1)
    quats = matrix_to_quat(torch.stack([t1, t2, normals], -1))
    scales = spacing[:, None].expand(-1, 2)
    mu, q, sl = world_to_local(points, quats, scales, face, av.R_c, av.T_c, av.k_c)
    s.mu_loc.data[ids], s.q_loc.data[ids], s.s_loc.data[ids] = mu, q, sl
    s.binding[ids] = face
    if s.face_region.numel():
        s.region_id[ids] = s.face_region[face]
    rows = [s.mu_loc, s.q_loc, s.s_loc]
    if s.opacity_offset is not None:
        s.opacity_offset.data[ids] = 0.0
        rows.append(s.opacity_offset)
    if s.attributes == "free":
        s.sh_dc.data[ids] = s.sh_dc.data[near[:, 0]]
        if hasattr(s, "sh_rest"):
            s.sh_rest.data[ids] = 0
            rows.append(s.sh_rest)
        s.opacity.data[ids] = 0.0
        rows += [s.sh_dc, s.opacity]
    for p in rows:
        for v in trainer.optimizer.state.get(p, {}).values():
            if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == p.shape[0]:
                v[ids.to(v.device)] = 0
    return m


def _any_perpendicular(n: torch.Tensor) -> torch.Tensor:
    """(N, 3) unit vectors not parallel to the unit vectors n (N, 3)."""
    x = torch.zeros_like(n)
    use_y = n[:, 0].abs() > 0.9
    x[~use_y, 0] = 1.0
    x[use_y, 1] = 1.0
    return x


def relocate(trainer: Phase1Trainer) -> RelocationResult:
    """One relocation (see the module doc) with the trainer's ``relocate`` config."""
    cfg = trainer.cfg.relocate
    n_frames = len(trainer.frames)
    pick = torch.randperm(n_frames, generator=trainer.generator)[: min(cfg.views, n_frames)].tolist()
    contrib, facing, errors = scan(trainer, pick)
    limit = int(cfg.fraction * len(trainer.avatar.surfels))
    src = sources(trainer.avatar.surfels.region_id, contrib, facing, cfg.floor, limit)
    if src.numel() == 0:
        return RelocationResult(0, 0, 0)
    pts, nrm = targets(trainer, errors, int(src.numel()))
    moved = move(trainer, src, pts, nrm)
    return RelocationResult(moved, int(src.numel()), int(pts.shape[0]))
