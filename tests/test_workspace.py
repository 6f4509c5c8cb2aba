"""Workspace contract: atomic writes, manifests, skip / --force / stale, lock, checkpoints."""

from __future__ import annotations

import multiprocessing as mp
from dataclasses import dataclass

import pytest
import torch

from sage_core.errors import StageError, WorkspaceError
from sage_core.workspace import (
    CHECKPOINT_FORMAT,
    Workspace,
    atomic_write_json,
    begin_stage,
    latest_checkpoint,
    load_checkpoint,
    read_json,
    rng_state,
    save_checkpoint,
    set_rng_state,
)


def _run(ws, stage, cfg_hash="c1", requires=(), files=None, force=False, seed=0, payload="x"):
    run = begin_stage(ws, stage, {"k": cfg_hash}, cfg_hash, requires=list(requires), external_inputs=files, seed=seed, force=force)
    if run is None:
        return None
    (run.work_dir / "out.txt").write_text(payload)
    run.metrics["value"] = 1.5
    return run.finish()


def test_atomic_json_and_no_temp_left(tmp_path):
    p = tmp_path / "a" / "b.json"
    atomic_write_json(p, {"x": 1})
    assert read_json(p) == {"x": 1}
    assert [f.name for f in p.parent.iterdir()] == ["b.json"]


def test_manifest_written_and_skip_force(tmp_path):
    ws = Workspace(tmp_path / "ws")
    m = _run(ws, "ingest", files={"model": "abc"})
    assert m["status"] == "complete" and m["metrics"]["value"] == 1.5
    assert (ws.stage_dir("ingest") / "out.txt").read_text() == "x"
    assert not ws.work_dir("ingest").exists()
    for key in ("config_hash", "fingerprint", "inputs", "version", "seed", "device", "started_at", "finished_at"):
        assert key in m
    assert _run(ws, "ingest", files={"model": "abc"}) is None  # same config and inputs: skipped
    m2 = _run(ws, "ingest", files={"model": "abc"}, force=True, payload="y")
    assert m2 is not None and (ws.stage_dir("ingest") / "out.txt").read_text() == "y"
    assert _run(ws, "ingest", files={"model": "abc"}, seed=3) is not None  # another seed reruns


def test_stale_detection_and_refusal(tmp_path):
    ws = Workspace(tmp_path / "ws")
    _run(ws, "ingest", files={"model": "abc"})
    _run(ws, "init-mesh", requires=["ingest"])
    assert ws.status("init-mesh").status == "complete"
    _run(ws, "ingest", files={"model": "CHANGED"})
    st = ws.status("init-mesh")
    assert st.status == "stale" and "ingest" in st.reason
    with pytest.raises(StageError, match="stale.*sage init-mesh"):
        ws.require("init-mesh", "phase1")
    # re-running init-mesh on the new ingest makes it fresh again (inputs changed, so it runs)
    assert _run(ws, "init-mesh", requires=["ingest"]) is not None
    assert ws.status("init-mesh").status == "complete"


def test_missing_upstream_is_refused(tmp_path):
    ws = Workspace(tmp_path / "ws")
    with pytest.raises(StageError, match="has not completed: run `sage ingest"):
        _run(ws, "init-mesh", requires=["ingest"])


def test_failed_stage_keeps_previous_output_and_resumes(tmp_path):
    ws = Workspace(tmp_path / "ws")
    _run(ws, "ingest", payload="good")
    run = begin_stage(ws, "ingest", {"k": "c2"}, "c2", seed=0)
    (run.work_dir / "partial.txt").write_text("half")
    run.fail("boom")
    assert (ws.stage_dir("ingest") / "out.txt").read_text() == "good"
    assert ws.manifest("ingest")["config_hash"] == "c1"
    # the same config resumes in the kept work folder
    again = begin_stage(ws, "ingest", {"k": "c2"}, "c2", seed=0)
    assert again.resumed and (again.work_dir / "partial.txt").exists()
    # another config starts clean
    other = begin_stage(ws, "ingest", {"k": "c3"}, "c3", seed=0)
    assert not other.resumed and not (other.work_dir / "partial.txt").exists()


def _try_lock(root, q):
    try:
        with Workspace(root).lock:
            q.put("acquired")
    except StageError as e:
        q.put(str(e))


