"""GaussianAvatars-compatible export: ``point_cloud.ply`` (local Gaussians) + ``flame_param.npz``.

The folder loads with GaussianAvatars' ``FlameGaussianModel`` (``load_ply`` with
``has_target=False``, then ``load_meshes`` of the npz) and plays in its viewers.

``point_cloud.ply`` — one row per surfel, INRIA property order then ``binding_0`` (float32, the
face id), all float32:

* frame: GA's per-face frame R = [a0 | a1 | a2] (docs/formats.md §6), not sage's surfel frame
  [a0 | −a2 | a1]; the local attributes are converted exactly:
  ``μ_loc = R_cᵀ(x_c − T_c)/k_c``, ``q_loc = q(R_c)⁻¹ ⊗ q_c``, ``ŝ_loc = log(s_c/k_c)``, with
  R_c, T_c, k_c the frames of sage's canonical mesh and (x_c, q_c, s_c) the surfels' canonical
  centre, rotation and in-plane scales. GA's posing ``μ = k·R·μ_loc + T``, ``s = k·exp(ŝ_loc)``,
  ``q = q(R) ⊗ q_loc`` on any posed mesh then gives exactly sage's uncorrected posed surfels.
* scales: three log scales in GA's k-relative convention; the surfel's thin third axis (its normal,
  the third column of R(q)) is ``1e-3·min(s0, s1)``, as in the viewer PLY (docs/formats.md §7.1).
* appearance: colours and opacities are evaluated once from sage's networks (or per-surfel SH) at
  the canonical pose, each surfel seen along its normal, and stored as SH degree 3 with
  ``f_dc = (rgb − 0.5)/C0`` and ``f_rest = 0`` (view-independent); opacity as a logit. A shaded
  avatar's canonical-pose irradiance is baked in.
* phase 2's surfel correction (stretch/curvature) has no counterpart in GA and is not applied.

``flame_param.npz`` — exactly GA's keys, float32: ``shape (300,)``, ``expr (T, 100)``,
``rotation, neck_pose, jaw_pose, translation (T, 3)``, ``eyes_pose (T, 6)``,
``static_offset (1, V, 3)``, ``dynamic_offset (T, V, 3)``; shape and expression coefficients are
zero-padded to 300/100 (a model with more raises), absent offsets are zeros. GA ignores
``dynamic_offset``; sage adds it when posing.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..workspace import atomic_write_bytes
from .ply import SH_C0, SURFEL_THICKNESS, _header, property_names

if TYPE_CHECKING:
    from ..avatar.model import Avatar
    from ..flame.params import FlameParams

GA_N_SHAPE = 300
GA_N_EXPR = 100
GA_SH_DEGREE = 3
GA_FLAME_KEYS: tuple[str, ...] = (
    "shape", "expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation", "static_offset", "dynamic_offset",
)  # fmt: skip
POINT_CLOUD = "point_cloud.ply"
FLAME_PARAM = "flame_param.npz"


@dataclass
class GaussianAvatarsExport:
    """What :func:`write_gaussian_avatars` wrote."""

    folder: Path
    n_gaussians: int
    n_timesteps: int
    n_vertices: int


def ga_local_gaussians(avatar: Avatar, view_from: torch.Tensor | None = None) -> dict[str, np.ndarray]:
    """The avatar's surfels as GA local Gaussians (module doc), float32.

    view_from: (3,) canonical-space point the colours are evaluated for (None: each surfel seen
    along its normal).
    Returns xyz (N, 3), f_dc (N, 3), f_rest (N, 45) channel-major zeros, opacity (N,) logit,
    scale (N, 3) log k-relative, rot (N, 4) wxyz unit, binding (N,) int64.
    """
    from ..flame.canonical import canonical_inputs
    from ..flame.frames import triangle_frames
    from ..geometry.rotations import matrix_to_quat, quat_conjugate, quat_multiply, quat_normalize

    with torch.no_grad():
        cs = avatar.canonical_state(with_sdf=avatar.attributes == "mlp")
        inputs = canonical_inputs(avatar.params, avatar.canonical_timestep, avatar.device)
        posed = avatar.posed(inputs, view_from, canonical=cs)
        R, T, k = triangle_frames(avatar.canonical_vertices, avatar.faces)
        b = avatar.surfels.binding.to(torch.long)
        Rb, Tb, kb = R[b], T[b], k[b]
        mu_loc = (Rb.transpose(-1, -2) @ (cs.means - Tb)[..., None]).squeeze(-1) / kb[:, None]
        q_loc = quat_multiply(quat_conjugate(matrix_to_quat(Rb)), quat_normalize(cs.quats))
        s_plane = cs.scales / kb[:, None]
        s_thin = SURFEL_THICKNESS * s_plane.min(dim=1).values
        log_s = torch.log(torch.cat([s_plane, s_thin[:, None]], dim=1))
        rgb = posed.colors.clamp(0.0, 1.0)
        opac = posed.opacities.clamp(1e-6, 1.0 - 1e-6)
    n = int(b.shape[0])

    def f(t: torch.Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float32).numpy()

    return {
        "xyz": f(mu_loc),
        "f_dc": f((rgb - 0.5) / SH_C0),
        "f_rest": np.zeros((n, 3 * ((GA_SH_DEGREE + 1) ** 2 - 1)), dtype=np.float32),
        "opacity": f(torch.log(opac) - torch.log1p(-opac)),
        "scale": f(log_s),
        "rot": f(q_loc),
        "binding": b.cpu().numpy().astype(np.int64),
    }


def encode_ga_point_cloud(g: dict[str, np.ndarray]) -> bytes:
    """``point_cloud.ply`` bytes of :func:`ga_local_gaussians` output (INRIA order + ``binding_0``)."""
    n = g["xyz"].shape[0]
    rows = np.concatenate(
        [g["xyz"], np.zeros((n, 3)), g["f_dc"], g["f_rest"], g["opacity"][:, None], g["scale"], g["rot"],
         g["binding"][:, None].astype(np.float64)],
        axis=1,
    ).astype("<f4")  # fmt: skip
    if not np.isfinite(rows).all():
        raise ValueError("non-finite local Gaussian attributes")
    names = property_names(g["f_rest"].shape[1] // 3) + ["binding_0"]
    comments = ["GaussianAvatars local Gaussians (binding_0 = FLAME face id), exported by sage"]
    return _header(names, n, comments) + np.ascontiguousarray(rows).tobytes()


def _pad_cols(a: np.ndarray, width: int, key: str) -> np.ndarray:
    if a.shape[-1] > width:
        raise ValueError(f"{key} has {a.shape[-1]} coefficients; GaussianAvatars' FLAME takes at most {width}")
    pad = [(0, 0)] * (a.ndim - 1) + [(0, width - a.shape[-1])]
    return np.pad(a, pad)


def ga_flame_arrays(params: FlameParams, n_vertices: int, shape: np.ndarray | None = None,
                    static_offset: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """GA's ``flame_param.npz`` arrays (module doc) for the T rows of ``params``.

    shape (S,) and static_offset (V, 3) replace the params' own when given (a motion driving
    another subject); offsets with fewer than ``n_vertices`` rows are zero-padded (the teeth).
    """
    T = params.n_timesteps
    shp = np.asarray(params.shape if shape is None else shape, dtype=np.float64).reshape(-1)
    so = params.static_offset if static_offset is None else static_offset
    so = np.zeros((n_vertices, 3)) if so is None else np.asarray(so, dtype=np.float64).reshape(-1, 3)
    do = params.dynamic_offset
    do = np.zeros((T, n_vertices, 3)) if do is None else np.asarray(do, dtype=np.float64)
    if so.shape[0] > n_vertices or do.shape[1] > n_vertices:
        raise ValueError(f"offsets have more rows than the model's {n_vertices} vertices")
    so = np.pad(so, [(0, n_vertices - so.shape[0]), (0, 0)])
    do = np.pad(do, [(0, 0), (0, n_vertices - do.shape[1]), (0, 0)])
    out = {
        "shape": _pad_cols(shp, GA_N_SHAPE, "shape"),
        "expr": _pad_cols(np.asarray(params.expr, dtype=np.float64), GA_N_EXPR, "expr"),
        "rotation": params.rotation, "neck_pose": params.neck_pose, "jaw_pose": params.jaw_pose,
        "eyes_pose": params.eyes_pose, "translation": params.translation,
        "static_offset": so[None], "dynamic_offset": do,
    }  # fmt: skip
    return {key: np.ascontiguousarray(out[key], dtype=np.float32) for key in GA_FLAME_KEYS}


def write_gaussian_avatars(avatar: Avatar, folder: str | Path, params: FlameParams | None = None) -> GaussianAvatarsExport:
    """Write ``folder/point_cloud.ply`` and ``folder/flame_param.npz`` (module doc), atomically.

    params: the FLAME sequence to store (default: the avatar's own tracked sequence); its shape and
    static offset are replaced by the avatar's own.
    """
    folder = Path(folder)
    g = ga_local_gaussians(avatar)
    atomic_write_bytes(folder / POINT_CLOUD, encode_ga_point_cloud(g))
    n_vertices = int(avatar.model_data.v_template.shape[0])
    own = avatar.params
    arrays = ga_flame_arrays(own if params is None else params, n_vertices, shape=own.shape, static_offset=own.static_offset)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(folder / FLAME_PARAM, buf.getvalue())
    return GaussianAvatarsExport(folder, int(g["xyz"].shape[0]), int(arrays["expr"].shape[0]), n_vertices)
