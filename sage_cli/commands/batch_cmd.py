"""``sage batch SUBJECTS ROOT``: ``sage run`` for many subjects, on a local process pool or a Ray cluster.

Parsing and display only; the engine is :mod:`sage_core.batch` (:class:`~sage_core.batch.BatchDriver`
runs the subjects and writes the summary, :func:`~sage_core.batch.run_subject` is a subject's worker).
Every subject gets the workspace ``ROOT/<id>/`` and runs in its own process, ``python -m
sage_cli.commands.batch_cmd ROOT/<id>/.batch_job.json --device D --cpus C`` (this module's
:func:`worker_main`: the worker with the chain's display, as ``sage run`` shows it, in
``ROOT/<id>/logs/batch-<UTC time>.log``). On a terminal the batch shows a live table; without one it
prints a line whenever a subject's state or stage changes. The summary lists every error in full
and goes to ``ROOT/batch_summary.json`` and ``ROOT/batch_summary.md``.
"""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from .._common import ConfigOpt, ForceOpt, PresetOpt, SeedOpt, SetOpt, VerboseOpt, cli_errors, console, err_console, fmt_metric

WORKER_MODULE = "sage_cli.commands.batch_cmd"
"""The module a subject's worker process runs (``python -m``)."""


# --------------------------------------------------------------------------------------------
# Worker (one subject, in its own process)
# --------------------------------------------------------------------------------------------


def worker_main(argv: list[str] | None = None) -> int:
    """Run one subject from its job file (:func:`sage_core.batch.run_subject`) with the chain's
    display in the subject's log; returns the exit code."""
    import json

    from sage_core.batch import parse_worker_args, read_status, run_subject

    from .run_cmd import ChainDisplay

    args = parse_worker_args(argv, prog=f"python -m {WORKER_MODULE}")
    spec = json.loads(args.job.read_text(encoding="utf-8"))
    ws = Path(spec["ws"])

    def report(e: BaseException, code: int) -> None:
        from sage_core.errors import SageError

        if code == 130:
            err_console.print("interrupted: the subject resumes from its last checkpoint when the batch runs again")
        elif isinstance(e, SageError) or code != 1:
            err_console.print(f"error: {e}", soft_wrap=True, markup=False)
        else:
            import traceback

            traceback.print_exception(e)

    with ChainDisplay(ws, verbose=False, preset=spec.get("preset")) as display:
        code = run_subject(spec, args.device, args.cpus, on_event=display, on_error=report)
    if code == 0:
        for name, outcome in read_status(ws).get("stages") or []:
            console.print(f"{name}: {outcome}")
    return code


# --------------------------------------------------------------------------------------------
# Display
# --------------------------------------------------------------------------------------------


COLORS = {"finished": "green", "skipped": "green", "failed": "red", "interrupted": "red", "running": "yellow", "not run": "magenta"}


def _table(rows: dict[str, dict[str, Any]]) -> Any:
    from rich.table import Table

    t = Table(title="sage batch", expand=False)
    for col, just in (("subject", "left"), ("state", "left"), ("stage", "left"), ("progress", "right"), ("elapsed", "right"), ("PSNR", "right")):
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    for sid, r in rows.items():
        state = r.get("state", "queued")
        done, total = r.get("done"), r.get("total")
        prog = f"{done}/{total}" if total else (str(done) if done else "")
        el = r.get("elapsed")
        t.add_row(sid, f"[{COLORS.get(state, 'white')}]{state}[/]", str(r.get("stage") or ""), prog,
                  f"{el:.0f} s" if isinstance(el, (int, float)) else "", fmt_metric(r.get("psnr"), ".2f"))  # fmt: skip
    return t


def change_line(sid: str, row: dict[str, Any]) -> str:
    """The line a batch without a terminal prints when a subject's state or stage changes."""
    state, stage = row.get("state", "queued"), row.get("stage")
    stamp = time.strftime("%H:%M:%S")
    if state == "running":
        return f"{stamp} {sid}: running {stage or ''}".rstrip()
    if state in ("failed", "interrupted"):
        return f"{stamp} {sid}: {state}" + (f" in {stage}" if stage else "")
    psnr = row.get("psnr")
    extra = f" (PSNR {fmt_metric(psnr, '.2f')} dB)" if isinstance(psnr, (int, float)) else ""
    return f"{stamp} {sid}: {state}{extra}"


