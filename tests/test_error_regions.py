"""benchmarks/error_regions.py: the per-image error split adds up, two copies of one avatar agree, and
the JSON and panels are written."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("error_regions", REPO / "benchmarks" / "error_regions.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_error_split_adds_up(cmd_avatar_ws, tmp_path, one_thread, capsys):
    er = _module()
    out = tmp_path / "regions.json"
    rc = er.main([f"{cmd_avatar_ws}:phase1:a", f"{cmd_avatar_ws}:phase1:b", "--out", str(out), "--panels", str(tmp_path / "panels"),
                  "--cams", "8", "--scale", "1"])  # fmt: skip
    assert rc == 0
    doc = json.loads(out.read_text())
    a, b = doc["images"]["a"], doc["images"]["b"]
    assert a and a == b
    for rec in a:
        parts = sum(rec[g] for g in (*er.GROUPS, "skin"))
        assert parts == pytest.approx(rec["inside"], rel=1e-6, abs=1e-6)
        assert rec["band"] + rec["inside"] <= rec["total"] * (1 + 1e-6) + 1e-6
        assert rec["total"] > 0 and rec["silhouette"] >= 0
    assert set(doc["mean"]["a"]) == set(er.COLUMNS)
    panels = sorted((tmp_path / "panels").glob("test_*_c08.png"))
    assert len(panels) == len({r["timestep"] for r in a})
    assert "| a |" in capsys.readouterr().out
    assert er.main(["no-stage-given"]) == 2


def test_ceiling_item_renders_the_capture_truth(cmd_avatar_ws, tiny_capture, tmp_path, one_thread):
    er = _module()
    out = tmp_path / "regions.json"
    assert er.main([f"ceiling:{tiny_capture}"]) == 2  # the first item must be an avatar
    assert er.main([f"{cmd_avatar_ws}:phase1:a", f"ceiling:{tiny_capture}", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    a, c = doc["images"]["a"], doc["images"]["ceiling"]
    assert [(r["timestep"], r["camera"]) for r in a] == [(r["timestep"], r["camera"]) for r in c]
    # an exact capture: its ground truth on the written model is the ground truth
    assert sum(r["total"] for r in c) < 1e-3 * sum(r["total"] for r in a)
