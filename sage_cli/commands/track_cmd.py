"""``sage track INPUT OUT``: a capture from photos, a video or a calibrated rig; ``sage track-models``:
install the face models it runs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .._common import ConfigOpt, DeviceOpt, ForceOpt, SeedOpt, SetOpt, ThreadsOpt, VerboseOpt, cli_errors, parse_sets, summary_panel


def track(
    input_path: Annotated[Path, typer.Argument(metavar="INPUT", help="One image, a folder of images, a video (mp4, mov, ...), or a folder of camera folders (with --cameras).")],
    out: Annotated[Path, typer.Argument(help="Capture folder to write (VHAP / GaussianAvatars layout, read by `sage ingest`).")],
    flame_model: Annotated[Path, typer.Option("--flame-model", help="FLAME-format model: official pickle (generic_model.pkl, flame2023.pkl) or a converted .npz.")],
    regime: Annotated[Optional[str], typer.Option("--regime", help="one-shot | sv-hr | mv (mv-sf for one timestep of a rig, mv-mf for several) | mv-sf | mv-mf (default: from the input: one image one-shot, a sequence sv-hr, cameras mv).")] = None,
    cameras: Annotated[Optional[Path], typer.Option("--cameras", help="Calibrated cameras of a multiview input: COLMAP text model (folder, cameras.txt or images.txt) or a VHAP / NeRF transforms.json.")] = None,
    flame_masks: Annotated[Optional[Path], typer.Option("--flame-masks", help="FLAME_masks.pkl region masks (default: beside the model); its scalp region lets the fit add hair volume.")] = None,
    landmark_embedding: Annotated[Optional[Path], typer.Option("--landmark-embedding", help="MediaPipe landmark embedding of the model (FLAME's mediapipe_landmark_embedding.npz, or one an earlier run wrote to OUT/track/); default: calibrated on the model.")] = None,
    models: Annotated[Optional[Path], typer.Option("--models", help="Folder of the MediaPipe face models (default: $SAGE_MEDIAPIPE_DIR, then ~/.cache/sage/mediapipe; see `sage track-models`).")] = None,
    focal: Annotated[Optional[float], typer.Option("--focal", help="Focal length of an uncalibrated camera in pixels of the input images (default: EXIF, else fitted).")] = None,
    fps: Annotated[Optional[float], typer.Option("--fps", help="Video: track this many frames per second (default: every frame).")] = None,
    preset: Annotated[str, typer.Option("--preset", help="tiny (tests: few iterations, small images) or default.")] = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    threads: ThreadsOpt = None,
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
) -> None:
    """Track photos, a video or a calibrated rig with FLAME on the CPU: landmarks, masks, cameras, FLAME parameters, into a capture for `sage ingest` / `sage run`."""
    from .._common import ProgressDisplay

    with cli_errors():
        from sage_core.config import load_config_file
        from sage_core.runtime import apply_threads
        from sage_core.track import resolve_track_config, track_capture
        from sage_core.workspace import resolve_device, seed_everything

        flags = {"regime": regime, "focal": focal, "fps": fps, **parse_sets(set_)}
        cfg = resolve_track_config(preset, load_config_file(config) if config is not None else None, flags)
        dev = resolve_device(device)
        apply_threads(threads)
        seed_everything(seed)
        with ProgressDisplay("track", enabled=verbose, device=dev) as progress:
            r = track_capture(input_path, out, flame_model, cfg, cameras=cameras, flame_masks=flame_masks,
                              landmark_embedding=landmark_embedding, models_dir=models, device=dev, seed=seed, force=force,
                              progress=progress)
        paths = [("capture", out), ("report", out / "track" / "report.json"), ("contact sheet", out / "track" / "contact_sheet.png")]
        summary_panel("sage track", r.rows(), paths)
        from .._common import console

        console.print(f"next: sage run {out} WS --flame-model {flame_model} --regime {r.regime}", soft_wrap=True)


def track_models(
    wheel: Annotated[Optional[Path], typer.Option("--wheel", help="Take the models from this mediapipe 0.10.21 wheel instead of fetching it with pip.")] = None,
    dest: Annotated[Optional[Path], typer.Option("--dir", help="Install into this folder (default: ~/.cache/sage/mediapipe; point $SAGE_MEDIAPIPE_DIR at another one).")] = None,
    check: Annotated[bool, typer.Option("--check", help="Only report whether the models are installed and intact.")] = False,
) -> None:
    """Install the MediaPipe face models `sage track` runs (Apache-2.0): fetch the mediapipe wheel with pip once, take out three files, check their SHA-256."""
    with cli_errors():
        from sage_core.track.weights import MODEL_FILES, find_models, install_models

        if check:
            found = find_models(dest)
            summary_panel("sage track-models", [(mf.name, "ok (SHA-256 checked)") for mf in MODEL_FILES], [("folder", found.folder)])
            return
        found = install_models(dest, wheel)
        summary_panel("sage track-models", [(mf.name, "installed, SHA-256 checked") for mf in MODEL_FILES], [("folder", found.folder)])
