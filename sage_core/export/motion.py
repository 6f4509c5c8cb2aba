"""Driving motion for reenactment: FLAME expression and pose sequences, and orbit cameras.

A motion comes from one of three sources (docs/formats.md §1.3, §7.2):

- a GaussianAvatars motion npz: T-leading float32 ``expr, rotation, neck_pose, jaw_pose,
  eyes_pose, translation`` and optionally ``dynamic_offset (T,V,3)`` and a scalar ``fps``;
- a folder of per-timestep VHAP files ``*.npz`` (sorted by name), or a folder holding
  ``flame_param/`` with them;
- another capture (a VHAP export with ``transforms*.json``): its timesteps in order, and its
  cameras in :attr:`Motion.cameras`.

Only the dynamic part is kept. ``shape`` and ``static_offset`` of the source are ignored, so the
driven avatar keeps its own identity (cross-reenactment). Everything is validated when the motion
is loaded, before anything renders; in particular every T-leading key must have the same number of
rows (GaussianAvatars indexes past the end on a mismatch, docs/formats.md §7.2).
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..data.cameras import Camera, look_at
from ..errors import InputError
from ..flame.params import DYNAMIC_KEYS, FlameParams, expr_overflow, params_from_arrays, stack_params
from ..npz import read_npz

if TYPE_CHECKING:
    import torch

DEFAULT_FPS = 25.0
SOURCE_KINDS: tuple[str, ...] = ("npz", "flame_param_folder", "capture")
_WIDTHS: dict[str, int | None] = {
    "expr": None, "rotation": 3, "neck_pose": 3, "jaw_pose": 3, "eyes_pose": 6, "translation": 3,
}


@dataclass
class Motion:
    """A driving sequence of FLAME parameters.

    Attributes:
        params: the dynamic parameters, T rows: ``expr (T,E)``, ``rotation, neck_pose, jaw_pose,
            translation (T,3)``, ``eyes_pose (T,6)``, optional ``dynamic_offset (T,V,3)``;
            ``shape`` is (0,) and ``static_offset`` None (the avatar's identity is used).
        source: the file or folder it was read from.
        source_kind: "npz", "flame_param_folder" or "capture".
        fps: frames per second (the file's ``fps`` when present, else 25).
        cameras: camera index -> camera of the source capture (capture sources only), else None.
    """

    params: FlameParams
    source: Path
    source_kind: str
    fps: float = DEFAULT_FPS
    cameras: dict[int, Camera] | None = None

    @property
    def n_frames(self) -> int:
        return self.params.n_timesteps

    @property
    def timesteps(self) -> np.ndarray:
        """(T,) int64 source timestep of each frame (capture timesteps, file numbers, or 0..T-1)."""
        return self.params.timesteps

    def frame_inputs(self, i: int, device: str | torch.device = "cpu",
                     dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
        """``FlameModel.forward`` keyword arguments of frame ``i``, batch 1, without identity.

        Returns ``expr (1,E)``, ``rotation, neck_pose, jaw_pose, translation (1,3)``,
        ``eyes_pose (1,6)`` and, when the motion has one, ``dynamic_offset (1,V,3)``; float32 unless
        ``dtype`` is given. IndexError for ``i`` outside ``[0, n_frames)``.
        """
        import torch

        if not 0 <= int(i) < self.n_frames:
            raise IndexError(f"frame {i} is outside the motion's {self.n_frames} frames")
        i = int(i)
        dt = torch.float32 if dtype is None else dtype

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a[i : i + 1]), device=device).to(dt)

        out = {k: t(getattr(self.params, k)) for k in DYNAMIC_KEYS}
        if self.params.dynamic_offset is not None:
            out["dynamic_offset"] = t(self.params.dynamic_offset)
        return out


def _dynamic_only(params: FlameParams) -> FlameParams:
    return replace(params, shape=np.zeros((0,), np.float32), static_offset=None)


def _fit_expr(params: FlameParams, n_expr: int | None) -> FlameParams:
    """Truncate or zero-pad the expression columns to ``n_expr``."""
    if n_expr is None or n_expr == params.n_expr:
        return params
    if n_expr <= 0:
        raise ValueError(f"n_expr must be positive, got {n_expr}")
    expr = params.expr[:, :n_expr]
    if expr.shape[1] < n_expr:
        expr = np.pad(expr, ((0, 0), (0, n_expr - expr.shape[1])))
    return replace(params, expr=np.ascontiguousarray(expr, dtype=np.float32))


def _read_fps(path: Path, arrays: dict[str, np.ndarray]) -> float:
    if "fps" not in arrays:
        return DEFAULT_FPS
    raw = np.asarray(arrays["fps"])
    if raw.size != 1 or not (np.issubdtype(raw.dtype, np.floating) or np.issubdtype(raw.dtype, np.integer)):
        raise InputError(path, f"key 'fps' must be one number, got shape {raw.shape} and dtype {raw.dtype}")
    fps = float(raw.reshape(-1)[0])
    if not math.isfinite(fps) or fps <= 0:
        raise InputError(path, f"key 'fps' must be a positive number, got {fps}")
    return fps


def check_motion_arrays(path: str | Path, arrays: dict[str, np.ndarray]) -> int:
    """Check that the T-leading keys of a motion file agree on T; returns T.

    arrays: the raw npz contents. Checks that every key of ``expr, rotation, neck_pose,
    jaw_pose, eyes_pose, translation`` is present and 2-D with the right width, that
    ``dynamic_offset`` (if present) is (T,V,3), and that they all have the same T >= 1.
    Raises InputError(path, ...) listing every key with its row count on a mismatch.
    """
    path = Path(path)
    missing = [k for k in DYNAMIC_KEYS if k not in arrays]
    if missing:
        raise InputError(path, "motion file lacks key(s) " + ", ".join(f"'{k}'" for k in missing))
    rows: dict[str, int] = {}
    for key, width in _WIDTHS.items():
        a = np.asarray(arrays[key])
        if a.ndim != 2 or (width is not None and a.shape[1] != width) or a.shape[1] == 0:
            want = f"(T,{'E' if width is None else width})"
            raise InputError(path, f"key '{key}' has shape {tuple(a.shape)}, expected {want}")
        rows[key] = int(a.shape[0])
    if "dynamic_offset" in arrays:
        d = np.asarray(arrays["dynamic_offset"])
        if d.ndim != 3 or d.shape[2] != 3 or d.shape[1] == 0:
            raise InputError(path, f"key 'dynamic_offset' has shape {tuple(d.shape)}, expected (T,V,3)")
        rows["dynamic_offset"] = int(d.shape[0])
    counts = sorted(set(rows.values()))
    if len(counts) > 1:
        listing = ", ".join(f"'{k}' has {n}" for k, n in rows.items())
        raise InputError(path, f"keys disagree on the number of frames T ({listing} rows)")
    T = counts[0]
    if T == 0:
        raise InputError(path, "motion file holds no frames (T = 0)")
    return T


def _load_npz_motion(path: Path) -> Motion:
    arrays = read_npz(path, "motion file")
    check_motion_arrays(path, arrays)
    fps = _read_fps(path, arrays)
    keep = {k: arrays[k] for k in (*DYNAMIC_KEYS, "dynamic_offset") if k in arrays}
    params = params_from_arrays(path, keep, require_shape=False)
    return Motion(params=_dynamic_only(params), source=path, source_kind="npz", fps=fps)


def _file_timesteps(files: list[Path]) -> np.ndarray:
    """Integer file stems (``00012.npz`` -> 12) when all are distinct integers, else 0..n-1."""
    try:
        ts = np.array([int(p.stem) for p in files], dtype=np.int64)
    except ValueError:
        return np.arange(len(files), dtype=np.int64)
    return ts if np.unique(ts).shape[0] == ts.shape[0] else np.arange(len(files), dtype=np.int64)


def _load_folder_motion(folder: Path, source: Path) -> Motion:
    files = sorted((p for p in folder.iterdir() if p.suffix == ".npz" and p.is_file()), key=lambda p: p.name)
    if not files:
        raise InputError(folder, "no FLAME parameter files (*.npz) in this folder")
    items: list[FlameParams] = []
    fps: float | None = None
    for p in files:
        arrays = read_npz(p, "motion file")
        T = check_motion_arrays(p, arrays)
        if T != 1:
            raise InputError(p, f"per-timestep FLAME file holds {T} rows, expected 1 (expr (1,E))")
        if fps is None and "fps" in arrays:
            fps = _read_fps(p, arrays)
        keep = {k: arrays[k] for k in (*DYNAMIC_KEYS, "dynamic_offset") if k in arrays}
        items.append(_dynamic_only(params_from_arrays(p, keep, require_shape=False)))
    ts = _file_timesteps(files)
    for item, t in zip(items, ts):
        item.timesteps = np.array([t], dtype=np.int64)
    params = stack_params(items, files)
    return Motion(params=params, source=source, source_kind="flame_param_folder",
                  fps=DEFAULT_FPS if fps is None else fps)


def _is_capture(folder: Path) -> bool:
    names = ("transforms_train.json", "transforms_val.json", "transforms_test.json", "transforms.json")
    return any((folder / n).is_file() for n in names)


def _load_capture_motion(folder: Path) -> Motion:
    from ..data.capture import read_capture

    cap = read_capture(folder, check_images=False)
    return Motion(params=_dynamic_only(cap.params), source=folder, source_kind="capture",
                  fps=DEFAULT_FPS, cameras=dict(cap.cameras))


def load_motion(source: str | Path, *, n_expr: int | None = None) -> Motion:
    """Read and validate a driving motion (see the module docstring for the three source kinds).

    source: a GaussianAvatars motion ``.npz``, a folder of per-timestep ``*.npz`` (or a folder
        holding ``flame_param/``), or a capture folder (``transforms*.json``).
    n_expr: the avatar's number of expression coefficients; the motion's ``expr`` columns are
        zero-padded to it, or truncated when the dropped columns are all (near) zero — non-zero ones
        raise InputError (None keeps them as stored).
    Raises InputError naming the offending file: missing keys, keys that disagree on T, wrong
    shapes, NaN/Inf, unreadable files.
    """
    path = Path(os.path.abspath(source))
    if not path.exists():
        raise InputError(path, "motion source not found")
    if path.is_file():
        motion = _load_npz_motion(path)
    elif _is_capture(path):
        motion = _load_capture_motion(path)
    elif (path / "flame_param").is_dir():
        motion = _load_folder_motion(path / "flame_param", path)
    else:
        motion = _load_folder_motion(path, path)
    if n_expr is not None:
        problem = expr_overflow(motion.params, n_expr)
        if problem is not None:
            raise InputError(path, problem)
    motion.params = _fit_expr(motion.params, n_expr)
    return motion


def orbit_cameras(
    center: np.ndarray,
    radius: float,
    n_frames: int,
    K: np.ndarray,
    width: int,
    height: int,
    elevation_deg: float = 0.0,
    arc_deg: float = 360.0,
    up: tuple[float, float, float] | np.ndarray = (0.0, 1.0, 0.0),
) -> list[Camera]:
    """Cameras on a circle around ``center``, all looking at it (OpenCV, via :func:`look_at`).

    center: (3,) head centre. radius: distance of every camera to it (metres). K: (3, 3).
    The orbit turns about ``up``; azimuth 0 is the +z side of the head (the front in VHAP
    captures, projected onto the plane orthogonal to ``up``). A full ``arc_deg = 360`` starts at
    azimuth 0 and spreads ``n_frames`` cameras without repeating the start; a partial arc spans
    ``[-arc_deg/2, +arc_deg/2]`` endpoints included. ``elevation_deg`` lifts the circle towards
    ``up`` (|elevation| < 90). Returns ``n_frames`` cameras named ``orbit_000``...
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    if not abs(elevation_deg) < 90.0:
        raise ValueError(f"elevation must be in (-90, 90) degrees, got {elevation_deg}")
    c = np.asarray(center, dtype=np.float64).reshape(3)
    u = np.asarray(up, dtype=np.float64).reshape(3)
    u = u / np.linalg.norm(u)
    front = np.array([0.0, 0.0, 1.0]) - u[2] * u
    if np.linalg.norm(front) < 1e-6:
        front = np.array([1.0, 0.0, 0.0]) - u[0] * u
    front /= np.linalg.norm(front)
    side = np.cross(u, front)
    if abs(arc_deg) >= 360.0:
        az = np.deg2rad(np.linspace(0.0, math.copysign(360.0, arc_deg), n_frames, endpoint=False))
    elif n_frames > 1:
        az = np.deg2rad(np.linspace(-arc_deg / 2.0, arc_deg / 2.0, n_frames))
    else:
        az = np.zeros(1)
    el = math.radians(elevation_deg)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    cams: list[Camera] = []
    for i, a in enumerate(az):
        d = math.cos(el) * (math.cos(a) * front + math.sin(a) * side) + math.sin(el) * u
        eye = c + radius * d
        cams.append(Camera(K.copy(), look_at(eye, c, u), int(width), int(height), i, f"orbit_{i:03d}"))
    return cams


def interpolate_keys(keys: dict[str, np.ndarray], steps: int) -> dict[str, np.ndarray]:
    """Linear interpolation between consecutive rows of T-leading arrays.

    keys: name -> (K, ...) key frames. Returns name -> ((K − 1)·steps + 1, ...) float32: ``steps``
    frames from each key to the next, then the last key.
    """
    out: dict[str, np.ndarray] = {}
    for name, a in keys.items():
        a = np.asarray(a, np.float64)
        if a.shape[0] == 1:
            out[name] = a.astype(np.float32)
            continue
        frames = []
        for i in range(a.shape[0] - 1):
            for s in range(steps):
                w = s / steps
                frames.append((1.0 - w) * a[i] + w * a[i + 1])
        frames.append(a[-1])
        out[name] = np.stack(frames).astype(np.float32)
    return out


def write_key_motion(capture: Path, out_path: Path, steps: int, fps: float = 25.0) -> tuple[Path, list[int]]:
    """A GaussianAvatars-style motion npz interpolated between the capture's test timesteps (or its
    training timesteps when it has no test split). Returns (path, key timesteps)."""
    from ..data.capture import read_capture
    from ..workspace import atomic_write_bytes

    cap = read_capture(capture, check_images=False)
    test_ts = sorted({f.timestep for f in cap.split("test")}) or sorted({f.timestep for f in cap.frames})
    p = cap.params.select_timesteps(test_ts)
    keys = {k: np.asarray(getattr(p, k)) for k in DYNAMIC_KEYS}
    if p.dynamic_offset is not None:
        keys["dynamic_offset"] = np.asarray(p.dynamic_offset)
    arrays: dict[str, np.ndarray] = interpolate_keys(keys, steps)
    arrays["fps"] = np.array(fps, np.float32)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(out_path, buf.getvalue())
    return out_path, test_ts
