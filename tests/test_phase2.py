"""Phase 2: correction glue, frozen SDF, detached teacher, loss decrease, exact resume, command."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from sage_core.avatar.corrected import CorrectedPosing
from sage_core.avatar.model import Avatar
from sage_core.config import resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.geometry.rotations import quat_to_matrix
from sage_core.render import RenderCamera
from sage_core.train.phase1 import Phase1Trainer, build_avatar
from sage_core.train.phase2 import Phase2Trainer, compose_inputs, sample_pixels
from sage_core.train.warp import pixel_rays, rigid_rays_to_canonical, warp_pixels_to_canonical

P1_FLAGS = {"iterations": 4, "n_surfels": 400, "rays_per_step": 32, "neus_samples": 8, "neus_importance": 8, "neus_up_steps": 1,
            "rebind_every": 0, "eval_every": 0, "mc_resolution": 32, "app_hidden": 16, "shape_hidden": 16, "app_sh_degree": 1}  # fmt: skip
P2_FLAGS = {"rays_per_step": 48, "neus_samples": 8, "neus_importance": 8, "neus_up_steps": 1, "eval_phase1": False}


@pytest.fixture(scope="session")
def p2_data(tiny_ws):
    return IngestedData.open(tiny_ws / "data")


@pytest.fixture(scope="session")
def p2_init_dir(tiny_init_dir):
    return tiny_init_dir


@pytest.fixture(scope="session")
def phase1_avatar_path(p2_data, p2_init_dir, tmp_path_factory):
    """A phase-1 avatar after a few optimisation steps, saved once."""
    cfg = resolve_config("phase1", "tiny", None, P1_FLAGS)
    g = torch.Generator().manual_seed(0)
    av = build_avatar(p2_data, p2_init_dir, cfg, "cpu", g)
    tr = Phase1Trainer(av, p2_data, cfg, "cpu", g)
    for _ in range(cfg.iterations):
        tr.step()
    path = tmp_path_factory.mktemp("p2_phase1") / "avatar.pt"
    av.save(path)
    return path


def _avatar(path) -> Avatar:
    return Avatar.load(path)


def _cfg(**kw):
    return resolve_config("phase2", "tiny", None, {**P2_FLAGS, **kw})


def _trainer(path, data, init_dir, seed=0, **kw) -> Phase2Trainer:
    return Phase2Trainer(_avatar(path), data, _cfg(**kw), "cpu", torch.Generator().manual_seed(seed), init_dir)


def _deformed_inputs(av: Avatar, data: IngestedData) -> dict[str, torch.Tensor]:
    base = av.frame_inputs(data.canonical_timestep)
    E = base["expr"].shape[-1]
    g = torch.Generator().manual_seed(3)
    sample = {
        "expr": 2.0 * torch.randn(1, E, generator=g),
        "jaw_pose": torch.tensor([[0.3, 0.0, 0.0]]),
        "eyes_pose": torch.zeros(1, 6),
        "neck_pose": torch.tensor([[0.05, 0.1, 0.0]]),
        "rotation": torch.zeros(1, 3),
        "translation": torch.zeros(1, 3),
    }
    return compose_inputs(base, sample)


def test_correction_off_equals_avatar_posed(phase1_avatar_path, p2_data):
    av = _avatar(phase1_avatar_path)
    posing = CorrectedPosing(av, enabled=False)
    inputs = _deformed_inputs(av, p2_data)
    centre = torch.tensor([0.1, 0.0, 1.0])
    with torch.no_grad():
        p, res = posing.posed(inputs, centre)
        ref = av.posed(inputs, centre)
    assert res is None
    for name in ("means", "quats", "scales", "opacities", "colors", "vertices"):
        torch.testing.assert_close(getattr(p, name), getattr(ref, name), atol=0, rtol=0)


def test_correction_on_keeps_normals_and_excludes_hair(phase1_avatar_path, p2_data):
    av = _avatar(phase1_avatar_path)
    posing = CorrectedPosing(av, enabled=True)
    inputs = _deformed_inputs(av, p2_data)
    with torch.no_grad():
        p, res = posing.posed(inputs, None)
        ref = av.posed(inputs, None)
    assert res is not None
    R, Rref = quat_to_matrix(p.quats), quat_to_matrix(ref.quats)
    torch.testing.assert_close(R[..., 2], Rref[..., 2], atol=1e-5, rtol=0)  # normals kept
    torch.testing.assert_close(p.means, ref.means)
    changed = (p.scales - ref.scales).abs().amax(-1) > 1e-7
    assert bool(changed.any())  # the deformation changes some surfels
    hair = av.surfels.hair_mask()
    if bool(hair.any()):
        torch.testing.assert_close(p.scales[hair], ref.scales[hair], atol=0, rtol=0)
        torch.testing.assert_close(p.quats[hair], ref.quats[hair], atol=0, rtol=0)
    assert not bool(res.valid[hair].any())


def test_curvature_cache_recomputes_only_moved_surfels(phase1_avatar_path):
    av = _avatar(phase1_avatar_path)
    posing = CorrectedPosing(av, enabled=True)
    with torch.no_grad():
        means = av.canonical_state().means
    g1 = posing.geometry(means)
    n = means.shape[0]
    assert posing.recomputed == n
    posing.geometry(means + 0.1 * posing.refresh_tolerance)  # below the tolerance: cached
    assert posing.recomputed == n
    moved = means.clone()
    moved[:3] += 0.01
    g2 = posing.geometry(moved)
    assert posing.recomputed == n + 3
    kappa, _, _ = av.sdf.curvature(moved[:3])
    torch.testing.assert_close(g2.kappa[:3], kappa)
    assert g1 is g2


def test_rigid_frame_warp_through_avatar_mesh(phase1_avatar_path, p2_data):
    """A frame that only rotates/translates the head: warping through the hit triangles of the
    Avatar's posed FLAME mesh equals the exact inverse rigid transform."""
    av = _avatar(phase1_avatar_path)
    inputs = dict(av.frame_inputs(p2_data.canonical_timestep))
    inputs["rotation"] = torch.tensor([[0.1, -0.3, 0.05]])
    inputs["translation"] = inputs["translation"] + torch.tensor([[0.01, 0.0, -0.02]])
    rigid = av.rigid_transform(inputs, tol=1e-4)
    assert rigid is not None
    R0, t = rigid
    fr = p2_data.train[0]
    cam = RenderCamera.from_camera(fr.camera, "cpu")
    pix = torch.arange(cam.width * cam.height)
    with torch.no_grad():
        verts = av.pose_mesh(inputs)
    rays = warp_pixels_to_canonical(verts, av.faces, (av.R_c, av.T_c, av.k_c), cam.K, cam.w2c, cam.width, cam.height, pix)
    o, d = pixel_rays(cam.K, cam.w2c, cam.width, cam.height, pix)
    ref = rigid_rays_to_canonical(o, d, R0, t, av.root_joint)
    v = rays.valid
    assert int(v.sum()) > 100
    torch.testing.assert_close(rays.dirs[v], ref.dirs[v], atol=2e-4, rtol=0)
    torch.testing.assert_close(rays.origins[v], ref.origins[v], atol=5e-4, rtol=0)


