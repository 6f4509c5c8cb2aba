"""Where MediaPipe's face-mesh points lie on a FLAME-format mesh: a landmark embedding.

An embedding maps landmark ``landmark_indices[k]`` (a face-mesh index, 0..467) to the point
``Σ_i lmk_b_coords[k, i] · v[faces[lmk_face_idx[k], i]]`` of the mesh, for any shape, expression and
pose. The file layout is FLAME's published MediaPipe embedding (``mediapipe_landmark_embedding.npz``:
``lmk_face_idx (K,)``, ``lmk_b_coords (K, 3)``, ``landmark_indices (K,)``); a calibrated embedding
adds ``spread (K,)`` (metres), ``views (K,)`` and ``format``.

:func:`calibrate_embedding` finds an embedding for any FLAME-format model: it renders the model's
neutral head, untextured and shaded, from several views (yaw × pitch, the jaw slightly open so the
inner lips separate), runs the detector and the landmark model on each render, looks up the mesh
triangle and barycentrics under every landmark, and keeps the landmarks whose back-projections agree
across the views (points on the face's outline slide over the surface as the view turns and are
dropped; :mod:`.fitting` matches the outline to the silhouette instead).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..atomic import atomic_writer
from ..data.cameras import Camera, look_at
from ..errors import InputError
from ..npz import read_npz
from .face_mesh import N_LANDMARKS
from .faces import FaceObserver, FaceProblem
from .shading import LIGHT, shade, vertex_normals

FORMAT = "sage-landmark-embedding-v1"
MIN_LANDMARKS = 30


@dataclass
class LandmarkEmbedding:
    """Face-mesh landmarks on a FLAME-format mesh.

    Attributes:
        landmark_ids: (K,) face-mesh indices.
        faces: (K,) triangle ids of the model's face table.
        bary: (K, 3) barycentric coordinates (sum 1).
        spread: (K,) calibration spread of each landmark in metres, or None (a published embedding).
        source: "calibrated" or the file it was read from.
    """

    landmark_ids: np.ndarray
    faces: np.ndarray
    bary: np.ndarray
    spread: np.ndarray | None = None
    source: str = "calibrated"

    def __len__(self) -> int:
        return int(self.landmark_ids.shape[0])

    def points(self, vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        """(..., K, 3) landmark positions on meshes (..., V, 3) with face table (F, 3)."""
        tri = faces[torch.as_tensor(self.faces, dtype=torch.long, device=faces.device)]  # (K, 3)
        b = torch.as_tensor(self.bary, dtype=vertices.dtype, device=vertices.device)
        return (vertices[..., tri, :] * b[:, :, None]).sum(-2)


def load_embedding(path: str | Path, n_faces: int) -> LandmarkEmbedding:
    """Read an embedding npz (FLAME's published MediaPipe embedding or one :func:`save_embedding` wrote),
    checked against a model with ``n_faces`` triangles. InputError names the file and the problem."""
    p = Path(path)
    arrays = read_npz(p, "landmark embedding")
    missing = [k for k in ("lmk_face_idx", "lmk_b_coords", "landmark_indices") if k not in arrays]
    if missing:
        raise InputError(p, f"lacks key(s) {', '.join(missing)} (expected a MediaPipe landmark embedding: lmk_face_idx, "
                            "lmk_b_coords, landmark_indices)")
    faces = np.asarray(arrays["lmk_face_idx"]).reshape(-1)
    bary = np.asarray(arrays["lmk_b_coords"], dtype=np.float64)
    ids = np.asarray(arrays["landmark_indices"]).reshape(-1)
    K = ids.shape[0]
    if bary.shape == (3, K) and K != 3:
        bary = bary.T
    if faces.shape[0] != K or bary.shape != (K, 3):
        raise InputError(p, f"lmk_face_idx has {faces.shape[0]} entries and lmk_b_coords shape {bary.shape} for {K} landmarks")
    if not (np.issubdtype(faces.dtype, np.integer) and np.issubdtype(ids.dtype, np.integer)):
        raise InputError(p, "lmk_face_idx and landmark_indices must hold integers")
    if K and (faces.min() < 0 or faces.max() >= n_faces):
        raise InputError(p, f"lmk_face_idx names triangles outside 0..{n_faces - 1}: the embedding is for another mesh")
    if K and (ids.min() < 0 or ids.max() >= N_LANDMARKS):
        raise InputError(p, f"landmark_indices must lie in 0..{N_LANDMARKS - 1} (MediaPipe's face mesh)")
    if not np.all(np.isfinite(bary)) or (K and np.abs(bary.sum(1) - 1).max() > 1e-3):
        raise InputError(p, "lmk_b_coords rows must be finite and sum to 1")
    if K < MIN_LANDMARKS:
        raise InputError(p, f"only {K} landmarks; at least {MIN_LANDMARKS} are needed")
    spread = np.asarray(arrays["spread"], dtype=np.float64) if "spread" in arrays else None
    return LandmarkEmbedding(ids.astype(np.int64), faces.astype(np.int64), bary, spread, str(p))


def save_embedding(path: str | Path, emb: LandmarkEmbedding, extra: dict[str, Any] | None = None) -> Path:
    """Write ``emb`` in FLAME's MediaPipe-embedding layout (plus ``spread``, ``format``), atomically."""
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT),
        "lmk_face_idx": emb.faces.astype(np.int64),
        "lmk_b_coords": emb.bary.astype(np.float64),
        "landmark_indices": emb.landmark_ids.astype(np.int64),
    }
    if emb.spread is not None:
        arrays["spread"] = emb.spread.astype(np.float64)
    for k, v in (extra or {}).items():
        arrays[k] = np.asarray(v)
    with atomic_writer(Path(path)) as fh:
        np.savez(fh, **arrays)
    return Path(path)


