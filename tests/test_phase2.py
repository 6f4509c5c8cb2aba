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
    torch.manual_seed(0)  # the networks' initialisation draws from the global generator: the same avatar in any test order
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
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, teacher="neus", lr_networks=1e-4)  # a student that learns
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
        # the teacher holds albedos (an avatar shaded by a world light is compared unshaded)
        img = tr.render(cam, tr.inputs(fr.timestep), shade=False)[0].color.reshape(-1, 3)
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


def test_wrinkle_basis_expression_ignores_skinning_but_not_expression_creases(phase1_avatar_path, p2_data, p2_init_dir, tmp_path):
    from sage_core.avatar.model import AVATAR_FORMAT, AVATAR_KIND
    from sage_core.avatar.wrinkles import surfel_compression
    from sage_core.serialization import load_file, save_file

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, wrinkle_shading=True)
    av = tr.avatar
    assert av.wrinkle_basis == "expression" and tr.cfg.wrinkles.basis == "expression"
    n = len(av.surfels)
    w = torch.stack([torch.ones(n), torch.full((n,), 0.25)], -1)  # every surfel at full amplitude
    base = av.frame_inputs(p2_data.canonical_timestep)
    jaw = dict(base, jaw_pose=base["jaw_pose"] + torch.tensor([[0.35, 0.0, 0.0]]), neck_pose=base["neck_pose"] + torch.tensor([[0.3, 0.2, 0.0]]))
    expr = dict(base, expr=base["expr"] + 2.0 * torch.randn(base["expr"].shape, generator=torch.Generator().manual_seed(5)))

    def compression(inputs):
        with torch.no_grad():
            mesh = av.posed_mesh(inputs)
            from sage_core.avatar.posing import wrinkle_meshes

            deformed, rest = wrinkle_meshes(av, mesh.vertices, mesh.shaped)
            return surfel_compression(deformed, rest, av.faces, av.surfels.binding, w[:, 1])

    def albedo(inputs):
        av.surfels.set_wrinkle(w)
        with torch.no_grad():
            dark = av.posed(inputs, None, shade=False).colors
        av.surfels.set_wrinkle(None)
        with torch.no_grad():
            plain = av.posed(inputs, None, shade=False).colors
        return dark, plain

    # jaw and neck rotations are skinning: no compression on the expression-shaped mesh, no darkening
    assert float(compression(jaw).abs().max()) == 0.0
    dark, plain = albedo(jaw)
    torch.testing.assert_close(dark, plain, atol=0, rtol=0)
    # an expression compresses the expression-shaped mesh, and the colours darken there
    c = compression(expr)
    assert float(c.max()) > 0.1
    dark, plain = albedo(expr)
    torch.testing.assert_close(dark, plain * (1.0 - c)[:, None], atol=1e-6, rtol=0)
    # the posed basis (the rule before the option) counts the skinning's compression under the chin
    av.wrinkle_basis = "posed"
    assert float(compression(jaw).max()) > 0.05
    dark, plain = albedo(jaw)
    assert bool((dark < plain - 1e-6).any())
    # the basis is stored with the avatar; a file written before it loads with the posed basis
    av.wrinkle_basis = "expression"
    path = av.save(tmp_path / "avatar.pt")
    assert Avatar.load(path).wrinkle_basis == "expression"
    blob, _ = load_file(path, AVATAR_KIND, AVATAR_FORMAT, "avatar file")
    del blob["args"]["wrinkle_basis"]
    save_file(tmp_path / "old.pt", blob, AVATAR_KIND, AVATAR_FORMAT)
    assert Avatar.load(tmp_path / "old.pt").wrinkle_basis == "posed"
    with pytest.raises(ValueError, match="wrinkle_basis"):
        Avatar(av.model_data, av.params, av.canonical_timestep, av.surfels, av.sdf_args, av.attributes, av.app_args,
               av.shape_args, wrinkle_basis="skinned")  # fmt: skip


def test_mouth_prior_by_face_visibility_colours_surfels_of_unseen_mouth_faces(phase1_avatar_path, p2_data, p2_init_dir):
    from sage_core.flame.regions import Regions

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior_visibility="faces", mouth_occlusion_jaw=0.0, mouth_prior_source="table")
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


