"""Phase-1 losses on hand-built cases: zero when they should be, known values, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from sage_core.train import losses as L


def test_rgb_loss_zero_for_identical_and_l1_value():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(24, 20, 3, generator=g, dtype=torch.float64)
    assert float(L.rgb_loss(img, img)) == pytest.approx(0.0, abs=1e-10)
    # without SSIM it is the plain L1
    assert float(L.rgb_loss(img + 0.1, img, ssim_weight=0.0)) == pytest.approx(0.1, abs=1e-12)
    pred = (img + 0.05).requires_grad_(True)
    loss = L.rgb_loss(pred, img)
    assert float(loss.detach()) > 0.8 * 0.05 - 1e-9
    loss.backward()
    assert pred.grad is not None and float(pred.grad.abs().sum()) > 0


def test_point_sdf_loss_value_and_gradient():
    sdf = torch.tensor([0.0, -0.2, 0.4], dtype=torch.float64, requires_grad=True)
    loss = L.point_sdf_loss(sdf, scale=2.0)
    assert float(loss.detach()) == pytest.approx(0.1)
    loss.backward()
    assert torch.allclose(sdf.grad, torch.tensor([0.0, -1.0, 1.0], dtype=torch.float64) / 6.0)


def test_align_loss_zero_for_parallel_and_antiparallel_one_for_perpendicular():
    n = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    assert float(L.align_loss(n, 3.0 * n)) == pytest.approx(0.0)
    assert float(L.align_loss(n, -2.0 * n)) == pytest.approx(0.0)
    perp = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    assert float(L.align_loss(n, perp)) == pytest.approx(1.0)
    # 60 degrees: 1 - cos = 0.5; gradient reaches both the surfel normal and the SDF gradient
    t3 = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    grad = torch.tensor([[math.sin(math.pi / 3), 0.0, math.cos(math.pi / 3)]], dtype=torch.float64, requires_grad=True)
    loss = L.align_loss(t3, grad)
    assert float(loss.detach()) == pytest.approx(0.5)
    loss.backward()
    assert float(t3.grad.abs().sum()) > 0 and float(grad.grad.abs().sum()) > 0


def test_depth_loss_masked_mean_and_gradient_to_sdf_side_only():
    sdf_d = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64, requires_grad=True)
    surf_d = torch.tensor([1.5, 2.0, 10.0], dtype=torch.float64)
    mask = torch.tensor([True, True, False])
    loss = L.depth_loss(sdf_d, surf_d.detach(), mask, scale=0.5)
    assert float(loss.detach()) == pytest.approx(0.5)  # mean(0.5, 0) / 0.5
    loss.backward()
    assert torch.allclose(sdf_d.grad, torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64))


def test_normal_loss_zero_when_equal_up_to_length_and_known_value():
    a = torch.tensor([[0.0, 0.0, 2.0], [0.0, 3.0, 0.0]], dtype=torch.float64)
    assert float(L.normal_loss(a, 0.5 * a)) == pytest.approx(0.0, abs=1e-12)
    b = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    c = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    assert float(L.normal_loss(b, c)) == pytest.approx(2.0 + 1.0)  # L1 of the difference 2, 1 - cos 1


def test_eikonal_and_smoothness():
    g = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    loss = L.eikonal_loss(g)
    assert float(loss.detach()) == pytest.approx(8.0)  # ((5-1)^2 + 0) / 2
    loss.backward()
    assert float(g.grad[1].abs().sum()) == pytest.approx(0.0)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    assert float(L.normal_smoothness_loss(n, 5 * n)) == pytest.approx(0.0)
    assert float(L.normal_smoothness_loss(n, -n)) == pytest.approx(2.0)


def test_normal_consistency_and_distortion():
    H, W = 6, 5
    n = torch.zeros(H, W, 3, dtype=torch.float64)
    n[..., 2] = -1.0
    assert float(L.normal_consistency_loss(n, n)) == pytest.approx(0.0)
    other = torch.zeros_like(n)
    other[..., 0] = 1.0
    assert float(L.normal_consistency_loss(n, other)) == pytest.approx(1.0)
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[:2] = True
    mixed = other.clone()
    mixed[:2] = n[:2]
    assert float(L.normal_consistency_loss(n, mixed, mask)) == pytest.approx(0.0)
    d = torch.full((H, W), 0.25, dtype=torch.float64)
    assert float(L.distortion_loss(d)) == pytest.approx(0.25)


def test_neus_rgb_loss():
    a = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    b = torch.full((4, 3), 0.5, dtype=torch.float64)
    loss = L.neus_rgb_loss(a, b)
    assert float(loss.detach()) == pytest.approx(0.5)
    loss.backward()
    assert torch.allclose(a.grad, torch.full((4, 3), -1.0 / 12, dtype=torch.float64))


def test_mask_losses_match_their_formulas():
    from sage_core.train.losses import alpha_mask_loss, mask_bce_loss

    o = torch.tensor([0.0, 0.3, 0.9, 0.6], requires_grad=True)
    m = torch.tensor([0.0, 1.0, 1.0, 0.0])
    oc = o.detach().clamp(1e-3, 1 - 1e-3)
    ref = -(m * oc.log() + (1 - m) * (1 - oc).log()).mean()
    loss = mask_bce_loss(o, m)
    assert torch.allclose(loss, ref)
    loss.backward()
    # foreground rays are pushed towards opacity, a background ray towards transparency
    assert float(o.grad[1]) < 0 and float(o.grad[2]) < 0 and float(o.grad[3]) > 0
    a = torch.tensor([[0.2, 1.0], [0.0, 0.5]])
    mk = torch.tensor([[0.0, 1.0], [0.0, 1.0]])
    assert torch.isclose(alpha_mask_loss(a, mk), torch.tensor(0.7 / 4))
    assert float(alpha_mask_loss(mk, mk)) == 0.0
    # a weight leaves pixels out of the sum but not out of the count
    w = torch.tensor([[1.0, 1.0], [1.0, 0.0]])
    assert torch.isclose(alpha_mask_loss(a, mk, w), torch.tensor(0.2 / 4))


def test_mask_edge_band_straddles_the_edge_and_follows_the_regime():
    from sage_core.config import resolve_config
    from sage_core.train.phase1 import mask_edge_keep

    mask = torch.zeros(12, 12)
    mask[3:9, 3:9] = 1.0  # a 6 x 6 foreground square
    assert torch.equal(mask_edge_keep(mask, 0), torch.ones(12, 12))
    keep = mask_edge_keep(mask, 1)
    band = keep == 0
    # one pixel either side of the edge: rows/cols 2..9 minus the untouched core 4..7
    ref = torch.zeros(12, 12, dtype=torch.bool)
    ref[2:10, 2:10] = True
    ref[4:8, 4:8] = False
    assert torch.equal(band, ref)
    assert int((mask_edge_keep(mask, 2) == 0).sum()) == 10 * 10 - 2 * 2
    # one photo trusts the mask's edge less; a clip or a rig keeps every pixel
    assert resolve_config("phase1", "tiny", regime="one-shot").mask_band == 1
    assert resolve_config("phase1", "tiny", regime="sv-hr").mask_band == 0
    assert resolve_config("phase1", "tiny", regime="mv-sf").mask_band == 0


# ---- the loss-term table ---------------------------------------------------------------------------


def test_add_terms_runs_a_table_in_order_with_weights_starts_polish_and_groups():
    from types import SimpleNamespace

    from sage_core.train.losses import LossTerm, add_terms

    calls = []

    def term(name, value):
        def compute(ctx):
            calls.append(name)
            return None if value is None else torch.tensor(value)

        return compute

    table = (
        LossTerm("a", None, term("a", 1.0)),
        LossTerm("b", "b", term("b", 2.0), start="b_from"),
        LossTerm("c", "c", term("c", 3.0), polish=False),
        LossTerm("g1", "g", term("g1", 4.0), group="g"),
        LossTerm("g2", "g", term("g2", 5.0), group="g", when=lambda ctx: ctx.flag),
        LossTerm("none", "g", term("none", None)),
        LossTerm("zero", "zero", term("zero", 7.0)),
        LossTerm("view", lambda ctx: ctx.view, term("view", 6.0)),
    )
    weights = SimpleNamespace(b=10.0, c=100.0, g=0.5, zero=0.0)
    schedule = SimpleNamespace(b_from=3)

    def run(step, polish, flag, view=2.0):
        calls.clear()
        terms = {}
        total = add_terms(table, SimpleNamespace(step=step, polish=polish, flag=flag, view=view), weights, schedule, terms)
        return total, terms, list(calls)

    total, terms, order = run(5, False, True)
    assert order == ["a", "b", "c", "g1", "g2", "none", "view"]  # the zero-weight term is not computed
    assert set(terms) == {"a", "b", "c", "g1", "g2", "view"}
    assert float(total) == 1 + 20 + 300 + (0.5 * 4 + 0.5 * 5) + 12
    total, terms, order = run(2, True, False, view=0.0)  # before b's start, in the polish, g2 off, view weight 0
    assert order == ["a", "g1", "none"] and float(total) == 1 + 2
    assert add_terms((LossTerm("z", "zero", term("z", 1.0)),), SimpleNamespace(step=0, polish=False), weights, schedule, {}) is None
