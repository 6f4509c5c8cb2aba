"""Thread policy, render-backend resolution and plumbing, duration estimates, over-long expr."""

from __future__ import annotations

import json
import sys
import types

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sage_cli.app import app
from sage_core import runtime
from sage_core.errors import ConfigError

runner = CliRunner()


# ---- threads ------------------------------------------------------------------------------------


def _busy(monkeypatch, busy: float) -> None:
    """Make the busy-core measurement report ``busy`` cores."""
    monkeypatch.setattr(runtime, "measure_busy_cores", lambda *a, **k: runtime.CpuSample(busy, runtime.available_cores(), 0.2, 0.0))


def test_apply_threads_flag_env_and_default(monkeypatch):
    before = torch.get_num_threads()
    try:
        monkeypatch.delenv(runtime.THREADS_ENV, raising=False)
        _busy(monkeypatch, 0.0)
        assert runtime.default_threads() == runtime.available_cores()
        assert runtime.apply_threads(1) == 1 and torch.get_num_threads() == 1
        monkeypatch.setenv(runtime.THREADS_ENV, "1")
        assert runtime.apply_threads(None) == 1 and torch.get_num_threads() == 1
        assert runtime.apply_thread_choice(None).source == "$SAGE_THREADS"
        monkeypatch.setenv(runtime.THREADS_ENV, "many")
        with pytest.raises(ConfigError, match="SAGE_THREADS"):
            runtime.apply_threads(None)
        assert runtime.apply_threads(1) == 1  # the flag wins over the environment
        with pytest.raises(ConfigError, match="--threads = 0"):
            runtime.apply_threads(0)
    finally:
        torch.set_num_threads(before)


def test_default_threads_leave_the_busy_cores_alone(monkeypatch):
    monkeypatch.delenv(runtime.THREADS_ENV, raising=False)
    monkeypatch.setattr(runtime, "available_cores", lambda: 8)
    for busy, want in ((0.0, 8), (0.4, 8), (0.6, 7), (3.0, 5), (7.2, 1), (12.0, 1)):
        _busy(monkeypatch, busy)
        choice = runtime.choose_threads(None)
        assert choice.threads == want and choice.source == "idle cores"
        assert choice.describe().startswith(f"{want} thread") and "of 8 cores idle" in choice.describe()
    monkeypatch.setenv(runtime.THREADS_ENV, "6")  # an explicit count is taken as given
    assert runtime.default_threads() == 6


def test_thread_counts_above_the_cores_are_capped_with_a_warning(monkeypatch):
    monkeypatch.setattr(runtime, "available_cores", lambda: 2)
    choice = runtime.choose_threads(999)
    assert choice.threads == 2 and choice.capped_from == 999
    assert "--threads 999 is more than the 2 cores" in (choice.warning() or "")
    monkeypatch.setenv(runtime.THREADS_ENV, "64")
    env = runtime.choose_threads(None)
    assert env.threads == 2 and "$SAGE_THREADS 64" in (env.warning() or "")
    assert runtime.choose_threads(2).warning() is None and runtime.choose_threads(1).describe() == "1 thread (--threads)"


