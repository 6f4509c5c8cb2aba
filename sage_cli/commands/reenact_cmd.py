"""``sage reenact WS --flame-seq SEQ``: drive the avatar with a FLAME sequence; frames + MP4.

SEQ is a GaussianAvatars motion npz, a folder of per-timestep ``flame_param`` npz files, or another
capture (cross-reenactment: its expressions and poses, this avatar's shape and static offset).
Cameras: one camera of this capture (``--camera N``; default the val / frontal camera), one camera
of another capture (``--cameras-from CAPTURE [--camera N]``, rescaled to this avatar's image
height), or an orbit around the head (``--orbit``). ``--bundle DIR`` drives an exported avatar
bundle without any workspace. Output: ``WS/reenact/<name>/frames/*.png|exr``, ``video.mp4`` and
``reenact.json`` (what was rendered and how fast).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from .._common import DeviceOpt, ThreadsOpt, VerboseOpt, cli_errors, require_workspace, summary_panel
from .._stage import StageDisplay

if TYPE_CHECKING:
    from sage_core.stages import ReenactResult


def reenact(
    ws: Annotated[Optional[Path], typer.Argument(help="Workspace folder with a trained avatar (omit when using --bundle).")] = None,
    flame_seq: Annotated[Optional[Path], typer.Option("--flame-seq", help="Driving motion: GaussianAvatars motion .npz, folder of flame_param/*.npz, or another capture folder.")] = None,
    camera: Annotated[Optional[int], typer.Option("--camera", help="Camera index of this capture (default: the val / frontal camera), or of --cameras-from.")] = None,
    cameras_from: Annotated[Optional[Path], typer.Option("--cameras-from", help="Take the camera from another capture (with --camera N; default its camera 8 or its first).")] = None,
    orbit: Annotated[bool, typer.Option("--orbit", help="Orbit the camera around the head, one step per frame.")] = False,
    orbit_arc: Annotated[float, typer.Option("--orbit-arc", help="Orbit span in degrees (360: full turn; less: a symmetric arc around the front).")] = 360.0,
    orbit_elevation: Annotated[float, typer.Option("--orbit-elevation", help="Orbit elevation in degrees.")] = 0.0,
    frame_format: Annotated[str, typer.Option("--format", help="Frame images: png (8-bit), exr (half float) or none.")] = "png",
    video: Annotated[bool, typer.Option("--video/--no-video", help="Write video.mp4 (H.264).")] = True,
    name: Annotated[Optional[str], typer.Option("--name", help="Output name: WS/reenact/<name>/ (default: from the sequence and camera).")] = None,
    stage: Annotated[str, typer.Option("--stage", help="Avatar: auto (latest finished of phase2, phase1), phase1 or phase2.")] = "auto",
    fps: Annotated[Optional[float], typer.Option("--fps", help="Video frame rate (default: the motion's, else 25).")] = None,
    max_frames: Annotated[Optional[int], typer.Option("--max-frames", help="Render only the first N frames of the motion.")] = None,
    bundle: Annotated[Optional[Path], typer.Option("--bundle", help="Avatar bundle folder from `sage export --bundle` (no workspace needed).")] = None,
    flame_model: Annotated[Optional[Path], typer.Option("--flame-model", help="With --bundle: the FLAME model file the bundle names (a bundle does not carry the licensed model unless exported with --include-flame-model); checked by SHA-256 before it is read.")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="Output folder (default: WS/reenact/<name>, or <bundle>/reenact/<name>).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Write into an --out folder that holds other files and no reenact.json (its frames/ and video.mp4 are replaced); without it such a folder is refused.")] = False,
    size: Annotated[Optional[str], typer.Option("--size", help="Output size: WIDTHxHEIGHT, or a HEIGHT (the width follows the camera's aspect ratio); the camera's intrinsics are rescaled (default: the camera's own size).")] = None,
    device: DeviceOpt = "auto",
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
) -> None:
    """Drive the avatar with a FLAME sequence (self- or cross-reenactment) and write frames and an MP4."""
    with cli_errors():
        from sage_core.stages.reenact import check_output_folder, check_output_name, check_reenact_options

        check_reenact_options(ws=ws, bundle=bundle, flame_seq=flame_seq, camera=camera, cameras_from=cameras_from, orbit=orbit,
                              frame_format=frame_format, video=video, fps=fps, max_frames=max_frames, size=size)  # fmt: skip
        if ws is not None:
            require_workspace(ws)
        check_output_name(name)
        if out is not None:
            check_output_folder(out, force)
        from sage_core.stages import reenact_stage

        with StageDisplay(verbose) as display:
            r = reenact_stage(ws=ws, flame_seq=flame_seq, camera=camera, cameras_from=cameras_from, orbit=orbit, orbit_arc=orbit_arc,
                              orbit_elevation=orbit_elevation, frame_format=frame_format, video=video, name=name, stage=stage, fps=fps,
                              max_frames=max_frames, bundle=bundle, out=out, device=device, size=size, threads=threads, flame_model=flame_model,
                              force=force, on_event=display)  # fmt: skip
        show(r)


def show(r: ReenactResult) -> None:
    """The closing panel of a reenactment: avatar, motion, cameras, speed and the files written."""
    report = r.report
    rows = [
        ("avatar", r.avatar_label),
        ("motion", r.motion_label),
        ("cameras", r.cameras),
        ("rendered FPS", f"{report.render_fps:.2f} frames/s (render only; {report.total_fps:.2f} with image and video IO)"),
        ("frame size", f"{report.width}x{report.height}"),
        ("video fps", report.fps),
    ]
    paths = []
    if report.frames_dir is not None:
        paths.append((f"frames ({report.frame_format})", report.frames_dir))
    if report.video_path is not None:
        paths.append(("video", report.video_path))
    paths.append(("record", r.out_dir / "reenact.json"))
    summary_panel("sage reenact", rows, paths)
