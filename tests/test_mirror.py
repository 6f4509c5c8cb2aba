"""Mirror geometry: the mirror camera, the template's vertex/face mirror correspondence, mirrored meshes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sage_core.data.cameras import Camera, look_at
from sage_core.flame.mirror import mirror_correspondence, model_mirror
from sage_core.render.mesh_raster import rasterize_mesh
from sage_core.train.pseudo_views import mirror_camera, mirror_vertices

S = np.array([-1.0, 1.0, 1.0])


def _camera(W: int = 40, H: int = 30) -> Camera:
    K = np.array([[55.0, 0.0, 17.3], [0.0, 52.0, 16.1], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(np.array([0.3, 0.1, 1.2]), np.array([0.02, -0.01, 0.0])), W, H, 3, "cam")


def test_mirror_camera_projects_reflections_to_w_minus_u():
    cam = _camera()
    mc = mirror_camera(cam)
    rng = np.random.default_rng(0)
    X = rng.normal(0.0, 0.1, (50, 3))
    uv, z = cam.project(X)
    uv_m, z_m = mc.project(X * S)
    assert np.all(z > 0)
    np.testing.assert_allclose(uv_m[:, 0], cam.width - uv[:, 0], atol=1e-10)
    np.testing.assert_allclose(uv_m[:, 1], uv[:, 1], atol=1e-10)
    np.testing.assert_allclose(z_m, z, atol=1e-12)
    assert mc.K[0, 2] == pytest.approx(cam.width - cam.K[0, 2])
    # a proper rotation and mirroring twice gives the camera back
    assert np.linalg.det(mc.w2c[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(mirror_camera(mc).w2c, cam.w2c, atol=1e-12)
    np.testing.assert_allclose(mirror_camera(mc).K, cam.K, atol=1e-12)


def test_mirror_camera_flips_the_rasterized_image_exactly():
    """With the rasterizer's pixel centres at +0.5, the mirrored scene is the column-flipped image."""
    cam = _camera(37, 29)
    mc = mirror_camera(cam)
    rng = np.random.default_rng(1)
    verts = torch.as_tensor(rng.normal(0.0, 0.08, (30, 3)))
    faces = torch.as_tensor(rng.integers(0, 30, (25, 3)))
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    r0 = rasterize_mesh(verts, faces, torch.as_tensor(cam.K), torch.as_tensor(cam.w2c), cam.width, cam.height)
    r1 = rasterize_mesh(verts * torch.as_tensor(S), faces, torch.as_tensor(mc.K), torch.as_tensor(mc.w2c), mc.width, mc.height)
    assert int((r0.face_id >= 0).sum()) > 50
    assert torch.equal(r1.face_id, torch.flip(r0.face_id, dims=[2]))


@pytest.fixture(scope="module")
def synthetic_model():
    """The tiny synthetic head with the mouth interior, teeth and tongue appended (as init-mesh builds it)."""
    from sage_core.data.synthetic import build_head, flame_model_data
    from sage_core.data.synthetic.config import preset
    from sage_core.flame import Regions, add_mouth_interior

    cfg = preset("tiny")
    head = build_head(cfg.head_rows, cfg.head_cols, cfg.eye_rows, cfg.eye_cols)
    md = flame_model_data(head)
    return add_mouth_interior(md, Regions(head.masks, md.faces, md.n_vertices, md.vertex_groups), tongue=True)


