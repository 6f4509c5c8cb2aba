"""Every stage of a workspace as a function: a resolved config and a workspace in, a result out.

Each function takes the stage's config dataclass (:mod:`sage_core.config`), the workspace (a path
or a :class:`sage_core.workspace.Workspace`), :class:`StageSettings` (seed, device, force, threads)
and an optional ``on_event`` callback that receives :class:`StageEvent` objects (started, note,
skipped, running, estimate, progress, finished; :mod:`sage_core.stages.events`). It returns a result
dataclass: what was written, the metrics, the device and renderer backend used, the duration, and
whether the stage was skipped or resumed. The engine never prints; the CLI and ``sage batch``
display the events.

    from sage_core.config import resolve_config
    from sage_core.stages import StageSettings, phase1_stage, workspace_regime

    cfg = resolve_config("phase1", "tiny", regime=workspace_regime("ws"))
    result = phase1_stage("ws", cfg, StageSettings(device="cpu"), on_event=print)
    print(result.metrics["val_psnr"], result.outputs["avatar.pt"])
"""

from __future__ import annotations

from ._runner import StageResult, StageSettings, setup_logging
from .demo import DemoResult, run_demo, synth_demo_capture
from .eval import EvalResult, eval_stage
from .events import EVENT_KINDS, EventFn, StageEvent
from .export import EXPORT_FORMATS, VIEWER_FORMATS, ExportResult, export_stage, viewer_format
from .ingest import IngestResult, ingest_stage
from .init_mesh import init_mesh_stage
from .phase1 import ingest_summary, phase1_stage, workspace_regime
from .phase2 import phase2_stage
from .reenact import ReenactResult, reenact_stage
from .run import PIPELINE_STAGES, RENDER_STAGES, STAGE_PREFIXES, PipelineResult, pipeline_configs, pipeline_stages, run_pipeline, split_sets

__all__ = [
    "EVENT_KINDS",
    "EXPORT_FORMATS",
    "PIPELINE_STAGES",
    "RENDER_STAGES",
    "STAGE_PREFIXES",
    "VIEWER_FORMATS",
    "DemoResult",
    "EvalResult",
    "EventFn",
    "ExportResult",
    "IngestResult",
    "PipelineResult",
    "ReenactResult",
    "StageEvent",
    "StageResult",
    "StageSettings",
    "eval_stage",
    "export_stage",
    "ingest_stage",
    "ingest_summary",
    "init_mesh_stage",
    "phase1_stage",
    "phase2_stage",
    "pipeline_configs",
    "pipeline_stages",
    "reenact_stage",
    "run_demo",
    "run_pipeline",
    "setup_logging",
    "split_sets",
    "synth_demo_capture",
    "viewer_format",
    "workspace_regime",
]
