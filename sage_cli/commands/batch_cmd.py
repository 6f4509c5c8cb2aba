"""``sage batch SUBJECTS ROOT``: ``sage run`` for many subjects, on a local process pool or a Ray cluster.

Every subject gets the workspace ``ROOT/<id>/`` and runs in its own process: ``python -m
sage_cli.commands.batch_cmd ROOT/<id>/.batch_job.json --device D --cpus C`` (this module's
worker), which runs :func:`sage_core.stages.run_pipeline` and shows it as ``sage run`` does, with
stdout/stderr in ``ROOT/<id>/logs/batch-<UTC time>.log``. The worker keeps
``ROOT/<id>/.batch_status.json`` up to date (stage, progress, elapsed, PSNR) from the stages' events
(:class:`sage_core.batch.StatusWriter`); the batch process polls these files for its live table and
reads each subject's metrics from its eval manifest. A subject whose stages are all complete with the same batch
options is skipped without starting a process; a failed subject does not stop the others; the
summary goes to ``ROOT/batch_summary.json`` and ``ROOT/batch_summary.md``.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from .._common import ConfigOpt, ForceOpt, PresetOpt, SeedOpt, SetOpt, VerboseOpt, cli_errors, console, err_console, fmt_metric


# --------------------------------------------------------------------------------------------
# Worker (one subject, in its own process)
# --------------------------------------------------------------------------------------------


def worker_main(argv: list[str] | None = None) -> int:
    """Run one subject's pipeline from its job file; returns the exit code."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m sage_cli.commands.batch_cmd", description="sage batch worker: one subject")
    ap.add_argument("job", type=Path)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--cpus", type=int, default=0)
    a = ap.parse_args(argv)
    spec = json.loads(a.job.read_text(encoding="utf-8"))
    ws = Path(spec["ws"])

    from sage_core.batch import StatusWriter, subject_metrics, write_status
    from sage_core.errors import SageError

    if a.cpus > 0:
        from sage_core.runtime import THREADS_ENV, apply_threads

        os.environ[THREADS_ENV] = str(apply_threads(a.cpus))
    _watch_parent()
    t0 = time.time()
    write_status(ws, state="running", stage=None, done=0, total=None, message="", psnr=None, started_at=t0, pid=os.getpid(),
                 device=a.device, error=None, run_key=None)  # fmt: skip
    from .run_cmd import run_chain

    def opt(key: str) -> Path | None:
        return None if spec.get(key) is None else Path(spec[key])

    try:
        with cli_errors():  # other failures are shown and mapped to exit codes as `sage run` does
            try:
                res = run_chain(
                    Path(spec["dataset"]), ws, Path(spec["flame_model"]), flame_masks=opt("flame_masks"),
                    ingest_flags=spec["ingest_flags"], skip_phase2=spec["skip_phase2"], lpips_weights=opt("lpips_weights"),
                    preset=spec["preset"], config=opt("config"), sets=spec["sets"], seed=spec["seed"], device=a.device,
                    force=spec["force"], verbose=False, on_event=StatusWriter(ws),
                )  # fmt: skip
            except SageError as e:
                err_console.print(f"error: {e}", soft_wrap=True, markup=False)
                write_status(ws, state="failed", error=str(e), elapsed_s=time.time() - t0)
                return e.exit_code
    except typer.Exit as e:  # an interrupt, an out-of-memory or a file-system refusal, printed by cli_errors
        code = int(getattr(e, "exit_code", 1) or 0)
        state = "interrupted" if code == 130 else "failed"
        write_status(ws, state=state, error="interrupted" if code == 130 else f"exit code {code}", elapsed_s=time.time() - t0)
        return code or 1
    except KeyboardInterrupt:
        err_console.print("interrupted: the subject resumes from its last checkpoint when the batch runs again")
        write_status(ws, state="interrupted", error="interrupted", elapsed_s=time.time() - t0)
        return 130
    except BaseException as e:
        import traceback

        traceback.print_exc()
        line = f"{type(e).__name__}: {e}".splitlines()[0]
        write_status(ws, state="failed", error=line, elapsed_s=time.time() - t0)
        return 1
    metrics = subject_metrics(ws)
    for name, outcome in res.stages:
        console.print(f"{name}: {outcome}")
    write_status(ws, state="finished", run_key=spec["run_key"], metrics=metrics, elapsed_s=time.time() - t0, stages=res.stages)
    return 0


def _watch_parent(poll_s: float = 2.0, grace_s: float = 60.0) -> None:
    """Stop this subject (as if by Ctrl-C) when the process that started it dies, so a killed
    batch or a lost Ray worker leaves no orphan training; exit hard if that does not end it."""
    import _thread
    import threading

    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        _thread.interrupt_main()
        time.sleep(grace_s)
        os._exit(130)

    threading.Thread(target=watch, name="sage-batch-parent-watch", daemon=True).start()


