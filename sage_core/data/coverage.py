"""Coverage diagnostics of a head-turn clip: where the camera sits relative to the head, per frame.

The head's own frame is the FLAME template's: x towards the subject's left, y up, z out of the
face. In a frame with global rotation R0 and neck pose R_n the head bone is turned by R0·R_n, so a
camera centre C seen from the head centre c (the posed mesh's mean vertex) has head coordinates

    v = (R0·R_n)ᵀ·(C − c),   yaw = atan2(v_x, v_z),   pitch = atan2(v_y, √(v_x² + v_z²))

(degrees; yaw 0 = frontal, positive yaw = the camera on the subject's left, positive pitch = seen
from above). A clip whose yaw does not reach ±``threshold`` on both sides is *narrow*: the sides of
the head it misses are left to the SDF prior and the symmetry term.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

DEFAULT_THRESHOLD_DEG = 45.0


def camera_angles(camera_centres: np.ndarray, head_rotations: np.ndarray, head_centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw and pitch (degrees) of cameras relative to heads.

    camera_centres: (T, 3) world camera centres; head_rotations: (T, 3, 3) world-from-head
    rotations; head_centres: (T, 3) -> yaw (T,), pitch (T,).
    """
    C = np.asarray(camera_centres, np.float64)
    R = np.asarray(head_rotations, np.float64)
    c = np.asarray(head_centres, np.float64)
    v = np.einsum("tji,tj->ti", R, C - c)  # Rᵀ (C − c)
    yaw = np.degrees(np.arctan2(v[:, 0], v[:, 2]))
    pitch = np.degrees(np.arctan2(v[:, 1], np.hypot(v[:, 0], v[:, 2])))
    return yaw, pitch


@dataclass
class Coverage:
    """Per-frame camera angles relative to the head and their range.

    yaw, pitch: (T,) degrees (module doc); timesteps: (T,) the frames' timesteps; threshold: the
    yaw (degrees) a clip must reach on both sides not to be narrow.
    """

    yaw: np.ndarray
    pitch: np.ndarray
    timesteps: np.ndarray
    threshold: float = DEFAULT_THRESHOLD_DEG

    @property
    def yaw_range(self) -> tuple[float, float]:
        return float(self.yaw.min()), float(self.yaw.max())

    @property
    def pitch_range(self) -> tuple[float, float]:
        return float(self.pitch.min()), float(self.pitch.max())

    @property
    def narrow(self) -> bool:
        """True when the yaw does not reach −threshold and +threshold."""
        lo, hi = self.yaw_range
        return lo > -self.threshold or hi < self.threshold

    def text(self) -> str:
        """One line: yaw and pitch ranges."""
        (a, b), (c, d) = self.yaw_range, self.pitch_range
        return f"yaw {a:+.0f}° .. {b:+.0f}°, pitch {c:+.0f}° .. {d:+.0f}° over {len(self.yaw)} frame(s)"

    def warning(self) -> str | None:
        """The narrow-coverage warning, or None."""
        if not self.narrow:
            return None
        lo, hi = self.yaw_range
        return (f"the clip covers yaw {lo:+.0f}° .. {hi:+.0f}° relative to the head, narrower than "
                f"±{self.threshold:.0f}°: unseen parts of the head are shaped only by the SDF prior and the "
                "left-right symmetry term")

    def metrics(self) -> dict[str, Any]:
        """Flat JSON-safe numbers for a manifest."""
        (a, b), (c, d) = self.yaw_range, self.pitch_range
        return {
            "coverage_yaw_min_deg": a,
            "coverage_yaw_max_deg": b,
            "coverage_pitch_min_deg": c,
            "coverage_pitch_max_deg": d,
            "coverage_narrow": bool(self.narrow),
        }

    def to_dict(self) -> dict[str, Any]:
        """Plain data (JSON-safe), per-frame angles included."""
        return {
            **self.metrics(),
            "threshold_deg": float(self.threshold),
            "timesteps": [int(t) for t in self.timesteps],
            "yaw_deg": [float(x) for x in self.yaw],
            "pitch_deg": [float(x) for x in self.pitch],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Coverage:
        """Inverse of :meth:`to_dict`."""
        return cls(np.asarray(d["yaw_deg"], np.float64), np.asarray(d["pitch_deg"], np.float64),
                   np.asarray(d["timesteps"], np.int64), float(d.get("threshold_deg", DEFAULT_THRESHOLD_DEG)))


def head_poses(model: Any, params: Any, timesteps: Sequence[int], chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """World-from-head rotations (T, 3, 3) = R(rotation)·R(neck_pose) and head centres (T, 3)
    (mean posed vertex) of the given timesteps. model: FlameModelData; params: FlameParams."""
    from ..flame import FlameModel
    from ..geometry.rotations import axis_angle_to_matrix

    flame = FlameModel(model)
    rows = [params.row_of(int(t)) for t in timesteps]
    rots, centres = [], []
    with torch.no_grad():
        for s in range(0, len(rows), chunk):
            sel = params.select(rows[s : s + chunk]).to_torch("cpu", torch.float64)
            out = flame.double()(**sel)
            centres.append(out.vertices.mean(1).numpy())
            R0 = axis_angle_to_matrix(sel["rotation"].reshape(-1, 3))
            Rn = axis_angle_to_matrix(sel["neck_pose"].reshape(-1, 3))
            rots.append((R0 @ Rn).numpy())
    return np.concatenate(rots, 0), np.concatenate(centres, 0)


def coverage_of_frames(model: Any, params: Any, frames: Sequence[tuple[int, Any]], threshold: float = DEFAULT_THRESHOLD_DEG) -> Coverage:
    """Coverage of (timestep, Camera) pairs (cameras in world space, OpenCV w2c)."""
    if not frames:
        raise ValueError("no frames")
    ts = [int(t) for t, _ in frames]
    R, c = head_poses(model, params, ts)
    C = np.stack([_centre(cam) for _, cam in frames])
    yaw, pitch = camera_angles(C, R, c)
    return Coverage(yaw, pitch, np.asarray(ts, np.int64), threshold)


def _centre(cam: Any) -> np.ndarray:
    w2c = np.asarray(cam.w2c, np.float64)
    return -w2c[:3, :3].T @ w2c[:3, 3]