def calibration_cameras(vertices: np.ndarray, size: int, yaw_deg: float, pitch_deg: float, n_yaw: int) -> list[Camera]:
    """Views of a head (vertices (V, 3), FLAME world: y up, face towards +z) for the calibration:
    ``n_yaw`` yaws in [-yaw, yaw] × pitches (-pitch, 0, pitch), the head's box filling 80 % of the height."""
    lo, hi = vertices.min(0), vertices.max(0)
    centre = (lo + hi) / 2
    height = float(hi[1] - lo[1])
    dist = 1.0
    f = 0.8 * size * dist / height
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    yaws = np.linspace(-yaw_deg, yaw_deg, n_yaw) if n_yaw > 1 else np.array([0.0])
    pitches = (-pitch_deg, 0.0, pitch_deg) if pitch_deg > 0 else (0.0,)
    cams = []
    for p in pitches:
        for y in yaws:
            a, b = np.deg2rad(y), np.deg2rad(p)
            eye = centre + dist * np.array([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)])
            cams.append(Camera(K.copy(), look_at(eye, centre), size, size, len(cams), f"yaw{y:+.0f}_pitch{p:+.0f}"))
    return cams


@dataclass
class CalibrationReport:
    """What the calibration saw: views rendered, views with a face, landmarks kept / dropped."""

    views: int
    views_with_face: int
    kept: int
    dropped: int
    median_spread_mm: float

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def calibrate_embedding(vertices: torch.Tensor, faces: torch.Tensor, observer: FaceObserver, *, size: int = 384,
                        yaw_deg: float = 30.0, pitch_deg: float = 12.0, n_yaw: int = 5, spread_frac: float = 0.035,
                        min_views_frac: float = 0.6, lights: tuple[tuple[float, float, float], ...] = (LIGHT,),
                        supersample: int = 1, progress: Callable[[int, int, str], None] | None = None
                        ) -> tuple[LandmarkEmbedding, CalibrationReport]:
    """Calibrate an embedding on a head mesh (see the module docstring).

    vertices: (V, 3) the neutral head (zero shape and expression, jaw slightly open); faces: (F, 3).
    spread_frac: keep a landmark whose back-projections lie within this fraction of the head height of
    their median (median distance); min_views_frac: ... and that lands on the surface, facing the
    camera, in at least this fraction of the views with a face. Raises InputError (naming no file: the
    caller adds it) when fewer than MIN_LANDMARKS landmarks survive.
    """
    v_np = vertices.detach().double().cpu().numpy()
    cams = calibration_cameras(v_np, size, yaw_deg, pitch_deg, n_yaw)
    normals = vertex_normals(vertices.double(), faces)
    samples: list[list[tuple[int, np.ndarray, np.ndarray]]] = [[] for _ in range(N_LANDMARKS)]
    seen = 0
    for i, (cam, light) in enumerate((c, lt) for c in cams for lt in lights):
        img, _, raster = shade(vertices.double(), faces, cam, supersample=supersample, light=light)
        if progress is not None:
            progress(i + 1, len(cams) * len(lights), f"calibrating landmarks: view {cam.name}")
        try:
            obs = observer(img)
        except FaceProblem:
            continue
        seen += 1
        fid = raster.face_id[0].numpy()
        bary = raster.bary[0].double().numpy()
        px = np.floor(obs.landmarks).astype(int)
        inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        centre_cam = cam.center
        for k in np.flatnonzero(inside):
            f = int(fid[px[k, 1], px[k, 0]])
            if f < 0:
                continue
            b = bary[px[k, 1], px[k, 0]]
            tri = faces[f].numpy()
            point = b @ v_np[tri]
            n = (b @ normals[tri].numpy())
            to_cam = centre_cam - point
            if np.dot(n, to_cam) / (np.linalg.norm(n) * np.linalg.norm(to_cam) + 1e-12) < 0.2:
                continue  # grazing or back-facing: the landmark sits on the outline
            samples[k].append((f, b, point))
    height = float(v_np[:, 1].max() - v_np[:, 1].min())
    ids, fs, bs, spreads, counts = [], [], [], [], []
    dropped = 0
    for k, s in enumerate(samples):
        if seen == 0 or len(s) < max(2, int(np.ceil(min_views_frac * seen))):
            dropped += 1
            continue
        pts = np.stack([p for _, _, p in s])
        med = np.median(pts, 0)
        dist = np.linalg.norm(pts - med, axis=1)
        spread = float(np.median(dist))
        if spread > spread_frac * height:
            dropped += 1
            continue
        best = int(np.argmin(dist))
        ids.append(k)
        fs.append(s[best][0])
        bs.append(s[best][1])
        spreads.append(spread)
        counts.append(len(s))
    report = CalibrationReport(len(cams) * len(lights), seen, len(ids), dropped, float(np.median(spreads) * 1000) if spreads else float("nan"))
    if len(ids) < MIN_LANDMARKS:
        raise InputError("<FLAME model>", f"the landmark calibration kept {len(ids)} landmarks ({seen} of {len(cams)} rendered "
                                          f"views showed a face); at least {MIN_LANDMARKS} are needed: pass a landmark embedding "
                                          "with --landmark-embedding")
    emb = LandmarkEmbedding(np.array(ids, np.int64), np.array(fs, np.int64), np.stack(bs), np.array(spreads), "calibrated")
    return emb, report