def test_learned_mouth_prior_composites_unseen_surfels_and_spares_seen_ones(phase1_avatar_path, p2_data, p2_init_dir,
                                                                            monkeypatch):
    from sage_core.avatar.mouth_prior import avatar_prior_colors
    from sage_core.flame.regions import Regions

    # the tiny avatar's few large mouth surfels are all seen at the open-jaw canonical timestep: the
    # views' real weights with every other mouth surfel made unseen
    base = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False)
    regions = Regions.from_dict(json.loads((p2_init_dir / "regions.json").read_text()))
    _, mouth = avatar_prior_colors(base.avatar, regions)
    weights = base.surfel_view_weights()
    hidden = mouth.nonzero().squeeze(-1)[::2]
    weights[hidden] = 0.0
    monkeypatch.setattr(Phase2Trainer, "surfel_view_weights", lambda self: weights.clone())
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior_visibility="surfels", mouth_prior_source="learned")
    av = tr.avatar
    cols, mouth = avatar_prior_colors(av, regions)
    prior = av.surfels.color_prior
    assert prior is not None
    on = prior[:, 3] > 0
    seen = weights >= 0.5
    # the unseen mouth surfels take the learned prior's albedo (no occlusion darkening), the seen ones
    # and every surfel outside the mouth keep their own colour
    assert bool(on.any()) and torch.equal(on, mouth & ~seen)
    torch.testing.assert_close(prior[on, :3], cols[on])
    table = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior_visibility="surfels", mouth_prior_source="table",
                     mouth_occlusion_jaw=0.0)
    assert not torch.allclose(table.avatar.surfels.color_prior[on, :3], prior[on, :3])


def test_mouth_prior_by_surfel_visibility_spares_seen_surfels(phase1_avatar_path, p2_data, p2_init_dir):
    from sage_core.errors import ConfigError
    from sage_core.flame.regions import Regions

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior_visibility="surfels", mouth_occlusion_jaw=0.0, mouth_prior_source="table")
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

    from sage_core.config import Phase2Config, Phase2Rates
    from sage_core.train.phase2 import Phase2Trainer

    cos = SimpleNamespace(cfg=Phase2Config(iterations=100, lr=Phase2Rates(schedule="cosine")))
    f = [Phase2Trainer.lr_factor(cos, s) for s in (0, 50, 100, 150)]
    assert f[0] == pytest.approx(1.0) and f[1] == pytest.approx(0.5) and f[2] == pytest.approx(0.0) and f[3] == pytest.approx(0.0)
    const = SimpleNamespace(cfg=Phase2Config(iterations=100, lr=Phase2Rates(schedule="constant")))
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


# ---------------------------------------------------------------- fast paths against their references


def _canonical_loss(cs) -> torch.Tensor:
    return cs.scales.sum() + (cs.rotation * torch.arange(9.0).reshape(3, 3)).sum() + cs.quats[:, 1:].abs().sum()


def _assert_same_canonical(a, b) -> None:
    for name in ("means", "quats", "scales", "rotation", "sdf", "sdf_grad", "feature"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=0, rtol=0, msg=name)


