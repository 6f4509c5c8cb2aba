"""Appearance and shape networks: SH basis, outputs, frames, and the gap-clamped eigh backward."""

from __future__ import annotations

import torch

from sage_core.fields.appearance import AppearanceNetwork, sh_basis
from sage_core.fields.shape import ShapeNetwork, frame_from_symmetric, safe_eigh, symmetric_from_tril
from sage_core.geometry.rotations import quat_to_matrix

BOX = ([-0.2] * 3, [0.2] * 3)


def test_sh_basis_orthonormal_on_sphere():
    torch.manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(400000, 3, dtype=torch.float64), dim=-1)
    y = sh_basis(d, 3)
    assert y.shape == (400000, 16)
    gram = 4 * torch.pi * (y.T @ y) / d.shape[0]
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.02, rtol=0)
    assert sh_basis(d[:5], 0).shape == (5, 1) and sh_basis(d[:5], 2).shape == (5, 9)


def test_appearance_outputs_and_view_independence():
    torch.manual_seed(0)
    n = 50
    x = torch.rand(n, 3) * 0.2
    v1 = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    v2 = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    z = torch.randn(n, 7)
    net = AppearanceNetwork(7, *BOX, hidden=32, n_layers=2, sh_degree=2)
    rgb, alpha = net(x, v1, nrm, z)
    assert rgb.shape == (n, 3) and alpha.shape == (n,)
    assert torch.all((rgb > 0) & (rgb < 1)) and torch.all((alpha > 0) & (alpha < 1))
    assert abs(float(alpha.detach().mean()) - 0.5) < 0.1  # opacity starts near 0.5 (bias 0)
    rgb2, _ = net(x, v2, nrm, z)
    assert (rgb - rgb2).abs().max() > 1e-6
    mono = AppearanceNetwork(7, *BOX, hidden=32, n_layers=2, view_dependent=False)
    a, _ = mono(x, v1, nrm, z)
    b, _ = mono(x, None, nrm, z)
    torch.testing.assert_close(a, b)
    (a.sum()).backward()
    assert all(p.grad is not None for p in mono.parameters())


def test_safe_eigh_matches_torch_backward_on_generic_matrices():
    torch.manual_seed(1)
    a = torch.randn(20, 3, 3, dtype=torch.float64)
    a = (a + a.transpose(1, 2)).requires_grad_(True)
    w_l = torch.randn(20, 3, dtype=torch.float64)
    w_v = torch.randn(20, 3, 3, dtype=torch.float64)

    def loss(fn):
        lam, vec = fn(a)
        # sign-invariant in the eigenvectors: use v v^T
        outer = vec[..., :, None, :] * vec[..., None, :, :]
        return (lam * w_l).sum() + (outer.sum(-1) * w_v).sum()

    (g_safe,) = torch.autograd.grad(loss(lambda m: safe_eigh(m, gap=1e-9)), a)
    (g_ref,) = torch.autograd.grad(loss(torch.linalg.eigh), a)
    g_ref = 0.5 * (g_ref + g_ref.transpose(1, 2))
    torch.testing.assert_close(g_safe, g_ref, rtol=1e-8, atol=1e-8)


def test_gradients_finite_at_repeated_eigenvalues():
    mats = torch.stack(
        [
            torch.eye(3, dtype=torch.float64),
            torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)),
            torch.diag(torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64)),
        ]
    ).requires_grad_(True)
    rot, mags = frame_from_symmetric(mats)
    loss = (rot * torch.randn_like(rot)).sum() + mags.sum()
    (g,) = torch.autograd.grad(loss, mats)
    assert torch.isfinite(g).all()
    (g_torch,) = torch.autograd.grad(
        (torch.linalg.eigh(mats)[1] * torch.randn(3, 3, 3, dtype=torch.float64)).sum(), mats
    )
    assert not torch.isfinite(g_torch).all()  # what the guard protects against


def test_symmetric_from_tril():
    e = torch.arange(1.0, 7.0)[None]
    a = symmetric_from_tril(e)[0]
    expected = torch.tensor([[1.0, 2.0, 4.0], [2.0, 3.0, 5.0], [4.0, 5.0, 6.0]])
    torch.testing.assert_close(a, expected)


def test_frame_normal_is_smallest_eigenvector_and_oriented():
    r0 = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))[0]
    a = r0 @ torch.diag(torch.tensor([0.01, -3.0, 1.5], dtype=torch.float64)) @ r0.T
    ref = -r0[:, 0]
    rot, mags = frame_from_symmetric(a[None], ref[None])
    torch.testing.assert_close(rot[0, :, 2], ref)
    torch.testing.assert_close(rot[0, :, 0].abs(), r0[:, 1].abs())
    torch.testing.assert_close(mags[0], torch.tensor([3.0, 1.5], dtype=torch.float64))
    assert torch.linalg.det(rot[0]) > 0.999


def test_shape_network_frames_scales_and_gradients():
    torch.manual_seed(2)
    n = 300
    net = ShapeNetwork(12, *BOX, hidden=32, n_layers=2, base_scale=2e-3, s_min=0.5, s_max=2.0, r_min=0.1)
    x = (torch.rand(n, 3) * 2 - 1) * 0.2
    feats = torch.randn(n, 6, 2)
    ref = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    quats, scales, rot = net(x, feats, reference_normal=ref)
    assert quats.shape == (n, 4) and scales.shape == (n, 2)
    eye = torch.eye(3).expand(n, 3, 3)
    torch.testing.assert_close(rot.transpose(1, 2) @ rot, eye, atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(n), atol=1e-5, rtol=0)
    torch.testing.assert_close(quat_to_matrix(quats), rot, atol=1e-5, rtol=0)
    assert torch.all((rot[:, :, 2] * ref).sum(-1) >= 0)
    assert torch.all(scales[:, 0] >= scales[:, 1] - 1e-9)
    lo, hi = 2e-3 * 0.5 * 0.1, 2e-3 * 2.0 * 1.9
    assert torch.all(scales >= lo * 0.999) and torch.all(scales <= hi * 1.001)
    per_point = torch.full((n,), 0.01)
    _, scales_pp, _ = net(x, feats, base_scale=per_point)
    torch.testing.assert_close(scales_pp, scales * 5.0)
    (scales.sum() + (quats * torch.randn_like(quats)).sum()).backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters())
    assert net.mlp[-1].weight.grad.abs().sum() > 0


def test_shape_network_finite_gradients_at_degenerate_output():
    net = ShapeNetwork(4, *BOX, hidden=16, n_layers=1)
    with torch.no_grad():
        last = net.mlp[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0]))  # A = I: all eigenvalues equal
    x = torch.zeros(4, 3)
    quats, scales, rot = net(x, torch.randn(4, 4))
    ((quats * torch.randn_like(quats)).sum() + scales.sum()).backward()
    assert torch.isfinite(net.mlp[-1].weight.grad).all()
    assert torch.isfinite(net.mlp[0].weight.grad).all()
