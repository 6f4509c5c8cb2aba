"""Registration of the training timestep: the translation fit, the exact canonical shift, the rules,
and the held-out views of the training timestep posed with the avatar's registered parameters."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
import trimesh

from sage_core.avatar.canonical_shift import shift_canonical
from sage_core.avatar.model import Avatar
from sage_core.config import RegistrationConfig, resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.flame.regions import Regions
from sage_core.render import RenderCamera
from sage_core.train.registration import estimate_translation, register_training_pose, registration_applies


def _sphere(center: torch.Tensor, radius: float):
    def f(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d = x - center.to(x)
        r = d.norm(dim=1)
        return r - radius, d / r[:, None]

    return f


def test_estimate_translation_recovers_a_known_offset_despite_outliers():
    g = torch.Generator().manual_seed(0)
    u = torch.randn(400, 3, generator=g, dtype=torch.float64)
    pts = 0.1 * u / u.norm(dim=1, keepdim=True)
    pts[:40] *= 1.6  # a tenth of the points far off the surface (hair over ears, say)
    shift = torch.tensor([0.0012, -0.0007, 0.0015], dtype=torch.float64)
    fit = estimate_translation(_sphere(shift, 0.1), pts, scale=0.0015)
    assert torch.allclose(fit.translation, shift, atol=2e-5)
    assert fit.residual_after < fit.residual_before
    assert abs(fit.offset) < 2e-5
    plain = estimate_translation(_sphere(shift, 0.1), pts, scale=1.0)  # no robust weights: the outliers pull it off
    assert (plain.translation - shift).norm() > 10 * (fit.translation - shift).norm()


def test_a_uniformly_fuller_surface_is_an_offset_not_a_translation():
    g = torch.Generator().manual_seed(1)
    u = torch.randn(600, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True)
    pts = 0.1 * u[u[:, 2] > -0.3]  # mostly forward-facing points, like a face and neck
    shift = torch.tensor([0.0005, 0.001, -0.0008], dtype=torch.float64)
    fit = estimate_translation(_sphere(shift, 0.1007), pts, scale=0.0015)  # 0.7 mm fuller than the mesh
    assert torch.allclose(fit.translation, shift, atol=1e-6)
    assert fit.offset == pytest.approx(-0.0007, abs=1e-6)  # the points sit 0.7 mm inside it
    assert fit.residual_after < 1e-6


def test_estimate_translation_refuses_an_undetermined_fit():
    plane = lambda x: (x[:, 2] - 0.01, torch.tensor([0.0, 0.0, 1.0], dtype=x.dtype).expand(len(x), 3))  # noqa: E731
    pts = torch.rand(50, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="undetermined"):
        estimate_translation(plane, pts, scale=0.01)
    with pytest.raises(ValueError, match="at least 4"):
        estimate_translation(plane, pts[:3], scale=0.01)


def test_registration_rules():
    assert registration_applies("auto", "mv-sf", 1, True, False) == (True, "auto")
    for regime in ("mv-mf", "sv-hr", "one-shot"):
        run, why = registration_applies("auto", regime, 1, True, False)
        assert not run and regime in why
    assert not registration_applies("auto", "mv-sf", 1, False, False)[0]
    assert not registration_applies("auto", "mv-sf", 1, True, True)[0]
    assert registration_applies("off", "mv-sf", 1, True, False) == (False, "off")
    assert registration_applies("on", "sv-hr", 1, True, False) == (True, "on")
    for args, msg in (((2, True, False), "one training timestep"), ((1, True, True), "pose_refine"), ((1, False, False), "SDF terms")):
        with pytest.raises(ValueError, match=msg):
            registration_applies("on", "mv-sf", *args)


def _render_training_view(av: Avatar, data: IngestedData) -> torch.Tensor:
    fr = data.train[0]
    with torch.no_grad():
        return av.render(RenderCamera.from_camera(fr.camera, "cpu"), av.frame_inputs(fr.timestep), 1.0)[0].color


def _posed_means(av: Avatar) -> torch.Tensor:
    with torch.no_grad():
        return av.posed(av.frame_inputs(av.canonical_timestep), None).means


@pytest.mark.parametrize("attributes", ["mlp", "free"])
def test_shift_canonical_with_the_moved_translation_renders_the_training_view_unchanged(tiny_avatar_ws, tiny_init_dir, attributes, one_thread):
    data = IngestedData.open(tiny_avatar_ws / "data")
    g = torch.Generator().manual_seed(1)
    av = Avatar.build(tiny_init_dir, data, 300, attributes, app_args={"hidden": 16}, shape_args={"hidden": 16}, generator=g)
    with torch.no_grad():
        av.surfels.mu_loc.add_(0.02 * torch.randn(av.surfels.mu_loc.shape, generator=g))
    before = _render_training_view(av, data)
    posed_before = _posed_means(av)
    probe = av.canonical_vertices[::7].detach().clone()
    sdf_before = av.sdf.sdf(probe).detach()
    means_before = av.canonical_state().means.detach()
    t0 = av.canonical_timestep
    R0, _ = av.rigid_transform(av.frame_inputs(t0))
    delta = torch.tensor([0.002, -0.001, 0.0015])
    shift_canonical(av, delta)
    params = av.params
    moved = params.translation.copy()
    moved[params.row_of(t0)] -= (R0 @ delta).numpy()  # the mesh moves the other way in the world
    av.params = dataclasses.replace(params, translation=moved)
    assert torch.allclose(av.canonical_state().means.detach(), means_before + delta, atol=1e-6)
    assert torch.allclose(av.sdf.sdf(probe + delta).detach(), sdf_before, atol=1e-6)
    assert float((_posed_means(av) - posed_before).abs().max()) < 1e-6
    assert float((_render_training_view(av, data) - before).abs().max()) < 2e-4
    # the content moved relative to the mesh: posed with the tracked translation it moves in the world
    av.params = params
    shifted = _posed_means(av) - posed_before
    assert torch.allclose(shifted, (R0 @ delta).expand_as(shifted), atol=1e-6)


def _exact_head(ws):
    """The workspace's phase-1 avatar with an SDF whose zero level set holds the canonical mesh's
    vertices exactly (the signed distance to the tangent plane of the nearest vertex), moved with
    the SDF's box like the network: a head reconstructed without error; and the model's regions."""
    av = Avatar.load(ws / "phase1" / "avatar.pt")
    regions = Regions.from_dict(json.loads((ws / "init" / "regions.json").read_text()))
    verts = av.canonical_vertices.detach().clone()
    mesh = trimesh.Trimesh(verts.numpy(), av.faces.cpu().numpy(), process=False)
    normals = torch.as_tensor(np.array(mesh.vertex_normals), dtype=verts.dtype)
    box0 = av.sdf.encoding.bbox_min.detach().clone()

    def tangent_planes(x: torch.Tensor) -> torch.Tensor:
        y = x - (av.sdf.encoding.bbox_min - box0)
        j = torch.cdist(y.detach(), verts).argmin(dim=1)
        return ((y - verts[j]) * normals[j]).sum(-1)

    av.sdf.sdf = tangent_planes
    return av, regions


def test_round_steps_are_spread_over_the_sdf_span():
    from sage_core.train.registration import round_steps

    assert round_steps(1, 0, 1200) == []
    assert round_steps(2, 0, 1200) == [600]
    assert round_steps(3, 300, 1200) == [600, 900]
    assert round_steps(4, 0, 2) == [1]  # duplicates and steps outside the span dropped


def test_rounds_refine_an_applied_registration_and_restore_the_translation(tiny_avatar_ws, one_thread):
    from sage_core.train.registration import RegistrationRounds, head_pixel

    data = IngestedData.open(tiny_avatar_ws / "data")
    av, regions = _exact_head(tiny_avatar_ws)
    t0 = av.canonical_timestep
    cams = [fr.camera for fr in data.train if fr.timestep == t0]
    pixel = head_pixel(av, cams)
    assert pixel is not None and 1e-4 < pixel < 1e-2
    assert head_pixel(av, []) is None
    cfg = dataclasses.replace(RegistrationConfig(), rounds=3)
    rounds = RegistrationRounds(av, regions, cams, cfg, [5, 10])
    assert rounds.due(5) and not rounds.due(6)
    row = data.params.row_of(t0)
    unit = torch.tensor([0.6, 0.0, -0.8])
    shift_canonical(av, 0.3 * pixel * unit)  # under half a pixel alone: not applied
    first = rounds.fit(av, 5)
    assert first["registration"].startswith("skipped: the fit moved the mesh") and np.allclose(av.params.translation[row], data.params.translation[row])
    shift_canonical(av, 0.4 * pixel * unit)  # now 0.7 px off: applied
    second = rounds.fit(av, 10)
    assert second["registration"] == "applied"
    assert np.allclose(rounds.applied, (0.7 * pixel * unit).numpy(), atol=1e-6)
    shift_canonical(av, 0.2 * pixel * unit)  # under half a pixel, but after an applied round: refines it
    third = rounds.fit(av, 15)
    assert third["registration"] == "applied"
    assert np.allclose(rounds.applied, (0.9 * pixel * unit).numpy(), atol=1e-6)
    summary = rounds.summary()
    assert summary["registration"] == "applied" and len(summary["registration_rounds"]) == 3
    assert summary["registration_applied_mm"] == pytest.approx(0.9 * pixel * 1000.0, rel=1e-3)
    R0, _ = av.rigid_transform(av.frame_inputs(t0))
    moved = av.params.translation[row] - data.params.translation[row]
    assert np.allclose(moved, (R0 @ (0.9 * pixel * unit)).numpy(), atol=1e-6)
    assert np.allclose(moved * 1000.0, summary["registration_applied_world_mm"], atol=1e-3)
    # restored on a fresh avatar (a resumed run: its content comes from the checkpoint)
    fresh = Avatar.load(tiny_avatar_ws / "phase1" / "avatar.pt")
    again = RegistrationRounds(fresh, regions, cams, cfg, [5, 10])
    again.load_state_dict(rounds.state_dict(), fresh)
    assert np.array_equal(fresh.params.translation, av.params.translation)
    assert again.summary() == summary


def test_register_training_pose_finds_a_known_shift_and_keeps_the_training_view(tiny_avatar_ws, one_thread):
    data = IngestedData.open(tiny_avatar_ws / "data")
    av, regions = _exact_head(tiny_avatar_ws)
    cfg = RegistrationConfig()
    first = register_training_pose(av, regions, cfg)
    assert first["registration"] == "applied" and first["registration_regions"] == ["face", "neck", "left_ear", "right_ear"]
    assert first["registration_translation_norm_mm"] < 1e-3
    # the content 2 mm off the mesh (a tracked pose that was off): found, and the mesh moved onto it
    e = torch.tensor([0.0015, 0.0005, -0.001])
    shift_canonical(av, e)
    before = _render_training_view(av, data)
    posed_before = _posed_means(av)
    second = register_training_pose(av, regions, cfg)
    assert second["registration"] == "applied"
    assert np.allclose(second["registration_translation_mm"], (e * 1000.0).numpy(), atol=1e-3)
    assert second["registration_residual_after_mm"] < 1e-3 < second["registration_residual_before_mm"]
    assert float((_posed_means(av) - posed_before).abs().max()) < 1e-6
    assert float((_render_training_view(av, data) - before).abs().max()) < 2e-4
    t0 = av.canonical_timestep
    row = data.params.row_of(t0)
    R0, _ = av.rigid_transform(av.frame_inputs(t0))
    moved = av.params.translation[row] - data.params.translation[row]
    assert np.allclose(moved, (R0 @ e).numpy(), atol=2e-6)
    assert np.allclose(moved * 1000.0, second["registration_world_translation_mm"], atol=2e-3)
    # a fit beyond max_translation is reported, not applied; no region of the model: skipped
    shift_canonical(av, torch.tensor([0.03, 0.0, 0.0]))
    p = av.params
    third = register_training_pose(av, regions, dataclasses.replace(cfg, max_translation=0.05))
    assert third["registration"].startswith("skipped") and av.params is p
    small = register_training_pose(av, regions, cfg, pixel=0.1)  # 30 mm under half a 100 mm pixel
    assert small["registration"].startswith("skipped: the fit moved the mesh") and "min_pixels" in small["registration"]
    assert av.params is p and small["registration_pixel_mm"] == pytest.approx(100.0)
    none = register_training_pose(av, regions, dataclasses.replace(cfg, regions=["no_such_region"]))
    assert none["registration"].startswith("skipped: the model has none")


def test_pixel_footprint_is_distance_over_focal_length():
    from sage_core.data.cameras import Camera
    from sage_core.train.registration import pixel_footprint

    def cam(z: float, f: float) -> Camera:
        w2c = np.eye(4)
        w2c[2, 3] = z
        return Camera(K=np.array([[f, 0, 64.0], [0, f, 93.0], [0, 0, 1]]), w2c=w2c, width=128, height=186)

    assert pixel_footprint([cam(1.0, 500.0), cam(2.0, 500.0), cam(1.0, 250.0)], np.zeros(3)) == pytest.approx(1.0 / 250.0)


def test_phase1_config_has_the_registration_section():
    cfg = resolve_config("phase1", "tiny", None, {"registration.mode": "off", "registration.regions": "face, neck"})
    assert cfg.registration.mode == "off" and cfg.registration.regions == ["face", "neck"]
    assert resolve_config("phase1", "tiny").registration.regions == ["face", "neck", "left_ear", "right_ear"]
    assert resolve_config("phase1", "small").registration.rounds == 1
    with pytest.raises(Exception, match="registration.rounds"):
        resolve_config("phase1", "tiny", None, {"registration.rounds": 0})
    with pytest.raises(Exception, match="registration.mode"):
        resolve_config("phase1", "tiny", None, {"registration.mode": "sometimes"})
    with pytest.raises(Exception, match="registration.regions"):
        resolve_config("phase1", "tiny", None, {"registration.regions": "face,elbow"})
