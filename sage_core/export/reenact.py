"""Reenactment: drive an avatar with a motion and write its frames and an MP4, streaming.

The caller's ``render_fn(flame_inputs, camera)`` poses the avatar (its own ``shape`` and
``static_offset``, the motion's dynamic parameters from :meth:`Motion.frame_inputs`) and returns
``(H, W, 3)``. Frames are rendered, written and dropped one at a time.

Output folder ``out_dir``:

- ``frames/{i:05d}.png`` (8-bit, clamped to [0, 1]) or ``frames/{i:05d}.exr`` (half float, values as
  rendered) — written into a hidden temporary folder that replaces ``frames/`` only when every frame
  is done; an interrupted run removes it and leaves the previous ``frames/`` untouched;
- ``video.mp4`` (H.264) — :class:`VideoWriter` writes a temporary file and renames it only on a
  clean close, so an interrupted run never leaves a finished-looking video.

Timing: the render time covers ``render_fn`` up to the finished tensor (CUDA is synchronised before
the clock stops); ``render_fps`` counts that alone, ``total_fps`` the whole run with image and video
IO.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..data.cameras import Camera
from .motion import Motion
from .video import VideoWriter

RenderFn = Callable[[dict[str, torch.Tensor], Camera], torch.Tensor]
"""``render_fn(flame_inputs, camera) -> (H, W, 3)`` float tensor."""

Progress = Callable[[int, int, str], None]
"""``progress(done, total, message)``."""

FRAME_FORMATS: tuple[str, ...] = ("png", "exr", "none")
FRAMES_DIR = "frames"
VIDEO_NAME = "video.mp4"


@dataclass
class ReenactReport:
    """What :func:`reenact` wrote and how fast it ran.

    Attributes:
        n_frames: frames rendered.
        render_fps: frames per second of rendering alone.
        total_fps: frames per second of the whole run (render + image and video IO).
        render_seconds, total_seconds: the corresponding wall times.
        fps: the video frame rate.
        frames_dir: the folder of frame images, or None (``frames_format="none"``).
        frame_format: "png", "exr" or "none".
        video_path: the MP4, or None (``video=False``).
        width, height: frame size in pixels.
    """

    n_frames: int
    render_fps: float
    total_fps: float
    render_seconds: float
    total_seconds: float
    fps: float
    frames_dir: Path | None
    frame_format: str
    video_path: Path | None
    width: int
    height: int
    paths: list[Path] = field(default_factory=list)

    def to_dict(self, relative_to: Path | None = None) -> dict[str, Any]:
        """Plain-data form (paths as strings); ``paths`` lists the top-level outputs.

        relative_to: write the paths relative to this folder (POSIX, with ``..`` steps as needed);
        None keeps them absolute."""

        def path(p: Path | None) -> str | None:
            if p is None:
                return None
            return Path(os.path.relpath(p, relative_to)).as_posix() if relative_to is not None else str(p)

        return {
            "n_frames": self.n_frames,
            "render_fps": self.render_fps,
            "total_fps": self.total_fps,
            "render_seconds": self.render_seconds,
            "total_seconds": self.total_seconds,
            "fps": self.fps,
            "frames_dir": path(self.frames_dir),
            "frame_format": self.frame_format,
            "video_path": path(self.video_path),
            "width": self.width,
            "height": self.height,
            "paths": [path(p) for p in self.paths],
        }


def _camera_list(cameras: Camera | list[Camera], n: int) -> list[Camera]:
    if isinstance(cameras, Camera):
        return [cameras] * n
    cams = list(cameras)
    if len(cams) != n:
        raise ValueError(f"got {len(cams)} cameras for a motion of {n} frames; pass one camera or one per frame")
    if not all(isinstance(c, Camera) for c in cams):
        raise TypeError("cameras must be Camera objects")
    return cams


def _sync(t: torch.Tensor) -> None:
    if t.device.type == "cuda":
        torch.cuda.synchronize(t.device)


def _to_numpy(render: Any, i: int, cam: Camera) -> np.ndarray:
    if not isinstance(render, torch.Tensor):
        raise TypeError(f"render_fn returned {type(render).__name__} for frame {i}, expected a torch.Tensor")
    want = (cam.height, cam.width, 3)
    if tuple(render.shape) != want:
        raise ValueError(f"render_fn returned shape {tuple(render.shape)} for frame {i}; its camera expects {want}")
    return render.detach().to(torch.float32).cpu().numpy()


def reenact(
    render_fn: RenderFn,
    motion: Motion,
    cameras: Camera | list[Camera],
    out_dir: str | Path,
    *,
    frames_format: str = "png",
    video: bool = True,
    fps: float | None = None,
    device: str | torch.device = "cpu",
    progress: Progress | None = None,
) -> ReenactReport:
    """Render every frame of ``motion`` and write frames and/or an MP4 into ``out_dir``.

    render_fn: ``(flame_inputs, camera) -> (H, W, 3)`` float tensor, H×W the camera's size;
        ``flame_inputs`` are :meth:`Motion.frame_inputs` on ``device`` (batch 1, no identity).
        It runs under ``torch.no_grad()`` (use ``torch.enable_grad()`` inside if it needs autograd).
    cameras: one camera for every frame, or a list with one camera per frame; all must have the
        same size when ``video`` is True.
    frames_format: "png" (8-bit), "exr" (half float) or "none".
    video: write ``out_dir/video.mp4``. fps: its frame rate (default: ``motion.fps``).
    progress: ``progress(done, total, message)`` after each frame.
    Raises ValueError for an unknown format, nothing to write, a wrong number of cameras, mixed
    camera sizes with a video, or a render of the wrong shape.
    """
    if frames_format not in FRAME_FORMATS:
        raise ValueError(f"frames_format must be one of {', '.join(FRAME_FORMATS)}, got {frames_format!r}")
    if frames_format == "none" and not video:
        raise ValueError("nothing to write: frames_format is 'none' and video is off")
    n = motion.n_frames
    cams = _camera_list(cameras, n)
    sizes = {(c.width, c.height) for c in cams}
    if video and len(sizes) > 1:
        raise ValueError(f"a video needs one frame size, the cameras have {sorted(sizes)}")
    rate = float(motion.fps if fps is None else fps)
    if not rate > 0:
        raise ValueError(f"fps must be positive, got {rate}")
    width, height = cams[0].width, cams[0].height

    out = Path(out_dir).resolve()  # the report's paths are absolute (its record may write them relative)
    out.mkdir(parents=True, exist_ok=True)
    frames_dir = out / FRAMES_DIR if frames_format != "none" else None
    tmp_frames = out / f".{FRAMES_DIR}.{os.getpid()}.{time.monotonic_ns()}.tmp" if frames_dir else None
    video_path = out / VIDEO_NAME if video else None
    writer = VideoWriter(video_path, fps=rate, width=width, height=height) if video_path else None

    render_s = 0.0
    t_start = time.perf_counter()
    try:
        if tmp_frames is not None:
            tmp_frames.mkdir()
        if writer is not None:
            writer.open()
        with torch.no_grad():
            for i in range(n):
                inputs = motion.frame_inputs(i, device)
                t0 = time.perf_counter()
                img = render_fn(inputs, cams[i])
                if isinstance(img, torch.Tensor):
                    _sync(img)
                render_s += time.perf_counter() - t0
                arr = _to_numpy(img, i, cams[i])
                del img, inputs
                if tmp_frames is not None:
                    from ..data.imageio import write_image

                    write_image(tmp_frames / f"{i:05d}.{frames_format}", arr)
                if writer is not None:
                    writer.write(arr)
                if progress is not None:
                    progress(i + 1, n, f"frame {i + 1}/{n}")
        if writer is not None:
            writer.close()
        if tmp_frames is not None and frames_dir is not None:
            if frames_dir.exists():
                shutil.rmtree(frames_dir)
            os.replace(tmp_frames, frames_dir)
    except BaseException:
        if writer is not None:
            writer.abort()
        if tmp_frames is not None and tmp_frames.exists():
            shutil.rmtree(tmp_frames, ignore_errors=True)
        raise
    total_s = time.perf_counter() - t_start

    paths = [p for p in (frames_dir, video_path) if p is not None]
    return ReenactReport(
        n_frames=n,
        render_fps=n / render_s if render_s > 0 else float("inf"),
        total_fps=n / total_s if total_s > 0 else float("inf"),
        render_seconds=render_s,
        total_seconds=total_s,
        fps=rate,
        frames_dir=frames_dir,
        frame_format=frames_format,
        video_path=video_path,
        width=width,
        height=height,
        paths=paths,
    )
