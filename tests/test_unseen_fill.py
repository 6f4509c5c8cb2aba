"""The unseen fill: unseen surfels continued from the seen surfels of their own region.

Synthetic surfel clouds on a sphere stand in for a head: the front (z > 0) is seen, the back is not;
the upper half is "hair", the lower front "face", so the hair's seen part borders the face's.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sage_core.avatar.init import REGION_FACE, REGION_HAIR, REGION_NECK
from sage_core.train.unseen_fill import fill_unseen, harmonic_fill, knn_graph, skin_like_sources

SKIN = torch.tensor([0.80, 0.60, 0.50])
HAIR = torch.tensor([0.10, 0.08, 0.06])


def _sphere(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return (v / v.norm(dim=1, keepdim=True)).float() * 0.1


def _head(n: int = 1500, seed: int = 0):
    """points (N, 3), colours, view weights, regions: hair above y = 0, face below in front, neck behind."""
    x = _sphere(n, seed)
    region = torch.where(x[:, 1] > 0, REGION_HAIR, torch.where(x[:, 2] > 0, REGION_FACE, REGION_NECK))
    front = x[:, 2] > 0.0
    weights = torch.where(front, 5.0 + 5.0 * x[:, 2] / 0.1, torch.zeros(n))
    colors = torch.where((region == REGION_HAIR)[:, None], HAIR, SKIN).clone()
    # what the network extrapolates behind the head: a ghost of the face (its colours mirrored back)
    colors[~front] = torch.tensor([0.9, 0.2, 0.2])
    opacity = torch.where(front, torch.full((n,), 0.9), torch.full((n,), 0.2))
    return x, colors, weights, region, opacity


def test_unseen_take_their_own_regions_colours_and_seen_are_unchanged() -> None:
    x, c, w, r, op = _head()
    res = fill_unseen(x, c, w, r, op, groups=((REGION_HAIR,), (REGION_FACE,), (REGION_NECK,)), hair_regions=(REGION_HAIR,),
                      skin_regions=(REGION_FACE,), neighbours=8)
    seen = w >= 0.5
    assert torch.equal(res.colors[seen], c[seen])
    assert torch.equal(res.opacity[seen], op[seen])
    assert not bool(res.filled[seen].any())
    back_hair = ~seen & (r == REGION_HAIR)
    assert bool(res.filled[back_hair].all())
    assert torch.allclose(res.colors[back_hair], HAIR.expand_as(res.colors[back_hair]), atol=1e-6)
    # the neck has no seen surfel: nothing to continue, left as it was
    neck = r == REGION_NECK
    assert not bool(res.filled[neck].any())
    assert torch.equal(res.colors[neck], c[neck])
    # opacity raised to the seen hair's median
    assert torch.allclose(res.opacity[back_hair], torch.full_like(res.opacity[back_hair], 0.9))
    assert res.per_group[str(REGION_HAIR)]["filled"] == float(back_hair.sum())


def test_hair_never_takes_skin_coloured_sources() -> None:
    """A fringe of skin-coloured hair-region surfels (a forehead the region mask calls hair) at the
    front borders the back: without the exclusion the back would turn skin coloured near it."""
    x, c, w, r, op = _head(2000, 1)
    seen = w >= 0.5
    forehead = seen & (r == REGION_HAIR) & (x[:, 1] < 0.05)
    c[forehead] = SKIN + 0.02
    # skin_ratio=0: no skin continued near the seen skin (tested below), only the exclusion
    res = fill_unseen(x, c, w, r, op, groups=((REGION_HAIR,),), hair_regions=(REGION_HAIR,), skin_regions=(REGION_FACE,),
                      skin_ratio=0.0)
    assert bool(res.skin_like[forehead].all())
    assert not bool(res.skin_like[seen & (r == REGION_HAIR) & ~forehead].any())
    back_hair = ~seen & (r == REGION_HAIR)
    got = res.colors[back_hair]
    assert float((got - HAIR).abs().max()) < 1e-6, "a back hair surfel took a skin colour"
    # the forehead itself (seen) keeps its colour
    assert torch.equal(res.colors[forehead], c[forehead])


def test_skin_is_continued_only_where_the_seen_skin_is_much_nearer_than_the_hair() -> None:
    """With the default skin_ratio (0.7) an unseen surfel of the hair group continues the skin
    exactly when its nearest seen skin-like surfel is nearer than 0.7 times its nearest hair source
    (the cheeks by the ears); every other one takes the hair."""
    from scipy.spatial import cKDTree

    x, c, w, r, op = _head(2000, 1)
    seen = w >= 0.5
    forehead = seen & (r == REGION_HAIR) & (x[:, 1] < 0.05)
    c[forehead] = SKIN + 0.02
    res = fill_unseen(x, c, w, r, op, groups=((REGION_HAIR,),), hair_regions=(REGION_HAIR,), skin_regions=(REGION_FACE,))
    back_hair = ~seen & (r == REGION_HAIR)
    assert bool(res.filled[back_hair].all())
    hair_src = res.sources.numpy()
    d_h, _ = cKDTree(x[hair_src].numpy()).query(x[back_hair].numpy(), k=1)
    d_s, _ = cKDTree(x[forehead].numpy()).query(x[back_hair].numpy(), k=1)
    near_skin = torch.as_tensor(d_s < 0.7 * d_h)
    assert 0 < int(near_skin.sum()) < int(back_hair.sum())
    got = res.colors[back_hair]
    # the far ones are pure hair; the near ones a continuation of the skin fringe (its colour range)
    assert float((got[~near_skin] - HAIR).abs().max()) < 1e-6
    assert float((got[near_skin] - (SKIN + 0.02)).abs().max()) < 1e-5


def test_regions_do_not_leak_and_taken_surfels_are_left_alone() -> None:
    x, c, w, r, op = _head(1500, 2)
    # put a mouth prior on part of the back hair: it must be neither filled nor a source
    taken = (r == REGION_HAIR) & (x[:, 2] < -0.05)
    res = fill_unseen(x, c, w, r, op, groups=((REGION_HAIR,), (REGION_FACE,)), hair_regions=(REGION_HAIR,),
                      skin_regions=(REGION_FACE,), taken=taken)
    assert not bool(res.filled[taken].any())
    assert torch.equal(res.colors[taken], c[taken])
    # the face region's unseen surfels (none here: the face is in front) and the hair's only take
    # their region's colours
    filled_hair = res.filled & (r == REGION_HAIR)
    assert bool(filled_hair.any())
    assert float((res.colors[filled_hair] - HAIR).abs().max()) < 1e-6


def test_only_named_regions_are_filled() -> None:
    x, c, w, r, op = _head(800, 3)
    res = fill_unseen(x, c, w, r, op, groups=((REGION_FACE,),), hair_regions=(REGION_HAIR,), skin_regions=(REGION_FACE,))
    assert not bool(res.filled[r == REGION_HAIR].any())
    assert torch.equal(res.colors[r == REGION_HAIR], c[r == REGION_HAIR])


def test_grazing_surfels_keep_their_colour_but_pass_nothing_on() -> None:
    x, c, w, r, op = _head(1500, 4)
    graze = (w >= 0.5) & (w < 2.0)
    assert not bool(graze.any())
    # make a band of hair surfels near the silhouette weakly seen and white (blended with the background)
    band = (r == REGION_HAIR) & (x[:, 2] > 0) & (x[:, 2] < 0.02)
    w[band] = 1.0
    c[band] = torch.tensor([1.0, 1.0, 1.0])
    res = fill_unseen(x, c, w, r, op, groups=((REGION_HAIR,),), hair_regions=(REGION_HAIR,), skin_regions=(REGION_FACE,),
                      source_min=2.0)
    assert torch.equal(res.colors[band], c[band])
    assert not bool(res.sources[band].any())
    back_hair = (w < 0.5) & (r == REGION_HAIR)
    assert float((res.colors[back_hair] - HAIR).abs().max()) < 1e-6


def test_harmonic_fill_interpolates_between_sources() -> None:
    # a path graph 0 - 1 - 2 - 3 - 4 with the ends known: the middle is linear
    import scipy.sparse as sp

    e = np.array([[0, 1], [1, 2], [2, 3], [3, 4]])
    a = sp.coo_matrix((np.ones(8), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(5, 5)).tocsr()
    vals = np.zeros((5, 1))
    vals[0], vals[4] = 0.0, 1.0
    known = np.array([True, False, False, False, True])
    out, reached = harmonic_fill(a, vals, known)
    assert reached.all()
    assert np.allclose(out[:, 0], [0.0, 0.25, 0.5, 0.75, 1.0])
    # a node in another component without a known node is not reached
    a2 = sp.block_diag([a, sp.csr_matrix((1, 1))]).tocsr()
    out2, reached2 = harmonic_fill(a2, np.vstack([vals, [[0.3]]]), np.r_[known, False])
    assert not reached2[5] and out2[5, 0] == pytest.approx(0.3)


def test_knn_graph_is_symmetric_and_connects_neighbours() -> None:
    pts = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0], [11, 0, 0]], dtype=float)
    a = knn_graph(pts, 1)
    assert (a != a.T).nnz == 0
    assert a[0, 1] == 1 and a[3, 4] == 1 and a[0, 3] == 0


def test_skin_like_split() -> None:
    rng = np.random.default_rng(0)
    hair = np.array([0.1, 0.08, 0.06]) + 0.02 * rng.standard_normal((60, 3))
    skin = np.array([0.8, 0.6, 0.5]) + 0.02 * rng.standard_normal((30, 3))
    got = skin_like_sources(np.vstack([hair, skin]), np.array([0.8, 0.6, 0.5]))
    assert not got[:60].any() and got[60:].all()
    # one colour throughout (hair like skin, or a bald scalp): nothing is excluded
    assert not skin_like_sources(skin, np.array([0.8, 0.6, 0.5])).any()
    # a small minority of dark pixels does not turn the majority into "skin"
    few = np.vstack([hair[:5], skin])
    assert not skin_like_sources(few, np.array([0.8, 0.6, 0.5])).any()
    # lighter and darker hair (shading, strands) are both hair: nearer the hair than the skin
    mixed = np.vstack([hair, hair + 0.2, skin])
    got = skin_like_sources(mixed, np.array([0.8, 0.6, 0.5]))
    assert not got[:120].any() and got[120:].all()


def test_skin_coloured_hair_seen_only_at_grazing_angles_is_refilled() -> None:
    x, c, w, r, op = _head(1500, 5)
    seen = w >= 0.5
    facing = w * 0.9
    # a skin-coloured blotch on the seen hair, seen only at grazing angles
    blotch = seen & (r == REGION_HAIR) & (x[:, 2] < 0.03) & (x[:, 0] > 0.0)
    c[blotch] = SKIN
    facing[blotch] = 0.1 * w[blotch]
    # another one seen frontally: real skin (a forehead), kept
    kept = seen & (r == REGION_HAIR) & (x[:, 2] < 0.03) & (x[:, 0] <= 0.0)
    c[kept] = SKIN
    res = fill_unseen(x, c, w, r, op, None, facing, groups=((REGION_HAIR,),), hair_regions=(REGION_HAIR,),
                      skin_regions=(REGION_FACE,), skin_ratio=0.0)
    assert bool(blotch.any()) and bool(res.filled[blotch].all())
    assert float((res.colors[blotch] - HAIR).abs().max()) < 1e-6
    assert torch.equal(res.colors[kept], c[kept]) and not bool(res.filled[kept].any())
    assert res.per_group[str(REGION_HAIR)]["grazing_skin_refilled"] == float(blotch.sum())



def test_cover_grows_unseen_surfels_but_not_past_the_meshs_open_edge() -> None:
    """A flat sheet (z = 0, x and y in [0, 1]) whose edge x = 1 is open: its strip x < 0.2 is seen,
    the rest is not and has small surfels. They grow to cover the gaps, except near the open edge at x = 1,
    where a disc of three standard deviations may reach the edge but not beyond it."""
    from sage_core.geometry.topology import boundary_edges, distance_to_segments

    g = torch.Generator().manual_seed(0)
    n = 3000
    x = torch.cat([torch.rand(n, 2, generator=g, dtype=torch.float64), torch.zeros(n, 1, dtype=torch.float64)], 1)
    seen = x[:, 0] < 0.2
    w = torch.where(seen, torch.full((n,), 3.0, dtype=torch.float64), torch.zeros(n, dtype=torch.float64))
    r = torch.full((n,), REGION_HAIR)
    c = torch.where(seen[:, None], HAIR, SKIN)
    op = torch.where(seen, torch.full((n,), 0.9), torch.full((n,), 0.3))
    scales = torch.full((n, 2), 0.002)
    # the open edge x = 1 as segments of a mesh: a strip of two triangles per step along y
    ys = np.linspace(0.0, 1.0, 11)
    verts = np.array([[xx, y, 0.0] for y in ys for xx in (0.9, 1.0)])
    faces = np.array([[2 * i, 2 * i + 1, 2 * i + 3] for i in range(10)] + [[2 * i, 2 * i + 3, 2 * i + 2] for i in range(10)])
    e = boundary_edges(faces)
    edge_x1 = np.all(verts[e][:, :, 0] == 1.0, axis=1)
    assert edge_x1.sum() == 10 and len(e) == 22  # ten along x = 1, ten along x = 0.9, the two ends
    segs = (verts[e[edge_x1, 0]], verts[e[edge_x1, 1]])
    kw = dict(groups=((REGION_HAIR,),), cover_regions=(REGION_HAIR,), seen_ratio=10.0)
    free = fill_unseen(x, c, w, r, op, scales, **kw)
    capped = fill_unseen(x, c, w, r, op, scales, boundary=segs, **kw)
    assert torch.equal(free.filled, capped.filled) and torch.equal(free.opacity, capped.opacity)
    d = torch.as_tensor(distance_to_segments(x.numpy(), *segs))
    far = free.filled & (d > 0.1)
    near = free.filled & (d < 0.005)
    assert bool(far.any()) and bool(near.any())
    torch.testing.assert_close(capped.scale_gain[far], free.scale_gain[far])
    assert bool((free.scale_gain[near] > 1.5).all())
    assert bool((capped.scale_gain[near] < free.scale_gain[near]).all())
    grown = capped.scale_gain > 1
    assert bool((0.002 * capped.scale_gain[grown] <= d[grown] / 3.0 + 1e-9).all())


def test_distance_to_segments_is_exact_and_boundary_edges_of_a_closed_mesh_are_none() -> None:
    from sage_core.geometry.topology import boundary_edges, distance_to_segments, edges

    tet = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    assert boundary_edges(tet).shape == (0, 2) and len(edges(tet)) == 6
    a = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 1.0]])
    p = np.array([[0.5, 1.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 2.0, 0.5], [3.0, 0.0, 4.0]])
    np.testing.assert_allclose(distance_to_segments(p, a, b, chunk=3), [1.0, 2.0, 0.0, np.hypot(2.0, 4.0)])


def test_surfels_seen_edge_on_do_not_hold_back_the_cover() -> None:
    """A clip sees the back of the head only edge-on: a surfel seen that way, facing no camera, does
    not limit the growth of its unseen neighbours as a seen surfel some view faces does; it keeps
    its own colour, opacity and scales."""
    x, c, w, r, op = _head(1500, 3)
    scales = torch.full((x.shape[0], 2), 0.002)
    seen = w >= 0.5
    # a grazed rim on the back (z < -0.05): every other hair surfel there just above the seen threshold
    rim = (x[:, 2] < -0.05) & (r == REGION_HAIR) & (torch.arange(x.shape[0]) % 2 == 0)
    w = torch.where(rim, torch.full_like(w, 0.8), w)
    away = x[:, 2] < -0.02
    kw = dict(groups=((REGION_HAIR,),), hair_regions=(REGION_HAIR,), skin_regions=(REGION_FACE,), cover_regions=(REGION_HAIR,))
    base = fill_unseen(x, c, w, r, op, scales, **kw)
    res = fill_unseen(x, c, w, r, op, scales, facing_away=away, **kw)
    assert bool(rim.any())
    assert torch.equal(res.filled, base.filled) and not bool(res.filled[rim].any())
    assert torch.equal(res.colors, base.colors) and torch.equal(res.opacity, base.opacity)
    assert bool((res.scale_gain[rim] == 1).all()) and bool((res.scale_gain[seen] == 1).all())
    unseen_back = res.filled & (x[:, 2] < -0.05)
    assert bool((res.scale_gain[unseen_back] >= base.scale_gain[unseen_back]).all())
    assert float(res.scale_gain[unseen_back].mean()) > 1.5 * float(base.scale_gain[unseen_back].mean())
    # away from the rim the seen surfels that the views face still hold the growth back as before
    front = res.filled & (x[:, 2] > -0.02)
    torch.testing.assert_close(res.scale_gain[front], base.scale_gain[front])
    assert res.per_group[str(REGION_HAIR)]["seen_facing_away"] == float(rim.sum())


def test_cover_facing_away_covers_the_grazed_rim_too() -> None:
    """``cover_facing_away``: the seen surfels that no view faces (the grazed rim on the back) get the
    opacity floor and grow like the unseen ones, their colours kept; without it they are left as they
    are; the filled surfels and every colour are the same either way."""
    x, c, w, r, op = _head(1500, 3)
    scales = torch.full((x.shape[0], 2), 0.002)
    rim = (x[:, 2] < -0.05) & (r == REGION_HAIR) & (torch.arange(x.shape[0]) % 2 == 0)
    w = torch.where(rim, torch.full_like(w, 0.8), w)
    op = torch.where(rim, torch.full_like(op, 0.1), op)
    away = x[:, 2] < -0.02
    kw = dict(groups=((REGION_HAIR,),), hair_regions=(REGION_HAIR,), skin_regions=(REGION_FACE,), cover_regions=(REGION_HAIR,),
              facing_away=away)
    base = fill_unseen(x, c, w, r, op, scales, **kw)
    res = fill_unseen(x, c, w, r, op, scales, cover_facing_away=True, **kw)
    assert bool(rim.any()) and not bool(base.covered[rim].any())
    assert torch.equal(base.covered, base.filled)
    assert torch.equal(res.filled, base.filled) and torch.equal(res.colors, base.colors)
    assert bool(res.covered[rim].all()) and torch.equal(res.covered, res.filled | rim)
    floor = res.per_group[str(REGION_HAIR)]["opacity_floor"]
    assert floor > 0.1 and bool((res.opacity[rim] == floor).all()) and bool((base.opacity[rim] == 0.1).all())
    assert float(res.scale_gain[rim].mean()) > 1.5 and bool((base.scale_gain[rim] == 1).all())
    # the seen surfels some view faces are untouched
    faced = (w >= 0.5) & ~rim
    assert bool((res.scale_gain[faced] == 1).all()) and torch.equal(res.opacity[faced], op[faced].to(res.opacity))
