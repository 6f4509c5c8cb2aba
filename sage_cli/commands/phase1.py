"""``sage phase1 WS``: joint optimisation of the surfels, the canonical SDF and the attribute networks."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .._common import (
    require_workspace,
    ConfigOpt,
    console,
    DeviceOpt,
    ForceOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    RenderBackendOpt,
    ThreadsOpt,
    VerboseOpt,
    cli_errors,
    parse_sets,
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
    threads: ThreadsOpt = None,
    render_backend: RenderBackendOpt = None,
) -> None:
    """Train the avatar: surfels bound to FLAME, jointly with the canonical SDF (phase 1)."""
    with cli_errors():

        flags = {"attributes": attributes, "iterations": iterations, "n_surfels": surfels, "render_backend": render_backend, **parse_sets(set_)}
        require_workspace(ws, " (run `sage ingest` and `sage init-mesh` first)")
        ingest_summary = _ingest_summary(ws)
        regime = ingest_summary.get("regime")
        from sage_core.config import load_config_file, resolve_config

        file_data = load_config_file(config) if config is not None else None
        cfg = resolve_config("phase1", preset, file_data, flags, file_label=str(config) if config else "config file",
                             regime=regime if isinstance(regime, str) else None)
        _print_coverage(ingest_summary, verbose)

        def body(run, progress) -> None:
            from sage_core.data.dataset import IngestedData
            from sage_core.train.phase1 import run_phase1

            data = IngestedData.open(run.ws.stage_dir("ingest"))
            metrics = run_phase1(
                data, run.ws.stage_dir("init-mesh"), run.work_dir, cfg, device=run.device, seed=run.seed,
                checkpoint_dir=run.checkpoint_dir, progress=progress,
            )  # fmt: skip
            run.metrics.update({k: v for k, v in metrics.items() if k not in ("final_losses", "exposure_gains")})
            out = run.ws.stage_dir("phase1")
            run.outputs.update({n: str(out / n) for n in ("avatar.pt", "sdf_mesh.ply", "metrics.json", "renders")})

        opts = StageOptions(ws, preset, config, seed, device, force, verbose, threads)
        manifest = execute_stage("phase1", opts, cfg, body, requires=("init-mesh",), title="phase 1")
        if manifest is None:
            return
        m = manifest["metrics"]
        out = ws / "phase1"
        extra = []
        if "test_psnr" in m:
            extra.append(("test PSNR / SSIM", f"{m['test_psnr']:.2f} dB / {m['test_ssim']:.4f}"))
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


def _ingest_summary(ws: Path) -> dict:
    """The workspace's ingest ``summary.json`` (empty when ingest has not run; the stage then reports it)."""
    import json

    from sage_core.errors import InputError
    from sage_core.workspace import Workspace

    path = Workspace(ws).stage_dir("ingest") / "summary.json"
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"cannot read the ingest summary: {e}") from None
    return doc if isinstance(doc, dict) else {}


def _print_coverage(summary: dict, verbose: bool) -> None:
    """Head coverage of a single-camera capture, and the narrow-clip warning."""
    cov = summary.get("coverage")
    if not isinstance(cov, dict):
        return
    from sage_core.data.coverage import Coverage

    c = Coverage.from_dict(cov)
    if verbose:
        console.print(f"[bold]head coverage[/] ({summary.get('regime', '?')}): {c.text()}")
    note = c.warning()
    if note is not None and summary.get("regime") == "sv-hr":
        console.print(f"[yellow]warning:[/] {note}")
