"""NeuS volume renderer on analytic SDFs and on the SDF network."""

from __future__ import annotations

import pytest
import torch

from sage_core.fields.appearance import AppearanceNetwork
from sage_core.fields.sdf import SDFNetwork
from sage_core.render.volume import (
    SVariance,
    default_length_unit,
    neus_alpha,
    ray_box_intersect,
    render_neus,
)

COLOUR = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)


class AnalyticSphere:
    """f = |x - c| - r in the SDFField interface."""

    def __init__(self, radius: float = 0.5, center=(0.0, 0.0, 0.0)) -> None:
        self.r = radius
        self.c = torch.tensor(center, dtype=torch.float64)
        self.bbox_min = torch.full((3,), -1.0, dtype=torch.float64)
        self.bbox_max = torch.full((3,), 1.0, dtype=torch.float64)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.c).norm(dim=-1) - self.r

    def gradient(self, x, create_graph=False):
        v = x - self.c
        n = v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return n[:, 0] - self.r, v / n, torch.zeros(x.shape[0], 2, dtype=x.dtype)


def constant_app(x, view_dir, normal, feature):
    return COLOUR.to(x.dtype).expand(x.shape[0], 3), torch.ones(x.shape[0], dtype=x.dtype)


def sphere_hit(o, d, c, r):
    d = d / d.norm(dim=-1, keepdim=True)
    oc = o - c
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - r * r)
    return -b - disc.clamp_min(0).sqrt(), disc > 0


def camera_rays(n: int = 12):
    torch.manual_seed(0)
    o = torch.tensor([[0.1, -0.2, -3.0]], dtype=torch.float64).expand(n, 3)
    d = torch.cat([torch.rand(n, 2, dtype=torch.float64) * 0.5 - 0.25, torch.ones(n, 1, dtype=torch.float64)], -1)
    return o, d


def test_svariance_init():
    s = SVariance()
    assert float(s().detach()) == pytest.approx(torch.exp(torch.tensor(3.0)).item(), rel=1e-6)
    s.variance.data.fill_(100.0)
    assert float(s().detach()) == 1e6


def test_ray_box_intersection():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    tn, tf = ray_box_intersect(o, d, torch.full((3,), -1.0), torch.full((3,), 1.0))
    assert tn[0] == pytest.approx(2.0) and tf[0] == pytest.approx(4.0)
    assert tf[1] <= tn[1]


def test_neus_alpha_formula():
    sdf = torch.tensor([0.1, 0.0, -0.05])
    cos = torch.tensor([-1.0, -0.5, 0.3])
    dist = torch.tensor([0.02, 0.02, 0.02])
    s = 50.0
    a = neus_alpha(sdf, cos, dist, s, cos_anneal_ratio=1.0)
    it = -torch.relu(-cos)
    prev, nxt = torch.sigmoid((sdf - it * dist / 2) * s), torch.sigmoid((sdf + it * dist / 2) * s)
    torch.testing.assert_close(a, ((prev - nxt + 1e-5) / (prev + 1e-5)).clamp(0, 1))
    # r = 1 skips the annealed term of weight 0: the same gradients as the whole formula
    c1, c2 = cos.clone().requires_grad_(True), cos.clone().requires_grad_(True)
    (g1,) = torch.autograd.grad(neus_alpha(sdf, c1, dist, s, cos_anneal_ratio=1.0).sum(), c1)
    full = -(torch.relu(-c2 * 0.5 + 0.5) * 0.0 + torch.relu(-c2) * 1.0)
    p2, n2 = torch.sigmoid((sdf - full * dist / 2) * s), torch.sigmoid((sdf + full * dist / 2) * s)
    (g2,) = torch.autograd.grad(((p2 - n2 + 1e-5) / (p2 + 1e-5)).clamp(0, 1).sum(), c2)
    assert torch.equal(g1, g2)
    a0 = neus_alpha(sdf, cos, dist, s, cos_anneal_ratio=0.0)
    it0 = -torch.relu(-cos * 0.5 + 0.5)
    prev, nxt = torch.sigmoid((sdf - it0 * dist / 2) * s), torch.sigmoid((sdf + it0 * dist / 2) * s)
    torch.testing.assert_close(a0, ((prev - nxt + 1e-5) / (prev + 1e-5)).clamp(0, 1))


