"""GaussianAvatars-compatible export: ``point_cloud.ply`` (local Gaussians) + ``flame_param.npz``,
written in GaussianAvatars' own FLAME topology.

The folder is meant for GaussianAvatars' ``FlameGaussianModel`` (``load_ply`` with
``has_target=False``, then ``load_meshes`` of the npz) and its viewers.

**Topology.** GaussianAvatars' FLAME is the user's FLAME model (N vertices, F faces; 5023 and 9976
for FLAME itself) with 120 teeth vertices and 168 teeth faces appended, placed by FLAME vertex ids
(docs/formats.md §4). sage's model may carry more: its mouth cavity (and, for a model without teeth, its
own teeth arcs), appended after the model's own vertices and faces. The folder holds exactly
GaussianAvatars' rows:

* ``static_offset (1, N + 120, 3)`` and ``dynamic_offset (T, N + 120, 3)``: the model's N rows,
  then the 120 teeth rows: sage's own teeth rows when sage's teeth are GaussianAvatars' (a
  5023-vertex FLAME whose teeth sage appended in GaussianAvatars' order, ``flame+sage-teeth-v1``),
  zeros otherwise. Rows of sage's cavity are left out.
* ``binding_0`` indexes GaussianAvatars' face table: ids below F are the model's own faces (the same
  triangles, in the same winding, as sage's); F + 0 is GaussianAvatars' first upper-teeth triangle
  (teeth vertices upper_root[0], upper_edge[1], upper_edge[0]) and F + 84 its first lower-teeth
  triangle (lower_edge[0], lower_edge[1], lower_root[0]).
* Surfels on the model's own faces keep their face. Surfels on sage's teeth or cavity faces are
  rebound: when sage's teeth are GaussianAvatars', to the teeth triangle above of their jaw (the
  upper parts follow the neck joint, the lower ones the jaw, rigidly, in both tools, so their posing
  stays exact wherever they are); otherwise to the nearest face of the model (by centroid, in the
  canonical mesh), which is exact at the canonical pose and follows that face elsewhere.

**Attributes.** One row per surfel, INRIA property order then ``binding_0`` (float32, the face id),
all float32:

* frame: GA's per-face frame R = [a0 | a1 | a2] (docs/formats.md §6), not sage's surfel frame
  [a0 | −a2 | a1]; the local attributes are converted exactly:
  ``μ_loc = R_cᵀ(x_c − T_c)/k_c``, ``q_loc = q(R_c)⁻¹ ⊗ q_c``, ``ŝ_loc = log(s_c/k_c)``, with
  R_c, T_c, k_c the frames of sage's canonical mesh and (x_c, q_c, s_c) the surfels' canonical
  centre, rotation and in-plane scales. GA's posing ``μ = k·R·μ_loc + T``, ``s = k·exp(ŝ_loc)``,
  ``q = q(R) ⊗ q_loc`` on any posed mesh then gives exactly sage's uncorrected posed surfels (for
  the rebound surfels, as said above).
* scales: three log scales in GA's k-relative convention; the surfel's thin third axis (its normal,
  the third column of R(q)) is ``1e-3·min(s0, s1)``, as in the viewer PLY (docs/formats.md §7.1).
* appearance: colours and opacities are evaluated once from sage's networks (or per-surfel SH) at
  the canonical pose, each surfel seen along its normal, and stored as SH degree 3 with
  ``f_dc = (rgb − 0.5)/C0`` and ``f_rest = 0`` (view-independent); opacity as a logit. A shaded
  avatar's canonical-pose irradiance is baked in.
* phase 2's surfel correction (stretch/curvature) has no counterpart in GA and is not applied.

``flame_param.npz`` — exactly GA's keys, float32: ``shape (300,)``, ``expr (T, 100)``,
``rotation, neck_pose, jaw_pose, translation (T, 3)``, ``eyes_pose (T, 6)``,
``static_offset (1, N + 120, 3)``, ``dynamic_offset (T, N + 120, 3)``; shape and expression
coefficients are zero-padded to 300/100 (a model with more raises), absent offsets are zeros. GA
ignores ``dynamic_offset``; sage adds it when posing.

``sage_export.json`` records the topology (N, F, the teeth rows' source, how many surfels were
rebound). What was checked: the row counts, the binding range and, on sage's own test models,
GaussianAvatars' posing math (re-implemented) against sage's posed surfels. GaussianAvatars itself
places its teeth by FLAME vertex ids, so running it needs a real FLAME model file.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..workspace import atomic_write_bytes, atomic_write_text
from .ply import SH_C0, SURFEL_THICKNESS, _header, property_names

if TYPE_CHECKING:
    from ..avatar.model import Avatar
    from ..flame.model_data import FlameModelData
    from ..flame.params import FlameParams

GA_N_SHAPE = 300
GA_N_EXPR = 100
GA_SH_DEGREE = 3
GA_FLAME_KEYS: tuple[str, ...] = (
    "shape", "expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation", "static_offset", "dynamic_offset",
)  # fmt: skip
POINT_CLOUD = "point_cloud.ply"
FLAME_PARAM = "flame_param.npz"
EXPORT_RECORD = "sage_export.json"
GA_TEETH_VERTICES = 120
GA_TEETH_FACES = 168
GA_LOWER_TEETH_FIRST_FACE = 84
"""GaussianAvatars' teeth faces: 84 upper triangles, then 84 lower ones."""
# GaussianAvatars' first upper and first lower teeth triangle, as offsets into its teeth vertices
# (docs/formats.md §4 order: upper_root 0-14, lower_root 15-29, upper_edge 30-44, lower_edge 45-59, ...)
_GA_UPPER_ANCHOR = (0, 31, 30)
_GA_LOWER_ANCHOR = (45, 46, 15)
_NECK, _JAW = 1, 2