def test_sample_pixels_prefers_high_error():
    g = torch.Generator().manual_seed(0)
    cand = torch.arange(1000)
    score = torch.zeros(1000, 2)
    score[:100, 0] = 10.0
    pix = sample_pixels(score, cand, 100, 0.1, g)
    assert pix.unique().numel() == 100
    assert int((pix < 100).sum()) > 60


def test_sdf_frozen_teacher_detached(phase1_avatar_path, p2_data, p2_init_dir):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, teacher="neus")
    av = tr.avatar
    sdf0 = {k: v.clone() for k, v in av.sdf.state_dict().items()}
    teach0 = {k: v.clone() for k, v in tr.teacher_app.state_dict().items()}
    app0 = {k: v.clone() for k, v in av.appearance.state_dict().items()}
    opt_ids = {id(p) for p in tr.trainable_parameters()}
    assert not any(id(p) in opt_ids for p in av.sdf.parameters())
    assert not any(p.requires_grad for p in av.sdf.parameters())
    for _ in range(2):
        terms = tr.step()
        assert "appearance" in terms and terms["appearance"] >= 0
    for k, v in av.sdf.state_dict().items():
        torch.testing.assert_close(v, sdf0[k], atol=0, rtol=0)
    assert all(p.grad is None for p in av.sdf.parameters())
    assert all(p.grad is None for p in av.sdf.grid_parameters())
    for k, v in tr.teacher_app.state_dict().items():
        torch.testing.assert_close(v, teach0[k], atol=0, rtol=0)
    assert any(not torch.equal(v, app0[k]) for k, v in av.appearance.state_dict().items())  # the student moved
    fr = p2_data.train[0]
    cam = RenderCamera.from_camera(fr.camera, "cpu")
    with torch.no_grad():
        verts = av.pose_mesh(tr.inputs(fr.timestep))
    with torch.enable_grad():
        colors, valid = tr.teacher(verts, cam, torch.arange(0, cam.width * cam.height, 97))
    assert not colors.requires_grad and colors.grad_fn is None
    assert bool(valid.any())


