"""Mouth interior: a small cavity mesh behind the lips, rigged to the neck (upper) and jaw (lower).

The parts are appended at the END of the vertex and face arrays, so existing indices (and VHAP's
``static_offset`` rows) are unchanged. Geometry, in the canonical template (FLAME axes: x lateral,
y up, z forward, the face looking towards +z):

- the lip slit: the lips region is split by jaw skinning weight into the upper lip (low weight)
  and the lower lip (high weight); the slit height is midway between the upper lip's lowest and
  the lower lip's highest vertex; the lip width ``w`` is the lips' extent along x;
- the cavity: half an ellipsoid behind the front plane ``z_f = min_z(lips) − 0.02·w``, centred
  on the slit, radii 0.45·w (x), 0.8·w (depth) and 0.3·w (height) per half, open towards the lips.
  The upper half (palate, ``mouth_upper``) is skinned one-hot to joint 1 (neck), the lower half
  (floor and tongue bed, ``mouth_lower``) to joint 2 (jaw). Its faces face into the cavity.
- the teeth (only if the model has none yet): two arcs just inside the cavity, a band above the
  slit (``teeth_upper``, joint 1) and one below it (``teeth_lower``, joint 2), facing forwards. The
  arcs follow the cavity's wall, so their middle is their deepest point (about half a lip width
  behind the front plane), where a jaw's dental arch has its incisors in front; an arch bulging
  forwards was measured and not adopted: its teeth surfels show through the lips' seam at rest and
  take the lips' colour, and pale teeth do not land on the captures' two-pixel rows (docs/results.md,
  "The rig's teeth arcs bulge the wrong way" and "Where the open mouth's surfels come from");
- the tongue (``tongue=True``, with the cavity): a low dome (radii 0.3·w lateral and deep, 0.08·w
  high) on the cavity floor, its centre 0.42·w behind the front plane and 0.14·w below the slit,
  skinned one-hot to the jaw (``mouth_tongue``, so a part of the ``mouth_interior`` region).

Identity blendshapes of each new vertex are copied from the nearest original vertex (so the part
follows the subject's shape); expression blendshapes, pose correctives and J_regressor columns
are zero. The face table gains ``+sage-mouth-v1`` (cavity only) or ``+sage-mouth-teeth-v1``, then
``+sage-tongue-v1`` with the tongue. :func:`mouth_frame` gives the frame (origin and ``w``) of any
mesh with the same lips, which the mouth-interior prior (:mod:`sage_core.avatar.mouth_prior`) uses
as its subject-independent coordinates.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.spatial import cKDTree

from .model_data import FlameModelData
from .regions import Regions
from .teeth import has_teeth

NECK_JOINT = 1
JAW_JOINT = 2
_N_THETA = 13  # columns around the cavity from one mouth corner to the other
_N_RINGS = 3  # rings per half before the pole
_N_ARC = 11  # columns of a teeth arc
TONGUE_RADII = (0.3, 0.08, 0.3)
"""Tongue dome radii (lateral, height, depth) in lip widths."""
TONGUE_CENTRE = (0.0, -0.14, 0.42)
"""Tongue dome centre (lateral, height, backward) in lip widths from the mouth frame's origin."""


def has_mouth_interior(data: FlameModelData) -> bool:
    """Whether the model already carries the mouth cavity groups."""
    return "mouth_upper" in data.vertex_groups and "mouth_lower" in data.vertex_groups


