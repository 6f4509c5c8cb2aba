"""Tracker-like FLAME parameters for ``tracking="fitted"`` captures.

The ground truth (:mod:`.truth`) is posed with the full head plus its non-linear correctives and
creases. What the capture's ``flame_param/*.npz`` hold is what a tracker would hand over: a
least-squares fit of the written (truncated) model to the ground-truth vertices — expression
coefficients, head rotation, neck, jaw and translation, by damped Gauss–Newton from the true pose
and a zero expression — followed by seeded pose noise (rotation and translation). The tracking
error is the per-timestep vertex distance between the written model posed with those parameters
and the truth.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from .head import HeadModel
from .motion import Frame
from .truth import TruthFields, correctives, crease_offsets, kept_expressions, truncated_head, truth_fields

_POSE_KEYS = ("rotation", "neck_pose", "jaw_pose", "translation")
_FD_STEP = 1e-5


@dataclass
class TrackedHead:
    """The truth and the written model of one fitted capture.

    Attributes:
        full: ``sage_core.flame.FlameModel`` (float64) of the procedural head with every expression
            component (the truth before its extra deformation).
        written: the same with only the leading ``n_keep`` expression components (written to model/).
        written_head: the written model as a :class:`HeadModel` (for the model files).
        fields: the truth's corrective and crease fields.
        n_keep: expression components kept by the written model.
        faces: (F, 3) triangles.
    """

    full: object
    written: object
    written_head: HeadModel
    fields: TruthFields
    n_keep: int
    faces: np.ndarray


def make_tracked_head(head: HeadModel, expr_keep: float, corrective_scale: float, crease_depth_mm: float) -> TrackedHead:
    """The truth / written-model pair of ``head`` (see :class:`TrackedHead`)."""
    from .model_files import flame_model

    n_keep = kept_expressions(expr_keep)
    written_head = truncated_head(head, n_keep)
    return TrackedHead(
        full=flame_model(head),
        written=flame_model(written_head),
        written_head=written_head,
        fields=truth_fields(head, corrective_scale, crease_depth_mm),
        n_keep=n_keep,
        faces=head.faces,
    )


def _forward(model, shape: np.ndarray, offset: np.ndarray, params: dict[str, np.ndarray]):
    """Pose ``model`` for a batch: params maps FLAME keys to (T, k) float64 arrays; offset (V, 3) or (T, V, 3)."""
    import torch

    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        return model(shape=t(shape), static_offset=t(offset), **{k: t(v) for k, v in params.items()})


def _frame_params(frames: list[Frame]) -> dict[str, np.ndarray]:
    keys = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
    return {k: np.stack([getattr(f, k) for f in frames]).astype(np.float64) for k in keys}


@dataclass
class TruthPose:
    """Posed ground truth.

    Attributes:
        vertices: (T, V, 3) posed world vertices.
        v_shaped: (T, V, 3) canonical vertices with expression, correctives and creases.
        neutral: (V, 3) canonical identity mesh (zero expression).
    """

    vertices: np.ndarray
    v_shaped: np.ndarray
    neutral: np.ndarray


def pose_truth(th: TrackedHead, shape: np.ndarray, static_offset: np.ndarray, frames: list[Frame]) -> TruthPose:
    """The ground truth of ``frames``: the full head with its correctives and creases, posed."""
    p = _frame_params(frames)
    linear = _forward(th.full, shape, static_offset, {"expr": p["expr"]}).v_shaped.numpy()
    neutral = _forward(th.full, shape, static_offset, {}).v_shaped[0].numpy()
    extra = correctives(th.fields, p["expr"], p["jaw_pose"][:, 0])
    extra = extra + crease_offsets(th.fields, linear + extra, neutral, th.faces)
    out = _forward(th.full, shape, static_offset[None] + extra, p)
    return TruthPose(out.vertices.numpy(), out.v_shaped.numpy(), neutral)


def _pack(p: dict[str, np.ndarray], n_keep: int) -> np.ndarray:
    return np.concatenate([p["expr"][:, :n_keep], *(p[k] for k in _POSE_KEYS)], 1)


def _unpack(x: np.ndarray, base: dict[str, np.ndarray], n_keep: int) -> dict[str, np.ndarray]:
    out = {k: v.copy() for k, v in base.items()}
    out["expr"] = np.zeros_like(base["expr"])
    out["expr"][:, :n_keep] = x[:, :n_keep]
    for i, k in enumerate(_POSE_KEYS):
        out[k] = x[:, n_keep + 3 * i : n_keep + 3 * i + 3]
    return out


def fit_frames(th: TrackedHead, shape: np.ndarray, static_offset: np.ndarray, frames: list[Frame], truth: np.ndarray,
               iterations: int, chunk: int = 4) -> list[Frame]:
    """Least-squares fit of the written model to the truth vertices, one parameter set per frame.

    truth: (T, V, 3) ground-truth vertices of ``frames``. Unknowns per frame: the kept expression
    coefficients, rotation, neck, jaw and translation (eyes keep the true gaze); start: the true
    pose and a zero expression. Damped Gauss–Newton with a forward-difference Jacobian; a step
    that does not lower the residual is rejected and the damping raised. Returns copies of
    ``frames`` with the fitted values (no noise yet). Frames are fitted ``chunk`` at a time (memory).
    """
    out: list[Frame] = []
    for i in range(0, len(frames), chunk):
        out += _fit_chunk(th, shape, static_offset, frames[i : i + chunk], truth[i : i + chunk], iterations)
    return out


def _fit_chunk(th: TrackedHead, shape: np.ndarray, static_offset: np.ndarray, frames: list[Frame], truth: np.ndarray,
               iterations: int) -> list[Frame]:
    base = _frame_params(frames)
    x = _pack(base, th.n_keep)
    x[:, : th.n_keep] = 0.0
    T, P = x.shape
    target = truth.reshape(T, -1)

    def verts(xx: np.ndarray, reps: int) -> np.ndarray:
        """xx: (reps·T, P) stacked parameter sets -> (reps, T, 3V) vertices."""
        b = {k: np.tile(v, (reps, 1)) for k, v in base.items()}
        v = _forward(th.written, shape, static_offset, _unpack(xx, b, th.n_keep)).vertices.numpy()
        return v.reshape(reps, T, -1)

    r = verts(x, 1)[0] - target
    cost = np.einsum("ti,ti->t", r, r)
    damp = np.full(T, 1e-6)
    eye = np.eye(P)
    for _ in range(iterations):
        # forward differences, all columns in one batch (the model is affine in the expression)
        probe = np.concatenate([x[None], x[None] + _FD_STEP * eye[:, None, :]], 0).reshape(-1, P)
        v = verts(probe, P + 1)
        J = np.moveaxis((v[1:] - v[0][None]) / _FD_STEP, 0, -1)  # (T, 3V, P)
        JtJ = np.einsum("tip,tiq->tpq", J, J)
        Jtr = np.einsum("tip,ti->tp", J, r)
        diag = np.einsum("tpp->tp", JtJ)
        A = JtJ + (damp[:, None] * np.maximum(diag, 1e-12))[:, :, None] * eye[None]
        x_new = x - np.linalg.solve(A, Jtr[..., None])[..., 0]
        r_new = verts(x_new, 1)[0] - target
        cost_new = np.einsum("ti,ti->t", r_new, r_new)
        ok = cost_new <= cost
        x[ok], r[ok], cost[ok] = x_new[ok], r_new[ok], cost_new[ok]
        damp = np.where(ok, damp * 0.3, damp * 10.0)
    fitted = _unpack(x, base, th.n_keep)
    out = []
    for i, f in enumerate(frames):
        g = copy.deepcopy(f)
        for k in ("expr", *_POSE_KEYS):
            setattr(g, k, fitted[k][i].copy())
        out.append(g)
    return out


def add_pose_noise(frames: list[Frame], rng: np.random.Generator, rot_deg: float, trans_mm: float) -> list[Frame]:
    """Copies of ``frames`` with tracker-like pose noise: N(0, rot_deg) per axis of the head
    rotation and N(0, trans_mm / √3) per axis of the translation (so about trans_mm in length)."""
    out = []
    for f in frames:
        g = copy.deepcopy(f)
        g.rotation = g.rotation + np.deg2rad(rng.normal(0.0, rot_deg, 3))
        g.translation = g.translation + 1e-3 * rng.normal(0.0, trans_mm / np.sqrt(3.0), 3)
        out.append(g)
    return out


def written_vertices(th: TrackedHead, shape: np.ndarray, static_offset: np.ndarray, frames: list[Frame]) -> np.ndarray:
    """(T, V, 3) the written model posed with ``frames`` rounded to float32 (as read back from the npz)."""
    p = {k: v.astype(np.float32).astype(np.float64) for k, v in _frame_params(frames).items()}
    sh = shape.astype(np.float32).astype(np.float64)
    off = static_offset.astype(np.float32).astype(np.float64)
    return _forward(th.written, sh, off, p).vertices.numpy()


def vertex_errors(written: np.ndarray, truth: np.ndarray, region: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-timestep mean and max vertex distance in millimetres over all vertices (or the vertex
    ids ``region``). written, truth: (T, V, 3) -> (T,), (T,)."""
    d = 1e3 * np.linalg.norm(written - truth, axis=-1)
    if region is not None:
        d = d[:, region]
    return d.mean(1), d.max(1)