def test_frozen_canonical_inputs_equal_the_uncached_path(phase1_avatar_path):
    """CorrectedPosing.canonical_state with frozen centres and SDF (cached centres, SDF values and hash
    encoding) against the uncached path: the same values bit for bit and the same shape-network
    gradients; the cache follows in-place changes of the centres and of the SDF table."""
    av = _avatar(phase1_avatar_path)
    av.sdf.requires_grad_(False)
    posing = CorrectedPosing(av, enabled=True)
    shape_params = list(av.shape.parameters())

    def reference():
        av.surfels.mu_loc.requires_grad_(True)
        assert not posing.frozen_inputs_apply()
        cs = posing.canonical_state()
        grads = torch.autograd.grad(_canonical_loss(cs), shape_params)
        av.surfels.mu_loc.requires_grad_(False)
        return cs, grads

    ref, g_ref = reference()
    assert posing._frozen is None  # the uncached path keeps nothing
    assert posing.frozen_inputs_apply()
    fast = posing.canonical_state()
    _assert_same_canonical(fast, ref)
    assert not fast.means.requires_grad
    for a, b in zip(torch.autograd.grad(_canonical_loss(fast), shape_params), g_ref):
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    fz = posing.frozen_inputs()
    assert posing.frozen_inputs() is fz  # nothing changed: reused
    with torch.no_grad():
        av.surfels.mu_loc[:10] += 0.002
    moved = posing.canonical_state()
    assert posing.frozen_inputs() is not fz
    ref2, _ = reference()
    _assert_same_canonical(moved, ref2)
    assert not torch.equal(moved.means[:10], fast.means[:10])
    with torch.no_grad():
        av.sdf.encoding.table.mul_(1.5)
    regrid = posing.canonical_state()
    ref3, _ = reference()
    _assert_same_canonical(regrid, ref3)
    assert not torch.equal(regrid.sdf, moved.sdf)
    av.surfels.mu_loc.requires_grad_(True)
    with torch.no_grad():
        assert posing.frozen_inputs_apply()  # without grad mode the centres' gradient is moot
    av.sdf.encoding.table.requires_grad_(True)
    av.surfels.mu_loc.requires_grad_(False)
    assert not posing.frozen_inputs_apply()  # a trained SDF table must get its gradient


def test_frozen_canonical_inputs_with_free_attributes(p2_data, p2_init_dir):
    cfg1 = resolve_config("phase1", "tiny", None, {**P1_FLAGS, "attributes": "free"})
    av = build_avatar(p2_data, p2_init_dir, cfg1, "cpu", torch.Generator().manual_seed(0))
    av.sdf.requires_grad_(False)
    posing = CorrectedPosing(av, enabled=True)
    ref = posing.canonical_state()  # mu_loc requires a gradient: uncached
    av.surfels.mu_loc.requires_grad_(False)
    fast = posing.canonical_state()
    assert posing._frozen is not None and posing._frozen.encoding is None
    _assert_same_canonical(fast, ref)
    assert fast.quats.requires_grad  # q_loc still trains


def test_phase2_trains_exactly_the_optimizer_parameters(phase1_avatar_path, p2_data, p2_init_dir):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir)
    av = tr.avatar
    trained = {id(p) for p in tr.trainable_parameters()}
    assert trained and all(p.requires_grad == (id(p) in trained) for p in av.parameters())
    assert not av.surfels.mu_loc.requires_grad and tr.posing.frozen_inputs_apply()
    tr.step()
    assert av.surfels.mu_loc.grad is None and tr.posing._frozen is not None
    tr2 = _trainer(phase1_avatar_path, p2_data, p2_init_dir, lr_position=1e-3)
    mu = tr2.avatar.surfels.mu_loc
    assert mu.requires_grad and not tr2.posing.frozen_inputs_apply()
    before = mu.detach().clone()
    tr2.step()
    assert mu.grad is not None and not torch.equal(mu.detach(), before)


def _sequential_lookup(views, depth_tol, faces, face_id, bary, ray_dirs, frames):
    """The rest teacher's lookup visiting the views one by one (the reference of the batched one)."""
    import torch.nn.functional as F

    def sample(img, u, v, width, height):
        grid = torch.stack([u / width * 2.0 - 1.0, v / height * 2.0 - 1.0], -1).to(img.dtype)[None, None]
        return F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0].T

    R = face_id.shape[0]
    d_loc = (frames[0][face_id].transpose(-1, -2) @ ray_dirs[..., None]).squeeze(-1)
    best = torch.full((R,), -2.0, dtype=ray_dirs.dtype)
    color = torch.zeros(R, 3, dtype=ray_dirs.dtype)
    view = torch.full((R,), -1, dtype=torch.long)
    tri = faces[face_id]
    for vi, v in enumerate(views):
        x = (bary[..., None] * v.vertices[tri]).sum(1)
        xc = x @ v.w2c[:3, :3].T + v.w2c[:3, 3]
        z = xc[:, 2]
        front = z > 1e-6
        zs = torch.where(front, z, torch.ones_like(z))
        uvw = xc @ v.K.T
        u, w_ = uvw[:, 0] / zs, uvw[:, 1] / zs
        inside = front & (u >= 0) & (u < v.width) & (w_ >= 0) & (w_ < v.height)
        surf = v.depth[w_.clamp(0, v.height - 1).long(), u.clamp(0, v.width - 1).long()]
        visible = inside & (z <= surf * (1.0 + depth_tol)) & (sample(v.interior, u, w_, v.width, v.height)[:, 0] > 0.999)
        dv = x + v.w2c[:3, :3].T @ v.w2c[:3, 3]
        dv = dv / dv.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        score = ((v.frames[0][face_id].transpose(-1, -2) @ dv[..., None]).squeeze(-1) * d_loc).sum(-1)
        take = visible & (score > best)
        color = torch.where(take[:, None], sample(v.color, u, w_, v.width, v.height).to(color), color)
        best = torch.where(take, score, best)
        view = torch.where(take, torch.full_like(view, vi), view)
    return color, view >= 0, view


