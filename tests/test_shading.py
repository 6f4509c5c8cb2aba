"""The optional albedo × world-normal shading model and the exposure gains stored with the avatar."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from sage_core.avatar.corrected import CorrectedPosing
from sage_core.avatar.correction import SurfelCorrection
from sage_core.avatar.model import Avatar, canonical_to_world_rigid
from sage_core.avatar.shading import SHIrradiance, orient_outward, shade_foreground
from sage_core.config import resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.export.avatar_ply import encode_posed_ply, sh_dc_to_rgb
from sage_core.export.ply import decode_ply
from sage_core.flame.canonical import canonical_inputs
from sage_core.flame.frames import surfel_frames
from sage_core.geometry.rotations import axis_angle_to_matrix, quat_to_matrix

_Y1 = 0.4886025119029199


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True)


def _directional(light: SHIrradiance, direction: torch.Tensor, strength: float) -> None:
    """Set a first-order light E(n) = 1 + strength·(n·l) (3DGS basis signs: Y_1..3 ∝ (−y, z, −x))."""
    lx, ly, lz = (float(v) for v in _unit(direction))
    with torch.no_grad():
        light.coeffs.zero_()
        light.coeffs[0] = 1.0
        light.coeffs[1] = -strength * ly / _Y1
        light.coeffs[2] = strength * lz / _Y1
        light.coeffs[3] = -strength * lx / _Y1


def _coloured_light(light: SHIrradiance, seed: int = 5) -> None:
    """A non-trivial light of all nine coefficients, positive over the sphere."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        light.coeffs.copy_(0.15 * torch.randn(light.coeffs.shape, generator=g))
        light.coeffs[0] = torch.tensor([1.0, 0.9, 1.1])


# ------------------------------------------------------------------ the irradiance model
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constant_init_is_exactly_one(dtype):
    light = SHIrradiance()
    n = _unit(torch.randn(500, 3, dtype=dtype, generator=torch.Generator().manual_seed(0)))
    e = light.irradiance(n)
    assert e.shape == (500, 3) and e.dtype == dtype
    assert torch.equal(e, torch.ones_like(e))
    assert float(light.mean_prior().detach()) == 0.0


def test_first_order_light_is_brighter_facing_it_and_floored():
    light = SHIrradiance(floor=0.05)
    l_dir = torch.tensor([0.3, -0.5, 0.8])
    _directional(light, l_dir, 0.5)
    lu = _unit(l_dir)
    n = _unit(torch.randn(2000, 3, generator=torch.Generator().manual_seed(1)))
    e = light.irradiance(n)
    assert torch.allclose(e, (1.0 + 0.5 * (n @ lu))[:, None].expand(-1, 3), atol=1e-5)
    facing, away = light.irradiance(lu[None]), light.irradiance(-lu[None])
    assert torch.allclose(facing, torch.full((1, 3), 1.5), atol=1e-5)
    assert torch.allclose(away, torch.full((1, 3), 0.5), atol=1e-5)
    assert bool((facing >= e - 1e-6).all()) and bool((away <= e + 1e-6).all())
    # a light stronger than its ambient part is clamped at the floor on the far side
    _directional(light, l_dir, 2.0)
    assert torch.allclose(light.irradiance(-lu[None]), torch.full((1, 3), 0.05))
    assert float(light.irradiance(n).detach().min()) >= 0.05


def test_gradient_reaches_every_coefficient():
    light = SHIrradiance()
    n = _unit(torch.randn(300, 3, generator=torch.Generator().manual_seed(2)))
    w = torch.randn(300, 3, generator=torch.Generator().manual_seed(3))
    (light.irradiance(n) * w).sum().backward()
    assert light.coeffs.grad is not None
    assert bool((light.coeffs.grad.abs() > 0).all())
    # analytic gradient of the band-0 row: the sum of the weights
    assert torch.allclose(light.coeffs.grad[0], w.sum(0), atol=1e-4)
    light.zero_grad()
    with torch.no_grad():
        light.coeffs[0] += 0.2
    light.mean_prior().backward()
    assert light.coeffs.grad is not None and float(light.coeffs.grad[0].abs().min()) > 0


def test_orient_outward_and_shade_foreground():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    ref = torch.tensor([[0.0, 0.2, -1.0], [0.1, 1.0, 0.0], [-1.0, 0.0, 0.3]])
    out = orient_outward(n, ref)
    assert torch.equal(out, torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))
    fg = torch.tensor([[0.2, 0.4, 0.6], [0.5, 0.5, 0.5]])
    alpha = torch.tensor([1.0, 0.25])
    composite = fg * alpha[:, None] + (1 - alpha[:, None]) * 1.0
    e = torch.tensor([[2.0, 1.0, 0.5], [2.0, 2.0, 2.0]])
    got = shade_foreground(composite, alpha, e, 1.0)
    assert torch.allclose(got, e * fg * alpha[:, None] + (1 - alpha[:, None]), atol=1e-6)


