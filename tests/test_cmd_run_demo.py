"""`sage run` and `sage demo`: the stage chain, per-stage --set, skipping, and a `demo --fast` smoke test."""

from __future__ import annotations

import json

import pytest

from helpers import invoke


def test_split_sets_addresses_stages():
    from sage_core.stages import split_sets
    from sage_core.errors import ConfigError

    out = split_sets(["phase1.iterations=5", "init-mesh.pretrain.steps=3", "init_mesh.mc_resolution=32", "export.up_axis=z"])
    assert out["phase1"] == ["iterations=5"]
    assert out["init-mesh"] == ["pretrain.steps=3", "mc_resolution=32"]
    assert out["export"] == ["up_axis=z"] and out["ingest"] == [] and out["phase2"] == []
    for bad in (["iterations=5"], ["bogus.x=1"], ["phase1.iterations"]):
        with pytest.raises(ConfigError):
            split_sets(bad)


def test_interpolated_demo_motion(tiny_capture, tmp_path):
    import numpy as np

    from sage_core.export.motion import interpolate_keys, write_key_motion
    from sage_core.data.capture import read_capture
    from sage_core.export.motion import load_motion

    keys = {"a": np.array([[0.0, 0.0], [1.0, 2.0], [3.0, 2.0]])}
    out = interpolate_keys(keys, 4)["a"]
    assert out.shape == (9, 2)
    assert np.allclose(out[2], [0.5, 1.0]) and np.allclose(out[4], [1.0, 2.0]) and np.allclose(out[-1], [3.0, 2.0])
    path, ts = write_key_motion(tiny_capture, tmp_path / "m.npz", 3)
    cap = read_capture(tiny_capture, check_images=False)
    assert ts == sorted({f.timestep for f in cap.split("test")})
    motion = load_motion(path)
    assert motion.n_frames == 3 * (len(ts) - 1) + 1
    row = cap.params.row_of(ts[1])
    assert np.allclose(motion.params.expr[3], cap.params.expr[row], atol=1e-6)  # key frames are the test frames


@pytest.mark.slow
def test_demo_fast_smoke_and_run_skips(tmp_path):
    from sage_core.stages.demo import FAST_SETS

    ws = tmp_path / "demo"
    res = invoke(["demo", ws, "--fast", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert "SMOKE TEST" in res.output
    from sage_core.workspace import Workspace

    w = Workspace(ws)
    for stage in ("ingest", "init-mesh", "phase1", "phase2", "eval", "export"):
        assert w.status(stage).status == "complete", stage
    av_stage = "phase2"  # the chain runs phase 2 unless --skip-phase2
    assert (ws / "phase2" / "avatar.pt").is_file() and (ws / "eval" / "phase2" / "val" / "metrics.json").is_file()
    for split in ("val", "test"):
        doc = json.loads((ws / "eval" / av_stage / split / "metrics.json").read_text())
        assert doc["counts"]["images"] > 0 and doc["overall"]["lpips"] is None  # no weights by default
        own = ws / av_stage / f"eval_{split}" / "metrics.json"
        if own.is_file():  # eval renders the phase-2 avatar as phase 2 does (with correction)
            ref = json.loads(own.read_text())["overall"]
            assert doc["overall"]["psnr"] == pytest.approx(ref["psnr"], abs=0.01)
            assert doc["overall"]["ssim"] == pytest.approx(ref["ssim"], abs=1e-4)
    assert (ws / "export" / "ply" / "canonical.ply").is_file() and (ws / "export" / "bundle" / "bundle.json").is_file()
    rec = json.loads((ws / "reenact" / "demo" / "reenact.json").read_text())
    assert rec["report"]["n_frames"] == 3 and (ws / "reenact" / "demo" / "video.mp4").stat().st_size > 0
    assert len(list((ws / "reenact" / "demo" / "frames").glob("*.png"))) == 3
    assert "reenact video" in res.output and "val" in res.output
    # `sage run` with the same settings finds every stage finished
    sets = [f"{stage}.{kv}" for stage, kvs in FAST_SETS.items() for kv in kvs]
    args = ["run", ws / "capture", ws, "--flame-model", ws / "capture" / "model" / "synth_flame.npz", "--preset", "tiny",
            "--device", "cpu", "--quiet"]  # fmt: skip
    for s in sets:
        args += ["--set", s]
    res = invoke(args)
    assert res.exit_code == 0, res.output
    assert res.output.count("skipped (already complete)") >= 6
