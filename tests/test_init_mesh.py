"""The init-mesh stage on the tiny synthetic workspace: outputs, metrics, exact resume."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
import trimesh
from typer.testing import CliRunner

from sage_cli.app import app
from sage_core.config import resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.fields.sdf_file import load_sdf
from sage_core.train.init_mesh import run_init_mesh


def _cfg(steps):
    return resolve_config(
        "init-mesh", "tiny", None, {"pretrain.steps": steps, "pretrain.bank_size": 6000, "pretrain.batch_size": 1536, "mc_resolution": 48, "checkpoint_every": 10, "pretrain.eval_samples": 3000}
    )


def test_init_mesh_cli_writes_outputs_and_metrics(tiny_ws, tmp_path, one_thread):
    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    res = CliRunner().invoke(
        app, ["init-mesh", str(ws), "--preset", "tiny", "--steps", "60", "--mc-resolution", "48", "--set", "pretrain.bank_size=6000", "--quiet", "--device", "cpu"]
    )
    assert res.exit_code == 0, res.output
    out = ws / "init"
    for name in ("flame_model.npz", "regions.json", "canonical_mesh.ply", "head_mesh.ply", "mouth_interior.ply", "sdf.pt", "sdf_mesh.ply", "metrics.json", "manifest.json", "config.json"):
        assert (out / name).is_file(), name
    m = json.loads((out / "manifest.json").read_text())
    assert m["inputs"]["stages"]["ingest"] == json.loads((ws / "data" / "manifest.json").read_text())["fingerprint"]
    met = m["metrics"]
    for key in ("mean_abs_sdf_vertices_m", "normal_cos", "chamfer_m", "chamfer_rel"):
        assert np.isfinite(met[key]), key
    assert met["n_mouth_faces"] > 0
    # even 60 steps pull the SDF onto the head: the zero set lies within a few percent of the diagonal
    assert met["chamfer_rel"] < 0.05
    assert met["normal_cos"] > 0.5
    # the canonical mesh has the model's vertex count; the SDF loads back and is ~0 on the head surface
    mesh = trimesh.load(out / "canonical_mesh.ply", process=False)
    assert len(mesh.vertices) == met["n_vertices"]
    net = load_sdf(out / "sdf.pt")
    head = trimesh.load(out / "head_mesh.ply", process=False)
    v = torch.as_tensor(np.asarray(head.vertices), dtype=torch.float32)
    with torch.no_grad():
        mean_abs = float(net.sdf(v).abs().mean())
    assert mean_abs == pytest.approx(met["mean_abs_sdf_vertices_m"], rel=1e-3)
    # same config and inputs: skipped
    res = CliRunner().invoke(app, ["init-mesh", str(ws), "--preset", "tiny", "--steps", "60", "--mc-resolution", "48", "--set", "pretrain.bank_size=6000", "--quiet"])
    assert res.exit_code == 0 and "skipping" in res.output


class _Stop(Exception):
    pass


def test_interrupted_pretraining_resumes_exactly(tiny_ws, tmp_path, one_thread):
    data = IngestedData.open(tiny_ws / "data")
    cfg = _cfg(30)
    ref_dir = tmp_path / "ref"
    ref_dir.mkdir()
    ref = run_init_mesh(data, ref_dir, cfg, checkpoint_dir=tmp_path / "ck_ref")

    def stop_at_25(step, total, *a, **k):
        if step == 25:
            raise _Stop

    out = tmp_path / "out"
    out.mkdir()
    ck = tmp_path / "ck"
    with pytest.raises(_Stop):
        run_init_mesh(data, out, cfg, checkpoint_dir=ck, progress=stop_at_25)
    assert sorted(p.name for p in ck.glob("ckpt_*.pt"))[-1] == "ckpt_00000020.pt"
    resumed = run_init_mesh(data, out, cfg, checkpoint_dir=ck)
    assert resumed["final_loss"] == pytest.approx(ref["final_loss"], rel=1e-6, abs=1e-9)
    from sage_core.fields.sdf_file import read_sdf_file

    a = read_sdf_file(ref_dir / "sdf.pt")[1]
    b = read_sdf_file(out / "sdf.pt")[1]
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-7), k