# ------------------------------------------------------------------ the avatar
@pytest.fixture(scope="module")
def data(tiny_ws):
    return IngestedData.open(tiny_ws / "data")


@pytest.fixture(scope="module")
def init_dir(tiny_init_dir):
    return tiny_init_dir


def _avatar(init_dir, data, mode="mlp", shading=None, n=300):
    g = torch.Generator().manual_seed(1)
    torch.manual_seed(2)
    kw = {} if shading is None else {"shading": shading}
    av = Avatar.build(init_dir, data, n, mode, app_args={"hidden": 16, "sh_degree": 1}, shape_args={"hidden": 16}, sh_degree=1,
                      generator=g, **kw)  # fmt: skip
    with torch.no_grad():
        av.surfels.mu_loc.add_(0.1 * torch.randn(av.surfels.mu_loc.shape, generator=g))
        av.surfels.q_loc.add_(0.2 * torch.randn(av.surfels.q_loc.shape, generator=g))
        if mode == "free":
            av.surfels.sh_rest.add_(0.1 * torch.randn(av.surfels.sh_rest.shape, generator=g))
            av.surfels.sh_dc.add_(0.3 * torch.randn(av.surfels.sh_dc.shape, generator=g))
    return av


def _outward_normals(av: Avatar, p) -> torch.Tensor:
    R_p, _, _ = surfel_frames(p.vertices, av.faces)
    return orient_outward(quat_to_matrix(p.quats)[..., 2], R_p[av.surfels.binding][..., 2])


@pytest.mark.parametrize("mode", ["mlp", "free"])
def test_none_and_untrained_sh2_leave_colours_unchanged(init_dir, data, mode):
    plain = _avatar(init_dir, data, mode)
    none = _avatar(init_dir, data, mode, "none")
    sh2 = _avatar(init_dir, data, mode, "sh2")
    assert plain.shading == "none" and plain.light is None
    assert not any(k.startswith("light.") for k in none.state_dict())
    assert set(plain.state_dict()) == set(none.state_dict())
    assert set(sh2.state_dict()) - set(none.state_dict()) == {"light.coeffs"}
    inputs = plain.frame_inputs(data.test[0].timestep)
    cam = torch.tensor([0.1, 0.0, 1.0])
    with torch.no_grad():
        p0 = plain.posed(inputs, cam)
        p1 = none.posed(inputs, cam)
        p1_albedo = none.posed(inputs, cam, shade=False)
        p2 = sh2.posed(inputs, cam)
    assert torch.equal(p0.colors, p1.colors) and torch.equal(p1.colors, p1_albedo.colors)
    assert torch.equal(p0.means, p2.means) and torch.equal(p0.quats, p2.quats)
    assert torch.equal(p0.colors, p2.colors)


@pytest.mark.parametrize("mode", ["mlp", "free"])
def test_world_light_follows_a_rigid_head_turn(init_dir, data, mode):
    none = _avatar(init_dir, data, mode, "none")
    sh2 = _avatar(init_dir, data, mode, "sh2")
    _coloured_light(sh2.light)
    inputs = none.frame_inputs(data.test[0].timestep)
    aa, t = torch.tensor([[0.0, 0.6, 0.1]]), torch.tensor([[0.01, 0.0, 0.02]])
    base = dict(inputs, rotation=torch.zeros(1, 3), translation=torch.zeros(1, 3))
    moved = dict(inputs, rotation=aa, translation=t)
    R0 = axis_angle_to_matrix(aa)[0]
    cam0 = torch.tensor([0.05, 0.02, 1.0])
    cam1 = canonical_to_world_rigid(cam0[None], R0, t[0], none.root_joint)[0]
    with torch.no_grad():
        n0, n1 = none.posed(base, cam0), none.posed(moved, cam1)
        s0, s1 = sh2.posed(base, cam0), sh2.posed(moved, cam1)
        a1 = sh2.posed(moved, cam1, shade=False)
    # head-space colour: a rigid motion (with the camera moving along) changes nothing
    assert torch.allclose(n0.colors, n1.colors, atol=1e-5)
    # albedo is the head-space colour; the shaded colour is albedo × E(world normal)
    assert torch.allclose(a1.colors, n1.colors, atol=1e-6)
    assert torch.allclose(s1.colors, a1.colors * sh2.light.irradiance(_outward_normals(sh2, s1)), atol=1e-6)
    # the light stays in the world while the head turns: the shading changes
    diff = (s1.colors - s0.colors).abs().amax(-1)
    assert float(diff.max()) > 0.02 and float((diff > 1e-3).float().mean()) > 0.5
    # the outward normal turned with the head
    assert torch.allclose(_outward_normals(sh2, s1), _outward_normals(sh2, s0) @ R0.T, atol=1e-4)
    # the outward normals face away from the head centre for most surfels
    nrm = _outward_normals(sh2, s0)
    centre = s0.vertices.mean(0)
    assert float(((nrm * (s0.means - centre)).sum(-1) > 0).float().mean()) > 0.8


