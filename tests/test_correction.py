"""Neighbour sets and the stretch/curvature surfel correction."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sage_core.avatar.correction import SurfelCorrection, affine_frames, principal_stretches
from sage_core.avatar.neighbours import surfel_neighbours, triangle_centroids, triangle_neighbours
from sage_core.flame.frames import surfel_frames, triangle_frames
from sage_core.geometry.rotations import axis_angle_to_matrix, matrix_to_quat, quat_multiply, quat_to_matrix

DT = torch.float64


def _grid(n: int = 9, h: float = 0.01):
    """Planar (z = 0) grid mesh, counter-clockwise seen from +z, centred at the origin."""
    xs = (torch.arange(n, dtype=DT) - (n - 1) / 2) * h
    yy, xx = torch.meshgrid(xs, xs, indexing="ij")
    verts = torch.stack([xx, yy, torch.zeros_like(xx)], -1).reshape(-1, 3)
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = torch.cat([torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


def _interior(verts, faces, margin: float):
    c = verts[faces].mean(1)
    lim = verts[:, 0].max() - margin
    return ((c[:, 0].abs() < lim) & (c[:, 1].abs() < lim)).nonzero().squeeze(-1)


def _surfels(verts, faces, binding, spin: torch.Tensor | None = None):
    """Canonical surfel rotations lying flat on their triangles, optionally turned about the normal."""
    R, _, _ = surfel_frames(verts, faces)
    q = matrix_to_quat(R[binding])
    if spin is not None:
        dz = torch.stack([torch.cos(spin / 2), 0 * spin, 0 * spin, torch.sin(spin / 2)], -1)
        q = quat_multiply(q, dz)
    return q


def _setup(canonical, faces, radius=0.025, **kw):
    corr = SurfelCorrection.from_mesh(canonical, faces, radius=radius, max_neighbours=24, **kw)
    binding = _interior(canonical, faces, margin=radius + 0.001)
    return corr, binding


# ---------------------------------------------------------------- neighbours


def test_triangle_neighbours_match_brute_force():
    g = np.random.default_rng(0)
    verts = torch.as_tensor(g.normal(size=(60, 3)) * 0.05)
    faces = torch.as_tensor(g.integers(0, 60, size=(80, 3)))
    radius, K = 0.04, 5
    idx, count = triangle_neighbours(verts, faces, radius, K)
    assert idx.shape == (80, K) and idx.dtype == torch.long and count.shape == (80,)
    c = triangle_centroids(verts, faces)
    D = np.linalg.norm(c[:, None] - c[None], axis=-1)
    for q in range(80):
        cand = [j for j in np.argsort(D[q], kind="stable") if j != q and D[q, j] <= radius]
        n = min(len(cand), K)
        assert int(count[q]) == n
        got = idx[q, :n].tolist()
        assert sorted(got) == sorted(cand[:n]) or np.allclose(sorted(D[q, got]), sorted(D[q, cand[:n]]))
        assert q not in got
        assert torch.all(idx[q, n:] == -1)
        assert np.all(np.diff(D[q, got]) >= -1e-12)  # nearest first
    assert count.max() == K and count.min() < K
    binding = torch.tensor([3, 3, 70])
    s_idx, s_count = surfel_neighbours(idx, count, binding)
    assert torch.equal(s_idx, idx[binding]) and torch.equal(s_count, count[binding])
    # more slots than triangles: everything within reach, rest padded
    idx_all, count_all = triangle_neighbours(verts[:9], torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]]), 10.0, 6)
    assert idx_all.shape == (3, 6) and torch.all(count_all == 2) and torch.all(idx_all[:, 2:] == -1)


# ---------------------------------------------------------------- stretch


@pytest.mark.parametrize("s", [0.7, 1.6])
def test_uniform_scale_gives_isotropic_stretch(s):
    verts, faces = _grid()
    corr, binding = _setup(verts, faces)
    Q = axis_angle_to_matrix(torch.tensor([0.4, -0.3, 0.9], dtype=DT))
    posed = s * verts @ Q.T + torch.tensor([0.1, 0.2, -0.3], dtype=DT)
    spin = torch.linspace(-1.0, 1.0, binding.numel(), dtype=DT)
    rot = _surfels(verts, faces, binding, spin)
    out = corr(posed, binding, rot, torch.tensor([0.0, 0.0, 1.0], dtype=DT).expand(binding.numel(), 3))
    assert out.valid.all()
    assert torch.allclose(out.principal_stretch, torch.full_like(out.principal_stretch, s), atol=1e-9)
    # the binding already scales by s: nothing is left to correct
    assert torch.allclose(out.stretch, torch.ones_like(out.stretch), atol=1e-9)
    assert torch.allclose(out.scale_factor, torch.ones_like(out.scale_factor), atol=1e-9)
    assert torch.allclose(out.quat, torch.tensor([1.0, 0, 0, 0], dtype=DT).expand_as(out.quat))


def test_rigid_motion_changes_nothing_beyond_the_rigid_one():
    verts, faces = _grid()
    corr, binding = _setup(verts, faces)
    N = binding.numel()
    Q = axis_angle_to_matrix(torch.tensor([-0.7, 0.2, 0.5], dtype=DT))
    posed = verts @ Q.T + torch.tensor([0.0, 0.05, 0.0], dtype=DT)
    rot = _surfels(verts, faces, binding)
    R = quat_to_matrix(rot)
    # curvature directions along the surfel axes, clearly anisotropic: the surfels are already aligned
    dirs = torch.stack([R[..., 0], R[..., 1]], -2)
    kappa = torch.tensor([30.0, 5.0], dtype=DT).expand(N, 2)
    out = corr(posed, binding, rot, R[..., 2], kappa, dirs)
    assert torch.allclose(out.principal_stretch, torch.ones_like(out.principal_stretch), atol=1e-9)
    assert torch.allclose(out.stretch, torch.ones_like(out.stretch), atol=1e-9)
    assert torch.allclose(out.quat, torch.tensor([1.0, 0, 0, 0], dtype=DT).expand_as(out.quat), atol=1e-12)
    # posed rotation = rigid rotation ⊗ canonical rotation, unchanged by the correction
    q_posed = quat_multiply(matrix_to_quat(Q).expand(N, 4), rot)
    q_new, _ = SurfelCorrection.apply(out, q_posed, torch.ones(N, 2, dtype=DT))
    assert torch.allclose(quat_to_matrix(q_new), Q @ R, atol=1e-12)


@pytest.mark.parametrize("tilt", [False, True])
def test_anisotropic_stretch_along_a_tangent_axis(tilt):
    s = 1.5
    verts, faces = _grid(11)
    stretch = torch.diag(torch.tensor([s, 1.0, 1.0], dtype=DT))
    canon, posed = verts, verts @ stretch.T
    B = torch.eye(3, dtype=DT)
    if tilt:  # the same experiment on a plane in general position
        B = axis_angle_to_matrix(torch.tensor([0.5, 0.8, -0.2], dtype=DT))
        canon, posed = verts @ B.T, posed @ B.T
    corr, binding = _setup(canon, faces)
    N = binding.numel()
    normal = B[:, 2].expand(N, 3)
    _, _, k_c = triangle_frames(canon, faces)
    _, _, k_d = triangle_frames(posed, faces)
    r = (k_d / k_c)[binding].unsqueeze(-1)  # the binding's own uniform scaling of each triangle
    # surfels whose first axis is the stretch axis ...
    rot = matrix_to_quat(B).expand(N, 4)
    out = corr(posed, binding, rot, normal)
    assert torch.allclose(out.principal_stretch, torch.tensor([s, 1.0], dtype=DT).expand(N, 2), atol=1e-9)
    assert torch.allclose(out.stretch * r, torch.tensor([s, 1.0], dtype=DT).expand(N, 2), atol=1e-9)
    assert torch.allclose(out.scale_factor * r, torch.tensor([s, 1.0], dtype=DT).expand(N, 2), atol=1e-9)
    assert (r - 1).abs().max() > 0.05  # the binding alone would have got it wrong
    # ... and surfels turned 30° in the plane: same principal stretches, per-axis stretch by the ellipse
    a = math.radians(30.0)
    rot30 = quat_multiply(rot, torch.tensor([math.cos(a / 2), 0, 0, math.sin(a / 2)], dtype=DT).expand(N, 4))
    out30 = corr(posed, binding, rot30, normal)
    assert torch.allclose(out30.principal_stretch, out.principal_stretch, atol=1e-9)
    expect = torch.tensor([math.hypot(s * math.cos(a), math.sin(a)), math.hypot(s * math.sin(a), math.cos(a))], dtype=DT)
    assert torch.allclose(out30.stretch * r, expect.expand(N, 2), atol=1e-9)


def test_principal_stretches_closed_form():
    g = torch.Generator().manual_seed(0)
    G = torch.randn(20, 2, 2, generator=g, dtype=DT)
    sigma, dirs = principal_stretches(G)
    sv = torch.linalg.svdvals(G)
    assert torch.allclose(sigma, sv, atol=1e-8)
    stretched = (G @ dirs).norm(dim=-2)
    assert torch.allclose(stretched, sigma, atol=1e-8)


# ---------------------------------------------------------------- rotation and curvature


def test_correction_keeps_the_normal_and_aligns_with_principal_directions():
    verts, faces = _grid()
    corr, binding = _setup(verts, faces, umbilic_tol=0.0)
    N = binding.numel()
    g = torch.Generator().manual_seed(3)
    spin = (torch.rand(N, generator=g, dtype=DT) - 0.5) * 2 * math.pi
    rot = _surfels(verts, faces, binding, spin)
    R = quat_to_matrix(rot)
    n = R[..., 2]
    beta = (torch.rand(N, generator=g, dtype=DT) - 0.5) * 2 * math.pi
    d1 = torch.stack([torch.cos(beta), torch.sin(beta), 0 * beta], -1)
    d2 = torch.linalg.cross(n, d1, dim=-1)
    kappa = torch.stack([torch.full((N,), 40.0, dtype=DT), torch.full((N,), -10.0, dtype=DT)], -1)
    out = corr(verts, binding, rot, n, kappa, torch.stack([d1, d2], -2))
    assert out.angle.abs().max() <= math.pi / 4 + 1e-12
    q_new, _ = SurfelCorrection.apply(out, rot, torch.ones(N, 2, dtype=DT))
    R_new = quat_to_matrix(q_new)
    assert torch.allclose(R_new[..., 2], R[..., 2], atol=1e-12)
    t1 = R_new[..., 0]
    align = torch.maximum((t1 * d1).sum(-1).abs(), (t1 * d2).sum(-1).abs())
    assert torch.allclose(align, torch.ones_like(align), atol=1e-10)
    # the axis aligned with d1 gets κ1's damping, the other κ2's (rest pose: stretch 1)
    on_d1 = (t1 * d1).sum(-1).abs() > 0.5
    w = corr.w_s
    a, b = torch.tensor(1 / (1 + w * 40.0), dtype=DT), torch.tensor(1 / (1 + w * 10.0), dtype=DT)
    f1, f2 = torch.where(on_d1, a, b), torch.where(on_d1, b, a)
    assert torch.allclose(out.scale_factor, torch.stack([f1, f2], -1), atol=1e-10)
    # a direction and its opposite give the same correction
    out_neg = corr(verts, binding, rot, -n, kappa, torch.stack([-d1, d2], -2))
    assert torch.allclose(out_neg.quat, out.quat, atol=1e-12)


def test_curvature_damping():
    verts, faces = _grid()
    corr, binding = _setup(verts, faces, w_s=0.002)
    N = binding.numel()
    rot = _surfels(verts, faces, binding)
    R = quat_to_matrix(rot)
    dirs = torch.stack([R[..., 0], R[..., 1]], -2)
    flat = corr(verts, binding, rot, R[..., 2], torch.zeros(N, 2, dtype=DT), dirs)
    assert torch.allclose(flat.scale_factor, torch.ones(N, 2, dtype=DT), atol=1e-12)
    kappa = torch.tensor([500.0, -200.0], dtype=DT).expand(N, 2)
    curved = corr(verts, binding, rot, R[..., 2], kappa, dirs)
    expect = torch.tensor([1 / (1 + 0.002 * 500.0), 1 / (1 + 0.002 * 200.0)], dtype=DT)
    assert torch.allclose(curved.scale_factor, expect.expand(N, 2), atol=1e-12)
    _, s_new = SurfelCorrection.apply(curved, rot, torch.full((N, 3), 0.003, dtype=DT))
    assert torch.allclose(s_new[:, :2], 0.003 * expect.expand(N, 2)) and torch.all(s_new[:, 2] == 0.003)


def test_hair_and_isolated_surfels_are_untouched_and_off_switch():
    verts, faces = _grid()
    far = torch.tensor([[1.0, 1.0, 0.0], [1.01, 1.0, 0.0], [1.0, 1.01, 0.0]], dtype=DT)
    verts2 = torch.cat([verts, far])
    faces2 = torch.cat([faces, torch.tensor([[0, 1, 2]]) + verts.shape[0]])
    corr, binding = _setup(verts2, faces2)
    lone = faces2.shape[0] - 1
    binding = torch.cat([binding[:6], torch.tensor([lone])])
    N = binding.numel()
    assert not bool(corr.triangle_valid()[lone])
    posed = verts2 * torch.tensor([1.4, 1.0, 1.0], dtype=DT)
    rot = _surfels(verts2, faces2, binding, torch.full((N,), 0.3, dtype=DT))
    R = quat_to_matrix(rot)
    d1 = torch.tensor([1.0, 0.0, 0.0], dtype=DT).expand(N, 3)
    dirs = torch.stack([d1, torch.linalg.cross(R[..., 2], d1, dim=-1)], -2)
    kappa = torch.tensor([50.0, 0.0], dtype=DT).expand(N, 2)
    hair = torch.zeros(N, dtype=torch.bool)
    hair[:3] = True
    out = corr(posed, binding, rot, R[..., 2], kappa, dirs, hair=hair)
    untouched = hair.clone()
    untouched[-1] = True
    assert torch.equal(out.valid, ~untouched)
    assert torch.all(out.quat[untouched] == torch.tensor([1.0, 0, 0, 0], dtype=DT))
    assert torch.all(out.scale_factor[untouched] == 1.0)
    assert not torch.allclose(out.scale_factor[~untouched], torch.ones(int((~untouched).sum()), 2, dtype=DT))
    assert not torch.allclose(out.quat[~untouched][:, 0], torch.ones(int((~untouched).sum()), dtype=DT))
    corr.enabled = False
    off = corr(posed, binding, rot, R[..., 2], kappa, dirs, hair=hair)
    assert torch.all(off.quat == torch.tensor([1.0, 0, 0, 0], dtype=DT)) and torch.all(off.scale_factor == 1.0)


# ---------------------------------------------------------------- batching and gradients


def test_batched_frames_match_single_and_gradients_flow():
    verts, faces = _grid(7)
    corr, binding = _setup(verts, faces, radius=0.02)
    N = binding.numel()
    g = torch.Generator().manual_seed(5)
    posed = verts + 0.002 * torch.randn(2, *verts.shape, generator=g, dtype=DT)
    rot = _surfels(verts, faces, binding, torch.rand(N, generator=g, dtype=DT)).requires_grad_(True)
    R = quat_to_matrix(rot.detach())
    beta = torch.rand(N, generator=g, dtype=DT) * 3
    d1 = torch.stack([torch.cos(beta), torch.sin(beta), 0 * beta], -1)
    dirs = torch.stack([d1, torch.linalg.cross(R[..., 2], d1, dim=-1)], -2)
    kappa = torch.tensor([60.0, 10.0], dtype=DT).expand(N, 2)
    posed.requires_grad_(True)
    both = corr(posed, binding, rot, R[..., 2], kappa, dirs)
    assert both.quat.shape == (2, N, 4) and both.scale_factor.shape == (2, N, 2)
    for b in range(2):
        one = corr(posed[b], binding, rot, R[..., 2], kappa, dirs)
        assert torch.allclose(one.scale_factor, both.scale_factor[b]) and torch.allclose(one.quat, both.quat[b])
    scales = torch.full((2, N, 2), 0.004, dtype=DT, requires_grad=True)
    q_new, s_new = SurfelCorrection.apply(both, rot.expand(2, N, 4), scales)
    (q_new[..., 1:].sum() + s_new.sum()).backward()
    for t in (rot, posed, scales):
        assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0

    def factors(p):
        return corr(p, binding, rot.detach(), R[..., 2], kappa, dirs).scale_factor

    assert torch.autograd.gradcheck(factors, (posed[0].detach().clone().requires_grad_(True),), eps=1e-7, atol=1e-5, fast_mode=True)


def test_affine_frames_deformation_gradient_is_exact_for_affine_maps():
    verts, faces = _grid(5)
    verts = verts + torch.tensor([0, 0, 0.003], dtype=DT) * torch.sin(verts[:, :1] * 300)  # not planar
    A = torch.tensor([[1.2, 0.3, 0.1], [-0.2, 0.9, 0.4], [0.05, 0.1, 1.1]], dtype=DT)
    Ac, _ = affine_frames(verts, faces)
    Ad, _ = affine_frames(verts @ A.T, faces)
    F = Ad @ torch.linalg.inv(Ac)
    e = Ac[..., :2]  # edges
    assert torch.allclose(F @ e, A @ e, atol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    verts, faces = _grid()
    corr, binding = _setup(verts, faces)
    N = binding.numel()
    posed = verts * torch.tensor([1.3, 0.9, 1.0], dtype=DT)
    rot = _surfels(verts, faces, binding, torch.linspace(0, 2, N, dtype=DT))
    R = quat_to_matrix(rot)
    d1 = torch.tensor([0.6, 0.8, 0.0], dtype=DT).expand(N, 3)
    dirs = torch.stack([d1, torch.linalg.cross(R[..., 2], d1, dim=-1)], -2)
    kappa = torch.tensor([80.0, 5.0], dtype=DT).expand(N, 2)
    args = (posed, binding, rot, R[..., 2], kappa, dirs)
    cpu = corr(*args)
    gpu = corr.to("cuda")(*(a.cuda() for a in args))
    assert torch.allclose(gpu.quat.cpu(), cpu.quat, atol=1e-10)
    assert torch.allclose(gpu.scale_factor.cpu(), cpu.scale_factor, atol=1e-10)


def test_anisotropy_gate_keeps_orientation_at_rest_and_turns_under_anisotropic_stretch():
    verts, faces = _grid()
    corr, binding = _setup(verts, faces, umbilic_tol=0.0, anisotropy_tol=0.1)
    N = binding.numel()
    g = torch.Generator().manual_seed(5)
    spin = (torch.rand(N, generator=g, dtype=DT) - 0.5) * 2 * math.pi
    rot = _surfels(verts, faces, binding, spin)
    n = quat_to_matrix(rot)[..., 2]
    d1 = torch.tensor([1.0, 0.0, 0.0], dtype=DT).expand(N, 3)
    dirs = torch.stack([d1, torch.linalg.cross(n, d1, dim=-1)], -2)
    kappa = torch.tensor([40.0, -10.0], dtype=DT).expand(N, 2)
    ungated, _ = _setup(verts, faces, umbilic_tol=0.0)
    full = ungated(verts, binding, rot, n, kappa, dirs)
    assert full.angle.abs().max() > 0.3
    # at rest and under uniform scaling: no turn
    for posed in (verts, 1.5 * verts):
        out = corr(posed, binding, rot, n, kappa, dirs)
        assert float(out.angle.abs().max()) < 1e-8
    # 5 % anisotropy: half the turn; 30 %: the full turn
    for sx, frac in ((1.05, 0.5), (1.3, 1.0)):
        posed = verts * torch.tensor([sx, 1.0, 1.0], dtype=DT)
        out = corr(posed, binding, rot, n, kappa, dirs)
        torch.testing.assert_close(out.angle, frac * full.angle, atol=1e-9, rtol=1e-6)


# ---------------------------------------------------------------- fast paths against their references


def _dense_relative_deformation(corr: SurfelCorrection, posed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The neighbourhood sum as a dense gather over the (F, K+1) table, every triangle (the reference)."""
    posed = posed.to(corr.A_inv.dtype)
    A_d, _ = affine_frames(posed, corr.faces)
    Fj = A_d @ corr.A_inv
    w = corr.weights / corr.weights.sum(1, keepdim=True).clamp_min(1e-30)
    F_bar = (Fj[..., corr.idx, :, :] * w[..., None, None]).sum(-3)
    R_d, _, k_d = triangle_frames(posed, corr.faces)
    Q = R_d @ corr.R_c.transpose(-1, -2)
    r = k_d / corr.k_c.clamp_min(1e-30)
    return Q.transpose(-1, -2) @ F_bar / r[..., None, None].clamp_min(1e-30), r


