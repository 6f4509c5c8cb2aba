"""Per-surfel projection: the splat→pixel matrix M, low-pass centre, hbb1 radius and tile rectangle.

Pixel coordinates are continuous with pixel centres at +0.5 (OpenCV K). Tile maths (16×16 tiles) is
done in pixel-index coordinates (continuous − 0.5), which is where hbb1 has its pixel centres, so the
tile rectangles equal hbb1's for the same image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from sage_core.geometry.rotations import quat_to_matrix

TILE = 16
CUTOFF = 3.0  # the disc u²+v² ≤ 3² bounds the screen box
FILTER_SIZE = math.sqrt(2.0) / 2.0  # low-pass σ in px
ALPHA_MIN = 1.0 / 255.0


@dataclass
class Projection:
    """Projected surfels for C cameras (leading dim C).

    Attributes:
        M: (C, N, 3, 3) rows Tu, Tv, Tw with M·(u, v, 1)ᵀ = (x·z, y·z, z).
        means2d: (C, N, 2) (or (N, 2) with ``squeeze``) projected centres in pixels; Tu[2] and
            Tv[2] are rebuilt from it, so its gradient is z_c·∂L/∂(Tu[2], Tv[2]) (the hbb1
            densification proxy in pixel units).
        center: (C, N, 2) exact dual-conic AABB centre, also the low-pass filter centre.
        depth: (C, N) view depth of the surfel centre.
        normal: (C, N, 3) camera-frame unit normal flipped to face the camera.
        radius: (C, N) int64 hbb1 square radius in px (0 where culled).
        rect: (C, N, 4) int64 tile rectangle (tx0, ty0, tx1, ty1), max exclusive.
        valid: (C, N) bool, not culled and touching at least one tile.
    """

    M: torch.Tensor
    means2d: torch.Tensor
    center: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    radius: torch.Tensor
    rect: torch.Tensor
    valid: torch.Tensor


def project_surfels(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    K: torch.Tensor,
    w2c: torch.Tensor,
    width: int,
    height: int,
    near: float,
    squeeze: bool = False,
) -> Projection:
    """Project N surfels into C cameras (docs/rendering.md §1.2, §1.7).

    means: (N, 3), quats: (N, 4) wxyz, scales: (N, 2), K: (C, 3, 3), w2c: (C, 4, 4).
    Culls: centre depth ≤ near, d = C*_33 ≥ 0 (the 3σ disc crosses the camera plane), a normal
    exactly perpendicular to the view direction of the centre, and rectangles touching no tile.
    With ``squeeze`` (C = 1), ``means2d`` is returned as (N, 2) and the rest is built from it, so
    that tensor itself sits upstream of every output.
    """
    R = quat_to_matrix(quats)  # (N, 3, 3), columns t_u, t_v, t_w
    Rcw = w2c[:, None, :3, :3]  # (C, 1, 3, 3)
    tcw = w2c[:, None, :3, 3]  # (C, 1, 3)
    a = (Rcw @ (R[:, :, 0] * scales[:, 0:1]).unsqueeze(-1)).squeeze(-1)  # (C, N, 3)
    b = (Rcw @ (R[:, :, 1] * scales[:, 1:2]).unsqueeze(-1)).squeeze(-1)
    pc = (Rcw @ means.unsqueeze(-1)).squeeze(-1) + tcw
    n = (Rcw @ R[:, :, 2].unsqueeze(-1)).squeeze(-1)
    M0 = K[:, None] @ torch.stack([a, b, pc], -1)  # (C, N, 3, 3)

    zc = pc[..., 2]
    z_safe = torch.where(zc.abs() > 1e-12, zc, torch.ones_like(zc))
    means2d = M0[..., :2, 2] / z_safe.unsqueeze(-1)  # (C, N, 2)
    if squeeze:
        means2d = means2d[0]
    m2 = means2d.unsqueeze(0) if squeeze else means2d
    col2 = torch.cat([m2 * z_safe.unsqueeze(-1), M0[..., 2:, 2]], -1)
    M = torch.cat([M0[..., :2], col2.unsqueeze(-1)], -1)

    Tu, Tv, Tw = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    c2 = CUTOFF * CUTOFF
    d = c2 * (Tw[..., 0] ** 2 + Tw[..., 1] ** 2) - Tw[..., 2] ** 2
    d_safe = torch.where(d < 0, d, -torch.ones_like(d))
    cx = (c2 * (Tu[..., 0] * Tw[..., 0] + Tu[..., 1] * Tw[..., 1]) - Tu[..., 2] * Tw[..., 2]) / d_safe
    cy = (c2 * (Tv[..., 0] * Tw[..., 0] + Tv[..., 1] * Tw[..., 1]) - Tv[..., 2] * Tw[..., 2]) / d_safe
    center = torch.stack([cx, cy], -1)

    cos = -(pc * n).sum(-1)
    normal = n * torch.where(cos > 0, 1.0, -1.0).to(n.dtype).unsqueeze(-1)

    with torch.no_grad():
        uu = (c2 * (Tu[..., 0] ** 2 + Tu[..., 1] ** 2) - Tu[..., 2] ** 2) / d_safe
        vv = (c2 * (Tv[..., 0] ** 2 + Tv[..., 1] ** 2) - Tv[..., 2] ** 2) / d_safe
        hx = (cx * cx - uu).clamp_min(1e-4).sqrt()
        hy = (cy * cy - vv).clamp_min(1e-4).sqrt()
        ok = (zc > near) & (d < 0) & (cos != 0) & torch.isfinite(hx) & torch.isfinite(hy)
        r = torch.maximum(torch.maximum(hx, hy), torch.full_like(hx, CUTOFF * FILTER_SIZE)).ceil()
        r = torch.where(ok, r, torch.zeros_like(r))
        gx, gy = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        px = torch.where(ok, cx - 0.5, torch.zeros_like(cx))
        py = torch.where(ok, cy - 0.5, torch.zeros_like(cy))
        # float64 keeps far-off-screen centres from overflowing the integer conversion
        px, py, r64 = px.double().clamp(-1e9, 1e9), py.double().clamp(-1e9, 1e9), r.double().clamp(0, 1e9)
        tx0 = torch.floor((px - r64) / TILE).clamp(0, gx).long()
        ty0 = torch.floor((py - r64) / TILE).clamp(0, gy).long()
        tx1 = torch.floor((px + r64 + TILE - 1) / TILE).clamp(0, gx).long()
        ty1 = torch.floor((py + r64 + TILE - 1) / TILE).clamp(0, gy).long()
        valid = ok & ((tx1 - tx0) * (ty1 - ty0) > 0)
        radius = torch.where(valid, r64.long(), torch.zeros_like(tx0))
        rect = torch.stack([tx0, ty0, tx1, ty1], -1) * valid.unsqueeze(-1)
    return Projection(M, means2d, center, zc, normal, radius, rect, valid)


def candidate_pixel_boxes(
    M: torch.Tensor, center: torch.Tensor, opacities: torch.Tensor, rect: torch.Tensor, width: int, height: int
) -> torch.Tensor:
    """Pixel boxes that contain every pixel of a surfel's tiles where α can reach 1/255.

    α ≥ 1/255 needs ρ = min(ρ3d, ρ2d) ≤ B = 2·ln(255·o). ρ3d ≤ B is the projected disc of radius √B,
    bounded exactly by the dual conic with t = (B, B, −1) when that disc lies in front of the camera
    (otherwise the whole tile rectangle is kept); ρ2d ≤ B is a square of half-size √(B/2) around the
    low-pass centre. The union box, widened by one pixel, is intersected with the tile rectangle, so
    the candidate set stays exactly hbb1's significant set while skipping most empty tile pixels.

    M: (N, 3, 3), center: (N, 2), opacities: (N,), rect: (N, 4) tiles. Returns (N, 4) int64 pixel
    box (x0, y0, x1, y1), max exclusive; empty boxes have x1 ≤ x0 or y1 ≤ y0.
    """
    with torch.no_grad():
        Mf = M.detach().double()
        Tu, Tv, Tw = Mf[:, 0], Mf[:, 1], Mf[:, 2]
        o = opacities.detach().double()
        B = 2.0 * torch.log((255.0 * o).clamp_min(1e-30))
        B = B.clamp_min(0.0)
        d = B * (Tw[:, 0] ** 2 + Tw[:, 1] ** 2) - Tw[:, 2] ** 2
        bounded = d < 0
        d_safe = torch.where(bounded, d, -torch.ones_like(d))
        ex = (B * (Tu[:, 0] * Tw[:, 0] + Tu[:, 1] * Tw[:, 1]) - Tu[:, 2] * Tw[:, 2]) / d_safe
        ey = (B * (Tv[:, 0] * Tw[:, 0] + Tv[:, 1] * Tw[:, 1]) - Tv[:, 2] * Tw[:, 2]) / d_safe
        uu = (B * (Tu[:, 0] ** 2 + Tu[:, 1] ** 2) - Tu[:, 2] ** 2) / d_safe
        vv = (B * (Tv[:, 0] ** 2 + Tv[:, 1] ** 2) - Tv[:, 2] ** 2) / d_safe
        hx = (ex * ex - uu).clamp_min(0.0).sqrt()
        hy = (ey * ey - vv).clamp_min(0.0).sqrt()
        r2 = (B / 2.0).sqrt()
        c = center.detach().double()
        lo_x = torch.minimum(ex - hx, c[:, 0] - r2)
        hi_x = torch.maximum(ex + hx, c[:, 0] + r2)
        lo_y = torch.minimum(ey - hy, c[:, 1] - r2)
        hi_y = torch.maximum(ey + hy, c[:, 1] + r2)
        big = 1e9
        finite = torch.isfinite(lo_x) & torch.isfinite(hi_x) & torch.isfinite(lo_y) & torch.isfinite(hi_y)
        bounded = bounded & finite
        x0 = torch.where(bounded, torch.floor(lo_x.clamp(-big, big) - 0.5) - 1, torch.full_like(lo_x, -big))
        x1 = torch.where(bounded, torch.floor(hi_x.clamp(-big, big) - 0.5) + 2, torch.full_like(lo_x, big))
        y0 = torch.where(bounded, torch.floor(lo_y.clamp(-big, big) - 0.5) - 1, torch.full_like(lo_x, -big))
        y1 = torch.where(bounded, torch.floor(hi_y.clamp(-big, big) - 0.5) + 2, torch.full_like(lo_x, big))
        x0 = torch.maximum(x0.long(), rect[:, 0] * TILE).clamp_min(0)
        y0 = torch.maximum(y0.long(), rect[:, 1] * TILE).clamp_min(0)
        x1 = torch.minimum(x1.long(), (rect[:, 2] * TILE).clamp_max(width))
        y1 = torch.minimum(y1.long(), (rect[:, 3] * TILE).clamp_max(height))
        empty = (o < ALPHA_MIN) | (x1 <= x0) | (y1 <= y0)
        x1 = torch.where(empty, x0, x1)
        y1 = torch.where(empty, y0, y1)
        return torch.stack([x0, y0, x1, y1], -1)