# --------------------------------------------------------------------------------------------
# Live table
# --------------------------------------------------------------------------------------------


def _table(rows: dict[str, dict[str, Any]]) -> Any:
    from rich.table import Table

    t = Table(title="sage batch", expand=False)
    for col, just in (("subject", "left"), ("state", "left"), ("stage", "left"), ("progress", "right"), ("elapsed", "right"), ("PSNR", "right")):
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    colors = {"finished": "green", "skipped": "green", "failed": "red", "running": "yellow", "not run": "magenta"}
    for sid, r in rows.items():
        state = r.get("state", "queued")
        done, total = r.get("done"), r.get("total")
        prog = f"{done}/{total}" if total else (str(done) if done else "")
        el = r.get("elapsed")
        psnr = r.get("psnr")
        t.add_row(sid, f"[{colors.get(state, 'white')}]{state}[/]", str(r.get("stage") or ""), prog,
                  f"{el:.0f} s" if isinstance(el, (int, float)) else "", fmt_metric(psnr, ".2f"))  # fmt: skip
    return t


# --------------------------------------------------------------------------------------------
# Command
# --------------------------------------------------------------------------------------------


def batch(
    subjects: Annotated[Path, typer.Argument(help="Subjects: a CSV or YAML file (id, capture, regime, timestep, camera, flame_model, flame_masks, set) or a folder of capture folders.")],
    root: Annotated[Path, typer.Argument(help="Output root: each subject's workspace is ROOT/<id>/.")],
    engine: Annotated[str, typer.Option("--engine", help="local (process pool on this machine) or ray (Ray cluster).")] = "local",
    address: Annotated[Optional[str], typer.Option("--address", help="Ray cluster to join (e.g. HEAD:6379 or auto); default: start a local Ray.")] = None,
    gpus_per_subject: Annotated[Optional[float], typer.Option("--gpus-per-subject", help="GPUs per subject (local default 1 when GPUs are used; ray default 0).")] = None,
    cpus_per_subject: Annotated[Optional[int], typer.Option("--cpus-per-subject", help="CPU threads per subject (default: the machine's CPUs shared out; ray: 1).")] = None,
    max_parallel: Annotated[Optional[int], typer.Option("--max-parallel", help="Subjects running at once (default: one per GPU, or CPUs / --cpus-per-subject).")] = None,
    max_retries: Annotated[int, typer.Option("--max-retries", help="Ray: retries of a subject whose worker was lost.")] = 2,
    flame_model: Annotated[Optional[Path], typer.Option("--flame-model", help="FLAME model for subjects without a flame_model field.")] = None,
    flame_masks: Annotated[Optional[Path], typer.Option("--flame-masks", help="FLAME_masks.pkl for subjects without a flame_masks field.")] = None,
    regime: Annotated[Optional[str], typer.Option("--regime", help="Default regime: mv-sf | mv-mf | sv-hr | one-shot.")] = None,
    downsample: Annotated[Optional[float], typer.Option("--downsample", help="Divide the image size by this factor.")] = None,
    height: Annotated[Optional[int], typer.Option("--height", help="Resize images to this height in pixels.")] = None,
    background: Annotated[Optional[str], typer.Option("--background", help="white (as exported) or black.")] = None,
    skip_phase2: Annotated[bool, typer.Option("--skip-phase2", help="Stop training after phase 1.")] = False,
    lpips_weights: Annotated[Optional[Path], typer.Option("--lpips-weights", help="LPIPS AlexNet v0.1 weights for the evaluations.")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: Annotated[str, typer.Option("--device", help="local engine: auto, cpu, cuda (all visible GPUs) or cuda:N.")] = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
) -> None:
    """Run `sage run` for every subject (ROOT/<id>/ each), locally or on Ray; finished subjects are skipped, failed ones do not stop the others."""
    with cli_errors():
        from sage_core.batch import REGIMES, Job, load_subjects
        from sage_core.errors import ConfigError
        from sage_core.workspace import atomic_write_json

        from sage_core.batch import subject_spec
        from sage_core.stages import StageSettings, pipeline_configs, split_sets

        from .run_cmd import stage_flags

        if engine not in ("local", "ray"):
            raise ConfigError(f"--engine {engine}: choose local or ray")
        if regime is not None and regime not in REGIMES:
            raise ConfigError(f"--regime {regime}: choose {', '.join(REGIMES)}")
        split_sets(set_)  # validates the stage prefixes before anything runs
        subs = load_subjects(subjects)
        opts = {"flame_model": flame_model, "flame_masks": flame_masks, "regime": regime, "downsample": downsample,
                "height": height, "background": background, "sets": set_, "skip_phase2": skip_phase2,
                "lpips_weights": lpips_weights, "preset": preset, "config": config, "seed": seed, "force": force}  # fmt: skip
        root = root.resolve()
        specs = [subject_spec(s, root, opts, subjects) for s in subs]
        StageSettings(seed=seed)  # checks the seed
        for spec in specs:  # every subject's stage configs are resolved and checked before anything runs
            flags = stage_flags(spec["sets"])
            flags["ingest"] = {**spec["ingest_flags"], **flags.get("ingest", {})}
            pipeline_configs(spec["preset"], spec["config"], flags, spec["skip_phase2"])
        root.mkdir(parents=True, exist_ok=True)
        runner = _BatchRun(root, specs, verbose)
        jobs = []
        for spec in specs:
            if runner.skip_if_finished(spec):
                continue
            ws = Path(spec["ws"])
            job_file = ws / ".batch_job.json"
            atomic_write_json(job_file, spec)
            stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
            argv = ["{python}", "-m", "sage_cli.commands.batch_cmd", str(job_file), "--device", "{device}", "--cpus", "{cpus}"]
            jobs.append(Job(spec["id"], ws, argv, ws / "logs" / f"batch-{stamp}.log"))
        meta = {"engine": engine, "address": address, "root": str(root), "subjects_file": str(Path(subjects).resolve()),
                "preset": preset, "skip_phase2": skip_phase2}  # fmt: skip
        runner.meta = meta
        runner.write()
        previous = _sigterm_as_interrupt()
        try:
            if jobs:
                runner.run(jobs, engine=engine, address=address, gpus_per_subject=gpus_per_subject, cpus_per_subject=cpus_per_subject,
                           max_parallel=max_parallel, max_retries=max_retries, device=device)  # fmt: skip
        except KeyboardInterrupt:
            runner.interrupted()
            raise
        finally:
            runner.close()
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        runner.finish()


def _sigterm_as_interrupt() -> Any:
    """Make SIGTERM (a scheduler ending the job) stop the batch like Ctrl-C; returns the old handler."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, handler)


class _BatchRun:
    """The batch process's bookkeeping: outcomes, live rows, summary files."""

    def __init__(self, root: Path, specs: list[dict[str, Any]], verbose: bool) -> None:
        from sage_core.batch import SubjectOutcome

        self.root = root
        self.specs = {s["id"]: s for s in specs}
        self.verbose = verbose
        self.meta: dict[str, Any] = {}
        self.t0 = time.time()
        self.outcomes: dict[str, SubjectOutcome] = {s["id"]: SubjectOutcome(s["id"], "not run", s["ws"]) for s in specs}
        self.rows: dict[str, dict[str, Any]] = {s["id"]: {"state": "queued"} for s in specs}
        self._live: Any = None

    def skip_if_finished(self, spec: dict[str, Any]) -> bool:
        from sage_core.batch import read_status, stages_wall_time, subject_finished, subject_metrics

        ws = Path(spec["ws"])
        if spec["force"] or not subject_finished(ws, spec["stages"], spec["run_key"]):
            return False
        o = self.outcomes[spec["id"]]
        o.status, o.metrics = "skipped", subject_metrics(ws)
        o.wall_time_s = round(stages_wall_time(ws, spec["stages"]), 3)
        st = read_status(ws)
        self.rows[spec["id"]] = {"state": "skipped", "stage": "all complete", "psnr": o.metrics.get("val_psnr") or st.get("psnr")}
        return True

    def run(self, jobs: list[Any], *, engine: str, address: str | None, gpus_per_subject: float | None, cpus_per_subject: int | None,
            max_parallel: int | None, max_retries: int, device: str) -> None:  # fmt: skip
        from sage_core.batch import run_local, run_ray
        from sage_core.errors import ConfigError
        from sage_core.runtime import available_cores, threads_per_worker

        ncpu = available_cores()
        if self.verbose:
            from rich.live import Live

            self._live = Live(_table(self.rows), console=console, refresh_per_second=2, transient=False)
            self._live.__enter__()
        if engine == "ray":
            run_ray(jobs, address=address, cpus_per_subject=cpus_per_subject or 1, gpus_per_subject=gpus_per_subject or 0,
                    max_parallel=max_parallel, max_retries=max_retries, on_result=self.on_result, on_poll=self.poll)  # fmt: skip
            return
        gpus = _local_gpus(device)
        if gpus:
            g = int(gpus_per_subject or 1)
            if g < 1 or g != (gpus_per_subject or 1):
                raise ConfigError("--gpus-per-subject must be a whole number of at least 1 for the local engine on GPUs")
            slots = max(1, len(gpus) // g)
            n = min(max_parallel or slots, slots)
            c = cpus_per_subject or threads_per_worker(n, ncpu)
        else:
            g = 1
            if cpus_per_subject is None and max_parallel is None:
                c = min(4, ncpu)
                n = max(1, ncpu // c)
            else:
                c = cpus_per_subject or threads_per_worker(max_parallel or 1, ncpu)
                n = max_parallel or max(1, ncpu // c)
        run_local(jobs, max_parallel=n, cpus_per_subject=c, gpus=gpus, gpus_per_subject=g, on_result=self.on_result, on_poll=self.poll)

    def poll(self) -> None:
        from sage_core.batch import read_status

        now = time.time()
        for sid, row in self.rows.items():
            if row.get("state") in ("finished", "failed", "skipped"):
                continue
            st = read_status(self.specs[sid]["ws"])
            if st.get("state") == "running" and isinstance(st.get("started_at"), (int, float)) and st["started_at"] >= self.t0 - 1:
                row.update(state="running", stage=st.get("stage"), done=st.get("done"), total=st.get("total"), psnr=st.get("psnr"),
                           elapsed=now - st["started_at"])  # fmt: skip
        if self._live is not None:
            self._live.update(_table(self.rows))

    def on_result(self, res: Any) -> None:
        from sage_core.batch import read_status, subject_metrics

        spec = self.specs[res.id]
        o = self.outcomes[res.id]
        st = read_status(spec["ws"])
        o.returncode, o.device, o.wall_time_s, o.attempts = res.returncode, res.device, round(res.wall_time_s, 3), 1
        o.log = None
        logs = sorted((Path(spec["ws"]) / "logs").glob("batch-*.log"))
        if logs:
            o.log = str(logs[-1])
        if res.ok and st.get("state") == "finished" and st.get("run_key") == spec["run_key"]:
            o.status, o.error = "finished", None
            o.metrics = subject_metrics(spec["ws"])
        else:
            o.status = "failed"
            o.error = (st.get("error") if st.get("state") in ("failed", "interrupted") else None) or res.error or f"exit code {res.returncode}"
        row = self.rows[res.id]
        row.update(state=o.status, elapsed=res.wall_time_s, psnr=o.metrics.get("val_psnr", row.get("psnr")))
        self.write()

    def write(self) -> tuple[Path, Path]:
        from sage_core.batch import write_summary

        return write_summary(self.root, list(self.outcomes.values()), {**self.meta, "wall_time_s": round(time.time() - self.t0, 3)})

    def interrupted(self) -> None:
        from sage_core.batch import read_status

        for sid, o in self.outcomes.items():
            if o.status == "not run":
                st = read_status(self.specs[sid]["ws"])
                running = st.get("state") in ("running", "interrupted") and (st.get("started_at") or 0) >= self.t0 - 1
                o.status = "interrupted" if running else "not run"
                o.error = "the batch was interrupted"
        self.close()
        self.write()

    def close(self) -> None:
        if self._live is not None:
            self.poll()
            self._live.__exit__(None, None, None)
            self._live = None

    def finish(self) -> None:
        from rich.table import Table

        from sage_core.errors import SageError

        jp, mp = self.write()
        if self.verbose and not console.is_terminal:
            console.print()
        t = Table(title="sage batch summary")
        for col in ("subject", "status", "wall time", "val PSNR", "test PSNR", "error"):
            t.add_column(col)
        for o in self.outcomes.values():
            vp, tp = o.metrics.get("val_psnr"), o.metrics.get("test_psnr")
            t.add_row(o.id, o.status, f"{o.wall_time_s:.1f} s", fmt_metric(vp, ".2f"), fmt_metric(tp, ".2f"), o.error or "")
        console.print(t)
        console.print(f"summary: {jp}\n         {mp}")
        failed = [o.id for o in self.outcomes.values() if o.status != "finished" and o.status != "skipped"]
        if failed:
            raise SageError(f"{len(failed)} of {len(self.outcomes)} subject(s) did not finish: {', '.join(failed)} (see {mp})")


def _local_gpus(device: str) -> list[int]:
    """GPU indices the local engine shares out for ``--device``."""
    from sage_core.batch import visible_gpus
    from sage_core.errors import ConfigError

    if device == "cpu":
        return []
    if device == "auto":
        return visible_gpus()
    if device == "cuda":
        g = visible_gpus()
        if not g:
            raise ConfigError("--device cuda: CUDA is not available on this machine (use --device cpu or auto)")
        return g
    if device.startswith("cuda:") and device[5:].isdigit():
        idx = int(device[5:])
        if idx not in visible_gpus():
            raise ConfigError(f"--device {device}: no such CUDA device")
        return [idx]
    raise ConfigError(f"--device {device}: expected auto, cpu, cuda or cuda:N")


if __name__ == "__main__":
    sys.exit(worker_main())
