"""``sage run DATASET WS``: every stage in order, with the single stages' own options and logic.

ingest → init-mesh → phase1 → phase2 (when the command is installed; ``--skip-phase2`` leaves it
out) → eval (test and val) → export (PLY at the canonical pose + the avatar bundle). Each stage is
the stage command itself, so a finished stage with the same config and inputs is skipped, an
interrupted one resumes from its checkpoint, and a failing one stops the chain with its own
message and exit code. ``--set stage.key=value`` addresses one stage's config (``--set
phase1.iterations=500``); a ``--config`` file holds one section per stage.
"""

from __future__ import annotations

import importlib
import inspect
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Callable, Optional

import typer

from .._common import (
    ConfigOpt,
    DeviceOpt,
    ForceOpt,
    PresetOpt,
    RenderBackendOpt,
    SeedOpt,
    SetOpt,
    ThreadsOpt,
    VerboseOpt,
    cli_errors,
    console,
    summary_panel,
)

# stage name -> accepted --set prefixes
STAGE_PREFIXES: dict[str, tuple[str, ...]] = {
    "ingest": ("ingest",),
    "init-mesh": ("init-mesh", "init_mesh"),
    "phase1": ("phase1",),
    "phase2": ("phase2",),
    "eval": ("eval",),
    "export": ("export",),
}


RENDER_STAGES: tuple[str, ...] = ("phase1", "phase2", "eval", "export")
"""Stages of ``sage run`` whose config has ``render_backend``."""


def split_sets(values: list[str] | None) -> dict[str, list[str]]:
    """``["phase1.iterations=500", "init_mesh.pretrain.steps=100"]`` -> per-stage ``--set`` lists."""
    from sage_core.errors import ConfigError

    out: dict[str, list[str]] = {s: [] for s in STAGE_PREFIXES}
    for v in values or []:
        key = v.split("=", 1)[0].strip()
        head, _, rest = key.partition(".")
        stage = next((s for s, prefixes in STAGE_PREFIXES.items() if head in prefixes), None)
        if stage is None or not rest or "=" not in v:
            raise ConfigError(f"--set {v!r}: `sage run` needs stage.key=value with a stage among {', '.join(STAGE_PREFIXES)}")
        out[stage].append(f"{rest}={v.split('=', 1)[1]}")
    return out


def phase2_command() -> Callable[..., None] | None:
    """The ``sage phase2`` command function when it is installed, else None."""
    try:
        mod = importlib.import_module("sage_cli.commands.phase2")
    except ImportError:
        return None
    return getattr(mod, "phase2", None)


def _call(fn: Callable[..., None], **kwargs: Any) -> None:
    """Call a command function with the keyword arguments it accepts."""
    params = inspect.signature(fn).parameters
    fn(**{k: v for k, v in kwargs.items() if k in params})


@dataclass
class PipelineResult:
    """What ``run`` did: per-stage outcome lines, the avatar stage used and the wall time."""

    ws: Path
    stages: list[tuple[str, str]] = field(default_factory=list)
    avatar_stage: str | None = None
    wall_time_s: float = 0.0
    notes: list[str] = field(default_factory=list)


def run_pipeline(
    dataset: Path,
    ws: Path,
    flame_model: Path,
    *,
    flame_masks: Path | None = None,
    ingest_flags: dict[str, Any] | None = None,
    skip_phase2: bool = False,
    lpips_weights: Path | None = None,
    preset: str = "default",
    config: Path | None = None,
    sets: dict[str, list[str]] | None = None,
    seed: int = 0,
    device: str = "auto",
    force: bool = False,
    verbose: bool = True,
    threads: int | None = None,
    render_backend: str | None = None,
) -> PipelineResult:
    """Run the stage chain by calling each stage command (see the module doc).

    threads: CPU threads of every stage (None: $SAGE_THREADS, else the idle cores); it is also put in
    $SAGE_THREADS for the rest of this process, so stage commands without the option use it too.
    render_backend: the ``render_backend`` of every stage that renders (None: their configs').
    """
    import os

    from sage_core.runtime import THREADS_ENV
    from sage_core.workspace import Workspace

    from . import eval_cmd, export_cmd, ingest, init_mesh, phase1

    sets = {s: list(v) for s, v in (sets or {s: [] for s in STAGE_PREFIXES}).items()}
    if render_backend is not None:
        for s in RENDER_STAGES:
            sets.setdefault(s, []).append(f"render_backend={render_backend}")
    if threads is not None:
        from sage_core.runtime import apply_threads

        os.environ[THREADS_ENV] = str(apply_threads(threads))
    common = {"preset": preset, "config": config, "seed": seed, "device": device, "force": force, "verbose": verbose, "threads": threads}
    t0 = time.time()
    res = PipelineResult(ws=ws)
    w = Workspace(ws)

    def stage(name: str, fn: Callable[[], None]) -> None:
        before = (w.manifest(name) or {}).get("finished_at") if ws.exists() else None
        console.rule(f"[bold]{name}")
        t = time.time()
        fn()
        after = (w.manifest(name) or {}).get("finished_at")
        outcome = "skipped (already complete)" if after is not None and after == before else f"done in {time.time() - t:.1f} s"
        res.stages.append((name, outcome))

    stage("ingest", lambda: _call(ingest.ingest, dataset=dataset, ws=ws, flame_model=flame_model, flame_masks=flame_masks,
                                  set_=sets["ingest"], **(ingest_flags or {}), **common))  # fmt: skip
    stage("init-mesh", lambda: _call(init_mesh.init_mesh, ws=ws, set_=sets["init-mesh"], **common))
    stage("phase1", lambda: _call(phase1.phase1, ws=ws, set_=sets["phase1"], **common))
    p2 = phase2_command()
    if skip_phase2:
        res.stages.append(("phase2", "left out (--skip-phase2)"))
    elif p2 is None:
        res.stages.append(("phase2", "not available in this installation"))
        res.notes.append("phase 2 is not installed: the phase-1 avatar is evaluated and exported")
    else:
        stage("phase2", lambda: _call(p2, ws=ws, set_=sets["phase2"], lpips_weights=lpips_weights, **common))
    av_stage = "phase1" if skip_phase2 or p2 is None else "phase2"
    res.avatar_stage = av_stage
    stage("eval", lambda: _call(eval_cmd.eval_, ws=ws, split="all", stage=av_stage, lpips_weights=lpips_weights,
                                set_=sets["eval"], **common))  # fmt: skip
    stage("export", lambda: _call(export_cmd.export, ws=ws, ply=True, bundle=True, stage=av_stage, set_=sets["export"], **common))
    res.wall_time_s = time.time() - t0
    return res