@dataclass
class GaussianAvatarsExport:
    """What :func:`write_gaussian_avatars` wrote: the folder, Gaussians, FLAME rows (timesteps),
    and GaussianAvatars' vertex count (N + 120); ``topology`` is the :class:`GATopology` record."""

    folder: Path
    n_gaussians: int
    n_timesteps: int
    n_vertices: int
    topology: dict[str, Any]

    def record(self) -> dict[str, Any]:
        """Plain-data numbers for the export's results index."""
        t = self.topology
        return {"ga_vertices": t["n_vertices"], "ga_faces": t["n_faces"], "teeth_rows": t["teeth_rows"],
                "rebound_from_mouth_interior": t["rebound"]}  # fmt: skip


@dataclass
class GATopology:
    """sage's model mapped onto GaussianAvatars' FLAME (module doc).

    n_model_vertices, n_model_faces: N and F of the user's model. sage_teeth_are_ga: sage's teeth
    rows are GaussianAvatars' (then its offset rows are copied, else zeros). faces: (F + 2, 3) the
    model's faces then the two GaussianAvatars teeth triangles used as anchors, in sage's vertex
    ids (only meaningful when sage_teeth_are_ga); ga_face_ids: (F + 2,) their GaussianAvatars ids.
    """

    n_model_vertices: int
    n_model_faces: int
    sage_teeth_are_ga: bool
    faces: np.ndarray
    ga_face_ids: np.ndarray

    @property
    def n_vertices(self) -> int:
        return self.n_model_vertices + GA_TEETH_VERTICES

    @property
    def n_faces(self) -> int:
        return self.n_model_faces + GA_TEETH_FACES


def ga_topology(md: FlameModelData) -> GATopology:
    """Map a sage model (the user's FLAME model plus sage's appended parts) onto GaussianAvatars'
    FLAME (module doc). ValueError when the model's own faces are not the first faces of sage's
    table (a model sage did not extend that way)."""
    from ..flame.teeth import FLAME_N_VERTICES, TEETH_FACE_TABLE

    n = int(md.n_base_vertices)
    faces = np.asarray(md.faces, dtype=np.int64)
    own = (faces < n).all(axis=1)
    n_faces = int(own.sum())
    if not own[:n_faces].all():
        raise ValueError("the model's own faces are not the first faces of its face table")
    up = np.asarray(md.vertex_groups.get("teeth_upper", []), dtype=np.int64)
    lo = np.asarray(md.vertex_groups.get("teeth_lower", []), dtype=np.int64)
    ga_upper = n + np.concatenate([np.arange(0, 15), np.arange(30, 45), np.arange(60, 90)])
    ga_lower = n + np.concatenate([np.arange(15, 30), np.arange(45, 60), np.arange(90, 120)])
    teeth_are_ga = (n == FLAME_N_VERTICES and TEETH_FACE_TABLE in str(md.face_table).split("+")
                    and np.array_equal(np.sort(up), ga_upper) and np.array_equal(np.sort(lo), ga_lower))  # fmt: skip
    anchors = np.array([_GA_UPPER_ANCHOR, _GA_LOWER_ANCHOR], dtype=np.int64) + n
    ids = np.concatenate([np.arange(n_faces), [n_faces, n_faces + GA_LOWER_TEETH_FIRST_FACE]]).astype(np.int64)
    return GATopology(n, n_faces, bool(teeth_are_ga), np.concatenate([faces[:n_faces], anchors], 0), ids)