def test_few_steps_lower_the_loss(phase1_avatar_path, p2_data, p2_init_dir):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=5, lr_networks=3e-3, lr_position=1e-3)
    g0 = tr.generator.get_state()
    first = tr.step()
    for _ in range(4):
        tr.step()
    tr.generator.set_state(g0)  # the same camera, expression, pixels and NeuS jitter as the first step
    again = tr.step()
    assert again["loss"] < first["loss"]


def test_exact_resume(phase1_avatar_path, p2_data, p2_init_dir):
    a = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=2)
    losses_a = [a.step()["loss"] for _ in range(3)]
    b = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=2)
    losses_b = [b.step()["loss"] for _ in range(1)]
    state = b.state_dict()
    c = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=99)
    c.load_state_dict(state)
    losses_c = [c.step()["loss"] for _ in range(2)]
    assert losses_b == losses_a[:1]
    assert losses_c == pytest.approx(losses_a[1:], rel=1e-6, abs=0)
    assert c.distortion_curve == pytest.approx(a.distortion_curve, rel=1e-6)
    for k, v in c.avatar.state_dict().items():
        if not k.startswith("flame."):
            torch.testing.assert_close(v, a.avatar.state_dict()[k], atol=1e-6, rtol=1e-5)


def _promote(ws, stage, src_dir, requires):
    """Complete an upstream stage of a workspace with already computed outputs."""
    from sage_core.workspace import Workspace, begin_stage

    w = Workspace(ws)
    run = begin_stage(w, stage, {"copied": True}, f"copied-{stage}", requires=list(requires))
    assert run is not None
    for f in src_dir.iterdir():
        if f.is_file():
            shutil.copy2(f, run.work_dir / f.name)
    run.finish()