def test_lock_excludes_a_second_process(tmp_path):
    ws = Workspace(tmp_path / "ws")
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    with ws.lock:
        p = ctx.Process(target=_try_lock, args=(str(ws.root), q))
        p.start()
        p.join(60)
        msg = q.get(timeout=5)
    assert "in use" in msg
    p = ctx.Process(target=_try_lock, args=(str(ws.root), q))
    p.start()
    p.join(60)
    assert q.get(timeout=5) == "acquired"


def test_checkpoint_round_trip_every_optimizer_group(tmp_path):
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.Linear(8, 2))
    opt = torch.optim.Adam([{"params": net[0].parameters(), "lr": 1e-2}, {"params": net[1].parameters(), "lr": 1e-3}])
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, 0.9)
    for _ in range(3):
        opt.zero_grad()
        net(torch.randn(4, 3)).sum().backward()
        opt.step()
        sched.step()
    state = {"net": net.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(), "rng": rng_state()}
    for step in (10, 20, 30):
        save_checkpoint(tmp_path, step, state, keep=2)
    assert sorted(p.name for p in tmp_path.glob("ckpt_*.pt")) == ["ckpt_00000020.pt", "ckpt_00000030.pt"]
    ck = load_checkpoint(latest_checkpoint(tmp_path))
    assert ck["step"] == 30 and ck["format"] == CHECKPOINT_FORMAT
    net2 = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.Linear(8, 2))
    opt2 = torch.optim.Adam([{"params": net2[0].parameters(), "lr": 0.5}, {"params": net2[1].parameters(), "lr": 0.5}])
    sched2 = torch.optim.lr_scheduler.ExponentialLR(opt2, 0.9)
    net2.load_state_dict(ck["state"]["net"])
    opt2.load_state_dict(ck["state"]["opt"])
    sched2.load_state_dict(ck["state"]["sched"])
    for g1, g2 in zip(opt.param_groups, opt2.param_groups):
        assert g1["lr"] == pytest.approx(g2["lr"])
    for p1, p2 in zip(net.parameters(), net2.parameters()):
        assert torch.equal(p1, p2)
        assert torch.equal(opt.state[p1]["exp_avg"], opt2.state[p2]["exp_avg"])
        assert torch.equal(opt.state[p1]["exp_avg_sq"], opt2.state[p2]["exp_avg_sq"])
    set_rng_state(ck["state"]["rng"])
    a = torch.rand(3)
    set_rng_state(ck["state"]["rng"])
    assert torch.equal(a, torch.rand(3))


def test_foreign_checkpoint_is_refused(tmp_path):
    from sage_core.serialization import save_file

    p = tmp_path / "x.pt"
    save_file(p, {"weights": torch.ones(2)}, "something-else", 1)
    with pytest.raises(StageError, match="not a sage checkpoint"):
        load_checkpoint(p)


def test_pickle_checkpoint_is_refused_with_conversion_hint(tmp_path):
    p = tmp_path / "ckpt_00000010.pt"
    torch.save({"format": 1, "step": 10, "state": {}}, p)
    with pytest.raises(StageError, match=r"old pickle format.*sage convert .*ckpt_00000010.pt --trust"):
        load_checkpoint(p)


def test_damaged_newest_checkpoint_falls_back_with_warning(tmp_path, caplog):
    for step in (10, 20):
        save_checkpoint(tmp_path, step, {"w": torch.full((64,), float(step))})
    newest = tmp_path / "ckpt_00000020.pt"
    newest.write_bytes(newest.read_bytes()[:-40])  # truncated mid-write
    with caplog.at_level("WARNING", logger="sage"):
        ck = latest_checkpoint(tmp_path)
    assert ck == tmp_path / "ckpt_00000010.pt"
    assert "ckpt_00000020.pt is damaged" in caplog.text and "resuming from ckpt_00000010.pt" in caplog.text
    assert float(load_checkpoint(ck)["state"]["w"][0]) == 10.0
    # a flipped byte in the tensor data is caught by the checksum
    good = tmp_path / "ckpt_00000010.pt"
    data = bytearray(good.read_bytes())
    data[-3] ^= 0xFF
    good.write_bytes(bytes(data))
    assert latest_checkpoint(tmp_path) is None
    with pytest.raises(StageError, match="checksum"):
        load_checkpoint(good)


