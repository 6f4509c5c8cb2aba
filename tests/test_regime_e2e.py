"""End to end through the CLI: a synthetic monocular clip as sv-hr, and a single image as one-shot
(synth → ingest → init-mesh → phase 1 with a few iterations)."""

from __future__ import annotations

import importlib.util
import json
import math

import pytest
import torch
from typer.testing import CliRunner

from sage_cli.app import app

_INIT = ["--preset", "tiny", "--steps", "10", "--mc-resolution", "24", "--set", "pretrain.bank_size=3000",
         "--set", "pretrain.batch_size=512", "--set", "pretrain.eval_samples=1000", "--quiet", "--device", "cpu"]  # fmt: skip
_P1 = ["--preset", "tiny", "--device", "cpu", "--iterations", "3", "--surfels", "500"] + [
    a for kv in ("rays_per_step=32", "neus_samples=8", "neus_importance=8", "neus_up_steps=1", "app_hidden=16",
                 "shape_hidden=16", "smooth_points=64", "sym_points=64", "mc_resolution=24", "eval_every=0",
                 "polish_fraction=0")
    for a in ("--set", kv)
]  # fmt: skip


def _ok(res) -> None:
    assert res.exit_code == 0, res.output


def _finite(d: dict) -> bool:
    return all(math.isfinite(v) for v in d.values())


def test_svhr_end_to_end(tmp_path, one_thread):
    r = CliRunner()
    cap, ws = tmp_path / "cap", tmp_path / "ws"
    _ok(r.invoke(app, ["synth", str(cap), "--preset", "tiny", "--regime", "monocular", "--width", "48", "--height", "69",
                       "--train-timesteps", "4", "--test-timesteps", "1", "--quiet"]))
    model = cap / "model" / "synth_flame.pkl"
    res = r.invoke(app, ["ingest", str(cap), str(ws), "--regime", "sv-hr", "--flame-model", str(model), "--device", "cpu"])
    _ok(res)
    assert "head coverage" in res.output and "yaw" in res.output
    manifest = json.loads((ws / "data" / "manifest.json").read_text())
    m = manifest["metrics"]
    assert m["regime"] == "sv-hr"
    assert m["coverage_yaw_min_deg"] < -40 and m["coverage_yaw_max_deg"] > 40 and m["coverage_narrow"] is False
    _ok(r.invoke(app, ["init-mesh", str(ws), *_INIT]))
    res = r.invoke(app, ["phase1", str(ws), *_P1, "--set", "pose_refine=true", "--set", "pose_refine_from=1"])
    _ok(res)
    assert "head coverage (sv-hr): yaw" in res.output and "test PSNR" in res.output
    cfg = json.loads((ws / "phase1" / "config.json").read_text())
    assert cfg["appearance"]["sh_degree"] == 0 and cfg["exposure"] == "gain" and cfg["loss"]["sym_sdf"] > 0 and cfg["loss"]["sym_color"] > 0
    metrics = json.loads((ws / "phase1" / "metrics.json").read_text())
    assert _finite(metrics["final_losses"]) and "sym_sdf" in metrics["final_losses"]
    gains = metrics["exposure_gains"]
    assert len(gains) == 4 and all(len(g) == 1 and 0.5 < g[0] < 2.0 for g in gains.values())
    assert math.isfinite(metrics["test_psnr"]) and metrics["test_images"] == 1
    assert metrics["pose_refine_rotation_max_deg"] > 0
    assert abs(metrics["symmetry_plane_normal"][0]) > 0.99
    p1 = json.loads((ws / "phase1" / "manifest.json").read_text())["metrics"]
    assert "exposure_gain_min" in p1 and "exposure_gains" not in p1


