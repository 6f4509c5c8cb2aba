"""Executing a plan: every step once, in order, a failed step failing only what depends on it;
then each row's numbers collected from its workspace."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from sage_core.workspace import Workspace, now_iso

from . import collect
from .rows import ROWS, RowSpec, Settings, Step
from .runner import command_line, run_process, sage_argv
from .workspaces import capture_is_current, ceiling_command, copy_command, copy_stages, motion_command, write_test_motion

Log = Callable[[str], None]


def step_command(step: Step) -> str:
    """The shell line that reproduces a step."""
    if step.kind in ("cli", "synth"):
        return command_line(step.argv)
    if step.kind == "copy":
        assert step.src is not None and step.dst is not None
        return copy_command(step.src, step.dst, step.stages)
    if step.kind == "motion":
        assert step.capture is not None and step.out is not None
        return motion_command(step.capture, step.out, step.steps)
    if step.kind == "ceiling":
        assert step.capture is not None and step.out is not None
        return ceiling_command(step.capture, step.out, step.split, step.lpips_weights)
    raise ValueError(f"unknown step kind {step.kind!r}")


def _manifest_stamp(ws: Path, stage: str | None) -> str | None:
    if stage is None:
        return None
    m = Workspace(ws).manifest(stage)
    return None if m is None else f"{m.get('fingerprint')}@{m.get('finished_at')}"


def run_step(step: Step, settings: Settings, previous: dict[str, Any] | None, poll_gpu: bool) -> dict[str, Any]:
    """Run one step; returns its record (command, rc, wall_s, peak_rss_mib, gpu_peak_mib, ran,
    error). A stage the workspace skips (already complete) keeps the memory figures of the
    ``previous`` record of the same step when that record produced the current manifest."""
    rec: dict[str, Any] = {"kind": step.kind, "command": step_command(step), "row": step.row, "stage": step.stage,
                           "started_at": now_iso(), "error": None}  # fmt: skip
    t0 = time.perf_counter()
    try:
        if step.kind == "synth":
            assert step.capture is not None
            if capture_is_current(step.capture, step.argv):
                rec.update(rc=0, ran=False, wall_s=time.perf_counter() - t0, note="capture already present")
                return _keep_previous(rec, previous)
            argv = list(step.argv) + (["--force"] if step.capture.exists() else [])
            rec["command"] = command_line(argv)
            return _run_cli(rec, argv, settings, step, poll_gpu, None)
        if step.kind == "cli":
            ws = settings.ws(step.row) if step.row else None
            stamp = _manifest_stamp(ws, step.stage) if ws is not None else None
            return _run_cli(rec, step.argv, settings, step, poll_gpu, (ws, stamp, previous))
        if step.kind == "copy":
            assert step.src is not None and step.dst is not None
            copied = copy_stages(step.src, step.dst, step.stages)
            rec.update(rc=0, ran=bool(copied), wall_s=time.perf_counter() - t0, copied=copied)
            return rec
        if step.kind == "motion":
            assert step.capture is not None and step.out is not None
            path, keys = write_test_motion(step.capture, step.out, step.steps)
            rec.update(rc=0, ran=True, wall_s=time.perf_counter() - t0, motion=str(path), key_timesteps=keys)
            return rec
        if step.kind == "ceiling":
            assert step.capture is not None and step.out is not None
            from sage_core.evaluate.ceiling import evaluate_ceiling

            report = evaluate_ceiling(step.capture, step.out, step.split, step.lpips_weights)
            rec.update(rc=0, ran=True, wall_s=time.perf_counter() - t0, run_wall_s=time.perf_counter() - t0, metrics=str(report.metrics_path))
            return rec
        raise ValueError(f"unknown step kind {step.kind!r}")
    except Exception as e:  # noqa: BLE001 - one failed step must not stop the suite
        rec.update(rc=1, ran=True, wall_s=time.perf_counter() - t0, error=f"{type(e).__name__}: {e}")
        return rec


def _keep_previous(rec: dict[str, Any], previous: dict[str, Any] | None) -> dict[str, Any]:
    if previous:
        for k in ("peak_rss_mib", "gpu_peak_mib", "run_wall_s"):
            if previous.get(k) is not None:
                rec[k] = previous[k]
    return rec


def _run_cli(rec: dict[str, Any], argv: list[str], settings: Settings, step: Step, poll_gpu: bool, check: Any) -> dict[str, Any]:
    log = settings.out / "logs" / (step.key.replace(":", "__") + ".log")
    res = run_process(sage_argv(argv), log, poll_gpu=poll_gpu)
    rec.update(rc=res.rc, wall_s=res.wall_s, log=str(log), ran=True)
    if res.rc != 0:
        rec["error"] = f"exit {res.rc}: {res.tail}"
    if check is not None and res.rc == 0:
        ws, stamp, previous = check
        after = _manifest_stamp(ws, step.stage)
        rec["stamp"] = after
        if stamp is not None and after == stamp:
            rec["ran"] = False
            rec["note"] = "stage already complete (skipped by the workspace)"
            return _keep_previous(rec, previous if previous and previous.get("stamp") == after else None)
    rec.update(peak_rss_mib=res.peak_rss_mib, gpu_peak_mib=res.gpu_peak_mib, run_wall_s=res.wall_s)
    return rec


def execute(steps: list[Step], settings: Settings, previous_steps: dict[str, Any], log: Log, poll_gpu: bool = False) -> dict[str, Any]:
    """Run every step in order; a step whose dependency failed is not run and fails with a note.
    Returns key -> record."""
    records: dict[str, Any] = {}
    for i, step in enumerate(steps, 1):
        failed = [d for d in step.deps if records.get(d, {}).get("error")]
        if failed:
            records[step.key] = {"kind": step.kind, "command": step_command(step), "row": step.row, "stage": step.stage,
                                 "rc": None, "ran": False, "error": f"not run: {', '.join(failed)} failed"}  # fmt: skip
            log(f"[{i}/{len(steps)}] {step.key}: not run ({', '.join(failed)} failed)")
            continue
        log(f"[{i}/{len(steps)}] {step.key}: {step_command(step)}")
        rec = run_step(step, settings, previous_steps.get(step.key), poll_gpu)
        records[step.key] = rec
        state = "FAILED " + rec["error"] if rec.get("error") else ("done" if rec.get("ran") else "up to date")
        log(f"    {state} ({rec.get('wall_s', 0.0):.1f} s)")
    return records


STAGE_COLUMNS = ("ingest", "init-mesh", "phase1", "phase2")


def _stage_step_key(row: RowSpec, stage: str) -> str:
    """Key of the step that produced ``stage`` of a row's workspace (its base's for copied stages)."""
    if stage in row.copy_stages and row.base is not None:
        return _stage_step_key(ROWS[row.base], stage)
    return f"{row.id}:{stage}"


def collect_row(row: RowSpec, settings: Settings, needs: list[str], records: dict[str, Any]) -> dict[str, Any]:
    """The numbers of one row from its workspace and the step records (missing ones are None;
    failures are listed in ``errors``)."""
    ws = settings.ws(row.id)
    out: dict[str, Any] = {
        "id": row.id, "label": row.label, "input_type": row.input_type, "regime": row.regime, "capture": row.capture,
        "eval_stage": row.eval_stage, "has_sdf": row.has_sdf, "workspace": str(ws), "steps": list(needs),
        "shared_from": row.base, "copied_stages": list(row.copy_stages), "finished_at": now_iso(), "errors": [],
    }  # fmt: skip
    errors: list[str] = out["errors"]
    for key in needs:
        err = (records.get(key) or {}).get("error")
        if err:
            errors.append(f"{key}: {err}")
    stages: dict[str, Any] = {}
    for stage in STAGE_COLUMNS:
        rec = collect.stage_record(ws, stage) if ws.exists() else None
        if rec is None:
            continue
        srec = records.get(_stage_step_key(row, stage)) or {}
        rec["peak_rss_mib"] = srec.get("peak_rss_mib")
        rec["gpu_peak_mib"] = srec.get("gpu_peak_mib")
        rec["shared"] = stage in row.copy_stages
        stages[stage] = rec
    for split in row.eval_splits:
        srec = records.get(f"{row.id}:eval:{split}") or {}
        stages[f"eval:{split}"] = {"wall_time_s": srec.get("run_wall_s"), "peak_rss_mib": srec.get("peak_rss_mib"),
                                   "gpu_peak_mib": srec.get("gpu_peak_mib"), "measured": "subprocess"}  # fmt: skip
    if row.reenact:
        srec = records.get(f"{row.id}:reenact") or {}
        stages["reenact"] = {"wall_time_s": srec.get("run_wall_s"), "peak_rss_mib": srec.get("peak_rss_mib"),
                             "gpu_peak_mib": srec.get("gpu_peak_mib"), "measured": "subprocess"}  # fmt: skip
    out["stages"] = stages

    metrics: dict[str, Any] = {}
    for split in row.eval_splits:
        names = ("val", "test") if split == "all" else (split,)
        for name in names:
            try:
                metrics[name] = collect.ceiling_metrics(ws, name) if row.ceiling else collect.eval_metrics(ws, row.eval_stage, name)
            except (OSError, ValueError) as e:
                if not any(k.startswith(f"{row.id}:eval:{split}") for k in errors):
                    errors.append(f"{row.id}:eval:{split}: no {name} result ({type(e).__name__})")
    out["metrics"] = metrics
    out["capture_tracking"] = collect.capture_tracking(settings.capture_dir(row.capture))

    if row.has_sdf and "phase1" in stages:
        try:
            out["geometry"] = collect.geometry_vs_gt(ws, settings.capture_dir(row.capture), seed=settings.seed)
        except Exception as e:  # noqa: BLE001
            errors.append(f"geometry: {type(e).__name__}: {e}")
    if row.reenact and not (records.get(f"{row.id}:reenact") or {}).get("error"):
        try:
            out["reenact"] = collect.reenact_record(ws)
        except (OSError, ValueError) as e:
            errors.append(f"reenact: {type(e).__name__}: {e}")
    rss = [s.get("peak_rss_mib") for s in stages.values() if s.get("peak_rss_mib") is not None]
    gpu = [s.get("gpu_peak_mib") for s in stages.values() if s.get("gpu_peak_mib") is not None]
    out["peak_rss_mib"] = max(rss) if rss else None
    out["gpu_peak_mib"] = max(gpu) if gpu else None
    return out
