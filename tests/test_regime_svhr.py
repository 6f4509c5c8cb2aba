"""SV-HR and one-shot pieces: exposure gain, symmetry regularizer, regime defaults, ingest checks,
and the phase-1 trainer with exposure, pose refinement (exact resume) and a mirrored pseudo view."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from sage_core.config import REGIME_OVERRIDES, get_field, resolve_config, to_dict
from sage_core.data.dataset import IngestedData
from sage_core.errors import ConfigError
from sage_core.flame.mirror import mirror_correspondence, model_mirror
from sage_core.train.exposure import ExposureGain
from sage_core.train.pseudo_views import PseudoView
from sage_core.train.symmetry import (
    MirrorPlane,
    color_symmetry_loss,
    plane_from_pairs,
    sdf_symmetry_loss,
)

_SMALL = {
    "n_surfels": 600, "rays_per_step": 32, "neus_samples": 8, "neus_importance": 8, "neus_up_steps": 1,
    "app_hidden": 16, "shape_hidden": 16, "smooth_points": 64, "sym_points": 64, "normal_consistency_from": 1,
    "distortion_from": 1, "eval_every": 0, "iterations": 20,
}  # fmt: skip


# ---------------------------------------------------------------------------- exposure
def test_exposure_gain_scales_the_foreground_only():
    ex = ExposureGain(3, per_channel=True)
    color = torch.rand(4, 5, 3)
    alpha = torch.rand(4, 5)
    assert torch.allclose(ex.apply(color, alpha, 1, 1.0), color)
    assert float(ex.prior().detach()) == 0.0
    with torch.no_grad():
        ex.log_gain[1] = torch.log(torch.tensor([2.0, 1.0, 0.5]))
    out = ex.apply(color, alpha, 1, 1.0)
    back = (1 - alpha)[..., None]
    assert torch.allclose(out, torch.tensor([2.0, 1.0, 0.5]) * (color - back) + back)
    bg_only = torch.ones(4, 5, 3)
    assert torch.allclose(ex.apply(bg_only, torch.zeros(4, 5), 1, 1.0), bg_only)  # background untouched
    assert torch.allclose(ex.apply(color, alpha, 0, 1.0), color)  # other frames unchanged
    assert float(ex.prior().detach()) > 0
    scalar = ExposureGain(2)
    assert scalar.log_gain.shape == (2, 1)
    loss = (scalar.apply(color, alpha, 0, 1.0) - 0.5 * color).abs().mean()
    loss.backward()
    assert scalar.log_gain.grad is not None and float(scalar.log_gain.grad[0].abs()) > 0 and float(scalar.log_gain.grad[1].abs()) == 0


# ---------------------------------------------------------------------------- symmetry
def _sphere(centre):
    c = torch.tensor(centre, dtype=torch.float64)
    return lambda x: (x - c).norm(dim=-1) - 0.3


def test_symmetry_losses_zero_when_symmetric_positive_when_not():
    plane = MirrorPlane(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64), 0.0)
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(200, 3, generator=g, dtype=torch.float64) * 2 - 1
    assert float(sdf_symmetry_loss(_sphere([0.0, 0.1, -0.2]), pts, plane)) == pytest.approx(0.0, abs=1e-12)
    assert float(sdf_symmetry_loss(_sphere([0.1, 0.1, -0.2]), pts, plane)) > 0.05
    sym_color = lambda x, v: torch.stack([x[:, 0].abs(), x[:, 1], v[:, 1]], -1)  # noqa: E731
    asym_color = lambda x, v: torch.stack([x[:, 0], x[:, 1], v[:, 0]], -1)  # noqa: E731
    dirs = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64), dim=-1)
    assert float(color_symmetry_loss(sym_color, pts, dirs, plane)) == pytest.approx(0.0, abs=1e-12)
    assert float(color_symmetry_loss(asym_color, pts, dirs, plane)) > 0.1
    # a tilted plane: reflection is an involution and keeps the plane's points
    n = torch.nn.functional.normalize(torch.tensor([1.0, 0.2, -0.1], dtype=torch.float64), dim=0)
    tilted = MirrorPlane(n, torch.tensor(0.05, dtype=torch.float64), 0.0)
    assert torch.allclose(tilted.reflect(tilted.reflect(pts)), pts, atol=1e-12)
    on = pts - ((pts @ n) - 0.05)[:, None] * n
    assert torch.allclose(tilted.reflect(on), on, atol=1e-12)
    # gradients reach an asymmetric field's parameters
    c = torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    sdf_symmetry_loss(lambda x: (x - c).norm(dim=-1) - 0.3, pts, plane).backward()
    assert c.grad is not None and float(c.grad[0].abs()) > 0


def test_sagittal_plane_of_the_template(tmp_path):
    """The (synthetic) FLAME template mirrors onto itself across x = 0; a moved copy gives the moved plane."""
    from sage_core.data.synthetic import make_capture
    from sage_core.data.synthetic.config import preset
    from sage_core.flame import load_flame_model
    from sage_core.geometry.rotations import axis_angle_to_matrix

    cap = make_capture(tmp_path / "c", preset("tiny", regime="oneshot", width=24, height=32, novel_views=1, novel_expressions=1))
    md = load_flame_model(cap.model_path)
    v = np.asarray(md.v_template)
    mm, reason = model_mirror(md)
    assert mm is not None, reason
    idx = mm.vertex
    assert np.allclose(v[idx], v * [-1, 1, 1], atol=1e-6)
    plane = plane_from_pairs(torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(idx))
    assert torch.allclose(plane.normal, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-6)
    assert abs(float(plane.offset)) < 1e-6 and plane.residual < 1e-6
    R = axis_angle_to_matrix(torch.tensor([[0.0, 0.3, 0.1]], dtype=torch.float64))[0]
    moved = torch.as_tensor(v, dtype=torch.float64) @ R.T + torch.tensor([0.02, 0.0, 0.0], dtype=torch.float64)
    p2 = plane_from_pairs(moved, torch.as_tensor(idx))
    assert torch.allclose(p2.normal, R[:, 0], atol=1e-6)
    assert float(p2.offset) == pytest.approx(0.02 * float(R[0, 0]), abs=1e-6)
    broken, reason = mirror_correspondence(v + np.array([[0.01, 0.0, 0.0]]) * (v[:, :1] > 0), np.asarray(md.faces))
    assert broken is None and reason


# ---------------------------------------------------------------------------- config
def test_regime_defaults_apply_and_yield_to_flags():
    plain = resolve_config("phase1", "tiny")
    assert to_dict(resolve_config("phase1", "tiny", regime="mv-sf")) == to_dict(plain)
    assert to_dict(resolve_config("phase1", "tiny", regime="mv-mf")) == to_dict(plain)
    assert plain.exposure == "off" and plain.loss.sym_sdf == 0 and plain.loss.sym_color == 0 and not plain.pose_refine
    for regime in ("sv-hr", "one-shot"):
        cfg = resolve_config("phase1", "tiny", regime=regime)
        assert cfg.appearance.sh_degree == 0 and cfg.exposure == "gain" and cfg.loss.sym_sdf > 0 and cfg.loss.sym_color > 0
        assert all(get_field(cfg, k) == v for k, v in REGIME_OVERRIDES[regime]["phase1"].items())
    over = resolve_config("phase1", "tiny", {"app_sh_degree": 1}, {"exposure": "rgb"}, regime="sv-hr")
    assert over.appearance.sh_degree == 1 and over.exposure == "rgb"


# ---------------------------------------------------------------------------- ingest
def test_ingest_refuses_captures_that_do_not_fit_and_uses_other_cameras(tiny_capture, monkeypatch):
    import importlib

    from sage_core.data.capture import read_capture
    from sage_core.data.ingest import select_frames

    cap = read_capture(tiny_capture)
    with pytest.raises(ConfigError, match=r"transforms_train\.json: sv-hr needs one camera"):
        select_frames(cap, "sv-hr")
    with pytest.raises(ConfigError, match=r"transforms_train\.json: one-shot uses a single image"):
        select_frames(cap, "one-shot")
    cam = cap.camera_indices("train")[0]
    with pytest.raises(ConfigError, match=r"transforms_train\.json: .*choose one with the timestep option"):
        select_frames(cap, "one-shot", camera=cam)
    sel = select_frames(cap, "sv-hr", camera=cam)
    train_ts = {f.timestep for f in sel.train}
    assert {f.camera_index for f in sel.train} == {cam}
    others = [f for f in sel.val if f.split == "train"]
    assert others and all(f.camera_index != cam and f.timestep in train_ts for f in others)
    n_other = len([f for f in cap.split("train") if f.camera_index != cam and f.timestep in train_ts])
    assert len(others) == n_other
    monkeypatch.setattr(importlib.import_module("sage_core.data.ingest"), "CROSS_VIEW_TIMESTEPS", 1)
    capped = [f for f in select_frames(cap, "sv-hr", camera=cam).val if f.split == "train"]
    assert len({f.timestep for f in capped}) == 1 and len(capped) == n_other // len(train_ts)


# ---------------------------------------------------------------------------- trainer
@pytest.fixture(scope="module")
def svhr_ws(tmp_path_factory):
    from sage_core.data.capture import read_capture
    from sage_core.data.ingest import ingest
    from sage_core.data.synthetic import make_capture
    from sage_core.data.synthetic.config import preset
    from sage_core.train.init_mesh import run_init_mesh

    root = tmp_path_factory.mktemp("svhr")
    cap = make_capture(root / "cap", preset("tiny", regime="monocular", width=48, height=69, train_timesteps=4,
                                            test_timesteps=1, novel_views=1, novel_expressions=1))
    s = ingest(read_capture(cap), cap.model_path, root / "data", regime="sv-hr", workers=1)
    assert s.coverage is not None and "coverage_yaw_min_deg" in s.metrics()
    cfg = resolve_config("init-mesh", "tiny", None, {"pretrain.steps": 10, "pretrain.bank_size": 3000, "pretrain.batch_size": 512,
                                                     "mc_resolution": 24, "pretrain.eval_samples": 1000})
    run_init_mesh(IngestedData.open(root / "data"), root / "init", cfg, seed=0)
    return root


def _trainer(ws, views=None, mirror=None, **over):
    from sage_core.train.phase1 import Phase1Trainer, build_avatar

    data = IngestedData.open(ws / "data")
    cfg = resolve_config("phase1", "tiny", None, {**_SMALL, **over}, regime=data.regime)
    g = torch.Generator().manual_seed(5)
    torch.manual_seed(5)
    av = build_avatar(data, ws / "init", cfg, "cpu", g)
    return Phase1Trainer(av, data, cfg, "cpu", g, pseudo_views=views, mirror_index=mirror)


def test_svhr_steps_with_exposure_and_pose_refinement_resume_exactly(svhr_ws, one_thread):
    tr = _trainer(svhr_ws, pose_refine=True, pose_refine_from=2, exposure="rgb")
    assert tr.exposure is not None and tr.exposure.per_channel and tr.pose is not None and tr.sym_plane is not None
    hist = [tr.step() for _ in range(3)]
    for h in hist:
        assert all(np.isfinite(v) for v in h.values())
        for k in ("rgb", "sym_sdf", "sym_color", "exposure_prior", "pt"):
            assert k in h
    assert "pose_prior" not in hist[1] and "pose_prior" in hist[2]
    assert float(tr.exposure.log_gain.detach().abs().max()) > 0
    assert float(tr.pose.rotation.detach().abs().max()) > 0
    buf = io.BytesIO()
    torch.save(tr.state_dict(), buf)
    ref = [tr.step() for _ in range(2)]
    buf.seek(0)
    state = torch.load(buf, weights_only=False)
    assert "exposure" in state and "pose" in state
    tr2 = _trainer(svhr_ws, pose_refine=True, pose_refine_from=2, exposure="rgb")
    tr2.load_state_dict(state)
    again = [tr2.step() for _ in range(2)]
    for a, b in zip(ref, again):
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-6, abs=1e-7), k
    assert torch.allclose(tr.pose.rotation, tr2.pose.rotation) and torch.allclose(tr.exposure.log_gain, tr2.exposure.log_gain)
    # corrections are baked into the parameters
    baked = tr.pose.bake(tr.avatar.params)
    t0 = tr.pose.timesteps[0]
    r = tr.avatar.params.row_of(t0)
    assert np.allclose(baked.rotation[r] - tr.avatar.params.rotation[r], tr.pose.rotation.detach()[0].numpy(), atol=1e-7)


def test_mirrored_pseudo_view_trains_with_weighted_loss(svhr_ws, one_thread):
    from sage_core.train.phase1 import mirror_transform

    data = IngestedData.open(svhr_ws / "data")
    fr = data.train[0]
    img = torch.as_tensor(data.load_image(fr))
    mask = torch.as_tensor(data.load_mask(fr))
    weight = mask.clone()
    weight[:, : weight.shape[1] // 2] = 0.0
    view = PseudoView("mirror-0", fr.camera, img.flip(1), mask.flip(1), weight, 0, True, 0.5)
    tr0 = _trainer(svhr_ws)
    mm, reason = model_mirror(tr0.avatar.model_data)
    assert mm is not None, reason
    mirror = torch.as_tensor(mm.vertex)
    with pytest.raises(ValueError, match="mirror index"):
        _trainer(svhr_ws, views=[view])
    tr = _trainer(svhr_ws, views=[view], mirror=mirror, pseudo_view_prob=1.0)
    h = tr.step()
    assert "pseudo_rgb" in h and "rgb" not in h and "neus_rgb" not in h and h["pseudo_view"] == 0.0
    assert np.isfinite(h["loss"]) and "sym_sdf" in h and "pt" in h
    # the mirrored posing: vertices are S·v_m(i), and the surfels follow their mirrored triangles
    av = tr.avatar
    inputs = tr.inputs(fr.timestep)
    f = mirror_transform(mirror)
    with torch.no_grad():
        v = av.pose_mesh(inputs)
        vm = f(v)
        assert torch.allclose(vm, v[mirror] * torch.tensor([-1.0, 1.0, 1.0]))
        p = av.posed(inputs, None, vertex_transform=f)
        q = av.posed(inputs, None, vertices=vm)
        assert torch.allclose(p.means, q.means) and torch.allclose(p.vertices, vm)
        plain = av.posed(inputs, None)
        assert not torch.allclose(p.means, plain.means)
    # a zero weight map gives a zero photometric term
    zero = PseudoView("blank", fr.camera, img, mask, torch.zeros_like(weight), 0, False, 1.0)
    tr3 = _trainer(svhr_ws, views=[zero], mirror=None, pseudo_view_prob=1.0)
    assert tr3.step()["pseudo_rgb"] == 0.0


def test_clip_cameras_seen_from_the_canonical_head(svhr_ws):
    """Surfel initialisation sees the head-turn clip's camera from each frame's own side of the head."""
    from sage_core.avatar.model import _clip_cameras_at_canonical, _rigid_world_from_canonical
    from sage_core.flame import FlameModel
    from sage_core.flame.canonical import canonical_inputs
    from sage_core.data.coverage import Coverage

    data = IngestedData.open(svhr_ws / "data")
    params, ct = data.params, data.canonical_timestep
    with torch.no_grad():
        J0 = FlameModel(data.load_model())(**canonical_inputs(params, ct)).joints[0, 0]
    W_ct = _rigid_world_from_canonical(params, params.row_of(ct), J0)
    cams = _clip_cameras_at_canonical(data, params, ct, J0, W_ct, limit=3)
    assert len(cams) == 3
    cov = Coverage.from_dict(data.summary["coverage"])
    inv = np.linalg.inv(W_ct)
    yaws = []
    for cam in cams:
        c = cam.center
        c_mesh = inv[:3, :3] @ c + inv[:3, 3]  # the camera centre in canonical-mesh coordinates
        yaws.append(np.degrees(np.arctan2(c_mesh[0], c_mesh[2])))
    assert yaws[0] == pytest.approx(cov.yaw[0], abs=5.0) and yaws[-1] == pytest.approx(cov.yaw[-1], abs=5.0)
    assert max(yaws) - min(yaws) > 60.0
