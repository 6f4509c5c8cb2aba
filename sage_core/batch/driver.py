"""The batch process's bookkeeping (``sage batch``): which subjects to run, their live rows from the
status files, their outcomes, and the summary files. The CLI draws the rows; this module never
prints.

:class:`BatchDriver` skips the subjects that are already finished with the same options, writes the
job files of the others, runs them on an engine (:func:`~sage_core.batch.engines.run_local` with a
:func:`~sage_core.batch.plan.plan_local` sharing, or :func:`~sage_core.batch.engines.run_ray`),
follows their status files while they run and turns each result into a
:class:`~sage_core.batch.summary.SubjectOutcome` (the stage that failed and the whole error line
included). ``on_change(subject_id, row)`` is called whenever a subject's state or stage changes, so
a display without a terminal can print a line per change instead of a live table.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from ..workspace import atomic_write_json
from .engines import Job, JobResult, run_local, run_ray
from .plan import local_gpus, plan_local
from .summary import SubjectOutcome, read_status, stages_wall_time, subject_finished, subject_metrics, write_summary

ChangeFn = Callable[[str, dict[str, Any]], None]
"""``on_change(subject_id, row)``: a subject's row after its state or stage changed."""

DONE_STATES = ("finished", "failed", "skipped", "interrupted")
"""States of a row that no longer changes."""


