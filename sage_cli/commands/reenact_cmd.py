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
from typing import Annotated, Any, Optional

import typer

from .._common import DeviceOpt, ProgressDisplay, VerboseOpt, cli_errors, require_workspace, summary_panel


def _seq_label(seq: Path) -> str:
    name = seq.stem if seq.is_file() else seq.name
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "motion"


def _pick_capture_camera(cams: dict[int, Any], index: int | None, source: Path) -> tuple[int, Any]:
    from sage_core.errors import InputError

    if index is not None:
        if index not in cams:
            raise InputError(source, f"no camera {index} in this capture (cameras: {sorted(cams)})")
        return index, cams[index]
    i = 8 if 8 in cams else sorted(cams)[0]
    return i, cams[i]


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
    out: Annotated[Optional[Path], typer.Option("--out", help="Output folder (default: WS/reenact/<name>, or <bundle>/reenact/<name>).")] = None,
    device: DeviceOpt = "auto",
    verbose: VerboseOpt = True,
) -> None:
    """Drive the avatar with a FLAME sequence (self- or cross-reenactment) and write frames and an MP4."""
    with cli_errors():
        from sage_core.errors import ConfigError

        if flame_seq is None:
            raise ConfigError("--flame-seq is required (a motion .npz, a flame_param folder or a capture)")
        if (ws is None) == (bundle is None):
            raise ConfigError("give either a workspace WS or --bundle DIR (exactly one)")
        if orbit and (camera is not None or cameras_from is not None):
            raise ConfigError("--orbit cannot be combined with --camera or --cameras-from")
        if frame_format not in ("png", "exr", "none"):
            raise ConfigError(f"--format must be png, exr or none, got {frame_format!r}")
        if frame_format == "none" and not video:
            raise ConfigError("nothing to write: --format none with --no-video")
        if fps is not None and not fps > 0:
            raise ConfigError(f"--fps must be positive, got {fps}")
        if max_frames is not None and max_frames < 1:
            raise ConfigError(f"--max-frames must be >= 1, got {max_frames}")
        if ws is not None:
            require_workspace(ws)
        if name is not None and (not name or "/" in name or name in (".", "..")):
            raise ConfigError(f"--name must be a plain folder name, got {name!r}")
        run_reenact(
            ws=ws, flame_seq=flame_seq, camera=camera, cameras_from=cameras_from, orbit=orbit, orbit_arc=orbit_arc,
            orbit_elevation=orbit_elevation, frame_format=frame_format, video=video, name=name, stage=stage, fps=fps,
            max_frames=max_frames, bundle=bundle, out=out, device=device, verbose=verbose,
        )  # fmt: skip


