"""Phase 1 on the tiny synthetic workspace: the loss falls, exact resume, the command's outputs."""

from __future__ import annotations

import io
import json
import shutil

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

from sage_cli.app import app as main_app
from sage_cli.commands.phase1 import phase1
from sage_core.config import resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.train.phase1 import Phase1Trainer, build_avatar

_SMALL = {
    "n_surfels": 1500,
    "rays_per_step": 64,
    "neus_samples": 8,
    "neus_importance": 8,
    "neus_up_steps": 1,
    "app_hidden": 16,
    "shape_hidden": 16,
    "mc_resolution": 40,
    "normal_consistency_from": 2,
    "distortion_from": 2,
    "eval_every": 0,
    "polish_fraction": 0.0,
}


@pytest.fixture(scope="module")
def init_ws(tiny_ws, tmp_path_factory):
    """A workspace with init-mesh done (few pretraining steps)."""
    ws = tmp_path_factory.mktemp("p1") / "ws"
    shutil.copytree(tiny_ws, ws)
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    res = CliRunner().invoke(
        main_app,
        ["init-mesh", str(ws), "--preset", "tiny", "--steps", "40", "--mc-resolution", "32", "--set", "pretrain.bank_size=4000",
         "--set", "pretrain.batch_size=1024", "--set", "pretrain.eval_samples=2000", "--quiet", "--device", "cpu"],
    )  # fmt: skip
    torch.set_num_threads(n)
    assert res.exit_code == 0, res.output
    return ws


def _trainer(ws, mode, **over):
    data = IngestedData.open(ws / "data")
    cfg = resolve_config("phase1", "tiny", None, {**_SMALL, "attributes": mode, **over})
    g = torch.Generator().manual_seed(3)
    torch.manual_seed(3)
    av = build_avatar(data, ws / "init", cfg, "cpu", g)
    return Phase1Trainer(av, data, cfg, "cpu", g)


@pytest.mark.parametrize("mode", ["mlp", "free"])
def test_steps_lower_the_loss(init_ws, mode, one_thread):
    tr = _trainer(init_ws, mode, iterations=40)
    before = tr.evaluate("train", max_frames=3)["psnr"]
    hist = [tr.step() for _ in range(40)]
    after = tr.evaluate("train", max_frames=3)["psnr"]
    first = np.mean([h["rgb"] for h in hist[:5]])
    last = np.mean([h["rgb"] for h in hist[-5:]])
    assert last < first
    assert after > before + 0.5
    for key in ("pt", "align", "depth", "normal", "neus_rgb", "eikonal", "smooth", "normal_consistency", "distortion"):
        assert np.isfinite(hist[-1][key]), key


