"""Smooth-albedo light prior: neighbour pairs, recovery of a known light, and phase 1's use of it."""

from __future__ import annotations

import pytest
import torch

from sage_core.avatar.init import REGION_EYES, REGION_FACE, REGION_NECK
from sage_core.avatar.shading import SHIrradiance
from sage_core.geometry.sh import sh_basis
from sage_core.train.light_prior import SmoothAlbedoLight, neighbour_pairs


def test_neighbour_pairs_match_brute_force():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(300, 3, generator=g, dtype=torch.float64)
    pairs = neighbour_pairs(pts, 5)
    assert tuple(pairs.shape) == (300 * 5, 2)
    d = torch.cdist(pts, pts)
    d.fill_diagonal_(float("inf"))
    expect = d.topk(5, largest=False).indices
    got = pairs[:, 1].reshape(300, 5)
    assert torch.equal(pairs[:, 0].reshape(300, 5), torch.arange(300)[:, None].expand(-1, 5))
    assert torch.equal(torch.sort(got, -1).values, torch.sort(expect, -1).values)
    assert neighbour_pairs(pts[:1], 5).shape == (0, 2)
    assert neighbour_pairs(pts[:3], 5).shape == (3 * 2, 2)


def _sphere_scene(n: int = 6000):
    """Surfels on the unit sphere (normal = position): a skin albedo with a slow, faint variation and a
    chromatically distinct 'lip' cap, shaded by a known white light.
    Returns (means, normals, region_id, albedo, true light)."""
    g = torch.Generator().manual_seed(1)
    x = torch.randn(n, 3, generator=g)
    x = x / x.norm(dim=-1, keepdim=True)
    skin = torch.tensor([0.80, 0.58, 0.45])
    lips = torch.tensor([0.60, 0.25, 0.22])
    albedo = skin * (1.0 + 0.05 * torch.sin(3.0 * x[:, :1]))
    cap = x[:, 2] > 0.8
    albedo[cap] = lips
    true = SHIrradiance()
    with torch.no_grad():
        # ambient + a clamped-cosine-like lobe towards (0.4, 0.6, 0.7), as an order-2 SH fit
        d = torch.tensor([0.4, 0.6, 0.7])
        d = d / d.norm()
        probe = torch.randn(20000, 3, generator=g)
        probe = probe / probe.norm(dim=-1, keepdim=True)
        target = 0.45 + 0.6 * (probe @ d).clamp_min(0.0)
        A = torch.cat([torch.ones(len(probe), 1), sh_basis(probe, 2)[:, 1:]], 1)
        coef = torch.linalg.lstsq(A, target[:, None]).solution[:, 0]
        true.coeffs.copy_((coef / coef[0])[:, None].expand(9, 3))
    region = torch.full((n,), REGION_FACE)
    region[x[:, 0] < -0.9] = REGION_EYES  # not used by the term
    region[x[:, 1] < -0.7] = REGION_NECK
    return x, x.clone(), region, albedo, true


def _fit(term: SmoothAlbedoLight, colors, normals, means, region, steps: int = 600) -> SHIrradiance:
    light = SHIrradiance()
    opt = torch.optim.Adam(light.parameters(), lr=0.02)
    g = torch.Generator().manual_seed(2)
    for _ in range(steps):
        loss = term.loss(light, colors, normals, means, region, 20000, g) + 0.01 * light.mean_prior()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return light


def test_the_term_recovers_the_light_that_shaded_a_smooth_albedo():
    means, normals, region, albedo, true = _sphere_scene()
    with torch.no_grad():
        colors = albedo * true.irradiance(normals)
    colors.requires_grad_(True)
    term = SmoothAlbedoLight(neighbours=16, chroma_sigma=0.02)
    light = _fit(term, colors, normals, means, region)
    assert colors.grad is None  # the colours (the albedo behind them) get no gradient
    with torch.no_grad():
        e_fit = light.irradiance(normals).log()
        e_true = true.irradiance(normals).log()
        a, b = e_fit - e_fit.mean(), e_true - e_true.mean()
        corr = float((a * b).sum() / (a.norm() * b.norm()))
        slope = float((a * b).sum() / (b * b).sum())
        flat = term.loss(SHIrradiance(), colors, normals, means, region)
        exact = term.loss(true, colors, normals, means, region)
    assert corr > 0.97 and 0.8 < slope < 1.2
    assert float(exact) < 1e-4 < float(flat)
    # without the chromaticity weight the lip cap's border pulls the light off
    loose = _fit(SmoothAlbedoLight(neighbours=16, chroma_sigma=100.0), colors, normals, means, region)
    with torch.no_grad():
        e_loose = loose.irradiance(normals).log()
        c = e_loose - e_loose.mean()
        assert float(((c - b) ** 2).mean()) > float(((a - b) ** 2).mean())


