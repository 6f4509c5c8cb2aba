"""Streaming H.264 MP4 writer on top of ``imageio_ffmpeg.write_frames``.

Frames go to a temporary file beside the target (``.<name>.<pid>.<ns>.tmp.mp4``), which is
renamed onto ``path`` only when the writer closes cleanly; on an error or with no frames written the
temporary file is removed and nothing appears at ``path``.

Pixel format yuv420p needs even dimensions: an odd width or height is padded by one column / row
that repeats the last one (edge padding), so the video is ``(width + width % 2) × (height +
height % 2)`` and no frame is rescaled.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from types import TracebackType
from typing import Any, Generator

import numpy as np


def _even(n: int) -> int:
    return n + (n % 2)


class VideoWriter:
    """Context manager writing RGB frames to an H.264 (libx264, yuv420p) MP4.

    path: target ``.mp4`` file. fps: frames per second. width, height: frame size in pixels.
    quality: imageio-ffmpeg quality 0..10 (10 best, larger files); default 8.

    Usage::

        with VideoWriter(out, fps=25, width=w, height=h) as vw:
            for img in frames:          # (H, W, 3) float in [0, 1] or uint8
                vw.write(img)
    """

    def __init__(
        self, path: str | Path, fps: float, width: int, height: int, quality: float = 8.0
    ) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"video size must be positive, got {width}x{height}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        if not 0 <= quality <= 10:
            raise ValueError(f"quality must be in [0, 10], got {quality}")
        self.path = Path(path)
        self.fps = float(fps)
        self.width = int(width)
        self.height = int(height)
        self.quality = float(quality)
        self.out_width = _even(self.width)
        self.out_height = _even(self.height)
        self.frames_written = 0
        self._tmp: Path | None = None
        self._gen: Generator[Any, Any, None] | None = None

    # -- lifecycle -----------------------------------------------------------------------------

    def open(self) -> "VideoWriter":
        """Start ffmpeg on the temporary file (called by ``__enter__``)."""
        if self._gen is not None:
            raise RuntimeError("VideoWriter is already open")
        import imageio_ffmpeg

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(
            f".{self.path.stem}.{os.getpid()}.{time.monotonic_ns()}.tmp.mp4"
        )
        self._gen = imageio_ffmpeg.write_frames(
            str(self._tmp),
            (self.out_width, self.out_height),
            pix_fmt_in="rgb24",
            pix_fmt_out="yuv420p",
            fps=self.fps,
            quality=self.quality,
            codec="libx264",
            macro_block_size=1,
            ffmpeg_log_level="error",
            output_params=["-movflags", "+faststart"],
        )
        self._gen.send(None)
        return self

    def write(self, frame: Any) -> None:
        """Append one frame. frame: (H, W, 3) float in [0, 1] (clipped) or uint8; numpy or torch."""
        if self._gen is None:
            raise RuntimeError("VideoWriter is not open")
        self._gen.send(self._to_rgb24(frame))
        self.frames_written += 1

    def close(self) -> None:
        """Finish the file and rename it onto ``path``. Raises ValueError if no frame was written."""
        if self._gen is None:
            return
        gen, self._gen = self._gen, None
        try:
            gen.close()
            if self.frames_written == 0:
                raise ValueError(f"no frames were written to {self.path}")
            if self._tmp is not None:
                os.replace(self._tmp, self.path)
        finally:
            self._remove_tmp()

    def abort(self) -> None:
        """Stop ffmpeg and delete the temporary file; ``path`` is left untouched."""
        gen, self._gen = self._gen, None
        try:
            if gen is not None:
                gen.close()
        finally:
            self._remove_tmp()

    def __enter__(self) -> "VideoWriter":
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # -- helpers ---------------------------------------------------------------------------------

    def _remove_tmp(self) -> None:
        if self._tmp is not None and self._tmp.exists():
            self._tmp.unlink()

    def _to_rgb24(self, frame: Any) -> bytes:
        """(H, W, 3) float/uint8 -> padded uint8 bytes of (out_height, out_width, 3)."""
        if hasattr(frame, "detach"):
            frame = frame.detach().cpu().numpy()
        a = np.asarray(frame)
        if a.shape != (self.height, self.width, 3):
            raise ValueError(
                f"frame shape {a.shape} does not match the video size "
                f"({self.height}, {self.width}, 3)"
            )
        if a.dtype != np.uint8:
            if not np.issubdtype(a.dtype, np.floating):
                raise ValueError(f"frames must be float in [0, 1] or uint8, got {a.dtype}")
            a = (np.clip(np.nan_to_num(a, nan=0.0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        pad_h, pad_w = self.out_height - self.height, self.out_width - self.width
        if pad_h or pad_w:
            a = np.pad(a, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        return np.ascontiguousarray(a).tobytes()
