"""The command line: help, synth -> ingest -> info, skip / --force / stale, errors and exit codes."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from sage_cli.app import app

runner = CliRunner()


def test_help_is_fast_and_lists_commands():
    out = subprocess.run([sys.executable, "-c", "import sys, sage_cli.app; print('torch' in sys.modules)"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"  # heavy imports happen inside commands
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0
    for cmd in ("synth", "ingest", "init-mesh", "info"):
        assert cmd in res.output


def test_ingest_then_info(tiny_ws):
    res = runner.invoke(app, ["info", str(tiny_ws)])
    assert res.exit_code == 0, res.output
    assert "ingest" in res.output and "complete" in res.output
    m = json.loads((tiny_ws / "data" / "manifest.json").read_text())
    assert m["status"] == "complete" and m["metrics"]["regime"] == "mv-sf"
    assert m["metrics"]["train_images"] > 0 and m["metrics"]["val_images"] > 0
    assert (tiny_ws / "data" / "config.json").is_file()
    assert list((tiny_ws / "logs").glob("ingest-*.log"))


def _ingest(cap, ws, *extra):
    return runner.invoke(app, ["ingest", str(cap), str(ws), "--flame-model", str(cap.model_path), "--preset", "tiny", "--quiet", "--device", "cpu", *extra])


def test_skip_force_and_stale(tiny_capture, tmp_path):
    ws = tmp_path / "ws"
    assert _ingest(tiny_capture, ws).exit_code == 0
    first = json.loads((ws / "data" / "manifest.json").read_text())
    res = _ingest(tiny_capture, ws)
    assert res.exit_code == 0 and "skipping" in res.output
    res = _ingest(tiny_capture, ws, "--force")
    assert res.exit_code == 0 and "skipping" not in res.output
    again = json.loads((ws / "data" / "manifest.json").read_text())
    assert again["fingerprint"] == first["fingerprint"] and again["finished_at"] >= first["finished_at"]
    # a downstream stage recorded against this ingest becomes stale when ingest changes
    from sage_core.workspace import Workspace, begin_stage

    w = Workspace(ws)
    run = begin_stage(w, "init-mesh", {}, "x", requires=["ingest"])
    run.finish()
    assert w.status("init-mesh").status == "complete"
    assert _ingest(tiny_capture, ws, "--set", "height=93").exit_code == 0
    assert w.status("init-mesh").status == "stale"
    assert "stale" in runner.invoke(app, ["info", str(ws)]).output


def test_bad_inputs_exit_nonzero_and_write_nothing(tiny_capture, tmp_path):
    ws = tmp_path / "new_ws"
    res = runner.invoke(app, ["ingest", str(tmp_path / "nope"), str(ws), "--flame-model", str(tiny_capture.model_path)])
    assert res.exit_code == 2 and "capture folder not found" in res.output and not ws.exists()
    res = _ingest(tiny_capture, ws, "--regime", "bogus")
    assert res.exit_code == 3 and "regime = 'bogus'" in res.output and "one of mv-sf" in res.output and not ws.exists()
    res = _ingest(tiny_capture, ws, "--height", "50", "--downsample", "2")
    assert res.exit_code == 3 and not ws.exists()
    broken = tmp_path / "broken"
    shutil.copytree(tiny_capture, broken)
    (broken / "transforms_train.json").write_text("{ not json")
    res = runner.invoke(app, ["ingest", str(broken), str(ws), "--flame-model", str(tiny_capture.model_path), "--quiet"])
    assert res.exit_code == 2 and "transforms_train.json" in res.output and not ws.exists()
    res = _ingest(tiny_capture, ws, "--regime", "one-shot")  # 16 cameras, none chosen
    assert res.exit_code != 0 and not ws.exists()


def test_stage_refuses_missing_upstream(tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    res = runner.invoke(app, ["init-mesh", str(ws), "--preset", "tiny", "--quiet"])
    assert res.exit_code == 4 and "sage ingest" in res.output


def test_config_file_and_flags(tiny_capture, tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("ingest:\n  height: 93\n  regime: mv-mf\n")
    ws = tmp_path / "ws"
    res = _ingest(tiny_capture, ws, "--config", str(cfg), "--regime", "mv-sf")
    assert res.exit_code == 0, res.output
    saved = json.loads((ws / "data" / "config.json").read_text())
    assert saved["height"] == 93 and saved["regime"] == "mv-sf"  # flag over file
    summary = json.loads((ws / "data" / "summary.json").read_text())
    assert summary["resolution"][1] == 93


@pytest.mark.parametrize("device", ["cuda:7", "tpu"])
def test_bad_device(tiny_capture, tmp_path, device):
    import torch

    if device.startswith("cuda") and torch.cuda.device_count() > 7:
        pytest.skip("machine has that device")
    res = _ingest(tiny_capture, tmp_path / "ws", "--device", device)
    assert res.exit_code == 3 and "--device" in res.output


def test_config_command_prints_a_reusable_config(tmp_path):
    from sage_core.config import config_hash, load_config_file, resolve_config

    res = runner.invoke(app, ["config", "init-mesh", "--preset", "tiny", "--set", "pretrain.steps=77"])
    assert res.exit_code == 0, res.output
    f = tmp_path / "c.yaml"
    f.write_text(res.output)
    again = resolve_config("init-mesh", "default", load_config_file(f))
    assert again.pretrain.steps == 77
    assert config_hash(again) == config_hash(resolve_config("init-mesh", "tiny", None, {"pretrain.steps": 77}))
    res = runner.invoke(app, ["config", "nope"])
    assert res.exit_code == 3


def test_config_command_applies_regime_defaults():
    plain = runner.invoke(app, ["config", "phase1", "--preset", "tiny"])
    svhr = runner.invoke(app, ["config", "phase1", "--preset", "tiny", "--regime", "sv-hr"])
    assert plain.exit_code == 0 and svhr.exit_code == 0, svhr.output
    assert "exposure: 'off'" in plain.output and "exposure: gain" in svhr.output
    import yaml

    app_sh = [yaml.safe_load(r.output)["phase1"]["appearance"]["sh_degree"] for r in (plain, svhr)]
    assert app_sh == [2, 0]
    bad = runner.invoke(app, ["config", "phase1", "--regime", "bogus"])
    assert bad.exit_code == 3 and "bogus" in bad.output


def test_set_without_equals_is_a_configuration_error(tmp_path):
    res = runner.invoke(app, ["config", "phase1", "--set", "iterations"])
    assert res.exit_code == 3 and "key=value" in res.output, res.output
    res = runner.invoke(app, ["phase1", str(tmp_path), "--set", "=5"])
    assert res.exit_code == 3, res.output


def test_out_of_range_flag_is_refused_before_anything_is_written(tiny_ws, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    before = sorted(p.relative_to(ws) for p in ws.rglob("*"))
    res = runner.invoke(app, ["phase1", str(ws), "--iterations", "-5", "--preset", "tiny", "--quiet", "--device", "cpu"])
    assert res.exit_code == 3, res.output
    assert "iterations = -5" in res.output and ">= 1" in res.output
    assert sorted(p.relative_to(ws) for p in ws.rglob("*")) == before  # no log, work folder or manifest
    res = runner.invoke(app, ["phase2", str(ws), "--set", "teacher=mesh", "--quiet"])
    assert res.exit_code == 3 and "one of rest, neus" in res.output, res.output
    res = runner.invoke(app, ["config", "phase1", "--explain"], env={"COLUMNS": "250"})
    assert res.exit_code == 0 and "one of off, gain, rgb" in res.output
    # the nested names, each with the flat name it had before (still accepted)
    assert "loss.light_albedo" in res.output and "(flat name w_light_albedo)" in res.output