def test_checkpoint_keeps_python_and_numpy_types(tmp_path):
    import numpy as np

    state = {"t": (1, 2.5, None, "s"), "ints": {0: torch.zeros(2), 3: [True, np.float32(0.1)]},
             "np": np.arange(6, dtype=np.uint32).reshape(2, 3), "__odd": 1}  # fmt: skip
    save_checkpoint(tmp_path, 1, state)
    back = load_checkpoint(latest_checkpoint(tmp_path))["state"]
    assert back["t"] == (1, 2.5, None, "s") and set(back["ints"]) == {0, 3}
    assert isinstance(back["ints"][3][1], np.float32) and back["ints"][3][1] == np.float32(0.1)
    assert back["np"].dtype == np.uint32 and back["np"].tolist() == [[0, 1, 2], [3, 4, 5]]
    assert back["__odd"] == 1


def test_missing_output_makes_stage_incomplete_and_reruns(tmp_path):
    ws = Workspace(tmp_path / "ws")
    _run(ws, "ingest")
    (ws.stage_dir("ingest") / "out.txt").unlink()
    st = ws.status("ingest")
    assert st.status == "incomplete" and "out.txt is missing" in st.reason
    with pytest.raises(StageError, match="incomplete.*out.txt"):
        ws.require("ingest", "init-mesh")
    assert _run(ws, "ingest") is not None  # not skipped
    assert ws.status("ingest").status == "complete"


def test_manifest_that_is_not_an_object_is_corrupt(tmp_path):
    ws = Workspace(tmp_path / "ws")
    _run(ws, "ingest")
    ws.manifest_path("ingest").write_text("[1, 2]\n")
    st = ws.status("ingest")
    assert st.status == "corrupt" and "not a JSON object" in st.reason
    with pytest.raises(StageError, match="corrupt"):
        ws.require("ingest", "init-mesh")
    assert _run(ws, "ingest") is not None and ws.status("ingest").status == "complete"


def test_workspace_path_that_is_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(WorkspaceError, match="is a file, not a workspace folder"):
        Workspace(f)
    with pytest.raises(WorkspaceError, match="is a file, not a folder"):
        Workspace(f / "ws")


def test_failed_rename_keeps_the_finished_run_and_next_run_promotes_it(tmp_path, monkeypatch):
    import os

    ws = Workspace(tmp_path / "ws")
    _run(ws, "ingest", payload="old")
    run = begin_stage(ws, "ingest", {"k": "c2"}, "c2", seed=0)
    (run.work_dir / "out.txt").write_text("new")
    save_checkpoint(run.checkpoint_dir, 5, {"w": torch.ones(1)})
    real = os.replace

    def failing(src, dst):
        if str(src) == str(run.work_dir):
            raise PermissionError(13, "Permission denied")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    with pytest.raises(WorkspaceError, match="cannot move the finished run into place"):
        run.finish()
    monkeypatch.setattr(os, "replace", real)
    # nothing lost: the old output is back, the new run (with its checkpoints) is in the work folder
    assert (ws.stage_dir("ingest") / "out.txt").read_text() == "old"
    assert (run.work_dir / "checkpoints" / "ckpt_00000005.pt").is_file()
    assert ws.status("ingest").status == "interrupted"
    # the next run promotes it and then skips, since it is complete with that config
    assert begin_stage(ws, "ingest", {"k": "c2"}, "c2", seed=0) is None
    assert (ws.stage_dir("ingest") / "out.txt").read_text() == "new"
    assert not (ws.stage_dir("ingest") / "checkpoints").exists() and not ws.work_dir("ingest").exists()


@dataclass
class _ToyConfig:
    value: int = 1


def _toy_body(run, emitter) -> None:
    (run.work_dir / "out.txt").write_text(str(run.config["value"]))


def _hold_lock(root, ready, release):
    with Workspace(root).lock:
        ready.set()
        release.wait(60)


