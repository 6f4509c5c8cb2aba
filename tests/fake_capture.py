"""Tiny fake VHAP exports (a handful of 48×64 frames, one or several sequences) and a tiny fake
FLAME model, written into a folder the test gives: plain builders shared by the capture-reader and
ingest tests."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sage_core.data import Camera, camera_to_nerf_frame, write_image
from sage_core.data.cameras import look_at

W, H = 48, 64
FX, FY = 60.0, 63.0
CX, CY_CV = 21.5, 36.0  # deliberately off-centre
N_SHAPE, N_EXPR = 300, 100
MODEL_V = 14
BLOB = np.array([0.02, 0.03, 0.01])  # a world point drawn into every image


def make_camera(ci: int, n_cameras: int) -> Camera:
    """Cameras on an arc at 1 m looking at the origin; index ``ci`` of ``n_cameras``."""
    ang = np.deg2rad(-40 + 80 * ci / max(n_cameras - 1, 1))
    eye = np.array([np.sin(ang), 0.05 * (ci % 3), np.cos(ang)])
    K = np.array([[FX, 0, CX], [0, FY, CY_CV], [0, 0, 1.0]])
    return Camera(K, look_at(eye, np.zeros(3)), W, H, ci, f"cam{ci:02d}")


def project_manual(cam: Camera, X: np.ndarray) -> np.ndarray:
    """Independent pinhole projection of one point: (2,) pixel coordinates."""
    Xc = cam.w2c[:3, :3] @ X + cam.w2c[:3, 3]
    return np.array([cam.K[0, 0] * Xc[0] / Xc[2] + cam.K[0, 2], cam.K[1, 1] * Xc[1] / Xc[2] + cam.K[1, 2]])


def blob_image(cam: Camera, radius: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """White image with a dark disc around the projection of BLOB, and its mask. (H,W,3), (H,W)."""
    uv = project_manual(cam, BLOB)
    yy, xx = np.mgrid[0:cam.height, 0:cam.width] + 0.5  # pixel centres
    mask = ((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= radius**2).astype(np.float32)
    img = np.ones((cam.height, cam.width, 3), np.float32)
    img[mask > 0] = np.array([0.2, 0.4, 0.6], np.float32)
    return img, mask


def vhap_params(t: int, n_vertices: int = MODEL_V, expr_scale: float = 1.0, jaw: float = 0.0,
                dynamic: bool = False) -> dict[str, np.ndarray]:
    """One per-timestep npz in the exact VHAP shapes."""
    rng = np.random.default_rng(100 + t)
    d = {
        "translation": (rng.normal(size=(1, 3)) * 0.005).astype(np.float32),
        "rotation": (rng.normal(size=(1, 3)) * 0.02).astype(np.float32),
        "neck_pose": (rng.normal(size=(1, 3)) * 0.02).astype(np.float32),
        "jaw_pose": np.array([[jaw, 0.0, 0.0]], np.float32),
        "eyes_pose": np.zeros((1, 6), np.float32),
        "shape": np.linspace(-1, 1, N_SHAPE).astype(np.float32),
        "expr": (np.ones((1, N_EXPR)) * expr_scale / np.sqrt(N_EXPR)).astype(np.float32),
        "static_offset": (np.arange(n_vertices * 3).reshape(1, n_vertices, 3) * 1e-4).astype(np.float32),
    }
    if dynamic:
        d["dynamic_offset"] = np.full((1, n_vertices, 3), 1e-3 * (t + 1), np.float32)
    return d


@dataclass
class FakeSpec:
    """What a fake sequence holds."""

    n_train_timesteps: int = 3
    n_test_timesteps: int = 1
    cameras: tuple[int, ...] = (0, 1, 8)
    val_camera: int | None = 8
    with_masks: bool = True
    n_vertices: int = MODEL_V
    # timestep -> (expression norm, jaw x-angle); default: the middle train timestep is the neutral one
    expressions: dict[int, tuple[float, float]] = field(default_factory=dict)


def _frame_entry(cam: Camera, ti: int, prefix: str) -> dict:
    fr = camera_to_nerf_frame(cam)
    fr.update({
        "timestep_index": ti,
        "timestep_index_original": ti,
        "timestep_id": f"frame_{ti:05d}",
        "camera_index": cam.index,
        "camera_id": cam.name,
        "file_path": f"{prefix}images/{ti:05d}_{cam.index:02d}.png",
        "fg_mask_path": f"{prefix}fg_masks/{ti:05d}_{cam.index:02d}.png",
        "flame_param_path": f"{prefix}flame_param/{ti:05d}.npz",
    })
    return fr


def write_transforms(path: Path, frames: list[dict]) -> None:
    doc = {
        # top-level intrinsics are deliberately wrong: readers must use the per-frame values
        "cx": 1.0, "cy": 1.0, "fl_x": 999.0, "fl_y": 999.0, "h": 7, "w": 5,
        "camera_angle_x": 0.1, "camera_angle_y": 0.1,
        "timestep_indices": sorted({f["timestep_index"] for f in frames}),
        "camera_indices": sorted({f["camera_index"] for f in frames}),
        "frames": frames,
    }
    path.write_text(json.dumps(doc, indent=1))


def write_sequence(seq: Path, spec: FakeSpec, t0: int = 0, prefix: str = "") -> dict[str, list[dict]]:
    """Write images, masks and FLAME files of one sequence; return its frames per split.

    t0: first timestep index (unions re-base timesteps cumulatively); prefix: path prefix for the
    frame entries (``../<seq>/`` in unions).
    """
    seq.mkdir(parents=True, exist_ok=True)
    n_cams = max(spec.cameras) + 1
    T = spec.n_train_timesteps + spec.n_test_timesteps
    splits: dict[str, list[dict]] = {"train": [], "val": [], "test": []}
    for k in range(T):
        ti = t0 + k
        norm, jaw = spec.expressions.get(ti, (0.1 if k == spec.n_train_timesteps // 2 else 1.0 + k,
                                              0.3 if k == spec.n_train_timesteps // 2 else 0.0))
        np.savez(_mkdir(seq / "flame_param") / f"{ti:05d}.npz", **vhap_params(ti, spec.n_vertices, norm, jaw))
        for ci in spec.cameras:
            cam = make_camera(ci, n_cams)
            img, mask = blob_image(cam)
            write_image(seq / "images" / f"{ti:05d}_{ci:02d}.png", img)
            if spec.with_masks:
                write_image(seq / "fg_masks" / f"{ti:05d}_{ci:02d}.png", mask)
            fr = _frame_entry(cam, ti, prefix)
            if not spec.with_masks:
                fr.pop("fg_mask_path")
            if k >= spec.n_train_timesteps:
                splits["test"].append(fr)
            elif ci == spec.val_camera:
                splits["val"].append(fr)
            else:
                splits["train"].append(fr)
    canon = vhap_params(0, spec.n_vertices, 0.0, 0.3)
    canon["translation"][:] = 0
    canon["rotation"][:] = 0
    canon["neck_pose"][:] = 0
    np.savez(seq / "canonical_flame_param.npz", **canon)
    return splits


def _mkdir(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


def make_fake_capture(root: Path, spec: FakeSpec | None = None) -> Path:
    """A single-sequence VHAP export in ``root``; returns root."""
    spec = spec or FakeSpec()
    splits = write_sequence(root, spec)
    for s, frames in splits.items():
        write_transforms(root / f"transforms_{s}.json", frames)
    return root


def make_fake_union(parent: Path, spec: FakeSpec | None = None, n_sequences: int = 2) -> Path:
    """Sibling sequences ``seq0..`` plus a union folder ``UNION`` whose paths start with ``../seqK/``.

    The last sequence is the test sequence (all cameras); the others give train/val.
    """
    spec = spec or FakeSpec()
    union = _mkdir(parent / "UNION")
    merged: dict[str, list[dict]] = {"train": [], "val": [], "test": []}
    t0 = 0
    for k in range(n_sequences):
        is_test = k == n_sequences - 1
        sub = FakeSpec(**{**spec.__dict__, "n_train_timesteps": 0 if is_test else spec.n_train_timesteps,
                          "n_test_timesteps": 2 if is_test else 0})
        splits = write_sequence(parent / f"seq{k}", sub, t0=t0, prefix=f"../seq{k}/")
        for s in merged:
            for fr in splits[s]:
                fr.pop("timestep_index_original")
                fr.pop("timestep_id")
            merged[s] += splits[s]
        t0 += sub.n_train_timesteps + sub.n_test_timesteps
    for s, frames in merged.items():
        write_transforms(union / f"transforms_{s}.json", frames)
    (union / "canonical_flame_param.npz").write_bytes((parent / "seq0" / "canonical_flame_param.npz").read_bytes())
    return union


def make_tiny_model(path: Path, n_vertices: int = MODEL_V, n_base_vertices: int | None = None) -> Path:
    """A tiny FLAME-style model (5 joints) written with the project's npz writer."""
    from sage_core.flame import FlameModelData, save_flame_npz

    rng = np.random.default_rng(7)
    V, J = n_vertices, 5
    dirs = rng.normal(size=(V, 3))
    v = 0.1 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    w = np.zeros((V, J))
    w[:, 1] = 1.0
    data = FlameModelData(
        v_template=v,
        faces=np.stack([np.arange(V), (np.arange(V) + 1) % V, (np.arange(V) + 2) % V], 1).astype(np.int64),
        shapedirs=rng.normal(size=(V, 3, 10)) * 1e-3,
        exprdirs=rng.normal(size=(V, 3, N_EXPR)) * 1e-3,
        posedirs=np.zeros((V, 3, 9 * (J - 1))),
        j_regressor=np.full((J, V), 1.0 / V),
        lbs_weights=w,
        parents=np.array([-1, 0, 1, 1, 1], dtype=np.int64),
        n_base_vertices=V if n_base_vertices is None else n_base_vertices,
    )
    return save_flame_npz(data, path)
