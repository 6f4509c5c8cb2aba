"""Adaptive density control of free surfels (the GaussianAvatars baseline): the projected-centre
gradient statistic over the views that keep a surfel, clone / split / prune / opacity reset with
binding inheritance and GA's last-surfel-per-triangle rule, GA's schedule (strict start, the reset
at the start, large surfels pruned past the first reset interval), the position rate scaled by the
scene extent, the local terms on visible surfels, the optimizer state that follows the rows, a
per-face initialisation, the teeth-only mouth, and exact resume of a phase 1 whose surfel count
changes."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch

from sage_core.avatar.init import init_surfels
from sage_core.avatar.surfels import SurfelSet
from sage_core.config import resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.errors import ConfigError
from sage_core.render import RenderCamera
from sage_core.train.densify import (
    RESET_OPACITY,
    SPLIT_SCALE_DIVISOR,
    DensifySchedule,
    DensityControl,
    keep_last_per_face,
    ndc_gradient_norm,
    scene_extent,
)
from sage_core.train.losses import local_position_loss, local_scale_loss
from sage_core.train.phase1 import Phase1Trainer, build_avatar

_GA = {
    "attributes": "free", "init_layout": "per_face", "densify": True, "densify_from": 2, "densify_every": 2,
    "densify_until": 6, "opacity_reset_every": 4, "densify_grad_threshold": 1e-7, "sdf_from": 10**9,
    "w_normal_consistency": 0.0, "w_distortion": 0.0, "w_mask": 0.0, "rebind_every": 0,
    "w_local_position": 0.01, "w_local_scale": 1.0, "eval_every": 0, "mc_resolution": 32,
}  # fmt: skip


def _camera() -> RenderCamera:
    K = torch.tensor([[120.0, 0.0, 64.0], [0.0, 110.0, 48.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    ang = 0.3
    w2c[:3, :3] = torch.tensor([[math.cos(ang), 0.0, math.sin(ang)], [0.0, 1.0, 0.0], [-math.sin(ang), 0.0, math.cos(ang)]])
    w2c[:3, 3] = torch.tensor([0.02, -0.01, 1.0])
    return RenderCamera(K=K, w2c=w2c, width=128, height=96)


def test_ndc_gradient_norm_is_exact_for_a_loss_on_the_projected_centre():
    torch.manual_seed(0)
    cam = _camera()
    means = (0.05 * torch.randn(20, 3, dtype=torch.float64)).requires_grad_(True)
    w = torch.randn(20, 2, dtype=torch.float64)
    R, t, K = cam.w2c[:3, :3].double(), cam.w2c[:3, 3].double(), cam.K.double()
    xc = means @ R.T + t
    uv = torch.stack([K[0, 0] * xc[:, 0] / xc[:, 2] + K[0, 2], K[1, 1] * xc[:, 1] / xc[:, 2] + K[1, 2]], -1)
    ndc = torch.stack([uv[:, 0] / (0.5 * cam.width) - 1.0, uv[:, 1] / (0.5 * cam.height) - 1.0], -1)
    (ndc * w).sum().backward()
    got = ndc_gradient_norm(means.detach(), means.grad, cam)
    assert torch.allclose(got, w.norm(dim=-1), rtol=1e-6, atol=1e-9)  # the float32 camera rotation is orthonormal to ~1e-7


def _surfels(n: int = 6) -> SurfelSet:
    g = torch.Generator().manual_seed(1)
    s = SurfelSet(torch.arange(n) % 3, 0.1 * torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g), torch.randn(n, 2, generator=g) * 0.1,
                  torch.arange(n) % 2, torch.tensor([0, 1, 0]), attributes="free", sh_degree=1, opacity=0.5)  # fmt: skip
    return s


def test_extend_appends_rows_and_zero_optimizer_state():
    s = _surfels()
    opt = torch.optim.Adam([s.mu_loc, s.opacity], lr=0.1)
    (s.mu_loc.sum() + s.opacity.sum()).backward()
    opt.step()
    old_mu, old_m = s.mu_loc.detach().clone(), opt.state[s.mu_loc]["exp_avg"].clone()
    rows = {k: v.detach()[:2].clone() + 1.0 for k, v in s._row_tensors().items()}
    assert s.extend(rows, opt) == 2
    assert len(s) == 8 and torch.equal(s.mu_loc[:6], old_mu) and torch.equal(s.mu_loc[6:], rows["mu_loc"])
    assert torch.equal(s.binding[6:], rows["binding"]) and s.sh_rest.shape == (8, 3, 3)
    st = opt.state[s.mu_loc]
    assert torch.equal(st["exp_avg"][:6], old_m) and bool((st["exp_avg"][6:] == 0).all())
    assert any(p is s.mu_loc for p in opt.param_groups[0]["params"])
    with pytest.raises(ValueError, match="missing"):
        s.extend({"binding": rows["binding"]})


class _StubAvatar:
    """What DensityControl reads of an avatar: free surfels, the canonical frames and base_scale."""

    attributes = "free"

    def __init__(self, surfels: SurfelSet) -> None:
        self.surfels = surfels
        F = 3
        self.R_c = torch.eye(3).expand(F, 3, 3).clone()
        self.T_c = torch.arange(F, dtype=torch.float32)[:, None].expand(F, 3).clone()
        self.k_c = torch.tensor([0.01, 0.01, 0.02])
        self.base_scale = torch.ones(len(surfels))


def test_clone_split_prune_and_reset():
    s = _surfels(6)
    with torch.no_grad():
        s.s_loc.zero_()
        s.s_loc[1] = math.log(5.0)  # large: 0.05 m > 0.01 * extent(1.0)
        s.opacity[2] = -10.0  # nearly transparent: pruned
    av = _StubAvatar(s)
    sched = DensifySchedule(0, 100, 10, grad_threshold=0.5, percent_dense=0.01, prune_opacity=0.005, reset_every=50)
    assert sched.prune_large_now(60) and not sched.prune_large_now(50)
    dc = DensityControl(av, sched, extent=1.0, generator=torch.Generator().manual_seed(0))  # type: ignore[arg-type]
    opt = torch.optim.Adam([s.mu_loc, s.q_loc, s.s_loc, s.sh_dc, s.sh_rest, s.opacity], lr=0.01)
    dc.grad_sum[:] = torch.tensor([1.0, 1.0, 0.0, 0.1, 0.0, 0.0], dtype=torch.float64)
    dc.count[:] = 1.0
    parent_binding, parent_mu, parent_s = int(s.binding[1]), s.mu_loc[1].detach().clone(), s.s_loc[1].detach().clone()
    out = dc.densify_and_prune(opt, 10)
    assert out == {"cloned": 1, "split": 1, "pruned": 1, "surfels": 6 - 1 - 1 + 1 + 2}
    assert len(s) == 7 and av.base_scale.shape == (7,)
    # the split children: parent's triangle, scales / 1.6, offsets within the parent's plane
    kids = slice(5, 7)
    assert bool((s.binding[kids] == parent_binding).all())
    assert torch.allclose(s.s_loc[kids], parent_s.expand(2, 2) - math.log(SPLIT_SCALE_DIVISOR))
    from sage_core.geometry.rotations import quat_normalize, quat_to_matrix

    normal = quat_to_matrix(quat_normalize(s.q_loc[5:6].detach()))[0, :, 2]
    d = s.mu_loc[kids].detach() - parent_mu
    assert torch.allclose(d @ normal, torch.zeros(2), atol=1e-6) and bool((d.norm(dim=-1) > 0).all())
    assert float(dc.count.sum()) == 0 and dc.grad_sum.shape == (7,)
    for p in opt.param_groups[0]["params"]:
        assert p.shape[0] == 7
    dc.reset_opacity(opt)
    assert float(torch.sigmoid(s.opacity.detach()).max()) <= RESET_OPACITY + 1e-6 and dc.resets == 1


def test_schedule():
    sc = DensifySchedule(100, 1000, 50, 2e-4, 0.01, 0.005, 500)
    # GaussianAvatars densifies strictly after its start step, resets on multiples before the stop
    assert [t for t in range(0, 1100, 50) if sc.densify_now(t)] == list(range(150, 1000, 50))
    assert [t for t in range(1, 1500) if sc.reset_now(t)] == [500]
    assert [t for t in range(1, 1500) if sc.prune_large_now(t)] == list(range(501, 1500))
    # and, on a white background, once more at the start
    ga = DensifySchedule.from_config(resolve_config("phase1", "tiny", None, {"densify_from": 25, "densify_until": 1500, "opacity_reset_every": 500}).densify)
    assert ga.reset_at_start and [t for t in range(1, 1600) if ga.reset_now(t)] == [25, 500, 1000]
    assert scene_extent(torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]])) == pytest.approx(1.1)


def test_prune_never_empties_a_triangle():
    binding = torch.tensor([0, 0, 1, 1, 2, 3])
    remove = torch.tensor([True, False, True, True, True, False])
    # triangle 0 keeps its unmarked surfel; 1 and 2 would lose all: theirs stay; 3 is untouched
    assert keep_last_per_face(remove, binding).tolist() == [True, False, False, False, False, False]
    assert not keep_last_per_face(torch.zeros(6, dtype=torch.bool), binding).any()


def test_statistics_count_every_kept_view():
    """3DGS's denominator: a surfel kept for the view counts it even when no gradient reached it
    (occluded); one outside the view neither adds nor counts."""
    s = _surfels(4)
    dc = DensityControl(_StubAvatar(s), DensifySchedule(0, 10, 1, 1.0, 0.01, 0.005, 0), 1.0, torch.Generator())  # type: ignore[arg-type]
    cam = _camera()
    means = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    means.grad = torch.tensor([[1.0, 0, 0], [0, 0, 0], [1.0, 0, 0], [0, 0, 0]], dtype=torch.float64)
    dc.accumulate(means, cam, torch.tensor([True, True, False, False]))
    assert dc.count.tolist() == [1.0, 1.0, 0.0, 0.0]
    assert float(dc.grad_sum[0]) > 0 and dc.grad_sum[1:].tolist() == [0.0, 0.0, 0.0]
    means.grad = None
    dc.accumulate(means, cam, torch.tensor([True, False, True, False]))
    assert dc.count.tolist() == [2.0, 1.0, 1.0, 0.0] and dc.grad_sum[2] == 0


def test_local_terms_average_over_the_given_rows():
    from types import SimpleNamespace

    from sage_core.train.phase1 import Phase1Step

    mu = torch.tensor([[3.0, 0, 0], [0.5, 0, 0], [0, 0, 2.0]])
    vis = torch.tensor([True, True, False])
    step = SimpleNamespace(render=SimpleNamespace(visible=vis))
    rows = Phase1Step.visible_rows(step, mu)  # type: ignore[arg-type]
    assert local_position_loss(rows, 1.0).item() == pytest.approx(1.0)  # (2 + 0) / 2 visible
    assert local_position_loss(mu, 1.0).item() == pytest.approx(1.0)  # (2 + 0 + 1) / 3
    assert local_position_loss(mu[:0], 1.0).item() == 0.0 and local_scale_loss(torch.zeros(0, 2), 0.6).item() == 0.0
    assert Phase1Step.visible_rows(SimpleNamespace(render=SimpleNamespace(visible=None)), mu) is mu  # type: ignore[arg-type]


def test_per_face_layout():
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    f = torch.tensor([[0, 1, 2], [1, 3, 2]])
    init = init_surfels(v, f, 1, layout="per_face")
    assert init.binding.tolist() == [0, 1]
    assert torch.equal(init.mu_loc, torch.zeros(2, 3)) and torch.equal(init.s_loc, torch.zeros(2, 2))
    with pytest.raises(ValueError, match="layout"):
        init_surfels(v, f, 1, layout="grid")


def test_config_rules():
    with pytest.raises(ConfigError, match="free"):
        resolve_config("phase1", "tiny", None, {"densify": True, "attributes": "mlp"})
    with pytest.raises(ConfigError, match="free"):
        resolve_config("phase1", "tiny", None, {"w_local_scale": 1.0})


def test_teeth_only_mouth(tiny_ws):
    from sage_core.flame.mouth import has_mouth_interior
    from sage_core.flame.teeth import has_teeth
    from sage_core.train.init_mesh import build_model

    data = IngestedData.open(tiny_ws / "data")
    full, _ = build_model(data, True, cavity=True)
    teeth, regions = build_model(data, True, cavity=False)
    base, _ = build_model(data, False)
    assert has_mouth_interior(full) and not has_mouth_interior(teeth) and has_teeth(teeth)
    assert base.faces.shape[0] < teeth.faces.shape[0] < full.faces.shape[0]
    assert regions is not None and regions.has("teeth") and "teeth-arcs" in teeth.face_table


def _ga_trainer(ws_dir, init_dir, **over):
    data = IngestedData.open(ws_dir / "data")
    cfg = resolve_config("phase1", "tiny", None, {**_GA, "iterations": 8, **over})
    g = torch.Generator().manual_seed(5)
    torch.manual_seed(5)
    return Phase1Trainer(build_avatar(data, init_dir, cfg, "cpu", g), data, cfg, "cpu", g)


def test_phase1_densifies_and_resumes_exactly(tiny_ws, tiny_init_dir, one_thread):
    n = 8
    ref = _ga_trainer(tiny_ws, tiny_init_dir)
    n0 = len(ref.avatar.surfels)
    assert n0 == ref.avatar.faces.shape[0]
    straight = [ref.step() for _ in range(n)]
    assert len(ref.avatar.surfels) != n0 and any("densify_surfels" in h for h in straight)
    # every triangle keeps a surfel; the position rate is GA's scaled by the scene extent
    assert torch.bincount(ref.avatar.surfels.binding, minlength=n0).min() >= 1
    c, ext = ref.cfg, ref.density.extent  # type: ignore[union-attr]
    assert ext > 0.5 and ref.position_lr_scale == ext
    t = (n - 1) / c.iterations
    want = math.exp((1 - t) * math.log(c.lr.position) + t * math.log(c.lr.position_final)) * ext
    assert next(g["lr"] for g in ref.optimizer.param_groups if g["name"] == "mu_loc") == pytest.approx(want)
    assert all(np.isfinite(h["local_position"]) and np.isfinite(h["local_scale"]) for h in straight)

    first = _ga_trainer(tiny_ws, tiny_init_dir)
    part = [first.step() for _ in range(5)]  # past a densification: the surfel count differs from a fresh build
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    second = _ga_trainer(tiny_ws, tiny_init_dir)
    buf.seek(0)
    second.load_state_dict(torch.load(buf, weights_only=False))
    part += [second.step() for _ in range(n - 5)]
    for a, b in zip(straight, part):
        assert set(a) == set(b)
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-6, abs=1e-7), k
    assert torch.equal(ref.avatar.surfels.binding, second.avatar.surfels.binding)