def test_batched_rest_lookup_equals_the_view_by_view_lookup(phase1_avatar_path, p2_data, p2_init_dir):
    """The batched lookup (views stacked per image size) against visiting the views in order, with a
    cropped view (another image size) and an exact duplicate (ties go to the earlier view)."""
    import dataclasses

    from sage_core.flame.frames import surfel_frames
    from sage_core.render.mesh_raster import rasterize_mesh
    from sage_core.train.rest_teacher import RestTeacher

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir)
    av = tr.avatar
    base = tr.rest_teacher.views
    crop = dataclasses.replace(base[1], width=90, height=100, color=base[1].color[..., :100, :90].clone(),
                               interior=base[1].interior[..., :100, :90].clone(), depth=base[1].depth[:100, :90].clone())  # fmt: skip
    # view 1 is replaced by its crop, at the end, so that it wins where view 1 would; view 3 is duplicated
    views = [dataclasses.replace(v, color=v.color.clone()) for i, v in enumerate(base) if i != 1]
    views += [crop, dataclasses.replace(base[3], color=base[3].color.clone())]
    ref_views = [dataclasses.replace(v) for v in views]  # the same tensors, kept out of the stacking
    teacher = RestTeacher(views, tr.cfg.rest_teacher.depth_tol)
    assert len(teacher._stacked()) == 2
    fr = p2_data.train[2]
    cam = RenderCamera.from_camera(fr.camera, "cpu")
    with torch.no_grad():
        verts = av.pose_mesh(_deformed_inputs(av, p2_data))
    ras = rasterize_mesh(verts, av.faces, cam.K, cam.w2c, cam.width, cam.height)
    pix = (ras.face_id.reshape(-1) >= 0).nonzero().squeeze(-1)
    fid = ras.face_id.reshape(-1)[pix]
    bary = ras.bary.reshape(-1, 3)[pix]
    _, dirs = pixel_rays(cam.K, cam.w2c, cam.width, cam.height, pix)
    frames = surfel_frames(verts, av.faces)
    look = teacher.lookup(av.faces, fid, bary, dirs, frames)
    color, valid, view = _sequential_lookup(ref_views, teacher.depth_tol, av.faces, fid, bary, dirs, frames)
    assert int(valid.sum()) > 100 and bool((view == len(base) - 1).any())  # the cropped view wins somewhere
    assert bool((view == 2).any()) and not bool((view == len(base)).any())  # view 3's duplicate never beats it
    assert torch.equal(look.valid, valid) and torch.equal(look.view, view)
    torch.testing.assert_close(look.color, color, atol=1e-6, rtol=0)
    rot = surfel_frames(verts, av.faces[fid])[0]
    again = teacher.lookup(av.faces, fid, bary, dirs, deformed_rotations=rot)
    assert torch.equal(again.view, look.view) and torch.equal(again.color, look.color)
    for v, r in zip(views, ref_views):  # the views now hold slices of the stacks, with the same values
        assert torch.equal(v.color, r.color) and torch.equal(v.depth, r.depth) and torch.equal(v.frames[0], r.frames[0])
    with pytest.raises(ValueError):
        teacher.lookup(av.faces, fid, bary, dirs)
    views[0].color.zero_()  # a view changed in place is seen (its pixels come from it, now black)
    dark = teacher.lookup(av.faces, fid, bary, dirs, frames)
    first = look.view == 0
    assert bool(first.any()) and bool((dark.color[first] == 0).all()) and torch.equal(dark.color[~first], look.color[~first])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pixel_rays_equal_the_full_image_rays(dtype):
    """pixel_rays computes the selected pixels only: the same rays as ray_directions over the image."""
    from sage_core.data.cameras import look_at
    from sage_core.render.mesh_raster import ray_directions

    W, H = 37, 23
    K = torch.tensor([[50.0, 0.3, 18.2], [0.0, 52.0, 11.7], [0.0, 0.0, 1.0]], dtype=dtype)
    w2c = torch.as_tensor(look_at(torch.tensor([0.3, -0.2, 1.5]).numpy(), torch.zeros(3).numpy()), dtype=dtype)
    pix = torch.tensor([0, 1, W - 1, W, W * H - 1, 5 * W + 17, 5 * W + 17, 300])
    o, d = pixel_rays(K, w2c, W, H, pix)
    o_ref, d_ref = ray_directions(K, w2c, W, H)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    assert o.dtype == d.dtype == dtype and o.shape == d.shape == (pix.numel(), 3)
    torch.testing.assert_close(d, d_ref.reshape(-1, 3)[pix], atol=tol, rtol=0)
    torch.testing.assert_close(o, o_ref.reshape(-1, 3)[pix], atol=tol, rtol=0)
    empty_o, empty_d = pixel_rays(K, w2c, W, H, pix[:0])
    assert empty_o.shape == empty_d.shape == (0, 3)