def ga_binding(md: FlameModelData, topo: GATopology, binding: np.ndarray, vertices: np.ndarray,
               means: np.ndarray) -> tuple[np.ndarray, int]:
    """Each surfel's row in ``topo.faces`` (its own face, or the one it is rebound to; module doc)
    and how many were rebound.

    binding: (N,) sage face ids; vertices: (V, 3) sage's canonical mesh; means: (N, 3) canonical
    surfel centres.
    """
    from scipy.spatial import cKDTree

    b = np.asarray(binding, dtype=np.int64)
    out = b.copy()
    moved = b >= topo.n_model_faces
    if not moved.any():
        return out, 0
    faces = np.asarray(md.faces, dtype=np.int64)
    if topo.sage_teeth_are_ga:
        joint = np.asarray(md.lbs_weights)[faces[b[moved], 0]].argmax(1)
        rigid = np.isin(joint, (_NECK, _JAW))
        idx = np.flatnonzero(moved)
        out[idx[rigid]] = np.where(joint[rigid] == _NECK, topo.n_model_faces, topo.n_model_faces + 1)
        moved[idx[rigid]] = False
    if moved.any():
        v = np.asarray(vertices, dtype=np.float64)
        _, near = cKDTree(v[faces[: topo.n_model_faces]].mean(1)).query(np.asarray(means, dtype=np.float64)[moved])
        out[moved] = near
    return out, int((b >= topo.n_model_faces).sum())


def ga_local_gaussians(avatar: Avatar, view_from: torch.Tensor | None = None, topology: GATopology | None = None) -> dict[str, np.ndarray]:
    """The avatar's surfels as GA local Gaussians (module doc), float32.

    view_from: (3,) canonical-space point the colours are evaluated for (None: each surfel seen
    along its normal). topology: bind into GaussianAvatars' face table (:func:`ga_topology`;
    ``binding`` then holds GaussianAvatars' face ids and ``rebound`` the count of surfels moved off
    sage's mouth interior); None keeps sage's own faces and bindings.
    Returns xyz (N, 3), f_dc (N, 3), f_rest (N, 45) channel-major zeros, opacity (N,) logit,
    scale (N, 3) log k-relative, rot (N, 4) wxyz unit, binding (N,) int64.
    """
    from ..flame.canonical import canonical_inputs
    from ..flame.frames import triangle_frames
    from ..geometry.rotations import matrix_to_quat, quat_conjugate, quat_multiply, quat_normalize

    rebound = 0
    with torch.no_grad():
        cs = avatar.canonical_state(with_sdf=avatar.attributes == "mlp")
        inputs = canonical_inputs(avatar.params, avatar.canonical_timestep, avatar.device)
        posed = avatar.posed(inputs, view_from, canonical=cs)
        if topology is None:
            faces = avatar.faces
            b = avatar.surfels.binding.to(torch.long)
            ids = None
        else:
            faces = torch.as_tensor(topology.faces, device=avatar.device)
            rows, rebound = ga_binding(avatar.model_data, topology, avatar.surfels.binding.cpu().numpy(),
                                       avatar.canonical_vertices.detach().cpu().numpy(), cs.means.detach().cpu().numpy())
            b = torch.as_tensor(rows, device=avatar.device)
            ids = topology.ga_face_ids[rows]
        R, T, k = triangle_frames(avatar.canonical_vertices, faces)
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
        "binding": (b.cpu().numpy() if ids is None else ids).astype(np.int64),
        "rebound": np.array(rebound),
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
    comments = ["GaussianAvatars local Gaussians (binding_0 = face id of GaussianAvatars' FLAME), exported by sage"]
    return _header(names, n, comments) + np.ascontiguousarray(rows).tobytes()


def _pad_cols(a: np.ndarray, width: int, key: str) -> np.ndarray:
    if a.shape[-1] > width:
        raise ValueError(f"{key} has {a.shape[-1]} coefficients; GaussianAvatars' FLAME takes at most {width}")
    pad = [(0, 0)] * (a.ndim - 1) + [(0, width - a.shape[-1])]
    return np.pad(a, pad)


