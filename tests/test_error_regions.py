"""benchmarks/error_regions.py: the per-image error split adds up, two copies of one avatar agree, the
JSON and panels are written, the train split scores the training frames, and the LPIPS areas
partition the image."""

from __future__ import annotations

import json

import pytest
from helpers import LPIPS_SKIP_REASON, LPIPS_WEIGHTS, load_benchmark


def _module():
    return load_benchmark("error_regions")


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


def test_train_split_scores_the_fitted_views(cmd_avatar_ws, tmp_path, one_thread):
    from sage_core.data.dataset import IngestedData
    from sage_core.workspace import Workspace

    er = _module()
    out = tmp_path / "train.json"
    assert er.main([f"{cmd_avatar_ws}:phase1", "--split", "train", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["split"] == "train"
    (recs,) = doc["images"].values()
    data = IngestedData.open(Workspace(cmd_avatar_ws).stage_dir("ingest"))
    train = data.role("train")
    assert train and [(r["timestep"], r["camera"]) for r in recs] == [(f.timestep, f.camera_index) for f in train]


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


def test_lpips_areas_partition_the_image():
    import numpy as np

    er = _module()
    mask = np.zeros((40, 30), np.float32)
    mask[8:32, 6:24] = 1
    band, inside = er._band_and_inside(mask)
    group = np.full(mask.shape, -1)
    group[10:30, 8:22] = 4
    group[20:24, 12:18] = 0  # the mouth group
    areas = er._lpips_areas(band, inside, group)
    assert tuple(areas) == er.LPIPS_AREAS
    stack = np.stack([areas[a] for a in er.LPIPS_AREAS]).astype(int)
    assert (stack.sum(0) == 1).all()  # disjoint and covering
    assert areas["mouth"][18:26, 10:20].all() and not areas["mouth"][10:14].any()  # dilated by 2 px
    assert not (areas["mouth"] & ~inside).any()


@pytest.mark.skipif(LPIPS_WEIGHTS is None, reason=LPIPS_SKIP_REASON)
def test_lpips_split(cmd_avatar_ws, tmp_path, one_thread, capsys):
    er = _module()
    out = tmp_path / "regions.json"
    rc = er.main([f"{cmd_avatar_ws}:phase1:a", f"{cmd_avatar_ws}:phase1:b", "--out", str(out), "--lpips", str(LPIPS_WEIGHTS)])
    assert rc == 0
    doc = json.loads(out.read_text())
    a, b = doc["images"]["a"], doc["images"]["b"]
    assert a == b
    for rec in a:
        assert 0 < rec["lpips"] < 1
        parts = [rec[f"lpips_{x}"] for x in er.LPIPS_AREAS]
        assert all(0 <= v <= rec["lpips"] + 0.05 for v in parts)
        assert max(parts) > 0
    assert "lpips" in doc["mean"]["a"] and "| a |" in capsys.readouterr().out
