"""Fitting FLAME and the cameras to the observations of every image at once.

Unknowns: the identity (shared), per timestep the expression, jaw, eyes, neck, head rotation and
translation; an uncalibrated camera's focal length (one per camera; its principal point stays at
the image centre); a calibrated rig's scale when its units are not metres; and, with region masks
that name the scalp, a smooth offset along the normals over the hair (the static offset: hair volume).

Three stages, all with Adam on every frame together:

1. **rigid**: head rotation and translation (and focal length, rig scale) from the landmarks, after a
   PnP initialisation per image;
2. **shape**: everything above on the landmarks (robust reprojection error in units of the face
   height, each landmark weighted by whether its triangle faces the camera and each image by how far
   the face is turned from the camera), priors on identity, expression and rotations, and temporal
   smoothing for videos;
   plus the silhouette term: the mesh's outline vertices in every image (found by rasterizing it with
   the project's mesh rasterizer, a few images per step in turn) against the signed distance to the
   person mask's outline; and the scalp offsets with a smoothness prior (squared differences along the mesh's edges);
3. **refine**: adds the photometric term on minibatches of images rasterized at the current fit (the
   images against the mesh coloured with the running mean of the colours every image sees at each
   vertex, through barycentrics that follow the vertices).

Long ordered sequences (videos; more timesteps than ``cfg.keyframes``) are fitted in two passes: the three stages on
evenly spaced keyframes (the shared parameters: identity, focal length, rig scale, landmark and scalp
offsets, and the keyframes' own), then every timestep with the shared parameters frozen, chunk by chunk
in time order (``cfg.track_chunk`` timesteps, warm-started from the keyframes interpolated, a short
**track** stage of ``cfg.track_steps`` on landmarks and silhouettes), each chunk's temporal smoothing
tied to the timestep before it (already tracked) and the one after it (still the interpolation).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch

from ..flame import FlameModel, FlameParams
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..geometry.topology import edges
from ..render.mesh_raster import rasterize_mesh
from .config import TrackConfig
from .embedding import LandmarkEmbedding, same_landmarks
from .flame_subset import FlameSubset, JointBasis
from .losses import (charbonnier, facing, pixel_barycentrics, project, sample_map, signed_distance, triangle_normals,
                     triangle_plane_frame, visibility_weight)
from .mesh_utils import edge_faces

Progress = Callable[..., None]
TRANS_UNIT = 0.1  # metres per unit of the translation parameter
PIXEL_UNIT = 100.0  # pixels per unit of a camera-relative head position
OFFSET_UNIT = 0.01  # metres per unit of the scalp offset parameter
SHARED = ("shape", "log_focal", "log_rig_scale", "offset", "lmk_offset")
"""Parameters shared by all timesteps (fitted on the keyframes of a long sequence, then frozen)."""
PER_TIMESTEP = ("expr", "rotation", "translation", "neck_pose", "jaw_pose", "eyes_pose")
"""Parameters of each timestep (rows of the parameter tensors); all of them are smoothed over time."""
ROTATIONS = ("rotation", "neck_pose", "jaw_pose", "eyes_pose")
"""Per-timestep parameters that are axis-angle rotations (eyes_pose: two of them), interpolated along
the rotation between two keyframes rather than coefficient by coefficient."""


@dataclass
class FitCamera:
    """A camera of the fit at the output image size: K (3, 3), w2c (4, 4), width, height, and whether
    its focal length is fitted (``fit_focal``)."""

    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    fit_focal: bool = False


@dataclass
class FitImage:
    """One image: its timestep row, camera, landmarks (468, 2) in output pixels (None: no face found,
    e.g. a profile view of a multiview rig), face height in pixels, and at the fit resolution its RGB
    (h, w, 3) and person probability (h, w) for the rasterized terms (None: skipped there)."""

    timestep: int
    camera: int
    landmarks: np.ndarray | None
    face_height: float
    rgb: np.ndarray | None = None
    person: np.ndarray | None = None


@dataclass
class FitProblem:
    """Everything the fit needs besides the model and the config.

    Attributes:
        cameras, images: see the dataclasses; n_timesteps: rows of the parameters.
        fit_rig_scale: fit one scale factor of the calibrated cameras' translations.
        smooth: smooth per-timestep parameters over time (videos).
        hair: vertex ids of the scalp offsets' region (None: no offsets).
        silhouette_exclude: (V,) bool, vertices never used as outline points (the neck opening).
        silhouette_inward: (V,) bool, outline vertices that the silhouette only pulls inwards (when they
            lie outside the person mask): where hair may cover the head's outline (ears, back of the head).
        silhouette_outward_max: outline points lying this far inside the person mask or further (in face
            heights) are not pulled outwards (None: up to the term's general cut-off, 0.2): what lies
            between them and the mask's edge is then hair, a collar or a hand rather than the head.
        hair_stage: with the face-only silhouette (``silhouette_inward``), end every joint fit with
            ``cfg.hair_steps`` steps that fit the hair volume (the scalp offsets) alone to the whole
            outline, both ways, the head's shape and pose held. With the face-only silhouette the scalp
            is only pulled inwards, so without it the hair volume never grows and the hair lies off the
            mesh (``TrackConfig.hair_fit``; measured in docs/track.md).
        landmark_offsets: fit one in-plane offset per landmark, shared by all images (the input sees
            the head from several directions, so a landmark's consistent disagreement with the
            embedding can be told from the shape).
        camera_relative: one uncalibrated camera: the head's position is fitted relative to it (its
            pixel position and a depth that scales with the focal length), so that a change of focal
            length moves every head along its viewing ray instead of changing the images.
        times: (n_timesteps,) position of each timestep on the time axis in frames (None: consecutive);
            the smoothing weighs the difference of two neighbouring timesteps by 1 / gap².
        steady_depth: with ``camera_relative``, pull every timestep's depth towards the timesteps' common
            depth (a head turning in front of a camera that stays put).
        steady_pivot: with ``camera_relative``, pull every timestep's pivot (the root joint) towards the
            timesteps' common position across the image and hold its depth as ``steady_depth`` does,
            whether that is set or not (a person sitting still and turning their head in front of a
            camera that stays put).
        steady_pivot_auto: with ``camera_relative`` and ``steady_pivot`` off: fit the timesteps (a long
            sequence's keyframes) without the pivot held first, and hold it (fitting again) when their
            pivots already agree, their spread (:meth:`Fitter.pivot_spread`) within
            ``cfg.steady_depth_scale``, the scale the steady-pivot prior itself allows.
    """

    cameras: list[FitCamera]
    images: list[FitImage]
    n_timesteps: int
    fit_rig_scale: bool = False
    smooth: bool = False
    hair: np.ndarray | None = None
    silhouette_exclude: np.ndarray | None = None
    silhouette_inward: np.ndarray | None = None
    silhouette_outward_max: float | None = None
    hair_stage: bool = False
    landmark_offsets: bool = False
    camera_relative: bool = False
    times: np.ndarray | None = None
    steady_depth: bool = False
    steady_pivot: bool = False
    steady_pivot_auto: bool = False

    def subset(self, rows: np.ndarray) -> FitProblem:
        """The problem restricted to the timesteps ``rows`` (sorted, renumbered 0..len-1, their images
        shared, not copied); ``times`` keeps their positions on the time axis."""
        rows = np.asarray(rows, np.int64)
        new = {int(t): k for k, t in enumerate(rows)}
        times = (np.arange(self.n_timesteps, dtype=np.float64) if self.times is None else np.asarray(self.times, np.float64))[rows]
        images = [replace(im, timestep=new[im.timestep]) for im in self.images if im.timestep in new]
        return replace(self, images=images, n_timesteps=len(rows), times=times)


@dataclass
class FitResult:
    """The fit: FLAME parameters per timestep, cameras, and per-image diagnostics.

    Attributes:
        params: the fitted FLAME parameters (numpy float32): shape (S,), expr (T, E), rotation,
            neck_pose, jaw_pose, translation (T, 3), eyes_pose (T, 6), static_offset (V, 3) or None
            (the scalp offsets), dynamic_offset None, timesteps (T,) the rows 0..T-1.
        cameras: the fitted cameras (focal length, rig scale applied).
        reprojection_px: (N_images,) mean landmark error in output pixels (NaN without landmarks).
        reprojection_max_px: (N_images,) largest landmark error of each image.
        losses: stage -> final loss value.
        rig_scale: the fitted scale (1 when fixed).
        timings: pass -> seconds (``joint``, or ``keyframes`` and ``track``).
        keyframes: the timestep rows fitted with the full schedule (all of them without keyframes).
        pivot_check: with ``steady_pivot_auto``: the pivot's spread over the timesteps fitted without it
            held (``spread``) and whether it was then held (``held``); empty otherwise.
    """

    params: FlameParams
    cameras: list[FitCamera]
    reprojection_px: np.ndarray
    reprojection_max_px: np.ndarray
    losses: dict[str, float] = field(default_factory=dict)
    rig_scale: float = 1.0
    timings: dict[str, float] = field(default_factory=dict)
    keyframes: list[int] = field(default_factory=list)
    pivot_check: dict[str, float | bool] = field(default_factory=dict)


def interpolate_rotations(a: torch.Tensor, b: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Rotations a fraction ``w`` of the way from ``a`` to ``b`` along the shortest rotation between them.

    a, b: (N, 3k) k axis-angle vectors per row; w: (N, 1) in [0, 1]. Returns (N, 3k) axis-angle.
    """
    n = a.shape[0]
    Ra = axis_angle_to_matrix(a.reshape(n, -1, 3).double())
    Rb = axis_angle_to_matrix(b.reshape(n, -1, 3).double())
    rel = matrix_to_axis_angle(Ra.transpose(-1, -2) @ Rb)  # (N, k, 3), angle <= pi
    out = matrix_to_axis_angle(Ra @ axis_angle_to_matrix(rel * w.double()[:, :, None]))
    return out.reshape(n, -1).to(a.dtype)


def _active(dirs: torch.Tensor, limit: int) -> int:
    """Number of leading blendshape columns to fit: up to ``limit``, stopping after the last non-zero one."""
    if dirs.numel() == 0 or limit <= 0:
        return 0
    nz = torch.nonzero(dirs.abs().amax(dim=0) > 0).flatten()
    return 0 if nz.numel() == 0 else min(limit, int(nz.max()) + 1)


class Fitter:
    """Runs the three stages on a :class:`FitProblem` (see the module docstring)."""

    def __init__(self, flame: FlameModel, emb: LandmarkEmbedding, problem: FitProblem, cfg: TrackConfig,
                 progress: Progress | None = None, seed: int = 0, pivot_embedding: LandmarkEmbedding | None = None) -> None:
        """``pivot_embedding``: the embedding the fit uses once ``steady_pivot_auto`` holds the pivot (the
        same landmarks with a wider pose table; None: ``emb`` throughout)."""
        self.flame = flame
        self.emb = emb
        if pivot_embedding is not None and not same_landmarks(pivot_embedding, emb):
            raise ValueError("pivot_embedding must embed the same landmarks as the embedding (it may differ in its pose table)")
        self.pivot_embedding = pivot_embedding
        self.p = problem
        self.cfg = cfg
        self.progress = progress
        self.gen = torch.Generator().manual_seed(int(seed))
        self.faces = flame.faces
        self.dtype = flame.v_template.dtype
        self.device = flame.v_template.device
        T = problem.n_timesteps
        V = flame.n_vertices
        self.n_shape = _active(flame.shapedirs, cfg.shape_components)
        self.n_expr = _active(flame.exprdirs, cfg.expr_components)
        self.joints = JointBasis(flame, self.n_shape, self.n_expr)
        z = lambda *s: torch.zeros(*s, dtype=self.dtype, device=self.device)  # noqa: E731
        self.params = {
            "shape": torch.nn.Parameter(z(self.n_shape)),
            "expr": torch.nn.Parameter(z(T, self.n_expr)),
            "rotation": torch.nn.Parameter(z(T, 3)),
            "translation": torch.nn.Parameter(z(T, 3)),
            "neck_pose": torch.nn.Parameter(z(T, 3)),
            "jaw_pose": torch.nn.Parameter(z(T, 3)),
            "eyes_pose": torch.nn.Parameter(z(T, 6)),
            "log_focal": torch.nn.Parameter(z(len(problem.cameras))),
            "log_rig_scale": torch.nn.Parameter(z(1)),
            "offset": torch.nn.Parameter(z(0 if problem.hair is None else len(problem.hair))),
            "lmk_offset": torch.nn.Parameter(z(len(emb), 2)),
        }
        self.K0 = self._t(np.stack([c.K for c in problem.cameras]))
        self.w2c0 = self._t(np.stack([c.w2c for c in problem.cameras]))
        self.focal_mask = torch.tensor([c.fit_focal for c in problem.cameras], dtype=torch.bool, device=self.device)
        # landmark observations
        lm = [im for im in problem.images if im.landmarks is not None]
        self.lm_images = [i for i, im in enumerate(problem.images) if im.landmarks is not None]
        ids = torch.as_tensor(emb.landmark_ids, dtype=torch.long, device=self.device)
        self.obs = self._t(np.stack([im.landmarks for im in lm]))[:, ids] if lm else z(0, len(emb), 2)
        self.obs_scale = self._t(np.array([im.face_height for im in lm]))
        self.obs_t = torch.as_tensor([im.timestep for im in lm], dtype=torch.long, device=self.device)
        self.obs_c = torch.as_tensor([im.camera for im in lm], dtype=torch.long, device=self.device)
        # (N, K) 1 where the landmark lies inside its image: the landmark model's points beyond the image's
        # edge (a face partly out of the frame) are its guesses and are left out of every landmark term
        size = self._t(np.array([[c.width, c.height] for c in problem.cameras], dtype=np.float64).reshape(-1, 2))[self.obs_c]
        self.obs_in = ((self.obs >= 0) & (self.obs <= size[:, None])).all(-1).to(self.dtype)
        self.tri = self.faces[torch.as_tensor(emb.faces, dtype=torch.long, device=self.device)]  # (K, 3)
        self.bary = self._t(emb.bary)
        # the detector's pose bias: (P, Y, K, 2) offsets over a pitch × yaw grid (radians), or None
        self.pose_table = self._pose_tensors(emb)
        # scalp offsets
        self.hair = None if problem.hair is None else torch.as_tensor(problem.hair, dtype=torch.long, device=self.device)
        if self.hair is not None:
            n = flame(shape=None).v_shaped[0]
            from .shading import vertex_normals

            self.hair_normals = vertex_normals(n, self.faces)[self.hair].detach()
            e = edges(self.faces.cpu().numpy())
            inside = np.zeros(V, bool)
            inside[problem.hair] = True
            e = e[inside[e[:, 0]] | inside[e[:, 1]]]  # edges within the region or along its border (where the offset is 0)
            slot = np.full(V, len(problem.hair), np.int64)
            slot[problem.hair] = np.arange(len(problem.hair))
            self.hair_edges = torch.as_tensor(slot[e], dtype=torch.long, device=self.device)
        # per-image silhouette maps at the fit resolution
        self.sil_inward = torch.as_tensor(problem.silhouette_inward if problem.silhouette_inward is not None
                                          else np.zeros(V, bool), device=self.device)
        self.sil_exclude = torch.as_tensor(problem.silhouette_exclude if problem.silhouette_exclude is not None
                                           else np.zeros(V, bool), device=self.device)
        ev, ef = edge_faces(self.faces.cpu().numpy())
        self.edge_v = torch.as_tensor(ev, dtype=torch.long, device=self.device)
        self.edge_f = torch.as_tensor(ef, dtype=torch.long, device=self.device)
        self.colour_sum = torch.zeros(V, 3, dtype=self.dtype, device=self.device)
        self.colour_n = torch.zeros(V, dtype=self.dtype, device=self.device)
        # silhouettes: each image's signed distance to its person mask's outline (fit resolution, padded
        # to one size) and the mesh vertices on its outline, re-rasterized a few images at a time
        self.sil_images = [i for i, im in enumerate(problem.images) if im.person is not None]
        self._sdt: torch.Tensor | None = None  # computed when the silhouette term first needs it
        self.sil_t = torch.as_tensor([problem.images[i].timestep for i in self.sil_images], dtype=torch.long, device=self.device)
        self.sil_c = torch.as_tensor([problem.images[i].camera for i in self.sil_images], dtype=torch.long, device=self.device)
        self.sil_fit = self._t(np.array([[problem.images[i].person.shape[1] / problem.cameras[problem.images[i].camera].width,
                                          problem.images[i].person.shape[0] / problem.cameras[problem.images[i].camera].height]
                                         for i in self.sil_images]).reshape(-1, 2))
        self.sil_scale = self._t(np.array([problem.images[i].face_height for i in self.sil_images])) * self.sil_fit[:, 1]
        self.outline = torch.full((len(self.sil_images), 0), -1, dtype=torch.long, device=self.device)
        self.outline_next = 0
        self._rebuild_subset()
        self.z0 = 1.0  # reference depth of camera-relative head positions (set by init_rigid)
        # common log depth of a chunk's sequence (the keyframes'), None: the mean of this fitter's timesteps
        self.depth_anchor: torch.Tensor | None = None
        # common pivot position across the image of a chunk's sequence (the keyframes'), None: the mean
        self.xy_anchor: torch.Tensor | None = None
        self.losses: dict[str, float] = {}
        self.timings: dict[str, float] = {}
        self.keyframes: list[int] = list(range(T))
        self.pivot_check: dict[str, float | bool] = {}
        # fixed neighbours of the first and last row for the smoothing (a chunk of a longer sequence):
        # name -> (1, d) tensors, or None
        self.smooth_before: dict[str, torch.Tensor] | None = None
        self.smooth_after: dict[str, torch.Tensor] | None = None

    def sdt_maps(self) -> tuple[torch.Tensor, tuple[int, int]]:
        """(signed distances (N_sil, h, w) of every silhouette image to its person mask's outline at the
        fit resolution, padded to one size; (w, h)), computed once."""
        if self._sdt is None:
            ims = [self.p.images[i] for i in self.sil_images]
            hmax = max(im.person.shape[0] for im in ims)
            wmax = max(im.person.shape[1] for im in ims)
            sdt = np.full((len(ims), hmax, wmax), float(max(hmax, wmax)), np.float32)
            for k, im in enumerate(ims):
                sdt[k, : im.person.shape[0], : im.person.shape[1]] = signed_distance(im.person > 0.5)
            self._sdt = self._t(sdt)
            self._sdt_size = (wmax, hmax)
        return self._sdt, self._sdt_size

    # -- model and cameras -------------------------------------------------------------------------

    def _pose_tensors(self, emb: LandmarkEmbedding) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The embedding's pose table as (pitches (P,), yaws (Y,) in radians, offsets (P, Y, K, 2)), or None."""
        if emb.pose is None:
            return None
        return self._t(np.deg2rad(emb.pose.pitches)), self._t(np.deg2rad(emb.pose.yaws)), self._t(emb.pose.offsets)

    def _t(self, a: np.ndarray) -> torch.Tensor:
        """A float tensor of the fit's dtype on its device."""
        return torch.as_tensor(np.asarray(a), device=self.device).to(self.dtype)

    def static_offset(self) -> torch.Tensor | None:
        if self.hair is None:
            return None
        off = torch.zeros(self.flame.n_vertices, 3, dtype=self.dtype, device=self.device)
        return off.index_add(0, self.hair, (self.params["offset"] * OFFSET_UNIT)[:, None] * self.hair_normals)

    def cameras(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(K (C, 3, 3), w2c (C, 4, 4)) with the fitted focal lengths and rig scale."""
        K = self.K0.clone()
        f = torch.where(self.focal_mask, torch.exp(self.params["log_focal"]), torch.ones_like(self.params["log_focal"]))
        K = torch.cat([K[:, :2, :2] * f[:, None, None], K[:, :2, 2:]], 2)
        K = torch.cat([K, self.K0[:, 2:]], 1)
        w2c = self.w2c0
        if self.p.fit_rig_scale:
            s = torch.exp(self.params["log_rig_scale"])
            w2c = torch.cat([w2c[:, :3, :3], w2c[:, :3, 3:] * s, ], 2)
            w2c = torch.cat([w2c, self.w2c0[:, 3:]], 1)
        return K, w2c

    def camera_centres(self, w2c: torch.Tensor) -> torch.Tensor:
        R = w2c[:, :3, :3]
        return -(R.transpose(1, 2) @ w2c[:, :3, 3:])[..., 0]

    def root_joint(self, expr: torch.Tensor) -> torch.Tensor:
        """(B, 3) rest position of joint 0 (the rotation's pivot) for the fitted identity and expressions (B, E)."""
        j = self.joints
        J0 = j.template[0] + torch.einsum("ck,k->c", j.shapedirs[0], self.params["shape"][: j.n_shape])
        J0 = J0[None] + torch.einsum("ck,bk->bc", j.exprdirs[0], expr[:, : j.n_expr])
        off = self.static_offset()
        return J0 if off is None else J0 + (self.flame.j_regressor[0] @ off)[None]

    def world_translation(self, trans: torch.Tensor, expr: torch.Tensor) -> torch.Tensor:
        """FLAME translations (B, 3) in metres from the translation parameters (B, 3): world decimetres,
        or with ``camera_relative`` the root joint's pixel offset from the principal point (in
        PIXEL_UNIT) and log depth relative to ``z0``, the depth scaling with the focal length."""
        if not self.p.camera_relative:
            return trans * TRANS_UNIT
        K, w2c = self.cameras()
        ratio = torch.exp(self.params["log_focal"][0]) if bool(self.focal_mask[0]) else trans.new_ones(())
        z = self.z0 * ratio * torch.exp(trans[:, 2])
        p = torch.stack([z * trans[:, 0] * PIXEL_UNIT / K[0, 0, 0], z * trans[:, 1] * PIXEL_UNIT / K[0, 1, 1], z], -1)
        R, t = w2c[0, :3, :3], w2c[0, :3, 3]
        X = (p - t) @ R  # camera -> world: R^T (p - t)
        return X - self.root_joint(expr)

    def pose_kwargs(self, rows: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        P = self.params
        sel = (lambda x: x) if rows is None else (lambda x: x[rows])  # noqa: E731
        return {"shape": P["shape"], "expr": sel(P["expr"]), "rotation": sel(P["rotation"]),
                "neck_pose": sel(P["neck_pose"]), "jaw_pose": sel(P["jaw_pose"]), "eyes_pose": sel(P["eyes_pose"]),
                "translation": self.world_translation(sel(P["translation"]), sel(P["expr"]))}

    def _rebuild_subset(self) -> None:
        """The posed-subset model over the landmark triangles' vertices and every image's outline vertices."""
        ids = torch.unique(torch.cat([self.tri.reshape(-1), self.outline[self.outline >= 0]]))
        self.sub = FlameSubset(self.flame, ids, self.joints)
        self.sub_lookup = torch.full((self.flame.n_vertices,), -1, dtype=torch.long, device=self.device)
        self.sub_lookup[ids] = torch.arange(ids.numel(), device=self.device)

    def posed_subset(self) -> torch.Tensor:
        """(T, n, 3) the subset's vertices at every timestep."""
        return self.sub(**self.pose_kwargs(), static_offset=self.static_offset())

    def full_vertices(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """(B, V, 3) posed meshes of the given timestep rows (all by default)."""
        kw = self.pose_kwargs(rows)
        return self.flame(**kw, static_offset=self.static_offset()).vertices

    # -- initialisation --------------------------------------------------------------------------

    def init_rigid(self) -> None:
        """Head rotation and translation of every timestep from PnP on the best image of that timestep."""
        import cv2

        with torch.no_grad():
            neutral = self.flame(shape=None)
            pts = self.emb.points(neutral.v_shaped[0], self.faces).double().cpu().numpy()
            J0 = neutral.joints[0, 0].double().cpu().numpy()
            K_all, w2c_all = self.cameras()
        best: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
        for n in range(self.obs.shape[0]):
            t, c = int(self.obs_t[n]), int(self.obs_c[n])
            K = K_all[c].double().cpu().numpy()
            keep = self.obs_in[n].cpu().numpy() > 0
            if keep.sum() < 6:
                continue
            img = self.obs[n].double().cpu().numpy()[keep]
            ok, rvec, tvec = cv2.solvePnP(pts[keep], img, K, None, flags=cv2.SOLVEPNP_EPNP)
            if not ok:
                continue
            rvec, tvec = cv2.solvePnPRefineLM(pts[keep], img, K, None, rvec, tvec)
            proj, _ = cv2.projectPoints(pts[keep], rvec, tvec, K, None)
            err = float(np.median(np.linalg.norm(proj[:, 0] - img, axis=1))) / float(self.obs_scale[n])
            Rc = cv2.Rodrigues(rvec)[0]
            if np.linalg.det(Rc) < 0 or tvec[2, 0] <= 0:
                continue
            w2c = w2c_all[c].double().cpu().numpy()
            Rw, tw = w2c[:3, :3], w2c[:3, 3]
            R0 = Rw.T @ Rc
            tr = Rw.T @ (tvec[:, 0] - tw) - J0 + R0 @ J0
            if t not in best or err < best[t][0]:
                best[t] = (err, R0, tr)
        if self.p.camera_relative and best:
            Kc, Wc = K_all[0].double().cpu().numpy(), w2c_all[0].double().cpu().numpy()
            cam_pos = {t: Wc[:3, :3] @ (J0 + tr) + Wc[:3, 3] for t, (_, _, tr) in best.items()}
            self.z0 = float(np.median([p[2] for p in cam_pos.values()]))
            for t, p in cam_pos.items():
                best[t] = (best[t][0], best[t][1], np.array([p[0] / p[2] * Kc[0, 0] / PIXEL_UNIT, p[1] / p[2] * Kc[1, 1] / PIXEL_UNIT,
                                                             np.log(p[2] / self.z0)]))
        with torch.no_grad():
            for t, (_, R0, tr) in best.items():
                aa = matrix_to_axis_angle(torch.as_tensor(R0, dtype=torch.float64)[None])[0]
                self.params["rotation"][t] = aa.to(self.params["rotation"])
                self.params["translation"][t] = self._t(tr if self.p.camera_relative else tr / TRANS_UNIT)
            known = sorted(best)
            for t in range(self.p.n_timesteps):  # timesteps without a PnP pose take the nearest one's
                if t not in best and known:
                    near = min(known, key=lambda k: abs(k - t))
                    self.params["rotation"][t] = self.params["rotation"][near]
                    self.params["translation"][t] = self.params["translation"][near]

    def init_rig_scale(self) -> None:
        """Scale of a calibrated rig in arbitrary units: from per-image PnP distances (metres) against
        the camera centres (rig units), by least squares over the images of each timestep."""
        import cv2

        with torch.no_grad():
            neutral = self.flame(shape=None)
            pts = self.emb.points(neutral.v_shaped[0], self.faces).double().cpu().numpy()
        K_all, w2c_all = self.K0.double().cpu().numpy(), self.w2c0.double().cpu().numpy()
        rows_a, rows_b = [], []
        by_t: dict[int, list[int]] = {}
        for n in range(self.obs.shape[0]):
            by_t.setdefault(int(self.obs_t[n]), []).append(n)
        T = self.p.n_timesteps
        for t, ns in by_t.items():
            if len(ns) < 2:
                continue
            for n in ns:
                c = int(self.obs_c[n])
                keep = self.obs_in[n].cpu().numpy() > 0
                if keep.sum() < 6:
                    continue
                ok, _, tvec = cv2.solvePnP(pts[keep], self.obs[n].double().cpu().numpy()[keep], K_all[c], None,
                                           flags=cv2.SOLVEPNP_EPNP)
                if not ok or tvec[2, 0] <= 0:
                    continue
                R, tw = w2c_all[c][:3, :3], w2c_all[c][:3, 3]
                # head centre h (camera frame, metres) = s·(R X + tw)  ->  R^T h · a − X = R^T tw, a = 1/s
                A = np.zeros((3, 1 + 3 * T))
                A[:, 0] = R.T @ tvec[:, 0]
                A[:, 1 + 3 * t: 4 + 3 * t] = -np.eye(3)
                rows_a.append(A)
                rows_b.append(R.T @ tw)
        if not rows_a:
            return
        sol = np.linalg.lstsq(np.concatenate(rows_a), np.concatenate(rows_b), rcond=None)[0]
        if sol[0] > 0:
            with torch.no_grad():
                self.params["log_rig_scale"][0] = -math.log(sol[0])

    # -- terms -----------------------------------------------------------------------------------

    def landmark_points(self, tri: torch.Tensor, extra: torch.Tensor | None = None) -> torch.Tensor:
        """Landmark positions (..., K, 3) on posed embedding triangles (..., K, 3, 3): the barycentric
        point plus the landmark's shared offset in its triangle's plane (along the first edge and the
        in-plane perpendicular; zero unless ``problem.landmark_offsets``) plus ``extra`` (..., K, 2),
        metres in the same frame (:meth:`pose_offsets`)."""
        pts = (tri * self.bary[:, :, None]).sum(-2)
        if not self.p.landmark_offsets and extra is None:
            return pts
        e1, e2 = triangle_plane_frame(tri)
        d = self.params["lmk_offset"] * OFFSET_UNIT if self.p.landmark_offsets else None
        if extra is not None:
            d = extra if d is None else d + extra
        return pts + d[..., :1] * e1 + d[..., 1:] * e2

    def pose_offsets(self, rows: torch.Tensor, tri: torch.Tensor, centres: torch.Tensor) -> torch.Tensor | None:
        """(N, K, 2) where the detector puts each landmark on the head of timestep ``rows`` (N,) seen from
        cameras at ``centres`` (N, 3): the embedding's pose table, bilinear in the camera's yaw and
        pitch seen from the face (the landmarks' centroid on the posed triangles ``tri`` (N, K, 3, 3); the
        global rotation and the neck's; clamped to the table), without gradient. None without a table."""
        if self.pose_table is None:
            return None
        pitches, yaws, table = self.pose_table
        with torch.no_grad():
            P = self.params
            R = axis_angle_to_matrix(P["rotation"].detach()[rows]) @ axis_angle_to_matrix(P["neck_pose"].detach()[rows])
            face = (tri.detach() * self.bary[:, :, None]).sum(-2).mean(1)
            d = (R.transpose(1, 2) @ (centres - face)[..., None])[..., 0]
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            yaw = torch.atan2(d[:, 0], d[:, 2])
            pitch = torch.asin(d[:, 1].clamp(-1.0, 1.0))

            def cell(grid: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                if grid.numel() == 1:
                    return torch.zeros_like(x, dtype=torch.long), torch.zeros_like(x)
                x = x.clamp(grid[0], grid[-1])
                i = (torch.searchsorted(grid, x.contiguous()) - 1).clamp(0, grid.numel() - 2)
                return i, (x - grid[i]) / (grid[i + 1] - grid[i])

            pi, pw = cell(pitches, pitch)
            yi, yw = cell(yaws, yaw)
            p1 = (pi + 1).clamp_max(pitches.numel() - 1)
            y1 = (yi + 1).clamp_max(yaws.numel() - 1)
            pw, yw = pw[:, None, None], yw[:, None, None]
            return ((1 - pw) * ((1 - yw) * table[pi, yi] + yw * table[pi, y1])
                    + pw * ((1 - yw) * table[p1, yi] + yw * table[p1, y1]))

    def view_weight(self, pts: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
        """(N,) weight of each landmark image by how far the camera is from the face's front: 1 up to
        ``landmark_full_deg``, falling to 0 at ``landmark_zero_deg`` (the detector's points slide on
        turned faces). pts: (N, K, 3) landmarks; centres: (N, 3) camera centres."""
        rot = axis_angle_to_matrix(self.params["rotation"].detach())[self.obs_t]  # (N, 3, 3)
        fwd = rot[:, :, 2]
        d = centres - pts.mean(1)
        cos = (fwd * d).sum(-1) / d.norm(dim=-1).clamp_min(1e-12)
        lo, hi = math.cos(math.radians(self.cfg.landmark_zero_deg)), math.cos(math.radians(self.cfg.landmark_full_deg))
        return ((cos - lo) / max(hi - lo, 1e-6)).clamp(0.0, 1.0) ** 2

    def landmark_terms(self, verts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(landmark loss, per-image mean pixel error (N,)) over every landmark image; verts: :meth:`posed_subset`."""
        if self.obs.shape[0] == 0:
            return torch.zeros((), dtype=self.dtype, device=self.device), torch.zeros(0, dtype=self.dtype, device=self.device)
        K, w2c = self.cameras()
        tri = verts[:, self.sub_lookup[self.tri]]  # (T, K, 3, 3)
        tri_i = tri[self.obs_t]
        Ki, Wi = K[self.obs_c], w2c[self.obs_c]
        with torch.no_grad():
            centres = self.camera_centres(Wi)
        pts_i = self.landmark_points(tri_i, self.pose_offsets(self.obs_t, tri_i, centres))
        uv, _ = project(pts_i, Ki, Wi)
        with torch.no_grad():
            cos = facing(triangle_normals(tri_i), pts_i, centres)
            w = visibility_weight(cos) * self.view_weight(pts_i, centres)[:, None] * self.obs_in
        err = (uv - self.obs).norm(dim=-1)  # (N, K) px
        r = err / self.obs_scale[:, None]
        loss = (w * charbonnier(r, self.cfg.landmark_scale)).sum() / w.sum().clamp_min(1e-9)
        px = (w * err).sum(1) / w.sum(1).clamp_min(1e-9)
        return loss, px

    def refresh_outlines(self, count: int) -> None:
        """Re-rasterize ``count`` images (round robin) at the current fit and store their outline vertices."""
        if not self.sil_images or count <= 0:
            return
        n = len(self.sil_images)
        pick = [(self.outline_next + k) % n for k in range(min(count, n))]
        self.outline_next = (self.outline_next + len(pick)) % n
        K, w2c = self.cameras()
        found: dict[int, torch.Tensor] = {}
        with torch.no_grad():
            rows = self.sil_t[pick]
            verts = self.full_vertices(torch.unique(rows))
            row_of = {int(t): k for k, t in enumerate(torch.unique(rows).tolist())}
            for k in pick:
                im = self.p.images[self.sil_images[k]]
                h, w = im.person.shape
                Kf = K[im.camera].clone()
                Kf[0] = Kf[0] * self.sil_fit[k, 0]
                Kf[1] = Kf[1] * self.sil_fit[k, 1]
                v = verts[row_of[im.timestep]]
                r = rasterize_mesh(v, self.faces, Kf, w2c[im.camera], w, h)
                uv, z = project(v[None], Kf[None], w2c[im.camera][None])
                found[k] = self.outline_vertices(v, uv[0], z[0], r.depth[0], w2c[im.camera])
        width = max([self.outline.shape[1]] + [int(v.numel()) for v in found.values()])
        out = torch.full((n, width), -1, dtype=torch.long, device=self.device)
        out[:, : self.outline.shape[1]] = self.outline
        for k, ids in found.items():
            out[k] = -1
            out[k, : ids.numel()] = ids
        self.outline = out
        self._rebuild_subset()

    def silhouette_term(self, verts: torch.Tensor, both_ways: bool = False) -> torch.Tensor:
        """Mean robust distance of every image's outline vertices to its person mask's outline, in face
        heights (distances beyond 0.2 face heights are ignored: occlusions, mask errors; inside the mask,
        beyond ``problem.silhouette_outward_max`` when set; inward-only vertices inside the mask too).
        ``both_ways``: every outline vertex pulled both ways, as the hair stage of :meth:`run_joint` does."""
        valid = self.outline >= 0
        if not bool(valid.any()):
            return torch.zeros((), dtype=self.dtype, device=self.device)
        K, w2c = self.cameras()
        Kf = K[self.sil_c].clone()
        Kf[:, 0] = Kf[:, 0] * self.sil_fit[:, :1]
        Kf[:, 1] = Kf[:, 1] * self.sil_fit[:, 1:]
        cid = self.sub_lookup[self.outline.clamp_min(0)]
        pts = verts[self.sil_t[:, None].expand_as(cid), cid]  # (N, M, 3)
        uv, _ = project(pts, Kf, w2c[self.sil_c])
        sdt, size = self.sdt_maps()
        d = sample_map(sdt, uv, *size) / self.sil_scale[:, None]
        keep = valid & (d.abs() < 0.2)
        if not both_ways:
            keep = keep & ~(self.sil_inward[self.outline.clamp_min(0)] & (d < 0))
            if self.p.silhouette_outward_max is not None:
                keep = keep & ~((d < 0) & (d.abs() >= self.p.silhouette_outward_max))
        return (charbonnier(d, self.cfg.silhouette_scale) * keep).sum() / keep.sum().clamp_min(1)

    def priors(self) -> torch.Tensor:
        P, c = self.params, self.cfg
        loss = c.w_shape * (P["shape"] ** 2).sum() + c.w_expr * (P["expr"] ** 2).sum(1).mean()
        loss = loss + c.w_pose * ((P["jaw_pose"] ** 2).sum(1) + (P["neck_pose"] ** 2).sum(1)
                                  + 4.0 * (P["eyes_pose"] ** 2).sum(1)).mean()
        loss = loss + c.w_focal * (P["log_focal"] ** 2).sum()
        if self.p.smooth:
            loss = loss + c.w_smooth * self.smoothness()
        if self.p.camera_relative and c.w_steady_depth > 0:
            if self.p.steady_depth or self.p.steady_pivot:  # the pivot's depth is held as steady_depth holds it
                loss = loss + c.w_steady_depth * self.steady_depth()
            if self.p.steady_pivot:
                loss = loss + c.w_steady_depth * self.steady_position()
        if self.p.landmark_offsets:
            loss = loss + c.w_landmark_offset * (P["lmk_offset"] ** 2).sum(1).mean()
        if self.hair is not None:
            off = P["offset"]
            loss = loss + c.w_offset * (off ** 2).mean()
            padded = torch.cat([off, off.new_zeros(1)])  # slot len(hair) = outside the region: offset 0
            diff = padded[self.hair_edges[:, 0]] - padded[self.hair_edges[:, 1]]
            loss = loss + c.w_offset_smooth * (diff ** 2).mean()
        return loss

    def steady_depth(self) -> torch.Tensor:
        """Mean robust deviation of the timesteps' log depths (the third camera-relative translation
        parameter) from their common value: the mean over the timesteps, or ``depth_anchor`` (a chunk's)."""
        logz = self.params["translation"][:, 2]
        ref = logz.mean() if self.depth_anchor is None else self.depth_anchor
        return charbonnier(logz - ref, self.cfg.steady_depth_scale).mean()

    def steady_position(self) -> torch.Tensor:
        """Mean robust deviation of the timesteps' pivot positions across the image (the first two
        camera-relative translation parameters) from their common value (the mean over the timesteps,
        or ``xy_anchor``, a chunk's), each measured as a share of the distance (pixels / focal length),
        on the same robust scale as :meth:`steady_depth`."""
        K, _ = self.cameras()
        per_unit = (PIXEL_UNIT / torch.stack([K[0, 0, 0], K[0, 1, 1]])).detach()
        xy = self.params["translation"][:, :2]
        ref = xy.mean(0) if self.xy_anchor is None else self.xy_anchor
        return charbonnier((xy - ref) * per_unit, self.cfg.steady_depth_scale).sum(-1).mean()

    def pivot_spread(self) -> float:
        """Largest standard deviation over the timesteps of the pivot's camera-relative position: its log
        depth, and its position across the image as a share of its distance (the measures of
        :meth:`steady_depth` and :meth:`steady_position`); 0 for one timestep."""
        tr = self.params["translation"].detach()
        if tr.shape[0] < 2:
            return 0.0
        K, _ = self.cameras()
        per_unit = (PIXEL_UNIT / torch.stack([K[0, 0, 0], K[0, 1, 1]])).detach()
        spread = torch.cat([tr[:, 2:3], tr[:, :2] * per_unit], 1).std(0, unbiased=False)
        return float(spread.max())

    def smoothness(self) -> torch.Tensor:
        """Sum over the per-timestep parameters of the mean squared difference of neighbouring timesteps,
        each pair weighted by 1 / gap² (``problem.times``), the fixed neighbours ``smooth_before`` /
        ``smooth_after`` (a chunk's) joining the sequence at a gap of 1."""
        P = self.params
        gap = np.diff(np.arange(self.p.n_timesteps, dtype=np.float64) if self.p.times is None else np.asarray(self.p.times, np.float64))
        gap = np.concatenate([[1.0] if self.smooth_before is not None else [], gap, [1.0] if self.smooth_after is not None else []])
        if gap.size == 0:
            return torch.zeros((), dtype=self.dtype, device=self.device)
        w = self._t(1.0 / np.maximum(gap, 1e-6) ** 2)
        total = torch.zeros((), dtype=self.dtype, device=self.device)
        for n in PER_TIMESTEP:
            x = P[n]
            if self.smooth_before is not None:
                x = torch.cat([self.smooth_before[n], x])
            if self.smooth_after is not None:
                x = torch.cat([x, self.smooth_after[n]])
            total = total + (w * ((x[1:] - x[:-1]) ** 2).sum(1)).mean()
        return total

    # -- rasterized terms ------------------------------------------------------------------------

    def outline_vertices(self, v: torch.Tensor, uv: torch.Tensor, z: torch.Tensor, depth: torch.Tensor,
                         w2c: torch.Tensor) -> torch.Tensor:
        """Vertex ids on the outer outline of a mesh (V, 3) seen by camera w2c: the ends of edges
        between a face turned towards the camera and one turned away that project within 2 pixels of the
        background of the raster's depth (h, w) (so not the contours of the nose or an ear inside the
        head's outline), excluding ``silhouette_exclude``. uv, z: (V, 2), (V,) projections at the
        raster's resolution."""
        tri = v[self.faces]
        n = triangle_normals(tri)
        centre = -(w2c[:3, :3].T @ w2c[:3, 3])
        front = ((centre - tri.mean(1)) * n).sum(-1) > 0
        sil = front[self.edge_f[:, 0]] != front[self.edge_f[:, 1]]
        ids = torch.unique(self.edge_v[sil].reshape(-1))
        ids = ids[~self.sil_exclude[ids]]
        if ids.numel() == 0:
            return ids
        h, w = depth.shape
        fg = torch.isfinite(depth)
        # pixels within 2 of the background: the outer outline (not the nose's or an ear's contour)
        near_bg = torch.nn.functional.max_pool2d((~fg).float()[None, None], 5, 1, 2)[0, 0] > 0
        p = uv[ids].floor().long()
        ok = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        ids, p = ids[ok], p[ok]
        return ids[near_bg[p[:, 1], p[:, 0]]]

    def photometric_term(self, batch: list[int]) -> torch.Tensor:
        """Photometric loss of a minibatch of images (indices into problem.images), rasterized at the
        current fit."""
        imgs = [self.p.images[i] for i in batch]
        rows = torch.as_tensor(sorted({im.timestep for im in imgs}), dtype=torch.long, device=self.device)
        row_of = {int(t): k for k, t in enumerate(rows.tolist())}
        verts = self.full_vertices(rows)
        K, w2c = self.cameras()
        photo = []
        for im in imgs:
            if im.person is None or im.rgb is None:
                continue
            h, w = im.person.shape
            cam = self.p.cameras[im.camera]
            sx, sy = w / cam.width, h / cam.height
            Kf = K[im.camera].clone()
            Kf = torch.cat([Kf[:1] * sx, Kf[1:2] * sy, Kf[2:]], 0)
            Wc = w2c[im.camera]
            v = verts[row_of[im.timestep]]
            with torch.no_grad():
                r = rasterize_mesh(v.detach(), self.faces, Kf.detach(), Wc.detach(), w, h)
            fid = r.face_id[0]
            fg = fid >= 0
            if not bool(fg.any()):
                continue
            uv, z = project(v[None], Kf[None], Wc[None])
            uv, z = uv[0], z[0]
            # photometric: the rendered pixels against the image through differentiable barycentrics
            ys, xs = torch.nonzero(fg & torch.as_tensor(im.person > 0.5, device=self.device), as_tuple=True)
            if ys.numel() > 0:
                if ys.numel() > 3000:
                    pick = torch.randperm(ys.numel(), generator=self.gen)[:3000].to(self.device)
                    ys, xs = ys[pick], xs[pick]
                f = fid[ys, xs]
                tri = self.faces[f]
                px = torch.stack([xs, ys], -1).to(self.dtype) + 0.5
                b = pixel_barycentrics(uv[tri], z[tri], px)
                target = self._t(im.rgb)[ys, xs]
                with torch.no_grad():  # accumulate the colours this image sees at its visible vertices
                    depth = r.depth[0]
                    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
                    vi = torch.nonzero(inside).flatten()
                    pix = uv[vi].long()
                    dz = depth[pix[:, 1], pix[:, 0]]
                    vis = vi[(z[vi] <= dz * 1.005) & torch.isfinite(dz)]
                    pv = uv[vis].long()
                    col = self._t(im.rgb)[pv[:, 1], pv[:, 0]]
                    self.colour_sum.index_add_(0, vis, col)
                    self.colour_n.index_add_(0, vis, torch.ones(vis.numel(), dtype=self.dtype, device=self.device))
                seen = self.colour_n[tri].min(1).values >= 2
                if bool(seen.any()):
                    mean = self.colour_sum / self.colour_n.clamp_min(1)[:, None]
                    pred = (b[seen][..., None] * mean[tri[seen]]).sum(1)
                    photo.append(charbonnier((pred - target[seen]).norm(dim=-1), 0.05).mean())
        return torch.stack(photo).mean() if photo else torch.zeros((), dtype=self.dtype, device=self.device)

    # -- stages ----------------------------------------------------------------------------------

    def _optimise(self, names: list[str], steps: int, stage: str) -> None:
        """Adam on the named parameters for ``steps`` steps (learning rate decaying to a tenth). The rigid
        stage uses the landmarks only; the others add the silhouettes (``refresh`` images re-rasterized per
        step), the refine stage the photometric term on a minibatch, and the hair stage pulls every outline
        vertex both ways (``silhouette_term``'s ``both_ways``)."""
        if steps <= 0:
            return
        c = self.cfg
        groups = []
        for n in names:
            p = self.params[n]
            if p.numel() == 0:
                continue
            lr = (c.track_lr if stage == "track" else c.lr) * (2.0 if n in ("expr", "shape", "offset") else 1.0)
            groups.append({"params": [p], "lr": lr, "base": lr})
        if not groups:
            return
        opt = torch.optim.Adam(groups)
        for p in self.params.values():
            p.requires_grad_(False)
        for n in names:
            self.params[n].requires_grad_(True)
        photo_imgs = [i for i, im in enumerate(self.p.images) if im.rgb is not None and im.person is not None]
        use_sil = stage != "rigid" and c.w_silhouette > 0 and bool(self.sil_images)
        use_photo = stage == "refine" and c.w_photo > 0 and bool(photo_imgs)
        if use_sil and self.outline.shape[1] == 0:
            self.refresh_outlines(len(self.sil_images))
        loss = torch.zeros(())
        # every image is re-rasterized about every outline_period steps, at most outline_refresh per step
        period = c.track_outline_period if stage == "track" else c.outline_period
        per_step = min(float(c.outline_refresh), len(self.sil_images) / period)
        credit = 0.0
        for step in range(steps):
            if use_sil and step > 0:
                credit += per_step
                self.refresh_outlines(int(credit))
                credit -= int(credit)
            frac = step / max(steps - 1, 1)
            for g in opt.param_groups:
                g["lr"] = g["base"] * (1.0 - 0.9 * frac)
            opt.zero_grad()
            verts = self.posed_subset()
            lm, px = self.landmark_terms(verts)
            loss = c.w_landmark * lm + self.priors()
            stats = {"landmark_px": float(px.detach().mean()) if px.numel() else float("nan")}
            if use_sil:
                sil = self.silhouette_term(verts, both_ways=stage == "hair")
                loss = loss + c.w_silhouette * sil
                stats["silhouette"] = float(sil.detach())
            if use_photo:
                perm = torch.randperm(len(photo_imgs), generator=self.gen)[: c.refine_batch]
                photo = self.photometric_term([photo_imgs[int(i)] for i in perm])
                loss = loss + c.w_photo * photo
                stats["photometric"] = float(photo.detach())
            loss.backward()
            opt.step()
            if self.progress is not None:
                self.progress(step + 1, steps, f"fitting: {stage}", loss=float(loss.detach()), **stats)
        self.losses[stage] = float(loss.detach())
        for p in self.params.values():
            p.requires_grad_(False)

    def run(self) -> FitResult:
        """All stages; returns the fit. An ordered sequence (``problem.smooth``: a video, or images with
        ``smooth_sequences``) with more timesteps than ``cfg.keyframes`` (> 0) is fitted on keyframes and
        then tracked chunk by chunk (module docstring): interpolating between keyframes is a start only
        where neighbouring timesteps are close in time. Anything else is fitted jointly."""
        T = self.p.n_timesteps
        keyframed = self.p.smooth and 0 < self.cfg.keyframes < T
        keys = self.keyframe_rows() if keyframed else np.arange(T)
        free = self.check_pivot(keys) if self.p.steady_pivot_auto and not self.p.steady_pivot and self.p.camera_relative else None
        if keyframed:
            self.run_keyframes(free)
        elif free is not None:  # the fit without the pivot held is the fit
            out = free.result()
            out.pivot_check = dict(self.pivot_check)
            return out
        else:
            t0 = time.time()
            self.run_joint()
            self.timings["joint"] = time.time() - t0
        return self.result()

    def keyframe_rows(self) -> np.ndarray:
        """The rows of a long sequence fitted with the full schedule: ``cfg.keyframes`` evenly spaced."""
        return np.unique(np.linspace(0, self.p.n_timesteps - 1, self.cfg.keyframes).round().astype(np.int64))

    def check_pivot(self, rows: np.ndarray) -> Fitter | None:
        """``steady_pivot_auto``: fit the timesteps ``rows`` without the pivot held; when their pivots'
        spread (:meth:`pivot_spread`) is within ``cfg.steady_depth_scale`` hold it from now on (this
        fitter's problem) and return None (fit again), else return that fit (the fitter of ``rows``).
        Records ``pivot_check``, and when it fits again the first fit's time (``pivot_check`` in ``timings``)."""
        t0 = time.time()
        free = self._child(rows, self.progress)
        free.run_joint()
        spread = free.pivot_spread()
        held = spread <= self.cfg.steady_depth_scale
        self.pivot_check = {"spread": round(spread, 5), "held": held}
        # the check's own cost when it leads to a second fit; otherwise its fit is the fit's first pass
        free.timings["joint"] = time.time() - t0
        if held:
            self.timings["pivot_check"] = free.timings["joint"]
            self.p = replace(self.p, steady_pivot=True)
            if self.pivot_embedding is not None:
                self.emb = self.pivot_embedding
                self.pose_table = self._pose_tensors(self.emb)
            return None
        return free

    def run_joint(self) -> None:
        """The three stages on every timestep at once."""
        c = self.cfg
        if self.p.fit_rig_scale:
            self.init_rig_scale()
        self.init_rigid()
        rigid = ["rotation", "translation"] + (["log_focal"] if bool(self.focal_mask.any()) else []) \
            + (["log_rig_scale"] if self.p.fit_rig_scale else [])
        self._optimise(rigid, c.rigid_steps, "rigid")
        full = rigid + ["shape", "expr", "neck_pose", "jaw_pose", "eyes_pose"] + (["lmk_offset"] if self.p.landmark_offsets else []) \
            + (["offset"] if self.hair is not None else [])
        self._optimise(full, c.steps, "shape")
        self._optimise(full, c.refine_steps, "refine")
        if self.p.hair_stage and self.hair is not None and self.hair.numel() and c.hair_steps > 0 and bool(self.sil_inward.any()):
            # the hair volume alone to the whole outline, both ways: the skull came from the face
            self._optimise(["offset"], c.hair_steps, "hair")

    def _child(self, rows: np.ndarray, progress: Progress | None) -> Fitter:
        """A fitter of the timesteps ``rows`` sharing this one's model, embedding, config and seed."""
        return Fitter(self.flame, self.emb, self.p.subset(rows), self.cfg, progress, seed=int(self.gen.initial_seed()))

    def run_keyframes(self, fitted: Fitter | None = None) -> None:
        """Keyframes with the full schedule (``fitted``: a fitter of the keyframe rows that has run
        already), then every timestep tracked with the shared parameters frozen."""
        c = self.cfg
        T = self.p.n_timesteps
        keys = self.keyframe_rows()
        t0 = time.time()
        kf = fitted
        if kf is None:
            kf = self._child(keys, self.progress)
            kf.run_joint()
        else:
            t0 -= kf.timings.get("joint", 0.0)
        self.z0 = kf.z0
        with torch.no_grad():
            for n in SHARED:
                self.params[n].copy_(kf.params[n])
            for n in PER_TIMESTEP:
                self.params[n].copy_(self._interpolate(kf.params[n], keys, T, rotation=n in ROTATIONS))
        self.losses.update({f"keyframes_{k}": v for k, v in kf.losses.items()})
        self.keyframes = [int(k) for k in keys]
        self.timings["keyframes"] = time.time() - t0
        t0 = time.time()
        chunks = [np.arange(a, min(a + c.track_chunk, T)) for a in range(0, T, c.track_chunk)]
        losses = []
        for k, rows in enumerate(chunks):
            ch = self._child(rows, None)
            ch.z0 = self.z0
            ch.depth_anchor = self.params["translation"][keys, 2].mean().detach().clone()
            ch.xy_anchor = self.params["translation"][keys, :2].mean(0).detach().clone()
            with torch.no_grad():
                for n in SHARED:
                    ch.params[n].copy_(self.params[n])
                for n in PER_TIMESTEP:
                    ch.params[n].copy_(self.params[n][rows])
            if self.p.smooth:
                a, b = int(rows[0]), int(rows[-1])
                ch.smooth_before = {n: self.params[n][a - 1: a].clone() for n in PER_TIMESTEP} if a > 0 else None
                ch.smooth_after = {n: self.params[n][b + 1: b + 2].clone() for n in PER_TIMESTEP} if b + 1 < T else None
            ch._optimise(list(PER_TIMESTEP), c.track_steps, "track")
            with torch.no_grad():
                for n in PER_TIMESTEP:
                    self.params[n][rows] = ch.params[n]
            losses.append(ch.losses.get("track", float("nan")))
            if self.progress is not None:
                self.progress(k + 1, len(chunks), "fitting: tracking every frame")
        if losses:
            self.losses["track"] = float(np.mean(losses))
        self.timings["track"] = time.time() - t0

    def _interpolate(self, values: torch.Tensor, keys: np.ndarray, n: int, rotation: bool = False) -> torch.Tensor:
        """Rows (len(keys), d) at the timesteps ``keys`` interpolated to all ``n`` timesteps (held constant
        beyond the first and last key): linearly, or with ``rotation`` (d a multiple of 3, axis-angle
        vectors) along the shortest rotation from one key to the next, at constant angular speed."""
        pos = np.arange(n, dtype=np.float64)
        hi = np.clip(np.searchsorted(keys, pos, side="right"), 1, len(keys) - 1) if len(keys) > 1 else np.zeros(n, np.int64)
        lo = np.maximum(hi - 1, 0)
        span = np.maximum(keys[hi] - keys[lo], 1)
        w = np.clip((pos - keys[lo]) / span, 0.0, 1.0)
        w = self._t(w)[:, None]
        a, b = values[torch.as_tensor(lo)], values[torch.as_tensor(hi)]
        if not rotation:
            return a * (1 - w) + b * w
        return interpolate_rotations(a, b, w)

    def result(self) -> FitResult:
        """The fitted parameters (numpy), cameras and per-image landmark errors."""
        with torch.no_grad():
            K, w2c = self.cameras()
            P = self.params
            n_img = len(self.p.images)
            rep = np.full(n_img, np.nan)
            rep_max = np.full(n_img, np.nan)
            if self.obs.shape[0]:
                verts = self.posed_subset()
                tri_i = verts[:, self.sub_lookup[self.tri]][self.obs_t]
                centres = self.camera_centres(w2c[self.obs_c])
                pts = self.landmark_points(tri_i, self.pose_offsets(self.obs_t, tri_i, centres))
                uv, _ = project(pts, K[self.obs_c], w2c[self.obs_c])
                cos = facing(triangle_normals(tri_i), pts, centres)
                w = (visibility_weight(cos) > 0.5) & (self.obs_in > 0)
                err = (uv - self.obs).norm(dim=-1)
                for n, i in enumerate(self.lm_images):
                    e = err[n][w[n]]
                    if e.numel():
                        rep[i] = float(e.mean())
                        rep_max[i] = float(e.max())
            cams = [FitCamera(K[i].double().cpu().numpy(), w2c[i].double().cpu().numpy(), cam.width, cam.height, cam.fit_focal)
                    for i, cam in enumerate(self.p.cameras)]
            off = self.static_offset()

            def np32(x: torch.Tensor) -> np.ndarray:
                return x.detach().float().cpu().numpy().copy()

            expr = torch.zeros(self.p.n_timesteps, self.flame.n_expr, dtype=self.dtype, device=self.device)
            expr[:, : self.n_expr] = P["expr"]
            shape = torch.zeros(self.flame.n_shape, dtype=self.dtype, device=self.device)
            shape[: self.n_shape] = P["shape"]
            params = FlameParams(
                shape=np32(shape), expr=np32(expr), rotation=np32(P["rotation"]), neck_pose=np32(P["neck_pose"]),
                jaw_pose=np32(P["jaw_pose"]), eyes_pose=np32(P["eyes_pose"]),
                translation=np32(self.world_translation(P["translation"], P["expr"])),
                static_offset=None if off is None else np32(off), dynamic_offset=None,
                timesteps=np.arange(self.p.n_timesteps, dtype=np.int64),
            )
            return FitResult(
                params=params, cameras=cams, reprojection_px=rep, reprojection_max_px=rep_max, losses=dict(self.losses),
                rig_scale=float(torch.exp(P["log_rig_scale"][0])) if self.p.fit_rig_scale else 1.0,
                timings={k: round(v, 2) for k, v in self.timings.items()}, keyframes=list(self.keyframes),
                pivot_check=dict(self.pivot_check),
            )
