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

The detector's points are not fixed on the face: its landmark network leans towards a frontal face,
so on a head pitched 20° its points sit where a head pitched about 14° would show them (on the
calibration renders; the yaw is compressed less). A head fitted to them comes out turned too little.
The calibration therefore also keeps a **pose table** (:class:`PoseTable`): for every view of a wider
yaw × pitch grid, where each kept landmark's back-projection lies relative to its embedded point, in
the plane of its triangle. The fit looks the table up at each image's head pose relative to its
camera, so the mesh point a landmark is compared with slides as the detector's does. Files add it as
``pose_yaws (Y,)``, ``pose_pitches (P,)`` (degrees) and ``pose_offsets (P, Y, K, 2)`` (metres).
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
from .losses import triangle_plane_frame
from .shading import LIGHT, shade, vertex_normals

FORMAT = "sage-landmark-embedding-v1"
MIN_LANDMARKS = 30


@dataclass
class PoseTable:
    """Where the detector puts each landmark as the head turns, relative to its embedded point.

    Attributes:
        yaws: (Y,) ascending yaws of the grid in degrees (the camera's direction seen from the head,
            FLAME frame: positive towards the head's +x).
        pitches: (P,) ascending pitches in degrees (positive: the camera above the face).
        offsets: (P, Y, K, 2) the landmark's back-projection minus its embedded point, in metres along
            its triangle's first edge and the in-plane perpendicular (normal × first edge), measured on
            the calibration head.
    """

    yaws: np.ndarray
    pitches: np.ndarray
    offsets: np.ndarray


@dataclass
class LandmarkEmbedding:
    """Face-mesh landmarks on a FLAME-format mesh.

    Attributes:
        landmark_ids: (K,) face-mesh indices.
        faces: (K,) triangle ids of the model's face table.
        bary: (K, 3) barycentric coordinates (sum 1).
        spread: (K,) calibration spread of each landmark in metres, or None (a published embedding).
        source: "calibrated" or the file it was read from.
        pose: how the detector's points slide with the head's pose (None: a fixed embedding, as
            FLAME's published one).
    """

    landmark_ids: np.ndarray
    faces: np.ndarray
    bary: np.ndarray
    spread: np.ndarray | None = None
    source: str = "calibrated"
    pose: PoseTable | None = None

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
    return LandmarkEmbedding(ids.astype(np.int64), faces.astype(np.int64), bary, spread, str(p), _read_pose(p, arrays, K))


def _read_pose(p: Path, arrays: dict[str, np.ndarray], K: int) -> PoseTable | None:
    """The pose table of an embedding file (None when it has none), checked; InputError names the file."""
    keys = ("pose_yaws", "pose_pitches", "pose_offsets")
    present = [k for k in keys if k in arrays]
    if not present:
        return None
    if len(present) != len(keys):
        raise InputError(p, f"has {', '.join(present)} but not {', '.join(k for k in keys if k not in arrays)} (a pose table needs all three)")
    yaws = np.asarray(arrays["pose_yaws"], dtype=np.float64).reshape(-1)
    pitches = np.asarray(arrays["pose_pitches"], dtype=np.float64).reshape(-1)
    off = np.asarray(arrays["pose_offsets"], dtype=np.float64)
    if off.shape != (pitches.size, yaws.size, K, 2):
        raise InputError(p, f"pose_offsets has shape {off.shape}; expected {(pitches.size, yaws.size, K, 2)} (pitches, yaws, landmarks, 2)")
    for name, a in (("pose_yaws", yaws), ("pose_pitches", pitches)):
        if a.size == 0 or not np.all(np.isfinite(a)) or np.any(np.diff(a) <= 0) or np.abs(a).max() > 90:
            raise InputError(p, f"{name} must be finite degrees in -90..90, strictly ascending")
    if not np.all(np.isfinite(off)) or np.abs(off).max() > 0.05:
        raise InputError(p, "pose_offsets must be finite and under 5 cm")
    return PoseTable(yaws, pitches, off)


def same_landmarks(a: LandmarkEmbedding, b: LandmarkEmbedding) -> bool:
    """Whether two embeddings place the same landmarks at the same points (ids, triangles and
    barycentrics; their pose tables may differ)."""
    return (np.array_equal(a.landmark_ids, b.landmark_ids) and np.array_equal(a.faces, b.faces)
            and a.bary.shape == b.bary.shape and bool(np.allclose(a.bary, b.bary)))


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
    if emb.pose is not None:
        arrays["pose_yaws"] = emb.pose.yaws.astype(np.float64)
        arrays["pose_pitches"] = emb.pose.pitches.astype(np.float64)
        arrays["pose_offsets"] = emb.pose.offsets.astype(np.float64)
    for k, v in (extra or {}).items():
        arrays[k] = np.asarray(v)
    with atomic_writer(Path(path)) as fh:
        np.savez(fh, **arrays)
    return Path(path)


