"""SDF network: sphere init, double backward, finite-difference Hessian and principal curvatures."""

from __future__ import annotations

import pytest
import torch

from sage_core.fields.sdf import SDFNetwork, hessian_fd, principal_curvatures, tangent_basis

BOX = 0.2


def tiny_net(seed: int = 0, **kw) -> SDFNetwork:
    torch.manual_seed(seed)
    args = dict(n_levels=6, n_features=2, log2_table=12, base_res=8, max_res=128, hidden=64, feature_dim=5)
    args.update(kw)
    return SDFNetwork([-BOX] * 3, [BOX] * 3, **args)


def test_sphere_init_is_world_sphere():
    errs, norms = [], []
    for seed in range(3):
        net = tiny_net(seed, sphere_radius=0.5)
        assert net.half_extent == pytest.approx(BOX)
        x = (torch.rand(4000, 3) * 2 - 1) * BOX
        sdf, grad, feat = net.gradient(x)
        assert feat.shape == (4000, 5)
        errs.append((sdf - (x.norm(dim=-1) - 0.5 * BOX)).abs().mean() / BOX)
        norms.append(grad.norm(dim=-1).mean())
    # normalized units; over 10 seeds this init averages 0.15 (0.10-0.24) with a 64-wide hidden layer
    assert float(torch.stack(errs).mean().detach()) < 0.2
    assert float(torch.stack(norms).mean().detach()) == pytest.approx(1.0, abs=0.2)
    # the zero level set is near the world sphere of radius 0.1 on average
    d = torch.nn.functional.normalize(torch.randn(2000, 3), dim=-1)
    net = tiny_net(0)
    with torch.no_grad():
        assert float(net.sdf(d * 0.05).mean()) < 0 < float(net.sdf(d * 0.19).mean())


def test_encoding_weights_zero_at_init_and_table_gradient_zero():
    net = tiny_net()
    assert torch.all(net.layers[0].weight[:, 3:] == 0)
    x = (torch.rand(100, 3) * 2 - 1) * BOX
    net.sdf(x).sum().backward()
    assert net.encoding.table.grad.abs().max() == 0  # expected on step 1 (docs/rendering.md §8.1)
    assert net.layers[0].weight.grad[:, 3:].abs().max() > 0


def test_eikonal_double_backward_matches_finite_differences():
    net = tiny_net(1).double()
    with torch.no_grad():
        net.encoding.table.uniform_(-0.05, 0.05)
        net.layers[0].weight[:, 3:].normal_(0, 0.5)  # so that the table receives gradients
    x = (torch.rand(64, 3, dtype=torch.float64) * 2 - 1) * BOX

    def eik() -> torch.Tensor:
        _, g, _ = net.gradient(x, create_graph=True)
        return ((g.norm(dim=-1) - 1) ** 2).mean()

    loss = eik()
    params = [net.layers[0].weight, net.layers[0].bias, net.layers[1].weight, net.encoding.table]
    grads = torch.autograd.grad(loss, params)
    torch.manual_seed(5)
    for p, gp in zip(params, grads):
        flat = gp.reshape(-1)
        k = int(torch.argmax(flat.abs()))
        assert flat[k].abs() > 0
        with torch.no_grad():
            orig = p.view(-1)[k].item()
            p.view(-1)[k] = orig + 1e-6
            up = eik().item()
            p.view(-1)[k] = orig - 1e-6
            dn = eik().item()
            p.view(-1)[k] = orig
        assert (up - dn) / 2e-6 == pytest.approx(flat[k].item(), rel=1e-4, abs=1e-9)


def test_hessian_symmetric_and_matches_autograd_for_smooth_part():
    net = tiny_net(2).double()
    x = (torch.rand(20, 3, dtype=torch.float64) * 2 - 1) * BOX
    h = net.hessian(x, eps=1e-5)
    assert h.shape == (20, 3, 3)
    torch.testing.assert_close(h, h.transpose(1, 2))
    # at init the encoding weights are 0, so the field is a smooth MLP: compare with exact autograd Hessian
    exact = torch.stack([torch.autograd.functional.hessian(lambda p: net.sdf(p[None])[0], xi) for xi in x])
    torch.testing.assert_close(h, exact, rtol=1e-3, atol=1e-3 * float(exact.abs().max()))
    assert net.default_fd_step() == pytest.approx(0.4 / net.encoding.level_scales[-1])


