"""One batch subject in its own process: its chain from the job file, its status file, its exit code.

The batch starts ``python -m <worker module> JOB --device D --cpus C`` for every subject that has
work to do (the module is the CLI's, which adds the chain's display to the subject's log; the
engine never prints). :func:`run_subject` sizes the threads, stops the subject when the batch
process that started it dies (:func:`watch_parent`), runs :func:`sage_core.stages.run_pipeline`
with a :class:`~sage_core.batch.progress.StatusWriter`, and maps how it ended to the exit code and
the status file's state (:func:`exit_state`): 0 finished, 130 interrupted (it resumes from its last
checkpoint when the batch runs again), anything else failed, with the stage that failed and the
error.
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..errors import EXIT_INTERRUPTED, exit_code_of
from ..stages.events import EventFn, StageEvent
from .progress import StatusWriter
from .summary import read_status, subject_metrics, write_status

ErrorFn = Callable[[BaseException, int], None]
"""``on_error(exception, exit_code)``: how the worker's caller reports a subject's failure (its log)."""


def exit_state(code: int) -> str:
    """The status-file state of a subject whose worker ended with ``code``."""
    if code == 0:
        return "finished"
    return "interrupted" if code == EXIT_INTERRUPTED else "failed"


def error_text(e: BaseException, code: int) -> str:
    """The status file's one-line error of a failure (the whole line: paths are never cut)."""
    if code == EXIT_INTERRUPTED:
        return "interrupted"
    from ..errors import SageError

    text = str(e) if isinstance(e, SageError) else f"{type(e).__name__}: {e}"
    lines = text.strip().splitlines()
    return lines[0] if lines else type(e).__name__


def watch_parent(poll_s: float = 2.0, grace_s: float = 60.0, interrupt: Callable[[], None] | None = None) -> threading.Thread:
    """Stop this process (as if by Ctrl-C) when the process that started it dies, so a killed batch
    or a lost Ray worker leaves no orphan training; exit hard if that does not end it within
    ``grace_s``. Returns the (daemon) watching thread."""
    import _thread

    parent = os.getppid()
    stop = interrupt or _thread.interrupt_main

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        stop()
        time.sleep(grace_s)
        os._exit(EXIT_INTERRUPTED)

    t = threading.Thread(target=watch, name="sage-batch-parent-watch", daemon=True)
    t.start()
    return t


@dataclass(frozen=True)
class WorkerArgs:
    """A worker's command line: the job file, the subject's device and its CPU threads (0: the
    process's default)."""

    job: Path
    device: str = "auto"
    cpus: int = 0


def parse_worker_args(argv: list[str] | None, prog: str = "sage batch worker") -> WorkerArgs:
    """Read ``JOB [--device D] [--cpus C]`` (the argv the batch's :class:`~sage_core.batch.engines.Job` gives)."""
    ap = argparse.ArgumentParser(prog=prog, description="sage batch worker: one subject")
    ap.add_argument("job", type=Path)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--cpus", type=int, default=0)
    a = ap.parse_args(argv)
    return WorkerArgs(a.job, a.device, a.cpus)


def worker_argv(module: str, job_file: Path) -> list[str]:
    """The job argv of a subject whose worker is ``python -m module`` (placeholders of
    :func:`~sage_core.batch.engines.run_job`)."""
    return ["{python}", "-m", module, str(job_file), "--device", "{device}", "--cpus", "{cpus}"]


def run_subject(
    spec: dict[str, Any],
    device: str = "auto",
    cpus: int = 0,
    *,
    on_event: EventFn | None = None,
    on_error: ErrorFn | None = None,
    watch: bool = True,
) -> int:
    """Run one subject's chain (``spec``: the job file's content, :func:`~sage_core.batch.specs.subject_spec`)
    and return its exit code, keeping ``WS/.batch_status.json`` up to date.

    cpus: the subject's threads (0: the process's default); on_event: also receives the stages'
    events (the CLI's display); on_error: told of a failure before its status is written; watch:
    stop when the parent process dies (:func:`watch_parent`).
    """
    from ..runtime import THREADS_ENV, apply_threads
    from ..stages import StageSettings, run_pipeline

    ws = Path(spec["ws"])
    if cpus > 0:
        os.environ[THREADS_ENV] = str(apply_threads(cpus))
    if watch:
        watch_parent()
    t0 = time.time()
    write_status(ws, state="running", stage=None, done=0, total=None, message="", psnr=None, started_at=t0, pid=os.getpid(),
                 device=device, error=None, run_key=None)  # fmt: skip
    status = StatusWriter(ws)

    def events(ev: StageEvent) -> None:
        status(ev)
        if on_event is not None:
            on_event(ev)

    def opt(key: str) -> Path | None:
        return None if spec.get(key) is None else Path(spec[key])

    flags = spec_flags(spec)
    try:
        res = run_pipeline(
            Path(spec["dataset"]), ws, Path(spec["flame_model"]), flame_masks=opt("flame_masks"), skip_phase2=spec["skip_phase2"],
            lpips_weights=opt("lpips_weights"), preset=spec["preset"], config_file=opt("config"), flags=flags,
            settings=StageSettings(spec["seed"], device, spec["force"], None), on_event=events,
        )  # fmt: skip
    except BaseException as e:  # every way a subject ends goes into its status file
        code = exit_code_of(e)
        if on_error is not None:
            on_error(e, code)
        write_status(ws, state=exit_state(code), failed_stage=read_status(ws).get("stage"), error=error_text(e, code),
                     elapsed_s=time.time() - t0)  # fmt: skip
        return code
    write_status(ws, state="finished", run_key=spec["run_key"], metrics=subject_metrics(ws), elapsed_s=time.time() - t0,
                 stages=res.stages, failed_stage=None)  # fmt: skip
    return 0


def spec_flags(spec: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The per-stage config flags of a subject's job (its ``sets`` and ``ingest_flags``)."""
    flags = {stage: _parse_sets(values) for stage, values in (spec.get("sets") or {}).items()}
    flags["ingest"] = {**(spec.get("ingest_flags") or {}), **flags.get("ingest", {})}
    return flags


def check_spec(spec: dict[str, Any]) -> None:
    """ConfigError when a subject's seed or any of its stage configs is invalid (nothing runs)."""
    from ..stages import StageSettings, pipeline_configs

    StageSettings(seed=spec["seed"])
    pipeline_configs(spec["preset"], spec.get("config"), spec_flags(spec), spec["skip_phase2"])


def _parse_sets(values: list[str]) -> dict[str, Any]:
    """``["a.b=1"]`` -> ``{"a.b": "1"}`` (the job's per-stage lists were validated by ``split_sets``)."""
    out: dict[str, Any] = {}
    for v in values:
        k, _, val = v.partition("=")
        out[k.strip()] = val.strip()
    return out
