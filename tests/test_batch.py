"""`sage batch`: SUBJECTS parsing, the local engine (with a broken subject), resume after a kill,
the Ray engine in local mode, and the live status files."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

FAST = [
    "init_mesh.pretrain.steps=5", "init_mesh.pretrain.bank_size=2000", "init_mesh.pretrain.batch_size=512",
    "init_mesh.pretrain.eval_samples=500", "init_mesh.mc_resolution=24", "phase1.iterations=2", "phase1.n_surfels=300",
    "phase1.eval_every=0", "phase1.mc_resolution=24", "phase1.rays_per_step=64", "phase1.neus_samples=8",
    "phase1.neus_importance=8", "eval.samples=2",
]  # fmt: skip
STAGES = ["ingest", "init-mesh", "phase1", "eval", "export"]


def _app() -> typer.Typer:
    from sage_cli.commands.batch_cmd import batch

    app = typer.Typer(add_completion=False)
    app.command()(batch)
    return app


def _args(subjects: Path, root: Path, *extra: str, quiet: bool = True) -> list[str]:
    args = [str(subjects), str(root), "--preset", "tiny", "--skip-phase2", "--device", "cpu", *(["--quiet"] if quiet else []), *extra]
    for s in FAST:
        args += ["--set", s]
    return args


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Two tiny captures (copies of one) and a broken one (truncated transforms_train.json)."""
    from sage_core.data.synthetic import make_capture, preset

    base = tmp_path_factory.mktemp("batch_caps")
    cfg = preset("tiny", n_cameras=4, width=48, height=70, train_timesteps=1, test_timesteps=1)
    a = Path(make_capture(base / "a", cfg))
    shutil.copytree(a, base / "b")
    shutil.copytree(a, base / "bad")
    (base / "bad" / "transforms_train.json").write_text('{"frames": [\n')
    return base


def _csv(path: Path, caps: Path, ids: list[str], sets: dict[str, str] | None = None, folders: dict[str, str] | None = None) -> Path:
    """A SUBJECTS file of the captures ``ids`` (``folders`` maps an id to another capture folder; ``sets``
    gives a subject ``stage.key=value`` overrides)."""
    sets, folders = sets or {}, folders or {}
    rows = ["id,capture,flame_model,set"] + [
        f"{i},{caps / folders.get(i, i)},{caps / folders.get(i, i) / 'model' / 'synth_flame.npz'},{sets.get(i, '')}" for i in ids
    ]
    path.write_text("\n".join(rows) + "\n")
    return path


def _summary(root: Path) -> dict[str, dict]:
    doc = json.loads((root / "batch_summary.json").read_text())
    return {s["id"]: s for s in doc["subjects"]}


def _finished_at(ws: Path) -> dict[str, str]:
    from sage_core.workspace import Workspace

    w = Workspace(ws)
    return {s: (w.manifest(s) or {}).get("finished_at") for s in STAGES}


# ---- SUBJECTS --------------------------------------------------------------------------------


