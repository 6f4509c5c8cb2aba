"""Triangle-mesh rasterizer (face id, barycentrics, depth) and ray warping through triangle frames.

Pure torch, batched over cameras or frames. Cameras are OpenCV (x right, y down, z forward) with
``K`` in pixels and pixel centres at +0.5: pixel (row i, column j) is sampled at (j + 0.5, i + 0.5).

The rasterizer works per face chunk: every face's screen bounding box is expanded into
(face, pixel) candidate pairs (no loop over pixels), each pair is tested with 2D edge functions, and
a z-buffer keeps the nearest hit per pixel (ties go to the lower face id). Faces with any vertex at
view depth ≤ ``near`` are dropped whole (no near-plane clipping). Back faces are kept. The selection
runs without gradients; the barycentrics and depth of the winning faces are then recomputed from
the vertices, so they are differentiable with respect to the vertices and cameras.

Perspective-correct barycentrics: with screen-space barycentrics λ_i of the pixel centre and view
depths z_i of the vertices, 1/z is affine in screen space, so the depth is z = 1 / Σ λ_i / z_i and
the 3D barycentrics are b_i = (λ_i / z_i) · z.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

_DEFAULT_MAX_PAIRS = 1 << 22


@dataclass
class MeshRaster:
    """Rasterized mesh for B views.

    Attributes:
        face_id: (B, H, W) int64 index of the visible face, −1 for background.
        bary: (B, H, W, 3) perspective-correct barycentrics of the pixel centre's hit point with
            respect to the face's vertices (faces[f, 0], faces[f, 1], faces[f, 2]); zeros for background.
        depth: (B, H, W) view depth (camera z, not the distance along the ray) of the hit point;
            +inf for background.
    """

    face_id: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        """(B, H, W) bool, True where a face is visible."""
        return self.face_id >= 0


def _as_batch(x: torch.Tensor, tail: int, name: str) -> torch.Tensor:
    if x.dim() == tail:
        return x.unsqueeze(0)
    if x.dim() != tail + 1:
        raise ValueError(f"{name} must have {tail} or {tail + 1} dims, got shape {tuple(x.shape)}")
    return x


def _batch_size(*sizes: int) -> int:
    B = max(sizes)
    for s in sizes:
        if s not in (1, B):
            raise ValueError(f"batch sizes {sizes} do not broadcast")
    return B


def _project(verts: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """verts: (V, 3) world; K: (3, 3); w2c: (4, 4) -> (uv (V, 2) pixels, z (V,) view depth)."""
    Xc = verts @ w2c[:3, :3].T + w2c[:3, 3]
    z = Xc[:, 2]
    p = Xc @ K.T
    uv = p[:, :2] / p[:, 2:3]
    return uv, z


def _edge_lambdas(tri_uv: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Screen barycentrics of points in triangles.

    tri_uv: (P, 3, 2) vertex pixel coordinates; px, py: (P,) -> (lam (P, 3), twice the signed area (P,)).
    """
    x0, y0 = tri_uv[:, 0, 0], tri_uv[:, 0, 1]
    x1, y1 = tri_uv[:, 1, 0], tri_uv[:, 1, 1]
    x2, y2 = tri_uv[:, 2, 0], tri_uv[:, 2, 1]
    area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    e0 = (x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)
    e1 = (x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)
    e2 = (x0 - px) * (y1 - py) - (x1 - px) * (y0 - py)
    lam = torch.stack([e0, e1, e2], -1) / area2.unsqueeze(-1)
    return lam, area2


def _chunks(counts: torch.Tensor, max_pairs: int) -> list[tuple[int, int]]:
    """Split a list of per-face pair counts (F',) into contiguous ranges of at most ``max_pairs`` pairs
    (a single face larger than that gets a range of its own)."""
    cum = torch.cumsum(counts, 0).cpu()
    n = int(cum.shape[0])
    out: list[tuple[int, int]] = []
    start = 0
    while start < n:
        base = int(cum[start - 1]) if start > 0 else 0
        end = int(torch.searchsorted(cum, torch.tensor(base + max_pairs, dtype=cum.dtype), right=True))
        end = max(end, start + 1)
        out.append((start, end))
        start = end
    return out


