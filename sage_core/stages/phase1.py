"""The phase-1 stage: surfels, canonical SDF and attribute networks optimised jointly on the images."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from ..config import Phase1Config
from ..workspace import Workspace
from ._runner import StageResult, StageSettings, as_workspace, execute_stage, finish_result
from .events import Emitter, EventFn

PHASE1_FILES: tuple[str, ...] = ("avatar.pt", "sdf_mesh.ply", "metrics.json", "renders")


def ingest_summary(ws: str | Path | Workspace) -> dict[str, Any]:
    """The workspace's ingest ``summary.json`` ({} when ingest has not run; the stage then reports it).

    InputError naming the file when it cannot be read."""
    from ..errors import InputError

    path = as_workspace(ws).stage_dir("ingest") / "summary.json"
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"cannot read the ingest summary: {e}") from None
    return doc if isinstance(doc, dict) else {}


def workspace_regime(ws: str | Path | Workspace) -> str | None:
    """The regime the workspace was ingested with (None before ingest): its defaults apply to phases 1 and 2."""
    regime = ingest_summary(ws).get("regime")
    return regime if isinstance(regime, str) else None


def _coverage_notes(summary: dict[str, Any], emitter: Emitter) -> None:
    """Head coverage of a single-camera capture (``info``), and the narrow-clip ``warning`` (sv-hr)."""
    cov = summary.get("coverage")
    if not isinstance(cov, dict):
        return
    from ..data.coverage import Coverage

    c = Coverage.from_dict(cov)
    emitter.emit("note", title=f"head coverage ({summary.get('regime', '?')})", message=c.text())
    note = c.warning()
    if note is not None and summary.get("regime") == "sv-hr":
        emitter.note(note, level="warning")


def phase1_stage(
    ws: str | Path | Workspace,
    cfg: Phase1Config,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> StageResult:
    """Train the avatar (phase 1) into ``WS/phase1/`` (needs a finished init-mesh); resumes an
    interrupted run from its newest checkpoint. Resolve ``cfg`` with the workspace's regime
    (:func:`workspace_regime`)."""
    t0 = time.time()
    emitter = Emitter("phase1", on_event, "phase 1")
    emitter.emit("started")
    w = as_workspace(ws)
    _coverage_notes(ingest_summary(w), emitter)

    def body(run, progress) -> None:
        from ..data.dataset import IngestedData
        from ..train.phase1 import run_phase1

        data = IngestedData.open(run.ws.stage_dir("ingest"))
        metrics = run_phase1(data, run.ws.stage_dir("init-mesh"), run.work_dir, cfg, device=run.device, seed=run.seed,
                             checkpoint_dir=run.checkpoint_dir, progress=progress)  # fmt: skip
        run.metrics.update({k: v for k, v in metrics.items() if k not in ("final_losses", "exposure_gains")})
        out = run.ws.stage_dir("phase1")
        run.outputs.update({n: str(out / n) for n in PHASE1_FILES})

    outcome = execute_stage("phase1", w, cfg, body, settings, emitter, requires=("init-mesh",))
    return finish_result(StageResult("phase1", w.root), outcome, w, emitter, t0)
