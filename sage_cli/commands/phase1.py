"""``sage phase1 WS``: joint optimisation of the surfels, the canonical SDF and the attribute networks."""

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
    VerboseOpt,
    cli_errors,
    parse_sets,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageOptions, execute_stage


def phase1(
    ws: Annotated[Path, typer.Argument(help="Workspace folder (after `sage init-mesh`).")],
    attributes: Annotated[Optional[str], typer.Option("--attributes", help="Surfel attributes: mlp (appearance and shape networks) or free (per-surfel).")] = None,
    iterations: Annotated[Optional[int], typer.Option("--iterations", help="Optimisation steps.")] = None,
    surfels: Annotated[Optional[int], typer.Option("--surfels", help="Number of surfels.")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
) -> None:
    """Train the avatar: surfels bound to FLAME, jointly with the canonical SDF (phase 1)."""
    with cli_errors():
        from sage_core.errors import ConfigError, InputError

        if attributes is not None and attributes not in ("mlp", "free"):
            raise ConfigError(f"--attributes must be mlp or free, got {attributes!r}")
        flags = {"attributes": attributes, "iterations": iterations, "n_surfels": surfels, **parse_sets(set_)}
        cfg = resolve_stage_config("phase1", preset, config, flags)
        if cfg.attributes not in ("mlp", "free"):
            raise ConfigError(f"attributes must be mlp or free, got {cfg.attributes!r}")
        if not ws.is_dir():
            raise InputError(ws, "workspace folder not found (run `sage ingest` and `sage init-mesh` first)")

        def body(run, progress) -> None:
            from sage_core.data.dataset import IngestedData
            from sage_core.train.phase1 import run_phase1

            data = IngestedData.open(run.ws.stage_dir("ingest"))
            metrics = run_phase1(
                data, run.ws.stage_dir("init-mesh"), run.work_dir, cfg, device=run.device, seed=run.seed,
                checkpoint_dir=run.checkpoint_dir, progress=progress,
            )  # fmt: skip
            run.metrics.update({k: v for k, v in metrics.items() if k != "final_losses"})
            out = run.ws.stage_dir("phase1")
            run.outputs.update({n: str(out / n) for n in ("avatar.pt", "sdf_mesh.ply", "metrics.json", "renders")})

        opts = StageOptions(ws, preset, config, seed, device, force, verbose)
        manifest = execute_stage("phase1", opts, cfg, body, requires=("init-mesh",), title="phase 1")
        if manifest is None:
            return
        m = manifest["metrics"]
        out = ws / "phase1"
        summary_panel(
            "sage phase1",
            [
                ("attributes / surfels", f"{m['attributes']} / {m['n_surfels']}"),
                ("val PSNR / SSIM", f"{m['val_psnr']:.2f} dB / {m['val_ssim']:.4f}"),
                ("train PSNR / SSIM", f"{m['train_psnr']:.2f} dB / {m['train_ssim']:.4f}"),
                ("SDF Chamfer to the mesh", f"{m['chamfer_m'] * 1000:.3f} mm ({m['chamfer_rel'] * 100:.3f} % of the head diagonal)"),
                ("SDF normal error", f"{m['normal_error_deg']:.2f} deg"),
                ("speed", f"{m['iterations_per_s']:.2f} it/s"),
                ("wall time", f"{manifest['wall_time_s']:.1f} s"),
            ],
            [("avatar", out / "avatar.pt"), ("SDF mesh", out / "sdf_mesh.ply"), ("renders", out / "renders"), ("metrics", out / "metrics.json")],
        )
