"""``sage ingest DATASET WS``: read a VHAP / GaussianAvatars capture into a workspace."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

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
from .._stage import StageOptions, execute_stage


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
        from sage_core.errors import InputError

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
        if not dataset.is_dir():
            raise InputError(dataset, "capture folder not found")
        if not flame_model.is_file():
            raise InputError(flame_model, "FLAME model file not found")
        masks = flame_masks
        if masks is None and (flame_model.parent / "FLAME_masks.pkl").is_file():
            masks = flame_model.parent / "FLAME_masks.pkl"
        if masks is not None and not masks.is_file():
            raise InputError(masks, "FLAME masks file not found")

        from sage_core.data.capture import read_capture
        from sage_core.data.ingest import ingest as run_ingest
        from sage_core.workspace import file_fingerprint

        capture = read_capture(dataset)  # validates everything before anything is written
        external = {"flame_model": file_fingerprint(flame_model)}
        if masks is not None:
            external["flame_masks"] = file_fingerprint(masks)
        for name in sorted(p.name for p in dataset.glob("transforms*.json")):
            external[name] = file_fingerprint(dataset / name)
        external["dataset"] = str(dataset.resolve())
        from sage_core.data.ingest import capture_fingerprint
        from sage_core.workspace import HASH_CACHE, Workspace

        external["capture_content"] = capture_fingerprint(capture, Workspace(ws).root / HASH_CACHE if ws.is_dir() else None)

        summary_holder: dict = {}

        def body(run, progress) -> None:
            s = run_ingest(
                capture,
                flame_model,
                run.work_dir,
                masks_path=masks,
                regime=cfg.regime,
                timestep=cfg.timestep,
                camera=cfg.camera,
                downsample=cfg.downsample,
                height=cfg.height,
                background=cfg.background,
                progress=progress,
            )
            summary_holder["s"] = s
            run.metrics.update(s.metrics())
            run.outputs.update({"data": str(run.ws.stage_dir("ingest"))})

        opts = StageOptions(ws, preset, config, seed, device, force, verbose, threads)
        manifest = execute_stage(
            "ingest",
            opts,
            cfg,
            body,
            external_inputs=external,
            title="ingest",
            remove_new_workspace_on_failure=True,
            discard_work_on_failure=True,
        )
        if manifest is None:
            return
        s = summary_holder["s"]
        summary_panel("sage ingest", list(s.rows()) + [("wall time", f"{manifest['wall_time_s']:.1f} s")], [("data", ws / "data")])