class _Display:
    """The batch's progress: a live table on a terminal, else one printed line per change."""

    def __init__(self, verbose: bool) -> None:
        self.verbose = verbose
        self.live = verbose and console.is_terminal
        self._live: Any = None
        self.driver: Any = None

    def on_change(self, sid: str, row: dict[str, Any]) -> None:
        if self.verbose and not self.live:
            console.print(change_line(sid, row), soft_wrap=True, markup=False)

    def start(self) -> None:
        if self.live:
            from rich.live import Live

            self._live = Live(_table(self.driver.rows), console=console, refresh_per_second=2, transient=False)
            self._live.__enter__()

    def refresh(self) -> None:
        if self._live is not None:
            self._live.update(_table(self.driver.rows))

    def close(self) -> None:
        if self._live is not None:
            self.driver.poll()
            self.refresh()
            self._live.__exit__(None, None, None)
            self._live = None


def show_summary(driver: Any, paths: tuple[Path, Path]) -> None:
    """The closing table (PSNR on val, test and gt/novel), then every failure in full."""
    from rich.table import Table

    t = Table(title="sage batch summary")
    for col in ("subject", "status", "stage", "wall time", "val PSNR", "test PSNR", "novel PSNR"):
        t.add_column(col)
    for o in driver.outcomes.values():
        m = o.metrics
        t.add_row(o.id, f"[{COLORS.get(o.status, 'white')}]{o.status}[/]", o.stage or "", f"{o.wall_time_s:.1f} s",
                  fmt_metric(m.get("val_psnr"), ".2f"), fmt_metric(m.get("test_psnr"), ".2f"), fmt_metric(m.get("novel_psnr"), ".2f"))  # fmt: skip
    console.print(t)
    for o in driver.outcomes.values():
        if o.error:
            where = f" in {o.stage}" if o.stage else ""
            console.print(f"{o.id} {o.status}{where}: {o.error}" + (f" (log: {o.log})" if o.log else ""), soft_wrap=True, markup=False)
    jp, mp = paths
    console.print(f"summary: {jp}\n         {mp}", soft_wrap=True, markup=False)


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
    regime: Annotated[Optional[str], typer.Option("--regime", help="Default regime: mv-sf | mv-mf | sv-hr (or monocular) | one-shot (or oneshot).")] = None,
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
        from sage_core.batch import REGIMES, BatchDriver, check_spec, load_subjects, subject_spec, worker_argv
        from sage_core.config import canonical_regime
        from sage_core.errors import ConfigError, SageError
        from sage_core.stages import split_sets

        if engine not in ("local", "ray"):
            raise ConfigError(f"--engine {engine}: choose local or ray")
        if regime is not None:
            regime = canonical_regime(regime)
            if regime not in REGIMES:
                raise ConfigError(f"--regime {regime}: choose {', '.join(REGIMES)}")
        split_sets(set_)  # validates the stage prefixes before anything runs
        subs = load_subjects(subjects)
        opts = {"flame_model": flame_model, "flame_masks": flame_masks, "regime": regime, "downsample": downsample,
                "height": height, "background": background, "sets": set_, "skip_phase2": skip_phase2,
                "lpips_weights": lpips_weights, "preset": preset, "config": config, "seed": seed, "force": force}  # fmt: skip
        root = root.resolve()
        specs = [subject_spec(s, root, opts, subjects) for s in subs]
        for spec in specs:  # every subject's seed and stage configs are checked before anything runs
            check_spec(spec)
        root.mkdir(parents=True, exist_ok=True)
        meta = {"engine": engine, "address": address, "root": str(root), "subjects_file": str(Path(subjects).resolve()),
                "preset": preset, "skip_phase2": skip_phase2}  # fmt: skip
        display = _Display(verbose)
        driver = BatchDriver(root, specs, meta, on_change=display.on_change)
        display.driver = driver
        jobs = driver.prepare(lambda job_file: worker_argv(WORKER_MODULE, job_file))
        driver.write()
        previous = _sigterm_as_interrupt()
        try:
            if jobs:
                display.start()
                driver.run(jobs, engine=engine, address=address, gpus_per_subject=gpus_per_subject, cpus_per_subject=cpus_per_subject,
                           max_parallel=max_parallel, max_retries=max_retries, device=device, on_poll=display.refresh)  # fmt: skip
        except KeyboardInterrupt:
            display.close()
            driver.interrupted()
            raise
        finally:
            display.close()
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
        paths = driver.write()
        show_summary(driver, paths)
        failed = driver.unfinished()
        if failed:
            raise SageError(f"{len(failed)} of {len(driver.outcomes)} subject(s) did not finish: {', '.join(failed)} (see {paths[1]})")


def _sigterm_as_interrupt() -> Any:
    """Make SIGTERM (a scheduler ending the job) stop the batch like Ctrl-C; returns the old handler."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, handler)


if __name__ == "__main__":
    sys.exit(worker_main())