def _select_faces(
    verts: torch.Tensor, faces: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, near: float, max_pairs: int
) -> torch.Tensor:
    """Z-buffer pass without gradients. Returns the visible face per pixel, (H*W,) int64, −1 for background."""
    device = verts.device
    HW = width * height
    zbuf = torch.full((HW,), float("inf"), dtype=verts.dtype, device=device)
    fbuf = torch.full((HW,), -1, dtype=torch.long, device=device)
    uv, z = _project(verts, K, w2c)
    tri_uv = uv[faces]  # (F, 3, 2)
    tri_z = z[faces]  # (F, 3)
    x = tri_uv[..., 0]
    y = tri_uv[..., 1]
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    valid = (tri_z > near).all(-1) & torch.isfinite(tri_uv).all(-1).all(-1) & (area2.abs() > 1e-12)
    j0 = torch.ceil(x.min(-1).values - 0.5).clamp(min=0, max=width)
    j1 = torch.floor(x.max(-1).values - 0.5).clamp(min=-1, max=width - 1)
    i0 = torch.ceil(y.min(-1).values - 0.5).clamp(min=0, max=height)
    i1 = torch.floor(y.max(-1).values - 0.5).clamp(min=-1, max=height - 1)
    valid &= (j1 >= j0) & (i1 >= i0)
    fidx = valid.nonzero().squeeze(-1)
    if fidx.numel() == 0:
        return fbuf
    j0 = j0[fidx].long()
    i0 = i0[fidx].long()
    nw = j1[fidx].long() - j0 + 1
    nh = i1[fidx].long() - i0 + 1
    counts = nw * nh
    for s, e in _chunks(counts, max_pairs):
        c = counts[s:e]
        local_face = torch.repeat_interleave(torch.arange(e - s, device=device), c)
        first = torch.cumsum(c, 0) - c
        local = torch.arange(int(c.sum()), device=device) - first[local_face]
        fi = s + local_face
        jj = j0[fi] + local % nw[fi]
        ii = i0[fi] + torch.div(local, nw[fi], rounding_mode="floor")
        face = fidx[fi]
        lam, _ = _edge_lambdas(tri_uv[face], jj.to(verts.dtype) + 0.5, ii.to(verts.dtype) + 0.5)
        inside = (lam >= 0).all(-1)
        inv_z = (lam / tri_z[face]).sum(-1)
        inside &= inv_z > 0
        if not bool(inside.any()):
            continue
        d = 1.0 / inv_z[inside]
        pix = (ii * width + jj)[inside]
        face = face[inside]
        chunk_min = torch.full((HW,), float("inf"), dtype=verts.dtype, device=device)
        chunk_min.scatter_reduce_(0, pix, d, reduce="amin")
        win = d <= chunk_min[pix]
        chunk_face = torch.full((HW,), torch.iinfo(torch.long).max, dtype=torch.long, device=device)
        chunk_face.scatter_reduce_(0, pix[win], face[win], reduce="amin")
        upd = chunk_min < zbuf
        zbuf = torch.where(upd, chunk_min, zbuf)
        fbuf = torch.where(upd, chunk_face, fbuf)
    return fbuf


