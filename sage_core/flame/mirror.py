"""Left/right mirror correspondence of a mesh template (reflection x → −x).

Every vertex i gets the partner m(i) whose position is the reflection S·v_i, S = diag(−1, 1, 1),
within a tolerance relative to the mesh size (the bounding-box diagonal). Coincident vertices (a
lip slit, the rim shared by the upper and lower mouth cavity) are told apart by their one-ring:
among the vertices close enough to S·v_i the one whose neighbour centroid is nearest to the
reflected neighbour centroid of i wins. The map must be an involution (m(m(i)) = i); vertices on the
symmetry plane map to themselves.

Faces map through the vertex map: the partner of face (a, b, c) is the face holding the vertex set
{m(a), m(b), m(c)}; ``face_perm`` records where each corner went, so a point with barycentrics
(β0, β1, β2) on face f is the mirror of the point with barycentric β_k at corner ``face_perm[f, k]``
of face ``face[f]``. A mesh can be symmetric in its vertices while its triangulation is not (quads
split along the same diagonal on both sides, as in the synthetic head): the face map is then None
with its reason in ``face_reason``, and the vertex map is still valid (a mirrored mesh
``S·v[m(i)]`` describes the reflected surface, only triangulated differently).

When the vertices are not symmetric (a vertex without a partner, a map that is not an involution)
:func:`mirror_correspondence` returns ``(None, reason)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from .model_data import FlameModelData

DEFAULT_REL_TOL = 1e-3
"""Default partner tolerance: 0.1 % of the bounding-box diagonal (≈ 0.3 mm on a FLAME head)."""

_S = np.array([-1.0, 1.0, 1.0])
_COINCIDENT = 1e-2


@dataclass
class MirrorMap:
    """A mesh's mirror correspondence.

    Attributes:
        vertex: (V,) int64 partner vertex m(i).
        face: (F,) int64 partner face, or None when the triangulation is not mirror-symmetric.
        face_perm: (F, 3) int64 with ``faces[face[f], face_perm[f, k]] == vertex[faces[f, k]]``, or None.
        residual: max_i |S·v_i − v_m(i)| relative to the bounding-box diagonal.
        n_fixed: vertices mapped to themselves (on the symmetry plane).
        face_reason: why ``face`` is None ("" when it exists).
    """

    vertex: np.ndarray
    face: np.ndarray | None
    face_perm: np.ndarray | None
    residual: float
    n_fixed: int
    face_reason: str = ""


def _neighbours(n_vertices: int, faces: np.ndarray) -> list[set[int]]:
    """Vertex adjacency along face edges."""
    nb: list[set[int]] = [set() for _ in range(n_vertices)]
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 0)
    for a, b in np.unique(np.sort(e, axis=1), axis=0).tolist():
        nb[a].add(b)
        nb[b].add(a)
    return nb


def _vertex_partners(vertices: np.ndarray, faces: np.ndarray, tol: float) -> tuple[np.ndarray | None, str, float]:
    """Partner per vertex, or (None, reason); also the largest position residual (absolute).

    Vertices with a single candidate within ``tol`` of their reflection are matched directly; the
    others (coincident vertices) take the candidate adjacent to the most partners of their own
    neighbours, resolved over a few passes (ties: the vertex itself, then the lowest index).
    """
    V = vertices.shape[0]
    refl = vertices * _S
    tree = cKDTree(vertices)
    d_near, i_near = tree.query(refl)
    worst = int(np.argmax(d_near))
    if d_near[worst] > tol:
        n_bad = int((d_near > tol).sum())
        return None, (f"{n_bad} of {V} vertices have no mirror partner within {tol:.3g} (vertex {worst} at "
                      f"{np.round(vertices[worst], 5).tolist()}: nearest reflection {d_near[worst]:.3g} away)"), float(d_near.max())
    partner = i_near.astype(np.int64)
    # near-coincident candidates (within ``_COINCIDENT`` × tol of the nearest) make a vertex ambiguous
    eps = _COINCIDENT * tol
    d2, _ = tree.query(refl, k=2)
    amb = np.nonzero(d2[:, 1] <= d2[:, 0] + eps)[0] if V > 1 else np.zeros(0, dtype=np.int64)
    if amb.size:
        nb = _neighbours(V, faces)
        known = np.ones(V, dtype=bool)
        known[amb] = False
        cands = {int(i): np.asarray(c, dtype=np.int64)
                 for i, c in zip(amb, tree.query_ball_point(refl[amb], r=d_near[amb] + eps))}
        for _ in range(8):
            pending = [i for i in cands if not known[i]]
            if not pending:
                break
            decided: dict[int, int] = {}
            for i in pending:
                mapped = {int(partner[n]) for n in nb[i] if known[n]}
                score = np.array([len(mapped & nb[int(c)]) for c in cands[i]])
                if score.max() == 0:
                    continue
                best = cands[i][score == score.max()]
                decided[i] = i if i in best else int(best.min())
            if not decided:
                break
            for i, c in decided.items():
                partner[i] = c
                known[i] = True
        for i in cands:
            if not known[i]:
                partner[i] = i if i in cands[i] else int(i_near[i])
    res = float(np.linalg.norm(vertices[partner] - refl, axis=1).max())
    back = partner[partner]
    bad = np.nonzero(back != np.arange(V))[0]
    if bad.size:
        i = int(bad[0])
        return None, (f"the mirror map is not an involution for {bad.size} vertices (vertex {i} -> {int(partner[i])} "
                      f"-> {int(back[i])})"), res
    return partner, "", res


def _face_partners(faces: np.ndarray, vmap: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    F = faces.shape[0]
    key = np.sort(faces, axis=1)
    lookup: dict[tuple[int, int, int], int] = {}
    for f, k in enumerate(map(tuple, key.tolist())):
        if k in lookup:
            return None, None, f"faces {lookup[k]} and {f} use the same three vertices"
        lookup[k] = f
    mapped = vmap[faces]  # (F, 3)
    partner = np.empty(F, dtype=np.int64)
    for f, k in enumerate(map(tuple, np.sort(mapped, axis=1).tolist())):
        g = lookup.get(k)
        if g is None:
            return None, None, f"the mirror of face {f} {faces[f].tolist()} (vertices {mapped[f].tolist()}) is not a face"
        partner[f] = g
    target = faces[partner]  # (F, 3)
    perm = np.argmax(target[:, None, :] == mapped[:, :, None], axis=2).astype(np.int64)
    if not np.all(np.take_along_axis(target, perm, 1) == mapped):
        return None, None, "a face and its mirror do not share corners"
    if not np.all(partner[partner] == np.arange(F)):
        return None, None, "the face mirror map is not an involution"
    return partner, perm, ""


def mirror_correspondence(
    vertices: np.ndarray, faces: np.ndarray, rel_tol: float = DEFAULT_REL_TOL
) -> tuple[MirrorMap | None, str]:
    """Mirror correspondence of a mesh under x → −x.

    vertices: (V, 3) template (symmetry plane x = 0, e.g. FLAME's ``v_template`` with its appended
    teeth and mouth interior); faces: (F, 3); rel_tol: partner tolerance relative to the bounding-box
    diagonal. Returns ``(MirrorMap, "")``, or ``(None, reason)`` when the vertices are not symmetric
    (the face map may still be absent, see :class:`MirrorMap`).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        return None, f"vertices must be a non-empty (V, 3) array, got shape {v.shape}"
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= v.shape[0])):
        return None, "faces must be (F, 3) vertex ids of the mesh"
    size = float(np.linalg.norm(v.max(0) - v.min(0)))
    if size <= 0 or not np.isfinite(size):
        return None, "the mesh has no extent"
    vmap, reason, res = _vertex_partners(v, f, rel_tol * size)
    if vmap is None:
        return None, reason
    fmap, perm, face_reason = _face_partners(f, vmap)
    n_fixed = int((vmap == np.arange(v.shape[0])).sum())
    return MirrorMap(vmap, fmap, perm, res / size, n_fixed, face_reason), ""


def model_mirror(model_data: FlameModelData, rel_tol: float = DEFAULT_REL_TOL) -> tuple[MirrorMap | None, str]:
    """Mirror correspondence of a FLAME model's template (:class:`sage_core.flame.FlameModelData`,
    appended teeth and mouth interior included)."""
    return mirror_correspondence(np.asarray(model_data.v_template), np.asarray(model_data.faces), rel_tol)
