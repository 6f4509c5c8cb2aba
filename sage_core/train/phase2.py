"""Phase 2: self-supervised fine-tuning for deformation robustness (SAGE §4).

Starting from the phase-1 avatar, the SDF and its hash grid are frozen (``requires_grad`` False, not
in the optimizer) and the surfel offsets and attribute heads (appearance and shape networks, or the
free per-surfel attributes) are fine-tuned; a group whose rate is 0 (by default the offsets) is
frozen the same way, so that what depends only on frozen tensors (the canonical centres, the SDF at
them and its hash encoding) is computed once, not every step. Each step:

1. samples an expression and pose: :class:`ExpressionSampler` with per-component ranges from the
   model's expression blendshapes (:func:`component_ranges_from_dirs`), a jaw range, gaze, and a
   mixture with the capture's own *training* expressions; the neck pose, global rotation and
   translation of a random training frame are jittered (the rotation jitter is composed on the left);
2. picks that training frame's camera, poses the surfels (with the surfel correction when enabled,
   :class:`~sage_core.avatar.corrected.CorrectedPosing`) and rasterizes them;
3. L_n (2DGS normal consistency) and L_d (depth distortion) of this deformed render;
4. appearance consistency: ``pixels.per_step`` pixels are drawn without replacement with probability
   ∝ e_n/mean(e_n) + e_d/mean(e_d) + ``pixels.error_floor`` (e_n = 1 − N_r·N_s and e_d the per-pixel
   distortion of the render, means over the candidates), among pixels whose ray hits the posed mesh
   on a non-hair triangle. Each pixel's teacher colour Ĉ is the canonical appearance of the surface
   point its ray hits, reached through the hit triangle's transform, from one of two teachers, both
   frozen at the phase-1 state and computed under ``no_grad``:

   * ``rest`` (default, :class:`~sage_core.train.rest_teacher.RestTeacher`): the phase-1 avatar's own
     rasterized renders of the training views at rest, looked up at the same triangle and
     barycentrics in the rest mesh, from the view whose direction in the triangle's frame is closest
     to the deformed ray's; surface points no training view sees have no teacher;
   * ``neus``: the ray warped into canonical space (:mod:`sage_core.train.warp`) and volume-rendered
     (NeuS) through the frozen SDF with a frozen copy of the phase-1 appearance network and
     s-variance.

   L_a = mean |Ĉ − I|² with I the rasterized surfel colour at those pixels;
5. optionally (``loss.photometric`` > 0) L_rgb of a captured training frame rendered at its own FLAME
   parameters; off by default, so phase 2 uses no images.

With ``expressions.rest_fraction`` > 0 a step poses the training frame exactly as captured with that
probability, so the appearance term also holds the avatar to its own phase-1 renders at rest.

Mouth-interior prior (``mouth.enabled``, SAGE's composited mouth prior): the surfels bound to
mouth-interior and teeth triangles that the training views at rest do not see get prior colours
(with ``mouth.visibility`` surfels, the default, those contributing under half a pixel of blending
weight, :meth:`Phase2Trainer.surfel_view_weights`; with faces those on triangles no training pixel
shows, :meth:`Phase2Trainer.seen_faces`): with ``mouth.prior`` learned the pretrained prior's albedo at their canonical
centre (:mod:`sage_core.avatar.mouth_prior`, :func:`learned_mouth_colors`); with table (the default)
the fixed ``mouth.cavity_color`` / ``mouth.teeth_color`` times their ambient visibility with the
jaw opened to ``mouth.occlusion_jaw`` (:meth:`Phase2Trainer.prior_visibility`). They are stored in the avatar
(:attr:`SurfelSet.color_prior`) and set before the first step; pixels on those triangles are left out
of the appearance term.

Unseen fill (``unseen_fill.enabled``; off by default, on in the single-camera regimes): the other
surfels that no training view sees at rest (less than ``SEEN_MIN_WEIGHT`` pixels of blending weight)
get, as their colour prior, the continuation of the albedos of the seen surfels of their region
group over the surfel graph (:mod:`sage_core.train.unseen_fill`, :func:`unseen_fill_groups`; the hair
only with ``unseen_fill.hair``, never from skin-coloured sources), and as their opacity floor the
median opacity of those sources with a gain on their scales that closes the gaps between them
(``unseen_fill.cover``, for the hair group and with ``unseen_fill.cover_neck`` the neck;
:meth:`Phase2Trainer.unseen_fill_colors`).

Wrinkle shading (``wrinkles.enabled``, on by default; :mod:`sage_core.avatar.wrinkles`): after the
last step every surfel gets a darkening amplitude, stored in the avatar and applied at render time in
proportion to the surface compression of the frame, measured on the mesh ``wrinkles.basis`` names (by
default FLAME's expression-shaped mesh, before skinning), which the avatar keeps. Which triangles may
darken is ``wrinkles.region``: ``skin`` (the default) gives every triangle outside hair and the mouth
prior the full amplitude; ``distortion`` (SAGE's rule) ramps it by the mean per-pixel distortion of
the deformed renders on the posed-mesh triangle each pixel sees, accumulated over the steps.

Total: λ_n L_n + λ_d L_d + λ_a L_a (+ λ_rgb L_rgb), the table :data:`PHASE2_TERMS` (weights in the
config's ``loss`` section). Every random draw uses the trainer's CPU
generator; :meth:`Phase2Trainer.state_dict` holds the parameters, the teacher, the optimizer, the
generator and the global RNG states, so a resumed run repeats the uninterrupted loss curve.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..avatar.corrected import CorrectedPosing
from ..avatar.init import REGION_EYES, REGION_FACE, REGION_HAIR, REGION_MOUTH, REGION_NECK, REGION_OTHER, face_region_labels
from ..avatar.model import Avatar
from ..avatar.posing import wrinkle_meshes
from ..avatar.wrinkles import FaceDistortionStats, face_compression, wrinkle_amplitude
from ..config import Phase2Config
from ..data.dataset import IngestedData, IngestedFrame, sample_indices
from ..errors import InputError
from ..flame.frames import surfel_frames
from ..geometry.knn import nearest_indices
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from ..geometry.topology import boundary_edges
from ..render import RenderCamera, rasterize_surfels
from ..render.mesh_raster import rasterize_mesh
from ..render.volume import render_neus
from ..runtime import resolve_render_backend
from ..workspace import rng_state, set_rng_state
from . import losses as L
from ._groups import adam, surfel_param_groups
from .expressions import ExpressionSampler, component_ranges_from_dirs
from .rest_teacher import RestTeacher, erode_mask
from .warp import pixel_rays, warp_pixels_to_canonical

TEACHERS: tuple[str, ...] = ("rest", "neus")

Progress = Callable[..., None]
STATE_FORMAT = 1


def hair_face_mask(avatar: Avatar, init_dir: str | Path | None = None) -> torch.Tensor:
    """(F,) bool hair triangles: from ``init_dir/regions.json`` when present, else the triangles that
    hair-region surfels are bound to."""
    F = int(avatar.faces.shape[0])
    if init_dir is not None:
        path = Path(init_dir) / "regions.json"
        if path.is_file():
            from ..flame.regions import Regions

            try:
                regions = Regions.from_dict(json.loads(path.read_text()))
                labels = face_region_labels(regions, F)
            except (ValueError, KeyError, TypeError) as e:
                raise InputError(path, f"malformed regions: {e}") from None
            return torch.as_tensor(labels == REGION_HAIR, device=avatar.device)
    mask = torch.zeros(F, dtype=torch.bool, device=avatar.device)
    s = avatar.surfels
    mask[s.binding[s.hair_mask()]] = True
    return mask


SEEN_MIN_WEIGHT = 0.5
"""Pixels of blending weight over the training views at rest below which a surfel counts as unseen."""


def unseen_fill_groups(hair: bool) -> tuple[tuple[int, ...], ...]:
    """Region labels the unseen fill continues together (one surfel graph and one set of sources per
    group): eyes, face, neck and mouth each alone; with ``hair`` the hair and the rest of the scalp
    (``other``: the back of the head below the scalp mask, the ears) as one group, else ``other``
    alone and the hair left out."""
    alone = ((REGION_FACE,), (REGION_EYES,), (REGION_NECK,), (REGION_MOUTH,))
    return (((REGION_HAIR, REGION_OTHER),) if hair else ((REGION_OTHER,),)) + alone


def mouth_prior_table(avatar: Avatar, init_dir: str | Path | None, cavity: list[float], teeth: list[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-face prior colours of the mouth interior: ((F, 3) colours, (F,) bool faces with a prior).

    The faces come from ``init_dir/regions.json`` (``mouth_interior`` with ``cavity``, ``teeth`` with
    ``teeth``); without that file, or without those regions, no face has a prior."""
    F = int(avatar.faces.shape[0])
    colors = torch.zeros(F, 3, device=avatar.device)
    has = torch.zeros(F, dtype=torch.bool, device=avatar.device)
    path = Path(init_dir) / "regions.json" if init_dir is not None else None
    if path is None or not path.is_file():
        return colors, has
    from ..flame.regions import Regions

    try:
        regions = Regions.from_dict(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(path, f"malformed regions: {e}") from None
    if regions.n_faces != F:
        raise InputError(path, f"regions describe {regions.n_faces} faces, the avatar has {F}")
    for name, rgb in (("mouth_interior", cavity), ("teeth", teeth)):
        if regions.has(name):
            m = torch.as_tensor(regions.face_mask(name), device=avatar.device)
            colors[m] = torch.tensor([float(v) for v in rgb], device=avatar.device)
            has |= m
    return colors, has


def learned_mouth_colors(avatar: Avatar, init_dir: str | Path | None, fallback: torch.Tensor) -> torch.Tensor:
    """(N, 3) per-surfel colours of the pretrained mouth prior (:mod:`sage_core.avatar.mouth_prior`)
    for the mouth-interior surfels, ``fallback`` (N, 3) for the others. Needs ``init_dir/regions.json``
    (present whenever :func:`mouth_prior_table` found mouth faces)."""
    from ..avatar.mouth_prior import avatar_prior_colors
    from ..flame.regions import Regions

    path = Path(init_dir) / "regions.json"  # type: ignore[arg-type]
    regions = Regions.from_dict(json.loads(path.read_text()))
    try:
        cols, on = avatar_prior_colors(avatar, regions)
    except ValueError as e:
        raise InputError(path, f"cannot place the mouth prior: {e}") from None
    out = fallback.clone()
    out[on] = cols[on].to(out)
    return out


def build_sampler(avatar: Avatar, data: IngestedData, cfg: Phase2Config, seed: int = 0) -> ExpressionSampler:
    """The expression sampler of phase 2: ranges from the model's expression blendshapes, the capture's
    training expressions (training timesteps only) as the observed mixture."""
    flame, x = avatar.flame, cfg.expressions
    E = int(flame.n_expr)
    V = int(avatar.canonical_vertices.shape[0])
    dirs = flame.exprdirs.detach().reshape(V, 3, E) if E else torch.zeros(V, 3, 0)
    std = component_ranges_from_dirs(dirs, cfg.expressions.target)
    rows = sorted({data.params.row_of(fr.timestep) for fr in data.train})
    obs_expr = np.asarray(data.params.expr)[rows] if rows else None
    obs_jaw = np.asarray(data.params.jaw_pose)[rows] if rows else None
    if obs_expr is not None and obs_expr.shape[1] == 0:
        obs_expr = obs_jaw = None
    return ExpressionSampler(
        E, std, clip_sigma=x.clip_sigma, n_active=x.active, jaw_range=(0.0, x.jaw_max),
        eye_range=x.eye_range, neck_std=x.neck_std, rotation_std=x.rotation_std,
        translation_std=x.translation_std, observed_expr=obs_expr, observed_jaw=obs_jaw,
        observed_weight=x.observed_weight if obs_expr is not None else 0.0, observed_noise=x.observed_noise,
        seed=seed, device=avatar.device,
    )  # fmt: skip


def compose_inputs(base: dict[str, torch.Tensor], sample: dict[str, torch.Tensor], i: int = 0) -> dict[str, torch.Tensor]:
    """FLAME kwargs (batch 1) of sample ``i`` applied to a frame's ``base`` kwargs: expression, jaw and
    gaze replaced, neck and translation jittered additively, rotation R = R_jitter·R_base."""
    out = {k: v for k, v in base.items() if k != "dynamic_offset"}
    ref = base["rotation"]
    out["expr"] = sample["expr"][i : i + 1].to(ref)
    out["jaw_pose"] = sample["jaw_pose"][i : i + 1].to(ref)
    out["eyes_pose"] = sample["eyes_pose"][i : i + 1].to(ref)
    out["neck_pose"] = base["neck_pose"] + sample["neck_pose"][i : i + 1].to(ref)
    Rj = axis_angle_to_matrix(sample["rotation"][i : i + 1].to(ref))
    Rb = axis_angle_to_matrix(base["rotation"].reshape(1, 3))
    out["rotation"] = matrix_to_axis_angle(Rj @ Rb).reshape(1, 3)
    out["translation"] = base["translation"] + sample["translation"][i : i + 1].to(ref)
    return out


def sample_pixels(
    score: torch.Tensor, candidates: torch.Tensor, n: int, floor: float, generator: torch.Generator
) -> torch.Tensor:
    """Draw up to n flat pixel ids without replacement among ``candidates`` (R,) with weights from the
    per-candidate error scores (R, k): Σ_j score_j / mean(score_j) + floor."""
    if candidates.numel() == 0 or n <= 0:
        return candidates[:0]
    s = score.detach().to(torch.float64).clamp_min(0)
    s = s / s.mean(0, keepdim=True).clamp_min(1e-12)
    w = (s.sum(-1) + floor).cpu()
    if not bool(torch.isfinite(w).all()) or float(w.sum()) <= 0:
        w = torch.ones_like(w)
    k = min(n, candidates.numel())
    pick = torch.multinomial(w, k, replacement=False, generator=generator)
    return candidates[pick.to(candidates.device)]


class Phase2Trainer:
    """Phase-2 optimisation (see the module doc).

    avatar: the phase-1 :class:`Avatar` (modified in place); data: the ingested capture (training
    cameras and frames); cfg: the stage config; generator: CPU generator for every random draw;
    init_dir: the init-mesh folder (hair triangles from its ``regions.json``; optional).
    """

    def __init__(
        self,
        avatar: Avatar,
        data: IngestedData,
        cfg: Phase2Config,
        device: str | torch.device = "cpu",
        generator: torch.Generator | None = None,
        init_dir: str | Path | None = None,
    ) -> None:
        self.avatar = avatar
        self.data = data
        self.cfg = cfg
        self.device = torch.device(device)
        self.render_backend = resolve_render_backend(cfg.render_backend, str(self.device))
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.step_count = 0
        self.frames: list[IngestedFrame] = list(data.train)
        if not self.frames:
            raise ValueError("no training frames")
        for p in avatar.sdf.parameters():
            p.requires_grad_(False)
        for p in avatar.variance.parameters():
            p.requires_grad_(False)
        self.teacher_app: torch.nn.Module | None = None
        self.teacher_variance: torch.nn.Module | None = None
        if cfg.teacher == "neus":
            self.teacher_app = copy.deepcopy(avatar.appearance).requires_grad_(False)
            self.teacher_variance = copy.deepcopy(avatar.variance).requires_grad_(False)
        self.posing = CorrectedPosing(
            avatar, cfg.correction.enabled, radius_edges=cfg.correction.radius_edges, max_neighbours=cfg.correction.max_neighbours,
            w_s=cfg.correction.w_s, umbilic_tol=cfg.correction.umbilic_tol, anisotropy_tol=cfg.correction.anisotropy_tol,
            mode=cfg.correction.mode,
        )  # fmt: skip
        self.hair_faces = hair_face_mask(avatar, init_dir)
        self.sampler = build_sampler(avatar, data, cfg)
        self.length_unit = float(avatar.sdf.half_extent)
        self._inputs: dict[int, dict[str, torch.Tensor]] = {}
        self._images: dict[tuple[int, int], torch.Tensor] = {}
        groups = self._param_groups()
        # the phase trains exactly the optimizer's parameters: the others take no gradient, so the
        # backward pass spends nothing on them and the posing may reuse what depends on them only
        # (CorrectedPosing.frozen_inputs: the surfel centres and the SDF at them)
        trained = {id(p) for g in groups for p in g["params"]}
        for p in avatar.parameters():
            p.requires_grad_(id(p) in trained)
        # every rate 0: the phase only attaches the mouth prior (and the wrinkle statistics) and
        # poses with the correction, without gradient steps
        self.optimizer: torch.optim.Adam | None = adam(groups) if groups else None
        for g in self.optimizer.param_groups if self.optimizer is not None else []:
            g["base_lr"] = g["lr"]
        self.distortion_curve: list[float] = []
        self.prior_colors, mouth_faces = mouth_prior_table(avatar, init_dir, cfg.mouth.cavity_color, cfg.mouth.teeth_color)
        if not cfg.mouth.enabled:
            mouth_faces = torch.zeros_like(mouth_faces)
        self.prior_faces = mouth_faces.clone()
        b = avatar.surfels.binding
        on = torch.zeros(len(avatar.surfels), dtype=torch.bool, device=avatar.device)
        rgb = self.prior_colors[b].clone()
        learned = cfg.mouth.prior == "learned" and bool(mouth_faces.any())
        if learned:
            rgb = learned_mouth_colors(avatar, init_dir, rgb)
        weights: torch.Tensor | None = None
        if bool(mouth_faces.any()):
            self.prior_faces &= ~self.seen_faces()
            if cfg.mouth.visibility == "faces":
                on = self.prior_faces[b]
            else:
                weights = self.surfel_view_weights()
                on = mouth_faces[b] & ~(weights >= SEEN_MIN_WEIGHT)
            if not learned and cfg.mouth.occlusion_jaw > 0 and bool(on.any()):
                rgb[on] *= self.prior_visibility(on, cfg.mouth.occlusion_jaw)[:, None].to(rgb)
        self.unseen_fill_result: Any = None
        if cfg.unseen_fill.enabled:
            weights = self.surfel_view_weights() if weights is None else weights
            fill, fill_rgb = self.unseen_fill_colors(weights, on, cfg.unseen_fill.neighbours)
            rgb[fill] = fill_rgb.to(rgb)
            on = on | fill
            res = self.unseen_fill_result
            cov = fill | res.covered.to(fill.device)  # filled surfels keep their opacity at the fill as a floor
            if cfg.unseen_fill.cover and res.opacity is not None and bool(cov.any()):
                floor = torch.stack([torch.where(cov, res.opacity, torch.zeros_like(res.opacity)), res.scale_gain.to(res.opacity)], -1)
                avatar.surfels.set_unseen_floor(floor)
        if bool(mouth_faces.any()) or bool(on.any()):
            avatar.surfels.set_color_prior(torch.cat([rgb, on.to(rgb)[:, None]], -1))
        self.rest_teacher: RestTeacher | None = None
        if cfg.teacher == "rest" and cfg.loss.appearance > 0:
            self.rest_teacher = self._build_rest_teacher()
        self.wrinkle_stats: FaceDistortionStats | None = None
        if cfg.wrinkles.enabled:
            avatar.wrinkle_basis = cfg.wrinkles.basis
            self.wrinkle_stats = FaceDistortionStats(int(avatar.faces.shape[0]), self.device)

    # ------------------------------------------------------------------ setup
    def _param_groups(self) -> list[dict[str, Any]]:
        lr = self.cfg.lr
        return surfel_param_groups(
            self.avatar,
            lr_position=lr.position,
            lr_networks=lr.networks,
            lr_rotation=lr.rotation,
            lr_scale=lr.scale,
            lr_color=lr.color,
            lr_opacity=lr.opacity,
            lr_shape=lr.shape,
        )

    def lr_factor(self, step: int) -> float:
        """Learning-rate multiplier of step ``step`` (0-based): 1 for ``lr.schedule`` constant; for
        cosine, 0.5·(1 + cos(π·step/iterations)), falling from 1 to 0 over the phase."""
        if self.cfg.lr.schedule == "constant":
            return 1.0
        return 0.5 * (1.0 + math.cos(math.pi * min(step, self.cfg.iterations) / self.cfg.iterations))

    def _set_lrs(self) -> None:
        f = self.lr_factor(self.step_count)
        for g in self.optimizer.param_groups if self.optimizer is not None else []:
            g["lr"] = g.setdefault("base_lr", g["lr"]) * f

    def _build_rest_teacher(self) -> RestTeacher:
        """Render the (phase-1) avatar at rest from at most ``rest_teacher.max_views`` training views."""
        c, av = self.cfg, self.avatar
        frames = evenly_spaced_frames(self.frames, c.rest_teacher.max_views)
        cams = [RenderCamera.from_camera(fr.camera, self.device) for fr in frames]
        canon = av.canonical_state(with_sdf=av.attributes == "mlp")

        def render_fn(i: int, inputs: dict[str, torch.Tensor]) -> torch.Tensor:
            img, _ = av.render(cams[i], inputs, c.background, canonical=canon, near=c.near, far=c.far, return_statistics=False,
                               shade=False, backend=self.render_backend)  # fmt: skip
            return img.color

        return RestTeacher.build(
            render_fn, av.pose_mesh, av.faces, [(cm.K, cm.w2c, cm.width, cm.height) for cm in cams],
            [self.inputs(fr.timestep) for fr in frames], depth_tol=c.rest_teacher.depth_tol,
        )  # fmt: skip

    @torch.no_grad()
    def prior_visibility(self, which: torch.Tensor, jaw: float, samples: int = 256) -> torch.Tensor:
        """Ambient visibility (:func:`sage_core.geometry.occlusion.ambient_visibility`, ``samples`` rays)
        of the surfels ``which`` ((N,) bool) with the jaw of the canonical frame opened to ``jaw``
        radians, on the side of their triangle that faces the open air (the larger of the two).
        Returns (M,) in [0, 1]."""
        from ..geometry.occlusion import ambient_visibility

        av = self.avatar
        inputs = dict(self.inputs(self.data.canonical_timestep))
        inputs["jaw_pose"] = torch.tensor([[float(jaw), 0.0, 0.0]], dtype=inputs["jaw_pose"].dtype, device=av.device)
        p = av.posed(inputs, None)
        V = p.vertices.detach().double().cpu().numpy()
        Fc = av.faces.detach().long().cpu().numpy()
        f = av.surfels.binding[which].cpu().numpy()
        n = np.cross(V[Fc[f, 1]] - V[Fc[f, 0]], V[Fc[f, 2]] - V[Fc[f, 0]])
        x = p.means[which].detach().double().cpu().numpy()
        eps = 1e-4 * float(np.linalg.norm(V.max(0) - V.min(0)))
        vis = np.maximum(ambient_visibility(V, Fc, x, n, samples, eps), ambient_visibility(V, Fc, x, -n, samples, eps))
        return torch.as_tensor(vis, device=av.device)

    @torch.no_grad()
    def unseen_fill_colors(self, weights: torch.Tensor, taken: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Colours for the surfels no training view sees at rest (:mod:`sage_core.train.unseen_fill`).

        weights: (N,) :meth:`surfel_view_weights`; taken: (N,) bool surfels that already have a prior.
        A surfel with less than ``SEEN_MIN_WEIGHT`` pixels of weight, not taken, in a region that
        ``unseen_fill.hair`` lets fill (without it, every region but the hair), takes the harmonic
        continuation over its group's surfel graph (``k`` neighbours) of the albedos of the group's
        seen surfels (eyes, face, neck, mouth each alone; the hair with the rest of the scalp, its
        skin-coloured sources left out, and those of them seen only at grazing angles filled too). Sets :attr:`unseen_fill_result` (with the opacity floor and
        scale gain of ``unseen_fill.cover`` for the hair group, and the neck with ``unseen_fill.cover_neck``,
        given with ``unseen_fill.cover_away`` also to their seen surfels that no training view faces;
        the growth is limited near the seen surfels that some training view faces (:attr:`view_toward`
        at least 0) and by the canonical mesh's open boundary).
        Returns ((N,) bool surfels filled, (M, 3) their colours)."""
        from .unseen_fill import fill_unseen

        av = self.avatar
        s = av.surfels
        c = self.cfg.unseen_fill
        canon = av.canonical_state(with_sdf=av.attributes == "mlp")
        p = av.posed(self.inputs(self.data.canonical_timestep), None, canonical=canon, shade=False)
        facing = getattr(self, "view_facing", None)
        toward = getattr(self, "view_toward", None)
        if facing is not None and tuple(facing.shape) != tuple(weights.shape):
            facing = toward = None
        edge = boundary_edges(av.faces.detach().cpu().numpy())
        verts = av.canonical_vertices.detach().double().cpu().numpy()
        res = fill_unseen(
            canon.means, p.colors, weights.to(av.device), s.region_id, p.opacities if c.cover else None,
            canon.scales if c.cover else None, facing,
            groups=unseen_fill_groups(c.hair), hair_regions=(REGION_HAIR,), skin_regions=(REGION_FACE,),
            cover_regions=(REGION_HAIR, REGION_OTHER) + ((REGION_NECK,) if c.cover_neck else ()), taken=taken,
            seen_min=SEEN_MIN_WEIGHT, source_min=c.source_min, neighbours=int(k), grazing_cos=c.grazing_cos,
            boundary=(verts[edge[:, 0]], verts[edge[:, 1]]), facing_away=None if toward is None else toward < 0,
            cover_facing_away=c.cover_away,
        )  # fmt: skip
        self.unseen_fill_result = res
        return res.filled, res.colors[res.filled]

    def seen_surfels(self, min_weight: float = SEEN_MIN_WEIGHT) -> torch.Tensor:
        """(N,) bool surfels that the training views at rest see: :meth:`surfel_view_weights` at least
        ``min_weight`` (pixels)."""
        return self.surfel_view_weights() >= min_weight

    def surfel_view_weights(self) -> torch.Tensor:
        """(N,) float64 blending weight of every surfel summed over the foreground pixels (the mesh
        raster's mask eroded by one pixel) of the training views at rest (at most
        ``rest_teacher.max_views``). The weight of surfel i is the gradient of Σ_p mask_p·C_p with respect
        to its colour, one backward pass per view; over all surfels it sums to Σ_p mask_p·A_p. Also sets
        :attr:`view_facing`: the same sum with each view's weight times |cos| of the angle between the
        surfel's normal and the direction to that view's camera, and :attr:`view_toward`: the largest
        cosine over those views between the outward normal of the surfel's triangle (posed) and the
        direction to the view's camera (negative: no view faces the surfel)."""
        from ..geometry.rotations import quat_to_matrix

        av, c = self.avatar, self.cfg
        total = torch.zeros(len(av.surfels), dtype=torch.float64, device=av.device)
        facing = torch.zeros_like(total)
        toward = torch.full_like(total, -1.0)
        binding = av.surfels.binding.long()
        canon = av.canonical_state(with_sdf=av.attributes == "mlp")
        for fr in evenly_spaced_frames(self.frames, c.rest_teacher.max_views):
            cam = RenderCamera.from_camera(fr.camera, self.device)
            with torch.no_grad():
                p = av.posed(self.inputs(fr.timestep), None, canonical=canon, shade=False)
                fid = rasterize_mesh(p.vertices, av.faces, cam.K, cam.w2c, cam.width, cam.height).face_id[0]
                inner = erode_mask(fid >= 0)[0, 0]
            cols = torch.zeros_like(p.colors).requires_grad_(True)
            img = rasterize_surfels(p.means.detach(), p.quats.detach(), p.scales.detach(), p.opacities.detach(), cols, cam, 0.0,
                                    near=c.near, far=c.far, return_statistics=False, backend=self.render_backend)  # fmt: skip
            (grad,) = torch.autograd.grad((img.color[..., 0] * inner).sum(), cols)
            total += grad[:, 0].detach().to(total)
            with torch.no_grad():
                n = quat_to_matrix(p.quats.detach() / p.quats.detach().norm(dim=-1, keepdim=True))[..., 2]
                to_cam = cam.w2c[:3, :3].T.to(p.means) @ -cam.w2c[:3, 3].to(p.means) - p.means.detach()
                cos = (n * to_cam).sum(-1).abs() / to_cam.norm(dim=-1).clamp_min(1e-12)
                facing += grad[:, 0].detach().to(total) * cos.to(total)
                fn = surfel_frames(p.vertices, av.faces)[0][..., 2][binding]  # outward unit triangle normals
                lit = (fn * to_cam).sum(-1) / to_cam.norm(dim=-1).clamp_min(1e-12)
                toward = torch.maximum(toward, lit.to(total))
        self.view_facing = facing
        self.view_toward = toward
        return total

    @torch.no_grad()
    def seen_faces(self) -> torch.Tensor:
        """(F,) bool triangles that are the visible surface of at least one foreground pixel (the mesh
        raster's mask eroded by one pixel) of the training views at rest (at most
        ``rest_teacher.max_views`` of them)."""
        av = self.avatar
        seen = torch.zeros(int(av.faces.shape[0]), dtype=torch.bool, device=av.device)
        for fr in evenly_spaced_frames(self.frames, self.cfg.rest_teacher.max_views):
            cam = RenderCamera.from_camera(fr.camera, self.device)
            ras = rasterize_mesh(av.pose_mesh(self.inputs(fr.timestep)), av.faces, cam.K, cam.w2c, cam.width, cam.height)
            fid = ras.face_id[0]
            inner = erode_mask(fid >= 0)[0, 0] > 0.5
            seen[fid[inner]] = True
        return seen

    def trainable_parameters(self) -> list[torch.nn.Parameter]:
        """Every parameter the optimizer updates."""
        return [p for g in self.optimizer.param_groups for p in g["params"]] if self.optimizer is not None else []

    def inputs(self, timestep: int) -> dict[str, torch.Tensor]:
        """Cached FLAME kwargs of a dataset timestep."""
        if timestep not in self._inputs:
            self._inputs[timestep] = self.avatar.frame_inputs(timestep)
        return self._inputs[timestep]

    def _randint(self, n: int) -> int:
        return int(torch.randint(n, (1,), generator=self.generator)[0])

    # ------------------------------------------------------------------ rendering
    def render(self, camera: RenderCamera, flame_inputs: dict[str, torch.Tensor], shade: bool = True) -> tuple[Any, Any]:
        """Pose (with correction when enabled) and rasterize. Returns (SurfelRender, PosedSurfels).
        shade: False renders the albedo of an avatar with world shading (the self-supervised terms
        compare albedos, the light is fixed)."""
        c, av = self.cfg, self.avatar
        w2c = camera.w2c.to(av.canonical_vertices)
        centre = -(w2c[:3, :3].T @ w2c[:3, 3])
        p, _ = self.posing.posed(flame_inputs, centre, shade=shade)
        img = rasterize_surfels(p.means, p.quats, p.scales, p.opacities, p.colors, camera, c.background,
                                near=c.near, far=c.far, return_statistics=False, backend=self.render_backend)  # fmt: skip
        return img, p

    @torch.no_grad()
    def teacher(self, posed_vertices: torch.Tensor, camera: RenderCamera, pix: torch.Tensor, raster: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Canonical NeuS colours of the pixels ``pix`` (R,) of a deformed frame, detached.

        Returns colours (R, 3) and a validity mask (R,) (rays that hit the posed mesh)."""
        c, av = self.cfg, self.avatar
        assert self.teacher_app is not None and self.teacher_variance is not None
        rays = warp_pixels_to_canonical(posed_vertices, av.faces, (av.R_c, av.T_c, av.k_c), camera.K, camera.w2c,
                                        camera.width, camera.height, pix, raster=raster)  # fmt: skip
        out = render_neus(
            av.sdf, self.teacher_app, rays.origins, rays.dirs, self.teacher_variance, c.neus.samples, c.neus.importance,
            c.neus.up_steps, 1.0, c.background, length_unit=self.length_unit, perturb=True, generator=self.generator,
        )  # fmt: skip
        return out.color.detach(), rays.valid

    @torch.no_grad()
    def rest_lookup(self, posed_vertices: torch.Tensor, camera: RenderCamera, pix: torch.Tensor, raster: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest-teacher colours (R, 3) of the pixels ``pix`` (R,) of a deformed frame whose mesh raster is
        ``raster`` (every pixel must hit the mesh), and their validity (R,)."""
        assert self.rest_teacher is not None
        av = self.avatar
        fid = raster.face_id.reshape(-1)[pix]
        bary = raster.bary.reshape(-1, 3)[pix]
        _, dirs = pixel_rays(camera.K, camera.w2c, camera.width, camera.height, pix)
        rot = surfel_frames(posed_vertices, av.faces[fid])[0]  # the hit triangles' frames only
        look = self.rest_teacher.lookup(av.faces, fid, bary, dirs.to(posed_vertices), deformed_rotations=rot)
        return look.color, look.valid

    # ------------------------------------------------------------------ one step
    def step(self) -> dict[str, float]:
        """One optimisation step; returns the loss terms (:data:`PHASE2_TERMS`) as floats."""
        c, av = self.cfg, self.avatar
        fr = self.frames[self._randint(len(self.frames))]
        cam = RenderCamera.from_camera(fr.camera, self.device)
        sample = self.sampler.sample(1, generator=self.generator)
        rest = c.expressions.rest_fraction
        at_rest = rest > 0 and float(torch.rand((), generator=self.generator)) < rest
        inputs = self.inputs(fr.timestep) if at_rest else compose_inputs(self.inputs(fr.timestep), sample)
        render, posed = self.render(cam, inputs, shade=False)
        e_n = 1.0 - (render.normal_world * render.surf_normal_world).sum(-1)

        raster = None
        verts = posed.vertices.detach()
        if (c.loss.appearance > 0 and c.pixels.per_step > 0) or self.wrinkle_stats is not None:
            with torch.no_grad():
                raster = rasterize_mesh(verts, av.faces, cam.K, cam.w2c, cam.width, cam.height)
                if self.wrinkle_stats is not None:
                    shaped = av.flame(**inputs).v_shaped[0] if av.wrinkle_basis == "expression" else None
                    comp = face_compression(*wrinkle_meshes(av, verts, shaped), av.faces, c.wrinkles.full_compression)
                    self.wrinkle_stats.update(raster.face_id, render.distortion.detach(), comp)
        ctx = Phase2Step(self, self.step_count, cam, inputs, render, verts, e_n, raster)
        terms: dict[str, torch.Tensor] = {}
        total = L.add_terms(PHASE2_TERMS, ctx, c.loss, c.schedule, terms)

        if self.optimizer is not None and total is not None:
            self.optimizer.zero_grad(set_to_none=True)
            total.backward()
            self._set_lrs()
            self.optimizer.step()
        self.step_count += 1
        out = {k: float(v.detach()) for k, v in terms.items()}
        out["loss"] = float(total.detach()) if total is not None else 0.0
        if len(self.distortion_curve) < c.schedule.curve_steps and self.step_count == len(self.distortion_curve) + 1:
            d = out["distortion"] if "distortion" in terms else float(L.distortion_loss(render.distortion.detach()))
            self.distortion_curve.append(d)
        return out

    @torch.no_grad()
    def finish_wrinkles(self) -> dict[str, float]:
        """Set the avatar's wrinkle shading from the accumulated distortion statistics (hair and
        mouth-interior triangles excluded) and return summary numbers: the share of surfels that can
        darken, their mean amplitude, and the Pearson correlation between the triangles' mean
        distortion and mean compression over the triangles seen."""
        assert self.wrinkle_stats is not None
        c, av, st = self.cfg, self.avatar, self.wrinkle_stats
        excluded = self.hair_faces | self.prior_faces
        w = c.wrinkles
        lo, hi = (float(q) for q in w.quantiles)
        if w.region == "distortion":
            amp = wrinkle_amplitude(st.mean(), st.count, excluded, w.strength, (lo, hi))
        else:
            amp = (~excluded).to(st.sum) * float(w.strength)
        b = av.surfels.binding
        a = amp.to(av.canonical_vertices)[b]
        av.surfels.set_wrinkle(torch.stack([a, torch.full_like(a, w.full_compression)], -1))
        seen = (st.count > 0) & ~excluded.to(st.count.device)
        d, k = st.mean()[seen], st.mean_compression()[seen]
        corr = float("nan")
        if d.numel() > 2 and float(d.std()) > 0 and float(k.std()) > 0:
            corr = float(((d - d.mean()) * (k - k.mean())).mean() / (d.std(unbiased=False) * k.std(unbiased=False)))
        return {"surfels_darkening": float((a > 0).double().mean()), "mean_amplitude": float(a[a > 0].mean()) if bool((a > 0).any()) else 0.0,
                "distortion_compression_corr": corr, "faces_seen": int(seen.sum())}  # fmt: skip

    def _image(self, fr: IngestedFrame) -> torch.Tensor:
        key = (fr.timestep, fr.camera_index)
        if key not in self._images:
            self._images[key] = torch.as_tensor(self.data.load_image(fr), device=self.device)
        return self._images[key]

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def render_frame(self, fr: IngestedFrame) -> torch.Tensor:
        """(H, W, 3) render of an ingested frame at its FLAME parameters, clamped to [0, 1]."""
        cam = RenderCamera.from_camera(fr.camera, self.device)
        img, _ = self.render(cam, self.inputs(fr.timestep))
        return img.color.clamp(0, 1)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly: avatar, teacher, optimizer, RNGs, step, curve."""
        return {
            "format": STATE_FORMAT,
            "step": self.step_count,
            "avatar": {k: v.detach().clone() for k, v in self.avatar.state_dict().items() if not k.startswith("flame.")},
            "teacher_app": _module_state(self.teacher_app),
            "teacher_variance": _module_state(self.teacher_variance),
            "wrinkle_stats": None if self.wrinkle_stats is None else self.wrinkle_stats.state_dict(),
            "optimizer": self.optimizer.state_dict() if self.optimizer is not None else None,
            "generator": self.generator.get_state(),
            "rng": rng_state(),
            "distortion_curve": list(self.distortion_curve),
            "curvature_cache": self.posing.cache_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (same surfel count)."""
        self.avatar.load_state_dict(state["avatar"], strict=False)
        if self.teacher_app is not None and state.get("teacher_app"):
            self.teacher_app.load_state_dict(state["teacher_app"])
        if self.teacher_variance is not None and state.get("teacher_variance"):
            self.teacher_variance.load_state_dict(state["teacher_variance"])
        if self.wrinkle_stats is not None and state.get("wrinkle_stats") is not None:
            self.wrinkle_stats.load_state_dict(state["wrinkle_stats"])
        if self.optimizer is not None and state.get("optimizer") is not None:
            self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        set_rng_state(state["rng"])
        self.step_count = int(state["step"])
        self.distortion_curve = list(state.get("distortion_curve", []))
        self.posing.load_cache_state(state.get("curvature_cache"))


@dataclass
class Phase2Step:
    """What the loss terms of one phase-2 step read (:data:`PHASE2_TERMS`): the trainer, the step,
    the deformed view (camera, FLAME kwargs), its render, the posed mesh vertices (V, 3, detached),
    the per-pixel normal-consistency error e_n (H, W) and the mesh raster (None when neither the
    appearance term nor the wrinkle statistics need it)."""

    trainer: Phase2Trainer
    step: int
    cam: RenderCamera
    inputs: dict[str, torch.Tensor]
    render: Any
    verts: torch.Tensor
    e_n: torch.Tensor
    raster: Any
    polish: bool = False


def _appearance(s: Phase2Step) -> torch.Tensor | None:
    """L_a on ``pixels.per_step`` pixels drawn by their error among the non-hair pixels of the posed
    mesh; None when no drawn pixel has a teacher colour."""
    tr, c, render = s.trainer, s.trainer.cfg, s.render
    assert s.raster is not None
    with torch.no_grad():
        fid = s.raster.face_id.reshape(-1)
        ok = fid >= 0
        ok &= ~tr.hair_faces[fid.clamp_min(0)]
        cand = ok.nonzero().squeeze(-1)
        score = torch.stack([s.e_n.detach().reshape(-1)[cand], render.distortion.detach().reshape(-1)[cand]], -1)
    pix = sample_pixels(score, cand, c.pixels.per_step, c.pixels.error_floor, tr.generator)
    if pix.numel() == 0:
        return None
    if tr.rest_teacher is not None:
        target, valid = tr.rest_lookup(s.verts, s.cam, pix, s.raster)
    else:
        target, valid = tr.teacher(s.verts, s.cam, pix, s.raster)
    valid = valid & ~tr.prior_faces[fid[pix]]
    if not bool(valid.any()):
        return None
    pred = render.color.reshape(-1, 3)[pix]
    return ((pred - target) ** 2).sum(-1)[valid].mean()


def _photometric(s: Phase2Step) -> torch.Tensor:
    """L_rgb of a random training frame rendered at its own FLAME parameters."""
    tr = s.trainer
    fr2 = tr.frames[tr._randint(len(tr.frames))]
    cam2 = RenderCamera.from_camera(fr2.camera, tr.device)
    img2, _ = tr.render(cam2, tr.inputs(fr2.timestep))
    return L.rgb_loss(img2.color, tr._image(fr2))


def _photometric_step(s: Phase2Step) -> bool:
    every = s.trainer.cfg.schedule.photometric_every
    return every > 0 and s.step % every == 0


PHASE2_TERMS: tuple[L.LossTerm[Phase2Step], ...] = (
    L.LossTerm("normal_consistency", "normal_consistency", lambda s: s.e_n.mean()),
    L.LossTerm("distortion", "distortion", lambda s: L.distortion_loss(s.render.distortion)),
    L.LossTerm("appearance", "appearance", _appearance, when=lambda s: s.trainer.cfg.pixels.per_step > 0),
    L.LossTerm("rgb", "photometric", _photometric, when=_photometric_step),
)
"""Phase 2's objective in summation order (:func:`sage_core.train.losses.add_terms`): λ_n L_n + λ_d L_d
of the deformed render, λ_a L_a against the teacher, and the optional photometric term."""


def _module_state(module: torch.nn.Module | None) -> dict[str, torch.Tensor] | None:
    return None if module is None else {k: v.detach().clone() for k, v in module.state_dict().items()}


def evenly_spaced_frames(frames: list[IngestedFrame], n: int) -> list[IngestedFrame]:
    """At most n evenly spaced frames (all when n <= 0)."""
    if n <= 0 or n >= len(frames):
        return frames
    return [frames[i] for i in sample_indices(len(frames), n)]