def test_depth_and_colour_of_analytic_sphere():
    sphere = AnalyticSphere(0.5, (0.05, 0.0, 0.1))
    o, d = camera_rays(24)
    t_true, hits = sphere_hit(o, d, sphere.c, sphere.r)
    assert hits.any() and (~hits).any()
    out = render_neus(sphere, constant_app, o, d, inv_s=2000.0, n_samples=64, n_importance=64, background=1.0)
    depth = out.depth / out.weights_sum
    assert (depth[hits] - t_true[hits]).abs().max() < 2e-3
    assert out.weights_sum[hits].min() > 0.995
    assert out.weights_sum[~hits].max() < 0.005  # only the 1e-5 terms of alpha
    torch.testing.assert_close(out.color[hits], COLOUR.expand(int(hits.sum()), 3), atol=5e-3, rtol=0)
    white = torch.ones(int((~hits).sum()), 3, dtype=torch.float64)
    torch.testing.assert_close(out.color[~hits], white, atol=5e-3, rtol=0)
    # normals: unit outward normals at the hit point
    hit_pts = o + d / d.norm(dim=-1, keepdim=True) * t_true[:, None]
    expected = (hit_pts - sphere.c) / sphere.r
    nrm = out.normal[hits] / out.weights_sum[hits, None]
    assert (nrm - expected[hits]).norm(dim=-1).max() < 0.02