def _bent(verts: torch.Tensor, seed: int, batch: tuple[int, ...] = ()) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    noise = 0.002 * torch.randn(*batch, *verts.shape, generator=g, dtype=DT).to(verts.dtype)
    posed = verts * torch.tensor([1.3, 0.8, 1.0], dtype=verts.dtype) + noise
    return posed + torch.stack([0 * posed[..., 0], 0 * posed[..., 0], 3.0 * posed[..., 0] ** 2], -1)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_sparse_neighbour_sum_matches_the_dense_gather(dtype):
    """relative_deformation (a sparse CSR product over the neighbourhoods, optionally on a subset of
    triangles) against the dense gather: values within 1e-12 (float64) / 1e-5 (float32) of the
    largest entry, float64 gradients within 1e-10."""
    verts, faces = _grid(8)
    corr = SurfelCorrection.from_mesh(verts.to(dtype), faces, radius=0.025, max_neighbours=24)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for batch in ((), (3,)):
        posed = _bent(verts, 1, batch).to(dtype)
        L_ref, r_ref = _dense_relative_deformation(corr, posed)
        L, r = corr.relative_deformation(posed)
        scale = float(L_ref.abs().max())
        torch.testing.assert_close(L, L_ref, atol=tol * scale, rtol=0)
        torch.testing.assert_close(r, r_ref, atol=tol, rtol=0)
        sub = torch.tensor([5, 0, 17, 17, 60])
        L_sub, r_sub = corr.relative_deformation(posed, sub)
        torch.testing.assert_close(L_sub, L_ref[..., sub, :, :], atol=tol * scale, rtol=0)
        torch.testing.assert_close(r_sub, r_ref[..., sub], atol=tol, rtol=0)
    if dtype == torch.float64:
        posed = _bent(verts, 2).requires_grad_(True)
        w = torch.randn(faces.shape[0], 3, 3, generator=torch.Generator().manual_seed(3), dtype=DT)
        (g_new,) = torch.autograd.grad((corr.relative_deformation(posed)[0] * w).sum(), posed)
        (g_ref,) = torch.autograd.grad((_dense_relative_deformation(corr, posed)[0] * w).sum(), posed)
        torch.testing.assert_close(g_new, g_ref, atol=1e-10 * float(g_ref.abs().max()), rtol=0)


