"""Running one workspace stage from the CLI: config, lock, skip/resume, log, progress, panel."""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ._common import ProgressDisplay, console, setup_logging


@dataclass
class StageOptions:
    """The options every stage command shares."""

    ws: Path
    preset: str
    config_file: Path | None
    seed: int
    device: str
    force: bool
    verbose: bool
    threads: int | None = None  # --threads (None: $SAGE_THREADS, else the idle cores)


def execute_stage(
    stage: str,
    opts: StageOptions,
    cfg: Any,
    body: Callable[[Any, ProgressDisplay], None],
    *,
    requires: tuple[str, ...] = (),
    external_inputs: dict[str, str] | None = None,
    title: str | None = None,
    validate: Callable[[], None] | None = None,
    remove_new_workspace_on_failure: bool = False,
    discard_work_on_failure: bool = False,
) -> dict[str, Any] | None:
    """Run ``body(run, progress)`` as stage ``stage`` of workspace ``opts.ws``.

    ``validate`` runs first, before anything is written. Returns the manifest, or None when the
    stage was skipped (already complete with the same config and inputs). ``body`` writes into
    ``run.work_dir`` and fills ``run.metrics`` / ``run.outputs``; it must not call ``finish``.
    A failure keeps the work folder (and its checkpoints) for a resume, or discards it with
    ``discard_work_on_failure``; a workspace created by this call is removed again on failure
    with ``remove_new_workspace_on_failure``.
    """
    from sage_core.config import config_hash, to_dict
    from sage_core.workspace import Workspace, begin_stage, resolve_device

    from sage_core.runtime import apply_threads, resolve_render_backend

    device = resolve_device(opts.device)
    threads = apply_threads(opts.threads)
    backend = resolve_render_backend(cfg.render_backend, device) if hasattr(cfg, "render_backend") else None
    if validate is not None:
        validate()
    existed = opts.ws.exists()
    ws = Workspace(opts.ws)
    ws.root.mkdir(parents=True, exist_ok=True)
    try:
        with ws.lock:
            run = begin_stage(
                ws,
                stage,
                to_dict(cfg),
                config_hash(cfg),
                requires=list(requires),
                external_inputs=external_inputs,
                seed=opts.seed,
                device=device,
                force=opts.force,
            )
            if run is None:
                m = ws.manifest(stage) or {}
                console.print(
                    f"[green]{stage}[/]: already complete with the same config and inputs "
                    f"(finished {m.get('finished_at', '?')}); skipping. Use --force to redo it."
                )
                return None
            run.metrics["threads"] = threads
            if backend is not None:
                run.metrics["render_backend"] = backend
            log_path = setup_logging(ws.root, stage, opts.verbose)
            log = logging.getLogger("sage")
            log.info("stage %s started: config %s, seed %s, device %s, resumed %s, threads %s, render backend %s",
                     stage, run.config_hash, opts.seed, device, run.resumed, threads, backend)  # fmt: skip
            if run.resumed:
                console.print(f"[yellow]{stage}[/]: resuming an interrupted run")
            try:
                with ProgressDisplay(title or stage, enabled=opts.verbose, device=device, preset=opts.preset) as progress:
                    body(run, progress)
            except BaseException as e:
                log.exception("stage %s failed", stage)
                if discard_work_on_failure:
                    shutil.rmtree(run.work_dir, ignore_errors=True)
                else:
                    run.fail(f"{type(e).__name__}: {e}")
                raise
            manifest = run.finish()
            log.info("stage %s complete: %s", stage, manifest.get("metrics"))
            if log_path is not None:
                log.info("log written to %s", log_path)
            return manifest
    except BaseException:
        if remove_new_workspace_on_failure and not existed and ws.root.exists():
            shutil.rmtree(ws.root, ignore_errors=True)
        raise