def test_load_subjects_forms_and_errors(tmp_path):
    from sage_core.batch import load_subjects
    from sage_core.errors import InputError

    for d in ("capA", "capB/x"):
        (tmp_path / d).mkdir(parents=True)
    (tmp_path / "capA" / "transforms.json").write_text("{}")
    (tmp_path / "model.npz").write_bytes(b"x")
    csv = tmp_path / "s.csv"
    csv.write_text("# subjects\nid,capture,regime,timestep,set\ns1,capA,mv-sf,3,phase1.iterations=5;eval.samples=2\ns2,capB,,,\n")
    subs = load_subjects(csv)
    assert [s.id for s in subs] == ["s1", "s2"]
    assert subs[0].capture == (tmp_path / "capA").resolve() and subs[0].regime == "mv-sf" and subs[0].timestep == 3
    assert subs[0].sets == ("phase1.iterations=5", "eval.samples=2") and subs[1].regime is None and subs[1].sets == ()

    y = tmp_path / "s.yaml"
    y.write_text("defaults: {regime: sv-hr, flame_model: model.npz}\nsubjects:\n  - {id: a, capture: capA, camera: 2}\n"
                 "  - {id: b, capture: capB, regime: mv-mf, set: [phase1.iterations=3]}\n")  # fmt: skip
    subs = load_subjects(y)
    assert [(s.id, s.regime, s.camera) for s in subs] == [("a", "sv-hr", 2), ("b", "mv-mf", None)]
    assert subs[0].flame_model == (tmp_path / "model.npz").resolve() and subs[1].sets == ("phase1.iterations=3",)

    folder = load_subjects(tmp_path)  # only capA holds a transforms*.json
    assert [s.id for s in folder] == ["capA"]

    bad = {
        "id,capture\ns1,capA\ns1,capB\n": "line 3: id 's1' repeats",
        "id,capture\ns1,missing\n": "line 2: capture",
        "id,capture,regime\ns1,capA,mono\n": "unknown regime",
        "id,capture,timestep\ns1,capA,x\n": "timestep must be an integer",
        "id,capture,colour\ns1,capA,red\n": "unknown field(s) colour",
        "id,capture\nbad id,capA\n": "id 'bad id'",
        "id,capture\ns1\n": "1 cells",
        "id,capture,set\ns1,capA,iterations\n": "stage.key=value",
    }
    for text, needle in bad.items():
        csv.write_text(text)
        with pytest.raises(InputError) as e:
            load_subjects(csv)
        assert e.value.path == csv and needle in e.value.problem, (text, e.value.problem)
    y.write_text("subjects:\n  - {id: a}\n")
    with pytest.raises(InputError, match="entry 1: 'capture' is missing"):
        load_subjects(y)
    with pytest.raises(InputError, match="no capture subfolders"):
        load_subjects(tmp_path / "capB")