def test_neighbour_matrix_rows_are_the_normalised_weights():
    verts, faces = _grid(6)
    corr = SurfelCorrection.from_mesh(verts, faces, radius=0.025, max_neighbours=24)
    dense = corr.neighbour_matrix().to_dense()
    ref = torch.zeros_like(dense)
    w = corr.weights / corr.weights.sum(1, keepdim=True).clamp_min(1e-30)
    ref.scatter_add_(1, corr.idx, w)
    torch.testing.assert_close(dense, ref, atol=0, rtol=0)
    ok = corr.tri_ok
    torch.testing.assert_close(dense[ok].sum(1), torch.ones(int(ok.sum()), dtype=DT), atol=1e-14, rtol=0)
    sub = torch.tensor([3, 1, 3])
    torch.testing.assert_close(corr.neighbour_matrix(sub).to_dense(), ref[sub], atol=0, rtol=0)


def test_forward_on_bound_triangles_equals_every_triangle_then_gather(monkeypatch):
    """The forward computes the relative deformation of the bound triangles only (remembered per
    binding tensor); the result equals computing every triangle and gathering by the binding, and a
    binding changed in place is seen."""
    verts, faces = _grid(9)
    corr, binding = _setup(verts, faces, anisotropy_tol=0.1)
    binding = binding.repeat_interleave(2)[:-3].clone()  # repeated triangles, not every interior one
    N = binding.numel()
    g = torch.Generator().manual_seed(4)
    rot = _surfels(verts, faces, binding, torch.rand(N, generator=g, dtype=DT))
    R = quat_to_matrix(rot)
    beta = torch.rand(N, generator=g, dtype=DT) * 3
    d1 = torch.stack([torch.cos(beta), torch.sin(beta), 0 * beta], -1)
    dirs = torch.stack([d1, torch.linalg.cross(R[..., 2], d1, dim=-1)], -2)
    kappa = torch.stack([60.0 + 0 * beta, 10.0 * beta], -1)
    posed = _bent(verts, 5)

    def every_triangle(b: torch.Tensor):
        return torch.arange(corr.faces.shape[0]), b, corr.neighbour_matrix()

    def run(b: torch.Tensor):
        return corr(posed, b, rot, R[..., 2], kappa, dirs)

    fast = run(binding)
    assert corr._bound_triangles(binding)[0].numel() < corr.faces.shape[0]
    with monkeypatch.context() as m:
        m.setattr(corr, "_bound_triangles", every_triangle)
        ref = run(binding)
    for name in ("quat", "scale_factor", "stretch", "principal_stretch", "angle"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), atol=1e-13, rtol=0)
    assert torch.equal(fast.valid, ref.valid)
    tri, row, _ = corr._bound_triangles(binding)
    assert corr._bound_triangles(binding)[0] is tri  # remembered
    binding[:5] = binding[-1]  # in place: the remembered triangles no longer apply
    moved = run(binding)
    with monkeypatch.context() as m:
        m.setattr(corr, "_bound_triangles", every_triangle)
        ref2 = run(binding)
    torch.testing.assert_close(moved.scale_factor, ref2.scale_factor, atol=1e-13, rtol=0)
    assert not torch.allclose(moved.scale_factor[:5], fast.scale_factor[:5])


