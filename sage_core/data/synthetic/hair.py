"""Hair volume of a detailed synthetic subject: geometry off the scalp that the FLAME-format model
does not have (``appearance="detailed"``).

A sheet of hair follows the scalp at ``hair_volume_mm`` (fuller at the crown and back, merging
into the scalp at the hairline); depending on the style it continues as a fringe over the forehead,
hangs to the jaw at the sides and back (bob), or carries a bun at the back of the crown. The sheet
is built along the columns of the head's latitude/longitude grid (template space) and described
relative to head vertices, so it follows the subject's identity shape and static offset; in a
posed frame it moves rigidly with the skull (the least-squares rigid motion of the scalp vertices,
which are skinned to the neck joint alone and have no expression), like real hair on a turning
head. It is part of the ground truth only: it is rendered into the images and masks and written
to ``gt/hair/``, never into ``model/``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ._fields import _hash01, smoothstep
from .detail import DetailStyle, _frame
from .head import PART_SKIN, HeadModel, _azimuth, _uv_sphere, hair_weight
from .mesh_render import vertex_normals

FRAME_SCALP, FRAME_BUN = 0, 1


@dataclass
class HairVolume:
    """Hair geometry described relative to the head (template space, float64).

    Vertex i sits at ``lerp(V[src[i, 0]], V[src[i, 1]], w[i]) + h[i]·n + extra[i]`` for head
    vertices V (n: the interpolated, normalised vertex normal), so identity and static offset carry
    over.

    Attributes:
        src: (H, 2) int64 head vertex ids; w: (H,) weight of the second one.
        h: (H,) offset along the head normal (metres); extra: (H, 3) further template offset.
        faces: (F, 3) int64 triangles over the hair vertices.
        tex: (H, 3) texture positions (template space) of the hair texture: the hair's own
            template position.
        tangent: (H, 3) unit strand direction (template space): down the sheet's columns, around
            the bun from its outer pole.
        force: (H,) in [0, 1]: hair regardless of the scalp's hairline (fringe, bob, bun).
        frame: (H,) int8 strand frame: :data:`FRAME_SCALP` (the crown whorl) or :data:`FRAME_BUN`.
        skull: (K,) int64 head vertex ids that move rigidly with the skull (for the posed fit).
        bun_frame: (origin, pole, e1, e2) of the bun's strands (template space), or None.
    """

    src: np.ndarray
    w: np.ndarray
    h: np.ndarray
    extra: np.ndarray
    faces: np.ndarray
    tex: np.ndarray
    tangent: np.ndarray
    force: np.ndarray
    frame: np.ndarray
    skull: np.ndarray
    bun_frame: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.src.shape[0])

    def place(self, head_vertices: np.ndarray, head_faces: np.ndarray) -> np.ndarray:
        """(H, 3) hair vertices on a head mesh (template or canonical) with vertices (V, 3)."""
        n = vertex_normals(head_vertices, head_faces)
        a, b = head_vertices[self.src[:, 0]], head_vertices[self.src[:, 1]]
        nn = n[self.src[:, 0]] * (1.0 - self.w[:, None]) + n[self.src[:, 1]] * self.w[:, None]
        nn /= np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12)
        return a * (1.0 - self.w[:, None]) + b * self.w[:, None] + self.h[:, None] * nn + self.extra


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation R (3, 3) and translation t (3,) with dst ≈ src @ R.T + t (Kabsch)."""
    cs, cd = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cd - R @ cs


@dataclass
class PosedHair:
    """The hair volume in one frame: vertices (H, 3), the volume and the skull rotation R (3, 3)
    (template directions such as strand tangents map to the frame by R)."""

    vertices: np.ndarray
    volume: HairVolume
    rotation: np.ndarray


def pose_hair(volume: HairVolume, canonical_head: np.ndarray, canonical_hair: np.ndarray, posed_head: np.ndarray) -> PosedHair:
    """The hair of a frame: ``canonical_hair`` (H, 3) moved by the rigid motion of the skull
    vertices from ``canonical_head`` (V, 3) to ``posed_head`` (V, 3)."""
    R, t = rigid_fit(canonical_head[volume.skull], posed_head[volume.skull])
    return PosedHair(canonical_hair @ R.T + t, volume, R)


def skull_vertices(head: HeadModel) -> np.ndarray:
    """Head vertex ids that move rigidly with the skull: skin of the scalp skinned to the neck joint
    alone, without expression displacement."""
    v = head.v_template
    expr = np.abs(head.shapedirs[:, :, 300:]).reshape(v.shape[0], -1).max(1)
    ok = (head.part == PART_SKIN) & (head.weights[:, 1] > 1.0 - 1e-9) & (hair_weight(v) > 0.99) & (expr < 1e-12) & (v[:, 1] > 0.05)
    return np.flatnonzero(ok).astype(np.int64)


