"""The stage functions of sage_core.stages called directly: result objects and event sequences."""

from __future__ import annotations

import shutil

import pytest

from sage_core.config import resolve_config
from sage_core.stages import StageEvent, StageSettings

CPU = StageSettings(device="cpu", threads=1)
QUICK_INIT = {"pretrain.steps": 6, "pretrain.bank_size": 2000, "pretrain.batch_size": 512, "pretrain.eval_samples": 1000,
              "mc_resolution": 24}  # fmt: skip


def _kinds(events: list[StageEvent]) -> list[str]:
    """Event kinds in order, with runs of progress events collapsed into one (the duration
    estimate of a training loop counts as progress)."""
    out: list[str] = []
    for e in events:
        kind = "progress" if e.kind == "estimate" else e.kind
        if not (kind == "progress" and out and out[-1] == "progress"):
            out.append(kind)
    return out


@pytest.fixture
def avatar_ws(tiny_avatar_ws, tmp_path):
    """A private copy of the session's workspace with ingest, init-mesh and an untrained phase-1 avatar."""
    dst = tmp_path / "ws"
    shutil.copytree(tiny_avatar_ws, dst)
    return dst


def test_emitter_sends_progress_and_estimate_events():
    from sage_core.stages.events import Emitter

    seen: list[StageEvent] = []
    em = Emitter("phase1", seen.append, "phase 1")
    em(1, 10, "phase 1", estimate_s=120.0, s_per_step=12.0)
    em(3, 10, "phase 1", loss=0.5, psnr=20.25)
    em.note("narrow clip", level="warning")
    assert [e.kind for e in seen] == ["estimate", "progress", "note"]
    assert seen[0].metrics == {"estimate_s": 120.0, "s_per_step": 12.0}
    p = seen[1]
    assert (p.stage, p.step, p.total, p.message, p.metrics) == ("phase1", 3, 10, "phase 1", {"loss": 0.5, "psnr": 20.25})
    assert seen[2].level == "warning" and seen[2].message == "narrow clip"
    Emitter("x", None)(1, 2)  # no callback: nothing to send, nothing raised


def test_init_mesh_stage_runs_then_skips(tiny_ws, tmp_path):
    from sage_core.stages import init_mesh_stage
    from sage_core.workspace import Workspace

    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    cfg = resolve_config("init-mesh", "tiny", None, QUICK_INIT)
    events: list[StageEvent] = []
    r = init_mesh_stage(ws, cfg, CPU, events.append)
    assert _kinds(events) == ["started", "running", "progress", "finished"]
    assert all(e.stage == "init-mesh" for e in events) and events[-1].result is r
    running = events[1]
    assert running.metrics["device"] == "cpu" and running.metrics["resumed"] is False and running.metrics["threads"] == 1
    steps = [e.step for e in events if e.kind == "progress" and e.total == 6]
    assert steps and steps == sorted(steps) and steps[-1] == 6
    estimates = [e for e in events if e.kind == "estimate"]
    assert len(estimates) <= 1 and all(e.metrics["estimate_s"] > 0 for e in estimates)
    assert not r.skipped and not r.resumed and r.device == "cpu" and r.threads == 1 and r.duration_s > 0
    assert r.workspace == ws.resolve() and r.manifest == Workspace(ws).manifest("init-mesh")
    assert r.metrics["n_faces"] > 0 and r.metrics["threads"] == 1
    from sage_core.fields.hashgrid import resolve_backend
    from sage_core.fields.sdf import resolve_fused_backend

    assert r.metrics["hashgrid_backend"] == resolve_backend("auto", "cpu")
    assert r.metrics["sdf_backend"] == resolve_fused_backend("auto", "cpu")
    assert {"canonical_mesh.ply", "sdf_mesh.ply", "sdf.pt"} <= set(r.outputs) and all(p.exists() for p in r.outputs.values())

    events.clear()
    again = init_mesh_stage(ws, cfg, CPU, events.append)
    assert [e.kind for e in events] == ["started", "skipped", "finished"]
    assert "already complete" in events[1].message and "--force" in events[1].message
    assert again.skipped and again.manifest["finished_at"] == r.manifest["finished_at"] and again.metrics == r.metrics


