"""Identity, per-timestep FLAME parameters and camera rigs of synthetic captures."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..cameras import Camera, look_at
from .head import EXPRESSION_NAMES, N_IDENTITY, HeadModel, hair_weight
from .mesh_render import vertex_normals

_E = {name: i for i, name in enumerate(EXPRESSION_NAMES)}
MILD_COMPONENTS = ("lips_part", "smile", "pucker", "lip_press", "brow_raise", "brow_furrow", "cheek_puff", "mouth_corners_down")


@dataclass
class Frame:
    """FLAME parameters of one timestep (float64, no batch dimension) and a short description."""

    expr: np.ndarray = field(default_factory=lambda: np.zeros(100))
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    neck_pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    jaw_pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    eyes_pose: np.ndarray = field(default_factory=lambda: np.zeros(6))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    label: str = "neutral"


def sample_identity(head: HeadModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Identity coefficients (300,) and a static offset (V, 3) that thickens the scalp hair."""
    shape = np.zeros(300)
    shape[:N_IDENTITY] = np.clip(rng.normal(0.0, 0.9, N_IDENTITY), -2.0, 2.0)
    thickness = rng.uniform(0.002, 0.008)
    n = vertex_normals(head.v_template, head.faces)
    w = hair_weight(head.v_template) * (head.part == 0)
    return shape, (thickness * w)[:, None] * n


def _expr(**coeffs: float) -> np.ndarray:
    e = np.zeros(100)
    for k, v in coeffs.items():
        e[_E[k]] = v
    return e


def _label(expr: np.ndarray, jaw: float) -> str:
    parts = [f"{EXPRESSION_NAMES[i]} {expr[i]:+.2f}" for i in np.flatnonzero(np.abs(expr[: len(EXPRESSION_NAMES)]) >= 0.5)]
    if jaw >= 0.05:
        parts.insert(0, f"jaw open {jaw:.2f} rad")
    return ", ".join(parts) if parts else "neutral"


def strong_expressions() -> list[tuple[np.ndarray, float]]:
    """Held-out expressions (expr (100,), jaw opening rad) never used for training timesteps."""
    return [
        (_expr(lips_part=1.2), 0.3),
        (_expr(smile=2.6, cheek_puff=0.3), 0.04),
        (_expr(brow_raise=2.6, lips_part=0.5), 0.12),
        (_expr(pucker=2.4, brow_furrow=1.2), 0.0),
        (_expr(blink=1.0, brow_furrow=1.8, mouth_corners_down=1.5), 0.0),
        (_expr(cheek_puff=2.2, lip_press=1.5), 0.0),
        (_expr(smile=1.6, lips_part=1.0, nose_wrinkle=1.8), 0.2),
        (_expr(mouth_stretch=2.2, blink_left=1.0, brow_raise=1.2), 0.1),
    ]


def _jitter(rng: np.random.Generator, frame: Frame, rot_deg: float, trans_m: float) -> Frame:
    frame.rotation = np.deg2rad(np.clip(rng.normal(0.0, rot_deg, 3), -2 * rot_deg, 2 * rot_deg))
    frame.neck_pose = np.deg2rad(np.clip(rng.normal(0.0, rot_deg, 3), -2 * rot_deg, 2 * rot_deg))
    frame.eyes_pose = np.tile(np.deg2rad(rng.normal(0.0, 4.0, 3)) * np.array([1.0, 1.0, 0.0]), 2)
    frame.translation = rng.normal(0.0, trans_m, 3)
    return frame