def test_default_phase2_keeps_the_appearance_network_and_trains_the_shape_network(phase1_avatar_path, p2_data, p2_init_dir):
    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir)
    assert tr.cfg.lr.networks == 0.0 and tr.cfg.lr.shape > 0 and tr.cfg.mouth.visibility == "surfels"
    av = tr.avatar
    app0 = {k: v.clone() for k, v in av.appearance.state_dict().items()}
    shape0 = {k: v.clone() for k, v in av.shape.state_dict().items()}
    for _ in range(3):
        tr.step()
    for k, v in av.appearance.state_dict().items():
        torch.testing.assert_close(v, app0[k], atol=0, rtol=0)
    assert any(not torch.equal(v, shape0[k]) for k, v in av.shape.state_dict().items())


def test_render_settings_keep_the_correction_mode_an_avatar_was_trained_with(tmp_path):
    import json

    from sage_core.config import Phase2Config, canonical_form, to_dict
    from sage_core.stages.avatars import stage_render_settings

    cfg = to_dict(Phase2Config())
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    s = stage_render_settings(tmp_path, None)
    assert s.correction is not None and s.correction["mode"] == "affine" and s.correction["radius_edges"] is None
    off = json.loads(json.dumps(cfg))
    off["correction"]["enabled"] = False
    (tmp_path / "config.json").write_text(json.dumps(off))
    assert stage_render_settings(tmp_path, None).correction is None
    # a config saved before the phase configs had sections (the flat form of canonical_form)
    flat = canonical_form(Phase2Config())
    assert flat["correction"] is True and flat["correction_mode"] == "affine"
    (tmp_path / "config.json").write_text(json.dumps({**flat, "correction_radius_edges": 1.5}))
    s = stage_render_settings(tmp_path, None)
    assert s.correction == {"radius_edges": 1.5, "max_neighbours": 16, "w_s": 0.0, "umbilic_tol": 1.0, "anisotropy_tol": 0.1, "mode": "affine"}
    # a phase-2 config from before the mode option: the curvature mode it was trained with
    old = {k: v for k, v in flat.items() if k != "correction_mode"}
    old["correction_radius_edges"] = 2.0
    (tmp_path / "config.json").write_text(json.dumps(old))
    s = stage_render_settings(tmp_path, None)
    assert s.correction["mode"] == "curvature" and s.correction["radius_edges"] == 2.0
    (tmp_path / "config.json").write_text(json.dumps({**flat, "correction": False}))
    assert stage_render_settings(tmp_path, None).correction is None


