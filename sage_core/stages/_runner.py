"""Running one workspace stage: device and threads, lock, skip / resume, log file, events, manifest."""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..errors import ConfigError
from ..workspace import StageRun, Workspace
from .events import Emitter



HASHGRID_STAGES = frozenset({"init-mesh", "phase1", "phase2", "eval", "export"})
"""Stages that evaluate the hash grids; their manifests record the hash-grid backend that ran
(``cpp`` or ``torch``, :func:`sage_core.fields.hashgrid.resolve_backend`)."""

@dataclass(frozen=True)
class StageSettings:
    """What every stage run shares besides its config: seed (recorded in the manifest), device
    (``auto``, ``cpu``, ``cuda[:N]``), ``force`` (redo a finished stage) and CPU threads (None:
    ``$SAGE_THREADS``, else the idle cores)."""

    seed: int = 0
    device: str = "auto"
    force: bool = False
    threads: int | None = None

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < 2**32:
            raise ConfigError(f"--seed must be an integer in 0..{2**32 - 1}, got {self.seed!r}")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1):
            raise ConfigError(f"--threads = {self.threads!r} is out of range (allowed: integers >= 1)")


@dataclass
class StageResult:
    """What a stage run did.

    skipped: already complete with the same config and inputs (nothing was run). resumed: the run
    continued an interrupted one from its checkpoint. manifest: the stage's manifest (on a skip, the
    one already there). metrics: the manifest's key numbers. outputs: the files written (name ->
    path; relative to the workspace in the manifest). device / render_backend / threads: where it ran. duration_s: wall time of this call.
    """

    stage: str
    workspace: Path
    skipped: bool = False
    resumed: bool = False
    manifest: dict[str, Any] | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    outputs: dict[str, Path] = field(default_factory=dict)
    device: str | None = None
    render_backend: str | None = None
    threads: int | None = None
    duration_s: float = 0.0

    @property
    def wall_time_s(self) -> float:
        """The stage's own wall time from its manifest (0 when there is none)."""
        return float((self.manifest or {}).get("wall_time_s") or 0.0)

    def fill(self, manifest: dict[str, Any] | None, t0: float) -> None:
        """Take metrics, outputs and device from ``manifest`` and set the duration since ``t0``."""
        self.manifest = manifest
        if manifest is not None:
            self.metrics = dict(manifest.get("metrics") or {})
            # manifests written since outputs became workspace-relative hold relative paths
            self.outputs = {k: self.workspace / v for k, v in (manifest.get("outputs") or {}).items() if v}
            self.device = manifest.get("device", self.device)
        self.duration_s = time.time() - t0


def as_workspace(ws: str | Path | Workspace) -> Workspace:
    """A :class:`Workspace` for a path (or the object itself)."""
    return ws if isinstance(ws, Workspace) else Workspace(ws)


def setup_logging(ws_root: Path | None, stage: str) -> Path | None:
    """Log file ``WS/logs/<stage>-<UTC time>.log`` for the ``sage`` logger (replacing an earlier
    stage's file handler); returns its path (None without a workspace)."""
    logger = logging.getLogger("sage")
    logger.setLevel(logging.DEBUG)
    for h in list(logger.handlers):
        if getattr(h, "_sage_file", False):
            logger.removeHandler(h)
            h.close()
    if ws_root is None:
        return None
    logs = ws_root / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    path = logs / f"{stage}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}.log"
    fh = logging.FileHandler(path, encoding="utf-8")
    fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    fh._sage_file = True  # type: ignore[attr-defined]
    logger.addHandler(fh)
    return path


@dataclass
class Outcome:
    """What :func:`execute_stage` returns: the manifest (None when skipped) and the run's settings."""

    manifest: dict[str, Any] | None
    device: str
    threads: int
    render_backend: str | None
    resumed: bool = False