def test_the_pairs_cover_face_and_neck_surfels_only_and_follow_the_surfel_count():
    means, normals, region, _, _ = _sphere_scene(800)
    term = SmoothAlbedoLight(neighbours=4)
    used, i, j = term.pairs(means, region)
    assert bool(((region[used] == REGION_FACE) | (region[used] == REGION_NECK)).all())
    assert int(used.numel()) == int(((region == REGION_FACE) | (region == REGION_NECK)).sum())
    assert i.numel() == j.numel() == used.numel() * 4 and int(torch.maximum(i, j).max()) < used.numel()
    used2, _, _ = term.pairs(means[:500], region[:500])
    assert int(used2.max()) < 500
    # same count, moved surfels (relocation): the old pairs stay until reset, then follow the new centres
    moved, moved_region = means[:500].flip(0), region[:500].flip(0)
    assert term.pairs(moved, moved_region) is term.pairs(means[:500], region[:500])
    term.reset()
    used3, i3, j3 = term.pairs(moved, moved_region)
    assert torch.equal(used3, ((moved_region == REGION_FACE) | (moved_region == REGION_NECK)).nonzero().squeeze(-1))
    assert i3.numel() == used3.numel() * 4 and term.state_dict()["points"].equal(moved)
    with pytest.raises(ValueError):
        SmoothAlbedoLight(neighbours=0)
    with pytest.raises(ValueError):
        SmoothAlbedoLight(chroma_sigma=0.0)


def _phase1(tiny_ws, tiny_init_dir, **over):
    from sage_core.config import resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.train.phase1 import Phase1Trainer, build_avatar

    data = IngestedData.open(tiny_ws / "data")
    flags = {"iterations": 6, "n_surfels": 600, "rays_per_step": 32, "neus_samples": 8, "neus_importance": 8, "neus_up_steps": 1,
             "app_hidden": 16, "shape_hidden": 16, "mc_resolution": 32, "eval_every": 0, "rebind_every": 0, "polish_fraction": 0.0,
             "shading": "sh2", "light_albedo_neighbours": 8, **over}  # fmt: skip
    cfg = resolve_config("phase1", "tiny", None, flags)
    g = torch.Generator().manual_seed(4)
    torch.manual_seed(4)
    return Phase1Trainer(build_avatar(data, tiny_init_dir, cfg, "cpu", g), data, cfg, "cpu", g)


def test_phase1_adds_the_term_and_only_the_light_takes_its_gradient(tiny_ws, tiny_init_dir, one_thread):
    tr = _phase1(tiny_ws, tiny_init_dir, w_light_albedo=1.0)
    assert tr.light_albedo is not None
    out = tr.step()
    assert out["light_albedo"] > 0.0
    # the term alone moves the light and nothing else
    av = tr.avatar
    tr.optimizer.zero_grad(set_to_none=True)
    canon = av.canonical_state()
    fr = tr.frames[0]
    inputs, _ = tr.frame_inputs(fr.timestep)
    posed = av.posed(inputs, None, canonical=canon)
    normals = tr.posed_mesh(fr.timestep, inputs, None).R[av.surfels.binding][..., 2]
    tr.light_albedo.loss(av.light, posed.colors, normals, canon.means, av.surfels.region_id).backward()
    assert av.light.coeffs.grad is not None and float(av.light.coeffs.grad.abs().sum()) > 0
    others = [p for n, p in av.named_parameters() if not n.startswith("light.")]
    assert all(p.grad is None or float(p.grad.abs().sum()) == 0.0 for p in others)
    # off by weight 0, and without a light
    assert "light_albedo" not in _phase1(tiny_ws, tiny_init_dir, w_light_albedo=0.0).step()
    assert _phase1(tiny_ws, tiny_init_dir, w_light_albedo=1.0, shading="none").light_albedo is None


def test_nearest_indices_match_brute_force_across_chunks():
    from sage_core.geometry.knn import nearest_indices

    g = torch.Generator().manual_seed(3)
    q, p = torch.rand(50, 3, generator=g), torch.rand(80, 3, generator=g)
    got = nearest_indices(q, p, 4, chunk=7)
    assert torch.equal(got, torch.cdist(q, p).topk(4, dim=1, largest=False).indices)
    own = nearest_indices(p, p, 3, exclude=torch.arange(80), chunk=9)
    assert not bool((own == torch.arange(80)[:, None]).any())
