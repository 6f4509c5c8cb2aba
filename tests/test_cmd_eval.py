"""`sage eval`: metrics.json with and without LPIPS, accumulated results, skip, stale refusal.

The avatar workspace used here (and by the other command tests) is conftest's ``cmd_avatar_ws``:
the tiny ingested capture with a reduced init-mesh and an untrained phase-1 avatar of a few hundred
surfels, recorded as complete stages, built once per test session.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from helpers import LPIPS_SKIP_REASON, LPIPS_WEIGHTS, invoke


@pytest.fixture(scope="module")
def base_ws(cmd_avatar_ws):
    return cmd_avatar_ws


@pytest.fixture
def ws(base_ws, tmp_path):
    dst = tmp_path / "ws"
    shutil.copytree(base_ws, dst)
    return dst


@pytest.mark.skipif(LPIPS_WEIGHTS is None, reason=LPIPS_SKIP_REASON)
def test_eval_writes_metrics_with_and_without_lpips(ws):
    res = invoke(["eval", ws, "--split", "val", "--lpips-weights", LPIPS_WEIGHTS, "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    path = ws / "eval" / "phase1" / "val" / "metrics.json"
    doc = json.loads(path.read_text())
    n_val = doc["counts"]["images"]
    assert n_val >= 1 and doc["lpips_available"] is True
    lp = doc["overall"]["lpips"]
    assert isinstance(lp, float) and 0.0 < lp < 1.5
    assert all(isinstance(r["lpips"], float) for r in doc["images"])
    assert doc["overall"]["psnr"] > 5.0 and 0.0 < doc["overall"]["ssim"] <= 1.0
    assert (ws / "eval" / "manifest.json").is_file()
    assert "camera 8" in res.output and "all" in res.output  # the per-camera table
    # without weights (no env var, no cache): LPIPS null and reported unavailable
    res = invoke(["eval", ws, "--split", "val", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    doc2 = json.loads(path.read_text())
    assert doc2["lpips_available"] is False and doc2["overall"]["lpips"] is None
    assert all(r["lpips"] is None for r in doc2["images"])
    assert "unavailable" in res.output
    # the renders did not change: the same PSNR
    assert doc2["overall"]["psnr"] == pytest.approx(doc["overall"]["psnr"], rel=1e-6)


def test_eval_results_accumulate_and_skip(ws):
    res = invoke(["eval", ws, "--split", "test", "--samples", "3", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    test_doc = json.loads((ws / "eval" / "phase1" / "test" / "metrics.json").read_text())
    from sage_core.data.dataset import IngestedData

    data = IngestedData.open(ws / "data")
    assert test_doc["counts"]["images"] == len(data.test)
    assert test_doc["counts"]["cameras"] == len({f.camera_index for f in data.test})
    assert len(list((ws / "eval" / "phase1" / "test" / "images").glob("*.png"))) == 3
    assert test_doc["frontal"] is not None and test_doc["frontal"]["count"] == sum(f.camera_index == 8 for f in data.test)
    # a second split joins the first one in WS/eval
    res = invoke(["eval", ws, "--split", "val", "--samples", "3", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    index = json.loads((ws / "eval" / "results.json").read_text())
    assert set(index) == {"phase1/test", "phase1/val"}
    assert (ws / "eval" / "phase1" / "test" / "metrics.json").is_file()
    manifest = json.loads((ws / "eval" / "manifest.json").read_text())
    assert "phase1/test psnr" in manifest["metrics"] and "phase1/val psnr" in manifest["metrics"]
    assert json.loads((ws / "eval" / "phase1" / "test" / "metrics.json").read_text()) == test_doc
    # same (stage, split), same inputs: skipped
    mtime = (ws / "eval" / "manifest.json").stat().st_mtime_ns
    res = invoke(["eval", ws, "--split", "all", "--samples", "3", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert "skipping" in res.output
    assert (ws / "eval" / "manifest.json").stat().st_mtime_ns == mtime
    from sage_core.workspace import Workspace

    assert Workspace(ws).status("eval").status == "complete"


def test_eval_refuses_a_stale_avatar(ws):
    m_path = ws / "phase1" / "manifest.json"
    m = json.loads(m_path.read_text())
    m["inputs"]["stages"]["init-mesh"] = "0" * 16  # as if init-mesh had been re-run since
    m_path.write_text(json.dumps(m))
    res = invoke(["eval", ws, "--split", "val", "--device", "cpu", "--quiet"])
    assert res.exit_code == 4, res.output
    assert "stale" in res.output and "sage phase1" in res.output
    assert not (ws / "eval").exists()


def test_eval_rejects_bad_options(ws, tmp_path):
    res = invoke(["eval", ws, "--split", "train", "--quiet"])
    assert res.exit_code == 3 and "split = 'train'" in res.output and "one of test, val, all, novel" in res.output
    res = invoke(["eval", ws, "--lpips-weights", tmp_path / "missing.pth", "--quiet"])
    assert res.exit_code == 2 and "missing.pth" in res.output
    res = invoke(["eval", ws, "--stage", "phase2", "--quiet"])
    assert res.exit_code == 4 and "phase2" in res.output


def test_eval_render_matches_the_avatar_render(ws):
    """The eval renderer is the avatar's own render (same pose, camera, background, planes)."""
    from sage_core.data.dataset import IngestedData
    from sage_core.render import RenderCamera
    from sage_core.stages.avatars import AvatarRenderer, load_stage_avatar
    from sage_core.workspace import Workspace

    w = Workspace(ws)
    data = IngestedData.open(ws / "data")
    loaded = load_stage_avatar(w, "phase1", data)
    assert loaded.render.background == 1.0 and loaded.render.near == pytest.approx(0.2) and loaded.render.far == pytest.approx(3.0)
    fr = data.test[0]
    img = AvatarRenderer(loaded.avatar, loaded.render).render(fr.camera, loaded.avatar.frame_inputs(fr.timestep))
    with torch.no_grad():
        ref, _ = loaded.avatar.render(RenderCamera.from_camera(fr.camera), loaded.avatar.frame_inputs(fr.timestep), 1.0,
                                      near=0.2, far=3.0, return_statistics=False)  # fmt: skip
    assert torch.allclose(img, ref.color, atol=1e-6)
    assert float((img < 0.99).float().mean()) > 0.02  # the head is visible
    assert np.isfinite(img.numpy()).all()


def test_lpips_env_var_is_honoured(ws, tmp_path):
    if LPIPS_WEIGHTS is None:
        pytest.skip(LPIPS_SKIP_REASON)
    res = invoke(["eval", ws, "--split", "val", "--device", "cpu", "--quiet"], SAGE_LPIPS_WEIGHTS=str(LPIPS_WEIGHTS))
    assert res.exit_code == 0, res.output
    doc = json.loads((ws / "eval" / "phase1" / "val" / "metrics.json").read_text())
    assert doc["lpips_available"] is True and isinstance(doc["overall"]["lpips"], float)