def test_eval_stage_result_and_skip(avatar_ws, tmp_path, monkeypatch):
    from sage_core.stages import EvalResult, eval_stage

    monkeypatch.setenv("SAGE_LPIPS_WEIGHTS", "")  # LPIPS unavailable wherever the weights are
    monkeypatch.setenv("HOME", str(tmp_path / "home"))

    cfg = resolve_config("eval", "tiny", None, {"split": "val", "samples": 1})
    events: list[StageEvent] = []
    r = eval_stage(avatar_ws, cfg, None, CPU, events.append)
    assert isinstance(r, EvalResult) and _kinds(events) == ["started", "running", "progress", "finished"]
    assert events[1].title == "eval phase1"
    last = [e for e in events if e.kind == "progress"][-1]
    assert last.step == last.total and last.message.startswith("val: ")
    assert r.avatar_stage == "phase1" and r.names == ["phase1/val"] and r.lpips_weights is None and not r.skipped
    doc = r.documents["phase1/val"]
    assert doc["counts"]["images"] >= 1 and doc["overall"]["lpips"] is None
    assert r.entries["phase1/val"]["overall"]["psnr"] == pytest.approx(doc["overall"]["psnr"])
    assert r.metrics["phase1/val psnr"] == pytest.approx(doc["overall"]["psnr"]) and r.render_backend in ("torch", "cpp")
    assert r.outputs["phase1/val"].is_file()

    events.clear()
    again = eval_stage(avatar_ws, cfg, None, CPU, events.append)
    assert [e.kind for e in events] == ["started", "skipped", "finished"] and again.skipped
    assert again.documents == r.documents and again.entries["phase1/val"]["key"] == r.entries["phase1/val"]["key"]


def test_export_and_reenact_stages(avatar_ws, tiny_capture):
    from sage_core.stages import ExportResult, export_stage, reenact_stage

    cfg = resolve_config("export", "tiny", None, {"mc_resolution": 16})
    events: list[StageEvent] = []
    r = export_stage(avatar_ws, cfg, viewer=["ply"], mesh=True, bundle=False, settings=CPU, on_event=events.append)
    assert isinstance(r, ExportResult) and _kinds(events) == ["started", "running", "progress", "finished"]
    assert sorted(r.items) == ["mesh:flame-canonical", "mesh:sdf", "ply:canonical"] and r.avatar_stage == "phase1"
    out = avatar_ws / "export"
    assert all((out / rel).exists() for e in r.items.values() for rel in e["files"])
    assert r.items["ply:canonical"]["rows"] > 0 and r.items["mesh:sdf"]["faces"] > 0
    events.clear()
    again = export_stage(avatar_ws, cfg, viewer=["ply"], mesh=True, bundle=False, settings=CPU, on_event=events.append)
    assert [e.kind for e in events] == ["started", "skipped", "finished"] and again.skipped and again.items == r.items

    events.clear()
    rec = reenact_stage(ws=avatar_ws, flame_seq=tiny_capture, max_frames=2, video=False, name="clip", device="cpu", on_event=events.append)
    assert _kinds(events) == ["started", "running", "progress", "finished"] and events[1].title == "reenact clip"
    assert rec.out_dir == avatar_ws / "reenact" / "clip" and rec.report.n_frames == 2
    assert len(list(rec.outputs["frames"].glob("*.png"))) == 2 and rec.outputs["record"].is_file() and "video" not in rec.outputs
    assert rec.record["motion"]["frames"] == 2 and rec.avatar_label.startswith("phase1")
    assert rec.device == "cpu" and rec.render_backend in ("torch", "cpp") and events[-1].result is rec


def test_stage_refuses_missing_inputs_before_running(tiny_ws, tmp_path):
    from sage_core.errors import ConfigError, StageError
    from sage_core.stages import eval_stage, export_stage

    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    events: list[StageEvent] = []
    with pytest.raises(StageError, match="neither phase2 nor phase1"):
        eval_stage(ws, resolve_config("eval", "tiny"), None, CPU, events.append)
    assert [e.kind for e in events] == ["started"] and not (ws / "eval").exists()
    with pytest.raises(ConfigError, match="not both"):
        export_stage(ws, resolve_config("export", "tiny"), frame=0, flame_seq=tmp_path, settings=CPU)


def test_run_pipeline_chains_every_stage(tiny_ws, tiny_capture, tmp_path):
    from sage_core.stages import PIPELINE_STAGES, PipelineResult, run_pipeline
    from sage_core.stages.demo import fast_flags

    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)  # ingested with the tiny preset: the chain finds ingest complete
    flags = fast_flags()
    flags["eval"]["samples"] = 0
    events: list[StageEvent] = []
    res = run_pipeline(tiny_capture, ws, tiny_capture.model_path, preset="tiny", flags=flags, settings=CPU, on_event=events.append)
    assert isinstance(res, PipelineResult) and res.avatar_stage == "phase2"
    assert [e.stage for e in events if e.kind == "started"] == list(PIPELINE_STAGES)
    assert [e.stage for e in events if e.kind == "finished"] == list(PIPELINE_STAGES)
    assert dict(res.stages)["ingest"] == "skipped (already complete)" and res.results["ingest"].skipped
    for stage in PIPELINE_STAGES[1:]:
        assert dict(res.stages)[stage].startswith("done in") and not res.results[stage].skipped, stage
    assert res.results["phase1"].metrics["iterations"] == 2 and res.results["phase2"].outputs["avatar.pt"].is_file()
    assert res.results["eval"].names == ["phase2/val", "phase2/test"] and sorted(res.results["export"].items) == ["bundle", "ply:canonical"]
    assert res.wall_time_s >= sum(r.duration_s for r in res.results.values()) - 1e-6
