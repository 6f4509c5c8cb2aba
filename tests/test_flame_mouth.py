"""Mouth interior on a synthetic ellipsoid head with a jaw-weighted lips band."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from sage_core.flame import FlameModel, FlameModelData, Regions
from sage_core.flame.mouth import add_mouth_interior, has_mouth_interior

RADII = np.array([0.08, 0.11, 0.10])
MOUTH_Y = -0.045


def ellipsoid_head(seed: int = 0) -> tuple[FlameModelData, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    v = np.asarray(sphere.vertices) * RADII
    faces = np.asarray(sphere.faces, dtype=np.int64)
    V = len(v)
    front = v[:, 2] > 0.6 * RADII[2]
    lips = np.nonzero(front & (np.abs(v[:, 0]) < 0.035) & (np.abs(v[:, 1] - MOUTH_Y) < 0.02))[0]
    chin = front & (v[:, 1] < MOUTH_Y)
    w = np.zeros((V, 5))
    w[:, 1] = 1.0
    w[chin] = np.eye(5)[2]
    upper = lips[v[lips, 1] >= MOUTH_Y]
    w[upper] = 0.9 * np.eye(5)[1] + 0.1 * np.eye(5)[2]
    lower = lips[v[lips, 1] < MOUTH_Y]
    w[lower] = 0.2 * np.eye(5)[1] + 0.8 * np.eye(5)[2]

    def regress(points: list[np.ndarray]) -> np.ndarray:
        row = np.zeros(V)
        for p in points:
            row[np.argmin(np.linalg.norm(v - p, axis=1))] += 1.0 / len(points)
        return row

    jr = np.stack([
        regress([np.array([0.0, -0.11, 0.0])]),
        regress([np.array([0.08, -0.06, -0.02]), np.array([-0.08, -0.06, -0.02])]),
        regress([np.array([0.08, -0.03, 0.0]), np.array([-0.08, -0.03, 0.0])]),
        regress([np.array([0.03, 0.02, 0.1])]),
        regress([np.array([-0.03, 0.02, 0.1])]),
    ])
    data = FlameModelData(
        v_template=v, faces=faces,
        shapedirs=rng.normal(size=(V, 3, 4)) * 0.005, exprdirs=rng.normal(size=(V, 3, 2)) * 0.005,
        posedirs=np.zeros((V, 3, 36)), j_regressor=jr, lbs_weights=w,
        parents=np.array([-1, 0, 1, 1, 1]), n_base_vertices=V, version="ellipsoid",
    )
    return data, {"lips": lips, "face": np.nonzero(front)[0]}


def test_parts_appended_and_originals_unchanged() -> None:
    d, masks = ellipsoid_head()
    m = add_mouth_interior(d, masks)
    assert has_mouth_interior(m) and not has_mouth_interior(d)
    for g in ("mouth_upper", "mouth_lower", "teeth_upper", "teeth_lower"):
        assert g in m.vertex_groups and len(m.vertex_groups[g]) > 0
        assert m.vertex_groups[g].min() >= d.n_vertices
    new = np.concatenate([m.vertex_groups[g] for g in ("mouth_upper", "mouth_lower", "teeth_upper", "teeth_lower")])
    np.testing.assert_array_equal(np.sort(new), np.arange(d.n_vertices, m.n_vertices))
    np.testing.assert_array_equal(m.v_template[: d.n_vertices], d.v_template)
    np.testing.assert_array_equal(m.faces[: d.n_faces], d.faces)
    np.testing.assert_array_equal(m.lbs_weights[: d.n_vertices], d.lbs_weights)
    assert m.faces[d.n_faces:].min() >= d.n_vertices and m.faces.max() < m.n_vertices
    assert m.face_table == "flame+sage-mouth-teeth-v1" and m.n_base_vertices == d.n_vertices
    n_new = m.n_vertices - d.n_vertices
    assert not m.exprdirs[d.n_vertices:].any() and not m.posedirs[d.n_vertices:].any()
    assert not m.j_regressor[:, d.n_vertices:].any()
    np.testing.assert_array_equal(m.lbs_weights[m.vertex_groups["mouth_upper"]].argmax(1), 1)
    np.testing.assert_array_equal(m.lbs_weights[m.vertex_groups["teeth_lower"]].argmax(1), 2)
    assert np.allclose(m.lbs_weights[d.n_vertices:].sum(1), 1.0) and n_new > 50


def test_parts_lie_behind_the_lips_inside_the_head() -> None:
    d, masks = ellipsoid_head()
    m = add_mouth_interior(d, masks)
    new = m.v_template[d.n_vertices:]
    lips = d.v_template[masks["lips"]]
    assert new[:, 2].max() < lips[:, 2].min()
    assert (((new / RADII) ** 2).sum(1) < 1.0).all()
    lip_w = lips[:, 0].max() - lips[:, 0].min()
    assert new[:, 0].max() - new[:, 0].min() <= lip_w + 1e-9
    up, lo = m.v_template[m.vertex_groups["mouth_upper"]], m.v_template[m.vertex_groups["mouth_lower"]]
    assert up[:, 1].min() >= lo[:, 1].max() - 1e-12
    assert abs(up[:, 1].min() - MOUTH_Y) < 0.02


def test_cavity_faces_face_inwards() -> None:
    d, masks = ellipsoid_head()
    m = add_mouth_interior(d, masks, teeth=False)
    f = m.faces[d.n_faces:]
    v = m.v_template
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    centroid = v[f].mean(1)
    # the centre of the cavity is the slit point on its open front plane
    cavity = v[np.concatenate([m.vertex_groups["mouth_upper"], m.vertex_groups["mouth_lower"]])]
    slit_y = v[m.vertex_groups["mouth_upper"], 1].min()
    centre = np.array([0.5 * (cavity[:, 0].max() + cavity[:, 0].min()), slit_y, cavity[:, 2].max()])
    assert ((n * (centre - centroid)).sum(1) > 0).all()
    assert "teeth_upper" not in m.vertex_groups and m.face_table.endswith("+sage-mouth-v1")
    with_teeth = add_mouth_interior(d, masks, teeth=True)
    teeth_ids = np.concatenate([with_teeth.vertex_groups["teeth_upper"], with_teeth.vertex_groups["teeth_lower"]])
    tf = with_teeth.faces[np.isin(with_teeth.faces, teeth_ids).all(1)]
    assert len(tf) == 40
    vt = with_teeth.v_template
    tn = np.cross(vt[tf[:, 1]] - vt[tf[:, 0]], vt[tf[:, 2]] - vt[tf[:, 0]])
    tn /= np.linalg.norm(tn, axis=1, keepdims=True)
    # the arcs face forwards (+z) on average and never backwards at the arc centre
    assert tn[:, 2].mean() > 0.5 and (tn[:, 2] > 0).all()


def test_jaw_moves_only_the_lower_parts() -> None:
    d, masks = ellipsoid_head()
    m = add_mouth_interior(d, masks)
    model = FlameModel(m, dtype=torch.float64)
    shape = torch.tensor([0.5, -0.3, 0.2, 0.1], dtype=torch.float64)
    rest = model(shape=shape)
    jaw = model(shape=shape, jaw_pose=torch.tensor([[0.35, 0.0, 0.0]], dtype=torch.float64))
    for g in ("mouth_upper", "teeth_upper"):
        ids = torch.as_tensor(m.vertex_groups[g])
        torch.testing.assert_close(jaw.vertices[0, ids], rest.vertices[0, ids])
    for g in ("mouth_lower", "teeth_lower"):
        ids = torch.as_tensor(m.vertex_groups[g])
        assert (jaw.vertices[0, ids] - rest.vertices[0, ids]).norm(dim=-1).min() > 1e-4
    neck = model(shape=shape, neck_pose=torch.tensor([[0.0, 0.3, 0.0]], dtype=torch.float64))
    ids = torch.as_tensor(m.vertex_groups["mouth_upper"])
    assert (neck.vertices[0, ids] - rest.vertices[0, ids]).norm(dim=-1).min() > 1e-4


def test_identity_blendshapes_follow_nearest_vertex() -> None:
    d, masks = ellipsoid_head()
    m = add_mouth_interior(d, masks)
    for i in range(d.n_vertices, m.n_vertices, 7):
        nearest = np.argmin(np.linalg.norm(d.v_template - m.v_template[i], axis=1))
        np.testing.assert_array_equal(m.shapedirs[i], d.shapedirs[nearest])


def test_regions_and_masks_inputs_agree() -> None:
    d, masks = ellipsoid_head()
    a = add_mouth_interior(d, masks)
    b = add_mouth_interior(d, Regions(masks, d.faces, d.n_vertices))
    np.testing.assert_array_equal(a.v_template, b.v_template)
    np.testing.assert_array_equal(a.faces, b.faces)
    r = Regions(masks, a.faces, a.n_vertices, a.vertex_groups)
    assert r.has("mouth_interior") and r.has("teeth")
    assert not r.vertex_mask("skin")[d.n_vertices:].any()


def test_existing_teeth_skip_arcs_and_errors() -> None:
    d, masks = ellipsoid_head()
    d.vertex_groups = {"teeth_upper": np.array([0]), "teeth_lower": np.array([1])}
    m = add_mouth_interior(d, masks)
    np.testing.assert_array_equal(m.vertex_groups["teeth_upper"], [0])
    assert m.face_table.endswith("+sage-mouth-v1")
    with pytest.raises(ValueError, match="already"):
        add_mouth_interior(m, masks)
    with pytest.raises(ValueError, match="lips"):
        add_mouth_interior(d, {"face": masks["face"]})
    flat = d.copy()
    flat.vertex_groups = {}
    flat.lbs_weights = np.tile(np.eye(5)[1], (d.n_vertices, 1))
    with pytest.raises(ValueError, match="jaw"):
        add_mouth_interior(flat, masks)