def ga_offset_rows(offsets: np.ndarray, n_model: int, teeth_from_sage: bool) -> np.ndarray:
    """(..., V_sage, 3) per-vertex offsets (sage's rows: the model's N, then its appended parts)
    -> (..., N + 120, 3) in GaussianAvatars' rows: the model's N rows, then sage's next 120 rows
    when ``teeth_from_sage`` (sage's teeth are GaussianAvatars'), else zeros."""
    a = np.asarray(offsets, dtype=np.float64)
    out = np.zeros(a.shape[:-2] + (n_model + GA_TEETH_VERTICES, 3))
    keep = min(a.shape[-2], n_model + GA_TEETH_VERTICES if teeth_from_sage else n_model)
    out[..., :keep, :] = a[..., :keep, :]
    return out


def ga_flame_arrays(params: FlameParams, topology: GATopology, shape: np.ndarray | None = None,
                    static_offset: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """GA's ``flame_param.npz`` arrays (module doc) for the T rows of ``params``.

    shape (S,) and static_offset (V, 3) replace the params' own when given (a motion driving
    another subject); offsets go to GaussianAvatars' N + 120 rows (:func:`ga_offset_rows`).
    """
    T = params.n_timesteps
    n, teeth = topology.n_model_vertices, topology.sage_teeth_are_ga
    shp = np.asarray(params.shape if shape is None else shape, dtype=np.float64).reshape(-1)
    so = params.static_offset if static_offset is None else static_offset
    so = np.zeros((topology.n_vertices, 3)) if so is None else ga_offset_rows(np.asarray(so).reshape(-1, 3), n, teeth)
    do = params.dynamic_offset
    do = np.zeros((T, topology.n_vertices, 3)) if do is None else ga_offset_rows(do, n, teeth)
    out = {
        "shape": _pad_cols(shp, GA_N_SHAPE, "shape"),
        "expr": _pad_cols(np.asarray(params.expr, dtype=np.float64), GA_N_EXPR, "expr"),
        "rotation": params.rotation, "neck_pose": params.neck_pose, "jaw_pose": params.jaw_pose,
        "eyes_pose": params.eyes_pose, "translation": params.translation,
        "static_offset": so[None], "dynamic_offset": do,
    }  # fmt: skip
    return {key: np.ascontiguousarray(out[key], dtype=np.float32) for key in GA_FLAME_KEYS}


def write_gaussian_avatars(avatar: Avatar, folder: str | Path, params: FlameParams | None = None) -> GaussianAvatarsExport:
    """Write ``folder/point_cloud.ply``, ``folder/flame_param.npz`` and ``folder/sage_export.json``
    (module doc), atomically.

    params: the FLAME sequence to store (default: the avatar's own tracked sequence); its shape and
    static offset are replaced by the avatar's own.
    """
    folder = Path(folder)
    md = avatar.model_data
    topo = ga_topology(md)
    g = ga_local_gaussians(avatar, topology=topo)
    atomic_write_bytes(folder / POINT_CLOUD, encode_ga_point_cloud(g))
    own = avatar.params
    arrays = ga_flame_arrays(own if params is None else params, topo, shape=own.shape, static_offset=own.static_offset)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(folder / FLAME_PARAM, buf.getvalue())
    doc = {
        "n_vertices": topo.n_vertices,
        "n_faces": topo.n_faces,
        "n_model_vertices": topo.n_model_vertices,
        "n_model_faces": topo.n_model_faces,
        "sage_face_table": str(md.face_table),
        "teeth_rows": "sage's teeth (GaussianAvatars' order)" if topo.sage_teeth_are_ga else "zeros (sage's teeth are not GaussianAvatars')",
        "rebound": int(g["rebound"]),
        "rebound_to": ("GaussianAvatars' first upper / lower teeth triangle of the surfel's jaw" if topo.sage_teeth_are_ga
                       else "the nearest face of the model (by centroid, canonical mesh)"),
        "frame_convention": "GaussianAvatars [a0,a1,a2]",
        "gaussians": int(g["xyz"].shape[0]),
        "timesteps": int(arrays["expr"].shape[0]),
    }  # fmt: skip
    atomic_write_text(folder / EXPORT_RECORD, json.dumps(doc, indent=2, sort_keys=True) + "\n")
    return GaussianAvatarsExport(folder, int(g["xyz"].shape[0]), int(arrays["expr"].shape[0]), topo.n_vertices,
                                 {"n_vertices": topo.n_vertices, "n_faces": topo.n_faces, "teeth_rows": doc["teeth_rows"],
                                  "rebound": doc["rebound"]})  # fmt: skip
