"""benchmarks/back_views.py: the counts by marker share, the face showing from the front, reproducible
counts, the JSON and panels, and bad arguments refused."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
from helpers import load_benchmark


def test_face_shows_from_the_front_and_the_outputs_are_written(cmd_avatar_ws, tmp_path, one_thread, capsys):
    bv = load_benchmark("back_views")
    front, back = tmp_path / "front.json", tmp_path / "back.json"
    assert bv.main([f"{cmd_avatar_ws}:phase1:a", "--from", "0", "--to", "0", "--out", str(front)]) == 0
    assert bv.main([f"{cmd_avatar_ws}:phase1:a", f"{cmd_avatar_ws}:phase1:b", "--from", "170", "--to", "190",
                    "--out", str(back), "--panels", str(tmp_path / "p.png"), "--angles", "0,180", "--scale", "1"]) == 0  # fmt: skip
    f = json.loads(front.read_text())["avatars"]["a"]
    doc = json.loads(back.read_text())
    a, b = doc["avatars"]["a"], doc["avatars"]["b"]
    assert doc["angles"] == [170.0, 180.0, 190.0] and len(a["per_angle"]) == 3
    assert a["per_angle"] == b["per_angle"]  # the same avatar twice
    for rec in a["per_angle"] + f["per_angle"]:
        assert 0 <= rec["face"] <= rec["foreground"] and 0 <= rec["mouth"] <= rec["foreground"] and rec["foreground"] > 100
    # the untrained test avatar is not closed from behind; from the front its face fills the head
    assert f["face_percent"] > 30.0 and f["mouth_percent"] > 0.0
    from sage_core.data.dataset import IngestedData
    from sage_core.stages.avatars import reference_camera
    from sage_core.workspace import Workspace

    cam = reference_camera(IngestedData.open(Workspace(cmd_avatar_ws).stage_dir("ingest")), None)
    img = iio.imread(tmp_path / "p.png")
    # per avatar a row of renders and a row of region colours, one column per panel angle
    assert img.shape[:2] == (4 * cam.height, 2 * cam.width)
    assert not (img[: cam.height] == img[cam.height : 2 * cam.height]).all()
    assert "| a | 3 |" in capsys.readouterr().out
    assert bv.main([f"{cmd_avatar_ws}:phase1", "--threshold", "1.5"]) == 2
    assert bv.main([str(tmp_path / "nowhere")]) == 2


def test_counts_follow_the_marker_shares_and_the_threshold():
    import numpy as np

    bv = load_benchmark("back_views")
    share = np.zeros((2, 3, 3))
    share[..., 2] = [[1.0, 1.0, 0.4], [1.0, 0.9, 0.0]]  # accumulated opacity: four pixels in the foreground
    share[..., 0] = [[0.1, 0.3, 0.4], [0.0, 0.6, 0.0]]  # the face's share
    share[..., 1] = [[0.5, 0.0, 0.3], [0.2, 0.0, 0.0]]  # the mouth's
    assert bv.count(share, 0.25) == {"foreground": 4, "face": 2, "mouth": 1}
    assert bv.count(share, 0.55) == {"foreground": 4, "face": 1, "mouth": 0}
    assert bv.parse_item("a/ws") == (Path("a/ws"), "phase2", "ws")
    assert bv.parse_item("a/ws:phase1:x")[1:] == ("phase1", "x")