def calibration_angles(yaw_deg: float, pitch_deg: float, n_yaw: int, pose_yaw_deg: float = 0.0,
                       pose_pitch_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Yaws and pitches (degrees, ascending) of the calibration grid: ``n_yaw`` yaws in [-yaw, yaw]
    and the pitches (-pitch, 0, pitch), continued at the same steps out to ``pose_yaw_deg`` and
    ``pose_pitch_deg`` when those are wider (the pose table's views)."""
    def axis(base: np.ndarray, wider: float) -> np.ndarray:
        if base.size < 2:
            return base
        step = float(base[1] - base[0])
        n = int(np.floor((wider - base[-1]) / step + 1e-9)) if wider > base[-1] else 0
        more = base[-1] + step * np.arange(1, n + 1)
        return np.concatenate([-more[::-1], base, more])

    yaws = np.linspace(-yaw_deg, yaw_deg, n_yaw) if n_yaw > 1 else np.array([0.0])
    pitches = np.array([-pitch_deg, 0.0, pitch_deg]) if pitch_deg > 0 else np.array([0.0])
    return axis(yaws, pose_yaw_deg), axis(pitches, pose_pitch_deg)


def calibration_cameras(vertices: np.ndarray, size: int, yaws: np.ndarray, pitches: np.ndarray) -> list[Camera]:
    """Views of a head (vertices (V, 3), FLAME world: y up, face towards +z) for the calibration, one per
    pitch × yaw (degrees; pitch-major), the head's box filling 80 % of the height."""
    lo, hi = vertices.min(0), vertices.max(0)
    centre = (lo + hi) / 2
    height = float(hi[1] - lo[1])
    dist = 1.0
    f = 0.8 * size * dist / height
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    cams = []
    for p in pitches:
        for y in yaws:
            a, b = np.deg2rad(y), np.deg2rad(p)
            eye = centre + dist * np.array([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)])
            cams.append(Camera(K.copy(), look_at(eye, centre), size, size, len(cams), f"yaw{y:+.0f}_pitch{p:+.0f}"))
    return cams


@dataclass
class CalibrationReport:
    """What the calibration saw: views rendered for the embedding, views with a face, landmarks kept /
    dropped, and the views of the pose table (0: none)."""

    views: int
    views_with_face: int
    kept: int
    dropped: int
    median_spread_mm: float
    pose_views: int = 0

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def calibrate_embedding(vertices: torch.Tensor, faces: torch.Tensor, observer: FaceObserver, *, size: int = 384,
                        yaw_deg: float = 30.0, pitch_deg: float = 12.0, n_yaw: int = 5, spread_frac: float = 0.035,
                        min_views_frac: float = 0.6, pose_yaw_deg: float = 0.0, pose_pitch_deg: float = 0.0,
                        pose_table: bool = True, lights: tuple[tuple[float, float, float], ...] = (LIGHT,),
                        supersample: int = 1, progress: Callable[[int, int, str], None] | None = None
                        ) -> tuple[LandmarkEmbedding, CalibrationReport]:
    """Calibrate an embedding on a head mesh (see the module docstring).

    vertices: (V, 3) the neutral head (zero shape and expression, jaw slightly open); faces: (F, 3).
    The embedding comes from the views within ``yaw_deg`` / ``pitch_deg``; with ``pose_table`` the pose
    table also from the grid continued to ``pose_yaw_deg`` / ``pose_pitch_deg`` (:func:`calibration_angles`).
    spread_frac: keep a landmark whose back-projections lie within this fraction of the head height of
    their median (median distance); min_views_frac: ... and that lands on the surface, facing the
    camera, in at least this fraction of the views with a face. Raises InputError (naming no file: the
    caller adds it) when fewer than MIN_LANDMARKS landmarks survive.
    """
    v_np = vertices.detach().double().cpu().numpy()
    wide = (pose_yaw_deg, pose_pitch_deg) if pose_table else (0.0, 0.0)
    yaws, pitches = calibration_angles(yaw_deg, pitch_deg, n_yaw, *wide)
    cams = calibration_cameras(v_np, size, yaws, pitches)
    grid = [(pi, yi) for pi in range(len(pitches)) for yi in range(len(yaws))]  # cams' order
    inner = [abs(yaws[yi]) <= yaw_deg + 1e-9 and abs(pitches[pi]) <= pitch_deg + 1e-9 for pi, yi in grid]
    normals = vertex_normals(vertices.double(), faces)
    # samples[k]: (view, triangle, barycentrics, point) of every view where landmark k lands on the surface
    samples: list[list[tuple[int, int, np.ndarray, np.ndarray]]] = [[] for _ in range(N_LANDMARKS)]
    seen = 0
    jobs = [(vi, lt) for vi in range(len(cams)) for lt in lights]
    for i, (vi, light) in enumerate(jobs):
        cam = cams[vi]
        img, _, raster = shade(vertices.double(), faces, cam, supersample=supersample, light=light)
        if progress is not None:
            progress(i + 1, len(jobs), f"calibrating landmarks: view {cam.name}")
        try:
            obs = observer(img)
        except FaceProblem:
            continue
        seen += int(inner[vi])
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
            samples[k].append((vi, f, b, point))
    height = float(v_np[:, 1].max() - v_np[:, 1].min())
    ids, fs, bs, spreads, counts = [], [], [], [], []
    dropped = 0
    for k, all_s in enumerate(samples):
        s = [x for x in all_s if inner[x[0]]]
        if seen == 0 or len(s) < max(2, int(np.ceil(min_views_frac * seen))):
            dropped += 1
            continue
        pts = np.stack([p for _, _, _, p in s])
        med = np.median(pts, 0)
        dist = np.linalg.norm(pts - med, axis=1)
        spread = float(np.median(dist))
        if spread > spread_frac * height:
            dropped += 1
            continue
        best = int(np.argmin(dist))
        ids.append(k)
        fs.append(s[best][1])
        bs.append(s[best][2])
        spreads.append(spread)
        counts.append(len(s))
    report = CalibrationReport(int(sum(inner)) * len(lights), seen, len(ids), dropped,
                               float(np.median(spreads) * 1000) if spreads else float("nan"), len(jobs) if pose_table else 0)
    if len(ids) < MIN_LANDMARKS:
        raise InputError("<FLAME model>", f"the landmark calibration kept {len(ids)} landmarks ({seen} of {sum(inner)} rendered "
                                          f"views showed a face); at least {MIN_LANDMARKS} are needed: pass a landmark embedding "
                                          "with --landmark-embedding")
    table = (_pose_table(samples, ids, fs, bs, v_np, faces.numpy(), yaws, pitches, grid, 2 * spread_frac * height)
             if pose_table else None)
    emb = LandmarkEmbedding(np.array(ids, np.int64), np.array(fs, np.int64), np.stack(bs), np.array(spreads), "calibrated", table)
    return emb, report


def _pose_table(samples: list[list[tuple[int, int, np.ndarray, np.ndarray]]], ids: list[int], fs: list[int],
                bs: list[np.ndarray], v: np.ndarray, faces: np.ndarray, yaws: np.ndarray, pitches: np.ndarray,
                grid: list[tuple[int, int]], limit: float) -> PoseTable:
    """Each kept landmark's back-projection in every grid view minus its embedded point, in the plane
    of its triangle (views that put it further than ``limit`` metres away, a detection that jumped to
    another feature, left out), smoothed over the grid by a quadratic in yaw and pitch (least squares over the
    views where it landed on the surface; one view's detection is noisy to a pixel or two, the
    detector's lean is smooth in the pose), within the range of its measured offsets; with too few
    views for the quadratic a plane, then the mean of the views it was seen in (0 when none)."""
    P, Y, K = len(pitches), len(yaws), len(ids)
    off = np.full((P, Y, K, 2), np.nan)
    tris = v[faces[np.asarray(fs, np.int64)]]  # (K, 3, 3)
    e1s, e2s = (a.numpy() for a in triangle_plane_frame(torch.from_numpy(tris)))
    for j, (k, b) in enumerate(zip(ids, bs)):
        p0, e1, e2 = b @ tris[j], e1s[j], e2s[j]
        for vi, _, _, point in samples[k]:
            if np.linalg.norm(point - p0) > limit:
                continue
            pi, yi = grid[vi]
            off[pi, yi, j] = ((point - p0) @ e1, (point - p0) @ e2)
    gp, gy = np.meshgrid(np.deg2rad(pitches), np.deg2rad(yaws), indexing="ij")  # (P, Y)
    basis = np.stack([np.ones_like(gy), gy, gp, gy ** 2, gp ** 2, gy * gp], -1)  # (P, Y, 6)
    table = np.zeros((P, Y, K, 2))
    for j in range(K):
        have = ~np.isnan(off[:, :, j, 0])
        if not have.any():
            continue
        seen_off = off[:, :, j][have]  # (n, 2)
        table[:, :, j] = seen_off.mean(0)
        for terms in (6, 3):  # the quadratic, else the plane, else the mean
            A = basis[..., :terms]
            if have.sum() >= terms and np.linalg.matrix_rank(A[have]) == terms:
                coef, *_ = np.linalg.lstsq(A[have], seen_off, rcond=None)
                table[:, :, j] = np.clip(A @ coef, seen_off.min(0), seen_off.max(0))  # never beyond what was seen
                break
    return PoseTable(np.asarray(yaws, np.float64), np.asarray(pitches, np.float64), table)