def build_hair(head: HeadModel, st: DetailStyle) -> HairVolume:
    """The hair volume of a style on ``head`` (whose skin grid is ``head.grid_shape``)."""
    R, C = head.grid_shape
    v = head.v_template
    n = vertex_normals(v, head.faces)
    cols = np.arange(C)
    ids = np.concatenate([np.zeros((1, C), np.int64), 1 + np.arange(R)[:, None] * C + cols[None]], 0)  # (R+1, C) pole first
    pts = v[ids]  # (R+1, C, 3)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=2)
    s = np.concatenate([np.zeros((1, C)), np.cumsum(seg, 0)], 0)  # arc length from the pole
    phi = _azimuth(pts[1])  # (C,) 0 = face
    aphi = np.abs(phi)
    hw = hair_weight(pts.reshape(-1, 3)).reshape(R + 1, C)
    y = pts[..., 1]

    def arc_at(mask_below: np.ndarray) -> np.ndarray:
        """Per column, the arc length where ``mask_below`` (R+1, C) first turns true (interpolated)."""
        out = np.empty(C)
        for c in range(C):
            k = int(np.argmax(mask_below[:, c])) if mask_below[:, c].any() else R
            out[c] = s[max(k - 1, 0), c] if k == 0 else 0.5 * (s[k - 1, c] + s[k, c])
        return out

    def arc_at_y(y_end: np.ndarray) -> np.ndarray:
        out = np.empty(C)
        for c in range(C):
            out[c] = np.interp(-y_end[c], -y[:, c], s[:, c])
        return out

    jag = 0.006 * (_hash01(cols, np.zeros(C, np.int64), np.zeros(C, np.int64), st.seed + 70) - 0.5)
    s_hair = arc_at(hw < 0.5)
    vol = 1e-3 * st.hair_volume_mm * (0.6 + 0.4 * (1.0 - np.cos(phi)) / 2.0)
    f_fringe = np.zeros(C)
    f_bob = np.zeros(C)
    s_end = s_hair.copy()
    if st.hair_style == "fringe":
        f_fringe = smoothstep(aphi, 1.05, 0.8)
        s_fr = arc_at_y(0.052 + 1e-3 * st.fringe_gap_mm + jag)
        s_end = s_hair + (np.maximum(s_fr, s_hair) - s_hair) * f_fringe
    elif st.hair_style == "bob":
        f_bob = smoothstep(aphi, 1.0, 1.35)
        back = smoothstep(aphi, 1.8, 2.8)
        s_bob = arc_at_y(st.bob_end_y - 0.03 * back + 2 * jag)
        s_end = s_hair + (np.maximum(s_bob, s_hair) - s_hair) * f_bob
    K = max(12, int(round(0.45 * R)))
    frac = np.arange(1, K + 1) / K
    s_rows = frac[:, None] * s_end[None]  # (K, C)
    src = np.zeros((K, C, 2), np.int64)
    wgt = np.zeros((K, C))
    for c in range(C):
        k = np.clip(np.searchsorted(s[:, c], s_rows[:, c], side="right") - 1, 0, R - 1)
        span = np.maximum(s[k + 1, c] - s[k, c], 1e-12)
        src[:, c, 0], src[:, c, 1] = ids[k, c], ids[k + 1, c]
        wgt[:, c] = np.clip((s_rows[:, c] - s[k, c]) / span, 0.0, 1.0)
    taper = smoothstep(s_rows, s_hair[None] + 0.002, s_hair[None] - 0.02)
    keep_out = np.maximum(f_fringe, f_bob)[None]
    h = vol[None] * (taper + (1.0 - taper) * f_bob[None]) + f_fringe[None] * (1.0 - taper) * (0.0035 + 0.3 * vol[None])
    force = np.broadcast_to(keep_out, h.shape)
    # sheet points without the hang (template) for the bob's hang and the texture positions
    a, b = v[src[..., 0]], v[src[..., 1]]
    base = a * (1.0 - wgt[..., None]) + b * wgt[..., None]
    nn = n[src[..., 0]] * (1.0 - wgt[..., None]) + n[src[..., 1]] * wgt[..., None]
    nn /= np.maximum(np.linalg.norm(nn, axis=-1, keepdims=True), 1e-12)
    sheet = base + h[..., None] * nn
    extra = np.zeros_like(sheet)
    if st.hair_style == "bob":
        # below the widest point of each column the hair hangs as a curtain: it keeps that radius
        # about the vertical axis (narrowing slightly) and the height of the skin behind it
        axis = np.array([0.0, -0.005])
        rad = sheet[..., [0, 2]] - axis
        rho = np.linalg.norm(rad, axis=-1)
        k_w = np.argmax(rho, axis=0)  # row of the widest point per column
        rows = np.arange(K)[:, None]
        below = rows > k_w[None]
        rho_w = rho[k_w, cols]
        drop = np.clip(s_rows - s_rows[k_w, cols][None], 0.0, None)
        unit = rad / np.maximum(rho[..., None], 1e-12)
        unit_w = unit[k_w, cols]
        curtain = np.empty_like(sheet)
        r_c = np.maximum(rho_w[None] - 0.08 * drop, 0.0)
        curtain[..., 0] = axis[0] + unit_w[None, :, 0] * r_c
        curtain[..., 2] = axis[1] + unit_w[None, :, 1] * r_c
        curtain[..., 1] = np.minimum(base[..., 1], sheet[k_w, cols, 1][None])
        wgt_c = (below * smoothstep(drop, 0.0, 0.01) * f_bob[None])[..., None]
        extra = (curtain - sheet) * wgt_c
    pole_h = float(np.max(vol))
    placed = sheet + extra  # template positions of the sheet
    pole = v[0] + pole_h * n[0]
    prev = np.concatenate([np.broadcast_to(pole, (1, C, 3)), placed[:-1]], 0)
    tangent = placed - prev
    tangent /= np.maximum(np.linalg.norm(tangent, axis=-1, keepdims=True), 1e-12)
    H_sheet = 1 + K * C
    src_all = np.concatenate([[[0, 0]], src.reshape(-1, 2)], 0)
    w_all = np.concatenate([[0.0], wgt.reshape(-1)])
    h_all = np.concatenate([[pole_h], h.reshape(-1)])
    extra_all = np.concatenate([np.zeros((1, 3)), extra.reshape(-1, 3)], 0)
    tex_all = np.concatenate([pole[None], placed.reshape(-1, 3)], 0)
    tan_all = np.concatenate([np.zeros((1, 3)), tangent.reshape(-1, 3)], 0)
    force_all = np.concatenate([[0.0], force.reshape(-1)])
    grid = 1 + np.arange(K * C).reshape(K, C)
    faces = [np.stack([np.zeros(C, np.int64), grid[0], np.roll(grid[0], -1)], -1)]
    aa, bb = grid[:-1], grid[1:]
    cc, dd = np.roll(grid[1:], -1, axis=1), np.roll(grid[:-1], -1, axis=1)
    faces += [np.stack([aa, bb, cc], -1).reshape(-1, 3), np.stack([aa, cc, dd], -1).reshape(-1, 3)]
    faces_all = np.concatenate(faces, 0)
    frame_all = np.zeros(H_sheet, np.int8)
    bun_frame = None
    if st.hair_style == "bun":
        parts = _bun(head, st, n)
        bsrc, bextra, bfaces, btex, bun_frame = parts
        nb = len(bsrc)
        o, w = bun_frame[0], bun_frame[1]
        q = btex - o
        meridian = np.cross(np.cross(w, q), q)  # along the bun's meridians, away from its outer pole
        meridian = -meridian / np.maximum(np.linalg.norm(meridian, axis=1, keepdims=True), 1e-12)
        tan_all = np.concatenate([tan_all, meridian], 0)
        src_all = np.concatenate([src_all, bsrc], 0)
        w_all = np.concatenate([w_all, np.zeros(nb)])
        h_all = np.concatenate([h_all, np.zeros(nb)])
        extra_all = np.concatenate([extra_all, bextra], 0)
        tex_all = np.concatenate([tex_all, btex], 0)
        force_all = np.concatenate([force_all, np.ones(nb)])
        frame_all = np.concatenate([frame_all, np.full(nb, FRAME_BUN, np.int8)])
        faces_all = np.concatenate([faces_all, bfaces + H_sheet], 0)
    return HairVolume(src_all.astype(np.int64), w_all, h_all, extra_all, faces_all.astype(np.int64), tex_all, tan_all, force_all,
                      frame_all, skull_vertices(head), bun_frame)


