"""``sage synth OUT``: write a synthetic FLAME-format head capture with its ground truth."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer

INGEST_SPELLINGS: dict[str, str] = {"one-shot": "oneshot", "one_shot": "oneshot", "sv-hr": "monocular", "mv-sf": "multiview", "mv-mf": "multiview"}
"""``sage ingest``'s regime names, accepted for the synthetic capture of that regime."""


def synth(
    out: Annotated[Path, typer.Argument(help="Folder to write the capture into (VHAP / GaussianAvatars layout).")],
    regime: Annotated[str, typer.Option("--regime", help="multiview (16-camera arc, train/val/test), monocular (one camera, head turns; also sv-hr) or oneshot (one frontal image; also one-shot).")] = "multiview",
    preset: Annotated[str, typer.Option("--preset", help="tiny (128x186 images, seconds on a CPU), small (256x372) or default (550x802, more timesteps).")] = "default",
    cameras: Annotated[Optional[int], typer.Option("--cameras", help="Number of multiview cameras (camera 8 is frontal and held out as val).")] = None,
    width: Annotated[Optional[int], typer.Option("--width", help="Image width in pixels.")] = None,
    height: Annotated[Optional[int], typer.Option("--height", help="Image height in pixels.")] = None,
    train_timesteps: Annotated[Optional[int], typer.Option("--train-timesteps", help="Training timesteps (mild expressions; monocular: head-turn frames).")] = None,
    test_timesteps: Annotated[Optional[int], typer.Option("--test-timesteps", help="Held-out timesteps with novel expressions (monocular: novel head poses).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Identity, texture and expression seed; the same seed writes identical files.")] = 0,
    tracking: Annotated[str, typer.Option("--tracking", help="fitted: the truth deforms beyond the written FLAME-format model and flame_param/ is a tracker-like fit with pose noise (error in gt/info.json); exact: the written model and parameters are the truth.")] = "fitted",
    appearance: Annotated[str, typer.Option("--appearance", help="detailed: pixel-scale skin detail, brows, lashes and hair strands, hair volume off the scalp, and (monocular, oneshot) held-out views all around the head; smooth: the smooth head of earlier versions (same seed, same files).")] = "detailed",
    sets: Annotated[Optional[list[str]], typer.Option("--set", help="Override a synth config field, e.g. --set crease_depth_mm=3 or --set pose_noise_deg=0 (repeatable; fields in docs/synthetic.md).")] = None,
    preview: Annotated[bool, typer.Option("--preview", help="Also write OUT/preview.png, a grid of views x expressions.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace OUT if it already holds files.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose/--quiet", help="Show the progress bar (default) or only errors and the final panel.")] = True,
) -> None:
    """Write a synthetic head capture: images, masks, FLAME parameters, cameras, the FLAME-format model and ground-truth meshes."""
    from .._common import ProgressDisplay, cli_errors, summary_panel

    with cli_errors():
        from sage_core.data.synthetic import preset as make_preset
        from sage_core.data.synthetic import write_capture
        from sage_core.data.synthetic.config import parse_sets

        options = {"seed": seed, "n_cameras": cameras, "width": width, "height": height, "train_timesteps": train_timesteps,
                   "test_timesteps": test_timesteps, "tracking": tracking, "appearance": appearance}
        cfg = make_preset(preset, regime=INGEST_SPELLINGS.get(regime.strip().lower(), regime), **{**options, **parse_sets(sets)})
        t0 = time.time()
        with ProgressDisplay("synth", enabled=verbose) as progress:
            path = write_capture(out, cfg, progress=progress, preview=preview, force=force)
        elapsed = time.time() - t0

        import json

        info = json.loads((path / "gt" / "info.json").read_text())
        counts = info["counts"]
        rows = [
            ("regime", cfg.regime),
            ("seed", cfg.seed),
            ("image size", f"{cfg.width}x{cfg.height}"),
            ("cameras", counts["cameras"]),
            ("timesteps", counts["timesteps"]),
            ("images train/val/test", f"{counts['train_images']}/{counts['val_images']}/{counts['test_images']}"),
            ("model", f"{counts['vertices']} vertices, {counts['faces']} faces"),
            ("tracking", _tracking_row(info)),
            ("appearance", _appearance_row(info)),
            ("wall time", f"{elapsed:.1f} s"),
        ]
        paths = [
            ("capture", path),
            ("flame model", path / info["model"]["pickle"]),
            ("flame masks", path / info["model"]["masks"]),
            ("ground truth", path / "gt"),
        ]
        if "novel" in info:
            paths.append(("held-out views", path / info["novel"]["folder"]))
        if "hair" in info:
            paths.append(("hair volume", path / info["hair"]["folder"]))
        if preview:
            paths.append(("preview", path / "preview.png"))
        summary_panel("sage synth", rows, paths)


def _tracking_row(info: dict) -> str:
    """The tracking line of the summary: exact, or the error of the written parameters."""
    tr = info.get("tracking")
    if not tr:
        return "exact (the written FLAME parameters are the ground truth)"
    err = tr["error"]["all"]
    return f"fitted: vertex error mean {err['mean_mm']:.2f} mm, max {err['max_mm']:.2f} mm over {err['timesteps']} timesteps"


def _appearance_row(info: dict) -> str:
    """The appearance line of the summary: smooth, or the detailed subject's main traits."""
    d = info.get("identity", {}).get("appearance", {}).get("detail")
    if not d:
        return "smooth"
    traits = [f"{d['hair_style']} hair"]
    if d.get("freckles", 0) > 0:
        traits.append("freckles")
    if d.get("stubble", 0) > 0:
        traits.append("stubble")
    return "detailed: " + ", ".join(traits)
