"""Reenactment: drive an avatar (a workspace's, or an exported bundle) with a FLAME sequence and write
frames and an MP4.

The motion is a GaussianAvatars motion npz, a folder of per-timestep ``flame_param`` npz files, or
another capture (cross-reenactment: its expressions and poses, this avatar's shape and static
offset). Cameras: one camera of this capture (default the val / frontal camera), one camera of
another capture (rescaled to this avatar's image height), or an orbit around the head. Output:
``<out>/frames/*.png|exr``, ``video.mp4`` and ``reenact.json`` (what was rendered and how fast;
its paths are relative to the folder it lies in, so a copied workspace or bundle still finds them).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..workspace import Workspace
from .events import Emitter, EventFn

FRAME_FORMATS: tuple[str, ...] = ("png", "exr", "none")


@dataclass
class ReenactResult:
    """What a reenactment wrote: ``out_dir``, ``record`` (the ``reenact.json`` document), the
    engine's ``report`` (:class:`sage_core.export.reenact.ReenactReport`), the labels of the avatar,
    the motion and the cameras, the files written (``frames``, ``video``, ``record``), the device and
    rasterizer backend, and the wall time of the call."""

    out_dir: Path
    label: str
    record: dict[str, Any]
    report: Any
    avatar_label: str
    motion_label: str
    cameras: str
    duration_s: float = 0.0
    outputs: dict[str, Path] = field(default_factory=dict)
    device: str | None = None
    render_backend: str | None = None
    stage: str = "reenact"


MAX_NAME_BYTES = 255
"""Longest folder name (in UTF-8 bytes) that file systems accept."""
RECORD_NAME = "reenact.json"


def seq_label(seq: Path) -> str:
    """A folder-name-safe label of a motion source (its file stem or folder name), at most 200
    bytes so that the camera's suffix still fits a folder name."""
    name = seq.stem if seq.is_file() else seq.name
    label = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
    return label.encode("utf-8")[:200].decode("utf-8", "ignore") or "motion"


def parse_size(size: str | None) -> tuple[int | None, int] | None:
    """``--size``: "WxH" -> (W, H), "H" -> (None, H) (the width follows the camera's aspect ratio),
    None -> None. ConfigError for anything else or a size below 8 pixels."""
    from ..errors import ConfigError

    if size is None:
        return None
    parts = size.lower().split("x")
    try:
        nums = [int(x) for x in parts]
    except ValueError:
        nums = []
    if len(nums) not in (1, 2) or min(nums) < 8 or max(nums) > 16384:
        raise ConfigError(f"--size {size!r}: give WIDTHxHEIGHT (e.g. 512x744) or a HEIGHT, 8..16384 pixels")
    return (None, nums[0]) if len(nums) == 1 else (nums[0], nums[1])


def sized(cam: Any, size: tuple[int | None, int] | None) -> Any:
    """The camera at the ``--size`` output size (K rescaled per axis), or as it is."""
    if size is None:
        return cam
    w, h = size
    if w is None:
        w = max(1, int(round(cam.width * h / cam.height)))
    return cam if (w, h) == (cam.width, cam.height) else cam.resized(w, h)


def check_reenact_options(*, ws: Path | None, bundle: Path | None, flame_seq: Path | None, camera: int | None = None,
                          cameras_from: Path | None = None, orbit: bool = False, frame_format: str = "png",
                          video: bool = True, fps: float | None = None, max_frames: int | None = None,
                          size: str | None = None) -> None:  # fmt: skip
    """ConfigError for an inconsistent set of reenactment options (before anything is read)."""
    from ..errors import ConfigError

    parse_size(size)

    if flame_seq is None:
        raise ConfigError("--flame-seq is required (a motion .npz, a flame_param folder or a capture)")
    if (ws is None) == (bundle is None):
        raise ConfigError("give either a workspace WS or --bundle DIR (exactly one)")
    if orbit and (camera is not None or cameras_from is not None):
        raise ConfigError("--orbit cannot be combined with --camera or --cameras-from")
    if frame_format not in FRAME_FORMATS:
        raise ConfigError(f"--format must be png, exr or none, got {frame_format!r}")
    if frame_format == "none" and not video:
        raise ConfigError("nothing to write: --format none with --no-video")
    if fps is not None and not fps > 0:
        raise ConfigError(f"--fps must be positive, got {fps}")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames must be >= 1, got {max_frames}")


