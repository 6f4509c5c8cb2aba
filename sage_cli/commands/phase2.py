"""``sage phase2 WS``: self-supervised fine-tuning under sampled expressions, SDF frozen."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

from .._common import (
    require_workspace,
    MISSING,
    ConfigOpt,
    DeviceOpt,
    ForceOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    RenderBackendOpt,
    ThreadsOpt,
    VerboseOpt,
    cli_errors,
    fmt_metric,
    parse_sets,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageDisplay

if TYPE_CHECKING:
    from sage_core.stages import StageResult


def _fmt_means(m: dict[str, Any] | None) -> str:
    """PSNR / SSIM / LPIPS means of one evaluation block; the dash for a block or metric not measured."""
    if not m:
        return MISSING
    return f"{fmt_metric(m.get('psnr'), '.2f')} dB / {fmt_metric(m.get('ssim'), '.4f')} / LPIPS {fmt_metric(m.get('lpips'), '.4f')}"


def phase2(
    ws: Annotated[Path, typer.Argument(help="Workspace folder (after `sage phase1`).")],
    correction: Annotated[Optional[str], typer.Option("--correction", help="Surfel correction from the local stretch (correction.mode: affine or the paper's curvature): on or off.")] = None,
    iterations: Annotated[Optional[int], typer.Option("--iterations", help="Optimisation steps.")] = None,
    lpips_weights: Annotated[Optional[Path], typer.Option("--lpips-weights", help="LPIPS AlexNet v0.1 weights for the evaluation (default: $SAGE_LPIPS_WEIGHTS or the cache).")] = None,
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
    """Self-supervised phase 2: sampled expressions, normal consistency, distortion and appearance
    consistency with the canonical volume rendering; the SDF and hash grid stay frozen."""
    with cli_errors():
        from sage_core.errors import ConfigError

        corr: bool | None = None
        if correction is not None:
            if correction.lower() not in ("on", "off"):
                raise ConfigError(f"--correction must be on or off, got {correction!r}")
            corr = correction.lower() == "on"
        flags = {"correction.enabled": corr, "iterations": iterations, "render_backend": render_backend, **parse_sets(set_)}
        cfg = resolve_stage_config("phase2", preset, config, flags)
        require_workspace(ws, " (run `sage ingest`, `sage init-mesh` and `sage phase1` first)")
        from sage_core.stages import StageSettings, phase2_stage

        with StageDisplay(verbose, preset) as display:
            r = phase2_stage(ws, cfg, lpips_weights, StageSettings(seed, device, force, threads), display)
        if not r.skipped:
            show(r, ws)


def show(r: StageResult, ws: Path) -> None:
    """The closing panel of a finished (not skipped) phase2 result (``sage phase2``, ``sage run``)."""
    manifest = r.manifest
    m = manifest["metrics"]
    out = ws / "phase2"
    test = m.get("test") or {}
    rows = [
        ("correction / surfels", f"{'on' if m['correction'] else 'off'} / {m['n_surfels']}"),
        ("self-reenactment (test, all cams)", _fmt_means(test.get("overall"))),
        ("self-reenactment (test, frontal)", _fmt_means(test.get("frontal"))),
        ("novel view (val)", _fmt_means((m.get("val") or {}).get("overall"))),
    ]
    if m.get("phase1_test"):
        rows.append(("phase 1 alone (test, all cams)", _fmt_means(m["phase1_test"].get("overall"))))
    rows += [
        ("distortion, first 100 steps", f"{m['distortion_first100_mean']:.3e}"),
        ("speed", f"{m['iterations_per_s']:.2f} it/s"),
        ("wall time", f"{manifest['wall_time_s']:.1f} s"),
    ]
    summary_panel(
        "sage phase2", rows,
        [("avatar", out / "avatar.pt"), ("metrics", out / "metrics.json"), ("distortion curve", out / "distortion_curve.json"),
         ("evaluation", out / "eval_test")],
    )  # fmt: skip
