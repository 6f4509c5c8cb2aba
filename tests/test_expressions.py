"""Expression sampler for phase 2."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sage_core.train.expressions import ExpressionSampler, component_ranges_from_dirs

KEYS = {"expr": 20, "jaw_pose": 3, "eyes_pose": 6, "neck_pose": 3, "rotation": 3, "translation": 3}


def _std(E=20):
    return torch.linspace(0.5, 2.0, E)


def test_shapes_dtype_and_ranges():
    s = ExpressionSampler(20, _std(), clip_sigma=2.0, n_active=4, jaw_range=(0.05, 0.3), eye_range=0.1,
                          neck_std=0.02, rotation_std=0.03, translation_std=0.004, seed=1)
    out = s.sample(500)
    assert set(out) == set(KEYS)
    for k, w in KEYS.items():
        assert out[k].shape == (500, w) and out[k].dtype == torch.float32
    std = _std()
    assert torch.all(out["expr"].abs() <= 2.0 * std + 1e-6)
    active = (out["expr"] != 0).sum(1)
    assert active.max() <= 4 and active.min() >= 1 and (active == 4).any() and (active == 1).any()
    # every component gets used, with a spread that follows its std
    assert torch.all((out["expr"] != 0).sum(0) > 0)
    jaw = out["jaw_pose"]
    assert torch.all(jaw[:, 0] >= 0.05 - 1e-7) and torch.all(jaw[:, 0] <= 0.3 + 1e-7) and torch.all(jaw[:, 1:] == 0)
    assert jaw[:, 0].max() - jaw[:, 0].min() > 0.2
    eyes = out["eyes_pose"]
    assert torch.all(eyes.abs() <= 0.1 + 1e-7) and torch.equal(eyes[:, :3], eyes[:, 3:]) and torch.all(eyes[:, 2] == 0)
    assert torch.all(out["neck_pose"].abs() <= 0.04 + 1e-7) and out["neck_pose"].std() > 0.01
    assert torch.all(out["rotation"].abs() <= 0.06 + 1e-7)
    assert torch.all(out["translation"].abs() <= 0.008 + 1e-7)


def test_reproducible_with_seed_and_generator():
    a = ExpressionSampler(20, 1.0, seed=7).sample(16)
    b = ExpressionSampler(20, 1.0, seed=7).sample(16)
    c = ExpressionSampler(20, 1.0, seed=8).sample(16)
    for k in KEYS:
        assert torch.equal(a[k], b[k])
    assert not torch.equal(a["expr"], c["expr"])
    s = ExpressionSampler(20, 1.0, seed=0)
    g1 = torch.Generator().manual_seed(3)
    g2 = torch.Generator().manual_seed(3)
    x, y = s.sample(8, generator=g1), s.sample(8, generator=g2)
    assert all(torch.equal(x[k], y[k]) for k in KEYS)
    # successive draws from the sampler's own generator differ
    assert not torch.equal(s.sample(8)["expr"], s.sample(8)["expr"])


def test_mixture_with_observed_expressions_stays_near_them():
    g = torch.Generator().manual_seed(0)
    observed = torch.randn(5, 20, generator=g) * 2
    observed_jaw = torch.zeros(5, 3)
    observed_jaw[:, 0] = torch.tensor([0.0, 0.1, 0.2, 0.25, 0.3])
    s = ExpressionSampler(20, 0.5, observed_expr=observed, observed_jaw=observed_jaw, observed_weight=1.0,
                          observed_noise=0.02, jaw_range=(0.0, 0.3), n_active=3, seed=2)
    out = s.sample(200)
    d = torch.cdist(out["expr"].double(), observed.double()).min(1).values
    # noise std 0.01 per component over 20 components: distances of about 0.045, never near 1
    assert d.max() < 0.1
    picked = torch.cdist(out["expr"].double(), observed.double()).argmin(1)
    assert len(set(picked.tolist())) == 5
    assert torch.all((out["jaw_pose"][:, 0] - observed_jaw[picked, 0]).abs() < 0.03)
    # a half-and-half mixture: about half the samples are near an observed row, the rest are sparse
    s2 = ExpressionSampler(20, 0.5, observed_expr=observed.numpy(), observed_weight=0.5, observed_noise=0.02,
                           n_active=3, seed=2)
    out2 = s2.sample(400)
    near = torch.cdist(out2["expr"].double(), observed.double()).min(1).values < 0.1
    assert 0.35 < near.float().mean() < 0.65
    assert torch.all((out2["expr"][~near] != 0).sum(1) <= 3)


def test_observed_columns_padded_and_validation():
    s = ExpressionSampler(10, 1.0, observed_expr=np.ones((3, 6), np.float32), observed_weight=1.0, observed_noise=0.0)
    out = s.sample(4)
    assert torch.allclose(out["expr"][:, :6], torch.ones(4, 6)) and torch.all(out["expr"][:, 6:] == 0)
    with pytest.raises(ValueError):
        ExpressionSampler(10, torch.ones(9))
    with pytest.raises(ValueError):
        ExpressionSampler(10, 1.0, jaw_range=(0.3, 0.1))
    with pytest.raises(ValueError):
        ExpressionSampler(10, 1.0, observed_expr=np.ones((3, 10)), observed_jaw=np.zeros((2, 3)))


def test_component_ranges_from_dirs():
    V, E = 50, 4
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(V, 3, E, generator=g, dtype=torch.float64) * 1e-3
    dirs[:, :, 3] = 0.0
    std = component_ranges_from_dirs(dirs, target=0.01)
    assert std.shape == (E,) and std[3] == 0
    # one std of component e moves the most-affected vertex by exactly the target
    for e in range(3):
        disp = (dirs[:, :, e] * float(std[e])).norm(dim=-1)
        assert abs(disp.max().item() - 0.01) < 1e-7
    mask = torch.zeros(V, dtype=torch.bool)
    mask[:10] = True
    std_m = component_ranges_from_dirs(dirs.numpy(), target=0.01, vertex_mask=mask)
    assert torch.all(std_m[:3] >= std[:3] - 1e-7)
    # feeds the sampler: a sample's largest displacement is bounded by clip_sigma·target per active component
    s = ExpressionSampler(E, std, clip_sigma=2.0, n_active=1, seed=0)
    expr = s.sample(100)["expr"].double()
    disp = torch.einsum("vce,ne->nvc", dirs, expr).norm(dim=-1).amax(1)
    assert disp.max() <= 0.02 + 1e-6 and disp.max() > 0.005