def test_svhr_warns_on_a_narrow_clip(tmp_path, one_thread):
    """A multiview capture restricted to its frontal camera sees the head from one direction only."""
    r = CliRunner()
    cap, ws = tmp_path / "cap", tmp_path / "ws"
    _ok(r.invoke(app, ["synth", str(cap), "--preset", "tiny", "--width", "32", "--height", "46", "--cameras", "3",
                       "--train-timesteps", "2", "--test-timesteps", "1", "--quiet"]))
    model = cap / "model" / "synth_flame.pkl"
    res = r.invoke(app, ["ingest", str(cap), str(ws), "--regime", "sv-hr", "--flame-model", str(model), "--device", "cpu"])
    assert res.exit_code != 0 and "transforms_train.json" in res.output and "sv-hr needs one camera" in res.output
    res = r.invoke(app, ["ingest", str(cap), str(ws), "--regime", "sv-hr", "--camera", "1", "--flame-model", str(model), "--device", "cpu"])
    _ok(res)
    assert "narrower than ±45°" in res.output
    m = json.loads((ws / "data" / "manifest.json").read_text())["metrics"]
    assert m["coverage_narrow"] is True and m["train_cameras"] == 1 and m["val_images"] >= 2


def test_one_shot_end_to_end(tmp_path, one_thread):
    r = CliRunner()
    cap, ws = tmp_path / "cap", tmp_path / "ws"
    _ok(r.invoke(app, ["synth", str(cap), "--preset", "tiny", "--regime", "oneshot", "--width", "48", "--height", "69", "--quiet"]))
    model = cap / "model" / "synth_flame.pkl"
    _ok(r.invoke(app, ["ingest", str(cap), str(ws), "--regime", "one-shot", "--flame-model", str(model), "--quiet", "--device", "cpu"]))
    m = json.loads((ws / "data" / "manifest.json").read_text())["metrics"]
    assert m["train_images"] == 1 and "coverage_yaw_min_deg" in m
    _ok(r.invoke(app, ["init-mesh", str(ws), *_INIT]))
    res = r.invoke(app, ["phase1", str(ws), *_P1, "--set", "pseudo_view_prob=0.7", "--set", "exposure=rgb", "--quiet"])
    _ok(res)
    cfg = json.loads((ws / "phase1" / "config.json").read_text())
    assert cfg["appearance"]["sh_degree"] == 0 and cfg["exposure"] == "rgb" and cfg["loss"]["sym_sdf"] > 0 and cfg["pseudo"]["prob"] == 0.7
    metrics = json.loads((ws / "phase1" / "metrics.json").read_text())
    assert _finite(metrics["final_losses"])
    assert len(metrics["exposure_gains"]) == 1 and len(next(iter(metrics["exposure_gains"].values()))) == 3
    if importlib.util.find_spec("sage_core.train.pseudo_views") is not None:
        assert metrics["pseudo_views"] > 0


# ---------------------------------------------------------------------------- the whole chain, per regime
CHAIN_SETS = [
    "init_mesh.pretrain.steps=5", "init_mesh.pretrain.bank_size=2000", "init_mesh.pretrain.batch_size=512",
    "init_mesh.pretrain.eval_samples=500", "init_mesh.mc_resolution=24",
    "phase1.iterations=2", "phase1.surfels.count=300", "phase1.schedule.eval_every=0", "phase1.mc_resolution=24",
    "phase1.neus.rays_per_step=32", "phase1.neus.samples=8", "phase1.neus.importance=8", "phase1.appearance.hidden=16",
    "phase1.shape.hidden=16", "phase1.pseudo.ring_views=1", "phase1.pseudo.ring_supersample=1",
    "phase2.iterations=1", "phase2.pixels.per_step=32", "phase2.eval_phase1=false", "phase2.rest_teacher.max_views=2",
    "eval.samples=1", "export.mc_resolution=24",
]  # fmt: skip
"""Settings of a whole chain in seconds (numbers not representative)."""

_CAPTURES = {  # regime of sage ingest -> sage synth options of a small capture of it
    "mv-sf": ["--regime", "multiview", "--cameras", "4", "--train-timesteps", "1", "--test-timesteps", "1"],
    "sv-hr": ["--regime", "monocular", "--train-timesteps", "4", "--test-timesteps", "1"],
    "one-shot": ["--regime", "oneshot"],
}


