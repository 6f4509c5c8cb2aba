"""`reenact.json` holds absolute paths (like the manifests) and `sage info` lists the reenactments."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from helpers import invoke


def test_reenact_record_paths_are_absolute_and_info_lists_it(cmd_avatar_ws, tiny_capture, tmp_path, monkeypatch):
    ws = tmp_path / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    monkeypatch.chdir(tmp_path)  # relative --out and workspace paths, resolved against the launch folder
    res = invoke(["reenact", "ws", "--flame-seq", tiny_capture, "--max-frames", "2", "--no-video",
                  "--out", "ws/reenact/rel", "--device", "cpu", "--quiet"])  # fmt: skip
    assert res.exit_code == 0, res.output
    doc = json.loads((ws / "reenact" / "rel" / "reenact.json").read_text())
    rep = doc["report"]
    assert Path(rep["frames_dir"]).is_absolute() and Path(rep["frames_dir"]) == (ws / "reenact" / "rel" / "frames").resolve()
    assert all(Path(p).is_absolute() for p in rep["paths"]) and Path(doc["motion"]["source"]).is_absolute()
    from typer.testing import CliRunner

    from sage_cli.app import app

    res = CliRunner().invoke(app, ["info", str(ws)], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "reenactments" in res.output and "rel" in res.output