def test_light_transform_reflects_the_normals(init_dir, data):
    sh2 = _avatar(init_dir, data, "mlp", "sh2")
    _directional(sh2.light, torch.tensor([1.0, 0.0, 0.3]), 0.6)
    inputs = sh2.frame_inputs(data.canonical_timestep)
    S = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))
    with torch.no_grad():
        p = sh2.posed(inputs, None, light_transform=S)
        a = sh2.posed(inputs, None, shade=False)
        plain = sh2.posed(inputs, None)
    assert torch.allclose(p.colors, a.colors * sh2.light.irradiance(_outward_normals(sh2, p) @ S.T), atol=1e-6)
    assert float((p.colors - plain.colors).abs().max()) > 0.02


def test_save_load_keeps_shading_light_and_gains(init_dir, data, tmp_path):
    sh2 = _avatar(init_dir, data, "mlp", "sh2")
    _coloured_light(sh2.light)
    gains = {(data.train[0].timestep, data.train[0].camera_index): [1.2], (data.train[1].timestep, data.train[1].camera_index): [0.9]}
    sh2.set_exposure_gains(gains)
    path = sh2.save(tmp_path / "a.pt")
    back = Avatar.load(path)
    assert back.shading == "sh2" and back.light is not None
    assert torch.equal(back.light.coeffs, sh2.light.coeffs)
    fr0, fr1 = data.train[0], data.train[1]
    assert torch.allclose(back.exposure_gain(fr0.timestep, fr0.camera_index), torch.tensor([1.2]))
    assert torch.allclose(back.exposure_gain(fr1.timestep, fr1.camera_index), torch.tensor([0.9]))
    assert back.exposure_gain(10**6, 0) is None
    inputs = sh2.frame_inputs(data.test[0].timestep)
    with torch.no_grad():
        assert torch.equal(back.posed(inputs, None).colors, sh2.posed(inputs, None).colors)
    with pytest.raises(ValueError):
        sh2.set_exposure_gains({(0, 0): [1.0, 2.0]})


def test_old_avatar_files_still_load(init_dir, data, tmp_path):
    av = _avatar(init_dir, data, "free", "none")
    from sage_core.avatar.model import AVATAR_FORMAT, AVATAR_KIND
    from sage_core.serialization import load_file, save_file

    path = av.save(tmp_path / "new.pt")
    blob, _ = load_file(path, AVATAR_KIND, AVATAR_FORMAT, "avatar file")
    assert blob["args"]["shading"] == "none" and "exposure_gains" not in blob
    del blob["args"]["shading"]
    old = tmp_path / "old.pt"
    save_file(old, blob, AVATAR_KIND, AVATAR_FORMAT)
    back = Avatar.load(old)
    assert back.shading == "none" and back.light is None and back.exposure_gains == {}
    inputs = av.frame_inputs(data.test[0].timestep)
    with torch.no_grad():
        assert torch.equal(back.posed(inputs, None).colors, av.posed(inputs, None).colors)


def test_corrected_posing_shades_with_the_corrected_normal(init_dir, data):
    sh2 = _avatar(init_dir, data, "mlp", "sh2")
    _coloured_light(sh2.light)
    posing = CorrectedPosing(sh2, True)
    fr = data.test[0]
    inputs = sh2.frame_inputs(fr.timestep)
    inputs["jaw_pose"] = inputs["jaw_pose"] + torch.tensor([[0.25, 0.0, 0.0]])
    inputs["expr"] = inputs["expr"] + 1.5
    cam = torch.tensor([0.0, 0.05, 1.0])
    with torch.no_grad():
        cs = posing.canonical_state()
        p, res = posing.posed(inputs, cam, canonical=cs)
        albedo, _ = posing.posed(inputs, cam, canonical=cs, shade=False)
        raw = sh2.posed(inputs, cam, canonical=cs, shade=False)
        q_corr, _ = SurfelCorrection.apply(res, raw.quats, raw.scales)
        R_p, _, _ = surfel_frames(raw.vertices, sh2.faces)
        tri_n = R_p[sh2.surfels.binding][..., 2]
        n_corr = orient_outward(quat_to_matrix(q_corr)[..., 2], tri_n)
        n_raw = orient_outward(quat_to_matrix(raw.quats)[..., 2], tri_n)
        want = raw.colors * sh2.light.irradiance(n_corr)
        uncorrected = raw.colors * sh2.light.irradiance(n_raw)
    assert res is not None
    assert torch.allclose(p.quats, q_corr)
    assert torch.allclose(albedo.colors, raw.colors)
    assert torch.allclose(p.colors, want, atol=1e-6)
    # the correction turned surfels (about their normals: SAGE's dq keeps t3), so the shading of the
    # corrected and the uncorrected normal agree
    assert float((quat_to_matrix(q_corr) - quat_to_matrix(raw.quats)).abs().max()) > 1e-3
    assert torch.allclose(n_corr, n_raw, atol=1e-5) and torch.allclose(p.colors, uncorrected, atol=1e-5)
    assert float((p.colors - albedo.colors).abs().max()) > 0.02
    # with shading off the corrected posing is unchanged by the shade flag
    none = _avatar(init_dir, data, "mlp", "none")
    posing_none = CorrectedPosing(none, True)
    with torch.no_grad():
        a, _ = posing_none.posed(inputs, cam)
        b, _ = posing_none.posed(inputs, cam, shade=False)
    assert torch.equal(a.colors, b.colors) and torch.equal(a.quats, b.quats)