def test_busy_cores_are_measured_over_a_short_window(monkeypatch, tmp_path):
    """The busy share of the cores this process may run on over the window, from /proc/stat, less
    this process's own CPU time: not the load average, which lags a minute behind."""
    import builtins

    monkeypatch.setattr(runtime, "_LAST_SAMPLE", [])
    monkeypatch.setattr(runtime.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    # /proc/stat lines of 3 CPUs, of which this process may use cpu0 and cpu1
    stats = iter([
        "cpu  0 0 0 0 0 0 0 0 0 0\ncpu0 100 0 0 100 0 0 0 0 0 0\ncpu1 100 0 0 100 0 0 0 0 0 0\ncpu2 0 0 0 0 0 0 0 0 0 0\n",
        # over the window: cpu0 fully busy (20 of 20 ticks), cpu1 half (user 10, idle 5, iowait 5), cpu2 ignored
        "cpu  0 0 0 0 0 0 0 0 0 0\ncpu0 120 0 0 100 0 0 0 0 0 0\ncpu1 110 0 0 105 5 0 0 0 0 0\ncpu2 50 0 0 0 0 0 0 0 0 0\n",
    ])
    real_open = builtins.open

    def fake_open(path, *a, **k):
        if str(path) == "/proc/stat":
            f = tmp_path / "stat"
            f.write_text(next(stats))
            return real_open(f, *a, **k)
        return real_open(path, *a, **k)

    clock = iter([10.0, 10.0, 10.2])  # the reuse check, then both ends of the window
    own = iter([1.0, 1.05])  # this process used a quarter of a core meanwhile
    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(runtime, "time", types.SimpleNamespace(monotonic=lambda: next(clock), sleep=lambda s: None, perf_counter=lambda: 0.0))
    monkeypatch.setattr(runtime, "_own_cpu_s", lambda: next(own))
    sample = runtime.measure_busy_cores()
    assert sample is not None and sample.cores == 2
    assert sample.busy == pytest.approx(2 * (30 / 40) - 0.25)  # 1.25 cores busy with other work
    monkeypatch.setattr(runtime, "time", types.SimpleNamespace(monotonic=lambda: 12.0, sleep=lambda s: None))
    assert runtime.measure_busy_cores() is sample  # reused within CPU_SAMPLE_REUSE_S
    assert runtime.busy_cores() == 1


def test_the_running_line_shows_the_thread_choice_and_a_capped_request(tiny_capture, tmp_path):
    ws = tmp_path / "ws"
    res = runner.invoke(app, ["ingest", str(tiny_capture), str(ws), "--flame-model", str(tiny_capture.model_path), "--preset", "tiny",
                              "--device", "cpu", "--threads", "999"], env={"COLUMNS": "200"})  # fmt: skip
    assert res.exit_code == 0, res.output
    n = runtime.available_cores()
    assert f"--threads 999 is more than the {n} cores" in res.output
    assert f"cpu · {runtime.choose_threads(999).describe()}" in res.output
    assert json.loads((ws / "data" / "manifest.json").read_text())["metrics"]["threads"] == n


def test_batch_divides_the_cores_among_concurrent_workers(tmp_path):
    assert runtime.threads_per_worker(1, cores=8) == 8
    assert runtime.threads_per_worker(3, cores=8) == 2
    assert runtime.threads_per_worker(4, cores=2) == 1  # never 0
    with pytest.raises(ConfigError):
        runtime.threads_per_worker(0, cores=2)
    from sage_core.batch.engines import Job, run_job

    log = tmp_path / "job.log"
    code = f"import os; print('threads', os.environ['{runtime.THREADS_ENV}'], os.environ['OMP_NUM_THREADS'])"
    res = run_job(Job("s1", tmp_path, ["{python}", "-c", code], log), "cpu", 3)
    assert res.ok, res.error
    assert "threads 3 3" in log.read_text()


def test_stage_manifest_records_threads_and_info_shows_them(tiny_capture, tmp_path):
    ws = tmp_path / "ws"
    res = runner.invoke(app, ["ingest", str(tiny_capture), str(ws), "--flame-model", str(tiny_capture.model_path), "--preset", "tiny",
                              "--quiet", "--device", "cpu", "--threads", "1"])  # fmt: skip
    assert res.exit_code == 0, res.output
    m = json.loads((ws / "data" / "manifest.json").read_text())
    assert m["metrics"]["threads"] == 1
    from sage_cli.commands.info import _ran_on

    assert _ran_on(m) == "cpu · 1 thread"
    assert _ran_on({"device": "cpu", "metrics": {"threads": 2, "render_backend": "cpp"}}) == "cpu · 2 threads · cpp rasterizer"
    assert _ran_on({"device": "cpu", "metrics": {"threads": 1, "render_backend": "cpp", "hashgrid_backend": "cpp"}}) == (
        "cpu · 1 thread · cpp rasterizer · cpp hash grid")
    assert _ran_on({"device": "cpu", "metrics": {"threads": 1, "hashgrid_backend": "cpp", "sdf_backend": "cpp"}}) == (
        "cpu · 1 thread · cpp hash grid · cpp SDF")
    assert runner.invoke(app, ["info", str(ws)]).exit_code == 0
    res = runner.invoke(app, ["ingest", str(tiny_capture), str(tmp_path / "ws2"), "--flame-model", str(tiny_capture.model_path),
                              "--quiet", "--device", "cpu", "--threads", "0"])  # fmt: skip
    assert res.exit_code == 3 and "--threads = 0" in res.output, res.output


# ---- render backend -----------------------------------------------------------------------------


def test_resolve_render_backend():
    assert runtime.resolve_render_backend("torch", "cpu") == "torch"
    assert runtime.resolve_render_backend("auto", "cpu") in ("torch", "cpp")
    with pytest.raises(ConfigError, match="render_backend = 'vulkan'"):
        runtime.resolve_render_backend("vulkan", "cpu")
    try:  # Triton's interpreter (set by the Triton tests of this session) does run it on the CPU
        from sage_core.render import _triton_surfels

        interpreted = bool(_triton_surfels.INTERPRETED)
    except ImportError:
        interpreted = False
    if not torch.cuda.is_available() and not interpreted:
        with pytest.raises(ConfigError, match="render_backend = 'triton' cannot run on cpu"):
            runtime.resolve_render_backend("triton", "cpu")


@pytest.fixture
def recorded_backends(monkeypatch):
    """Every rasterize_surfels call's ``backend`` argument, for the callers that import it."""
    import sage_core.avatar.rendering as rendering
    import sage_core.train.phase2 as phase2
    from sage_core.render import rasterize_surfels

    seen: list[str] = []

    def spy(*args, **kwargs):
        seen.append(kwargs.get("backend", "<default>"))
        return rasterize_surfels(*args, **kwargs)

    monkeypatch.setattr(rendering, "rasterize_surfels", spy)
    monkeypatch.setattr(phase2, "rasterize_surfels", spy)
    monkeypatch.setattr(sys.modules["sage_core.render"], "rasterize_surfels", spy)
    return seen


def test_render_backend_reaches_the_rasterizer_in_phase1(tiny_ws, tiny_init_dir, recorded_backends, one_thread):
    from sage_core.config import resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.train.phase1 import Phase1Trainer, build_avatar
    from sage_core.stages.avatars import AvatarRenderer, stage_render_settings

    data = IngestedData.open(tiny_ws / "data")
    flags = {"n_surfels": 600, "rays_per_step": 32, "neus_samples": 8, "neus_importance": 4, "neus_up_steps": 1, "app_hidden": 16,
             "shape_hidden": 16, "eval_every": 0, "render_backend": "torch"}  # fmt: skip
    cfg = resolve_config("phase1", "tiny", None, flags)
    g = torch.Generator().manual_seed(0)
    av = build_avatar(data, tiny_init_dir, cfg, "cpu", g)
    trainer = Phase1Trainer(av, data, cfg, "cpu", g)
    trainer.step()
    trainer.evaluate("val", max_frames=1)
    assert recorded_backends and set(recorded_backends) == {"torch"}
    recorded_backends.clear()
    renderer = AvatarRenderer(av, stage_render_settings(tiny_init_dir, data), backend="torch")
    fr = data.val[0] if data.val else data.train[0]
    renderer.render(fr.camera, av.frame_inputs(fr.timestep))
    assert recorded_backends == ["torch"]


# ---- duration estimate --------------------------------------------------------------------------


def test_step_clock_extrapolates_from_the_first_steps(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(runtime, "time", types.SimpleNamespace(perf_counter=lambda: now[0]))
    clock = runtime.StepClock(total=1000, start=0, warmup=1, steps=4)
    out = []
    for step in range(1, 8):
        now[0] += 5.0 if step == 1 else 2.0  # a slow first step, then 2 s per step
        out.append(clock.tick(step))
    est = [e for e in out if e is not None]
    assert len(est) == 1 and out[4] is est[0]  # reported once, after 1 warm-up + 4 timed steps
    e = est[0]
    assert e.first and e.basis == "steps 2-5"
    assert e.s_per_step == pytest.approx(2.0)
    assert e.remaining_s == pytest.approx(2.0 * (1000 - 5))
    assert e.total_s == pytest.approx(5.0 + 4 * 2.0 + e.remaining_s)
    assert runtime.format_duration(e.total_s) == "33 min"


def test_step_clock_updates_the_estimate_from_the_recent_steps(monkeypatch):
    """When the machine gets busier half-way, the updates follow the recent rate, not the first steps'."""
    now = [0.0]
    monkeypatch.setattr(runtime, "time", types.SimpleNamespace(perf_counter=lambda: now[0]))
    clock = runtime.StepClock(total=400, start=0, warmup=1, steps=4, update_s=30.0, window_s=60.0)
    out = []
    for step in range(1, 400):
        now[0] += 1.0 if step <= 100 else 4.0  # 1 s per step, then 4 s
        e = clock.tick(step)
        if e is not None:
            out.append((step, e, now[0]))
    first = out[0][1]
    assert first.first and first.s_per_step == pytest.approx(1.0)
    updates = [e for _, e, _ in out[1:]]
    assert updates and not any(e.first for e in updates)
    assert all(b[2] - a[2] >= 30 for a, b in zip(out, out[1:]))  # at most every update_s seconds
    late = [e for s, e, _ in out[1:] if s > 130]
    assert late and all(e.s_per_step == pytest.approx(4.0) for e in late)  # the last minute's steps only
    assert late[0].basis.startswith("the last ") and "steps" in late[0].basis


def test_progress_display_prints_updates_that_move_the_estimate(monkeypatch):
    from sage_cli import _common

    shown: list[str] = []
    monkeypatch.setattr(_common.console, "print", lambda text, **kw: shown.append(str(text)))
    disp = _common.ProgressDisplay("phase 1", enabled=True, device="cpu", preset="tiny")
    disp._progress = None  # no bar: only the printed lines
    disp(5, 1000, "phase 1", **runtime.Estimate(1.0, 995.0, 1000.0, 1000, "steps 2-5", True).as_stats())
    assert len(shown) == 1 and "about 17 min" in shown[0] and "over steps 2-5" in shown[0]
    disp(40, 1000, "phase 1", **runtime.Estimate(1.05, 1008.0, 1050.0, 1000, "the last 30 steps (31 s)", False).as_stats())
    assert len(shown) == 1  # within a quarter of what was printed: logged only
    disp(70, 1000, "phase 1", **runtime.Estimate(2.0, 1860.0, 1930.0, 1000, "the last 30 steps (60 s)", False).as_stats())
    assert len(shown) == 2 and "now about 31 min to go" in shown[1] and "over the last 30 steps (60 s)" in shown[1]


def test_estimate_lines_warn_on_cpu_with_the_default_preset_or_a_long_stage():
    from sage_cli._common import estimate_lines

    from sage_core.config import PRESETS

    fits = "small" if "small" in PRESETS else "tiny"
    lines = estimate_lines("phase 1", 3 * 86400, 8.6, "cpu", "default")
    assert "3.0 days" in lines[0] and len(lines) == 2
    assert "preset 'default'" in lines[1] and f"--preset {fits} fits" in lines[1]
    if "small" in PRESETS:
        assert "--preset tiny fits" in estimate_lines("phase 1", 3 * 3600, 2.7, "cpu", "small")[1]
    assert len(estimate_lines("phase 1", 400, 0.3, "cpu", "tiny")) == 1
    assert "lower --iterations" in estimate_lines("phase 1", 3 * 3600, 7.2, "cpu", "tiny")[1]
    assert len(estimate_lines("phase 1", 3 * 86400, 8.6, "cuda", "default")) == 1


def test_progress_display_prints_the_estimate(capsys):
    from sage_cli import _common

    shown: list[str] = []
    disp = _common.ProgressDisplay("phase 1", enabled=False, device="cpu", preset="default")
    orig = _common.console.print
    _common.console.print = lambda text, **kw: shown.append(str(text))  # type: ignore[method-assign]
    try:
        with disp:
            disp(5, 30000, "phase 1", **runtime.Estimate(8.0, 8.0 * 29995, 8.0 * 30000, 30000).as_stats())
    finally:
        _common.console.print = orig  # type: ignore[method-assign]
    assert len(shown) == 1 and "warning" in shown[0] and "--preset " in shown[0]  # quiet: only the warning


# ---- over-long expr -----------------------------------------------------------------------------


def _params(expr):
    from sage_core.flame.params import FlameParams

    T = expr.shape[0]
    z = np.zeros((T, 3), np.float32)
    return FlameParams(shape=np.zeros(10, np.float32), expr=expr.astype(np.float32), rotation=z, neck_pose=z, jaw_pose=z,
                       eyes_pose=np.zeros((T, 6), np.float32), translation=z, static_offset=None, dynamic_offset=None,
                       timesteps=np.arange(T))  # fmt: skip


def test_over_long_expr_is_refused_only_when_coefficients_would_be_lost():
    from sage_core.flame.params import expr_overflow

    assert expr_overflow(_params(np.zeros((2, 100))), 50) is None  # zero padding columns lose nothing
    assert expr_overflow(_params(np.ones((2, 20))), 50) is None  # shorter: zero-padded by the model
    e = np.zeros((2, 100))
    e[1, 60], e[0, 70] = 0.3, -1.0
    msg = expr_overflow(_params(e), 50)
    assert msg is not None and "100 coefficients" in msg and "50 expression components" in msg and "60..70" in msg
