"""Teeth extension of the 5023-vertex FLAME mesh (docs/formats.md §4): V 5023 -> 5143.

The 120 vertices follow the GaussianAvatars/VHAP order exactly, so per-vertex data indexed in that
layout (e.g. VHAP's 5143-row ``static_offset``) lines up. The faces are this project's own table
``sage-teeth-v1``: for each jaw three strips of 14 quads (front, back and biting surface), 168
triangles in all. With the lip rings running towards +x, front faces face +z, back faces −z, the
upper biting surface −y and the lower +y.
"""

from __future__ import annotations

import numpy as np

from .model_data import FlameModelData

FLAME_N_VERTICES = 5023
N_TEETH_VERTICES = 120
TEETH_FACE_TABLE = "sage-teeth-v1"

LIP_RING_UPPER = np.array([1713, 1715, 1716, 1735, 1696, 1694, 1657, 3543, 2774, 2811, 2813, 2850, 2833, 2832, 2830])
LIP_RING_LOWER = np.array([1576, 1577, 1773, 1774, 1795, 1802, 1865, 3503, 2948, 2905, 2898, 2881, 2880, 2713, 2712])

_RING = 15
# (group, joint) in append order; each group holds 15 vertices.
_GROUPS = (
    ("upper_root", 1),
    ("lower_root", 2),
    ("upper_edge", 1),
    ("lower_edge", 2),
    ("upper_root_back", 1),
    ("upper_edge_back", 1),
    ("lower_root_back", 2),
    ("lower_edge_back", 2),
)


def has_teeth(data: FlameModelData) -> bool:
    """Whether the model already carries the teeth groups."""
    return "teeth_upper" in data.vertex_groups and "teeth_lower" in data.vertex_groups


def teeth_vertices(v_template: np.ndarray) -> np.ndarray:
    """The 120 teeth vertices (120, 3) built from a (5023, 3) template, in the §4 append order."""
    U = v_template[LIP_RING_UPPER]
    L = v_template[LIP_RING_LOWER]
    d = float(np.linalg.norm(U - L, axis=1).mean())
    e_y = np.array([0.0, d, 0.0])
    e_z = np.array([0.0, 0.0, d])
    mid = (U + L) / 2.0
    mid[:, 1] = mid[:, 1].mean()
    mid[:, 2] -= 1.5 * d
    rows = {"upper_edge": mid + 0.1 * e_y, "lower_edge": mid - 0.1 * e_y - 0.4 * e_z}
    rows["upper_root"] = rows["upper_edge"] + 2.0 * e_y
    rows["lower_root"] = rows["lower_edge"] - 2.0 * e_y
    for name in ("upper_root", "upper_edge", "lower_root", "lower_edge"):
        rows[name + "_back"] = rows[name] - e_z
    return np.concatenate([rows[name] for name, _ in _GROUPS], axis=0)


def _strip(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Triangles (2·14, 3) of the quads (a_i, b_i, b_i+1, a_i+1) between two 15-vertex rows."""
    i = np.arange(_RING - 1)
    t1 = np.stack([a[i], b[i], b[i + 1]], axis=1)
    t2 = np.stack([a[i], b[i + 1], a[i + 1]], axis=1)
    return np.stack([t1, t2], axis=1).reshape(-1, 3)


def teeth_faces(offset: int = FLAME_N_VERTICES) -> np.ndarray:
    """The sage-teeth-v1 faces (168, 3) int64, for teeth vertices starting at ``offset``."""
    row = {name: offset + _RING * k + np.arange(_RING) for k, (name, _) in enumerate(_GROUPS)}
    upper = [
        _strip(row["upper_root"], row["upper_edge"]),
        _strip(row["upper_edge_back"], row["upper_root_back"]),
        _strip(row["upper_edge"], row["upper_edge_back"]),
    ]
    lower = [
        _strip(row["lower_edge"], row["lower_root"]),
        _strip(row["lower_root_back"], row["lower_edge_back"]),
        _strip(row["lower_edge_back"], row["lower_edge"]),
    ]
    return np.concatenate(upper + lower, axis=0).astype(np.int64)


def add_teeth(data: FlameModelData) -> FlameModelData:
    """Append the 120 teeth vertices and 168 faces to a 5023-vertex FLAME model.

    Identity shapedirs of every group are the mean of the two lip rings' rows; expression dirs,
    posedirs and J_regressor columns are 0; skinning is one-hot (upper teeth -> joint 1 neck, lower
    -> joint 2 jaw). Records groups "teeth_upper"/"teeth_lower" and extends ``face_table``.
    Raises ValueError if the model is not the plain 5023-vertex topology or already has teeth.
    """
    if data.n_vertices != FLAME_N_VERTICES:
        raise ValueError(f"teeth need a {FLAME_N_VERTICES}-vertex FLAME model, got {data.n_vertices}")
    if has_teeth(data):
        raise ValueError("model already has teeth")
    if data.n_joints < 3:
        raise ValueError("teeth need the neck (1) and jaw (2) joints")
    V, J = data.n_vertices, data.n_joints
    verts = teeth_vertices(data.v_template)
    n_new = verts.shape[0]
    sd_ring = (data.shapedirs[LIP_RING_UPPER] + data.shapedirs[LIP_RING_LOWER]) / 2.0  # (15, 3, S)
    shapedirs = np.concatenate([data.shapedirs] + [sd_ring] * len(_GROUPS), axis=0)
    exprdirs = np.concatenate([data.exprdirs, np.zeros((n_new, 3, data.n_expr))], axis=0)
    posedirs = np.concatenate([data.posedirs, np.zeros((n_new, 3, data.posedirs.shape[2]))], axis=0)
    j_reg = np.concatenate([data.j_regressor, np.zeros((J, n_new))], axis=1)
    joints = np.repeat([j for _, j in _GROUPS], _RING)
    weights = np.concatenate([data.lbs_weights, np.eye(J)[joints]], axis=0)
    new_ids = V + np.arange(n_new)
    groups = dict(data.vertex_groups)
    groups["teeth_upper"] = new_ids[joints == 1].astype(np.int64)
    groups["teeth_lower"] = new_ids[joints == 2].astype(np.int64)
    return FlameModelData(
        v_template=np.concatenate([data.v_template, verts], axis=0),
        faces=np.concatenate([data.faces, teeth_faces(V)], axis=0),
        shapedirs=shapedirs,
        exprdirs=exprdirs,
        posedirs=posedirs,
        j_regressor=j_reg,
        lbs_weights=weights,
        parents=data.parents.copy(),
        n_base_vertices=data.n_base_vertices,
        face_table=f"{data.face_table}+{TEETH_FACE_TABLE}",
        version=data.version,
        vertex_groups=groups,
    )
