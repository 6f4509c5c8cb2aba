"""``sage run DATASET WS``: every stage in order (:func:`sage_core.stages.run_pipeline`), shown as
the single stage commands show them.

ingest → init-mesh → phase1 → phase2 (``--skip-phase2`` leaves it out) → eval (the workspace's test
and val frames, and the capture's held-out ground truth ``gt/novel`` when it has one) → export (PLY
at the canonical pose + the avatar bundle). A finished stage with the same config and
inputs is skipped, an interrupted one resumes from its checkpoint, and a failing one stops the
chain with its own message and exit code. ``--set stage.key=value`` addresses one stage's config (``--set
phase1.iterations=500``); a ``--config`` file holds one section per stage.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Optional

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
    summary_panel,
)
from .._stage import StageDisplay


def stage_flags(sets: dict[str, list[str]] | None) -> dict[str, dict[str, Any]]:
    """Per-stage ``--set`` lists (:func:`sage_core.stages.split_sets`) as per-stage config flags."""
    from .._common import parse_sets

    return {stage: parse_sets(values) for stage, values in (sets or {}).items()}


def show_result(result: Any, ws: Path) -> None:
    """The closing output of one stage of a chain, as the stage's own command prints it."""
    from . import eval_cmd, export_cmd, ingest, init_mesh, phase1, phase2, reenact_cmd

    stage = getattr(result, "stage", None)
    single = {"ingest": ingest.show, "init-mesh": init_mesh.show, "phase1": phase1.show, "phase2": phase2.show}
    if stage in single:
        if not result.skipped:
            single[stage](result, ws)
    elif stage == "eval":
        eval_cmd.show(result, ws)
    elif stage == "export":
        export_cmd.show(result)
    elif stage == "reenact":
        reenact_cmd.show(result)


class ChainDisplay(StageDisplay):
    """:class:`StageDisplay` for a chain of stages (``sage run``, ``sage demo``, a ``sage batch``
    subject): a rule above each stage and each stage's closing panel."""

    def __init__(self, ws: Path, verbose: bool = True, preset: str | None = None) -> None:
        super().__init__(verbose, preset, rules=True)
        self.ws = ws

    def __call__(self, ev: Any) -> None:
        super().__call__(ev)
        if ev.kind == "finished" and ev.result is not None:
            show_result(ev.result, self.ws)


def run_chain(
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
    on_event: Any = None,
) -> Any:
    """:func:`sage_core.stages.run_pipeline` with the chain's display (and ``on_event`` after it)."""
    from sage_core.stages import StageSettings, run_pipeline

    flags = stage_flags(sets)
    flags["ingest"] = {**(ingest_flags or {}), **flags.get("ingest", {})}
    with ChainDisplay(ws, verbose, preset) as display:

        def events(ev: Any) -> None:
            display(ev)
            if on_event is not None:
                on_event(ev)

        return run_pipeline(dataset, ws, flame_model, flame_masks=flame_masks, skip_phase2=skip_phase2, lpips_weights=lpips_weights,
                            preset=preset, config_file=config, flags=flags, render_backend=render_backend,
                            settings=StageSettings(seed, device, force, threads), on_event=events)  # fmt: skip


def pipeline_rows(res: Any) -> tuple[list[tuple[str, Any]], list[tuple[str, Path]]]:
    """Panel rows (stages, metrics) and paths of a finished pipeline."""
    from sage_core.workspace import read_json

    rows: list[tuple[str, Any]] = [(name, outcome) for name, outcome in res.stages]
    ws = res.ws
    paths: list[tuple[str, Path]] = []
    if res.avatar_stage is not None:
        labels = {"val": "novel view (val)", "test": "self-reenactment (test)", "novel": "held-out views and expressions (gt/novel)"}
        for split, label in labels.items():
            p = ws / "eval" / res.avatar_stage / split / "metrics.json"
            if p.is_file():
                doc = read_json(p)
                rows.append((f"{label} PSNR / SSIM / LPIPS", _means(doc["overall"])))
                if split == "novel" and doc.get("visible_region"):
                    rows.append(("  on the surface the training views saw", _means(doc["visible_region"]["overall"])))
                paths.append((f"{split} metrics", p))
        paths.append(("avatar", ws / res.avatar_stage / "avatar.pt"))
    for label, rel in (("viewer PLY", "export/ply/canonical.ply"), ("avatar bundle", "export/bundle")):
        if (ws / rel).exists():
            paths.append((label, ws / rel))
    rows.append(("wall time", f"{res.wall_time_s:.1f} s"))
    return rows, paths


def _means(o: dict[str, Any]) -> str:
    lp = "unavailable" if o.get("lpips") is None else f"{o['lpips']:.4f}"
    return f"{_num(o['psnr'], 2)} dB / {_num(o['ssim'], 4)} / {lp}"


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
    """Run every stage: ingest, init-mesh, phase1, phase2, eval (test, val and the capture's gt/novel), export (PLY + bundle); finished stages are skipped, interrupted ones resume."""
    with cli_errors():
        from sage_core.stages import split_sets

        sets = split_sets(set_)
        ingest_flags = {"regime": regime, "timestep": timestep, "camera": camera, "downsample": downsample, "height": height, "background": background}
        res = run_chain(
            dataset, ws, flame_model, flame_masks=flame_masks, ingest_flags=ingest_flags, skip_phase2=skip_phase2,
            lpips_weights=lpips_weights, preset=preset, config=config, sets=sets, seed=seed, device=device, force=force,
            verbose=verbose, threads=threads, render_backend=render_backend,
        )  # fmt: skip
        rows, paths = pipeline_rows(res)
        summary_panel("sage run", rows, paths)