def test_unseen_fill_continues_each_groups_seen_surfels_and_keeps_the_back_covered(phase1_avatar_path, p2_data, p2_init_dir,
                                                                                    monkeypatch):
    from sage_core.avatar.init import REGION_EYES, REGION_FACE, REGION_HAIR, REGION_MOUTH, REGION_NECK, REGION_OTHER
    from sage_core.train.phase2 import SEEN_MIN_WEIGHT, unseen_fill_groups

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False)
    av = tr.avatar
    N = len(av.surfels)
    g = torch.Generator().manual_seed(1)
    weights = torch.rand(N, generator=g, dtype=torch.float64) * 4.0
    weights[torch.randperm(N, generator=g)[: N // 5]] = 0.0
    taken = torch.zeros(N, dtype=torch.bool)
    taken[:7] = True
    weights[:7] = 0.0
    seen = weights >= SEEN_MIN_WEIGHT
    region = av.surfels.region_id
    hair = av.surfels.hair_mask()
    with torch.no_grad():
        colors = av.posed(av.frame_inputs(p2_data.canonical_timestep), None, shade=False).colors
    # without unseen_fill.hair: every region but the hair, each from its own seen surfels
    fill, rgb = tr.unseen_fill_colors(weights, taken, 4)
    assert not bool((fill & (seen | taken | hair)).any())
    assert bool(fill.any()) and rgb.shape == (int(fill.sum()), 3)
    for r in torch.unique(region[fill]).tolist():
        src = colors[seen & (region == r)]
        got = rgb[region[fill] == r]
        # a harmonic continuation is a mean of its sources: inside their colour range
        assert bool((got >= src.min(0).values - 1e-5).all() and (got <= src.max(0).values + 1e-5).all())
    assert unseen_fill_groups(False) == ((REGION_OTHER,), (REGION_FACE,), (REGION_EYES,), (REGION_NECK,), (REGION_MOUTH,))
    assert (REGION_HAIR, REGION_OTHER) in unseen_fill_groups(True)
    # through the trainer with the single-camera regimes' settings: the filled surfels carry the colours
    # as their prior; the hair's unseen surfels are filled too and get the unseen floor
    monkeypatch.setattr(Phase2Trainer, "surfel_view_weights", lambda self: weights.clone())
    tr2 = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False, unseen_fill=True, unseen_fill_hair=True)
    res = tr2.unseen_fill_result
    prior = tr2.avatar.surfels.color_prior
    assert prior is not None and torch.equal(prior[:, 3] > 0, res.filled)
    torch.testing.assert_close(prior[res.filled, :3], res.colors[res.filled].to(prior))
    assert bool((res.filled & hair).any()) and not bool((res.filled & seen).any())
    floor = tr2.avatar.surfels.unseen_floor
    assert floor is not None
    assert bool((floor[~res.filled, 0] == 0).all() and (floor[~res.filled, 1] == 1).all())
    assert bool((floor[res.filled & hair, 0] > 0).all() and (floor[:, 1] >= 1).all())
    # the floor reaches the posed opacities and scales; seen surfels are posed as before
    inputs = tr2.avatar.frame_inputs(p2_data.canonical_timestep)
    with torch.no_grad():
        after = tr2.avatar.posed(inputs, None)
        ref = _avatar(phase1_avatar_path).posed(inputs, None)
    torch.testing.assert_close(after.opacities[seen], ref.opacities[seen])
    torch.testing.assert_close(after.scales[seen], ref.scales[seen])
    assert bool((after.opacities[res.filled & hair] >= floor[res.filled & hair, 0] - 1e-6).all())
    # the neck is covered only with cover_neck (the single-camera regimes' default), and no surfel's
    # disc grows past the mesh's open boundary (the neck's cut)
    neck = res.filled & (region == REGION_NECK)
    assert bool(neck.any()) and bool((floor[neck, 1] == 1).all()) and "opacity_floor" not in res.per_group[str(REGION_NECK)]
    tr3 = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False, unseen_fill=True, unseen_fill_hair=True,
                   **{"unseen_fill.cover_neck": True})
    res3, floor3 = tr3.unseen_fill_result, tr3.avatar.surfels.unseen_floor
    assert torch.equal(res3.filled, res.filled)
    src_op = ref.opacities[seen & (region == REGION_NECK) & ~taken]
    assert res3.per_group[str(REGION_NECK)]["opacity_floor"] == pytest.approx(float(src_op.median()), rel=1e-5)
    assert bool((floor3[neck, 0] >= float(src_op.median()) - 1e-6).all())
    from sage_core.geometry.topology import boundary_edges, distance_to_segments

    canon = tr3.avatar.canonical_state()
    v = tr3.avatar.canonical_vertices.detach().double().numpy()
    e = boundary_edges(tr3.avatar.faces.numpy())
    assert len(e) > 0
    d_edge = torch.as_tensor(distance_to_segments(canon.means.detach().double().numpy(), v[e[:, 0]], v[e[:, 1]]))
    geo = canon.scales.detach().double().prod(-1).sqrt()
    grown = res3.filled & (floor3[:, 1] > 1)
    assert bool((geo[grown] * floor3[grown, 1].double() <= d_edge[grown] / 3.0 + 1e-9).all())
    # with cover_away the seen hair surfels that no view faces get the floor too, their colours kept
    away = seen & hair & (torch.arange(len(seen)) % 2 == 0)
    toward = torch.where(away, -0.5, 0.5).double()

    def weights_and_toward(self):
        self.view_toward = toward.clone()
        return weights.clone()

    monkeypatch.setattr(Phase2Trainer, "surfel_view_weights", weights_and_toward)
    tr4 = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False, unseen_fill=True, unseen_fill_hair=True,
                   **{"unseen_fill.cover_away": True})
    res4, floor4 = tr4.unseen_fill_result, tr4.avatar.surfels.unseen_floor
    assert bool(away.any()) and torch.equal(res4.filled, res.filled) and torch.equal(res4.covered, res.covered | away)
    assert torch.equal(tr4.avatar.surfels.color_prior[:, 3] > 0, res4.filled)
    hair_floor = next(v["opacity_floor"] for k, v in res4.per_group.items() if str(REGION_HAIR) in k.split("+"))
    assert bool((floor4[away, 0] >= hair_floor - 1e-6).all()) and bool((floor4[seen & ~away, 0] == 0).all())


