"""The whole chain of stages for one subject (``sage run``, ``sage batch``, ``sage demo``).

ingest → init-mesh → phase1 → phase2 (unless ``skip_phase2``) → eval → export (PLY at the canonical
pose + the avatar bundle). Eval scores what the regime has (:func:`eval_splits`): the val and test
frames of the workspace (novel views, self-reenactment) when it has any, and the capture's held-out
ground truth (``gt/novel``) when it has one; a one-shot capture has only the latter, and one
tracked from a photo has neither (eval is then left out). Each stage is
its stage function, so a finished stage with the same config and inputs is skipped, an interrupted
one resumes from its checkpoint, and a failing one stops the chain with its own error. Every
stage's config is resolved before the first stage runs (phase 1 with the regime being ingested),
so a bad value stops the chain before anything is written: preset < regime defaults < config file
(one section per stage) < the per-stage flags.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ._runner import StageResult, StageSettings
from .events import EventFn

PIPELINE_STAGES: tuple[str, ...] = ("ingest", "init-mesh", "phase1", "phase2", "eval", "export")
RENDER_STAGES: tuple[str, ...] = ("phase1", "phase2", "eval", "export")
"""Stages of the chain whose config has ``render_backend``."""


STAGE_PREFIXES: dict[str, tuple[str, ...]] = {
    "ingest": ("ingest",),
    "init-mesh": ("init-mesh", "init_mesh"),
    "phase1": ("phase1",),
    "phase2": ("phase2",),
    "eval": ("eval",),
    "export": ("export",),
}
"""Stage of the chain -> the prefixes that address it in ``stage.key=value`` overrides."""


def split_sets(values: list[str] | None) -> dict[str, list[str]]:
    """``["phase1.iterations=500", "init_mesh.pretrain.steps=100"]`` -> per-stage ``key=value`` lists
    (every stage of :data:`STAGE_PREFIXES` present). ConfigError for an item without a known stage
    prefix, a key or a value."""
    from ..errors import ConfigError

    out: dict[str, list[str]] = {s: [] for s in STAGE_PREFIXES}
    for v in values or []:
        key = v.split("=", 1)[0].strip()
        head, _, rest = key.partition(".")
        stage = next((s for s, prefixes in STAGE_PREFIXES.items() if head in prefixes), None)
        if stage is None or not rest or "=" not in v:
            raise ConfigError(f"--set {v!r}: `sage run` needs stage.key=value with a stage among {', '.join(STAGE_PREFIXES)}")
        out[stage].append(f"{rest}={v.split('=', 1)[1]}")
    return out


def eval_splits(ws: str | Path) -> list[str]:
    """The eval splits of a chain on an ingested workspace: ``all`` when it has val or test frames,
    ``novel`` when its capture has held-out ground truth; none when it has neither (e.g. a capture
    tracked from one photo: the chain then leaves eval out and still exports)."""
    from ..data.dataset import IngestedData
    from ..evaluate.novel import has_novel_ground_truth

    data = IngestedData.open(Path(ws) / "data")
    splits = ["all"] if (data.role("val") or data.role("test")) else []
    if has_novel_ground_truth(data):
        splits.append("novel")
    return splits


def pipeline_stages(skip_phase2: bool) -> list[str]:
    """The stages :func:`run_pipeline` runs with these options."""
    return [s for s in PIPELINE_STAGES if not (skip_phase2 and s == "phase2")]


@dataclass
class PipelineResult:
    """What :func:`run_pipeline` did: per-stage outcome lines (``skipped (already complete)``,
    ``done in 12.3 s``, ``left out (--skip-phase2)``), each stage's result object (the eval of the
    held-out ground truth under ``eval novel``), the avatar stage evaluated and exported, the eval
    splits run, and the wall time."""

    ws: Path
    stages: list[tuple[str, str]] = field(default_factory=list)
    results: dict[str, StageResult] = field(default_factory=dict)
    avatar_stage: str | None = None
    eval_splits: list[str] = field(default_factory=list)
    wall_time_s: float = 0.0


def pipeline_configs(
    preset: str = "default",
    config_file: str | Path | None = None,
    flags: dict[str, dict[str, Any]] | None = None,
    skip_phase2: bool = False,
    render_backend: str | None = None,
) -> dict[str, Any]:
    """Every stage config :func:`run_pipeline` will run with, resolved and checked (ConfigError
    before anything runs). Phases 1 and 2 take the defaults of the regime ingest will record; eval and
    export take the avatar stage (phase 2, or phase 1 with ``skip_phase2``)."""
    from ..config import load_config_file, resolve_config

    per_stage = {s: dict((flags or {}).get(s) or {}) for s in PIPELINE_STAGES}
    if render_backend is not None:
        for s in RENDER_STAGES:
            per_stage[s]["render_backend"] = render_backend
    cfg_path = None if config_file is None else Path(config_file)
    data = load_config_file(cfg_path) if cfg_path is not None else None
    label = str(cfg_path) if cfg_path is not None else "config file"

    def config(stage: str, extra: dict[str, Any] | None = None, regime: str | None = None) -> Any:
        return resolve_config(stage, preset, data, {**(extra or {}), **per_stage[stage]}, file_label=label, regime=regime)

    av_stage = "phase1" if skip_phase2 else "phase2"
    cfgs = {"ingest": config("ingest"), "init-mesh": config("init-mesh")}
    cfgs["phase1"] = config("phase1", regime=cfgs["ingest"].regime)
    if not skip_phase2:
        cfgs["phase2"] = config("phase2", regime=cfgs["ingest"].regime)
    cfgs["eval"] = config("eval", {"split": "all", "stage": av_stage})
    cfgs["export"] = config("export", {"stage": av_stage})
    return cfgs


def run_pipeline(
    dataset: str | Path,
    ws: str | Path,
    flame_model: str | Path,
    *,
    flame_masks: str | Path | None = None,
    skip_phase2: bool = False,
    lpips_weights: str | Path | None = None,
    preset: str = "default",
    config_file: str | Path | None = None,
    flags: dict[str, dict[str, Any]] | None = None,
    render_backend: str | None = None,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> PipelineResult:
    """Run the stage chain on the capture ``dataset`` into workspace ``ws``.

    flags: per-stage config overrides (stage -> {dotted key: value}; None values are unset), e.g.
    ``{"ingest": {"height": 128}, "phase1": {"iterations": 500}}``. render_backend: the
    ``render_backend`` of every stage that renders (None: their configs'). settings.threads: CPU
    threads of every stage (None: ``$SAGE_THREADS``, else the idle cores); also put in
    ``$SAGE_THREADS`` for the rest of this process. Each stage's events go to ``on_event``.
    """
    import os

    from ..runtime import THREADS_ENV, apply_threads
    from .eval import eval_stage
    from .export import export_stage
    from .ingest import ingest_stage
    from .init_mesh import init_mesh_stage
    from .phase1 import phase1_stage
    from .phase2 import phase2_stage

    if settings.threads is not None:
        os.environ[THREADS_ENV] = str(apply_threads(settings.threads))
    cfgs = pipeline_configs(preset, config_file, flags, skip_phase2, render_backend)
    av_stage = "phase1" if skip_phase2 else "phase2"

    t0 = time.time()
    ws = Path(ws)
    res = PipelineResult(ws=ws)

    def record(r: StageResult, name: str | None = None) -> None:
        res.results[name or r.stage] = r
        res.stages.append((name or r.stage, "skipped (already complete)" if r.skipped else f"done in {r.duration_s:.1f} s"))

    record(ingest_stage(dataset, ws, cfgs["ingest"], flame_model, flame_masks, settings, on_event))
    record(init_mesh_stage(ws, cfgs["init-mesh"], settings, on_event))
    record(phase1_stage(ws, cfgs["phase1"], settings, on_event))
    if skip_phase2:
        res.stages.append(("phase2", "left out (--skip-phase2)"))
    else:
        record(phase2_stage(ws, cfgs["phase2"], lpips_weights, settings, on_event))
    res.avatar_stage = av_stage
    res.eval_splits = eval_splits(ws)
    if not res.eval_splits:
        res.stages.append(("eval", "left out (no val, test or held-out ground-truth frames)"))
    for split in res.eval_splits:
        cfg = cfgs["eval"] if split == "all" else replace(cfgs["eval"], split=split)
        record(eval_stage(ws, cfg, lpips_weights, settings, on_event), "eval" if split == "all" else f"eval {split}")
    record(export_stage(ws, cfgs["export"], viewer=["ply"], bundle=True, settings=settings, on_event=on_event))
    res.wall_time_s = time.time() - t0
    return res