@pytest.fixture(scope="module")
def regime_captures(tmp_path_factory):
    r = CliRunner()
    root = tmp_path_factory.mktemp("regime_caps")
    for regime, opts in _CAPTURES.items():
        _ok(r.invoke(app, ["synth", str(root / regime), "--preset", "tiny", "--width", "48", "--height", "69", "--quiet", *opts]))
    return root


def _sets() -> list[str]:
    return [a for kv in CHAIN_SETS for a in ("--set", kv)]


@pytest.mark.slow
def test_one_shot_through_sage_run_evaluates_the_held_out_ground_truth_and_exports(regime_captures, tmp_path, one_thread):
    """One image: no val or test frames, so the chain evaluates gt/novel (and does not stop at eval);
    the synth spelling of the regime is accepted."""
    from helpers import invoke

    cap, ws = regime_captures / "one-shot", tmp_path / "ws"
    res = invoke(["run", str(cap), str(ws), "--flame-model", str(cap / "model" / "synth_flame.npz"), "--regime", "oneshot",
                  "--preset", "tiny", "--device", "cpu", "--threads", "1", *_sets()])  # fmt: skip
    _ok(res)
    assert json.loads((ws / "data" / "manifest.json").read_text())["metrics"]["regime"] == "one-shot"
    novel = json.loads((ws / "eval" / "phase2" / "novel" / "metrics.json").read_text())
    assert math.isfinite(novel["overall"]["psnr"]) and math.isfinite(novel["visible_region"]["overall"]["psnr"])
    assert not (ws / "eval" / "phase2" / "val").exists() and not (ws / "eval" / "phase2" / "test").exists()
    assert (ws / "export" / "bundle").is_dir() and (ws / "export" / "ply" / "canonical.ply").is_file()
    out = " ".join(res.output.split())
    assert "held-out views and expressions (gt/novel) PSNR / SSIM / LPIPS" in out and "on the surface the training views saw" in out
    assert "eval novel" in out and "export" in out


@pytest.mark.slow
def test_every_regime_through_sage_batch_reports_held_out_metrics(regime_captures, tmp_path):
    """mv-sf, sv-hr and one-shot subjects (sv-hr and one-shot spelled as sage synth names them) all
    finish; the summary carries each one's held-out metrics: val and gt/novel (a detailed multiview
    capture's views of its training timestep from new directions) for mv-sf, test and gt/novel for
    sv-hr, gt/novel for one-shot."""
    from sage_cli.commands.batch_cmd import batch

    import typer

    rows = ["id,capture,regime,flame_model"] + [
        f"{rid},{regime_captures / reg},{spelling},{regime_captures / reg / 'model' / 'synth_flame.npz'}"
        for rid, reg, spelling in (("mv", "mv-sf", "mv-sf"), ("mono", "sv-hr", "monocular"), ("one", "one-shot", "oneshot"))
    ]
    subjects = tmp_path / "subjects.csv"
    subjects.write_text("\n".join(rows) + "\n")
    local = typer.Typer(add_completion=False)
    local.command()(batch)
    root = tmp_path / "root"
    res = CliRunner().invoke(local, [str(subjects), str(root), "--preset", "tiny", "--device", "cpu", "--quiet", "--skip-phase2",
                                     "--max-parallel", "1", "--cpus-per-subject", "1", *_sets()])  # fmt: skip
    assert res.exit_code == 0, res.output
    doc = json.loads((root / "batch_summary.json").read_text())
    s = {x["id"]: x for x in doc["subjects"]}
    assert all(x["status"] == "finished" for x in s.values()), {k: (x["status"], x["error"]) for k, x in s.items()}
    assert math.isfinite(s["mv"]["metrics"]["val_psnr"]) and math.isfinite(s["mv"]["metrics"]["novel_psnr"])
    assert math.isfinite(s["mono"]["metrics"]["test_psnr"]) and math.isfinite(s["mono"]["metrics"]["novel_psnr"])
    assert math.isfinite(s["one"]["metrics"]["novel_psnr"]) and s["one"]["metrics"]["val_psnr"] is None
    assert all((root / rid / "export" / "bundle").is_dir() for rid in s)
    md = (root / "batch_summary.md").read_text()
    assert "novel PSNR" in md
