"""Initial surfel distribution over the canonical triangles: counts, region and camera weighting,
determinism, placement on the triangles and initial scales."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from sage_core.avatar.binding import point_triangle_distance
from sage_core.avatar.init import (
    REGION_EYES,
    REGION_FACE,
    REGION_HAIR,
    REGION_MOUTH,
    REGION_NAMES,
    REGION_NECK,
    REGION_OTHER,
    face_region_labels,
    init_surfels,
)
from sage_core.avatar.surfels import SurfelSet
from sage_core.data.cameras import Camera, look_at
from sage_core.flame import Regions, surfel_frames
from sage_core.geometry.rotations import axis_angle_to_matrix, quat_to_matrix

DT = torch.float64


def _sphere() -> tuple[torch.Tensor, torch.Tensor]:
    m = trimesh.creation.icosphere(subdivisions=3)
    return torch.tensor(m.vertices, dtype=DT), torch.tensor(m.faces, dtype=torch.long)


def _regions(V: torch.Tensor, F: torch.Tensor) -> Regions:
    v = V.numpy()
    masks = {
        "face": np.nonzero(v[:, 2] > 0.2)[0],
        "scalp": np.nonzero(v[:, 1] > 0.3)[0],
        "neck": np.nonzero(v[:, 1] < -0.8)[0],
    }
    return Regions(masks, F.numpy(), V.shape[0])


def _areas(V: torch.Tensor, F: torch.Tensor) -> np.ndarray:
    t = V[F]
    return (0.5 * torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], dim=-1).norm(dim=-1)).numpy()


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _camera(eye: np.ndarray, target: np.ndarray = np.zeros(3)) -> Camera:
    K = np.array([[300.0, 0.0, 100.0], [0.0, 300.0, 100.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, w2c=look_at(np.asarray(eye, float), target), width=200, height=200)


def _density(init, labels: np.ndarray, area: np.ndarray, label: int) -> float:
    counts = np.bincount(init.binding.numpy(), minlength=labels.shape[0])
    m = labels == label
    return counts[m].sum() / area[m].sum()


def test_counts_bindings_and_summary():
    V, F = _sphere()
    init = init_surfels(V, F, 5000, _regions(V, F), generator=_gen(0), dtype=DT)
    N = 5000
    assert init.binding.shape == (N,) and init.binding.dtype == torch.long
    assert init.mu_loc.shape == (N, 3) and init.q_loc.shape == (N, 4) and init.s_loc.shape == (N, 2)
    assert init.binding.min() >= 0 and init.binding.max() < F.shape[0]
    assert torch.all(init.binding[1:] >= init.binding[:-1])
    s = init.summary
    assert s["n_surfels"] == N and sum(r["surfels"] for r in s["regions"].values()) == N
    assert sum(r["faces"] for r in s["regions"].values()) == F.shape[0]
    assert set(s["regions"]) <= set(REGION_NAMES) and {"face", "hair", "neck", "other"} <= set(s["regions"])
    assert torch.equal(init.region_id, init.face_region[init.binding])
    assert init.mu_loc.dtype == DT and init.face_region.shape == (F.shape[0],)


def test_region_weighting():
    V, F = _sphere()
    regions = _regions(V, F)
    labels = face_region_labels(regions, F.shape[0])
    area = _areas(V, F)
    init = init_surfels(V, F, 20000, regions, generator=_gen(1), face_weight=3.0, hair_weight=0.5,
                        neck_weight=0.5, dtype=DT)
    face = _density(init, labels, area, REGION_FACE)
    hair = _density(init, labels, area, REGION_HAIR)
    other = _density(init, labels, area, REGION_OTHER)
    neck = _density(init, labels, area, REGION_NECK)
    assert 4.5 < face / hair < 7.5  # expected 6
    assert 2.4 < face / other < 3.6  # expected 3
    assert neck < other
    # without region weights the density is uniform per unit area
    flat = init_surfels(V, F, 20000, None, generator=_gen(1), dtype=DT)
    r = _density(flat, labels, area, REGION_FACE) / _density(flat, labels, area, REGION_HAIR)
    assert 0.85 < r < 1.15
    # a zero weight removes a region
    none = init_surfels(V, F, 3000, regions, generator=_gen(2), hair_weight=0.0, dtype=DT)
    assert not (none.region_id == REGION_HAIR).any()


def test_camera_weighting_prefers_faces_seen_up_close():
    V, F = _sphere()
    R, T, _ = surfel_frames(V, F)
    n = R[:, :, 2]
    area = _areas(V, F)
    cams = [_camera(np.array([0.0, 0.0, 4.0]))]
    init = init_surfels(V, F, 20000, None, cams, camera_weight=4.0, generator=_gen(3), dtype=DT)
    counts = np.bincount(init.binding.numpy(), minlength=F.shape[0])
    front = (n[:, 2] > 0.8).numpy()
    back = (n[:, 2] < -0.2).numpy()
    d_front = counts[front].sum() / area[front].sum()
    d_back = counts[back].sum() / area[back].sum()
    assert d_front > 3.0 * d_back
    # the weight grows with cos(normal, view direction) on the seen side
    w = init.face_weight / area
    tilted = ((n[:, 2] > 0.3) & (n[:, 2] < 0.5)).numpy()
    assert w[front].mean() > w[tilted].mean() > w[back].mean()
    assert np.allclose(w[back], 1.0)  # unseen faces keep the base weight
    # a nearer camera weighs more than a farther one looking at the opposite side
    cams2 = [_camera(np.array([0.0, 0.0, 3.0])), _camera(np.array([0.0, 0.0, -9.0]))]
    w2 = init_surfels(V, F, 100, None, cams2, generator=_gen(3), dtype=DT).face_weight / area
    neg = (n[:, 2] < -0.8).numpy()
    assert w2[front].mean() > w2[neg].mean() > 1.0


def test_world_from_mesh_transforms_the_view_term():
    V, F = _sphere()
    cams = [_camera(np.array([0.5, 0.2, 3.0]))]
    base = init_surfels(V, F, 100, None, cams, generator=_gen(4), dtype=DT).face_weight
    Rot = axis_angle_to_matrix(torch.tensor([0.2, 1.0, -0.4], dtype=DT))
    t = torch.tensor([0.3, -0.1, 0.2], dtype=DT)
    M = np.eye(4)
    M[:3, :3] = Rot.numpy()
    M[:3, 3] = t.numpy()
    V_mesh = (V - t) @ Rot  # world = Rot·mesh + t
    moved = init_surfels(V_mesh, F, 100, None, cams, world_from_mesh=M, generator=_gen(4), dtype=DT).face_weight
    assert np.allclose(moved, base, rtol=1e-9)
    unmoved = init_surfels(V_mesh, F, 100, None, cams, generator=_gen(4), dtype=DT).face_weight
    assert not np.allclose(unmoved, base, rtol=1e-3)


def test_determinism():
    V, F = _sphere()
    regions = _regions(V, F)
    cams = [_camera(np.array([0.0, 0.5, 4.0]))]
    a = init_surfels(V, F, 3000, regions, cams, random_rotation=True, generator=_gen(5))
    b = init_surfels(V, F, 3000, regions, cams, random_rotation=True, generator=_gen(5))
    c = init_surfels(V, F, 3000, regions, cams, random_rotation=True, generator=_gen(6))
    for name in ("binding", "mu_loc", "q_loc", "s_loc", "region_id"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert not torch.equal(a.binding, c.binding)
    assert not torch.equal(a.mu_loc, c.mu_loc)
    assert a.mu_loc.dtype == torch.float32


@pytest.mark.parametrize("random_rotation", [False, True])
def test_surfels_lie_flat_on_their_triangles(random_rotation):
    V, F = _sphere()
    init = init_surfels(V, F, 4000, _regions(V, F), generator=_gen(7), random_rotation=random_rotation, dtype=DT)
    S = SurfelSet.from_init(init)
    R, T, k = surfel_frames(V, F)
    means, quats, scales = S.pose(R, T, k)
    tri = V[F[init.binding]]
    d = point_triangle_distance(means, tri[:, 0], tri[:, 1], tri[:, 2])
    assert d.max() < 1e-12  # on the triangle (inside it, not merely on its plane)
    rot = quat_to_matrix(quats)
    assert torch.allclose(rot[:, :, 2], R[init.binding][:, :, 2], atol=1e-12)  # flat
    assert torch.allclose(init.mu_loc[:, 2], torch.zeros(4000, dtype=DT))
    if random_rotation:
        angle = torch.atan2(init.q_loc[:, 3], init.q_loc[:, 0]) * 2
        assert angle.std() > 1.0  # spread over the circle
    else:
        assert torch.equal(init.q_loc, torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=DT).expand(4000, 4))


def test_positions_uniform_within_a_triangle():
    V = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=DT)
    F = torch.tensor([[0, 1, 2]])
    init = init_surfels(V, F, 20000, None, generator=_gen(8), dtype=DT)
    S = SurfelSet.from_init(init)
    means = S.canonical_positions(*surfel_frames(V, F)).detach()
    assert torch.allclose(means.mean(0), V.mean(0), atol=0.01)
    assert (means[:, 0] >= -1e-12).all() and (means[:, 1] >= -1e-12).all()
    assert (means[:, 0] + means[:, 1] / 2 <= 1 + 1e-12).all()
    # the fraction in the sub-triangle near vertex 0 scaled by 1/2 is 1/4
    near0 = (means[:, 0] + means[:, 1] / 2 < 0.5).double().mean()
    assert abs(float(near0) - 0.25) < 0.015


def test_initial_scales_cover_the_triangle():
    V, F = _sphere()
    init = init_surfels(V, F, 6000, None, generator=_gen(9), dtype=DT)
    _, _, k = surfel_frames(V, F)
    area = torch.tensor(_areas(V, F), dtype=DT)
    counts = torch.bincount(init.binding, minlength=F.shape[0]).to(DT)
    b = init.binding
    s = k[b, None] * torch.exp(init.s_loc)
    expected = torch.sqrt(area[b] / (math.pi * counts[b]))
    assert torch.allclose(s, expected[:, None].expand(-1, 2), rtol=1e-10)
    # n_f disks of radius s cover the triangle's area
    covered = torch.zeros(F.shape[0], dtype=DT).index_add_(0, b, math.pi * s[:, 0] ** 2)
    used = counts > 0
    assert torch.allclose(covered[used], area[used], rtol=1e-10)
    # the clamp bounds s/k
    tight = init_surfels(V, F, 6000, None, generator=_gen(9), scale_range=(0.3, 0.35), dtype=DT)
    assert tight.s_loc.min() >= math.log(0.3) - 1e-12 and tight.s_loc.max() <= math.log(0.35) + 1e-12


def test_min_per_face_and_errors():
    V, F = _sphere()
    init = init_surfels(V, F, 2 * F.shape[0] + 100, None, min_per_face=2, generator=_gen(10))
    assert torch.bincount(init.binding, minlength=F.shape[0]).min() >= 2
    assert init.summary["faces_used"] == F.shape[0]
    with pytest.raises(ValueError):
        init_surfels(V, F, F.shape[0] - 1, None, min_per_face=1, generator=_gen(10))
    with pytest.raises(ValueError):
        init_surfels(V, F, 0, None)
    with pytest.raises(ValueError):
        init_surfels(V, F, 10, None, face_weight=-1.0)
    regions = _regions(V, F)
    with pytest.raises(ValueError):
        init_surfels(V, F[:-1], 10, regions)  # regions describe another mesh
    flat = torch.zeros_like(V)
    with pytest.raises(ValueError):
        init_surfels(flat, F, 10, None)  # every triangle degenerate


@pytest.fixture(scope="module")
def synthetic_head():
    from sage_core.data.synthetic import build_head, flame_model_data
    from sage_core.flame import add_mouth_interior

    head = build_head(24, 32, 4, 8)
    data = add_mouth_interior(flame_model_data(head), head.masks)
    regions = Regions(head.masks, data.faces, data.v_template.shape[0], data.vertex_groups)
    return torch.tensor(data.v_template, dtype=DT), torch.tensor(data.faces, dtype=torch.long), regions


def test_synthetic_head_labels_and_density(synthetic_head):
    V, F, regions = synthetic_head
    labels = face_region_labels(regions, F.shape[0])
    for label in (REGION_FACE, REGION_EYES, REGION_MOUTH, REGION_HAIR, REGION_NECK):
        assert (labels == label).any(), REGION_NAMES[label]
    assert (labels[regions.face_ids("mouth_interior")] == REGION_MOUTH).all()
    assert (labels[regions.face_ids("teeth")] == REGION_MOUTH).all()
    assert (labels[regions.face_ids("eyeballs")] == REGION_EYES).all()
    cams = [_camera(np.array([x, 0.0, 0.6]), np.zeros(3)) for x in (-0.3, 0.0, 0.3)]
    init = init_surfels(V, F, 8000, regions, cams, generator=_gen(11), dtype=DT)
    area = _areas(V, F)
    face = _density(init, labels, area, REGION_FACE)
    assert face > 3 * _density(init, labels, area, REGION_HAIR)
    assert face > 2 * _density(init, labels, area, REGION_NECK)
    assert init.summary["regions"]["mouth"]["surfels"] > 0