def test_ply_export_bakes_the_irradiance(init_dir, data):
    sh2 = _avatar(init_dir, data, "mlp", "sh2")
    _directional(sh2.light, torch.tensor([0.2, 0.4, 1.0]), 0.4)
    inputs = canonical_inputs(sh2.params, sh2.canonical_timestep)
    with torch.no_grad():
        shaded = sh2.posed(inputs, None)
        albedo = sh2.posed(inputs, None, shade=False)
    blob, dropped = encode_posed_ply(shaded, up_axis=None)
    ply = decode_ply(blob)
    keep = shaded.opacities >= 1 / 255
    assert dropped == int((~keep).sum())
    rgb = sh_dc_to_rgb(torch.as_tensor(ply["sh_dc"], dtype=torch.float32))
    e = sh2.light.irradiance(_outward_normals(sh2, shaded))[keep]
    want = (albedo.colors[keep] * e).clamp(0, 1)
    assert torch.allclose(rgb, want, atol=1e-5)
    assert float((rgb - albedo.colors[keep].clamp(0, 1)).abs().max()) > 0.02
    # with shading "none" the bytes do not depend on the shade flag
    none = _avatar(init_dir, data, "mlp", "none")
    with torch.no_grad():
        b1, _ = encode_posed_ply(none.posed(inputs, None), up_axis=None)
        b2, _ = encode_posed_ply(none.posed(inputs, None, shade=False), up_axis=None)
    assert b1 == b2


# ------------------------------------------------------------------ phase 1
def test_phase1_trains_the_light_and_saves_shading_and_gains(init_dir, tiny_ws, tmp_path):
    from sage_core.train.phase1 import run_phase1

    data = IngestedData.open(tiny_ws / "data")
    cfg = resolve_config(
        "phase1", "tiny", None,
        {"iterations": 4, "n_surfels": 800, "rays_per_step": 64, "neus_samples": 8, "neus_importance": 8, "neus_up_steps": 1,
         "app_hidden": 16, "shape_hidden": 16, "mc_resolution": 32, "eval_every": 0, "rebind_every": 0,
         "shading": "sh2", "exposure": "gain", "lr_light": 0.05, "polish_fraction": 0.0},
    )  # fmt: skip
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        metrics = run_phase1(data, init_dir, tmp_path / "p1", cfg, seed=0)
    finally:
        torch.set_num_threads(n)
    assert metrics["shading"] == "sh2"
    assert np.isfinite(metrics["final_losses"]["light_prior"]) and np.isfinite(metrics["final_losses"]["neus_rgb"])
    av = Avatar.load(tmp_path / "p1" / "avatar.pt")
    assert av.shading == "sh2" and av.light is not None
    init = SHIrradiance().coeffs
    assert float((av.light.coeffs.detach() - init.detach()).abs().max()) > 1e-3
    assert float((av.light.coeffs.detach()[1:]).abs().max()) > 1e-3
    saved = json.loads((tmp_path / "p1" / "metrics.json").read_text())["exposure_gains"]
    assert len(av.exposure_gains) == len(data.train) == len(saved)
    for fr in data.train:
        g = av.exposure_gain(fr.timestep, fr.camera_index)
        assert g is not None
        assert g.tolist() == pytest.approx(saved[f"t{fr.timestep:05d}_c{fr.camera_index:02d}"], rel=1e-6)
    with pytest.raises(Exception, match="shading"):
        from sage_core.train.phase1 import build_avatar

        build_avatar(data, init_dir, resolve_config("phase1", "tiny", None, {"shading": "sh9", "n_surfels": 100}), "cpu",
                     torch.Generator().manual_seed(0))  # fmt: skip