def test_view_toward_is_the_largest_cosine_of_each_surfels_triangle_to_the_training_cameras(phase1_avatar_path, p2_data, p2_init_dir):
    """:attr:`Phase2Trainer.view_toward`, which tells the cover which surfels no training view faces,
    recomputed from the posed meshes and camera centres of the same views."""
    from sage_core.train.phase2 import evenly_spaced_frames

    tr = _trainer(phase1_avatar_path, p2_data, p2_init_dir, mouth_prior=False, unseen_fill=True, unseen_fill_hair=True)
    av = tr.avatar
    got = tr.view_toward
    assert got is not None and got.shape == (len(av.surfels),)
    want = torch.full((len(av.surfels),), -1.0, dtype=torch.float64)
    with torch.no_grad():
        for fr in evenly_spaced_frames(tr.frames, tr.cfg.rest_teacher.max_views):
            v = av.pose_mesh(tr.inputs(fr.timestep)).double()
            tri = v[av.faces]
            n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
            n = n / n.norm(dim=-1, keepdim=True)
            means = av.posed(tr.inputs(fr.timestep), None, shade=False).means.double()
            to_cam = torch.as_tensor(fr.camera.center) - means
            cos = (n[av.surfels.binding] * to_cam).sum(-1) / to_cam.norm(dim=-1)
            want = torch.maximum(want, cos)
    torch.testing.assert_close(got, want, atol=1e-4, rtol=0)
    # the face is faced by the cameras of a frontal rig; some of the back of the head by none
    region = av.surfels.region_id
    from sage_core.avatar.init import REGION_FACE

    assert float(got[region == REGION_FACE].median()) > 0.5 and bool((got < 0).any())


def test_correction_radius_defaults_by_attributes(phase1_avatar_path):
    from sage_core.avatar.corrected import default_radius_edges, median_edge_length

    av = _avatar(phase1_avatar_path)
    edge = median_edge_length(av.canonical_vertices.detach(), av.faces)
    assert default_radius_edges("mlp") == 1.0 and default_radius_edges("free") == 2.0
    posing = CorrectedPosing(av, True)
    assert posing.radius == pytest.approx(default_radius_edges(av.attributes) * edge)
    assert CorrectedPosing(av, True, radius_edges=1.5).radius == pytest.approx(1.5 * edge)