def test_command_writes_outputs_and_manifest(tiny_ws, tmp_path, p2_init_dir, phase1_avatar_path):
    import typer
    from typer.testing import CliRunner

    from sage_cli.commands.phase2 import phase2

    app = typer.Typer()
    app.callback()(lambda: None)  # a command group: `phase2` is a subcommand as in the sage app
    app.command("phase2")(phase2)
    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    _promote(ws, "init-mesh", p2_init_dir, ["ingest"])
    _promote(ws, "phase1", phase1_avatar_path.parent, ["init-mesh"])
    run = CliRunner().invoke
    sets = sum((["--set", f"{k}={v}"] for k, v in {**P2_FLAGS, "eval_frames": 3}.items()), [])
    args = ["phase2", str(ws), "--preset", "tiny", "--device", "cpu", "--quiet", "--iterations", "2", "--correction", "off", *sets]
    r = run(app, args)
    assert r.exit_code == 0, r.output
    assert "sage phase2" in r.output
    out = ws / "phase2"
    for name in ("avatar.pt", "metrics.json", "distortion_curve.json", "manifest.json"):
        assert (out / name).is_file(), name
    m = json.loads((out / "manifest.json").read_text())
    assert m["status"] == "complete" and m["inputs"]["stages"]["phase1"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["correction"] is False
    assert metrics["test"]["counts"]["images"] == 3 and metrics["val"]["counts"]["images"] >= 1
    curve = json.loads((out / "distortion_curve.json").read_text())
    assert len(curve["distortion"]) == 2
    Avatar.load(out / "avatar.pt")
    r = run(app, args)
    assert r.exit_code == 0 and "skipping" in r.output
    r = run(app, ["phase2", str(ws), "--correction", "maybe"])
    assert r.exit_code != 0


def test_rest_teacher_reproduces_the_avatar_at_rest(phase1_avatar_path, p2_data, p2_init_dir):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, correction=False)
    assert tr.rest_teacher is not None and len(tr.rest_teacher.views) == len(p2_data.train)
    fr = p2_data.train[0]
    cam = RenderCamera.from_camera(fr.camera, "cpu")
    with torch.no_grad():
        img = tr.render_frame(fr).reshape(-1, 3)
        verts = tr.avatar.pose_mesh(tr.inputs(fr.timestep))
        from sage_core.render.mesh_raster import rasterize_mesh

        ras = rasterize_mesh(verts, tr.avatar.faces, cam.K, cam.w2c, cam.width, cam.height)
    pix = (ras.face_id.reshape(-1) >= 0).nonzero().squeeze(-1)
    colors, valid = tr.rest_lookup(verts, cam, pix, ras)
    assert float(valid.double().mean()) > 0.7
    # at rest the training view itself is the closest view: its own render comes back
    err = (colors[valid] - img[pix[valid]]).abs().amax(-1)
    assert float((err < 1e-4).double().mean()) > 0.9  # the view's own pixel, sampled at its centre
    assert float(err.mean()) < 0.01  # pixels next to the silhouette come from a neighbouring view


def test_teacher_choice_is_checked(phase1_avatar_path, p2_data, p2_init_dir):
    from sage_core.errors import ConfigError

    with pytest.raises(ConfigError, match="teacher"):
        _trainer(phase1_avatar_path, p2_data, p2_init_dir, teacher="photo")
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, teacher="neus")
    assert tr.rest_teacher is None
    assert "appearance" in tr.step()


def test_mouth_prior_faces_and_colours(phase1_avatar_path, p2_data, p2_init_dir):
    from sage_core.flame.regions import Regions
    from sage_core.train.phase2 import mouth_prior_table

    av = _avatar(phase1_avatar_path)
    regions = Regions.from_dict(json.loads((p2_init_dir / "regions.json").read_text()))
    cavity = torch.as_tensor(regions.face_mask("mouth_interior"))
    teeth = torch.as_tensor(regions.face_mask("teeth"))
    assert bool(cavity.any()) and bool(teeth.any())
    colors, has = mouth_prior_table(av, p2_init_dir, [0.1, 0.2, 0.3], [0.9, 0.8, 0.7])
    assert torch.equal(has, cavity | teeth)
    torch.testing.assert_close(colors[cavity & ~teeth], torch.tensor([0.1, 0.2, 0.3]).expand(int((cavity & ~teeth).sum()), 3))
    torch.testing.assert_close(colors[teeth], torch.tensor([0.9, 0.8, 0.7]).expand(int(teeth.sum()), 3))
    assert not bool(has[~(cavity | teeth)].any())
    _, none = mouth_prior_table(av, None, [0.1, 0.2, 0.3], [0.9, 0.8, 0.7])
    assert not bool(none.any())
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False)
    assert not bool(tr.prior_faces.any())


