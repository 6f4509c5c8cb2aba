"""`benchmarks/profile_train.py`: a profiled phase-1 run on CPU, its JSON and trace, and the helpers
that shape the CUDA report (op ordering, synchronisation call sites, the Markdown table)."""

from __future__ import annotations

import json
import shutil
import statistics
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest


REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import profile_train  # noqa: E402

SMALL = ["n_surfels=600", "app_hidden=16", "shape_hidden=16", "rays_per_step=128", "neus_samples=8", "neus_importance=8",
         "smooth_points=128"]  # fmt: skip


@pytest.fixture(scope="module")
def base_ws(cmd_avatar_ws):
    return cmd_avatar_ws


def _listing(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


def test_phase1_profile_on_cpu(base_ws, tmp_path, capsys):
    before = _listing(base_ws)
    out = tmp_path / "prof"
    args = [str(base_ws), "--stage", "phase1", "--device", "cpu", "--warmup", "1", "--steps", "2", "--out", str(out), "--preset", "tiny"]
    for s in SMALL:
        args += ["--set", s]
    assert profile_train.main(args) == 0
    doc = json.loads((out / "profile_phase1.json").read_text())
    assert doc["stage"] == "phase1" and doc["device"] == "cpu" and doc["gpu"] is None
    assert doc["warmup"] == 1 and doc["steps"] == 2 and doc["n_surfels"] == 600
    assert len(doc["step_ms"]) == 2 and all(t > 0 for t in doc["step_ms"])
    assert doc["median_step_ms"] == pytest.approx(statistics.median(doc["step_ms"]))
    ops = doc["top_ops"]
    assert 0 < len(ops) <= profile_train.TOP_OPS and doc["sort_by"] == "self_cpu_ms"
    assert [o["self_cpu_ms"] for o in ops] == sorted((o["self_cpu_ms"] for o in ops), reverse=True)
    assert all(o["count"] >= 1 and 0 <= o["self_cpu_ms"] <= o["cpu_total_ms"] + 1e-6 for o in ops)
    assert "self_device_ms" not in ops[0]
    # two steps of a surfel trainer spend their time in aten ops
    assert any(o["name"].startswith("aten::") for o in ops)
    assert doc["peak_memory_mib"] > 0 and "resident" in doc["peak_memory_kind"] and doc["syncs"] is None
    trace = json.loads((out / "trace_phase1.json").read_text())
    assert len(trace["traceEvents"]) > 0
    assert sorted(p.name for p in out.iterdir()) == ["profile_phase1.json", "trace_phase1.json"]
    printed = capsys.readouterr().out
    assert "| op | count | self ms |" in printed and ops[0]["name"] in printed
    assert _listing(base_ws) == before  # the workspace is only read


def test_missing_phase1_avatar_is_an_error(base_ws, tmp_path, capsys):
    ws = tmp_path / "ws"
    shutil.copytree(base_ws, ws)
    (ws / "phase1" / "avatar.pt").unlink()
    rc = profile_train.main([str(ws), "--stage", "phase2", "--device", "cpu", "--steps", "1", "--out", str(tmp_path / "p")])
    assert rc == 2 and "avatar.pt" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_bad_step_counts_are_refused(base_ws, tmp_path):
    with pytest.raises(SystemExit):
        profile_train.main([str(base_ws), "--steps", "0", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        profile_train.main([str(base_ws), "--warmup", "-1", "--out", str(tmp_path)])


def _event(key: str, count: int, self_cpu: float, cpu: float, **device: float) -> SimpleNamespace:
    return SimpleNamespace(key=key, count=count, self_cpu_time_total=self_cpu, cpu_time_total=cpu, **device)


def test_op_rows_order_by_device_time_on_cuda():
    events = [
        _event("a", 3, 5000.0, 9000.0, self_device_time_total=100.0, device_time_total=200.0),
        _event("b", 1, 10.0, 20.0, self_device_time_total=7000.0, device_time_total=7000.0),
        # an older torch names the device fields after CUDA
        _event("c", 2, 20.0, 30.0, self_cuda_time_total=3000.0, cuda_time_total=4000.0),
    ]
    rows = profile_train.op_rows(events, on_cuda=True)
    assert [r["name"] for r in rows] == ["b", "c", "a"]
    assert rows[1] == {"name": "c", "count": 2, "self_cpu_ms": 0.02, "cpu_total_ms": 0.03, "self_device_ms": 3.0, "device_total_ms": 4.0}
    cpu_rows = profile_train.op_rows(events, on_cuda=False, limit=2)
    assert [r["name"] for r in cpu_rows] == ["a", "c"] and "self_device_ms" not in cpu_rows[0]


def _warning(message: str, filename: str, lineno: int) -> warnings.WarningMessage:
    return warnings.WarningMessage(UserWarning(message), UserWarning, filename, lineno)


def test_sync_sites_count_and_rank_call_sites():
    msg = "called a synchronizing CUDA operation (Triggered internally at ...)"
    records = [
        _warning(msg, "/x/phase1.py", 10),
        _warning(msg, "/x/phase1.py", 10),
        _warning(msg, "/x/losses.py", 3),
        _warning("some other warning", "/x/phase1.py", 10),
        _warning(msg, profile_train.__file__, 99),  # the profiler's own synchronisations
    ]
    n, sites = profile_train.sync_sites(records, profile_train.__file__)
    assert n == 3
    assert sites == [{"site": "/x/phase1.py:10", "count": 2}, {"site": "/x/losses.py:3", "count": 1}]
    assert profile_train.sync_sites(records, profile_train.__file__, limit=1)[1] == [{"site": "/x/phase1.py:10", "count": 2}]


def test_markdown_table_of_a_cuda_profile():
    doc = {
        "stage": "phase2", "device": "cuda", "steps": 4, "median_step_ms": 12.5, "peak_memory_mib": 1024.0,
        "peak_memory_kind": "cuda max_memory_allocated",
        "top_ops": [{"name": "k|1", "count": 8, "self_cpu_ms": 1.0, "cpu_total_ms": 2.0, "self_device_ms": 40.0, "device_total_ms": 41.0}],
        "syncs": {"count": 6, "sites": [{"site": "/x/phase2.py:7", "count": 6}]},
    }  # fmt: skip
    text = profile_train.markdown_table(doc)
    assert "median step 12.50 ms over 4 steps" in text and "1024.0 MiB" in text
    assert "synchronisations in the measured steps: 6" in text
    assert "| k\\|1 | 8 | 40.000 | 41.000 | 10.000 | 1.000 |" in text
    assert "| /x/phase2.py:7 | 6 |" in text
