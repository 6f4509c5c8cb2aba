"""Hash grid: tcnn conventions, a naive per-level reference, and derivative properties."""

from __future__ import annotations

import math

import pytest
import torch

from sage_core.fields.hashgrid import HashGrid

PRIMES = (1, 2654435761, 805459861)


def naive_encode(grid: HashGrid, x: torch.Tensor) -> torch.Tensor:
    """Per-level, per-corner loop straight from the instant-ngp definition (python ints for the hash)."""
    lo, hi = grid.bbox_min.to(x.dtype), grid.bbox_max.to(x.dtype)
    x01 = ((x - lo) / (hi - lo)).clamp(0, 1)
    b = math.exp((math.log(grid.max_res) - math.log(grid.base_res)) / (grid.n_levels - 1))
    feats = []
    offset = 0
    for level in range(grid.n_levels):
        scale = grid.base_res * b**level - 1.0
        if abs(scale - round(scale)) < 1e-9 * scale:
            scale = float(round(scale))
        res = math.ceil(scale) + 1
        size = min(((res**3 + 7) // 8) * 8, 2**grid.log2_table)
        pos = x01 * scale + 0.5
        cell = torch.floor(pos)
        frac = pos - cell
        acc = torch.zeros(x.shape[0], grid.n_features, dtype=x.dtype)
        for n in range(x.shape[0]):
            for corner in range(8):
                c = [int(cell[n, k]) + ((corner >> k) & 1) for k in range(3)]
                if res**3 <= size:
                    index = c[0] + res * c[1] + res * res * c[2]
                else:
                    index = (c[0] * PRIMES[0]) ^ (c[1] * PRIMES[1]) ^ (c[2] * PRIMES[2])
                    index &= 0xFFFFFFFF
                index = index % size + offset
                w = 1.0
                for k in range(3):
                    w = w * (frac[n, k] if (corner >> k) & 1 else 1 - frac[n, k])
                acc[n] = acc[n] + w * grid.table[index].to(x.dtype)
        feats.append(acc)
        offset += size
    return torch.cat(feats, -1)


def small_grid(**kw) -> HashGrid:
    args = dict(n_levels=6, n_features=2, log2_table=10, base_res=4, max_res=64)
    args.update(kw)
    torch.manual_seed(0)
    g = HashGrid([-0.3, -0.2, -0.1], [0.3, 0.4, 0.5], **args)
    with torch.no_grad():
        g.table.uniform_(-1, 1)  # large values so the comparison is meaningful
    return g


def test_level_layout_tcnn_conventions():
    g = HashGrid([-1] * 3, [1] * 3, n_levels=16, n_features=2, log2_table=19, base_res=16, max_res=2048)
    assert g.level_resolutions[0] == 16
    assert g.level_resolutions[-1] == 2048  # not 2049
    assert g.level_scales[-1] == 2047.0
    t = 2**19
    dense = [r**3 <= s for r, s in zip(g.level_resolutions, g.level_sizes)]
    assert all(s <= t and s % 8 == 0 for s in g.level_sizes)
    assert dense[:5] == [True] * 5 and not any(dense[5:])
    assert g.table.shape == (sum(g.level_sizes), 2)
    assert 12.0e6 < g.table.numel() < 12.4e6  # docs/rendering.md §7: about 12.2M entries
    assert g.table.abs().max() <= 1e-4


def test_matches_naive_reference_values_and_gradients():
    g = small_grid().double()
    torch.manual_seed(1)
    lo, hi = g.bbox_min.double(), g.bbox_max.double()
    x = (lo + torch.rand(40, 3, dtype=torch.float64) * (hi - lo)).requires_grad_(True)
    fast = g(x)
    ref = naive_encode(g, x)
    assert fast.shape == (40, g.n_levels * g.n_features)
    torch.testing.assert_close(fast, ref, rtol=1e-10, atol=1e-10)
    w = torch.randn_like(fast)
    gx_fast, gt_fast = torch.autograd.grad((fast * w).sum(), [x, g.table])
    gx_ref, gt_ref = torch.autograd.grad((ref * w).sum(), [x, g.table])
    torch.testing.assert_close(gx_fast, gx_ref, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(gt_fast, gt_ref, rtol=1e-9, atol=1e-9)


def test_uses_hashed_levels():
    g = small_grid()
    assert any(r**3 > s for r, s in zip(g.level_resolutions, g.level_sizes))


def test_level_features_and_masking():
    g = small_grid()
    x = torch.rand(10, 3) * 0.2
    lf = g.level_features(x)
    assert lf.shape == (10, 6, 2)
    torch.testing.assert_close(g(x), lf.reshape(10, -1))
    cell_all = g.finest_cell_size()
    g.set_active_levels(3)
    assert g.active_levels == 3
    masked = g.level_features(x)
    assert torch.all(masked[:, 3:] == 0)
    torch.testing.assert_close(masked[:, :3], lf[:, :3])
    assert g.finest_cell_size() > cell_all
    assert g.finest_cell_size() == pytest.approx(0.6 / g.level_scales[2])


def test_second_derivative_along_axis_is_zero_inside_cell():
    g = small_grid()
    torch.manual_seed(2)
    x = (torch.rand(30, 3) * 0.2).requires_grad_(True)
    y = (g(x) * torch.randn(1, 12)).sum()
    (grad,) = torch.autograd.grad(y, x, create_graph=True)
    for i in range(3):
        (h_row,) = torch.autograd.grad(grad[:, i].sum(), x, retain_graph=True)
        assert h_row[:, i].abs().max() == 0.0  # exact zero in float32 with explicit products
    assert h_row.abs().max() > 0  # mixed terms exist


def test_double_backward_matches_finite_differences():
    g = small_grid().double()
    torch.manual_seed(3)
    x = (torch.rand(8, 3, dtype=torch.float64) * 0.2).requires_grad_(True)
    w = torch.randn(12, dtype=torch.float64)

    def eik(table: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            g.table.copy_(table)
        xx = x.detach().requires_grad_(True)
        (gr,) = torch.autograd.grad((g(xx) @ w).sum(), xx, create_graph=True)
        return (gr**2).sum()

    base = g.table.detach().clone()
    loss = eik(base)
    (gtab,) = torch.autograd.grad(loss, g.table)
    idx = torch.nonzero(gtab.abs() > 1e-6)[:4]
    assert len(idx) == 4
    for r, c in idx.tolist():
        e = torch.zeros_like(base)
        e[r, c] = 1e-4
        fd = (eik(base + e) - eik(base - e)) / 2e-4
        assert float(fd.detach()) == pytest.approx(float(gtab[r, c]), rel=1e-4, abs=1e-8)
    with torch.no_grad():
        g.table.copy_(base)


def test_points_outside_box_are_clamped():
    g = small_grid()
    inside = torch.tensor([[0.3, 0.4, 0.5]])
    outside = torch.tensor([[0.9, 1.4, 2.5]])
    torch.testing.assert_close(g(inside), g(outside))
