"""Streaming MP4 writer: frame count, pixel fidelity, odd sizes, atomicity on errors."""

from __future__ import annotations

import imageio_ffmpeg
import numpy as np
import pytest
import torch

from sage_core.export import VideoWriter


def _frames(n: int, h: int, w: int) -> list[np.ndarray]:
    yy, xx = np.mgrid[0:h, 0:w]
    return [
        np.stack([xx / (w - 1), yy / (h - 1), np.full((h, w), i / max(n - 1, 1))], -1)
        for i in range(n)
    ]


def _first_frame(path) -> tuple[np.ndarray, tuple[int, int]]:
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frame = np.frombuffer(next(gen), dtype=np.uint8).reshape(h, w, 3)
    gen.close()
    return frame, (w, h)


def test_ten_frames_round_trip(tmp_path):
    h, w = 48, 64
    frames = _frames(10, h, w)
    path = tmp_path / "out" / "clip.mp4"
    with VideoWriter(path, fps=10, width=w, height=h) as vw:
        for i, f in enumerate(frames):
            vw.write(f if i % 2 else (f * 255).round().astype(np.uint8))
    assert path.is_file()
    assert [p.name for p in path.parent.iterdir()] == ["clip.mp4"]  # no temp file left
    nframes, secs = imageio_ffmpeg.count_frames_and_secs(str(path))
    assert nframes == 10
    assert secs == pytest.approx(1.0, abs=0.15)
    first, size = _first_frame(path)
    assert size == (w, h)
    err = np.abs(first / 255.0 - frames[0]).mean()
    assert err < 0.02


def test_odd_size_is_edge_padded(tmp_path):
    h, w = 33, 47
    frames = [torch.from_numpy(f).float() for f in _frames(3, h, w)]
    path = tmp_path / "odd.mp4"
    with VideoWriter(path, fps=5, width=w, height=h) as vw:
        for f in frames:
            vw.write(f)
    assert (vw.out_width, vw.out_height) == (48, 34)
    first, size = _first_frame(path)
    assert size == (48, 34)
    assert np.abs(first[:h, :w] / 255.0 - frames[0].numpy()).mean() < 0.02


def test_error_leaves_nothing(tmp_path):
    path = tmp_path / "broken.mp4"
    with pytest.raises(ValueError, match="does not match"):
        with VideoWriter(path, fps=5, width=16, height=16) as vw:
            vw.write(np.zeros((16, 16, 3)))
            vw.write(np.zeros((8, 16, 3)))  # wrong size
    assert list(tmp_path.iterdir()) == []


def test_no_frames_is_an_error_and_replaces_nothing(tmp_path):
    path = tmp_path / "empty.mp4"
    path.write_bytes(b"old")
    with pytest.raises(ValueError, match="no frames"):
        with VideoWriter(path, fps=5, width=16, height=16):
            pass
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["empty.mp4"]
