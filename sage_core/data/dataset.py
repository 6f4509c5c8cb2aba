"""Read an ingest output folder (``WS/data``): the data every later stage trains and evaluates on."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError, StageError
from .cameras import Camera

if TYPE_CHECKING:
    from ..flame.params import FlameParams

REQUIRED_FILES: tuple[str, ...] = (
    "summary.json", "cameras.json", "frames.json", "flame_params.npz", "flame_model.npz",
)
ROLES: tuple[str, ...] = ("train", "val", "test")


@dataclass
class IngestedFrame:
    """One ingested image.

    Attributes:
        role: "train", "val" (novel view) or "test" (self-reenactment).
        split: the capture split it came from.
        timestep: dataset timestep (``params.row_of(timestep)`` gives its FLAME row).
        camera_index, camera_id: the capture's camera.
        image: absolute path of the RGB PNG.
        mask: absolute path of the mask PNG, or None.
        camera: the camera at the ingested resolution.
    """

    role: str
    split: str
    timestep: int
    camera_index: int
    camera_id: str
    image: Path
    mask: Path | None
    camera: Camera


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise InputError(path, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None


@dataclass
class IngestedData:
    """The ingested data folder.

    Attributes:
        root: the folder.
        cameras: camera_index -> camera at the ingested resolution.
        frames: every ingested frame.
        params: stacked FLAME parameters (every timestep any frame uses).
        model_path: ``flame_model.npz`` (load with ``sage_core.flame.load_flame_model``).
        masks_path: ``flame_masks.json`` or None.
        summary: the contents of ``summary.json``.
    """

    root: Path
    cameras: dict[int, Camera]
    frames: list[IngestedFrame]
    params: FlameParams
    model_path: Path
    masks_path: Path | None
    summary: dict[str, Any]

    @classmethod
    def open(cls, data_dir: str | Path) -> IngestedData:
        """Open and check a complete ingest output folder.

        Raises StageError when the folder or one of its files is missing (ingest has not run or did
        not finish), InputError naming the file when a file is malformed.
        """
        root = Path(data_dir)
        if not root.is_dir():
            raise StageError(f"{root}: no ingested data here; run `sage ingest` first")
        missing = [name for name in REQUIRED_FILES if not (root / name).is_file()]
        if missing:
            raise StageError(
                f"{root}: incomplete ingest output (missing {', '.join(missing)}); run `sage ingest` again"
            )
        summary = _read_json(root / "summary.json")
        if not isinstance(summary, dict) or "canonical_timestep" not in summary:
            raise InputError(root / "summary.json", "not an ingest summary (no 'canonical_timestep')")

        cam_doc = _read_json(root / "cameras.json")
        try:
            cameras = {int(k): Camera.from_dict(v) for k, v in cam_doc["cameras"].items()}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(root / "cameras.json", f"malformed camera entry ({type(exc).__name__}: {exc})") from None

        frames_path = root / "frames.json"
        doc = _read_json(frames_path)
        frames: list[IngestedFrame] = []
        try:
            for e in doc["frames"]:
                img = root / e["image"]
                mask = root / e["mask"] if e.get("mask") else None
                if e["role"] not in ROLES:
                    raise ValueError(f"unknown role {e['role']!r}")
                frames.append(IngestedFrame(
                    role=str(e["role"]), split=str(e.get("split", e["role"])), timestep=int(e["timestep"]),
                    camera_index=int(e["camera_index"]), camera_id=str(e.get("camera_id", "")),
                    image=img, mask=mask, camera=Camera.from_dict(e["camera"]),
                ))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(frames_path, f"malformed frame entry ({type(exc).__name__}: {exc})") from None
        for f in frames:
            for p in (f.image, f.mask):
                if p is not None and not p.is_file():
                    raise StageError(f"{p}: ingested file missing; run `sage ingest --force`")

        from ..flame.params import load_stacked_npz

        params = load_stacked_npz(root / "flame_params.npz")
        known = set(int(t) for t in params.timesteps)
        absent = sorted({f.timestep for f in frames} - known)
        if absent:
            raise InputError(root / "flame_params.npz", f"no FLAME parameters for timestep(s) {absent[:10]}")
        if int(summary["canonical_timestep"]) not in known:
            raise InputError(root / "flame_params.npz",
                             f"no FLAME parameters for the canonical timestep {summary['canonical_timestep']}")
        if not any(f.role == "train" for f in frames):
            raise InputError(frames_path, "no training frames")
        masks_path = root / "flame_masks.json"
        return cls(root=root, cameras=cameras, frames=frames, params=params, model_path=root / "flame_model.npz",
                   masks_path=masks_path if masks_path.is_file() else None, summary=summary)

    @property
    def canonical_timestep(self) -> int:
        return int(self.summary["canonical_timestep"])

    @property
    def regime(self) -> str:
        return str(self.summary.get("regime", ""))

    @property
    def has_masks(self) -> bool:
        return all(f.mask is not None for f in self.frames)

    def role(self, name: str) -> list[IngestedFrame]:
        """Frames of one role ("train", "val", "test")."""
        if name not in ROLES:
            raise ValueError(f"unknown role {name!r}; expected one of {ROLES}")
        return [f for f in self.frames if f.role == name]

    def split(self, name: str) -> list[IngestedFrame]:
        """Frames that came from one capture split ("train", "val", "test")."""
        return [f for f in self.frames if f.split == name]

    def frame(self, timestep: int, camera_index: int) -> IngestedFrame:
        """The frame of (timestep, camera_index); KeyError if it was not ingested."""
        for f in self.frames:
            if f.timestep == timestep and f.camera_index == camera_index:
                return f
        raise KeyError(f"no ingested frame for timestep {timestep}, camera {camera_index}")

    def load_model(self) -> Any:
        """The FLAME model (:class:`sage_core.flame.FlameModelData`) from ``flame_model.npz``."""
        from ..flame import load_flame_model

        return load_flame_model(self.model_path)

    @property
    def train(self) -> list[IngestedFrame]:
        return self.role("train")

    @property
    def val(self) -> list[IngestedFrame]:
        return self.role("val")

    @property
    def test(self) -> list[IngestedFrame]:
        return self.role("test")

    def load_image(self, frame: IngestedFrame) -> np.ndarray:
        """(H, W, 3) float32 in [0, 1]."""
        from .imageio import read_image

        img = read_image(frame.image)
        if img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
        return np.ascontiguousarray(img[:, :, :3], dtype=np.float32)

    def load_mask(self, frame: IngestedFrame) -> np.ndarray:
        """(H, W) float32 in [0, 1]; StageError when the capture had no mask for this frame."""
        from .imageio import read_image

        if frame.mask is None:
            raise StageError(f"{self.root}: no foreground mask was ingested for timestep {frame.timestep}, "
                             f"camera {frame.camera_index}")
        return np.ascontiguousarray(read_image(frame.mask)[:, :, 0], dtype=np.float32)

    def load_masks_json(self) -> dict[str, np.ndarray]:
        """FLAME region masks (name -> int64 vertex ids), empty when none were ingested."""
        if self.masks_path is None:
            return {}
        doc = _read_json(self.masks_path)
        try:
            return {k: np.asarray(v, dtype=np.int64) for k, v in doc["masks"].items()}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(self.masks_path, f"malformed masks ({type(exc).__name__}: {exc})") from None


def sample_indices(n_frames: int, n_samples: int) -> list[int]:
    """``n_samples`` evenly spaced indices in ``range(n_frames)`` (first and last included)."""
    if n_samples <= 0 or n_frames <= 0:
        return []
    if n_samples >= n_frames:
        return list(range(n_frames))
    if n_samples == 1:
        return [0]
    return sorted({int(round(x)) for x in np.linspace(0, n_frames - 1, n_samples)})