def test_mirror_correspondence_of_the_synthetic_head_is_an_involution(synthetic_model):
    md = synthetic_model
    v = np.asarray(md.v_template)
    assert v.shape[0] > md.n_base_vertices  # teeth, mouth interior and tongue included
    m, reason = model_mirror(md)
    assert m is not None, reason
    idx = np.arange(v.shape[0])
    assert np.array_equal(m.vertex[m.vertex], idx)
    assert np.array_equal(np.sort(m.vertex), idx)  # a permutation: coincident lip vertices resolved
    size = np.linalg.norm(v.max(0) - v.min(0))
    assert np.abs(v[m.vertex] - v * S).max() < 1e-9 * size
    fixed = m.vertex == idx
    assert m.n_fixed == int(fixed.sum()) > 0
    assert np.abs(v[fixed, 0]).max() < 1e-9
    # coincident vertices exist (the lip slit) and go to different partners
    from scipy.spatial import cKDTree

    pairs = np.array(sorted(cKDTree(v).query_pairs(1e-12)))
    assert len(pairs) > 0
    assert np.all(m.vertex[pairs[:, 0]] != m.vertex[pairs[:, 1]])
    # mouth-interior vertices map onto mouth-interior vertices
    mouth = np.concatenate([md.vertex_groups["mouth_upper"], md.vertex_groups["mouth_lower"]])
    assert set(m.vertex[mouth].tolist()) == set(mouth.tolist())
    # the synthetic triangulation is not mirror-symmetric: no face map, but a reason
    assert m.face is None and m.face_reason


def test_mirror_vertices_of_a_symmetric_template(synthetic_model):
    m, _ = model_mirror(synthetic_model)
    idx = torch.as_tensor(m.vertex)
    v = torch.as_tensor(np.asarray(synthetic_model.v_template))
    assert torch.allclose(mirror_vertices(v, idx), v, atol=1e-12)
    x = torch.randn(2, 3, v.shape[0], 3, dtype=torch.float64)
    y = mirror_vertices(x, idx)
    assert y.shape == x.shape
    assert torch.allclose(y[..., 5, :], x[..., int(idx[5]), :] * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    assert torch.allclose(mirror_vertices(y, idx), x)


def _symmetric_grid(n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A (2n+1)×(n+1) grid in the plane z = x² with diagonals mirrored about x = 0."""
    xs = np.linspace(-1.0, 1.0, 2 * n + 1)
    ys = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(xs, ys)
    v = np.stack([X.ravel(), Y.ravel(), X.ravel() ** 2], 1)
    ids = np.arange(v.shape[0]).reshape(len(ys), len(xs))
    faces = []
    for r in range(len(ys) - 1):
        for c in range(len(xs) - 1):
            a, b, cc, d = ids[r, c], ids[r, c + 1], ids[r + 1, c + 1], ids[r + 1, c]
            if xs[c] < 0:
                faces += [[a, b, cc], [a, cc, d]]
            else:
                faces += [[a, b, d], [b, cc, d]]
    return v, np.array(faces)


def test_face_correspondence_of_a_symmetric_triangulation():
    v, f = _symmetric_grid()
    m, reason = mirror_correspondence(v, f)
    assert m is not None, reason
    assert m.face is not None and m.face_perm is not None, m.face_reason
    assert np.array_equal(m.face[m.face], np.arange(len(f)))
    assert np.array_equal(np.take_along_axis(f[m.face], m.face_perm, 1), m.vertex[f])
    # a point (f, β) and the point (face[f], β at corners face_perm) are reflections of each other
    beta = np.array([0.2, 0.3, 0.5])
    for fi in range(len(f)):
        p = beta @ v[f[fi]]
        g = m.face[fi]
        b2 = np.zeros(3)
        b2[m.face_perm[fi]] = beta
        np.testing.assert_allclose(b2 @ v[f[g]], p * S, atol=1e-12)


def test_asymmetric_meshes_return_none_with_a_reason(synthetic_model):
    v = np.asarray(synthetic_model.v_template).copy()
    f = np.asarray(synthetic_model.faces)
    size = np.linalg.norm(v.max(0) - v.min(0))
    v[100, 0] += 0.01 * size
    m, reason = mirror_correspondence(v, f)
    assert m is None
    assert "no mirror partner" in reason and "vertex" in reason
    # a one-sided mesh (only x > 0) has no partners at all
    keep = np.nonzero(v[:, 0] > 0.01)[0]
    m, reason = mirror_correspondence(v[keep], np.zeros((0, 3), dtype=np.int64))
    assert m is None and reason
    m, reason = mirror_correspondence(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    assert m is None and "non-empty" in reason