def test_tangent_basis_orthonormal():
    n = torch.nn.functional.normalize(torch.randn(500, 3, dtype=torch.float64), dim=-1)
    n[0] = torch.tensor([1.0, 0, 0])
    e = tangent_basis(n)
    frame = torch.cat([e, n[:, None]], 1)
    torch.testing.assert_close(frame @ frame.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(500, 3, 3))
    assert torch.allclose(torch.linalg.det(frame), torch.ones(500, dtype=torch.float64))


def test_curvature_analytic_sphere_and_cylinder():
    r = 0.07
    grad_sphere = lambda p: p / p.norm(dim=-1, keepdim=True)  # noqa: E731
    pts = torch.nn.functional.normalize(torch.randn(200, 3, dtype=torch.float64), dim=-1) * r
    kappa, dirs, normal = principal_curvatures(grad_sphere, pts, eps=1e-4)
    torch.testing.assert_close(kappa, torch.full_like(kappa, 1 / r), rtol=1e-5, atol=0)
    assert (dirs * normal[:, None]).sum(-1).abs().max() < 1e-9
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(200, 2, dtype=torch.float64))
    # cylinder around z: f = sqrt(x^2 + y^2) - r, k1 = 1/r along the circle, k2 = 0 along z
    grad_cyl = lambda p: torch.nn.functional.pad(  # noqa: E731
        p[:, :2] / p[:, :2].norm(dim=-1, keepdim=True), (0, 1)
    )
    ang = torch.rand(100, dtype=torch.float64) * 6.28
    pc = torch.stack([r * ang.cos(), r * ang.sin(), torch.rand(100, dtype=torch.float64)], -1)
    kappa, dirs, _ = principal_curvatures(grad_cyl, pc, eps=1e-4)
    torch.testing.assert_close(kappa[:, 0], torch.full_like(kappa[:, 0], 1 / r), rtol=1e-5, atol=0)
    assert kappa[:, 1].abs().max() < 1e-6
    assert (dirs[:, 1, 2].abs() - 1).abs().max() < 1e-6  # k2 direction is the axis
    # concave side (inside-out sphere) gives negative curvature
    kappa_in, _, _ = principal_curvatures(lambda p: -grad_sphere(p), pts, eps=1e-4)
    assert torch.all(kappa_in < 0)


def test_hessian_fd_exact_for_quadratic():
    a = torch.tensor([[2.0, 0.5, 0.0], [0.5, -1.0, 0.3], [0.0, 0.3, 4.0]], dtype=torch.float64)
    h = hessian_fd(lambda p: p @ a, torch.randn(5, 3, dtype=torch.float64), 1e-2)
    torch.testing.assert_close(h, a.expand(5, 3, 3))


def test_curvature_of_network_fitted_to_sphere(one_thread):
    torch.manual_seed(0)
    net = tiny_net(3, n_levels=4, max_res=32, hidden=32)
    r = 0.1
    opt = torch.optim.Adam(
        [{"params": net.grid_parameters(), "lr": 1e-2}, {"params": net.mlp_parameters(), "lr": 1e-3}]
    )
    for _ in range(150):
        x = (torch.rand(2048, 3) * 2 - 1) * BOX
        sdf, g, _ = net.gradient(x, create_graph=True)
        loss = (sdf - (x.norm(dim=-1) - r)).abs().mean() + 0.1 * ((g.norm(dim=-1) - 1) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    pts = torch.nn.functional.normalize(torch.randn(300, 3), dim=-1) * r
    assert float(net.sdf(pts).detach().abs().mean()) < 0.004
    kappa, dirs, normal = net.curvature(pts)
    assert kappa.shape == (300, 2) and torch.all(kappa[:, 0] >= kappa[:, 1])
    mean_k = float(kappa.mean())
    assert mean_k == pytest.approx(1 / r, rel=0.25)
    assert (dirs * normal[:, None]).sum(-1).abs().max() < 1e-4
    radial = torch.nn.functional.normalize(pts, dim=-1)
    assert float((normal * radial).sum(-1).mean()) > 0.98
    s, n = net.sdf_and_normal(pts)
    torch.testing.assert_close(n, normal)


def test_sdf_and_feature_stay_differentiable_after_a_detached_gradient():
    import torch

    from sage_core.fields.sdf import SDFNetwork

    net = SDFNetwork([-1.0] * 3, [1.0] * 3, n_levels=4, log2_table=10, max_res=64, hidden=16, feature_dim=4)
    x = torch.rand(32, 3) * 1.2 - 0.6
    sdf, grad, feature = net.gradient(x, create_graph=False)
    assert not grad.requires_grad
    (sdf.abs().sum() + feature.sum()).backward()
    assert all(p.grad is not None for p in net.mlp_parameters())
