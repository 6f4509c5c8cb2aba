"""Quaternion / matrix / axis-angle conversions."""

from __future__ import annotations

import math

import torch

from sage_core.geometry.rotations import (
    axis_angle_to_matrix,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
)


def _rand_quats(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return quat_normalize(torch.randn(n, 4, generator=g, dtype=torch.float64))


def test_quat_matrix_round_trip_all_angles():
    q = _rand_quats(2000)
    R = quat_to_matrix(q)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(R @ R.transpose(-1, -2), eye.expand_as(R), atol=1e-12)
    assert torch.allclose(torch.det(R), torch.ones(2000, dtype=torch.float64), atol=1e-12)
    q2 = matrix_to_quat(R)
    assert torch.allclose(quat_to_matrix(q2), R, atol=1e-12)
    assert (q2[:, 0] >= 0).all()
    # near-180-degree rotations (trace ~ -1) take the other branches
    pi_rot = axis_angle_to_matrix(torch.tensor([[math.pi - 1e-9, 0, 0], [0, math.pi, 0], [0, 0, math.pi]], dtype=torch.float64), eps=0)
    assert torch.allclose(quat_to_matrix(matrix_to_quat(pi_rot)), pi_rot, atol=1e-7)


def test_hamilton_product_composes_rotations():
    a, b = _rand_quats(50, 1), _rand_quats(50, 2)
    assert torch.allclose(quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b), atol=1e-12)
    ident = quat_multiply(a, quat_conjugate(a))
    assert torch.allclose(ident, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand_as(ident), atol=1e-12)


def test_axis_angle_round_trip_and_known_rotation():
    g = torch.Generator().manual_seed(3)
    aa = torch.randn(500, 3, generator=g, dtype=torch.float64)
    aa = aa / aa.norm(dim=-1, keepdim=True) * torch.rand(500, 1, generator=g, dtype=torch.float64) * 3.1
    assert torch.allclose(matrix_to_axis_angle(axis_angle_to_matrix(aa, eps=0)), aa, atol=1e-9)
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64), eps=0)
    assert torch.allclose(R @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)


def test_rodrigues_gradient_finite_at_zero():
    aa = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()
