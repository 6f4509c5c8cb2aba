"""The ingest stage: a VHAP / GaussianAvatars capture read into ``WS/data/``."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import IngestConfig
from ..workspace import Workspace
from ._runner import StageResult, StageSettings, as_workspace, execute_stage, finish_result
from .events import Emitter, EventFn


@dataclass
class IngestResult(StageResult):
    """:class:`StageResult` of ingest, with the ingest summary (None when skipped)."""

    summary: Any = None


def default_masks(flame_model: Path, flame_masks: Path | None) -> Path | None:
    """The region masks to read: ``flame_masks``, else ``FLAME_masks.pkl`` beside the model when present."""
    if flame_masks is None and (flame_model.parent / "FLAME_masks.pkl").is_file():
        return flame_model.parent / "FLAME_masks.pkl"
    return flame_masks


def ingest_stage(
    dataset: str | Path,
    ws: str | Path | Workspace,
    cfg: IngestConfig,
    flame_model: str | Path,
    flame_masks: str | Path | None = None,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> IngestResult:
    """Read the capture ``dataset`` (cameras, frames and splits, FLAME parameters, resized images and
    masks, the FLAME model) into ``WS/data/``.

    Everything is validated before anything is written (InputError naming the file); a workspace
    created by a failing call is removed again.
    """
    from ..data.capture import read_capture
    from ..data.ingest import capture_fingerprint, ingest as run_ingest
    from ..errors import InputError, require_file
    from ..workspace import HASH_CACHE, file_fingerprint

    t0 = time.time()
    emitter = Emitter("ingest", on_event)
    emitter.emit("started")
    dataset, flame_model = Path(dataset), Path(flame_model)
    w = as_workspace(ws)
    if not dataset.is_dir():
        raise InputError(dataset, "is a file, expected a capture folder" if dataset.exists() else "capture folder not found")
    require_file(flame_model, "FLAME model file")
    masks = default_masks(flame_model, None if flame_masks is None else Path(flame_masks))
    if masks is not None:
        require_file(masks, "FLAME masks file")

    capture = read_capture(dataset, follow_symlinks=cfg.follow_symlinks)  # validates everything before anything is written
    external = {"flame_model": file_fingerprint(flame_model)}
    if masks is not None:
        external["flame_masks"] = file_fingerprint(masks)
    for name in sorted(p.name for p in dataset.glob("transforms*.json")):
        external[name] = file_fingerprint(dataset / name)
    external["dataset"] = _dataset_key(w, dataset)
    external["capture_content"] = capture_fingerprint(capture, w.root / HASH_CACHE if w.root.is_dir() else None)

    result = IngestResult("ingest", w.root)

    def body(run, progress) -> None:
        s = run_ingest(capture, flame_model, run.work_dir, masks_path=masks, regime=cfg.regime, timestep=cfg.timestep,
                       camera=cfg.camera, downsample=cfg.downsample, height=cfg.height, background=cfg.background,
                       progress=progress)  # fmt: skip
        result.summary = s
        run.metrics.update(s.metrics())
        run.outputs.update({"data": str(run.ws.stage_dir("ingest"))})

    outcome = execute_stage("ingest", w, cfg, body, settings, emitter, external_inputs=external,
                            remove_new_workspace_on_failure=True, discard_work_on_failure=True)  # fmt: skip
    return finish_result(result, outcome, w, emitter, t0)


def _dataset_key(w: Workspace, dataset: Path) -> str:
    """The capture folder as the ingest manifest records it: relative to the workspace, so a workspace
    copied beside its capture stays whole and no path of the machine is written. A workspace ingested
    by an earlier version recorded the absolute path; while that still names the same folder it is
    kept, so upgrading does not make the workspace stale."""
    m = w.manifest("ingest") if w.root.is_dir() else None
    old = ((m or {}).get("inputs") or {}).get("files", {}).get("dataset")
    if isinstance(old, str) and os.path.isabs(old) and Path(old).resolve() == dataset.resolve():
        return old
    return Path(os.path.relpath(dataset.resolve(), w.root.resolve())).as_posix()