def rasterize_mesh(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,
    w2c: torch.Tensor,
    width: int,
    height: int,
    near: float = 1e-3,
    max_pairs: int = _DEFAULT_MAX_PAIRS,
) -> MeshRaster:
    """Rasterize a triangle mesh into B views.

    vertices: (B, V, 3) or (V, 3) world positions; faces: (F, 3) int; K: (B, 3, 3) or (3, 3);
    w2c: (B, 4, 4) or (4, 4) OpenCV world-to-camera. A batch size of 1 (or an unbatched input)
    broadcasts against the others. ``max_pairs`` bounds the (face, pixel) candidates held at once.
    Returns a :class:`MeshRaster` with leading dimension B (B = 1 when nothing is batched).
    """
    verts_b = _as_batch(vertices, 2, "vertices")
    K_b = _as_batch(K, 2, "K").to(verts_b)
    w2c_b = _as_batch(w2c, 2, "w2c").to(verts_b)
    B = _batch_size(verts_b.shape[0], K_b.shape[0], w2c_b.shape[0])
    faces = faces.to(device=verts_b.device, dtype=torch.long)
    width, height = int(width), int(height)
    HW = width * height
    jj, ii = torch.meshgrid(
        torch.arange(width, device=verts_b.device, dtype=verts_b.dtype) + 0.5,
        torch.arange(height, device=verts_b.device, dtype=verts_b.dtype) + 0.5,
        indexing="xy",
    )
    px_all = jj.reshape(-1)
    py_all = ii.reshape(-1)
    face_ids, barys, depths = [], [], []
    for b in range(B):
        v = verts_b[b if verts_b.shape[0] > 1 else 0]
        Kb = K_b[b if K_b.shape[0] > 1 else 0]
        Wb = w2c_b[b if w2c_b.shape[0] > 1 else 0]
        with torch.no_grad():
            fbuf = _select_faces(v.detach(), faces, Kb.detach(), Wb.detach(), width, height, near, max_pairs)
        fg = (fbuf >= 0).nonzero().squeeze(-1)
        bary = torch.zeros(HW, 3, dtype=v.dtype, device=v.device)
        depth = torch.full((HW,), float("inf"), dtype=v.dtype, device=v.device)
        if fg.numel() > 0:
            f = fbuf[fg]
            tri = faces[f]  # (P, 3)
            uv, z = _project(v, Kb, Wb)
            lam, _ = _edge_lambdas(uv[tri], px_all[fg], py_all[fg])
            w = lam / z[tri]
            inv_z = w.sum(-1)
            d = 1.0 / inv_z
            bary = bary.index_put((fg,), w * d.unsqueeze(-1))
            depth = depth.index_put((fg,), d)
        face_ids.append(fbuf.view(height, width))
        barys.append(bary.view(height, width, 3))
        depths.append(depth.view(height, width))
    return MeshRaster(torch.stack(face_ids), torch.stack(barys), torch.stack(depths))