def check_output_name(name: str | None) -> None:
    """ConfigError unless ``name`` is None or a plain folder name of at most
    :data:`MAX_NAME_BYTES` bytes."""
    import reprlib

    from ..errors import ConfigError

    if name is None:
        return
    if not name or "/" in name or "\0" in name or name in (".", ".."):
        raise ConfigError(f"--name must be a plain folder name, got {reprlib.repr(name)}")
    size = len(name.encode("utf-8", "surrogateescape"))
    if size > MAX_NAME_BYTES:
        raise ConfigError(f"--name is {size} bytes long; a folder name holds at most {MAX_NAME_BYTES} "
                          f"(got {reprlib.repr(name)})")


def check_output_folder(out: Path, force: bool = False) -> None:
    """Refuse an ``--out`` folder that holds files but no ``reenact.json`` (so it is not an earlier
    reenactment's output), unless ``force``: a reenactment replaces ``frames/`` and ``video.mp4``
    in it. InputError when ``out`` is a file, ConfigError for such a folder."""
    from ..errors import ConfigError, InputError

    if out.exists() and not out.is_dir():
        raise InputError(out, "the output path exists and is not a folder")
    if force or not out.is_dir() or (out / RECORD_NAME).is_file() or not any(out.iterdir()):
        return
    raise ConfigError(f"{out} holds files and no {RECORD_NAME}, so it is not an earlier reenactment's folder; "
                      f"a reenactment replaces frames/ and video.mp4 in it: give a new or empty folder, or pass --force")


def _pick_capture_camera(cams: dict[int, Any], index: int | None, source: Path) -> tuple[int, Any]:
    from ..errors import InputError

    if index is not None:
        if index not in cams:
            raise InputError(source, f"no camera {index} in this capture (cameras: {sorted(cams)})")
        return index, cams[index]
    i = 8 if 8 in cams else sorted(cams)[0]
    return i, cams[i]


def orbit_around(ref_cam: Any, centre: Any, n: int, arc_deg: float, elevation_deg: float) -> tuple[list[Any], float]:
    """``n`` cameras on an orbit about ``centre`` (3,) at the reference camera's distance, with its
    focal lengths, its principal point moved to the image centre (so the head is framed in the middle
    even when the reference image was cropped off-centre, e.g. a photo's head near its top edge) and
    its up direction (−y of the camera); returns (cameras, radius in metres)."""
    import numpy as np

    from ..export.motion import orbit_cameras

    c2w = np.linalg.inv(ref_cam.w2c)
    up = -c2w[:3, 1]
    radius = float(np.linalg.norm(ref_cam.center - centre))
    K = np.array(ref_cam.K, dtype=np.float64)
    K[0, 2], K[1, 2] = ref_cam.width / 2.0, ref_cam.height / 2.0
    cams = orbit_cameras(centre, radius, n, K, ref_cam.width, ref_cam.height, elevation_deg=elevation_deg, arc_deg=arc_deg, up=up)
    return cams, radius