class BatchDriver:
    """One ``sage batch`` run over the subjects ``specs`` (:func:`~sage_core.batch.specs.subject_spec`)
    with their workspaces under ``root``.

    rows: per subject, what a live table shows: ``state`` (queued, running, finished, skipped,
    failed, interrupted, not run), ``stage`` (the running one, or the one that failed), ``done`` /
    ``total``, ``elapsed`` and ``psnr`` (training PSNR while running, then val or held-out PSNR).
    """

    def __init__(self, root: Path, specs: list[dict[str, Any]], meta: dict[str, Any] | None = None,
                 on_change: ChangeFn | None = None) -> None:  # fmt: skip
        self.root = Path(root)
        self.specs = {s["id"]: s for s in specs}
        self.meta = dict(meta or {})
        self.on_change = on_change
        self.t0 = time.time()
        self.outcomes: dict[str, SubjectOutcome] = {s["id"]: SubjectOutcome(s["id"], "not run", s["ws"]) for s in specs}
        self.rows: dict[str, dict[str, Any]] = {s["id"]: {"state": "queued"} for s in specs}

    # ---------------------------------------------------------------- before the run
    def prepare(self, argv: Callable[[Path], list[str]]) -> list[Job]:
        """The jobs of the subjects that have work to do (the others are marked skipped); each job
        file ``WS/.batch_job.json`` is written, the log goes to ``WS/logs/batch-<UTC time>.log``.
        argv: the worker command of a job file."""
        jobs = []
        for spec in self.specs.values():
            if self.skip_if_finished(spec):
                continue
            ws = Path(spec["ws"])
            job_file = ws / ".batch_job.json"
            atomic_write_json(job_file, spec)
            stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
            jobs.append(Job(spec["id"], ws, argv(job_file), ws / "logs" / f"batch-{stamp}.log"))
        return jobs

    def skip_if_finished(self, spec: dict[str, Any]) -> bool:
        """Mark a subject skipped when all its stages are complete with the same run key."""
        ws = Path(spec["ws"])
        if spec["force"] or not subject_finished(ws, spec["stages"], spec["run_key"]):
            return False
        o = self.outcomes[spec["id"]]
        o.status, o.metrics = "skipped", subject_metrics(ws)
        o.wall_time_s = round(stages_wall_time(ws, spec["stages"]), 3)
        st = read_status(ws)
        self._set(spec["id"], state="skipped", stage="all complete", psnr=_held_out_psnr(o.metrics, st.get("psnr")))
        return True

    # ---------------------------------------------------------------- the run
    def run(self, jobs: list[Job], *, engine: str = "local", address: str | None = None, gpus_per_subject: float | None = None,
            cpus_per_subject: int | None = None, max_parallel: int | None = None, max_retries: int = 2, device: str = "auto",
            cores: int | None = None, on_poll: Callable[[], None] | None = None) -> None:  # fmt: skip
        """Run the jobs on ``engine`` (``local`` or ``ray``) with the batch's sharing options; the rows
        follow the status files while they run, and ``on_poll`` is called after each update."""
        from ..errors import ConfigError
        from ..runtime import available_cores

        if engine not in ("local", "ray"):
            raise ConfigError(f"--engine {engine}: choose local or ray")

        def poll() -> None:
            self.poll()
            if on_poll is not None:
                on_poll()

        if engine == "ray":
            run_ray(jobs, address=address, cpus_per_subject=cpus_per_subject or 1, gpus_per_subject=gpus_per_subject or 0,
                    max_parallel=max_parallel, max_retries=max_retries, on_result=self.on_result, on_poll=poll)  # fmt: skip
            return
        plan = plan_local(cores or available_cores(), local_gpus(device), gpus_per_subject=gpus_per_subject,
                          cpus_per_subject=cpus_per_subject, max_parallel=max_parallel)  # fmt: skip
        run_local(jobs, max_parallel=plan.max_parallel, cpus_per_subject=plan.cpus_per_subject, gpus=plan.gpus,
                  gpus_per_subject=plan.gpus_per_subject, on_result=self.on_result, on_poll=poll)  # fmt: skip

    def poll(self) -> None:
        """Update the rows of the running subjects from their status files."""
        now = time.time()
        for sid, row in self.rows.items():
            if row.get("state") in DONE_STATES:
                continue
            st = read_status(self.specs[sid]["ws"])
            if st.get("state") == "running" and isinstance(st.get("started_at"), (int, float)) and st["started_at"] >= self.t0 - 1:
                self._set(sid, state="running", stage=st.get("stage"), done=st.get("done"), total=st.get("total"), psnr=st.get("psnr"),
                          elapsed=now - st["started_at"])  # fmt: skip

    def on_result(self, res: JobResult) -> None:
        """A subject's worker ended: its outcome from the exit code and its status file."""
        spec = self.specs[res.id]
        o = self.outcomes[res.id]
        st = read_status(spec["ws"])
        o.returncode, o.device, o.wall_time_s, o.attempts = res.returncode, res.device, round(res.wall_time_s, 3), 1
        logs = sorted((Path(spec["ws"]) / "logs").glob("batch-*.log"))
        o.log = str(logs[-1]) if logs else None
        if res.ok and st.get("state") == "finished" and st.get("run_key") == spec["run_key"]:
            o.status, o.error, o.stage = "finished", None, None
            o.metrics = subject_metrics(spec["ws"])
        else:
            state = st.get("state") if st.get("state") in ("failed", "interrupted") else "failed"
            o.status = "interrupted" if state == "interrupted" else "failed"
            o.stage = st.get("failed_stage") or st.get("stage")
            o.error = (st.get("error") if st.get("state") in ("failed", "interrupted") else None) or res.error or f"exit code {res.returncode}"
        row = self.rows[res.id]
        self._set(res.id, state=o.status, stage=o.stage if o.status != "finished" else "done", elapsed=res.wall_time_s,
                  psnr=_held_out_psnr(o.metrics, row.get("psnr")))  # fmt: skip
        self.write()

    def interrupted(self) -> None:
        """The batch was stopped: the running subjects are interrupted (they resume next time)."""
        for sid, o in self.outcomes.items():
            if o.status == "not run":
                st = read_status(self.specs[sid]["ws"])
                running = st.get("state") in ("running", "interrupted") and (st.get("started_at") or 0) >= self.t0 - 1
                o.status = "interrupted" if running else "not run"
                o.stage = st.get("stage") if running else None
                o.error = "the batch was interrupted"
        self.write()

    # ---------------------------------------------------------------- after the run
    def write(self) -> tuple[Path, Path]:
        """Write the summary files (``batch_summary.json``, ``batch_summary.md``); returns their paths."""
        return write_summary(self.root, list(self.outcomes.values()), {**self.meta, "wall_time_s": round(time.time() - self.t0, 3)})

    def unfinished(self) -> list[str]:
        """Subjects that neither finished now nor were finished before."""
        return [o.id for o in self.outcomes.values() if o.status not in ("finished", "skipped")]

    def _set(self, sid: str, **fields: Any) -> None:
        row = self.rows[sid]
        changed = any(row.get(k) != fields.get(k) for k in ("state", "stage") if k in fields)
        row.update(fields)
        if changed and self.on_change is not None:
            self.on_change(sid, dict(row))


def _held_out_psnr(metrics: dict[str, Any], fallback: Any) -> Any:
    """The PSNR a row shows for a done subject: val (novel view), else gt/novel, else test."""
    for key in ("val_psnr", "novel_psnr", "test_psnr"):
        if isinstance(metrics.get(key), (int, float)):
            return metrics[key]
    return fallback
