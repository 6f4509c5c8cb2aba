"""A procedural FLAME-style head: template mesh, joints, skinning, identity and expression bases.

The head is one closed surface (open only at the neck base) built on a latitude/longitude grid
around the skull, with a mouth slit whose lips part when the jaw opens (the slit leads into a
closed mouth pocket) and two separate eyeball spheres sitting in eye sockets. Units are metres,
FLAME's world: face towards +z, up +y, subject's left at +x; the head is centred near the origin.

Joints follow FLAME: 0 root (neck base), 1 neck, 2 jaw (near the ear line), 3 left eye (+x),
4 right eye, parents [-1, 0, 1, 1, 1]. ``shapedirs`` has FLAME's 400 columns: identity in
[:300] (the first :data:`N_IDENTITY` non-zero), expression in [300:400] (the first
:data:`N_EXPRESSION` non-zero).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._fields import gauss, smoothstep

N_SHAPE_COLUMNS = 300
N_EXPR_COLUMNS = 100
IDENTITY_NAMES = (
    "head_width",
    "head_length",
    "face_length",
    "nose_size",
    "jaw_width",
    "cheek_fullness",
    "chin_forward",
    "lip_fullness",
)
EXPRESSION_NAMES = (
    "lips_part",
    "smile",
    "pucker",
    "lip_press",
    "brow_raise",
    "brow_furrow",
    "blink",
    "cheek_puff",
    "nose_wrinkle",
    "mouth_corners_down",
    "blink_left",
    "blink_right",
    "mouth_stretch",
)
N_IDENTITY = len(IDENTITY_NAMES)
N_EXPRESSION = len(EXPRESSION_NAMES)
PARENTS = np.array([-1, 0, 1, 1, 1], dtype=np.int64)

# Vertex part codes (HeadModel.part)
PART_SKIN, PART_LEFT_EYE, PART_RIGHT_EYE, PART_MOUTH = 0, 1, 2, 3

# Base skull: ellipsoid centre and semi-axes (front/back and top/bottom differ).
_C = np.array([0.0, 0.01, -0.005])
_AX, _AY_TOP, _AY_BOT, _AZ_FRONT, _AZ_BACK = 0.075, 0.11, 0.12, 0.092, 0.105
_THETA_NECK = np.deg2rad(145.0)
_THETA_MOUTH = np.deg2rad(114.0)
_NECK_BOTTOM_Y = -0.165
_NECK_CZ, _NECK_RX, _NECK_RZ = -0.012, 0.05, 0.055
_EYE_X, _EYE_Y, _EYE_R = 0.032, 0.025, 0.0125
_SOCKET_DEPTH, _SOCKET_SX, _SOCKET_SY = 0.0078, 0.0125, 0.0068
_MOUTH_HALF_WIDTH = 0.024
_POCKET_LAYERS, _POCKET_DEPTH, _POCKET_GAP = 3, 0.02, 0.006


@dataclass
class HeadModel:
    """The procedural model as plain arrays (float64).

    Attributes:
        v_template: (V, 3) template vertices.
        faces: (F, 3) int64 triangles, outward winding.
        shapedirs: (V, 3, 400) identity [:300] and expression [300:] blendshapes.
        posedirs: (V, 3, 36) pose correctives (zeros).
        j_regressor: (5, V) joint regressor (rows are convex vertex weights).
        weights: (V, 5) skinning weights (rows sum to 1).
        part: (V,) int8 part code (skin, left/right eyeball, mouth pocket).
        side: (V,) int8 +1 above the mouth slit, -1 below it (jaw side), 0 on the slit corners.
        eye_dir: (V, 3) unit direction from the eyeball centre (eyeball vertices; zeros elsewhere).
        mouth_depth: (V,) 0 at the lips .. 1 at the back of the mouth pocket.
        masks: region name -> sorted int64 vertex ids (FLAME_masks.pkl keys).
        neck_line: vertex ids (left, right, front-bottom) for the neck-line rule (docs/formats.md §1.1).
        mouth_y: height of the mouth slit in the template.
        slit_pairs: (n, 2) int64 (upper, lower) vertex ids that coincide on the closed mouth slit.
        grid_shape: (rows, cols) of the skin grid: vertex 0 is the top pole, grid vertex (r, c) is
            ``1 + r·cols + c`` (rows from the top to the neck base, columns around the head).
    """

    v_template: np.ndarray
    faces: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    j_regressor: np.ndarray
    weights: np.ndarray
    part: np.ndarray
    side: np.ndarray
    eye_dir: np.ndarray
    mouth_depth: np.ndarray
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    neck_line: tuple[int, int, int] = (0, 0, 0)
    mouth_y: float = 0.0
    slit_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    grid_shape: tuple[int, int] = (0, 0)

    @property
    def n_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def joints(self) -> np.ndarray:
        """(5, 3) template joints."""
        return self.j_regressor @ self.v_template


# ----------------------------------------------------------------------------- base surface


def _row_angles(n_head_rows: int) -> np.ndarray:
    """Polar angles (n,) of the head rows, denser over the face band."""
    grid = np.linspace(0.0, _THETA_NECK, 4001)
    dens = 1.0 + 1.6 * gauss(grid - np.deg2rad(100.0), np.deg2rad(28.0))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    cdf /= cdf[-1]
    q = np.arange(1, n_head_rows + 1) / n_head_rows
    return np.interp(q, cdf, grid)


def _col_angles(n_cols: int) -> np.ndarray:
    """Azimuths (n,) in [-pi, pi), 0 = front (+z), denser at the front."""
    s = np.arange(n_cols) / n_cols * 2.0 - 1.0  # [-1, 1)
    a = 0.45
    return np.pi * (s + a * np.sin(np.pi * s) / np.pi)


def _skull(theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ellipsoid points and outward normals for broadcastable (theta, phi) -> (..., 3) each."""
    st, ct = np.sin(theta), np.cos(theta)
    sp, cp = np.sin(phi), np.cos(phi)
    ay = np.where(ct >= 0, _AY_TOP, _AY_BOT)
    az = np.where(cp >= 0, _AZ_FRONT, _AZ_BACK)
    d = np.stack(np.broadcast_arrays(st * sp * _AX, ct * ay, st * cp * az), -1)
    p = _C + d
    n = np.stack(np.broadcast_arrays(st * sp / _AX, ct / ay, st * cp / az), -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return p, n


def _skull_front_z(x: float, y: float) -> float:
    ay = _AY_TOP if y >= _C[1] else _AY_BOT
    return float(_C[2] + _AZ_FRONT * np.sqrt(max(0.0, 1.0 - (x / _AX) ** 2 - ((y - _C[1]) / ay) ** 2)))


def _nose_height(p: np.ndarray) -> np.ndarray:
    """Nose profile height (N,) along the skull normal."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    u = np.clip((0.03 - y) / 0.036, 0.0, 1.0)
    ridge = 0.0035 + 0.021 * u**1.6
    above = 0.0035 * gauss(y - 0.03, 0.012)
    below = 0.0245 * gauss(y + 0.006, 0.0062)
    amp = np.where(y > 0.03, above, np.where(y < -0.006, below, ridge))
    width = 0.0065 + 0.0065 * np.clip((0.03 - y) / 0.036, 0.0, 1.2)
    return amp * np.exp(-np.square(x / width) ** 1.3) * smoothstep(z, 0.02, 0.06)


def _eye_gauss(p: np.ndarray, sign: float) -> np.ndarray:
    return gauss(p[:, 0] - sign * _EYE_X, _SOCKET_SX) * gauss(p[:, 1] - _EYE_Y, _SOCKET_SY) * smoothstep(p[:, 2], 0.02, 0.05)


def _face_height(p: np.ndarray, mouth_y: float) -> np.ndarray:
    """Sum of the facial relief heights (N,) along the skull normal (sockets included)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    front = smoothstep(z, -0.01, 0.045)
    lipx = np.exp(-((x / 0.023) ** 4))
    h = _nose_height(p)
    h -= _SOCKET_DEPTH * (_eye_gauss(p, 1.0) + _eye_gauss(p, -1.0))
    h += 0.0045 * gauss(y - 0.044, 0.008) * gauss(ax - 0.03, 0.022) * front
    h += 0.004 * gauss(ax - 0.046, 0.014) * gauss(y - 0.002, 0.014) * front
    h += 0.0045 * gauss(y - (mouth_y + 0.0045), 0.0035) * lipx * front
    h += 0.005 * gauss(y - (mouth_y - 0.0055), 0.004) * lipx * front
    h -= 0.0012 * gauss(y - mouth_y, 0.0015) * lipx * front
    h += 0.015 * gauss(y + 0.058, 0.028) * smoothstep(z, -0.04, 0.03) * smoothstep(y, -0.1, -0.08)
    h += 0.008 * gauss(y + 0.078, 0.011) * gauss(x, 0.02) * front
    h -= 0.003 * gauss(ax - 0.064, 0.012) * gauss(y - 0.045, 0.02) * smoothstep(z, 0.0, 0.03)
    return h


def _ear_offset(p: np.ndarray) -> np.ndarray:
    """(N, 3) outward ear bumps on the sides of the head."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    w = gauss(y - 0.012, 0.021) * gauss(z + 0.014, 0.0105) * smoothstep(np.abs(x), 0.05, 0.072)
    off = np.zeros_like(p)
    off[:, 0] = 0.017 * w * np.sign(x)
    off[:, 2] = -0.004 * w
    return off


# ----------------------------------------------------------------------------- topology


def _grid_faces(idx: np.ndarray) -> list[np.ndarray]:
    """Quads between consecutive rows of an (R, C) periodic index grid -> triangle arrays."""
    a = idx[:-1]
    b = idx[1:]
    c = np.roll(idx[1:], -1, axis=1)
    d = np.roll(idx[:-1], -1, axis=1)
    return [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]


def _uv_sphere(center: np.ndarray, radius: float, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sphere with poles on ±z. Returns (vertices (2 + rows·cols, 3), faces, unit directions)."""
    lat = np.pi * (np.arange(1, rows + 1) / (rows + 1))  # from the front pole (+z)
    lon = 2 * np.pi * np.arange(cols) / cols
    d = np.stack(
        [
            np.sin(lat)[:, None] * np.cos(lon)[None],
            np.sin(lat)[:, None] * np.sin(lon)[None],
            np.broadcast_to(np.cos(lat)[:, None], (rows, cols)),
        ],
        -1,
    ).reshape(-1, 3)
    dirs = np.concatenate([[[0.0, 0.0, 1.0]], d, [[0.0, 0.0, -1.0]]], 0)
    idx = 1 + np.arange(rows * cols).reshape(rows, cols)
    faces = _grid_faces(idx)
    front = np.stack([np.zeros(cols, np.int64), idx[0], np.roll(idx[0], -1)], -1)
    back = np.stack([np.full(cols, rows * cols + 1), np.roll(idx[-1], -1), idx[-1]], -1)
    f = np.concatenate([front] + faces + [back], 0)
    # orient outward: the grid runs from +z pole with longitude counter-clockwise about z
    v = center + radius * dirs
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if np.sum(np.einsum("ij,ij->i", nrm, tri.mean(1) - center)) < 0:
        f = f[:, ::-1]
    return v, f.astype(np.int64), dirs


# ----------------------------------------------------------------------------- builder


def build_head(head_rows: int = 110, head_cols: int = 144, eye_rows: int = 12, eye_cols: int = 20) -> HeadModel:
    """Build the procedural head.

    head_rows: rows of the skin grid (pole to neck base); head_cols: columns around the head;
    eye_rows, eye_cols: latitude/longitude resolution of each eyeball.
    """
    n_neck = max(4, head_rows // 8)
    n_head = head_rows - n_neck
    theta = _row_angles(n_head)
    phi = _col_angles(head_cols)
    r_m = int(np.argmin(np.abs(theta - _THETA_MOUTH)))

    base, normal = _skull(theta[:, None], phi[None, :])  # (n_head, C, 3)
    ring = base[-1]
    neck_xz = np.stack([_NECK_RX * np.sin(phi), _NECK_CZ + _NECK_RZ * np.cos(phi)], -1)
    neck_rows, neck_norm = [], []
    for k in range(1, n_neck + 1):
        t = k / n_neck
        s = smoothstep(t, 0.0, 0.6)
        p = np.empty((head_cols, 3))
        p[:, 0] = (1 - s) * ring[:, 0] + s * neck_xz[:, 0]
        p[:, 2] = (1 - s) * ring[:, 2] + s * neck_xz[:, 1]
        p[:, 1] = (1 - t) * ring[:, 1] + t * _NECK_BOTTOM_Y
        n = np.stack([np.sin(phi), np.zeros_like(phi), np.cos(phi)], -1)
        neck_rows.append(p)
        neck_norm.append(n)
    grid = np.concatenate([base, np.stack(neck_rows)], 0)  # (R, C, 3)
    gnorm = np.concatenate([normal, np.stack(neck_norm)], 0)
    R, C = grid.shape[:2]
    mouth_y = float(grid[r_m, np.argmin(np.abs(phi)), 1])

    top = _C + np.array([0.0, _AY_TOP, 0.0])
    skin = np.concatenate([top[None], grid.reshape(-1, 3)], 0)
    skin_n = np.concatenate([[[0.0, 1.0, 0.0]], gnorm.reshape(-1, 3)], 0)
    rel = _face_height(skin, mouth_y)
    skin = skin + rel[:, None] * skin_n + _ear_offset(skin)
    idx = 1 + np.arange(R * C).reshape(R, C)

    # mouth slit on row r_m: interior columns get a lower copy
    x_row = skin[idx[r_m], 0]
    front_cols = np.abs(phi) < np.pi / 2
    in_slit = front_cols & (np.abs(x_row) < _MOUTH_HALF_WIDTH)
    slit_cols = np.flatnonzero(in_slit)
    slit_cols = slit_cols[np.argsort(phi[slit_cols])]
    corner_l, corner_r = slit_cols[0] - 1, slit_cols[-1] + 1
    n_skin = skin.shape[0]
    lower_copy = {int(j): n_skin + k for k, j in enumerate(slit_cols)}
    verts = [skin, skin[idx[r_m, slit_cols]]]
    side_list = [np.zeros(n_skin, np.int8), -np.ones(len(slit_cols), np.int8)]
    side_skin = side_list[0]
    row_of = np.full(n_skin, -1)
    row_of[idx] = np.arange(R)[:, None]
    side_skin[row_of < r_m] = 1
    side_skin[row_of > r_m] = -1
    side_skin[idx[r_m, slit_cols]] = 1
    side_skin[0] = 1

    faces = [np.stack([np.zeros(C, np.int64), idx[0], np.roll(idx[0], -1)], -1)]
    faces += _grid_faces(idx[: r_m + 1])
    band = idx[r_m : r_m + 2].copy()
    for j, vid in lower_copy.items():
        band[0, j] = vid
    faces += _grid_faces(band)
    faces += _grid_faces(idx[r_m + 1 :])

    # mouth pocket: the slit loop extruded inwards and zipped shut at the back
    upper = np.concatenate([[idx[r_m, corner_l]], idx[r_m, slit_cols], [idx[r_m, corner_r]]])
    lower = np.concatenate([[idx[r_m, corner_l]], [lower_copy[int(j)] for j in slit_cols], [idx[r_m, corner_r]]])
    all_v = np.concatenate(verts, 0)
    n_loop = len(upper)
    loop_prev_u, loop_prev_l = upper, lower
    next_id = all_v.shape[0]
    pocket_pos, pocket_side, pocket_depth = [], [], []
    for k in range(1, _POCKET_LAYERS + 1):
        t = k / _POCKET_LAYERS
        open_amt = _POCKET_GAP * np.sin(np.pi * k / (_POCKET_LAYERS + 1.5))
        pu = all_v[upper].copy()
        pl = all_v[lower].copy()
        for pts, sgn in ((pu, 1.0), (pl, -1.0)):
            pts[:, 2] -= _POCKET_DEPTH * t
            pts[:, 0] *= 1.0 - 0.2 * t
            bulge = np.sin(np.pi * np.linspace(0, 1, n_loop))
            pts[:, 1] += sgn * open_amt * bulge
        ids_u = np.arange(next_id, next_id + n_loop)
        next_id += n_loop
        ids_l = np.concatenate([[ids_u[0]], np.arange(next_id, next_id + n_loop - 2), [ids_u[-1]]])
        next_id += n_loop - 2
        pocket_pos += [pu, pl[1:-1]]
        side_u = np.ones(n_loop, np.int8)
        side_u[[0, -1]] = 0
        pocket_side += [side_u, -np.ones(n_loop - 2, np.int8)]
        pocket_depth += [np.full(n_loop, t), np.full(n_loop - 2, t)]
        for prev, cur in ((loop_prev_u, ids_u), (loop_prev_l, ids_l)):
            a, b = prev[:-1], cur[:-1]
            c, d = cur[1:], prev[1:]
            faces.append(np.stack([a, b, c], -1))
            faces.append(np.stack([a, c, d], -1))
        loop_prev_u, loop_prev_l = ids_u, ids_l
    u, l_ = loop_prev_u, loop_prev_l
    zip_faces = [np.array([[u[0], u[1], l_[1]]]), np.array([[u[-2], u[-1], l_[-2]]])]
    for i in range(1, n_loop - 2):
        zip_faces.append(np.array([[u[i], u[i + 1], l_[i + 1]], [u[i], l_[i + 1], l_[i]]]))
    faces += zip_faces
    verts = [all_v, np.concatenate(pocket_pos, 0)]
    n_head_v = next_id
    head_faces = np.concatenate(faces, 0).astype(np.int64)
    head_v = np.concatenate(verts, 0)
    head_faces = _orient_outward(head_v, head_faces, n_skin)

    side = np.concatenate(side_list + pocket_side)
    part = np.concatenate([np.zeros(n_skin + len(slit_cols), np.int8), np.full(n_head_v - n_skin - len(slit_cols), PART_MOUTH, np.int8)])
    mouth_depth = np.concatenate([np.zeros(n_skin + len(slit_cols)), np.concatenate(pocket_depth)])

    # eyeballs
    eye_parts = []
    eye_centers = []
    for sign, code in ((1.0, PART_LEFT_EYE), (-1.0, PART_RIGHT_EYE)):
        zs = _skull_front_z(sign * _EYE_X, _EYE_Y)
        ctr = np.array([sign * _EYE_X, _EYE_Y, zs - _EYE_R - 0.0006])
        ev, ef, ed = _uv_sphere(ctr, _EYE_R, eye_rows, eye_cols)
        eye_parts.append((ev, ef, ed, code))
        eye_centers.append(ctr)
    V_list, F_list = [head_v], [head_faces]
    part_list, side_list2, depth_list, dir_list = [part], [side], [mouth_depth], [np.zeros((n_head_v, 3))]
    offset = n_head_v
    eye_ids = []
    for ev, ef, ed, code in eye_parts:
        V_list.append(ev)
        F_list.append(ef + offset)
        part_list.append(np.full(len(ev), code, np.int8))
        side_list2.append(np.ones(len(ev), np.int8))
        depth_list.append(np.zeros(len(ev)))
        dir_list.append(ed)
        eye_ids.append(np.arange(offset, offset + len(ev)))
        offset += len(ev)
    v_template = np.concatenate(V_list, 0)
    faces_all = np.concatenate(F_list, 0)
    part = np.concatenate(part_list)
    side = np.concatenate(side_list2)
    mouth_depth = np.concatenate(depth_list)
    eye_dir = np.concatenate(dir_list, 0)
    V = v_template.shape[0]

    # anchors: eyeball vertices follow their centre in the identity fields (rigid eyeballs)
    anchor = v_template.copy()
    for ids, ctr in zip(eye_ids, eye_centers):
        anchor[ids] = ctr
    nrm_skin = np.zeros((V, 3))
    nrm_skin[:n_skin] = skin_n
    nrm_skin[n_skin:n_head_v] = [0.0, 0.0, 1.0]
    nrm_skin[n_skin : n_skin + len(slit_cols)] = skin_n[idx[r_m, slit_cols]]

    # joints
    j_reg = np.zeros((5, V))
    bottom_ring = idx[-1]
    j_reg[0, bottom_ring] = 1.0 / len(bottom_ring)
    neck_row = int(np.argmin(np.abs(grid[:, np.argmin(np.abs(phi)), 1] - (-0.09))))
    neck_row = max(neck_row, n_head)
    j_reg[1, idx[neck_row]] = 1.0 / C
    hinge = []
    for sx in (1.0, -1.0):
        target = np.array([sx * 0.066, -0.012, -0.012])
        cand = np.flatnonzero(part == PART_SKIN)
        d = np.linalg.norm(v_template[cand] - target, axis=1)
        hinge.append(cand[np.argsort(d)[:3]])
    hinge_ids = np.concatenate(hinge)
    j_reg[2, hinge_ids] = 1.0 / len(hinge_ids)
    for j, ids in zip((3, 4), eye_ids):
        j_reg[j, ids] = 1.0 / len(ids)

    # skinning
    weights = _skinning(v_template, part, side, phi_of=_azimuth(v_template), mouth_y=mouth_y)

    # blendshapes
    shapedirs = np.zeros((V, 3, N_SHAPE_COLUMNS + N_EXPR_COLUMNS))
    ident = _identity_fields(anchor, nrm_skin, part, mouth_y)
    shapedirs[:, :, : ident.shape[2]] = ident
    expr = _expression_fields(v_template, nrm_skin, part, side, mouth_y)
    shapedirs[:, :, N_SHAPE_COLUMNS : N_SHAPE_COLUMNS + expr.shape[2]] = expr

    masks = _masks(v_template, part, side, eye_dir, idx, mouth_y, n_head_v)
    front_col = int(np.argmin(np.abs(phi)))
    left_col = int(np.argmin(np.abs(phi - np.pi / 2)))
    right_col = int(np.argmin(np.abs(phi + np.pi / 2)))
    neck_line = (int(idx[R - 1, left_col]), int(idx[R - 1, right_col]), int(idx[R - 1, front_col]))
    return HeadModel(
        v_template=v_template,
        faces=faces_all,
        shapedirs=shapedirs,
        posedirs=np.zeros((V, 3, 36)),
        j_regressor=j_reg,
        weights=weights,
        part=part,
        side=side,
        eye_dir=eye_dir,
        mouth_depth=mouth_depth,
        masks=masks,
        neck_line=neck_line,
        mouth_y=mouth_y,
        slit_pairs=np.array([[idx[r_m, j], lower_copy[int(j)]] for j in slit_cols], dtype=np.int64),
        grid_shape=(int(R), int(C)),
    )


def _orient_outward(v: np.ndarray, f: np.ndarray, n_skin: int) -> np.ndarray:
    """Make the winding consistent over the head surface and the skin's normals point outward."""
    import trimesh

    mesh = trimesh.Trimesh(v, f, process=False)
    trimesh.repair.fix_winding(mesh)
    f2 = np.asarray(mesh.faces, dtype=np.int64)
    skin_faces = np.all(f2 < n_skin, axis=1)
    tri = v[f2[skin_faces]]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = tri.mean(1) - _C
    if np.sum(np.einsum("ij,ij->i", nrm, out)) < 0:
        f2 = f2[:, ::-1]
    return np.ascontiguousarray(f2)


def _azimuth(p: np.ndarray) -> np.ndarray:
    return np.arctan2(p[:, 0], p[:, 2] - _C[2])


def _skinning(v: np.ndarray, part: np.ndarray, side: np.ndarray, phi_of: np.ndarray, mouth_y: float) -> np.ndarray:
    """(V, 5) weights: eyeballs -> eye joints, lower face -> jaw, the rest -> neck/root."""
    V = v.shape[0]
    w = np.zeros((V, 5))
    y = v[:, 1]
    aphi = np.abs(phi_of)
    a = smoothstep(aphi, np.deg2rad(100.0), np.deg2rad(50.0))
    below_chin = smoothstep(y, -0.112, -0.088)
    jaw = np.zeros(V)
    jaw = np.where(side < 0, a * below_chin, jaw)
    jaw = np.where(side == 0, 0.5 * a * below_chin, jaw)
    cheek = 0.35 * a * smoothstep(aphi, np.deg2rad(14.0), np.deg2rad(30.0)) * gauss(y - mouth_y, 0.015)
    jaw = np.where(side > 0, cheek * (y < mouth_y + 0.04), jaw)
    mouth = part == PART_MOUTH
    jaw[mouth & (side < 0)] = 1.0
    jaw[mouth & (side > 0)] = 0.0
    jaw[mouth & (side == 0)] = 0.5
    root = smoothstep(y, -0.105, -0.15) * (part == PART_SKIN)
    root = np.minimum(root, 1.0 - jaw)
    w[:, 2] = jaw
    w[:, 0] = root
    w[:, 1] = 1.0 - jaw - root
    eyes = (part == PART_LEFT_EYE) | (part == PART_RIGHT_EYE)
    w[eyes] = 0.0
    w[part == PART_LEFT_EYE, 3] = 1.0
    w[part == PART_RIGHT_EYE, 4] = 1.0
    return w


def _regions(p: np.ndarray, mouth_y: float) -> dict[str, np.ndarray]:
    """Soft region weights (N,) used by the blendshapes."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    front = smoothstep(z, 0.0, 0.045)
    return {
        "lips": np.exp(-((x / 0.026) ** 4)) * gauss(y - mouth_y, 0.009) * front,
        "corner": gauss(ax - 0.025, 0.009) * gauss(y - mouth_y, 0.009) * front,
        "cheek": gauss(ax - 0.042, 0.016) * gauss(y - (mouth_y + 0.025), 0.016) * front,
        "cheek_low": gauss(ax - 0.042, 0.018) * gauss(y - (mouth_y + 0.006), 0.018) * front,
        "brow": gauss(y - 0.045, 0.009) * gauss(ax - 0.032, 0.022) * front,
        "brow_inner": gauss(y - 0.043, 0.009) * gauss(ax - 0.016, 0.013) * front,
        "forehead": smoothstep(y, 0.095, 0.05) * smoothstep(y, 0.03, 0.045) * gauss(x, 0.06) * front,
        "nose_side": gauss(ax - 0.012, 0.008) * gauss(y - 0.012, 0.012) * front,
        "chin": gauss(y + 0.078, 0.015) * gauss(x, 0.022) * front,
        "jaw": gauss(y + 0.05, 0.03) * smoothstep(ax, 0.01, 0.05) * smoothstep(z, -0.05, 0.0),
        "lid_left": _eye_gauss(p, 1.0),
        "lid_right": _eye_gauss(p, -1.0),
        "upper_lid": smoothstep(y - _EYE_Y, -0.0045, 0.003),
        "lower_lid": smoothstep(y - _EYE_Y, 0.0, -0.006),
    }


def _identity_fields(anchor: np.ndarray, n: np.ndarray, part: np.ndarray, mouth_y: float) -> np.ndarray:
    """(V, 3, N_IDENTITY) identity displacements per unit coefficient, evaluated at anchors."""
    x, y, z = anchor[:, 0], anchor[:, 1], anchor[:, 2]
    r = _regions(anchor, mouth_y)
    V = anchor.shape[0]
    out = np.zeros((V, 3, N_IDENTITY))
    above_neck = smoothstep(y, -0.11, -0.07)
    out[:, 0, 0] = 0.005 * x / _AX * above_neck
    out[:, 2, 1] = -0.007 * smoothstep(z, 0.0, -0.09) * smoothstep(y, -0.09, -0.04)
    out[:, 1, 2] = -0.006 * smoothstep(y, 0.02, -0.085) * smoothstep(y, -0.13, -0.095)
    out[:, :, 3] = (0.35 * _nose_height(anchor))[:, None] * n
    out[:, 0, 4] = 0.005 * np.sign(x) * r["jaw"]
    out[:, :, 5] = (0.004 * r["cheek_low"])[:, None] * n
    out[:, 2, 6] = 0.005 * r["chin"]
    out[:, 1, 6] = -0.002 * r["chin"]
    out[:, :, 7] = (0.0015 * r["lips"])[:, None] * n
    eyes = (part == PART_LEFT_EYE) | (part == PART_RIGHT_EYE)
    out[eyes, :, 3] = 0.0
    out[eyes, :, 5] = 0.0
    out[eyes, :, 7] = 0.0
    return out


def _expression_fields(v: np.ndarray, n: np.ndarray, part: np.ndarray, side: np.ndarray, mouth_y: float) -> np.ndarray:
    """(V, 3, N_EXPRESSION) expression displacements per unit coefficient (eyeballs excluded)."""
    r = _regions(v, mouth_y)
    x = v[:, 0]
    sx = np.sign(x)
    up = (side > 0).astype(float) + 0.5 * (side == 0)
    down = (side < 0).astype(float) + 0.5 * (side == 0)
    mouth = part == PART_MOUTH
    lips = r["lips"] * ~mouth
    V = v.shape[0]
    E = np.zeros((V, 3, N_EXPRESSION))
    # 0 lips part
    E[:, 1, 0] = 0.0022 * lips * up - 0.003 * lips * down
    E[:, 2, 0] = -0.001 * lips
    # 1 smile
    E[:, 0, 1] = 0.004 * sx * r["corner"]
    E[:, 1, 1] = 0.0055 * r["corner"] + 0.003 * r["cheek"]
    E[:, 2, 1] = -0.003 * r["corner"]
    E[:, :, 1] += (0.0015 * r["cheek"])[:, None] * n
    lids = r["lid_left"] + r["lid_right"]
    E[:, 1, 1] += 0.0015 * lids * r["lower_lid"]
    # 2 pucker
    E[:, 2, 2] = 0.006 * lips
    E[:, 0, 2] = -0.3 * x * lips - 0.003 * sx * r["corner"]
    # 3 lip press
    E[:, 2, 3] = -0.002 * lips
    E[:, 1, 3] = -0.0015 * lips * up + 0.0015 * lips * down
    # 4 brow raise
    E[:, 1, 4] = 0.006 * r["brow"] + 0.005 * r["forehead"] * (1 - r["brow"]) + 0.0015 * lids * r["upper_lid"]
    # 5 brow furrow
    E[:, 1, 5] = -0.003 * r["brow_inner"]
    E[:, 0, 5] = -0.003 * sx * r["brow_inner"]
    E[:, :, 5] += (0.0015 * r["brow_inner"])[:, None] * n
    # 6/10/11 blinks: the lid skin fills the socket over the eyeball and slides down
    for col, which in ((6, ("lid_left", "lid_right")), (10, ("lid_left",)), (11, ("lid_right",))):
        g = sum(r[k] for k in which)
        E[:, :, col] = (1.5 * _SOCKET_DEPTH * g)[:, None] * n
        E[:, 1, col] += -0.003 * g * r["upper_lid"] + 0.001 * g * r["lower_lid"]
    # 7 cheek puff
    E[:, :, 7] = (0.007 * r["cheek_low"] * ~mouth)[:, None] * n
    # 8 nose wrinkle
    E[:, 1, 8] = 0.0025 * r["nose_side"] + 0.0015 * lips * up - 0.002 * r["brow_inner"]
    # 9 mouth corners down
    E[:, 1, 9] = -0.005 * r["corner"] - 0.0015 * lips * down
    # 12 mouth stretch
    E[:, 0, 12] = 0.005 * sx * r["corner"]
    E[:, 2, 12] = -0.001 * lips
    E[mouth] *= 0.5
    eyes = (part == PART_LEFT_EYE) | (part == PART_RIGHT_EYE)
    E[eyes] = 0.0
    return E


def _masks(v: np.ndarray, part: np.ndarray, side: np.ndarray, eye_dir: np.ndarray, idx: np.ndarray, mouth_y: float, n_head_v: int) -> dict[str, np.ndarray]:
    """FLAME_masks.pkl-style regions (name -> sorted int64 vertex ids)."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    skin = part == PART_SKIN
    phi = _azimuth(v)
    hair = hair_weight(v) > 0.5
    front = z > 0.01
    neck = skin & (((y < -0.088) & (np.abs(phi) < np.pi / 2)) | (y < -0.075) & ~hair)
    face = skin & front & ~hair & ~neck & (np.abs(x) < 0.062)
    eye_reg = {}
    for name, sgn in (("left_eye_region", 1.0), ("right_eye_region", -1.0)):
        d = np.hypot((x - sgn * _EYE_X) / 0.022, (y - _EYE_Y) / 0.014)
        eye_reg[name] = skin & front & (d < 1.0)
    lips = skin & (np.abs(x) < 0.027) & (np.abs(y - mouth_y) < 0.0105 * np.sqrt(np.clip(1 - (x / 0.028) ** 2, 0, 1))) & front
    nose = skin & (_nose_height(v) > 0.003) & (y > mouth_y + 0.008)
    forehead = face & (y > 0.05)
    ears = {}
    for name, sgn in (("left_ear", 1.0), ("right_ear", -1.0)):
        w = gauss(y - 0.012, 0.021) * gauss(z + 0.014, 0.0105) * smoothstep(np.abs(x), 0.05, 0.072)
        ears[name] = skin & (sgn * x > 0) & (w > 0.25)
    boundary = np.zeros(v.shape[0], bool)
    boundary[idx[-1]] = True
    iris = (eye_dir[:, 2] > np.cos(0.5)) & (part != PART_SKIN)
    ids = lambda m: np.flatnonzero(m).astype(np.int64)  # noqa: E731
    return {
        "face": ids(face),
        "scalp": ids(skin & hair),
        "neck": ids(neck),
        "boundary": ids(boundary),
        "forehead": ids(forehead),
        "eye_region": ids(eye_reg["left_eye_region"] | eye_reg["right_eye_region"]),
        "left_eye_region": ids(eye_reg["left_eye_region"]),
        "right_eye_region": ids(eye_reg["right_eye_region"]),
        "nose": ids(nose),
        "lips": ids(lips),
        "left_eyeball": ids(part == PART_LEFT_EYE),
        "right_eyeball": ids(part == PART_RIGHT_EYE),
        "left_iris": ids(iris & (part == PART_LEFT_EYE)),
        "right_iris": ids(iris & (part == PART_RIGHT_EYE)),
        "left_ear": ids(ears["left_ear"]),
        "right_ear": ids(ears["right_ear"]),
        "mouth_interior": ids(part == PART_MOUTH),
    }


def hair_weight(p: np.ndarray) -> np.ndarray:
    """Soft scalp-hair weight (N,) in [0, 1] from template positions (hairline around the head)."""
    phi = _azimuth(p)
    hairline = 0.02125 + 0.0675 * np.cos(phi) - 0.01375 * np.cos(2 * phi)
    return smoothstep(p[:, 1] - hairline, -0.002, 0.008) * (p[:, 1] > -0.1)
