"""The phase-2 stage: self-supervised fine-tuning under sampled expressions, SDF and hash grid frozen."""

from __future__ import annotations

import time
from pathlib import Path

from ..config import Phase2Config
from ..workspace import Workspace
from ._runner import StageResult, StageSettings, as_workspace, execute_stage, finish_result
from .events import Emitter, EventFn

PHASE2_FILES: tuple[str, ...] = ("avatar.pt", "metrics.json", "distortion_curve.json", "eval_test", "eval_val")


def phase2_stage(
    ws: str | Path | Workspace,
    cfg: Phase2Config,
    lpips_weights: str | Path | None = None,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> StageResult:
    """Fine-tune the phase-1 avatar into ``WS/phase2/`` (needs a finished phase1) and evaluate it.

    lpips_weights: LPIPS AlexNet weights for the evaluation (None: ``$SAGE_LPIPS_WEIGHTS`` or the
    cache; InputError when a given file is missing). Resumes an interrupted run.
    """
    from ..errors import InputError

    t0 = time.time()
    emitter = Emitter("phase2", on_event, "phase 2")
    emitter.emit("started")
    w = as_workspace(ws)
    lp = None if lpips_weights is None else Path(lpips_weights)
    if lp is not None and not lp.is_file():
        raise InputError(lp, "LPIPS weights file not found")
    external = None
    if lp is not None:
        from ..workspace import file_fingerprint

        external = {"lpips_weights": file_fingerprint(lp)}

    def body(run, progress) -> None:
        from ..data.dataset import IngestedData
        from ..train.phase2 import run_phase2

        data = IngestedData.open(run.ws.stage_dir("ingest"))
        metrics = run_phase2(data, run.ws.stage_dir("phase1"), run.ws.stage_dir("init-mesh"), run.work_dir, cfg, device=run.device,
                             seed=run.seed, checkpoint_dir=run.checkpoint_dir, progress=progress, lpips_weights=lp)  # fmt: skip
        run.metrics.update({k: v for k, v in metrics.items() if k != "final_losses"})
        out = run.ws.stage_dir("phase2")
        run.outputs.update({n: str(out / n) for n in PHASE2_FILES})

    outcome = execute_stage("phase2", w, cfg, body, settings, emitter, requires=("phase1",), external_inputs=external)
    return finish_result(StageResult("phase2", w.root), outcome, w, emitter, t0)
