"""Topology helpers for the fit: the neck opening, vertex rings, the scalp region, faces across an edge."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from ..geometry.topology import boundary_edges, edges


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Vertex loops of the open boundaries (edges used by one face), largest first."""
    border = boundary_edges(faces)
    adj: dict[int, list[int]] = defaultdict(list)
    for a, b in border:
        adj[int(a)].append(int(b))
        adj[int(b)].append(int(a))
    seen: set[int] = set()
    loops = []
    for start in adj:
        if start in seen:
            continue
        comp, todo = [], [start]
        while todo:
            v = todo.pop()
            if v in seen:
                continue
            seen.add(v)
            comp.append(v)
            todo.extend(adj[v])
        loops.append(np.array(sorted(comp), np.int64))
    loops.sort(key=lambda a: -len(a))
    return loops


def ring(faces: np.ndarray, seeds: np.ndarray, n_vertices: int, rings: int) -> np.ndarray:
    """Vertices within ``rings`` edges of ``seeds`` (bool (V,))."""
    e = edges(faces)
    sel = np.zeros(n_vertices, bool)
    sel[seeds] = True
    for _ in range(rings):
        grow = sel.copy()
        grow[e[sel[e[:, 0]], 1]] = True
        grow[e[sel[e[:, 1]], 0]] = True
        sel = grow
    return sel


def neck_line_vertices(vertices: np.ndarray, faces: np.ndarray, flame_topology: bool = False) -> tuple[int, int, int]:
    """(left, right, front-bottom) vertex ids of the neck opening for VHAP's neck-line rule.

    The neck opening is the largest boundary loop of the mesh; left and right are its extreme
    vertices along x, front its vertex furthest along +z (the face's side). ``flame_topology``: the
    model has FLAME's own 5023-vertex topology, whose published points (3193, 3296, 3285) are used.
    """
    if flame_topology:
        return 3193, 3296, 3285
    loops = boundary_loops(faces)
    if not loops:
        lo = int(np.argmin(vertices[:, 1]))
        return lo, lo, lo
    loop = loops[0]
    x = vertices[loop, 0]
    z = vertices[loop, 2]
    return int(loop[np.argmax(x)]), int(loop[np.argmin(x)]), int(loop[np.argmax(z)])


def hair_region(groups: dict[str, np.ndarray], n_vertices: int) -> np.ndarray | None:
    """Vertex ids of the hair region from FLAME region masks: ``scalp`` minus ``face`` and ``neck``
    (formats.md §5), or None when the masks have no scalp."""
    scalp = groups.get("scalp")
    if scalp is None or len(scalp) == 0:
        return None
    sel = np.zeros(n_vertices, bool)
    sel[np.asarray(scalp, np.int64)] = True
    for k in ("face", "neck"):
        if k in groups:
            sel[np.asarray(groups[k], np.int64)] = False
    ids = np.flatnonzero(sel)
    return ids if ids.size else None


def edge_faces(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges shared by exactly two faces: (E, 2) vertex pairs and (E, 2) the two face ids."""
    F = faces.shape[0]
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    f = np.tile(np.arange(F), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, f = key[order], f[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    first = np.flatnonzero(same)
    # keep pairs that occur exactly twice
    single = np.ones(len(first), bool)
    if len(first) > 1:
        single &= ~np.isin(first, first + 1) & ~np.isin(first + 1, first)
    first = first[single]
    return key[first], np.stack([f[first], f[first + 1]], 1)