def multiview_frames(rng: np.random.Generator, n_train: int, n_test: int) -> list[Frame]:
    """Training timesteps with mild expressions, then held-out timesteps with strong ones."""
    frames: list[Frame] = []
    for i in range(n_train):
        e = np.zeros(100)
        if i > 0:
            comps = rng.choice(len(MILD_COMPONENTS), size=2, replace=False)
            for c in comps:
                e[_E[MILD_COMPONENTS[c]]] = rng.uniform(-0.6, 0.8)
        jaw = float(rng.uniform(0.0, 0.08)) if i > 0 else 0.0
        f = _jitter(rng, Frame(expr=e), 1.2, 0.003)
        f.jaw_pose = np.array([jaw, 0.0, 0.0])
        f.label = "train: " + _label(e, jaw)
        frames.append(f)
    strong = strong_expressions()
    for i in range(n_test):
        e, jaw = strong[i % len(strong)]
        e = e * (1.0 if i < len(strong) else rng.uniform(0.7, 1.0))
        f = _jitter(rng, Frame(expr=e.copy()), 1.8, 0.004)
        f.jaw_pose = np.array([jaw, 0.0, 0.0])
        f.label = "test: " + _label(e, jaw)
        frames.append(f)
    # a common offset before re-centring, as a tracker would produce
    base = np.array([0.004, -0.012, 0.01])
    for f in frames:
        f.translation = f.translation + base
    return frames


def monocular_frames(rng: np.random.Generator, n_train: int, n_test: int) -> list[Frame]:
    """A head-turn clip: neutral expression, yaw sweep ±60° with some pitch; translations sum to 0."""
    frames: list[Frame] = []
    for i in range(n_train):
        s = i / max(n_train - 1, 1)
        yaw = np.deg2rad(-60.0 + 120.0 * s)
        pitch = np.deg2rad(6.0 * np.sin(2 * np.pi * s))
        frames.append(Frame(rotation=np.array([pitch, yaw, 0.0]), label=f"train: yaw {np.rad2deg(yaw):+.0f}°"))
    for i in range(n_test):
        s = (i + 0.5) / max(n_test, 1)
        yaw = np.deg2rad(45.0 - 90.0 * s)
        pitch = np.deg2rad(15.0 * (1 if i % 2 == 0 else -1))
        frames.append(Frame(rotation=np.array([pitch, yaw, 0.0]), label=f"test: yaw {np.rad2deg(yaw):+.0f}°, pitch {np.rad2deg(pitch):+.0f}°"))
    for f in frames:
        f.eyes_pose = np.tile(np.deg2rad(rng.normal(0.0, 3.0, 3)) * np.array([1.0, 1.0, 0.0]), 2)
    return frames


def novel_frames(rng: np.random.Generator, n: int) -> list[Frame]:
    """Ground-truth-only timesteps: the neutral face, then n held-out strong expressions."""
    frames = [Frame(label="val: neutral, novel views")]
    strong = strong_expressions()
    for i in range(n):
        e, jaw = strong[i % len(strong)]
        f = Frame(expr=e.copy(), label="test: " + _label(e, jaw))
        f.jaw_pose = np.array([jaw, 0.0, 0.0])
        frames.append(f)
    return frames


def _orbit_camera(rng: np.random.Generator, yaw: float, elev: float, distance: float, fl: float, width: int, height: int,
                  index: int) -> Camera:
    """A camera ``distance`` from the head centre at azimuth ``yaw`` and elevation ``elev`` (radians),
    aimed near the centre (a few mm of random aim), focal length about ``fl`` and a slightly
    off-centre principal point, as in real calibrations."""
    eye = distance * np.array([np.sin(yaw) * np.cos(elev), np.sin(elev), np.cos(yaw) * np.cos(elev)])
    target = np.array([0.0, -0.005, 0.0]) + rng.normal(0.0, 0.004, 3)
    K = np.array(
        [
            [fl * rng.uniform(0.99, 1.01), 0.0, width / 2 + rng.uniform(-0.02, 0.02) * width],
            [0.0, fl, height / 2 + rng.uniform(-0.02, 0.02) * height],
            [0.0, 0.0, 1.0],
        ]
    )
    return Camera(K, look_at(eye, target), width, height, index, f"{222200000 + 37 * index}")