def test_free_surfels_keep_position_opacity_scale_rotation_by_default(p2_data, p2_init_dir):
    cfg1 = resolve_config("phase1", "tiny", None, {**P1_FLAGS, "attributes": "free"})
    av = build_avatar(p2_data, p2_init_dir, cfg1, "cpu", torch.Generator().manual_seed(0))
    tr = Phase2Trainer(av, p2_data, _cfg(), "cpu", torch.Generator().manual_seed(0), p2_init_dir)
    names = {g["name"] for g in tr.optimizer.param_groups}
    assert "sh_dc" in names and not names & {"mu_loc", "opacity", "s_loc", "q_loc"}
    before = {k: getattr(av.surfels, k).detach().clone() for k in ("mu_loc", "opacity", "s_loc", "q_loc")}
    tr.step()
    for k, v in before.items():
        assert torch.equal(getattr(av.surfels, k), v)
    tr2 = Phase2Trainer(av, p2_data, _cfg(lr_opacity=1e-2), "cpu", torch.Generator().manual_seed(0), p2_init_dir)
    assert "opacity" in {g["name"] for g in tr2.optimizer.param_groups}


def test_rest_teacher_keeps_no_neus_copy(phase1_avatar_path, p2_data, p2_init_dir):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir)
    assert tr.rest_teacher is not None and tr.teacher_app is None and tr.teacher_variance is None
    state = tr.state_dict()
    assert state["teacher_app"] is None
    assert state["teacher_variance"] is None and "appearance" in tr.step()


def test_wrinkle_shading_statistics_storage_and_rest_pose(phase1_avatar_path, p2_data, p2_init_dir, tmp_path):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=3, wrinkle_shading=True, wrinkle_strength=0.4)
    fr = p2_data.train[0]
    for _ in range(3):
        tr.step()
    before = tr.render_frame(fr)
    st = tr.wrinkle_stats
    assert st is not None and float(st.count.sum()) > 0 and float(st.sum.sum()) > 0
    resumed = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=9, wrinkle_shading=True, wrinkle_strength=0.4)
    resumed.load_state_dict(tr.state_dict())
    torch.testing.assert_close(resumed.wrinkle_stats.mean(), st.mean())
    out = tr.finish_wrinkles()
    av = tr.avatar
    w = av.surfels.wrinkle
    assert w is not None and tuple(w.shape) == (len(av.surfels), 2)
    assert 0.0 < out["surfels_darkening"] < 1.0
    assert float(w[:, 0].max()) <= 0.4 + 1e-6 and float(w[:, 0].min()) >= 0.0
    assert float(w[av.surfels.hair_mask(), 0].abs().sum()) == 0.0
    torch.testing.assert_close(w[:, 1], torch.full_like(w[:, 1], 0.25))
    # the training frame's mesh is the rest mesh: wrinkle shading changes nothing there
    after = tr.render_frame(fr)
    torch.testing.assert_close(after, before, atol=1e-5, rtol=0)
    path = av.save(tmp_path / "avatar.pt")
    torch.testing.assert_close(Avatar.load(path).surfels.wrinkle, w)
    # under a compressing expression some surfel darkens
    inputs = _deformed_inputs(av, p2_data)
    with torch.no_grad():
        p, _ = tr.posing.posed(inputs, None)
        from sage_core.avatar.wrinkles import apply_wrinkles

        dark = apply_wrinkles(p.colors, w, p.vertices, av.canonical_vertices, av.faces, av.surfels.binding)
    assert bool((dark < p.colors - 1e-6).any()) and bool((dark <= p.colors + 1e-7).all())


def test_mouth_prior_colours_unseen_mouth_surfels_only(phase1_avatar_path, p2_data, p2_init_dir):
    from sage_core.flame.regions import Regions

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_occlusion_jaw=0.0)
    av = tr.avatar
    regions = Regions.from_dict(json.loads((p2_init_dir / "regions.json").read_text()))
    mouth = torch.as_tensor(regions.face_mask("mouth_interior") | regions.face_mask("teeth"))
    seen = tr.seen_faces()
    assert bool(seen.any()) and not bool(seen.all())
    assert torch.equal(tr.prior_faces, mouth & ~seen)
    prior = av.surfels.color_prior
    assert prior is not None and tuple(prior.shape) == (len(av.surfels), 4)
    on = prior[:, 3] > 0
    assert bool(on.any())
    assert torch.equal(on, tr.prior_faces[av.surfels.binding])
    # without occlusion the prior colour is the table colour
    torch.testing.assert_close(prior[on, :3], tr.prior_colors[av.surfels.binding[on]])
    # the blended colours: prior where set, the network's elsewhere
    cols = torch.rand(len(av.surfels), 3)
    out = av.surfels.blend_color_prior(cols)
    torch.testing.assert_close(out[~on], cols[~on])
    torch.testing.assert_close(out[on], prior[on, :3])
    # occlusion darkens: ambient visibility lies in [0, 1] and is below 1 somewhere inside the mouth
    vis = tr.prior_visibility(on, 0.3, samples=64)
    assert vis.shape == (int(on.sum()),) and float(vis.min()) >= 0 and float(vis.max()) <= 1 and float(vis.min()) < 1
    off = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False)
    assert off.avatar.surfels.color_prior is None


