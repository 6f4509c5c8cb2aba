"""``sage ingest DATASET WS``: read a VHAP / GaussianAvatars capture into a workspace."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from .._common import (
    ConfigOpt,
    DeviceOpt,
    ForceOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    ThreadsOpt,
    VerboseOpt,
    cli_errors,
    parse_sets,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageDisplay

if TYPE_CHECKING:
    from sage_core.stages import IngestResult


def ingest(
    dataset: Annotated[Path, typer.Argument(help="Capture folder (VHAP 'NeRF-style' export or a union folder).")],
    ws: Annotated[Path, typer.Argument(help="Workspace folder to create or update.")],
    flame_model: Annotated[Path, typer.Option("--flame-model", help="FLAME model: official pickle (generic_model.pkl, flame2023.pkl) or a converted .npz.")],
    flame_masks: Annotated[Optional[Path], typer.Option("--flame-masks", help="FLAME_masks.pkl region masks (default: FLAME_masks.pkl beside the model, if present).")] = None,
    regime: Annotated[Optional[str], typer.Option("--regime", help="mv-sf | mv-mf | sv-hr | one-shot.")] = None,
    timestep: Annotated[Optional[int], typer.Option("--timestep", help="Training timestep for mv-sf, canonical timestep for mv-mf / sv-hr, the image's timestep for one-shot (default: chosen automatically).")] = None,
    camera: Annotated[Optional[int], typer.Option("--camera", help="Camera index for sv-hr / one-shot (sv-hr: the capture's other cameras become cross-view ground truth).")] = None,
    downsample: Annotated[Optional[float], typer.Option("--downsample", help="Divide the image size by this factor.")] = None,
    height: Annotated[Optional[int], typer.Option("--height", help="Resize images to this height in pixels.")] = None,
    background: Annotated[Optional[str], typer.Option("--background", help="white (as exported) or black.")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
) -> None:
    """Read a capture: cameras (OpenCV), frames and splits, FLAME parameters, resized images and masks, and the FLAME model."""
    with cli_errors():
        flags = {
            "regime": regime,
            "timestep": timestep,
            "camera": camera,
            "downsample": downsample,
            "height": height,
            "background": background,
            **parse_sets(set_),
        }
        cfg = resolve_stage_config("ingest", preset, config, flags)

        from sage_core.stages import StageSettings, ingest_stage

        with StageDisplay(verbose, preset) as display:
            r = ingest_stage(dataset, ws, cfg, flame_model, flame_masks, StageSettings(seed, device, force, threads), display)
        if not r.skipped:
            show(r, ws)


def show(r: IngestResult, ws: Path) -> None:
    """The closing panel of a finished (not skipped) ingest result (``sage ingest``, ``sage run``)."""
    summary_panel("sage ingest", list(r.summary.rows()) + [("wall time", f"{r.wall_time_s:.1f} s")], [("data", ws / "data")])
