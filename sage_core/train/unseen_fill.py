"""What no training view saw: colours and opacities of unseen surfels, continued from the seen ones of their region.

A single camera (SV-HR: head turns; one-shot: one image) never sees the back of the head, and the
attribute networks extrapolate there whatever their inputs suggest: the appearance network's
features of the back are the ones the front trained (a ghost of the face on the back of the head),
or a grey that is the mean of nothing. This module replaces that extrapolation by a continuation of
what was seen, region by region (docs/method.md, "The unseen back and sides"):

1. **Seen, sources, targets.** A surfel is *seen* when its blending weight summed over the training
   views at rest reaches ``seen_min`` pixels (phase 2's visibility); it is a *source* when it reaches
   ``source_min`` pixels (at least ``seen_min``). Targets are the unseen surfels of the region groups
   to fill that no other prior colours (the mouth interior has its own).
2. **Hair sources are hair.** Among the sources of a group with the hair, those whose colour belongs to the skin
   are left out (:func:`skin_like_sources`): a 2-means split of their colours gives the hair centre
   (the one farther from the skin reference, the median colour of the face region's sources), and a
   colour nearer the skin reference than the hair centre is skin, provided the hair centre is
   clearly apart from the skin and not a small minority (an avatar without hair keeps all). A
   skin-coloured surfel of such a group that the views saw only at grazing angles (weighted mean
   |cosine| between its normal and the view direction below ``grazing_cos``) is filled as if unseen:
   in a clip of head turns the back of the head is seen only that way, and at the lower edge of
   hair that stands off the scalp the rays graze the scalp and take the skin below. The skin left
   out is not lost: a target whose nearest seen skin is nearer than 0.7 times its nearest seen hair
   continues the skin instead (the cheeks by the ears, which the region masks put with the scalp).
3. **Propagation over the surface.** Within each group of regions (the hair with the rest of the
   scalp; the face; the neck; ...), the surfels (canonical centres) form a symmetric
   k-nearest-neighbour graph, a discrete version of the surface; the unseen colours solve the graph
   Laplace equation with the sources fixed (:func:`harmonic_fill`): every target colour is a
   weighted mean of source colours, reached only through its own group's surfels, so a geodesic
   continuation that never crosses to another group (hair never takes the face's colours). A
   connected part of a group without any source takes the median colour of the group's sources.
4. **Cover.** Nothing trained the unseen surfels to cover the surface: where the random layout
   leaves gaps between them, the back of the head shows the inside of the face through it. A
   target's opacity is raised to at least the median opacity of its group's sources, and its in-plane
   scales are multiplied by the gain that makes their geometric mean at least 0.75 times the
   distance to its 4th nearest surfel of the group (at most 4x): the Gaussians of neighbours then
   overlap well above half opacity (on the tiny one-shot avatar the inside of the face made 6 % of
   the back views' pixels before, 0.1 % after). The growth near the seen surface is limited by the
   seen surfels that some training view faces only: a surfel seen edge-on at an outline, its
   triangle turned away from every training camera (``facing_away``), holds nothing back, since a
   clip of head turns sees the back of the head only that way and its unseen surfels there would
   otherwise keep the gaps that show the face from behind. A surfel near the mesh's open boundary (the cut
   at the bottom of the neck) grows no further than the disc of three standard deviations reaching
   that boundary (``boundary``), so the cover never stands out of the surface's edge. With
   ``cover_facing_away`` the seen surfels of a covered group that no view faces get the floor and
   the gain too (colours kept): a clip trained them only edge-on. Both are stored in the surfel set
   (:meth:`SurfelSet.set_unseen_floor`).

Inputs are per-surfel tensors (N surfels): canonical centres (N, 3), albedo colours (N, 3), view
weights (N,), region labels (N,) (:data:`sage_core.avatar.init.REGION_NAMES`), opacities (N,),
in-plane scales (N, 2).
Nothing here depends on how the attributes are produced, so the result applies to both attribute
modes (mlp and free) through the surfel set's colour prior and unseen floor.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from ..geometry.topology import distance_to_segments

__all__ = ["FillResult", "fill_unseen", "harmonic_fill", "knn_graph", "skin_like_sources"]


@dataclass
class FillResult:
    """What :func:`fill_unseen` decided.

    Attributes:
        filled: (N,) bool surfels given a colour (the targets that some source reached).
        colors: (N, 3) their colours (rows of other surfels are their input colours).
        opacity: (N,) opacities with the floor applied to the covered surfels (others unchanged); None
            without input opacities.
        scale_gain: (N,) gain (≥ 1) on the in-plane scales of the covered surfels (1 elsewhere).
        covered: (N,) bool surfels given the opacity floor and scale gain: the filled surfels of the
            covered groups, and with ``cover_facing_away`` their seen surfels that no view faces.
        sources: (N,) bool surfels whose colours were propagated.
        skin_like: (N,) bool hair-region sources left out as skin coloured.
        per_group: plain-data counts per group ("4+0": the labels joined; surfels, targets, filled,
            sources, skin-like sources, the opacity floor).
    """

    filled: torch.Tensor
    colors: torch.Tensor
    opacity: torch.Tensor | None
    scale_gain: torch.Tensor
    sources: torch.Tensor
    skin_like: torch.Tensor
    covered: torch.Tensor
    per_group: dict[str, dict[str, float]] = field(default_factory=dict)


def knn_graph(points: np.ndarray, k: int):  # -> scipy.sparse.csr_matrix
    """Symmetric k-nearest-neighbour adjacency of ``points`` (M, 3): (M, M) CSR with weight 1 on
    every edge (i, j) where j is among the k nearest of i or i among those of j."""
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    m = int(points.shape[0])
    if m < 2:
        return sp.csr_matrix((m, m))
    kk = min(int(k), m - 1)
    _, idx = cKDTree(points).query(points, k=kk + 1)
    rows = np.repeat(np.arange(m), kk)
    cols = np.asarray(idx)[:, 1:].reshape(-1)
    a = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(m, m)).tocsr()
    a = a.maximum(a.T)
    a.data[:] = 1.0
    return a


def harmonic_fill(adjacency, values: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve the graph Laplace equation for the unknown nodes with the known ones fixed.

    adjacency: (M, M) symmetric sparse weights; values: (M, C) (rows of unknown nodes ignored);
    known: (M,) bool. Returns ((M, C) values: known rows unchanged, unknown rows the harmonic
    interpolation; (M,) bool nodes whose connected component holds a known node). Unknown nodes of
    a component without any known node keep their input rows.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import spsolve

    known = np.asarray(known, dtype=bool)
    out = np.array(values, dtype=np.float64, copy=True)
    m = known.size
    if m == 0:
        return out, known.copy()
    _, comp = connected_components(adjacency, directed=False)
    comp_known = np.zeros(comp.max() + 1, dtype=bool)
    comp_known[comp[known]] = True
    reached = comp_known[comp]
    solve = reached & ~known
    if not solve.any():
        return out, reached
    A = sp.csr_matrix(adjacency)
    U = np.nonzero(solve)[0]
    K = np.nonzero(known)[0]
    deg = np.asarray(A.sum(1)).ravel()
    A_uu = A[U][:, U]
    A_uk = A[U][:, K]
    L = (sp.diags(deg[U]) - A_uu).tocsc()
    rhs = A_uk @ out[K]
    sol = spsolve(L, rhs)
    out[U] = np.asarray(sol).reshape(U.size, -1)
    return out, reached


def _two_means(x: np.ndarray, iters: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """2-means of rows x (M, C) started at the darkest and the brightest row. Returns ((M,) labels in
    {0, 1}, (2, C) centres)."""
    lum = x.mean(1)
    c = np.stack([x[int(lum.argmin())], x[int(lum.argmax())]]).astype(np.float64)
    lab = np.zeros(len(x), dtype=np.int64)
    for _ in range(iters):
        d = ((x[:, None, :] - c[None]) ** 2).sum(-1)
        new = d.argmin(1)
        for j in range(2):
            if (new == j).any():
                c[j] = x[new == j].mean(0)
        if np.array_equal(new, lab):
            break
        lab = new
    return lab, c


def skin_like_sources(colors: np.ndarray, skin: np.ndarray, separation: float = 0.12, min_share: float = 0.2) -> np.ndarray:
    """(M,) bool: which hair colours ``colors`` (M, 3) are skin, given the skin reference ``skin`` (3,).

    The colours are split in two by 2-means; the centre farther from ``skin`` is the hair's. When it
    is at least ``separation`` (RGB distance) from the skin reference and its cluster holds at least
    ``min_share`` of the colours, a colour is skin-like when it is nearer the skin reference than the
    hair centre. Otherwise (hair coloured like skin, or no hair) nothing is skin-like.
    """
    colors = np.asarray(colors, dtype=np.float64)
    skin = np.asarray(skin, dtype=np.float64)
    out = np.zeros(len(colors), dtype=bool)
    if len(colors) < 4:
        return out
    lab, c = _two_means(colors)
    far = int(np.argmax([np.linalg.norm(c[j] - skin) for j in range(2)]))
    if np.linalg.norm(c[far] - skin) < separation or (lab == far).mean() < min_share:
        return out
    return np.linalg.norm(colors - skin[None], axis=1) < np.linalg.norm(colors - c[far][None], axis=1)


def fill_unseen(
    points: torch.Tensor,
    colors: torch.Tensor,
    weights: torch.Tensor,
    region: torch.Tensor,
    opacity: torch.Tensor | None = None,
    scales: torch.Tensor | None = None,
    facing: torch.Tensor | None = None,
    *,
    groups: Sequence[Sequence[int]],
    hair_regions: Iterable[int] = (),
    skin_regions: Iterable[int] = (),
    cover_regions: Iterable[int] | None = None,
    taken: torch.Tensor | None = None,
    seen_min: float = 0.5,
    source_min: float = 0.5,
    neighbours: int = 8,
    grazing_cos: float = 0.3,
    skin_ratio: float = 0.7,
    cover_neighbours: int = 4,
    cover_ratio: float = 0.75,
    seen_ratio: float = 0.15,
    max_gain: float = 4.0,
    boundary: tuple[np.ndarray, np.ndarray] | None = None,
    boundary_ratio: float = 1.0 / 3.0,
    facing_away: torch.Tensor | None = None,
    cover_facing_away: bool = False,
) -> FillResult:
    """Colours (and opacities) of the unseen surfels of ``groups``, continued from their group's sources.

    points: (N, 3) canonical centres; colors: (N, 3) albedos; weights: (N,) blending weight (pixels)
    over the training views; region: (N,) labels; opacity: (N,) (None: no opacity floor); scales:
    (N, 2) canonical in-plane scales (None: no scale gain); facing: (N,) the view weights times the
    |cosine| between the surfel's normal and the direction to the camera, summed like ``weights``
    (None: no surfel counts as seen only at grazing angles); groups:
    region labels filled together (one graph and one set of sources per group, e.g. the hair with
    the rest of the scalp); hair_regions: a group holding one of these labels leaves out its
    skin-coloured sources (:func:`skin_like_sources`); skin_regions: labels whose sources give the
    skin reference; cover_regions: the opacity floor and scale gain apply to the groups holding one
    of these labels (None: every group); taken: (N,) bool surfels with another prior (never filled, never sources);
    seen_min / source_min: pixels of weight to count as seen / as a source; neighbours: k of the
    group graph; grazing_cos: in a group with hair, a seen skin-like surfel whose weighted mean
    |cosine| (facing / weights) is below this was seen only at grazing angles and is filled like an
    unseen one; skin_ratio: in a group with hair, a target whose nearest seen skin-like surfel is
    nearer than ``skin_ratio`` times its nearest hair source continues the skin instead (0: never);
    cover_neighbours, cover_ratio, seen_ratio, max_gain: the scale gain of a filled
    surfel makes its geometric mean scale at least ``cover_ratio`` times the distance to its
    ``cover_neighbours``-th nearest surfel of the group, but not beyond ``seen_ratio`` times its
    distance to the nearest seen surfel, and at most ``max_gain``; boundary: the segments (two (B, 3)
    arrays of end points, in the space of ``points``) of the mesh's open boundary, which caps that
    geometric mean at ``boundary_ratio`` times the distance to the nearest segment (None or B = 0:
    no cap); facing_away: (N,) bool surfels that no training view faces, left out of the seen
    surfels that limit the growth (None: none); cover_facing_away: in the covered groups, the seen
    surfels of ``facing_away`` get the opacity floor and the scale gain too, their colours kept (a
    head-turn clip sees the back of the head only edge-on, so nothing trained those surfels to
    cover it from behind). Other seen surfels are returned unchanged.
    """
    dev = colors.device
    x = points.detach().double().cpu().numpy()
    col = colors.detach().double().cpu().numpy()
    w = weights.detach().double().cpu().numpy()
    reg = region.detach().long().cpu().numpy()
    n = int(x.shape[0])
    tk = taken.detach().bool().cpu().numpy() if taken is not None else np.zeros(n, dtype=bool)
    away = facing_away.detach().bool().cpu().numpy() if facing_away is not None else np.zeros(n, dtype=bool)
    op = opacity.detach().double().cpu().numpy() if opacity is not None else None
    sg = scales.detach().double().cpu().numpy() if scales is not None else None
    grazing = np.zeros(n, dtype=bool)
    if facing is not None:
        fc = facing.detach().double().cpu().numpy()
        grazing = (w >= float(seen_min)) & (fc < float(grazing_cos) * w)
    gain = np.ones(n)
    seen = w >= float(seen_min)
    src_all = (w >= max(float(source_min), float(seen_min))) & ~tk
    skin_ids = [int(r) for r in skin_regions]
    hair_ids = {int(r) for r in hair_regions}
    cover_ids = None if cover_regions is None else {int(r) for r in cover_regions}
    skin_src = src_all & np.isin(reg, skin_ids) if skin_ids else np.zeros(n, dtype=bool)
    skin_ref = np.median(col[skin_src], axis=0) if skin_src.any() else None
    skin_like = np.zeros(n, dtype=bool)
    filled = np.zeros(n, dtype=bool)
    covered_all = np.zeros(n, dtype=bool)
    out_col = col.copy()
    out_op = op.copy() if op is not None else None
    stats: dict[str, dict[str, float]] = {}
    for group in groups:
        ids = sorted({int(v) for v in group})
        in_g = np.isin(reg, ids)
        if hair_ids & set(ids) and skin_ref is not None:
            gs = np.nonzero(src_all & in_g)[0]
            if gs.size:
                skin_like[gs[skin_like_sources(col[gs], skin_ref)]] = True
        sources = src_all & in_g & ~skin_like
        target = in_g & ~seen & ~tk
        refill = np.zeros(n, dtype=bool)
        if hair_ids & set(ids):
            refill = in_g & skin_like & grazing & ~tk
            target |= refill
        s = {"surfels": float(in_g.sum()), "targets": float(target.sum()), "sources": float(sources.sum()),
             "skin_like_sources": float((skin_like & in_g).sum()), "grazing_skin_refilled": float(refill.sum()), "filled": 0.0}
        stats["+".join(map(str, ids))] = s
        if not target.any() or not sources.any():
            continue
        # the graph over the group's surfels that no other prior colours
        nodes = np.nonzero(in_g & ~tk)[0]
        adj = knn_graph(x[nodes], neighbours)
        vals, reached = harmonic_fill(adj, col[nodes], sources[nodes])
        vals[~reached] = np.median(col[sources], axis=0)
        t = target[nodes]
        skin_src = src_all & in_g & skin_like & ~grazing
        if skin_src.any() and float(skin_ratio) > 0:
            # skin continued where the seen skin is much nearer than the seen hair (cheeks, ears)
            from scipy.spatial import cKDTree

            d_h, _ = cKDTree(x[sources]).query(x[nodes], k=1)
            d_s, _ = cKDTree(x[skin_src]).query(x[nodes], k=1)
            near_skin = t & (d_s < float(skin_ratio) * d_h)
            if near_skin.any():
                sv, _ = harmonic_fill(adj, col[nodes], skin_src[nodes])
                vals[near_skin] = sv[near_skin]
                s["skin_continued"] = float(near_skin.sum())
        out_col[nodes[t]] = vals[t].clip(0.0, 1.0)
        filled[nodes[t]] = True
        s["filled"] = float(t.sum())
        s["unreached"] = float((t & ~reached).sum())
        covered = cover_ids is None or bool(cover_ids & set(ids))
        cov = nodes[t]
        if covered and cover_facing_away:
            cov = np.union1d(cov, np.nonzero(in_g & seen & away & ~tk)[0])
        if covered:
            covered_all[cov] = True
            s["covered"] = float(cov.size)
        if out_op is not None and covered:
            floor = float(np.median(op[sources]))
            out_op[cov] = np.maximum(op[cov], floor)
            s["opacity_floor"] = floor
        if sg is not None and covered and nodes.size > cover_neighbours:
            from scipy.spatial import cKDTree

            d, _ = cKDTree(x[nodes]).query(x[cov], k=int(cover_neighbours) + 1)
            want = float(cover_ratio) * d[:, -1]
            kept = seen & ~filled & ~away  # the seen surface some view faces
            if kept.any():  # near the seen surface the seen surfels cover: grow only away from it
                d_seen, _ = cKDTree(x[kept]).query(x[cov], k=1)
                want = np.minimum(want, float(seen_ratio) * d_seen)
            if boundary is not None and len(boundary[0]):  # the disc ends where the surface does
                want = np.minimum(want, float(boundary_ratio) * distance_to_segments(x[cov], boundary[0], boundary[1]))
            geo = np.sqrt(np.maximum(sg[cov, 0] * sg[cov, 1], 1e-30))
            gain[cov] = np.clip(want / geo, 1.0, float(max_gain))
            s["scale_gain_median"] = float(np.median(gain[cov]))
            s["seen_facing_away"] = float((seen & away & in_g).sum())
    all_sources = src_all & ~skin_like & np.isin(reg, [int(v) for g in groups for v in g])
    return FillResult(
        filled=torch.as_tensor(filled, device=dev),
        colors=torch.as_tensor(out_col, dtype=colors.dtype, device=dev),
        opacity=torch.as_tensor(out_op, dtype=opacity.dtype, device=dev) if (out_op is not None and opacity is not None) else None,
        scale_gain=torch.as_tensor(gain, dtype=colors.dtype, device=dev),
        covered=torch.as_tensor(covered_all, device=dev),
        sources=torch.as_tensor(all_sources, device=dev),
        skin_like=torch.as_tensor(skin_like, device=dev),
        per_group=stats,
    )