def test_hostile_yaml_subjects_are_refused_quickly(tmp_path):
    from sage_core.batch import load_subjects
    from sage_core.errors import InputError

    (tmp_path / "capA").mkdir()
    y = tmp_path / "s.yaml"
    levels = ["&a0 [lol,lol,lol,lol,lol,lol,lol,lol,lol]"]
    levels += [f"&a{i} [{','.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 4)]  # each level 9 times the last
    y.write_text(f"- {{id: a, capture: capA, set: [{', '.join(levels)}]}}\n")
    with pytest.raises(InputError, match=r"invalid YAML: aliases \(\*name\) are not accepted") as e:
        load_subjects(y)
    assert e.value.path == y

    y.write_text("- id: " + "[" * 20_000 + "]" * 20_000 + "\n")
    with pytest.raises(InputError, match="invalid YAML: nested too deeply"):
        load_subjects(y)

    for text, needle in {
        "- {id: a, capture: capA, set: [[phase1.iterations=3]]}\n": "entry 1: 'set' items must be strings",
        "- {id: a, capture: capA, set: [{phase1.iterations: 3}]}\n": "entry 1: 'set' items must be strings",
        "- {id: [a, b], capture: capA}\n": "entry 1: 'id' must be a single value, not a list",
        "- {id: a, capture: {path: capA}}\n": "entry 1: 'capture' must be a single value, not a mapping",
    }.items():
        y.write_text(text)
        with pytest.raises(InputError) as e:
            load_subjects(y)
        assert e.value.path == y and needle in e.value.problem, (text, e.value.problem)
    y.write_text("- {id: a, capture: capA, set: [phase1.iterations=3, 'eval.samples=2']}\n")
    assert load_subjects(y)[0].sets == ("phase1.iterations=3", "eval.samples=2")


def test_status_writer_and_missing_ray(tmp_path, monkeypatch):
    from sage_core.batch import StatusWriter, read_status, run_ray
    from sage_core.errors import ConfigError
    from sage_core.stages import StageEvent

    w = StatusWriter(tmp_path, min_interval=0.0)
    w(StageEvent("running", "phase1", title="phase 1", metrics={"resumed": False, "device": "cpu"}))
    assert read_status(tmp_path)["stage"] == "phase1" and read_status(tmp_path)["message"] == "started"
    w(StageEvent("progress", "phase1", step=7, total=20, message="phase 1", metrics={"val_psnr": float("nan"), "loss": 0.5, "psnr": 21.5}))
    st = read_status(tmp_path)
    assert st["stage"] == "phase1" and st["done"] == 7 and st["total"] == 20 and st["psnr"] == pytest.approx(21.5)

    assert "loss 0.5" in st["message"]
    w(StageEvent("progress", "phase1", step=8, total=20, message="phase 1", metrics={"psnr": float("nan")}))
    assert read_status(tmp_path)["psnr"] == pytest.approx(21.5)  # a NaN PSNR keeps the last value

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(ConfigError, match="pip install 'ray>=2.9'"):
        run_ray([])


# ---- local engine ------------------------------------------------------------------------------


def test_run_local_placeholders_results_and_exit_codes(tmp_path):
    from sage_core.batch import Job, run_local

    code = (
        "import os, sys; print('dev', sys.argv[1], 'cpus', sys.argv[2], 'omp', os.environ['OMP_NUM_THREADS']); "
        "rc = int(sys.argv[3]); print('error: subject broke', file=sys.stderr) if rc else None; sys.exit(rc)"
    )
    jobs = [Job(f"j{i}", tmp_path / f"j{i}", ["{python}", "-c", code, "{device}", "{cpus}", str(rc)], tmp_path / f"j{i}" / "logs" / "b.log")
            for i, rc in enumerate((0, 3, 0))]  # fmt: skip
    seen, polls = [], []
    results = run_local(jobs, max_parallel=2, cpus_per_subject=3, on_result=seen.append, on_poll=lambda: polls.append(1), poll_interval=0.05)
    by = {r.id: r for r in results}
    assert sorted(by) == ["j0", "j1", "j2"] and len(seen) == 3 and polls
    assert by["j0"].ok and by["j0"].device == "cpu" and by["j0"].error is None
    assert by["j1"].returncode == 3 and by["j1"].error == "exit code 3"  # the log is not parsed
    assert "dev cpu cpus 3 omp 3" in (tmp_path / "j2" / "logs" / "b.log").read_text()



def test_local_batch_with_a_broken_subject_then_rerun(captures, tmp_path):
    subjects = _csv(tmp_path / "subjects.csv", captures, ["a", "b", "bad"])
    root = tmp_path / "root"
    runner = CliRunner()
    res = runner.invoke(_app(), _args(subjects, root, "--max-parallel", "2", "--cpus-per-subject", "1", quiet=False))
    assert res.exit_code == 1, res.output  # one subject failed; the others finished
    s = _summary(root)
    assert s["a"]["status"] == "finished" and s["b"]["status"] == "finished"
    assert s["bad"]["status"] == "failed" and "transforms_train.json" in s["bad"]["error"] and s["bad"]["returncode"] == 2
    assert s["bad"]["stage"] == "ingest"
    for sid in ("a", "b"):
        assert s[sid]["metrics"]["val_psnr"] > 5 and s[sid]["wall_time_s"] > 0 and s[sid]["stage"] is None
        assert json.loads((root / sid / ".batch_status.json").read_text())["state"] == "finished"
        assert all(_finished_at(root / sid).values())
        assert list((root / sid / "logs").glob("batch-*.log"))
    md = (root / "batch_summary.md").read_text()
    assert "| a | finished |" in md and "| bad | failed | ingest |" in md
    assert not (root / "bad" / "data").exists()
    # without a terminal: a line per change as it happens, and every error in full (paths are not cut)
    out = res.output
    assert "a: running phase1" in out and "bad: failed in ingest" in out and "a: finished (PSNR" in out
    assert str(captures / "bad" / "transforms_train.json") in out
    assert out.index("a: running phase1") < out.index("sage batch summary")

    before = {sid: _finished_at(root / sid) for sid in ("a", "b")}
    logs_before = len(list((root / "a" / "logs").glob("batch-*.log")))
    res = runner.invoke(_app(), _args(subjects, root, "--max-parallel", "2", "--cpus-per-subject", "1"))
    assert res.exit_code == 1, res.output
    s = _summary(root)
    assert s["a"]["status"] == "skipped" and s["b"]["status"] == "skipped" and s["bad"]["status"] == "failed"
    assert s["a"]["metrics"]["val_psnr"] > 5
    assert {sid: _finished_at(root / sid) for sid in ("a", "b")} == before
    assert len(list((root / "a" / "logs").glob("batch-*.log"))) == logs_before  # no process started


def test_resume_after_killing_the_batch(captures, tmp_path):
    """The batch is killed while subject b trains (b cannot finish: its phase 1 is a million steps);
    the next batch skips a and runs b to the end. The test waits on the status files, not the clock."""
    from sage_core.batch import read_status

    long_b = _csv(tmp_path / "long.csv", captures, ["a", "b"], sets={"b": "phase1.iterations=1000000"})
    root = tmp_path / "root"
    code = "import sys, typer; from sage_cli.commands.batch_cmd import batch; typer.run(batch)"
    cmd = [sys.executable, "-c", code, *_args(long_b, root, "--max-parallel", "1", "--cpus-per-subject", "1")]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        while p.poll() is None and not (read_status(root / "a").get("state") == "finished" and (read_status(root / "b").get("done") or 0) > 0
                                        and read_status(root / "b").get("stage") == "phase1"):  # fmt: skip
            time.sleep(0.05)
        assert p.poll() is None, "the batch ended before subject b trained"
        os.killpg(p.pid, signal.SIGKILL)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    assert read_status(root / "a").get("state") == "finished" and read_status(root / "b").get("state") == "running"
    a_before = _finished_at(root / "a")
    assert all(a_before.values())

    subjects = _csv(tmp_path / "subjects.csv", captures, ["a", "b"])
    res = CliRunner().invoke(_app(), _args(subjects, root, "--max-parallel", "1", "--cpus-per-subject", "1"))
    assert res.exit_code == 0, res.output
    s = _summary(root)
    assert s["a"]["status"] == "skipped" and s["b"]["status"] == "finished"
    assert _finished_at(root / "a") == a_before
    assert all(_finished_at(root / "b").values())


def test_worker_outcomes_and_the_local_sharing():
    from sage_core.batch import exit_state, local_gpus, plan_local
    from sage_core.batch.worker import error_text
    from sage_core.errors import ConfigError, InputError

    assert [exit_state(c) for c in (0, 130, 2, 1)] == ["finished", "interrupted", "failed", "failed"]
    assert error_text(InputError("/a/very/long/path/" + "x" * 120 + "/transforms_train.json", "cannot parse"), 2).endswith(
        "transforms_train.json: cannot parse")  # the whole line
    assert error_text(ValueError("bad\nsecond line"), 1) == "ValueError: bad" and error_text(KeyboardInterrupt(), 130) == "interrupted"
    # the device parser of the local engine
    assert local_gpus("cpu", [0, 1]) == [] and local_gpus("auto", [0, 1]) == [0, 1] and local_gpus("auto", []) == []
    assert local_gpus("cuda", [0, 1]) == [0, 1] and local_gpus("cuda:1", [0, 1]) == [1]
    for device, needle in (("cuda:5", "no such CUDA device"), ("gpu", "expected auto, cpu, cuda or cuda:N"), ("cuda:x", "expected")):
        with pytest.raises(ConfigError, match=needle):
            local_gpus(device, [0, 1])
    with pytest.raises(ConfigError, match="CUDA is not available"):
        local_gpus("cuda", [])
    # the sharing of cores and GPUs
    assert plan_local(8) == plan_local(8, cpus_per_subject=None) and plan_local(8).max_parallel == 2 and plan_local(8).cpus_per_subject == 4
    assert plan_local(2).max_parallel == 1 and plan_local(2).cpus_per_subject == 2
    assert (plan_local(8, max_parallel=3).max_parallel, plan_local(8, max_parallel=3).cpus_per_subject) == (3, 2)
    assert plan_local(2, cpus_per_subject=999).cpus_per_subject == 2  # never more threads than cores
    gpu = plan_local(16, [0, 1, 2, 3], gpus_per_subject=2)
    assert (gpu.max_parallel, gpu.cpus_per_subject, gpu.gpus, gpu.gpus_per_subject) == (2, 8, (0, 1, 2, 3), 2)
    with pytest.raises(ConfigError, match="whole number"):
        plan_local(8, [0, 1], gpus_per_subject=1.5)
    with pytest.raises(ConfigError, match="at least 1"):
        plan_local(8, max_parallel=0)


def test_a_failed_subject_names_the_stage_that_failed(tmp_path, monkeypatch):
    """A stage that fails before its work begins (here eval, after phase 1 trained) is the subject's
    failed stage, in its status file, its outcome and the summary; the error line is kept whole."""
    import sage_core.stages as stages
    from sage_core.batch import BatchDriver, JobResult, read_status, run_subject
    from sage_core.errors import InputError
    from sage_core.stages import StageEvent

    long_path = tmp_path / ("deep" * 30) / "gt" / "novel"

    def pipeline(*args, on_event=None, **kw):
        for stage in ("ingest", "init-mesh", "phase1"):
            on_event(StageEvent("started", stage))
            on_event(StageEvent("running", stage, title=stage, metrics={}))
            on_event(StageEvent("progress", stage, step=2, total=2, message=stage, metrics={"psnr": 20.0}))
        on_event(StageEvent("started", "eval"))
        raise InputError(long_path, "the capture has no held-out ground truth")

    monkeypatch.setattr(stages, "run_pipeline", pipeline)
    ws = tmp_path / "s1"
    spec = {"id": "s1", "ws": str(ws), "dataset": str(tmp_path), "flame_model": str(tmp_path / "m.npz"), "flame_masks": None,
            "ingest_flags": {}, "skip_phase2": True, "lpips_weights": None, "preset": "tiny", "config": None, "sets": {}, "seed": 0,
            "force": False, "run_key": "k", "stages": ["ingest"]}  # fmt: skip
    seen = []
    code = run_subject(spec, "cpu", 0, on_error=lambda e, c: seen.append(c), watch=False)
    st = read_status(ws)
    assert code == 2 and seen == [2] and st["state"] == "failed" and st["failed_stage"] == "eval"
    assert st["error"] == f"{long_path}: the capture has no held-out ground truth"
    changes = []
    driver = BatchDriver(tmp_path, [spec], on_change=lambda sid, row: changes.append((row["state"], row.get("stage"))))
    driver.on_result(JobResult("s1", 2, 3.0, "cpu", "exit code 2"))
    o = driver.outcomes["s1"]
    assert (o.status, o.stage, o.error) == ("failed", "eval", st["error"]) and changes[-1] == ("failed", "eval")
    assert "| s1 | failed | eval |" in (tmp_path / "batch_summary.md").read_text()


def test_change_lines_without_a_terminal():
    from sage_cli.commands.batch_cmd import change_line

    assert change_line("s1", {"state": "running", "stage": "phase1"}).endswith("s1: running phase1")
    assert change_line("s1", {"state": "failed", "stage": "eval"}).endswith("s1: failed in eval")
    assert change_line("s1", {"state": "finished", "psnr": 24.123}).endswith("s1: finished (PSNR 24.12 dB)")


# ---- Ray engine ------------------------------------------------------------------------------


@pytest.mark.slow
def test_ray_engine_local_mode(captures, tmp_path):
    ray = pytest.importorskip("ray")
    subjects = _csv(tmp_path / "subjects.csv", captures, ["a", "b"])
    root = tmp_path / "root"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        res = CliRunner().invoke(_app(), _args(subjects, root, "--engine", "ray", "--cpus-per-subject", "1"))
    finally:
        ray.shutdown()
    assert res.exit_code == 0, res.output
    s = _summary(root)
    assert [s[i]["status"] for i in ("a", "b")] == ["finished", "finished"]
    assert all(s[i]["device"] == "cpu" and s[i]["metrics"]["test_psnr"] > 5 for i in ("a", "b"))
    assert json.loads((root / "batch_summary.json").read_text())["engine"] == "ray"