def pipeline_rows(res: PipelineResult) -> tuple[list[tuple[str, Any]], list[tuple[str, Path]]]:
    """Panel rows (stages, metrics) and paths of a finished pipeline."""
    from sage_core.workspace import read_json

    rows: list[tuple[str, Any]] = [(name, outcome) for name, outcome in res.stages]
    ws = res.ws
    paths: list[tuple[str, Path]] = []
    if res.avatar_stage is not None:
        for split in ("val", "test"):
            p = ws / "eval" / res.avatar_stage / split / "metrics.json"
            if p.is_file():
                o = read_json(p)["overall"]
                lp = "unavailable" if o.get("lpips") is None else f"{o['lpips']:.4f}"
                label = "novel view (val)" if split == "val" else "self-reenactment (test)"
                rows.append((f"{label} PSNR / SSIM / LPIPS", f"{_num(o['psnr'], 2)} dB / {_num(o['ssim'], 4)} / {lp}"))
                paths.append((f"{split} metrics", p))
        paths.append(("avatar", ws / res.avatar_stage / "avatar.pt"))
    for label, rel in (("viewer PLY", "export/ply/canonical.ply"), ("avatar bundle", "export/bundle")):
        if (ws / rel).exists():
            paths.append((label, ws / rel))
    rows += [("note", n) for n in res.notes]
    rows.append(("wall time", f"{res.wall_time_s:.1f} s"))
    return rows, paths


def _num(v: Any, digits: int) -> str:
    return f"{v:.{digits}f}" if isinstance(v, (int, float)) else str(v)


def run(
    dataset: Annotated[Path, typer.Argument(help="Capture folder (VHAP 'NeRF-style' export or a union folder).")],
    ws: Annotated[Path, typer.Argument(help="Workspace folder to create or continue.")],
    flame_model: Annotated[Path, typer.Option("--flame-model", help="FLAME model: official pickle (generic_model.pkl, flame2023.pkl) or a converted .npz.")],
    flame_masks: Annotated[Optional[Path], typer.Option("--flame-masks", help="FLAME_masks.pkl region masks (default: beside the model, if present).")] = None,
    regime: Annotated[Optional[str], typer.Option("--regime", help="mv-sf | mv-mf | sv-hr | one-shot.")] = None,
    timestep: Annotated[Optional[int], typer.Option("--timestep", help="Training timestep for mv-sf (default: chosen automatically).")] = None,
    camera: Annotated[Optional[int], typer.Option("--camera", help="Camera index for sv-hr / one-shot.")] = None,
    downsample: Annotated[Optional[float], typer.Option("--downsample", help="Divide the image size by this factor.")] = None,
    height: Annotated[Optional[int], typer.Option("--height", help="Resize images to this height in pixels.")] = None,
    background: Annotated[Optional[str], typer.Option("--background", help="white (as exported) or black.")] = None,
    skip_phase2: Annotated[bool, typer.Option("--skip-phase2", help="Stop training after phase 1 (evaluate and export the phase-1 avatar).")] = False,
    lpips_weights: Annotated[Optional[Path], typer.Option("--lpips-weights", help="LPIPS AlexNet v0.1 weights for the evaluations (default: $SAGE_LPIPS_WEIGHTS, then ~/.cache/sage/lpips_alex_v0.1.pth).")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
    render_backend: RenderBackendOpt = None,
) -> None:
    """Run every stage: ingest, init-mesh, phase1, phase2, eval (test and val), export (PLY + bundle); finished stages are skipped, interrupted ones resume."""
    with cli_errors():
        sets = split_sets(set_)
        ingest_flags = {"regime": regime, "timestep": timestep, "camera": camera, "downsample": downsample, "height": height, "background": background}
        res = run_pipeline(
            dataset, ws, flame_model, flame_masks=flame_masks, ingest_flags=ingest_flags, skip_phase2=skip_phase2,
            lpips_weights=lpips_weights, preset=preset, config=config, sets=sets, seed=seed, device=device, force=force,
            verbose=verbose, threads=threads, render_backend=render_backend,
        )  # fmt: skip
        rows, paths = pipeline_rows(res)
        summary_panel("sage run", rows, paths)