@pytest.mark.parametrize("offset_lr", [0.0, 0.05])
def test_resume_repeats_the_loss_curve(init_ws, offset_lr, one_thread):
    n = 6
    # rebinding and relocation both every 2 steps: their state (bindings, moved rows, optimiser rows) resumes too,
    # and so does the opacity offset when one is trained
    over = {"iterations": n, "rebind_every": 2, "relocate.enabled": True, "relocate.every": 2, "relocate.until": 1.0,
            "relocate.floor": 1e9, "relocate.views": 2, "lr.opacity_offset": offset_lr}
    ref = _trainer(init_ws, "mlp", **over)
    straight = [ref.step() for _ in range(n)]

    first = _trainer(init_ws, "mlp", **over)
    part = [first.step() for _ in range(n // 2)]
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    del first
    second = _trainer(init_ws, "mlp", **over)
    buf.seek(0)
    second.load_state_dict(torch.load(buf, weights_only=False))
    part += [second.step() for _ in range(n - n // 2)]
    for a, b in zip(straight, part):
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-6, abs=1e-7), k
    assert torch.equal(ref.avatar.surfels.binding, second.avatar.surfels.binding)
    assert any(h.get("relocated", 0) > 0 for h in straight)
    if offset_lr > 0:
        assert torch.equal(ref.avatar.surfels.opacity_offset, second.avatar.surfels.opacity_offset)
        assert float(ref.avatar.surfels.opacity_offset.detach().abs().max()) > 0
    else:
        assert ref.avatar.surfels.opacity_offset is None


def test_resume_after_a_registration_round_keeps_the_registered_pose(init_ws, one_thread):
    from sage_core.train.phase1 import registration_decision, registration_rounds

    n = 6
    over = {"iterations": n, "registration.mode": "on", "registration.rounds": 2, "registration.min_pixels": 0.0,
            "registration.max_translation": 1.0}

    def trainer() -> Phase1Trainer:
        tr = _trainer(init_ws, "mlp", **over)
        tr.registration = registration_rounds(tr, init_ws / "init", registration_decision(tr.data, tr.cfg))
        return tr

    ref = trainer()
    assert ref.registration is not None and ref.registration.steps == [3]
    row = ref.data.params.row_of(ref.avatar.canonical_timestep)
    straight = []
    for _ in range(n):
        straight.append(ref.step())
        if ref.registration.due(ref.step_count):
            met = ref.register(ref.step_count)
    assert met["registration"] == "applied" and met["registration_step"] == 3
    assert not np.allclose(ref.avatar.params.translation[row], ref.data.params.translation[row])

    first = trainer()
    part = [first.step() for _ in range(n // 2)]
    first.register(n // 2)
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    del first
    second = trainer()
    buf.seek(0)
    second.load_state_dict(torch.load(buf, weights_only=False))
    assert np.array_equal(second.avatar.params.translation, ref.avatar.params.translation)
    part += [second.step() for _ in range(n - n // 2)]
    for a, b in zip(straight, part):
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-6, abs=1e-7), k
    assert second.registration is not None and second.registration.state_dict() == ref.registration.state_dict()


def test_command_writes_outputs_and_manifest(init_ws, tmp_path, one_thread):
    ws = tmp_path / "ws"
    shutil.copytree(init_ws, ws)
    app = typer.Typer()
    app.command("phase1")(phase1)
    app.command("other")(lambda: None)
    args = ["phase1", str(ws), "--preset", "tiny", "--attributes", "free", "--iterations", "8", "--surfels", "1200", "--quiet", "--device", "cpu"]
    for k, v in _SMALL.items():
        if k != "n_surfels":
            args += ["--set", f"{k}={v}"]
    args += ["--set", "registration.rounds=2"]
    res = CliRunner().invoke(app, args + ["--set", "checkpoint_every=4"])
    assert res.exit_code == 0, res.output
    out = ws / "phase1"
    for name in ("avatar.pt", "sdf_mesh.ply", "metrics.json", "manifest.json", "config.json"):
        assert (out / name).is_file(), name
    renders = list((out / "renders").glob("val_*.png"))
    assert len(renders) == 1
    m = json.loads((out / "manifest.json").read_text())
    met = m["metrics"]
    assert met["attributes"] == "free" and met["n_surfels"] == 1200 and met["iterations"] == 8
    for key in ("val_psnr", "val_ssim", "train_psnr", "chamfer_m", "chamfer_rel", "iterations_per_s"):
        assert np.isfinite(met[key]), key
    assert met["val_psnr"] > 10 and met["chamfer_rel"] < 0.1
    assert not (ws / ".work" / "phase1" / "checkpoints").exists()
    from sage_core.avatar.model import Avatar

    av = Avatar.load(out / "avatar.pt")
    assert av.attributes == "free" and len(av.surfels) == 1200
    # one multiview timestep: phase 1 ends with the registration of its pose (applied, or why not)
    data = IngestedData.open(ws / "data")
    row = data.params.row_of(av.canonical_timestep)
    moved = (av.params.translation[row] - data.params.translation[row]) * 1000.0
    # (two rounds: after step 4 of 8, while the SDF trains, and after the last)
    assert [r["registration_step"] for r in met["registration_rounds"]] == [4, 8]
    assert np.allclose(moved, met["registration_applied_world_mm"], atol=1e-3)
    if met["registration"] == "applied":
        assert met["registration_applied_mm"] > 0
    else:
        assert met["registration"].startswith("skipped") and np.allclose(moved, 0.0)
    res = CliRunner().invoke(app, args + ["--set", "checkpoint_every=4"])
    assert res.exit_code == 0 and "skipping" in res.output
    bad = CliRunner().invoke(app, ["phase1", str(ws), "--attributes", "nope", "--quiet"])
    assert bad.exit_code != 0


def test_background_band_rays_and_mask_terms(init_ws, one_thread):
    tr = _trainer(init_ws, "mlp", iterations=4, neus_background_rays=0.5, neus_background_band=3, w_neus_mask=0.1, w_mask=0.1)
    assert tr.frames[0].mask is not None
    _, mask, _ = tr._frame(0)
    fg_pix, band = tr._ray_pixels(0, mask)
    assert band.numel() > 0
    flat = mask.reshape(-1)
    assert torch.equal(fg_pix, torch.nonzero(flat > 0.5).reshape(-1))
    # the band is exactly the background within 3 pixels (Chebyshev) of a foreground pixel
    h, w = mask.shape
    fg = mask > 0.5
    padded = torch.nn.functional.pad(fg.to(torch.uint8), (3, 3, 3, 3)).bool()
    near = torch.zeros_like(fg)
    for dy in range(7):
        for dx in range(7):
            near |= padded[dy : dy + h, dx : dx + w]
    assert torch.equal(band, torch.nonzero((near & ~fg).reshape(-1)).reshape(-1))
    seen = set()
    for _ in range(4):
        out = tr.step()
        seen |= set(out)
        for key in ("neus_mask", "mask"):
            if key in out:
                assert np.isfinite(out[key]) and out[key] >= 0, key
    assert {"neus_mask", "mask"} <= seen


def test_mask_band_leaves_the_masks_edge_out_of_the_mask_terms(init_ws, one_thread):
    from sage_core.train.phase1 import mask_edge_keep

    losses = {}
    for band in (0, 1):
        tr = _trainer(init_ws, "mlp", iterations=4, w_neus_mask=0.1, w_mask=0.1, mask_band=band)
        out = tr.step()
        losses[band] = (out["mask"], out["neus_mask"])
        _, mask, _ = tr._frame(0)
        keep = mask_edge_keep(mask, band)
        assert 0 < int((keep == 0).sum()) < keep.numel() if band else bool((keep == 1).all())
    # the same first render, its outline's disagreement with the mask no longer counted
    assert losses[1][0] < losses[0][0]
    assert np.isfinite(losses[1][1]) and losses[1][1] >= 0


def test_polish_fraction_trains_on_the_photometric_loss_alone(init_ws, one_thread):
    tr = _trainer(init_ws, "mlp", iterations=6, polish_fraction=0.5, w_mask=0.1)
    assert tr.polish_from == 3
    hist = [tr.step() for _ in range(6)]
    geometric = ("pt", "align", "depth", "normal", "neus_rgb", "eikonal", "normal_consistency", "distortion", "mask")
    assert all({"pt", "neus_rgb", "mask"} <= set(h) for h in hist[:3])
    assert {"normal_consistency", "distortion"} <= set(hist[2])
    for h in hist[3:]:
        assert "rgb" in h and not set(geometric) & set(h), sorted(h)


def _first_step_grads(ws, **over):
    tr = _trainer(ws, "mlp", iterations=4, **over)
    tr.step()
    app = [p.grad.clone() for p in tr.avatar.appearance.parameters() if p.grad is not None]
    sdf = [p.grad.clone() for p in tr.avatar.sdf.parameters() if p.grad is not None]
    return app, sdf


def test_neus_colour_leaves_the_appearance_fields_to_the_surfels_when_asked(init_ws, one_thread):
    """neus.appearance_grad=false: the NeuS colour term's gradient reaches the SDF, never the
    appearance network or its hash table; true (the paper's coupling) reaches both."""

    def same(a, b):
        return len(a) == len(b) and all(torch.equal(x, y) for x, y in zip(a, b))

    app_on, sdf_on = _first_step_grads(init_ws, w_neus_rgb=1.0)
    app_off, sdf_off = _first_step_grads(init_ws, w_neus_rgb=0.0)
    assert app_on and not same(app_on, app_off)  # the paper's coupling: NeuS colour trains the appearance
    app_on, sdf_on = _first_step_grads(init_ws, w_neus_rgb=1.0, **{"neus.appearance_grad": False})
    app_off, sdf_off = _first_step_grads(init_ws, w_neus_rgb=0.0, **{"neus.appearance_grad": False})
    assert app_on and same(app_on, app_off)
    assert sdf_on and not same(sdf_on, sdf_off)


def test_neus_colour_reaches_the_appearance_fields_at_the_share_asked(init_ws, one_thread):
    """neus.appearance_grad_scale=s: the appearance fields' gradient is the surfel render's plus s times
    the NeuS colour term's; the SDF's is the same as at s = 1."""
    app_1, sdf_1 = _first_step_grads(init_ws, w_neus_rgb=1.0)
    app_0, _ = _first_step_grads(init_ws, w_neus_rgb=1.0, **{"neus.appearance_grad_scale": 0.0})
    app_q, sdf_q = _first_step_grads(init_ws, w_neus_rgb=1.0, **{"neus.appearance_grad_scale": 0.25})
    assert len(app_1) == len(app_0) == len(app_q) > 0 and len(sdf_1) == len(sdf_q) > 0
    assert any(not torch.allclose(a, b) for a, b in zip(app_1, app_0))
    for a1, a0, aq in zip(app_1, app_0, app_q):
        torch.testing.assert_close(aq, a0 + 0.25 * (a1 - a0), rtol=1e-4, atol=1e-7)
    for s1, sq in zip(sdf_1, sdf_q):
        torch.testing.assert_close(sq, s1, rtol=1e-5, atol=1e-8)


def test_posed_mesh_is_kept_while_the_inputs_are_constant(init_ws, one_thread):
    """The trainer poses each timestep's mesh once, and not while a pose correction is learned."""
    tr = _trainer(init_ws, "mlp", iterations=4, pose_refine=True, pose_refine_from=2)
    t = tr.frames[0].timestep
    inputs, _ = tr.frame_inputs(t)
    mesh = tr.posed_mesh(t, inputs, None)
    assert mesh is not None and tr.posed_mesh(t, inputs, None) is mesh
    assert torch.equal(mesh.vertices, tr.avatar.pose_mesh(inputs))
    tr.step_count = 2
    corrected, _ = tr.frame_inputs(t)
    assert tr.posed_mesh(t, corrected, None) is None


def test_ssim_targets_are_kept_within_their_budget(init_ws, one_thread, monkeypatch):
    """Frames past the byte budget get their SSIM target made anew each step, with the same losses."""
    import sage_core.train.phase1 as p1

    runs = []
    for budget in (p1.SSIM_TARGET_BUDGET, 1):
        monkeypatch.setattr(p1, "SSIM_TARGET_BUDGET", budget)
        tr = _trainer(init_ws, "mlp", iterations=3)
        runs.append(([tr.step()["rgb"] for _ in range(3)], len(tr._ssim_targets)))
    (kept_losses, kept), (made_losses, made) = runs
    assert kept_losses == made_losses and kept >= 1 and made == 0


def test_default_initial_opacity_is_one_half_in_the_config_and_the_network():
    from sage_core.config import Phase1Config
    from sage_core.fields.appearance import AppearanceNetwork
    from sage_core.train.phase1 import appearance_args

    assert Phase1Config().appearance.init_opacity == 0.5
    assert appearance_args(Phase1Config())["opacity_bias"] == 0.0
    assert AppearanceNetwork(4, [-1.0] * 3, [1.0] * 3).mlp[-1].bias[3].item() == 0.0


@pytest.mark.parametrize("p", [0.5, 0.8808, 0.2])
def test_appearance_init_opacity_sets_the_opacity_logit_bias(p):
    """The appearance network starts every surfel near appearance.init_opacity: its opacity-logit bias is
    logit(p), and with the last layer's weights zeroed every predicted opacity is exactly p."""
    from sage_core.config import resolve_config
    from sage_core.fields.appearance import AppearanceNetwork
    from sage_core.train.phase1 import appearance_args

    args = appearance_args(resolve_config("phase1", flags={"appearance.init_opacity": p, "appearance.grid": False}))
    net = AppearanceNetwork(4, [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], **args)
    with torch.no_grad():
        net.mlp[-1].weight.zero_()
    g = torch.Generator().manual_seed(0)
    x = torch.rand(10, 3, generator=g) * 2 - 1
    v = torch.nn.functional.normalize(torch.randn(10, 3, generator=g), dim=-1)
    _, alpha = net(x, v, v, torch.randn(10, 4, generator=g))
    torch.testing.assert_close(alpha, torch.full((10,), p), rtol=0, atol=1e-6)


def test_relocation_sources_are_idle_facing_surfels_outside_mouth_and_eyes():
    from sage_core.avatar.init import REGION_EYES, REGION_MOUTH
    from sage_core.train import relocate

    regions = torch.tensor([0, REGION_MOUTH, 0, REGION_EYES, 0, 0, 0])
    contrib = torch.tensor([0.01, 0.0, 0.03, 0.0, 0.02, 5.0, 0.0])
    facing = torch.tensor([True, True, True, True, True, True, False])
    assert relocate.sources(regions, contrib, facing, 0.05, 10).tolist() == [0, 4, 2]  # least contributing first
    assert relocate.sources(regions, contrib, facing, 0.05, 2).tolist() == [0, 4]
    assert relocate.due(250, 250, 900) and not relocate.due(0, 250, 900) and not relocate.due(1000, 250, 900)


@pytest.mark.parametrize("mode", ["mlp", "free"])
def test_relocated_surfels_sit_flat_on_the_target_points(init_ws, mode, one_thread):
    from sage_core.train import relocate

    tr = _trainer(init_ws, mode, iterations=4)
    tr.step()
    av = tr.avatar
    s = av.surfels
    faces = torch.tensor([10, 200, 700])
    pts = av.canonical_vertices[av.faces[faces]].mean(1)  # (3, 3) the triangles' centroids
    nrm = av.R_c[faces][..., 2]
    ids = torch.tensor([0, 5, 9])
    assert relocate.move(tr, ids, pts, nrm) == 3
    centres = s.canonical_positions(av.R_c, av.T_c, av.k_c)
    assert torch.allclose(centres[ids], pts, atol=1e-6)
    assert torch.equal(s.binding[ids], faces)
    state = tr.optimizer.state[s.mu_loc]
    assert all(float(v[ids].abs().sum()) == 0 for v in state.values() if isinstance(v, torch.Tensor) and v.dim() > 0)
    if mode == "free":
        assert torch.allclose(torch.sigmoid(s.opacity.data[ids]), torch.full((3, 1), 0.5).reshape(s.opacity.data[ids].shape))
    out = tr.step()
    assert all(np.isfinite(v) for v in out.values())


def test_relocation_moves_idle_surfels_to_where_the_error_is(init_ws, one_thread):
    """With every facing surfel idle (floor above any contribution) a relocation moves its whole budget
    onto the SDF surface (within a few millimetres of the canonical mesh) and training goes on."""
    from sage_core.avatar.binding import nearest_triangles
    from sage_core.train import relocate

    tr = _trainer(init_ws, "mlp", iterations=10, **{"relocate.floor": 1e9, "relocate.fraction": 0.02, "relocate.views": 2})
    for _ in range(2):
        tr.step()
    before = tr.avatar.surfels.binding.clone()
    r = relocate.relocate(tr)
    assert r.sources == int(0.02 * len(tr.avatar.surfels)) and 0 < r.moved <= r.sources
    av = tr.avatar
    moved = torch.nonzero(av.surfels.binding != before).reshape(-1)
    assert moved.numel() > 0
    centres = av.surfels.canonical_positions(av.R_c, av.T_c, av.k_c)[moved].detach()
    _, dist = nearest_triangles(centres, av.canonical_vertices, av.faces)
    # on the SDF's surface (NeuS depth), which the 40 pretraining steps fitted to the mesh roughly
    assert float(dist.median()) < 0.01 and float(dist.max()) < 0.03
    out = tr.step()
    assert all(np.isfinite(v) for v in out.values())


def test_opacity_offset_trains_in_phase1_only_and_is_saved(init_ws, tmp_path, one_thread):
    """lr.opacity_offset > 0 gives the mlp surfels a per-surfel logit on the network's opacity: phase 1
    trains it, relocation restarts the moved rows, the avatar file keeps it, phase 2's groups leave it
    out; with the default rate 0 there is none."""
    from sage_core.avatar.model import Avatar
    from sage_core.train import relocate
    from sage_core.train._groups import surfel_param_groups

    assert _trainer(init_ws, "mlp", iterations=2).avatar.surfels.opacity_offset is None
    tr = _trainer(init_ws, "mlp", iterations=4, **{"lr.opacity_offset": 0.05})
    s = tr.avatar.surfels
    assert [g["name"] for g in tr.optimizer.param_groups].count("opacity_offset") == 1
    for _ in range(3):
        tr.step()
    off = s.opacity_offset.detach()
    assert float(off.abs().max()) > 0.05  # Adam moves every touched logit by about the rate per step
    ids = torch.tensor([1, 7, 11])
    pts = tr.avatar.canonical_vertices[tr.avatar.faces[torch.tensor([10, 200, 700])]].mean(1)
    relocate.move(tr, ids, pts, tr.avatar.R_c[torch.tensor([10, 200, 700])][..., 2])
    assert torch.equal(s.opacity_offset.data[ids], torch.zeros(3))
    assert all(float(v[ids].abs().sum()) == 0 for v in tr.optimizer.state[s.opacity_offset].values()
               if isinstance(v, torch.Tensor) and v.dim() > 0)
    # the posed opacities are the network's with exactly the offset added to their logits
    inputs = tr.avatar.frame_inputs(tr.frames[0].timestep)
    with torch.no_grad():
        with_off = tr.avatar.posed(inputs, None).opacities
        saved = s.opacity_offset.data.clone()
        s.opacity_offset.data.zero_()
        without = tr.avatar.posed(inputs, None).opacities
        s.opacity_offset.data.copy_(saved)
    inner = (without > 1e-4) & (without < 1 - 1e-4)
    assert bool(inner.any()) and not torch.allclose(with_off, without)
    expected = torch.sigmoid(torch.logit(without[inner].double()) + saved[inner].double())
    assert torch.allclose(with_off[inner].double(), expected, atol=1e-5)
    path = tr.avatar.save(tmp_path / "avatar.pt")
    back = Avatar.load(path)
    assert torch.equal(back.surfels.opacity_offset.detach(), s.opacity_offset.detach())
    with torch.no_grad():
        assert torch.allclose(back.posed(inputs, None).opacities, with_off, atol=1e-6)
    groups = surfel_param_groups(back, lr_position=0.0, lr_networks=0.0, lr_rotation=0.0, lr_scale=0.0, lr_color=0.0,
                                 lr_opacity=0.0, lr_shape=1e-5)
    assert "opacity_offset" not in [g["name"] for g in groups]