def run_reenact(
    *,
    ws: Path | None,
    flame_seq: Path,
    camera: int | None = None,
    cameras_from: Path | None = None,
    orbit: bool = False,
    orbit_arc: float = 360.0,
    orbit_elevation: float = 0.0,
    frame_format: str = "png",
    video: bool = True,
    name: str | None = None,
    stage: str = "auto",
    fps: float | None = None,
    max_frames: int | None = None,
    bundle: Path | None = None,
    out: Path | None = None,
    device: str = "auto",
    verbose: bool = True,
) -> dict[str, Any]:
    """The body of ``sage reenact`` (options already checked); returns what ``reenact.json`` holds."""
    import numpy as np

    from sage_core.data.capture import read_capture
    from sage_core.errors import ConfigError, InputError
    from sage_core.export.motion import load_motion, orbit_cameras
    from sage_core.export.reenact import reenact as run_engine
    from sage_core.train.pipeline import AvatarRenderer, check_motion_for_avatar, with_identity
    from sage_core.workspace import atomic_write_json, now_iso, resolve_device

    dev = resolve_device(device)
    # ---- the avatar
    if bundle is not None:
        from sage_core.export.bundle import load_bundle

        b = load_bundle(bundle, dev)
        avatar, settings, ref_cam, centre = b.avatar, b.render, b.reference_camera, b.head_center
        avatar_label = f"bundle {b.root}"
        data = None
    else:
        assert ws is not None
        from sage_core.data.dataset import IngestedData
        from sage_core.train.pipeline import head_center, load_stage_avatar, reference_camera, resolve_avatar_stage
        from sage_core.workspace import Workspace

        w = Workspace(ws)
        w.require("ingest", "reenact")
        av_stage = resolve_avatar_stage(w, stage, "reenact")
        data = IngestedData.open(w.stage_dir("ingest"))
        loaded = load_stage_avatar(w, av_stage, data, dev)
        avatar, settings = loaded.avatar, loaded.render
        ref_cam = reference_camera(data, camera if cameras_from is None else None)
        centre = head_center(data)
        avatar_label = f"{av_stage} ({loaded.path})"

    # ---- the motion (validated before anything renders)
    motion = load_motion(flame_seq, n_expr=avatar.params.n_expr)
    if max_frames is not None and max_frames < motion.n_frames:
        motion.params = motion.params.select(list(range(max_frames)))
    check_motion_for_avatar(avatar, motion)
    n = motion.n_frames

    # ---- the cameras
    if orbit:
        if ref_cam is None or centre is None:
            raise InputError(bundle or ws, "no reference camera or head centre to orbit around")
        c2w = np.linalg.inv(ref_cam.w2c)
        up = -c2w[:3, 1]
        radius = float(np.linalg.norm(ref_cam.center - centre))
        cams = orbit_cameras(centre, radius, n, ref_cam.K, ref_cam.width, ref_cam.height,
                             elevation_deg=orbit_elevation, arc_deg=orbit_arc, up=up)  # fmt: skip
        cam_label, cam_desc = "orbit", f"orbit of {n} views, radius {radius:.3f} m, arc {orbit_arc:g} deg"
    elif cameras_from is not None:
        src = Path(cameras_from).resolve()
        if motion.source_kind == "capture" and motion.source == src and motion.cameras:
            other = motion.cameras
        else:
            other = dict(read_capture(src, check_images=False).cameras)
        idx, cam = _pick_capture_camera(other, camera, src)
        if ref_cam is not None and cam.height != ref_cam.height:
            h = ref_cam.height
            cam = cam.resized(max(1, int(round(cam.width * h / cam.height))), h)
        cams = cam
        cam_label, cam_desc = f"{src.name}-cam{idx:02d}", f"camera {idx} of {src} ({cam.width}x{cam.height})"
    else:
        if bundle is not None:
            if ref_cam is None:
                raise ConfigError("this bundle has no reference camera: use --orbit or --cameras-from CAPTURE")
            if camera is not None and camera != ref_cam.index:
                raise ConfigError(f"a bundle carries only its reference camera ({ref_cam.index}); use --cameras-from CAPTURE --camera {camera}")
        assert ref_cam is not None
        cams = ref_cam
        cam_label, cam_desc = f"cam{ref_cam.index:02d}", f"camera {ref_cam.index} of this capture ({ref_cam.width}x{ref_cam.height})"

    label = name or f"{_seq_label(Path(flame_seq))}-{cam_label}"
    if out is not None:
        out_dir = Path(out)
    elif ws is not None:
        out_dir = Path(ws) / "reenact" / label
    else:
        assert bundle is not None
        out_dir = Path(bundle) / "reenact" / label

    if ws is not None:
        from .._common import setup_logging

        setup_logging(Path(ws).resolve(), "reenact", verbose)
    renderer = AvatarRenderer(avatar, settings)

    def render_fn(inputs, cam):
        return renderer.render(cam, with_identity(avatar, inputs))

    with ProgressDisplay(f"reenact {label}", enabled=verbose) as progress:
        report = run_engine(render_fn, motion, cams, out_dir, frames_format=frame_format, video=video, fps=fps,
                            device=avatar.device, progress=progress)  # fmt: skip
    doc = {
        "finished_at": now_iso(),
        "avatar": avatar_label,
        "motion": {"source": str(Path(motion.source).resolve()), "kind": motion.source_kind, "frames": n,
                   "timesteps": [int(t) for t in motion.timesteps]},
        "identity": "the avatar's own shape and static offset; expressions and poses from the motion",
        "cameras": cam_desc,
        "render": settings.to_dict(),
        "report": report.to_dict(),
    }
    atomic_write_json(out_dir / "reenact.json", doc)
    rows = [
        ("avatar", avatar_label),
        ("motion", f"{motion.source} ({motion.source_kind}, {n} frames)"),
        ("cameras", cam_desc),
        ("rendered FPS", f"{report.render_fps:.2f} frames/s (render only; {report.total_fps:.2f} with image and video IO)"),
        ("frame size", f"{report.width}x{report.height}"),
        ("video fps", report.fps),
    ]
    paths = []
    if report.frames_dir is not None:
        paths.append((f"frames ({report.frame_format})", report.frames_dir))
    if report.video_path is not None:
        paths.append(("video", report.video_path))
    paths.append(("record", out_dir / "reenact.json"))
    summary_panel("sage reenact", rows, paths)
    return doc