def test_mouth_prior_by_surfel_visibility_spares_seen_surfels(phase1_avatar_path, p2_data, p2_init_dir):
    from sage_core.errors import ConfigError
    from sage_core.flame.regions import Regions

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior_visibility="surfels", mouth_occlusion_jaw=0.0)
    av = tr.avatar
    regions = Regions.from_dict(json.loads((p2_init_dir / "regions.json").read_text()))
    mouth = torch.as_tensor(regions.face_mask("mouth_interior") | regions.face_mask("teeth"))[av.surfels.binding]
    seen = tr.seen_surfels()
    assert bool(seen.any()) and not bool(tr.seen_surfels(min_weight=1e9).any())
    on = av.surfels.color_prior[:, 3] > 0
    assert torch.equal(on, mouth & ~seen)
    # the weights behind it sum to the rendered alpha over the eroded foreground of the views
    w = tr.surfel_view_weights()
    expect = 0.0
    for fr in p2_data.train:
        cam = RenderCamera.from_camera(fr.camera, "cpu")
        with torch.no_grad():
            img, p = av.render(cam, tr.inputs(fr.timestep), 0.0, near=tr.cfg.near, far=tr.cfg.far, return_statistics=False)
            from sage_core.render.mesh_raster import rasterize_mesh
            from sage_core.train.rest_teacher import erode_mask

            fid = rasterize_mesh(p.vertices, av.faces, cam.K, cam.w2c, cam.width, cam.height).face_id[0]
            inner = erode_mask(fid >= 0)[0, 0]
        expect += float((img.alpha * inner).sum())
    assert float(w.sum()) == pytest.approx(expect, rel=1e-3)
    with pytest.raises(ConfigError):
        _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior_visibility="pixels")


def test_cosine_schedule_falls_from_the_set_rate_to_zero():
    from types import SimpleNamespace

    from sage_core.config import Phase2Config
    from sage_core.train.phase2 import Phase2Trainer

    cos = SimpleNamespace(cfg=Phase2Config(iterations=100, lr_schedule="cosine"))
    f = [Phase2Trainer.lr_factor(cos, s) for s in (0, 50, 100, 150)]
    assert f[0] == pytest.approx(1.0) and f[1] == pytest.approx(0.5) and f[2] == pytest.approx(0.0) and f[3] == pytest.approx(0.0)
    const = SimpleNamespace(cfg=Phase2Config(iterations=100, lr_schedule="constant"))
    assert {Phase2Trainer.lr_factor(const, s) for s in (0, 50, 99)} == {1.0}


def test_every_rate_zero_poses_and_prices_without_training(phase1_avatar_path, p2_data, p2_init_dir):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=3, lr_networks=0.0, lr_shape=0.0, lr_position=0.0)
    assert tr.optimizer is None and tr.trainable_parameters() == []
    before = {k: v.clone() for k, v in tr.avatar.state_dict().items() if not k.startswith("flame.")}
    out = tr.step()
    assert out["loss"] > 0 and tr.step_count == 1
    for k, v in tr.avatar.state_dict().items():
        if k in before:
            torch.testing.assert_close(v, before[k], atol=0, rtol=0)
    state = tr.state_dict()
    tr2 = _trainer(phase1_avatar_path, p2_data, p2_init_dir, seed=4, lr_networks=0.0, lr_shape=0.0, lr_position=0.0)
    tr2.load_state_dict(state)
    assert tr2.step_count == 1