def test_missed_box_gives_background_and_chunking_invariance():
    sphere = AnalyticSphere()
    o = torch.tensor([[0.0, 3.0, -3.0], [0.0, 0.0, -3.0], [0.2, 0.1, -3.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    bg = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    out = render_neus(sphere, constant_app, o, d, inv_s=500.0, n_samples=32, n_importance=32, background=bg, chunk=1)
    assert not out.hit[0] and out.hit[1:].all()
    torch.testing.assert_close(out.color[0], bg)
    assert out.weights_sum[0] == 0 and out.depth[0] == 0
    full = render_neus(sphere, constant_app, o, d, inv_s=500.0, n_samples=32, n_importance=32, background=bg)
    torch.testing.assert_close(out.color, full.color)
    torch.testing.assert_close(out.depth, full.depth)


def test_rays_that_hit_render_alike_beside_a_missed_ray(one_thread):
    """The outputs of rays that hit the box, and the gradients they give, do not depend on whether a
    ray that misses it is rendered with them (its rows are zeros)."""
    torch.manual_seed(0)
    box = ([-0.2] * 3, [0.2] * 3)
    net = SDFNetwork(*box, n_levels=4, log2_table=10, base_res=8, max_res=64, hidden=16, feature_dim=4)
    app = AppearanceNetwork(4, *box, hidden=16, n_layers=1, sh_degree=1)
    o = torch.tensor([[0.0, 0.0, -0.6]]).repeat(5, 1)
    d = torch.cat([torch.randn(5, 2).clamp(-2, 2) * 0.05, torch.ones(5, 1)], -1)
    miss = (torch.tensor([[0.0, 1.0, -0.6]]), torch.tensor([[0.0, 0.0, 1.0]]))
    results = []
    for rays_o, rays_d in ((o, d), (torch.cat([o, miss[0]]), torch.cat([d, miss[1]]))):
        net.zero_grad(set_to_none=True)
        out = render_neus(net, app, rays_o, rays_d, 50.0, n_samples=8, n_importance=8, up_sample_steps=1,
                          length_unit=0.2, return_samples=True)  # fmt: skip
        keys = ("color", "depth", "normal", "weights_sum", "t", "weights", "sdf", "gradients")
        rows = {k: getattr(out, k)[:5] for k in keys}
        (rows["color"].sum() + rows["normal"].sum() + rows["gradients"].norm(dim=-1).sum()).backward()
        results.append((rows, net.layers[0].weight.grad.clone(), net.encoding.table.grad.clone()))
    (a, wa, ta), (b, wb, tb) = results
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert torch.equal(wa, wb) and torch.equal(ta, tb)


def test_importance_sampling_concentrates_samples_at_surface():
    sphere = AnalyticSphere()
    o = torch.tensor([[0.0, 0.0, -3.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    out = render_neus(sphere, constant_app, o, d, inv_s=500.0, n_samples=16, n_importance=32, return_samples=True)
    near = ((out.t - 2.5).abs() < 0.05).sum()
    assert int(near) >= 16
    assert out.t.shape == (1, 48) and torch.all(out.t[:, 1:] >= out.t[:, :-1])
    assert abs(float(out.depth / out.weights_sum) - 2.5) < 1e-3


def test_perturbed_sampling_is_repeatable_with_generator():
    sphere = AnalyticSphere()
    o, d = camera_rays(6)
    a = render_neus(sphere, constant_app, o, d, 200.0, 16, 16, perturb=True, generator=torch.Generator().manual_seed(3))
    b = render_neus(sphere, constant_app, o, d, 200.0, 16, 16, perturb=True, generator=torch.Generator().manual_seed(3))
    c = render_neus(sphere, constant_app, o, d, 200.0, 16, 16, perturb=True, generator=torch.Generator().manual_seed(4))
    torch.testing.assert_close(a.depth, b.depth)
    assert (a.depth - c.depth).abs().max() > 0


def test_gradients_reach_networks_and_eikonal_samples(one_thread):
    torch.manual_seed(0)
    box = ([-0.2] * 3, [0.2] * 3)
    net = SDFNetwork(*box, n_levels=4, log2_table=10, base_res=8, max_res=64, hidden=16, feature_dim=4)
    with torch.no_grad():
        net.layers[0].weight[:, 3:].normal_(0, 0.1)
    app = AppearanceNetwork(4, *box, hidden=16, n_layers=1, sh_degree=1)
    var = SVariance()
    o = torch.tensor([[0.0, 0.0, -0.6]]).repeat(8, 1)
    d = torch.cat([torch.randn(8, 2).clamp(-2, 2) * 0.05, torch.ones(8, 1)], -1)
    unit = default_length_unit(net)
    assert unit == pytest.approx(0.2)
    out = render_neus(net, app, o, d, var, n_samples=16, n_importance=16, up_sample_steps=2,
                      cos_anneal_ratio=0.5, length_unit=unit, return_samples=True)  # fmt: skip
    assert out.weights_sum.min() > 0.5  # the init sphere is hit
    eik = ((out.gradients[out.sample_mask].norm(dim=-1) - 1) ** 2).mean()
    loss = out.color.sum() + out.normal.sum() + eik
    loss.backward()
    assert net.encoding.table.grad.abs().sum() > 0
    assert net.layers[0].weight.grad.abs().sum() > 0
    assert app.mlp[0].weight.grad.abs().sum() > 0
    assert var.variance.grad is not None and var.variance.grad != 0
    with torch.no_grad():
        inf = render_neus(net, app, o, d, var, n_samples=16, n_importance=16, up_sample_steps=2,
                          cos_anneal_ratio=0.5, length_unit=unit)  # fmt: skip
    torch.testing.assert_close(inf.color, out.color.detach())


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    torch.manual_seed(0)
    box = ([-0.2] * 3, [0.2] * 3)
    net = SDFNetwork(*box, n_levels=4, log2_table=10, base_res=8, max_res=64, hidden=16, feature_dim=4)
    with torch.no_grad():
        net.layers[0].weight[:, 3:].normal_(0, 0.1)
    app = AppearanceNetwork(4, *box, hidden=16, n_layers=1, sh_degree=1)
    o = torch.tensor([[0.0, 0.0, -0.6]]).repeat(8, 1)
    d = torch.cat([torch.randn(8, 2).clamp(-2, 2) * 0.05, torch.ones(8, 1)], -1)
    args = dict(inv_s=50.0, n_samples=16, n_importance=16, up_sample_steps=2, length_unit=0.2)
    cpu = render_neus(net, app, o, d, **args)
    gpu = render_neus(net.cuda(), app.cuda(), o.cuda(), d.cuda(), **args)
    torch.testing.assert_close(gpu.color.cpu(), cpu.color, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(gpu.depth.cpu(), cpu.depth, atol=1e-4, rtol=1e-4)
