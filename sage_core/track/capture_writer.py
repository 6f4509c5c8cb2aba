"""The capture ``sage track`` writes, in the VHAP / GaussianAvatars export layout that ``sage ingest``
reads (formats.md §1): per-timestep FLAME files, ``canonical_flame_param.npz`` and the transforms
files with VHAP's splits. Images and masks are written by the pipeline as it goes."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write_bytes
from ..data.cameras import Camera, camera_to_nerf_frame
from ..flame.params import FlameParams, save_param_npz


@dataclass
class OutFrame:
    """One written image: timestep row (0..T-1), camera index, camera (output pixels), and the ids it
    came from (``timestep_id``: file stem or video frame; ``original``: index in the input's timesteps)."""

    timestep: int
    camera_index: int
    camera_id: str
    camera: Camera
    timestep_id: str
    original: int

    @property
    def name(self) -> str:
        return f"{self.timestep:05d}_{self.camera_index:02d}"


def split_of(timestep: int, n_timesteps: int, train_ratio: float, camera_index: int, val_camera: int | None) -> str:
    """VHAP's split rule: the first ``ceil(train_ratio·T)`` timesteps are train (val for ``val_camera``),
    the rest test."""
    n_train = max(1, min(n_timesteps, math.ceil(train_ratio * n_timesteps - 1e-9)))
    if timestep >= n_train:
        return "test"
    return "val" if val_camera is not None and camera_index == val_camera else "train"


def _nerf_frame(f: OutFrame) -> dict[str, Any]:
    return {
        "timestep_index": f.timestep,
        "timestep_index_original": f.original,
        "timestep_id": f.timestep_id,
        "camera_index": f.camera_index,
        "camera_id": f.camera_id,
        **camera_to_nerf_frame(f.camera),
        "file_path": f"images/{f.name}.png",
        "fg_mask_path": f"fg_masks/{f.name}.png",
        "flame_param_path": f"flame_param/{f.timestep:05d}.npz",
    }


def _transforms(frames: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {"frames": frames,
                           "timestep_indices": sorted({f["timestep_index"] for f in frames}),
                           "camera_indices": sorted({f["camera_index"] for f in frames})}
    if frames:
        for k in ("cx", "cy", "fl_x", "fl_y", "h", "w", "camera_angle_x", "camera_angle_y"):
            out[k] = frames[-1][k]
    return out


def write_json(path: Path, obj: Any) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=1) + "\n").encode())


def write_transforms(root: Path, frames: list[OutFrame], n_timesteps: int, train_ratio: float,
                     val_camera: int | None) -> dict[str, int]:
    """``transforms.json`` (all frames) and ``transforms_{train,val,test}.json``; returns frames per split."""
    by_split: dict[str, list[dict[str, Any]]] = {"train": [], "val": [], "test": []}
    for f in sorted(frames, key=lambda f: (f.timestep, f.camera_index)):
        by_split[split_of(f.timestep, n_timesteps, train_ratio, f.camera_index, val_camera)].append(_nerf_frame(f))
    for split, fr in by_split.items():
        write_json(root / f"transforms_{split}.json", _transforms(fr))
    everything = sorted((d for fr in by_split.values() for d in fr), key=lambda d: (d["timestep_index"], d["camera_index"]))
    write_json(root / "transforms.json", _transforms(everything))
    return {k: len(v) for k, v in by_split.items()}


def write_flame_params(root: Path, params: FlameParams) -> None:
    """``flame_param/{ti:05d}.npz`` for every row of ``params`` (VHAP's keys and shapes, written by
    :func:`save_param_npz`) and ``canonical_flame_param.npz`` (zero pose and expression, jaw 0.3 rad
    open, the tracked identity and static offset).

    params: shape (S,), expr (T, E), rotation / neck_pose / jaw_pose / translation (T, 3), eyes_pose (T, 6),
    static_offset (V, 3) or None; row t is written as ``flame_param/{t:05d}.npz``.
    """
    for t in range(params.n_timesteps):
        save_param_npz(root / "flame_param" / f"{t:05d}.npz", params, t)
    zeros3 = np.zeros((1, 3), np.float32)
    canonical = FlameParams(
        shape=params.shape, expr=np.zeros((1, params.n_expr), np.float32), rotation=zeros3, neck_pose=zeros3,
        jaw_pose=np.array([[0.3, 0, 0]], np.float32), eyes_pose=np.zeros((1, 6), np.float32), translation=zeros3,
        static_offset=params.static_offset, dynamic_offset=None, timesteps=np.zeros(1, np.int64),
    )
    save_param_npz(root / "canonical_flame_param.npz", canonical, 0)