def execute_stage(
    stage: str,
    ws: Workspace,
    cfg: Any,
    body: Callable[[StageRun, Emitter], None],
    settings: StageSettings,
    emitter: Emitter,
    *,
    requires: tuple[str, ...] = (),
    external_inputs: dict[str, str] | None = None,
    validate: Callable[[], None] | None = None,
    remove_new_workspace_on_failure: bool = False,
    discard_work_on_failure: bool = False,
) -> Outcome:
    """Run ``body(run, emitter)`` as stage ``stage`` of ``ws``.

    ``validate`` runs first, before anything is written. The manifest is None when the stage was
    skipped (complete with the same config and inputs; a ``skipped`` event says so). ``body``
    writes into ``run.work_dir`` and fills ``run.metrics`` / ``run.outputs``; it must not call
    ``finish``. A failure keeps the work folder (and its checkpoints) for a resume, or discards it
    with ``discard_work_on_failure``; a workspace created by this call is removed again on failure
    with ``remove_new_workspace_on_failure``.
    """
    from ..config import config_hash, to_dict
    from ..runtime import apply_thread_choice, resolve_render_backend
    from ..workspace import begin_stage, resolve_device, stage_up_to_date

    device = resolve_device(settings.device)
    choice = apply_thread_choice(settings.threads)
    threads = choice.threads
    backend = resolve_render_backend(cfg.render_backend, device) if hasattr(cfg, "render_backend") else None
    if validate is not None:
        validate()

    def skipped() -> Outcome:
        m = ws.manifest(stage) or {}
        emitter.emit("skipped", message=f"already complete with the same config and inputs (finished {m.get('finished_at', '?')}); "
                                        "skipping. Use --force to redo it.")  # fmt: skip
        return Outcome(None, device, threads, backend)

    # an up-to-date stage is skipped without the lock, so another stage may be running meanwhile
    if not settings.force and stage_up_to_date(ws, stage, config_hash(cfg), requires=list(requires), external_inputs=external_inputs,
                                               seed=settings.seed):  # fmt: skip
        return skipped()
    existed = ws.root.exists()
    ws.root.mkdir(parents=True, exist_ok=True)
    try:
        with ws.lock:
            run = begin_stage(ws, stage, to_dict(cfg), config_hash(cfg), requires=list(requires), external_inputs=external_inputs,
                              seed=settings.seed, device=device, force=settings.force)  # fmt: skip
            if run is None:
                return skipped()
            run.metrics["threads"] = threads
            if backend is not None:
                run.metrics["render_backend"] = backend
            if stage in HASHGRID_STAGES:
                from ..fields.hashgrid import resolve_backend as resolve_hashgrid_backend
                from ..fields.sdf import resolve_fused_backend

                run.metrics["hashgrid_backend"] = resolve_hashgrid_backend("auto", device)
                run.metrics["sdf_backend"] = resolve_fused_backend("auto", device)
            log_path = setup_logging(ws.root, stage)
            log = logging.getLogger("sage")
            log.info("stage %s started: config %s, seed %s, device %s, resumed %s, %s, render backend %s",
                     stage, run.config_hash, settings.seed, device, run.resumed, choice.describe(), backend)  # fmt: skip
            if choice.warning() is not None:
                log.warning("%s", choice.warning())
                emitter.note(str(choice.warning()), level="warning")
            emitter.emit("running", title=emitter.title, metrics={"resumed": run.resumed, "device": device, "threads": threads,
                                                                   "threads_basis": choice.describe(), "render_backend": backend})  # fmt: skip
            try:
                body(run, emitter)
            except KeyboardInterrupt:
                log.warning("stage %s interrupted", stage)
                if discard_work_on_failure:
                    shutil.rmtree(run.work_dir, ignore_errors=True)
                else:
                    run.interrupted()
                raise
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
            return Outcome(manifest, device, threads, backend, run.resumed)
    except BaseException:
        if remove_new_workspace_on_failure and not existed and ws.root.exists():
            shutil.rmtree(ws.root, ignore_errors=True)
        raise


def finish_result(result: StageResult, outcome: Outcome, ws: Workspace, emitter: Emitter, t0: float) -> StageResult:
    """Fill ``result`` from the outcome (or, when skipped, from the manifest already there), then
    emit ``finished`` with it."""
    result.skipped, result.resumed = outcome.manifest is None, outcome.resumed
    result.device, result.threads, result.render_backend = outcome.device, outcome.threads, outcome.render_backend
    result.fill(outcome.manifest if outcome.manifest is not None else ws.manifest(result.stage), t0)
    emitter.emit("finished", result=result)
    return result
