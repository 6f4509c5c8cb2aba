"""`reenact.json` holds paths relative to its own folder, so `sage info` on a copied workspace lists the
copy's reenactments; `--size` sets the output size."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from helpers import invoke


def test_reenact_record_paths_are_relative_and_info_lists_the_copy(cmd_avatar_ws, tiny_capture, tmp_path, monkeypatch):
    ws = tmp_path / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    monkeypatch.chdir(tmp_path)  # relative --out and workspace paths, resolved against the launch folder
    res = invoke(["reenact", "ws", "--flame-seq", tiny_capture, "--max-frames", "2", "--no-video", "--size", "64",
                  "--out", "ws/reenact/rel", "--device", "cpu", "--quiet", "--threads", "1"])  # fmt: skip
    assert res.exit_code == 0, res.output
    doc = json.loads((ws / "reenact" / "rel" / "reenact.json").read_text())
    rep = doc["report"]
    assert rep["frames_dir"] == "frames" and rep["paths"] == ["frames"] and rep["video_path"] is None
    assert doc["avatar_path"] == "../../phase1/avatar.pt" and doc["threads"] == 1
    assert Path(doc["motion"]["source"]) == tiny_capture.resolve()  # outside the workspace: absolute
    # --size 64: the height, the width following the camera's aspect ratio
    assert rep["height"] == 64 and 30 < rep["width"] < 64
    from sage_core.data.imageio import read_image

    assert read_image(ws / "reenact" / "rel" / "frames" / "00000.png").shape[:2] == (64, rep["width"])
    copy = tmp_path / "copy"
    shutil.move(ws, copy)
    from typer.testing import CliRunner

    from sage_cli.app import app

    res = CliRunner().invoke(app, ["info", str(copy)], env={"COLUMNS": "300"})
    assert res.exit_code == 0, res.output
    assert "reenactments" in res.output and "rel" in res.output
    text = "".join(res.output.split())  # the table may fold long paths
    assert "copy/reenact/rel/frames" in text and "/ws/reenact" not in text
    assert "complete" in res.output and str(ws) not in text


def test_size_option_is_checked():
    res = invoke(["reenact", "x", "--flame-seq", "y", "--size", "12xq", "--quiet"])
    assert res.exit_code == 3 and "--size" in res.output
