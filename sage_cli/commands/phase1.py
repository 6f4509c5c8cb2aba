"""``sage phase1 WS``: joint optimisation of the surfels, the canonical SDF and the attribute networks."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

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
    parse_sets,
    require_workspace,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageDisplay

if TYPE_CHECKING:
    from sage_core.stages import StageResult


def phase1(
    ws: Annotated[Path, typer.Argument(help="Workspace folder (after `sage init-mesh`).")],
    attributes: Annotated[str | None, typer.Option("--attributes", help="Surfel attributes: mlp (appearance and shape networks) or free (per-surfel).")] = None,
    iterations: Annotated[int | None, typer.Option("--iterations", help="Optimisation steps.")] = None,
    surfels: Annotated[int | None, typer.Option("--surfels", help="Number of surfels.")] = None,
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
    """Train the avatar: surfels bound to FLAME, jointly with the canonical SDF (phase 1)."""
    with cli_errors():

        flags = {"attributes": attributes, "iterations": iterations, "surfels.count": surfels, "render_backend": render_backend, **parse_sets(set_)}
        require_workspace(ws, " (run `sage ingest` and `sage init-mesh` first)")
        from sage_core.stages import StageSettings, phase1_stage, workspace_regime

        cfg = resolve_stage_config("phase1", preset, config, flags, regime=workspace_regime(ws))
        with StageDisplay(verbose, preset) as display:
            r = phase1_stage(ws, cfg, StageSettings(seed, device, force, threads), display)
        if not r.skipped:
            show(r, ws)


def show(r: StageResult, ws: Path) -> None:
    """The closing panel of a finished (not skipped) phase1 result (``sage phase1``, ``sage run``)."""
    manifest = r.manifest
    m = manifest["metrics"]
    out = ws / "phase1"
    extra = []
    if "test_psnr" in m:
        extra.append(("test PSNR / SSIM", f"{m['test_psnr']:.2f} dB / {m['test_ssim']:.4f}" if m.get("test_images", 1) else "no test frames"))
    if "exposure_gain_min" in m:
        extra.append(("exposure gains", f"{m['exposure_gain_min']:.3f} .. {m['exposure_gain_max']:.3f}"))
    if "pseudo_views" in m:
        extra.append(("pseudo views", str(m["pseudo_views"])))
    if "pose_refine_rotation_mean_deg" in m:
        extra.append(("pose corrections (mean)", f"rotation {m['pose_refine_rotation_mean_deg']:.3f} deg, neck "
                      f"{m['pose_refine_neck_mean_deg']:.3f} deg, translation {m['pose_refine_translation_mean_mm']:.3f} mm"))
    summary_panel(
        "sage phase1",
        [
            ("attributes / surfels", f"{m['attributes']} / {m['n_surfels']}"),
            ("val PSNR / SSIM", f"{m['val_psnr']:.2f} dB / {m['val_ssim']:.4f}" if m.get("val_images", 1) else "no val frames"),
            ("train PSNR / SSIM", f"{m['train_psnr']:.2f} dB / {m['train_ssim']:.4f}"),
            *extra,
            ("SDF Chamfer to the mesh", f"{m['chamfer_m'] * 1000:.3f} mm ({m['chamfer_rel'] * 100:.3f} % of the head diagonal)"),
            ("SDF normal error", f"{m['normal_error_deg']:.2f} deg"),
            ("speed", f"{m['iterations_per_s']:.2f} it/s"),
            ("wall time", f"{manifest['wall_time_s']:.1f} s"),
        ],
        [("avatar", out / "avatar.pt"), ("SDF mesh", out / "sdf_mesh.ply"), ("renders", out / "renders"), ("metrics", out / "metrics.json")],
    )