def _bun(head: HeadModel, st: DetailStyle, normals: np.ndarray):
    """A bun at the back of the crown: an ellipsoid flattened against the head, anchored to the
    nearest scalp vertex; its strands wrap around its outer pole."""
    v = head.v_template
    ang = math.radians(58.0) + 0.3 * (st.whorl[0] - 0.5)
    d = np.array([0.0, math.cos(ang), -math.sin(ang)])
    skin = np.flatnonzero(head.part == PART_SKIN)
    rel = v[skin] - np.array([0.0, 0.01, -0.005])
    k = skin[int(np.argmax(rel @ d / np.maximum(np.linalg.norm(rel, axis=1), 1e-12)))]
    radius = 0.026 + 0.0012 * (st.hair_volume_mm - 5.0)
    centre = v[k] + normals[k] * (1e-3 * st.hair_volume_mm + 0.55 * radius)
    _, bf, dirs = _uv_sphere(np.zeros(3), 1.0, 9, 16)
    o, w, e1, e2 = _frame(centre, normals[k], np.array([0.0, 1.0, 0.0]))
    local = dirs @ np.stack([e1, e2, w], 0)  # sphere directions in the bun frame (pole along w)
    squash = local - 0.25 * (local @ w)[:, None] * w[None]
    pos = centre + radius * squash
    nb = len(pos)
    src = np.full((nb, 2), k, np.int64)
    return src, pos - v[k], bf.astype(np.int64), pos, (o, w, e1, e2)
