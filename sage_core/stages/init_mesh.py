"""The init-mesh stage: canonical mesh (+ mouth interior), the SDF pretrained on it, its zero level set."""

from __future__ import annotations

import time
from pathlib import Path

from ..config import InitMeshConfig
from ..workspace import Workspace
from ._runner import StageResult, StageSettings, as_workspace, execute_stage, finish_result
from .events import Emitter, EventFn

INIT_MESH_FILES: tuple[str, ...] = ("canonical_mesh.ply", "sdf_mesh.ply", "sdf.pt")


def init_mesh_stage(
    ws: str | Path | Workspace,
    cfg: InitMeshConfig,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> StageResult:
    """Build the canonical FLAME mesh, pretrain the SDF on it and extract its zero level set into
    ``WS/init/`` (needs a finished ingest)."""
    t0 = time.time()
    emitter = Emitter("init-mesh", on_event)
    emitter.emit("started")
    w = as_workspace(ws)

    def body(run, progress) -> None:
        from ..data.dataset import IngestedData
        from ..train.init_mesh import run_init_mesh

        data = IngestedData.open(run.ws.stage_dir("ingest"))
        metrics = run_init_mesh(data, run.work_dir, cfg, device=run.device, seed=run.seed, checkpoint_dir=run.checkpoint_dir,
                                progress=progress)  # fmt: skip
        run.metrics.update(metrics)
        run.outputs.update({n: str(run.ws.stage_dir("init-mesh") / n) for n in INIT_MESH_FILES})

    outcome = execute_stage("init-mesh", w, cfg, body, settings, emitter, requires=("ingest",))
    return finish_result(StageResult("init-mesh", w.root), outcome, w, emitter, t0)