def ray_directions(K: torch.Tensor, w2c: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays through the pixel centres.

    K: (B, 3, 3) or (3, 3); w2c: (B, 4, 4) or (4, 4). Returns origins (B, H, W, 3), the camera
    centre repeated, and unit directions (B, H, W, 3) through (j + 0.5, i + 0.5). A hit at view
    depth z lies at origin + z · dir / dir_cam_z, where dir_cam_z is the direction's camera z.
    """
    K_b = _as_batch(K, 2, "K")
    w2c_b = _as_batch(w2c, 2, "w2c").to(K_b)
    B = _batch_size(K_b.shape[0], w2c_b.shape[0])
    K_b = K_b.expand(B, 3, 3)
    w2c_b = w2c_b.expand(B, 4, 4)
    width, height = int(width), int(height)
    jj, ii = torch.meshgrid(
        torch.arange(width, device=K_b.device, dtype=K_b.dtype) + 0.5,
        torch.arange(height, device=K_b.device, dtype=K_b.dtype) + 0.5,
        indexing="xy",
    )
    pix = torch.stack([jj, ii, torch.ones_like(jj)], -1)  # (H, W, 3)
    d_cam = torch.einsum("bij,hwj->bhwi", torch.linalg.inv(K_b), pix)
    R = w2c_b[:, :3, :3]
    t = w2c_b[:, :3, 3]
    d_world = torch.einsum("bji,bhwj->bhwi", R, d_cam)  # Rᵀ d
    dirs = d_world / d_world.norm(dim=-1, keepdim=True)
    centre = -torch.einsum("bji,bj->bi", R, t)  # −Rᵀ t
    origins = centre[:, None, None, :].expand(B, height, width, 3)
    return origins, dirs


def points_on_mesh(vertices: torch.Tensor, faces: torch.Tensor, face_id: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Points from face ids and barycentrics: Σ_i b_i · vertices[faces[f, i]].

    vertices: (V, 3); faces: (F, 3); face_id: (R,) int (all ≥ 0); bary: (R, 3) -> (R, 3).
    """
    tri = vertices[faces.to(device=vertices.device, dtype=torch.long)[face_id.long()]]  # (R, 3, 3)
    return (bary.unsqueeze(-1) * tri).sum(-2)


Frames = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _gather_frames(frames: Frames, face_id: torch.Tensor) -> Frames:
    R, T, k = frames
    if bool((face_id < 0).any()):
        raise ValueError("face_id contains background (−1) entries; select hit rays first")
    f = face_id.long()
    return R[f], T[f], k[f]


def warp_points_to_canonical(
    points: torch.Tensor, face_id: torch.Tensor, frames_deformed: Frames, frames_canonical: Frames
) -> torch.Tensor:
    """Map points through the similarity transform of the triangle they belong to.

    points: (R, 3) in the deformed (posed) space; face_id: (R,) int ≥ 0; frames_*: (R_f (F, 3, 3),
    T_f (F, 3), k_f (F,)) per-face frames of the deformed and canonical meshes (docs/formats.md §6; the GA
    or the surfel convention, as long as both use the same one). Returns (R, 3):
    x_c = T_c + k_c · R_c · R_dᵀ · (x − T_d) / k_d.
    """
    Rd, Td, kd = _gather_frames(frames_deformed, face_id)
    Rc, Tc, kc = _gather_frames(frames_canonical, face_id)
    local = torch.einsum("rji,rj->ri", Rd, points - Td) / kd.unsqueeze(-1)
    return Tc + kc.unsqueeze(-1) * torch.einsum("rij,rj->ri", Rc, local)


def warp_directions_to_canonical(
    dirs: torch.Tensor, face_id: torch.Tensor, frames_deformed: Frames, frames_canonical: Frames, normalize: bool = True
) -> torch.Tensor:
    """Map ray directions through the linear part of the same transform: d_c = (k_c / k_d) · R_c · R_dᵀ · d.

    dirs: (R, 3); face_id: (R,); frames as in :func:`warp_points_to_canonical`. With ``normalize``
    (default) the result is unit length; without it, a ray x_d + t·d maps to x_c + t·d_c.
    """
    Rd, _, kd = _gather_frames(frames_deformed, face_id)
    Rc, _, kc = _gather_frames(frames_canonical, face_id)
    out = torch.einsum("rij,rj->ri", Rc, torch.einsum("rji,rj->ri", Rd, dirs)) * (kc / kd).unsqueeze(-1)
    if normalize:
        out = out / out.norm(dim=-1, keepdim=True).clamp_min(1e-20)
    return out


def warp_rays_to_canonical(
    points: torch.Tensor, dirs: torch.Tensor, face_id: torch.Tensor, frames_deformed: Frames, frames_canonical: Frames
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp rays that hit the deformed mesh back to canonical space through the hit triangle's frames.

    points: (R, 3) ray hit points (or any points on the ray) in deformed space, e.g. from
    :func:`points_on_mesh` with the rasterizer's face ids and barycentrics; dirs: (R, 3);
    face_id: (R,) hit faces (≥ 0). Returns (points_c (R, 3), unit dirs_c (R, 3)).
    """
    return (
        warp_points_to_canonical(points, face_id, frames_deformed, frames_canonical),
        warp_directions_to_canonical(dirs, face_id, frames_deformed, frames_canonical),
    )