def arc_cameras(rng: np.random.Generator, n: int, width: int, height: int, distance: float, view_height: float,
                yaw_span_deg: float = 130.0, frontal: int | None = None) -> list[Camera]:
    """Cameras on an arc in front of the head (NeRSemble-like), index ``frontal`` (default 8 or n//2) at yaw 0.

    Principal points are slightly off-centre and differ per camera, as in real calibrations.
    """
    f_idx = (8 if n > 8 else n // 2) if frontal is None else frontal
    step = yaw_span_deg / max(n - 1, 1)
    fl = height * distance / view_height
    cams = []
    for i in range(n):
        yaw = np.deg2rad((i - f_idx) * step)
        elev = 0.0 if i == f_idx else np.deg2rad(10.0 if i % 2 == 0 else -6.0)
        cams.append(_orbit_camera(rng, yaw, elev, distance, fl, width, height, i))
    return cams


def off_arc_cameras(rng: np.random.Generator, n: int, n_arc: int, width: int, height: int, distance: float,
                    view_height: float, arc_span_deg: float = 130.0, first_index: int = 0) -> list[Camera]:
    """``n`` held-out cameras for a capture whose ``n_arc`` cameras span ``arc_span_deg`` of yaw (the
    :func:`arc_cameras` arc): yaws midway between two arc cameras, spread evenly over the arc, at
    elevations 22° above and 16° below the arc in turn, so none sees the head as a training camera
    does; same distance and framing, indices from ``first_index``."""
    step = arc_span_deg / max(n_arc - 1, 1)
    gaps = (np.arange(n_arc - 1) - (n_arc - 1) / 2 + 0.5) * step  # yaws midway between neighbours
    pick = np.unique(np.linspace(0, len(gaps) - 1, n).round().astype(int)) if n <= len(gaps) else np.arange(len(gaps))
    fl = height * distance / view_height
    cams = []
    for k, g in enumerate(gaps[pick]):
        yaw = np.deg2rad(g)
        elev = np.deg2rad(22.0 if k % 2 == 0 else -16.0)
        cams.append(_orbit_camera(rng, yaw, elev, distance, fl, width, height, first_index + k))
    return cams


def around_cameras(rng: np.random.Generator, n: int, width: int, height: int, distance: float, view_height: float,
                   first_index: int = 0) -> list[Camera]:
    """``n`` cameras around the sides and back of the head: azimuths evenly from 90° (the subject's
    left) over the back to 270° (the right), elevations alternating 5° and 30° (above, seeing the
    crown); same distance and framing as :func:`arc_cameras`, indices from ``first_index``."""
    fl = height * distance / view_height
    cams = []
    for k in range(n):
        yaw = np.deg2rad(90.0 + 180.0 * k / max(n - 1, 1))
        elev = np.deg2rad(30.0 if k % 2 else 5.0)
        cams.append(_orbit_camera(rng, yaw, elev, distance, fl, width, height, first_index + k))
    return cams


def monocular_camera(width: int, height: int, focal: float) -> Camera:
    """VHAP's monocular convention: c2w rotation I at (0, 0, 1) in OpenGL, centred principal point."""
    fl = focal * max(width, height)
    c2w_gl = np.eye(4)
    c2w_gl[:3, 3] = [0.0, 0.0, 1.0]
    c2w_cv = c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0])
    K = np.array([[fl, 0.0, width / 2], [0.0, fl, height / 2], [0.0, 0.0, 1.0]])
    return Camera(K, np.linalg.inv(c2w_cv), width, height, 0, "monocular")


def shift_camera(cam: Camera, offset: np.ndarray) -> Camera:
    """The camera moved by ``offset`` in world space (c2w' = translate(offset)·c2w)."""
    w2c = cam.w2c.copy()
    w2c[:3, 3] = w2c[:3, 3] - w2c[:3, :3] @ np.asarray(offset, float)
    return Camera(cam.K.copy(), w2c, cam.width, cam.height, cam.index, cam.name)
