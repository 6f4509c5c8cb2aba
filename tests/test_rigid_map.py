"""The rigid head map (sage_core.geometry.rigid): round trips, rays, the 4x4 form, and agreement with
FLAME posing of a frame that differs from canonical only in global rotation and translation."""

from __future__ import annotations

import numpy as np
import torch

from sage_core.flame import FlameModel, FlameModelData
from sage_core.geometry.rigid import (
    canonical_to_world,
    rays_canonical_to_world,
    rays_world_to_canonical,
    rigid_from_flame,
    world_from_canonical_matrix,
    world_to_canonical,
)

EXACT = "donot_use_mm_for_euclid_dist"


def _rigid(seed: int = 0, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    w = 0.7 * torch.randn(3, generator=g, dtype=dtype)
    zero = torch.zeros((), dtype=dtype)
    skew = torch.stack([zero, -w[2], w[1], w[2], zero, -w[0], -w[1], w[0], zero]).reshape(3, 3)
    R0 = torch.linalg.matrix_exp(skew)  # orthonormal to rounding (FLAME's Rodrigues adds a small eps)
    return R0, 0.1 * torch.randn(3, generator=g, dtype=dtype), 0.05 * torch.randn(3, generator=g, dtype=dtype)


def test_points_round_trip_and_fixed_root_joint():
    R0, t, J0 = _rigid()
    x = torch.randn(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(10))
    w = canonical_to_world(x, R0, t, J0)
    assert torch.allclose(world_to_canonical(w, R0, t, J0), x, atol=1e-12)
    assert torch.allclose(canonical_to_world(world_to_canonical(x, R0, t, J0), R0, t, J0), x, atol=1e-12)
    # the root joint only translates; distances are preserved
    assert torch.allclose(canonical_to_world(J0[None], R0, t, J0)[0], J0 + t, atol=1e-12)
    assert torch.allclose(torch.cdist(w, w, compute_mode=EXACT), torch.cdist(x, x, compute_mode=EXACT), atol=1e-12)
    # not the identity (the test would pass for a no-op map otherwise)
    assert float((w - x).norm(dim=-1).min()) > 1e-3


def test_batched_points_match_row_by_row():
    R0, t, J0 = _rigid(1)
    x = torch.randn(4, 5, 3, dtype=torch.float64)
    w = canonical_to_world(x, R0, t, J0)
    for i in range(4):
        assert torch.allclose(w[i], canonical_to_world(x[i], R0, t, J0), atol=1e-14)


def test_rays_round_trip_and_preserve_distances():
    R0, t, J0 = _rigid(2)
    o = torch.randn(30, 3, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(30, 3, dtype=torch.float64), dim=-1)
    o_c, d_c = rays_world_to_canonical(o, d, R0, t, J0)
    assert torch.allclose(d_c.norm(dim=-1), torch.ones(30, dtype=torch.float64), atol=1e-12)
    s = torch.rand(30, 1, dtype=torch.float64) * 3
    # a point along the world ray maps to the same distance along the canonical ray
    assert torch.allclose(world_to_canonical(o + s * d, R0, t, J0), o_c + s * d_c, atol=1e-12)
    o_w, d_w = rays_canonical_to_world(o_c, d_c, R0, t, J0)
    assert torch.allclose(o_w, o, atol=1e-12) and torch.allclose(d_w, d, atol=1e-12)


def test_matrix_form_agrees_with_the_point_map():
    R0, t, J0 = _rigid(3)
    M = world_from_canonical_matrix(R0, t, J0)
    x = torch.randn(20, 3, dtype=torch.float64)
    xh = torch.cat([x, torch.ones(20, 1, dtype=torch.float64)], -1)
    assert torch.allclose((xh @ M.T)[:, :3], canonical_to_world(x, R0, t, J0), atol=1e-12)
    assert torch.allclose(M[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64))
    Minv = torch.linalg.inv(M)
    assert torch.allclose((xh @ Minv.T)[:, :3], world_to_canonical(x, R0, t, J0), atol=1e-12)


def test_gradients_flow_through_the_map():
    R0, t, J0 = _rigid(4)
    x = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    canonical_to_world(x, R0, t, J0).sum().backward()
    assert x.grad is not None
    assert torch.allclose(x.grad, R0.sum(0).expand(6, 3), atol=1e-12)


def _flame_model(V: int = 40, seed: int = 0) -> FlameModelData:
    """A small random model with FLAME's joint tree (root, neck, jaw, two eyes)."""
    rng = np.random.default_rng(seed)
    parents = np.array([-1, 0, 1, 1, 1], np.int64)
    J = len(parents)
    w = rng.random((V, J)) ** 2
    reg = rng.random((J, V))
    return FlameModelData(
        v_template=rng.normal(size=(V, 3)) * 0.1,
        faces=rng.integers(0, V, size=(V, 3)),
        shapedirs=rng.normal(size=(V, 3, 6)) * 0.01,
        exprdirs=rng.normal(size=(V, 3, 7)) * 0.01,
        posedirs=rng.normal(size=(V, 3, 9 * (J - 1))) * 0.01,
        j_regressor=reg / reg.sum(1, keepdims=True),
        lbs_weights=w / w.sum(1, keepdims=True),
        parents=parents,
        n_base_vertices=V,
    )


def test_agrees_with_flame_posing_of_a_rigid_only_pose():
    model = FlameModel(_flame_model()).double()
    g = torch.Generator().manual_seed(5)

    def r(*shape: int, s: float = 0.2) -> torch.Tensor:
        return s * torch.randn(*shape, generator=g, dtype=torch.float64)

    # canonical: a non-trivial expression, jaw, eyes and neck pose; zero global rotation/translation
    common = {"shape": r(1, 6), "expr": r(1, 7), "neck_pose": r(1, 3), "jaw_pose": r(1, 3), "eyes_pose": r(1, 6)}
    zero = torch.zeros(1, 3, dtype=torch.float64)
    canon = model(**common, rotation=zero, translation=zero)
    rotation, translation = r(1, 3, s=0.5), r(1, 3, s=0.1)
    frame = model(**common, rotation=rotation, translation=translation)
    R0, t = rigid_from_flame(rotation, translation)
    J0 = canon.joints[0, 0]
    v_c, v_w = canon.vertices[0], frame.vertices[0]
    assert float((v_w - v_c).norm(dim=-1).max()) > 1e-2  # the frame really moved
    assert torch.allclose(canonical_to_world(v_c, R0, t, J0), v_w, atol=1e-10)
    assert torch.allclose(world_to_canonical(v_w, R0, t, J0), v_c, atol=1e-10)
    # every joint follows the same map
    assert torch.allclose(canonical_to_world(canon.joints[0], R0, t, J0), frame.joints[0], atol=1e-10)
    # a non-rigid change (another jaw pose) is not explained by the map
    other = model(**{**common, "jaw_pose": common["jaw_pose"] + 0.3}, rotation=rotation, translation=translation)
    assert float((canonical_to_world(v_c, R0, t, J0) - other.vertices[0]).norm(dim=-1).max()) > 1e-4