def _dome(sign: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit half-dome: vertices (R·T + 1, 3) in (lateral, vertical, backward) units and faces.

    sign = +1 for the upper half (vertical ≥ 0), −1 for the lower half. Faces are oriented so that
    their normals point towards the dome's centre (into the cavity).
    """
    theta = np.linspace(0.0, np.pi, _N_THETA)
    phi = np.arange(_N_RINGS) / _N_RINGS * (np.pi / 2)
    th, ph = np.meshgrid(theta, phi)  # (R, T)
    pts = np.stack([np.cos(th) * np.cos(ph), sign * np.sin(ph), np.sin(th) * np.cos(ph)], -1).reshape(-1, 3)
    pts = np.concatenate([pts, [[0.0, sign, 0.0]]], 0)
    idx = np.arange(_N_RINGS * _N_THETA).reshape(_N_RINGS, _N_THETA)
    pole = _N_RINGS * _N_THETA
    faces = []
    for r in range(_N_RINGS - 1):
        for i in range(_N_THETA - 1):
            a, b, c, d = idx[r, i], idx[r, i + 1], idx[r + 1, i + 1], idx[r + 1, i]
            faces += [[a, b, c], [a, c, d]]
    for i in range(_N_THETA - 1):
        faces.append([idx[-1, i], idx[-1, i + 1], pole])
    faces = np.array(faces, dtype=np.int64)
    return pts, _orient(pts, faces, inward_to=np.zeros(3))


def _cap() -> tuple[np.ndarray, np.ndarray]:
    """Unit upper hemisphere (the tongue): vertices (R·T + 1, 3) (x, y ≥ 0, z) and faces facing out."""
    # starting on the midline (θ = π/2) makes the columns mirror-symmetric (x → −x maps θ to π − θ),
    # so the mesh keeps its left/right vertex correspondence (sage_core.flame.mirror)
    theta = np.pi / 2 + np.linspace(0.0, 2 * np.pi, _N_THETA, endpoint=False)
    phi = np.arange(_N_RINGS) / _N_RINGS * (np.pi / 2)
    th, ph = np.meshgrid(theta, phi)
    pts = np.stack([np.cos(th) * np.cos(ph), np.sin(ph), np.sin(th) * np.cos(ph)], -1).reshape(-1, 3)
    pts = np.concatenate([pts, [[0.0, 1.0, 0.0]]], 0)
    idx = np.arange(_N_RINGS * _N_THETA).reshape(_N_RINGS, _N_THETA)
    pole = _N_RINGS * _N_THETA
    faces = []
    for r in range(_N_RINGS - 1):
        for i in range(_N_THETA):
            a, b = idx[r, i], idx[r, (i + 1) % _N_THETA]
            c, d = idx[r + 1, (i + 1) % _N_THETA], idx[r + 1, i]
            faces += [[a, b, c], [a, c, d]]
    for i in range(_N_THETA):
        faces.append([idx[-1, i], idx[-1, (i + 1) % _N_THETA], pole])
    faces = np.array(faces, dtype=np.int64)
    return pts, _orient(pts, faces, inward_to=np.array([0.0, -10.0, 0.0]))[:, [0, 2, 1]]


def _orient(pts: np.ndarray, faces: np.ndarray, inward_to: np.ndarray) -> np.ndarray:
    """Flip faces whose normal points away from ``inward_to``."""
    v0, v1, v2 = pts[faces[:, 0]], pts[faces[:, 1]], pts[faces[:, 2]]
    n = np.cross(v1 - v0, v2 - v0)
    centroid = (v0 + v1 + v2) / 3
    flip = (n * (inward_to - centroid)).sum(1) < 0
    out = faces.copy()
    out[flip] = out[flip][:, [0, 2, 1]]
    return out


def _arc(y0: float, y1: float) -> tuple[np.ndarray, np.ndarray]:
    """A vertical band on a unit arc: vertices (2·N, 3) (rows y0 and y1), faces facing −backward."""
    theta = np.linspace(0.15 * np.pi, 0.85 * np.pi, _N_ARC)
    row = np.stack([np.cos(theta), np.zeros_like(theta), np.sin(theta)], -1)
    pts = np.concatenate([row + [0.0, y0, 0.0], row + [0.0, y1, 0.0]], 0)
    faces = []
    for i in range(_N_ARC - 1):
        a, b, c, d = i, i + 1, _N_ARC + i + 1, _N_ARC + i
        faces += [[a, b, c], [a, c, d]]
    faces = np.array(faces, dtype=np.int64)
    # orient towards the front (backward coordinate smaller): the point far in front of the arc
    return pts, _orient(pts, faces, inward_to=np.array([0.0, 0.5 * (y0 + y1), -10.0]))


def _lips(regions_or_masks: Regions | Mapping[str, np.ndarray], n_base: int) -> np.ndarray:
    if isinstance(regions_or_masks, Regions):
        if not regions_or_masks.has("lips"):
            raise ValueError("the regions have no 'lips' set; the mouth cannot be located")
        ids = regions_or_masks.vertex_ids("lips")
    else:
        if "lips" not in regions_or_masks:
            raise ValueError("the masks have no 'lips' entry; the mouth cannot be located")
        ids = np.asarray(regions_or_masks["lips"], dtype=np.int64)
    ids = np.unique(ids[(ids >= 0) & (ids < n_base)])
    if ids.size < 4:
        raise ValueError(f"the lips region has {ids.size} vertices; need at least 4")
    return ids


def mouth_frame(v: np.ndarray, lips: np.ndarray, lbs_weights: np.ndarray) -> tuple[np.ndarray, float]:
    """The mouth's frame from a mesh: (origin (3,) = (x_c, y_slit, z_f), lip width w).

    v: (V, 3) vertices (template or canonical); lips: lip vertex ids; lbs_weights: (V, J) skinning
    weights (joint 2 tells the lower lip from the upper). See the module doc for the definitions.
    Raises ValueError if the lips cannot be split or have no width.
    """
    jaw_w = lbs_weights[lips, JAW_JOINT]
    lo, hi = float(jaw_w.min()), float(jaw_w.max())
    if hi - lo < 1e-6:
        raise ValueError("the lips have uniform jaw skinning weights; upper and lower lip cannot be told apart")
    thr = 0.5 if lo < 0.5 <= hi else 0.5 * (lo + hi)
    upper_lip, lower_lip = lips[jaw_w < thr], lips[jaw_w >= thr]
    lp = v[lips]
    width = float(lp[:, 0].max() - lp[:, 0].min())
    if width <= 0:
        raise ValueError("the lips region has zero width")
    y_slit = 0.5 * (float(v[upper_lip, 1].min()) + float(v[lower_lip, 1].max()))
    x_c = 0.5 * float(lp[:, 0].max() + lp[:, 0].min())
    z_f = float(lp[:, 2].min()) - 0.02 * width
    return np.array([x_c, y_slit, z_f]), width


def lip_ids(regions_or_masks: Regions | Mapping[str, np.ndarray], n_base: int) -> np.ndarray:
    """The lip vertex ids (below ``n_base``) of a :class:`Regions` or a mask dict; ValueError if absent."""
    return _lips(regions_or_masks, n_base)


def add_mouth_interior(data: FlameModelData, regions_or_masks: Regions | Mapping[str, np.ndarray],
                       teeth: bool | None = None, cavity: bool = True, tongue: bool = False) -> FlameModelData:
    """Append the mouth cavity (and teeth arcs) rigged to the neck and jaw joints.

    data: a model with joints 1 (neck) and 2 (jaw). regions_or_masks: a :class:`Regions` or a
    mask dict holding ``lips`` (ids below ``n_base_vertices``). teeth: add the teeth arcs; None =
    only when the model has no teeth groups yet. cavity: add the cavity (False: the teeth arcs
    alone, FLAME with teeth as GaussianAvatars rigs it). tongue: with the cavity, also the tongue
    (``mouth_tongue``, rigged to the jaw). Returns a new model; ``data`` is
    unchanged. Raises ValueError if the mouth cannot be located, the model already has a mouth
    interior, or nothing would be added.
    """
    if has_mouth_interior(data):
        raise ValueError("model already has a mouth interior")
    if data.n_joints <= JAW_JOINT:
        raise ValueError("the mouth interior needs the neck (1) and jaw (2) joints")
    if teeth is None:
        teeth = not has_teeth(data)
    elif teeth and has_teeth(data):
        raise ValueError("model already has teeth groups")
    if not cavity and not teeth:
        raise ValueError("neither the cavity nor the teeth would be added")
    n_base = data.n_base_vertices
    v = data.v_template
    origin, width = mouth_frame(v, _lips(regions_or_masks, n_base), data.lbs_weights)

    def place(unit: np.ndarray, rx: float, ry: float, depth: float, dz: float = 0.0) -> np.ndarray:
        return origin + np.stack([unit[:, 0] * rx, unit[:, 1] * ry, -unit[:, 2] * depth + dz], -1)

    parts: list[tuple[str, np.ndarray, np.ndarray, int]] = []
    for name, sign, joint in (("mouth_upper", 1.0, NECK_JOINT), ("mouth_lower", -1.0, JAW_JOINT)) if cavity else ():
        unit, f = _dome(sign)
        # the unit dome's z is the backward coordinate; mirrored z flips the winding, so re-flip
        parts.append((name, place(unit, 0.45 * width, 0.3 * width, 0.8 * width), f[:, [0, 2, 1]], joint))
    if teeth:
        for name, y0, y1, joint, dz in (("teeth_upper", 0.2, 0.02, NECK_JOINT, -0.02 * width),
                                         ("teeth_lower", -0.02, -0.18, JAW_JOINT, -0.05 * width)):
            unit, f = _arc(y0, y1)
            parts.append((name, place(unit, 0.38 * width, width, 0.45 * width, dz), f[:, [0, 2, 1]], joint))
    if cavity and tongue:
        unit, f = _cap()
        # unit z is forward here; place() maps its third coordinate backwards, hence the sign
        pts = place(unit * np.array([1.0, 1.0, -1.0]), TONGUE_RADII[0] * width, TONGUE_RADII[1] * width,
                    TONGUE_RADII[2] * width, -TONGUE_CENTRE[2] * width)
        pts[:, 1] += TONGUE_CENTRE[1] * width
        parts.append(("mouth_tongue", pts, f, JAW_JOINT))

    V, J = data.n_vertices, data.n_joints
    new_v, new_f, joints = [], [], []
    groups = {k: g.copy() for k, g in data.vertex_groups.items()}
    start = V
    for name, pts, f, joint in parts:
        new_v.append(pts)
        new_f.append(f + start)
        joints.append(np.full(len(pts), joint))
        groups[name] = np.arange(start, start + len(pts), dtype=np.int64)
        start += len(pts)
    verts = np.concatenate(new_v, 0)
    n_new = verts.shape[0]
    _, nearest = cKDTree(v[:n_base]).query(verts)
    tag = ("sage-mouth-teeth-v1" if teeth else "sage-mouth-v1") if cavity else "sage-teeth-arcs-v1"
    if cavity and tongue:
        tag += "+sage-tongue-v1"
    return FlameModelData(
        v_template=np.concatenate([v, verts], 0),
        faces=np.concatenate([data.faces] + new_f, 0).astype(np.int64),
        shapedirs=np.concatenate([data.shapedirs, data.shapedirs[nearest]], 0),
        exprdirs=np.concatenate([data.exprdirs, np.zeros((n_new, 3, data.n_expr))], 0),
        posedirs=np.concatenate([data.posedirs, np.zeros((n_new, 3, data.posedirs.shape[2]))], 0),
        j_regressor=np.concatenate([data.j_regressor, np.zeros((J, n_new))], 1),
        lbs_weights=np.concatenate([data.lbs_weights, np.eye(J)[np.concatenate(joints)]], 0),
        parents=data.parents.copy(),
        n_base_vertices=n_base,
        face_table=f"{data.face_table}+{tag}",
        version=data.version,
        vertex_groups=groups,
    )