def reenact_stage(
    *,
    ws: str | Path | Workspace | None,
    flame_seq: str | Path,
    camera: int | None = None,
    cameras_from: str | Path | None = None,
    orbit: bool = False,
    orbit_arc: float = 360.0,
    orbit_elevation: float = 0.0,
    frame_format: str = "png",
    video: bool = True,
    name: str | None = None,
    stage: str = "auto",
    fps: float | None = None,
    max_frames: int | None = None,
    bundle: str | Path | None = None,
    out: str | Path | None = None,
    device: str = "auto",
    size: str | None = None,
    threads: int | None = None,
    flame_model: str | Path | None = None,
    force: bool = False,
    on_event: EventFn | None = None,
) -> ReenactResult:
    """Render the avatar of ``ws`` (``stage``: auto, phase1, phase2) or of ``bundle`` driven by
    ``flame_seq`` into ``out`` (default ``WS/reenact/<name>`` or ``<bundle>/reenact/<name>``).

    size: the output size, "WxH" or a height (:func:`parse_size`; default the camera's own).
    threads: CPU threads (None: ``$SAGE_THREADS``, else the idle cores). flame_model: the FLAME
    model file a bundle that does not carry its model was built with (checked by SHA-256 first).
    force: write into an ``out`` that holds other files (:func:`check_output_folder`).
    Options as :func:`check_reenact_options` describes (ConfigError); the motion is validated
    against the avatar before anything renders (InputError naming the source).
    """
    from ..runtime import apply_threads

    from ..data.capture import read_capture
    from ..errors import ConfigError, InputError
    from ..export.reenact import reenact as run_engine
    from .avatars import AvatarRenderer
    from .motion import load_driving_motion, with_identity
    from ..workspace import atomic_write_json, now_iso, resolve_device

    t0 = time.time()
    emitter = Emitter("reenact", on_event)
    emitter.emit("started")
    ws_path = None if ws is None else (ws.root if isinstance(ws, Workspace) else Path(ws))
    bundle = None if bundle is None else Path(bundle)
    cameras_from = None if cameras_from is None else Path(cameras_from)
    flame_seq = Path(flame_seq)
    check_reenact_options(ws=ws_path, bundle=bundle, flame_seq=flame_seq, camera=camera, cameras_from=cameras_from, orbit=orbit,
                          frame_format=frame_format, video=video, fps=fps, max_frames=max_frames, size=size)  # fmt: skip
    check_output_name(name)
    if out is not None:
        check_output_folder(Path(out), force)
    out_size = parse_size(size)
    dev = resolve_device(device)
    n_threads = apply_threads(threads)
    # ---- the avatar
    if bundle is not None:
        from ..export.bundle import load_bundle

        b = load_bundle(bundle, dev, flame_model=flame_model)
        avatar, settings, ref_cam, centre = b.avatar, b.render, b.reference_camera, b.head_center
        avatar_label = "bundle"
        avatar_path = Path(b.root)
    else:
        assert ws_path is not None
        from ..data.dataset import IngestedData
        from .avatars import head_center, load_stage_avatar, reference_camera, resolve_avatar_stage

        w = Workspace(ws_path)
        w.require("ingest", "reenact")
        av_stage = resolve_avatar_stage(w, stage, "reenact")
        data = IngestedData.open(w.stage_dir("ingest"))
        loaded = load_stage_avatar(w, av_stage, data, dev)
        avatar, settings = loaded.avatar, loaded.render
        ref_cam = reference_camera(data, camera if cameras_from is None else None)
        centre = head_center(data)
        avatar_label = f"{av_stage} of the workspace"
        avatar_path = Path(loaded.path)

    # ---- the motion (validated before anything renders)
    motion = load_driving_motion(avatar, flame_seq, max_frames)
    n = motion.n_frames

    # ---- the cameras
    if orbit:
        if ref_cam is None or centre is None:
            raise InputError(bundle or ws_path, "no reference camera or head centre to orbit around")
        cams, radius = orbit_around(sized(ref_cam, out_size), centre, n, orbit_arc, orbit_elevation)
        cam_label, cam_desc = "orbit", f"orbit of {n} views, radius {radius:.3f} m, arc {orbit_arc:g} deg"
    elif cameras_from is not None:
        src = cameras_from.resolve()
        if motion.source_kind == "capture" and motion.source == src and motion.cameras:
            other = motion.cameras
        else:
            other = dict(read_capture(src, check_images=False).cameras)
        idx, cam = _pick_capture_camera(other, camera, src)
        if ref_cam is not None and cam.height != ref_cam.height:
            h = ref_cam.height
            cam = cam.resized(max(1, int(round(cam.width * h / cam.height))), h)
        cam = sized(cam, out_size)
        cams = cam
        cam_label, cam_desc = f"{src.name}-cam{idx:02d}", f"camera {idx} of {src} ({cam.width}x{cam.height})"
    else:
        if bundle is not None:
            if ref_cam is None:
                raise ConfigError("this bundle has no reference camera: use --orbit or --cameras-from CAPTURE")
            if camera is not None and camera != ref_cam.index:
                raise ConfigError(f"a bundle carries only its reference camera ({ref_cam.index}); use --cameras-from CAPTURE --camera {camera}")
        assert ref_cam is not None
        cams = sized(ref_cam, out_size)
        whose = "the bundle's reference camera (camera" if bundle is not None else "camera"
        cam_label = f"cam{ref_cam.index:02d}"
        cam_desc = (f"{whose} {ref_cam.index} of the capture{')' if bundle is not None else ''}"
                    f" ({cams.width}x{cams.height})")  # fmt: skip

    label = name or f"{seq_label(flame_seq)}-{cam_label}"
    if out is not None:
        out_dir = Path(out)
    elif ws_path is not None:
        out_dir = ws_path / "reenact" / label
    else:
        assert bundle is not None
        out_dir = bundle / "reenact" / label

    if ws_path is not None:
        from ._runner import setup_logging

        setup_logging(ws_path.resolve(), "reenact")
    renderer = AvatarRenderer(avatar, settings)

    def render_fn(inputs, cam):
        return renderer.render(cam, with_identity(avatar, inputs))

    emitter.title = f"reenact {label}"
    emitter.emit("running", title=emitter.title, metrics={"device": dev, "render_backend": renderer.backend, "threads": n_threads})
    report = run_engine(render_fn, motion, cams, out_dir, frames_format=frame_format, video=video, fps=fps,
                        device=avatar.device, progress=emitter)  # fmt: skip
    here = out_dir.resolve()
    home = (ws_path if ws_path is not None else bundle).resolve()  # type: ignore[union-attr]
    doc = {
        "finished_at": now_iso(),
        "avatar": avatar_label,
        "avatar_path": _relative(avatar_path, here, home),
        "motion": {"source": _relative(Path(motion.source), here, home), "kind": motion.source_kind, "frames": n,
                   "timesteps": [int(t) for t in motion.timesteps]},
        "identity": "the avatar's own shape and static offset; expressions and poses from the motion",
        "cameras": cam_desc,
        "render": settings.to_dict(),
        "render_backend": renderer.backend,
        "report": report.to_dict(relative_to=here),
        "threads": n_threads,
        "paths": "relative to this file's folder",
    }
    atomic_write_json(out_dir / RECORD_NAME, doc)
    outputs: dict[str, Path] = {}
    if report.frames_dir is not None:
        outputs["frames"] = Path(report.frames_dir)
    if report.video_path is not None:
        outputs["video"] = Path(report.video_path)
    outputs["record"] = out_dir / RECORD_NAME
    shown = f"{avatar_label} ({avatar_path})"
    result = ReenactResult(out_dir, label, doc, report, shown, f"{motion.source} ({motion.source_kind}, {n} frames)", cam_desc,
                           time.time() - t0, outputs, dev, renderer.backend)  # fmt: skip
    emitter.emit("finished", result=result)
    return result


def _relative(path: Path, base: Path, home: Path) -> str:
    """``path`` relative to the folder ``base`` (POSIX, with ``..`` steps) when it lies in ``home``
    (the workspace or bundle), so that the record keeps pointing at its neighbours when ``home`` is
    copied or moved; a path outside it (a motion elsewhere) stays absolute."""
    p = Path(path).resolve()
    if p != home and home not in p.parents:
        return str(p)
    return Path(os.path.relpath(p, base)).as_posix()