def test_an_up_to_date_stage_is_skipped_while_another_process_holds_the_lock(tmp_path):
    from sage_core.config import config_hash
    from sage_core.stages._runner import StageSettings, execute_stage
    from sage_core.stages.events import Emitter
    from sage_core.workspace import stage_up_to_date

    ws = Workspace(tmp_path / "ws")
    events = []
    emitter = Emitter("ingest", events.append)
    first = execute_stage("ingest", ws, _ToyConfig(1), _toy_body, StageSettings(seed=3, device="cpu"), emitter)
    assert first.manifest is not None
    assert stage_up_to_date(ws, "ingest", config_hash(_ToyConfig(1)), seed=3)
    assert not stage_up_to_date(ws, "ingest", config_hash(_ToyConfig(2)), seed=3)
    assert not stage_up_to_date(ws, "ingest", config_hash(_ToyConfig(1)), seed=4)
    assert not stage_up_to_date(ws, "phase1", config_hash(_ToyConfig(1)), requires=["ingest"], seed=3)
    ctx = mp.get_context("spawn")
    ready, release = ctx.Event(), ctx.Event()
    holder = ctx.Process(target=_hold_lock, args=(str(ws.root), ready, release))
    holder.start()
    try:
        assert ready.wait(60)
        # same config and seed: reported as skipped without waiting for the lock
        again = execute_stage("ingest", ws, _ToyConfig(1), _toy_body, StageSettings(seed=3, device="cpu"), emitter)
        assert again.manifest is None and events[-1].kind == "skipped"
        # anything that has to run still needs the lock
        with pytest.raises(StageError, match="in use"):
            execute_stage("ingest", ws, _ToyConfig(2), _toy_body, StageSettings(seed=3, device="cpu"), emitter)
        with pytest.raises(StageError, match="in use"):
            execute_stage("ingest", ws, _ToyConfig(1), _toy_body, StageSettings(seed=3, device="cpu", force=True), emitter)
    finally:
        release.set()
        holder.join(60)
    assert (ws.stage_dir("ingest") / "out.txt").read_text() == "1"
    # a promotion cut short is left to the locked path, which recovers it
    (ws.stage_dir("ingest") / "RUN").write_text("{}")
    assert ws.needs_recovery("ingest")
    assert not stage_up_to_date(ws, "ingest", config_hash(_ToyConfig(1)), seed=3)
    (ws.stage_dir("ingest") / "RUN").unlink()
    # the files a manifest lists must exist for the stage to count as up to date
    (ws.stage_dir("ingest") / "out.txt").unlink()
    assert not stage_up_to_date(ws, "ingest", config_hash(_ToyConfig(1)), seed=3)


def test_ingest_manifest_records_no_absolute_path(tiny_ws):
    """The ingest manifest names the capture relative to the workspace, so a workspace copied beside
    its capture stays whole and carries no path of the machine it was made on."""
    import json
    import os

    m = json.loads((tiny_ws / "data" / "manifest.json").read_text())

    def strings(x):
        if isinstance(x, dict):
            for v in x.values():
                yield from strings(v)
        elif isinstance(x, list):
            for v in x:
                yield from strings(v)
        elif isinstance(x, str):
            yield x

    assert not [s for s in strings(m) if s.startswith("/") or str(tiny_ws.parent) in s]
    rel = m["inputs"]["files"]["dataset"]
    capture = (tiny_ws / rel).resolve()
    assert (capture / "transforms.json").is_file() and os.path.isabs(rel) is False


def test_dataset_key_keeps_an_earlier_absolute_record_of_the_same_folder(tmp_path):
    """Workspaces ingested when the manifest recorded the absolute capture path stay up to date while
    that path names the same folder; otherwise the path is relative to the workspace."""
    import json

    from sage_core.stages.ingest import _dataset_key
    from sage_core.workspace import Workspace

    cap, other, ws = tmp_path / "cap", tmp_path / "other", tmp_path / "ws"
    cap.mkdir(), other.mkdir()
    w = Workspace(ws)
    assert _dataset_key(w, cap) == "../cap"
    (ws / "data").mkdir(parents=True)
    (ws / "data" / "manifest.json").write_text(json.dumps({"status": "complete", "inputs": {"files": {"dataset": str(cap.resolve())}}}))
    assert _dataset_key(w, cap) == str(cap.resolve())
    assert _dataset_key(w, other) == "../other"