# ---------------------------------------------------------------- affine mode


def _plane_covariance(R: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) covariance R·diag(s1², s2², 0)·Rᵀ of flat surfels with rotations R (N, 3, 3), scales s (N, 2)."""
    d = torch.cat([s**2, torch.zeros_like(s[:, :1])], -1)
    return R @ torch.diag_embed(d) @ R.transpose(-1, -2)


@pytest.mark.parametrize("tilt", [False, True])
def test_affine_mode_maps_each_ellipse_exactly_under_an_affine_deformation(tilt):
    verts, faces = _grid(11)
    A = torch.tensor([[1.4, 0.3, 0.0], [0.0, 0.8, 0.0], [0.0, 0.0, 1.0]], dtype=DT)  # stretch and shear in the plane
    B = torch.eye(3, dtype=DT)
    if tilt:
        B = axis_angle_to_matrix(torch.tensor([0.5, 0.8, -0.2], dtype=DT))
    canon, posed = verts @ B.T, verts @ A.T @ B.T
    corr, binding = _setup(canon, faces, mode="affine")
    N = binding.numel()
    g = torch.Generator().manual_seed(3)
    spin = (torch.rand(N, generator=g, dtype=DT) - 0.5) * 2 * math.pi
    rot = _surfels(canon, faces, binding, spin)
    scales = 0.002 + 0.004 * torch.rand(N, 2, generator=g, dtype=DT)
    out = corr(posed, binding, rot, B[:, 2].expand(N, 3), scales=scales)
    # the binding's posed surfel (similarity of the bound triangle), then the correction
    R_c, _, k_c = triangle_frames(canon, faces)
    R_d, _, k_d = triangle_frames(posed, faces)
    Q = (R_d @ R_c.transpose(-1, -2))[binding]
    r = (k_d / k_c)[binding].unsqueeze(-1)
    q_posed = quat_multiply(matrix_to_quat(Q), rot)
    q_new, s_new = SurfelCorrection.apply(out, q_posed, scales * r)
    got = _plane_covariance(quat_to_matrix(q_new), s_new)
    M = B @ A @ B.T  # the world deformation
    want = M @ _plane_covariance(quat_to_matrix(rot), scales) @ M.T
    torch.testing.assert_close(got, want, atol=1e-12 * float(want.abs().max()) * 1e4, rtol=1e-6)
    assert float(out.angle.abs().max()) <= math.pi / 4 + 1e-12
    # the paper's mode scales the fitted axes and cannot shear an ellipse: it is off here
    paper, _ = _setup(canon, faces)
    q_p, s_p = SurfelCorrection.apply(paper(posed, binding, rot, B[:, 2].expand(N, 3)), q_posed, scales * r)
    assert float((_plane_covariance(quat_to_matrix(q_p), s_p) - want).abs().max()) > 0.05 * float(want.abs().max())


def test_affine_mode_is_the_identity_under_similarities_and_needs_scales():
    verts, faces = _grid()
    corr, binding = _setup(verts, faces, mode="affine", w_s=0.0)
    N = binding.numel()
    g = torch.Generator().manual_seed(9)
    rot = _surfels(verts, faces, binding, (torch.rand(N, generator=g, dtype=DT) - 0.5) * 6)
    scales = 0.001 + 0.004 * torch.rand(N, 2, generator=g, dtype=DT)
    n = quat_to_matrix(rot)[..., 2]
    R = axis_angle_to_matrix(torch.tensor([0.2, -0.4, 0.7], dtype=DT))
    kappa = torch.tensor([40.0, -10.0], dtype=DT).expand(N, 2)
    d1 = torch.tensor([1.0, 0.0, 0.0], dtype=DT).expand(N, 3)
    dirs = torch.stack([d1, torch.linalg.cross(n, d1, dim=-1)], -2)
    for posed in (verts, 1.7 * verts @ R.T + 0.3):
        out = corr(posed, binding, rot, n, kappa, dirs, scales=scales)
        # the ellipse is unchanged (its angle is ill-conditioned only for nearly round surfels)
        c, s_ = torch.cos(out.angle), torch.sin(out.angle)
        U = torch.stack([torch.stack([c, -s_], -1), torch.stack([s_, c], -1)], -2)
        ellipse = U @ torch.diag_embed((out.scale_factor * scales) ** 2) @ U.transpose(-1, -2)
        torch.testing.assert_close(ellipse, torch.diag_embed(scales**2), atol=1e-12 * float(scales.max()) ** 2 * 1e3, rtol=0)
        torch.testing.assert_close(out.scale_factor, torch.ones(N, 2, dtype=DT), atol=1e-9, rtol=0)
        assert float(out.angle[(scales[:, 0] - scales[:, 1]).abs() > 1e-4].abs().max()) < 1e-9
    with pytest.raises(ValueError, match="scales"):
        corr(verts, binding, rot, n)
    with pytest.raises(ValueError, match="mode"):
        _setup(verts, faces, mode="shear")
