"""``sage init-mesh WS``: canonical mesh, mouth interior and the SDF pretrained on it."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from .._common import (
    require_workspace,
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
    from sage_core.stages import StageResult


def init_mesh(
    ws: Annotated[Path, typer.Argument(help="Workspace folder (after `sage ingest`).")],
    steps: Annotated[Optional[int], typer.Option("--steps", help="SDF pretraining steps (pretrain.steps).")] = None,
    mouth_interior: Annotated[Optional[bool], typer.Option("--mouth-interior/--no-mouth-interior", help="Add the mouth-interior mesh rigged to the jaw.")] = None,
    mc_resolution: Annotated[Optional[int], typer.Option("--mc-resolution", help="Marching-cubes resolution of the extracted SDF mesh.")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
) -> None:
    """Build the canonical FLAME mesh (+ mouth interior), pretrain the SDF on it, extract its zero level set."""
    with cli_errors():

        flags = {"pretrain.steps": steps, "mouth_interior": mouth_interior, "mc_resolution": mc_resolution, **parse_sets(set_)}
        cfg = resolve_stage_config("init-mesh", preset, config, flags)
        require_workspace(ws, " (run `sage ingest` first)")

        from sage_core.stages import StageSettings, init_mesh_stage

        with StageDisplay(verbose, preset) as display:
            r = init_mesh_stage(ws, cfg, StageSettings(seed, device, force, threads), display)
        if not r.skipped:
            show(r, ws)


def show(r: StageResult, ws: Path) -> None:
    """The closing panel of a finished (not skipped) init-mesh result (``sage init-mesh``, ``sage run``)."""
    manifest = r.manifest
    m = manifest["metrics"]
    out = ws / "init"
    summary_panel(
        "sage init-mesh",
        [
            ("canonical mesh", f"{m['n_vertices']} vertices, {m['n_faces']} faces ({m['n_mouth_faces']} mouth interior)"),
            ("mean |SDF| at vertices", f"{m['mean_abs_sdf_vertices_m'] * 1000:.3f} mm ({m['mean_abs_sdf_rel'] * 100:.3f} % of the head diagonal)"),
            ("normal agreement (mean cos)", m["normal_cos"]),
            ("Chamfer to the mesh", f"{m['chamfer_m'] * 1000:.3f} mm ({m['chamfer_rel'] * 100:.3f} %)"),
            ("wall time", f"{manifest['wall_time_s']:.1f} s"),
        ],
        [("canonical mesh", out / "canonical_mesh.ply"), ("SDF mesh", out / "sdf_mesh.ply"), ("SDF", out / "sdf.pt")],
    )
