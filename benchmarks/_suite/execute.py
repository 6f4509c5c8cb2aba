"""Executing a plan: every step once, in order, a failed step failing only what depends on it;
then each row's numbers collected from its workspace."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from sage_core.workspace import Workspace, now_iso

from . import collect
from .rows import ROWS, RowSpec, Settings, Step, row_eval_splits
from .runner import command_line, run_process, sage_argv
from .workspaces import (capture_is_current, ceiling_command, copy_command, copy_stages, motion_command, photo_command, track_is_current,
                         write_photo, write_test_motion)

Log = Callable[[str], None]


def step_command(step: Step) -> str:
    """The shell line that reproduces a step."""
    if step.kind in ("cli", "synth"):
        return command_line(step.argv)
    if step.kind == "track":
        return photo_command(Path(step.argv[1])) + " && " + command_line(step.argv)
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
        if step.kind in ("synth", "track"):  # a capture: kept when it is what the command would write
            assert step.capture is not None
            current = capture_is_current if step.kind == "synth" else track_is_current
            if current(step.capture, step.argv):
                rec.update(rc=0, ran=False, wall_s=time.perf_counter() - t0, note="capture already present")
                return _keep_previous(rec, previous)
            if step.kind == "track":
                write_photo(Path(step.argv[1]))
            argv = list(step.argv) + (["--force"] if step.capture.exists() else [])
            rec["command"] = step_command(replace(step, argv=argv))
            return _run_cli(rec, argv, settings, step, poll_gpu, None)
        if step.kind == "cli":
            ws = settings.for_subject(step.subject).ws(step.row) if step.row else None
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
    log = settings.out / "logs" / (step.key.replace(":", "__").replace("/", "__") + ".log")
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


def _stage_step_key(row: RowSpec, stage: str, st: Settings) -> str:
    """Key of the step that produced ``stage`` of a row's workspace (its base's for copied stages)."""
    if stage in row.copy_stages and row.base is not None:
        return _stage_step_key(ROWS[row.base], stage, st)
    return st.key(f"{row.id}:{stage}")


def collect_row(row: RowSpec, settings: Settings, needs: list[str], records: dict[str, Any]) -> dict[str, Any]:
    """The numbers of one row: per subject (``subjects``) from its workspace and step records, and
    their mean over the subjects at the top level (``metrics``, ``geometry``; counts are summed);
    stage costs and the reenactment are the first subject's. Missing numbers are None; failures are
    listed in ``errors`` (a further subject's prefixed with its seed)."""
    from .rows import row_steps

    subs = []
    for k in range(settings.subjects):
        st = settings.for_subject(k)
        keys = [s.key for s in row_steps(st, row)]
        subs.append(_collect_subject(row, st, keys, records))
    first = subs[0]
    out: dict[str, Any] = {
        "id": row.id, "label": row.label, "input_type": row.input_type, "regime": row.regime, "capture": row.capture,
        "eval_stage": row.eval_stage, "has_sdf": row.has_sdf, "workspace": first["workspace"], "steps": list(needs),
        "shared_from": row.base, "copied_stages": list(row.copy_stages), "finished_at": now_iso(),
        "errors": [e if k == 0 else f"seed {sub['seed']}: {e}" for k, sub in enumerate(subs) for e in sub["errors"]],
    }  # fmt: skip
    out["stages"] = first["stages"]
    out["metrics"] = mean_tree([sub["metrics"] for sub in subs])
    out["capture_tracking"] = first["capture_tracking"]
    geo = [sub["geometry"] for sub in subs if sub.get("geometry")]
    if geo:
        out["geometry"] = mean_tree(geo)
    if first.get("reenact"):
        out["reenact"] = first["reenact"]
    rss = [sub["peak_rss_mib"] for sub in subs if sub.get("peak_rss_mib") is not None]
    gpu = [sub["gpu_peak_mib"] for sub in subs if sub.get("gpu_peak_mib") is not None]
    out["peak_rss_mib"] = max(rss) if rss else None
    out["gpu_peak_mib"] = max(gpu) if gpu else None
    out["subjects"] = subs
    return out


_SUMMED = ("count", "images")
"""Keys of :func:`mean_tree` that add up over the subjects instead of being averaged."""


def mean_tree(docs: list[Any]) -> Any:
    """The mean of equally shaped JSON trees: numbers averaged over the trees that have them (the
    keys of :data:`_SUMMED` summed), dicts merged key by key, anything else taken from the first
    tree that has it; None when no tree has a value."""
    vals = [d for d in docs if d is not None]
    if not vals:
        return None
    if all(isinstance(v, dict) for v in vals):
        keys = list(dict.fromkeys(k for v in vals for k in v))
        out = {}
        for key in keys:
            sub = [v.get(key) for v in vals]
            if key in _SUMMED and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in sub if x is not None):
                nums = [x for x in sub if x is not None]
                out[key] = sum(nums) if nums else None
            else:
                out[key] = mean_tree(sub)
        return out
    nums = [v for v in vals if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if nums and len(nums) == len(vals):
        return float(sum(nums)) / len(nums)
    return vals[0]


def _collect_subject(row: RowSpec, st: Settings, keys: list[str], records: dict[str, Any]) -> dict[str, Any]:
    """A row's numbers on one subject (the settings' subject)."""
    ws = st.ws(row.id)
    out: dict[str, Any] = {"seed": st.capture_seed, "workspace": str(ws), "capture": str(st.capture_dir(row.capture)), "errors": []}
    errors: list[str] = out["errors"]
    for key in keys:
        err = (records.get(key) or {}).get("error")
        if err:
            errors.append(f"{key}: {err}")
    stages: dict[str, Any] = {}
    for stage in STAGE_COLUMNS:
        rec = collect.stage_record(ws, stage) if ws.exists() else None
        if rec is None:
            continue
        srec = records.get(_stage_step_key(row, stage, st)) or {}
        rec["peak_rss_mib"] = srec.get("peak_rss_mib")
        rec["gpu_peak_mib"] = srec.get("gpu_peak_mib")
        rec["shared"] = stage in row.copy_stages
        stages[stage] = rec
    for split in row_eval_splits(st, row):
        srec = records.get(st.key(f"{row.id}:eval:{split}")) or {}
        stages[f"eval:{split}"] = {"wall_time_s": srec.get("run_wall_s"), "peak_rss_mib": srec.get("peak_rss_mib"),
                                   "gpu_peak_mib": srec.get("gpu_peak_mib"), "measured": "subprocess"}  # fmt: skip
    if row.reenact:
        srec = records.get(st.key(f"{row.id}:reenact")) or {}
        stages["reenact"] = {"wall_time_s": srec.get("run_wall_s"), "peak_rss_mib": srec.get("peak_rss_mib"),
                             "gpu_peak_mib": srec.get("gpu_peak_mib"), "measured": "subprocess"}  # fmt: skip
    out["stages"] = stages

    metrics: dict[str, Any] = {}
    for split in row_eval_splits(st, row):
        names = ("val", "test") if split == "all" else (split,)
        for name in names:
            try:
                metrics[name] = collect.ceiling_metrics(ws, name) if row.ceiling else collect.eval_metrics(ws, row.eval_stage, name)
            except (OSError, ValueError) as e:
                if not any(k.startswith(st.key(f"{row.id}:eval:{split}")) for k in errors):
                    errors.append(f"{st.key(f'{row.id}:eval:{split}')}: no {name} result ({type(e).__name__})")
    out["metrics"] = metrics
    out["capture_tracking"] = collect.capture_tracking(st.capture_dir(row.capture))
    out.update(collect.capture_appearance(st.capture_dir(row.capture)))

    if row.has_sdf and "phase1" in stages:
        try:
            out["geometry"] = collect.geometry_vs_gt(ws, st.capture_dir(row.capture), seed=st.seed)
        except Exception as e:  # noqa: BLE001
            errors.append(f"geometry: {type(e).__name__}: {e}")
    if row.reenact and not (records.get(st.key(f"{row.id}:reenact")) or {}).get("error"):
        try:
            out["reenact"] = collect.reenact_record(ws)
        except (OSError, ValueError) as e:
            errors.append(f"reenact: {type(e).__name__}: {e}")
    rss = [s.get("peak_rss_mib") for s in stages.values() if s.get("peak_rss_mib") is not None]
    gpu = [s.get("gpu_peak_mib") for s in stages.values() if s.get("gpu_peak_mib") is not None]
    out["peak_rss_mib"] = max(rss) if rss else None
    out["gpu_peak_mib"] = max(gpu) if gpu else None
    return out
