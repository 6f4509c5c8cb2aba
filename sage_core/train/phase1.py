"""Phase 1: joint optimisation of the triangle-bound surfels, the canonical SDF and the attribute
networks, supervised by the training images (SAGE §1–2).

Each step picks a random training frame (camera + timestep), poses the surfels with its FLAME
parameters, rasterizes them and combines:

* L_rgb = 0.8·L1 + 0.2·(1 − SSIM) of the surfel render;
* 2DGS normal consistency and depth distortion (from their start steps);
* L_pt and L_align at the canonical surfel centres (mouth-interior surfels excluded: the SDF models
  the outer head surface);
* on a random subset of foreground pixels, mapped to canonical rays (rigidly when the frame differs
  from canonical only by global rotation/translation, otherwise through the hit triangle of the
  posed mesh), NeuS volume rendering of the canonical SDF and appearance network: L1 against the
  image, L_D and L_N against the surfels' expected depth and rendered normal (the surfel side
  detached: the surfels supervise the SDF), eikonal on the NeuS samples and the surfel centres;
* MonoSDF normal smoothness at a subset of surfel centres.

Shading (``shading``; :mod:`sage_core.avatar.shading`): with "sh2" the avatar's surfel colours are
albedo × the irradiance of a world-fixed order-2 SH light at the surfels' outward world normals, the
light (``lr.light``) being optimised with the rest under the weak prior
``loss.light_prior·mean_c (mean irradiance − 1)²`` that fixes the albedo/light brightness scale and
the smooth-albedo prior ``loss.light_albedo`` (:mod:`sage_core.train.light_prior`; on real frames, its
gradient reaching the light alone) that picks the light the images cannot tell apart. The
NeuS colour is shaded the same way, so that the appearance network learns one albedo from both
renders: each ray's composited colour is multiplied on its foreground by E(n_w), n_w the ray's
expected canonical SDF normal (normalised, without gradient) mapped to the world by the transpose of
the warp's world → canonical rotation (exact for rigid frames, the hit triangle's rotation otherwise).
Mirrored one-shot pseudo views see the mirrored light (normals reflected by S before the irradiance).

Single-camera regimes (SV-HR, one-shot; paper §5) add, through the config (regime defaults in
``sage_core.config.REGIME_OVERRIDES``):

* a per-frame exposure gain on the foreground of the renders (:mod:`.exposure`) with a weak prior;
* soft left–right symmetry of the canonical SDF and appearance colour (:mod:`.symmetry`);
* optional refinement of per-timestep corrections of the global rotation, neck pose and translation
  (:class:`PoseRefinement`), from ``schedule.pose_refine_from`` on;
* one-shot: synthesized pseudo views (``sage_core.train.pseudo_views``), drawn with probability
  ``pseudo.prob``; a pseudo view poses the avatar with a training frame's parameters, optionally
  mirrors the posed mesh, and adds a per-pixel weighted photometric loss (no SDF ray terms).

Canonical rays come from a :class:`~sage_core.train.canonical_warp.CanonicalWarp` (``canonical_warp``).

After the last step, one multiview training timestep (mv-sf) is registered to the surface the SDF
reconstructed (``registration``; :mod:`sage_core.train.registration`): the avatar's canonical
content moves by the opposite of the tracked mesh's fitted offset and the timestep's translation is
baked into the avatar's parameters, so the training views render as before
(``registration.rounds`` > 1: also at steps while the SDF trains; the rounds are trainer state).

The objective is the table :data:`PHASE1_TERMS` (each term's weight in the config's ``loss`` section,
its first step in ``schedule``), run by :func:`sage_core.train.losses.add_terms`.

Every random draw uses the trainer's own CPU generator, so a run resumed from ``state_dict`` repeats
the uninterrupted loss curve.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from ..avatar.init import REGION_MOUTH
from ..avatar.model import Avatar
from ..avatar.posing import PosedMesh
from ..avatar.shading import shade_foreground
from ..runtime import resolve_render_backend
from ..config import Phase1Config
from ..data.dataset import IngestedData, IngestedFrame
from ..errors import InputError
from ..flame.frames import surfel_frames
from ..flame.regions import Regions
from ..image_metrics import SSIMTarget, psnr, ssim, ssim_map, ssim_target
from ..render import RenderCamera
from ..render.volume import AppearanceFn, render_neus
from ..workspace import rng_state, set_rng_state
from . import losses as L
from . import relocate
from ._groups import adam, surfel_param_groups
from .densify import DensityControl, DensifySchedule, scene_extent
from .canonical_warp import CanonicalWarp, make_warp
from .exposure import ExposureGain
from .light_prior import SmoothAlbedoLight
from .registration import RegistrationRounds
from .symmetry import MirrorPlane, color_symmetry_loss, plane_from_pairs, sdf_symmetry_loss
from .warp import pixel_rays

Progress = Callable[..., None]
STATE_FORMAT = 1
SSIM_TARGET_BUDGET = 256 * 2**20
"""Bytes of SSIM target moments a trainer keeps (the first frames visited; about 470 tiny, 120 small or
25 full-size frames): a kept target saves two of the five SSIM window blurs of each later step."""


def build_avatar(data: IngestedData, init_dir: str | Path, cfg: Phase1Config, device: str | torch.device, generator: torch.Generator) -> Avatar:
    """The phase-1 avatar from the init-mesh outputs and the config."""
    return Avatar.build(
        init_dir, data, cfg.surfels.count, cfg.attributes,
        app_args=appearance_args(cfg),
        shape_args={"hidden": cfg.shape.hidden, "n_layers": cfg.shape.layers, **({"detail_grid": True} if cfg.shape.detail_grid else {})},
        sh_degree=cfg.free.sh_degree, init_opacity=cfg.free.init_opacity,
        init_args={"face_weight": cfg.surfels.face_weight, "mouth_weight": cfg.surfels.mouth_weight, "hair_weight": cfg.surfels.hair_weight,
                   "neck_weight": cfg.surfels.neck_weight, "camera_weight": cfg.surfels.camera_weight,
                   "scale_factor": cfg.surfels.scale_factor, "layout": cfg.surfels.layout},
        neus_variance=cfg.neus.variance, shading=cfg.shading, device=device, generator=generator,
    )  # fmt: skip


def appearance_args(cfg: Phase1Config) -> dict[str, Any]:
    """:class:`AppearanceNetwork` kwargs of a phase-1 config (plain data, saved with the avatar)."""
    a = cfg.appearance
    args: dict[str, Any] = {"hidden": a.hidden, "n_layers": a.layers, "sh_degree": a.sh_degree,
                            "opacity_bias": math.log(a.init_opacity / (1.0 - a.init_opacity))}
    if a.grid:
        args["grid"] = {"n_levels": a.grid_levels, "n_features": 2, "log2_table": a.grid_log2_table, "base_res": 16, "max_res": a.grid_max_res}
    return args


class CanonicalRays:
    """Tuple-returning adapter over a :class:`CanonicalWarp` (default: the rigid map for rigid frames,
    else the hit-triangle warp)."""

    def __init__(self, avatar: Avatar, warp: CanonicalWarp | None = None) -> None:
        self.avatar = avatar
        self.warp = warp if warp is not None else make_warp("auto")

    def map(
        self,
        flame_inputs: dict[str, torch.Tensor],
        camera: RenderCamera,
        pix: torch.Tensor,
        rigid: tuple[torch.Tensor, torch.Tensor] | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """pix: (R,) flat pixel ids. Returns canonical origins (R, 3), unit directions (R, 3), the
        per-ray map of world distances to canonical distances (R,), world→canonical rotations
        (R, 3, 3) for normals, and a validity mask (R,) (False where a non-rigid ray misses the mesh)."""
        r = self.warp.map(self.avatar, flame_inputs, camera, pix, rigid)
        return r.origins, r.dirs, r.scale, r.rotation, r.valid


class PoseRefinement(nn.Module):
    """Per-timestep corrections of the FLAME global rotation, neck pose (axis-angle, added to the
    tracked vectors) and translation (metres, added), zero-initialised.

    timesteps: the timesteps that get a correction (the training timesteps).
    """

    def __init__(self, timesteps: list[int]) -> None:
        super().__init__()
        self.timesteps = [int(t) for t in timesteps]
        self._row = {t: i for i, t in enumerate(self.timesteps)}
        n = len(self.timesteps)
        self.rotation = nn.Parameter(torch.zeros(n, 3))
        self.neck_pose = nn.Parameter(torch.zeros(n, 3))
        self.translation = nn.Parameter(torch.zeros(n, 3))

    def has(self, timestep: int) -> bool:
        return int(timestep) in self._row

    def apply(self, inputs: dict[str, torch.Tensor], timestep: int) -> dict[str, torch.Tensor]:
        """FLAME kwargs (batch 1) with the timestep's corrections added (differentiable)."""
        i = self._row[int(timestep)]
        out = dict(inputs)
        for k in ("rotation", "neck_pose", "translation"):
            out[k] = inputs[k] + getattr(self, k)[i].to(inputs[k])[None]
        return out

    def prior(self, length_unit: float) -> torch.Tensor:
        """mean of squared corrections (rad², translation in units of ``length_unit``), 0-d."""
        return (self.rotation**2).mean() + (self.neck_pose**2).mean() + ((self.translation / length_unit) ** 2).mean()

    def bake(self, params: Any) -> Any:
        """A copy of ``params`` (FlameParams) with the corrections added to their rows."""
        import dataclasses

        rot, neck, tr = params.rotation.copy(), params.neck_pose.copy(), params.translation.copy()
        with torch.no_grad():
            for t, i in self._row.items():
                r = params.row_of(t)
                rot[r] += self.rotation[i].cpu().numpy().astype(rot.dtype)
                neck[r] += self.neck_pose[i].cpu().numpy().astype(neck.dtype)
                tr[r] += self.translation[i].cpu().numpy().astype(tr.dtype)
        return dataclasses.replace(params, rotation=rot, neck_pose=neck, translation=tr)

    def summary(self) -> dict[str, float]:
        """Mean and max magnitudes of the corrections (degrees, millimetres)."""
        with torch.no_grad():
            r = torch.rad2deg(self.rotation.norm(dim=-1))
            n = torch.rad2deg(self.neck_pose.norm(dim=-1))
            t = self.translation.norm(dim=-1) * 1000.0
        return {
            "pose_refine_rotation_mean_deg": float(r.mean()), "pose_refine_rotation_max_deg": float(r.max()),
            "pose_refine_neck_mean_deg": float(n.mean()), "pose_refine_neck_max_deg": float(n.max()),
            "pose_refine_translation_mean_mm": float(t.mean()), "pose_refine_translation_max_mm": float(t.max()),
        }  # fmt: skip


def mirror_transform(mirror_index: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
    """The left-right mirror of a posed mesh: v'_i = S·v_m(i), S = diag(−1, 1, 1). (V, 3) -> (V, 3)."""
    from .pseudo_views import mirror_vertices

    return lambda verts: mirror_vertices(verts, mirror_index)


def near_mask(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Pixels within Chebyshev distance ``radius`` of a True pixel of ``mask`` (H, W) bool -> (H, W) bool:
    a square max filter of side 2·radius + 1, run as its two one-dimensional passes."""
    k = 2 * radius + 1
    m = mask.to(torch.float32)[None, None]
    m = torch.nn.functional.max_pool2d(m, (k, 1), stride=1, padding=(radius, 0))
    m = torch.nn.functional.max_pool2d(m, (1, k), stride=1, padding=(0, radius))
    return m[0, 0] > 0


def mask_edge_keep(mask: torch.Tensor, band: int) -> torch.Tensor:
    """(H, W) float 0 on the pixels within Chebyshev distance ``band`` of the other side of the
    foreground mask's edge (mask (H, W) > 0.5 against the rest: a band 2·band pixels wide straddling
    the edge), 1 elsewhere; all ones for band 0. The weights of the mask terms (``mask_band``)."""
    if band <= 0:
        return torch.ones_like(mask, dtype=torch.float32)
    fg = mask > 0.5
    return (~(near_mask(fg, band) & near_mask(~fg, band))).to(torch.float32)


def weighted_rgb_loss(pred: torch.Tensor, gt: torch.Tensor, weight: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 − w)·mean(ω·|pred − gt|) + w·mean(ω·(1 − SSIM map)); pred, gt: (H, W, 3), weight ω: (H, W)."""
    om = weight[..., None]
    l1 = (om * (pred - gt).abs()).mean()
    if ssim_weight == 0:
        return l1
    sm = ssim_map(pred.permute(2, 0, 1), gt.permute(2, 0, 1)).permute(1, 2, 0)
    return (1.0 - ssim_weight) * l1 + ssim_weight * (om * (1.0 - sm)).mean()


class Phase1Trainer:
    """Phase-1 optimisation (see the module doc).

    avatar: an :class:`Avatar` (mlp or free attributes); data: the ingested capture; cfg: the
    stage config; generator: CPU generator for every random draw (frames, rays, NeuS jitter);
    pseudo_views: one-shot pseudo views (objects with the attributes of
    ``sage_core.train.pseudo_views.PseudoView``; ``frame_index`` indexes ``data.train``);
    mirror_index: (V,) vertex mirror index for pseudo views with ``mirror`` set.
    """

    def __init__(
        self,
        avatar: Avatar,
        data: IngestedData,
        cfg: Phase1Config,
        device: str | torch.device = "cpu",
        generator: torch.Generator | None = None,
        pseudo_views: list[Any] | None = None,
        mirror_index: torch.Tensor | None = None,
    ) -> None:
        self.avatar = avatar
        self.data = data
        self.cfg = cfg
        self.device = torch.device(device)
        self.render_backend = resolve_render_backend(cfg.render_backend, str(self.device))
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.step_count = 0
        # first step of the polish (photometric loss alone): the last polish_fraction of the iterations
        self.polish_from = cfg.iterations - round(cfg.schedule.polish_fraction * cfg.iterations)
        self.frames: list[IngestedFrame] = list(data.train)
        if not self.frames:
            raise ValueError("no training frames")
        self._cache: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._pixels: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self._ssim_targets: dict[int, SSIMTarget] = {}
        self._ssim_target_bytes = 0
        self._inputs: dict[int, dict[str, torch.Tensor]] = {}
        self._rigid: dict[int, tuple[torch.Tensor, torch.Tensor] | None] = {}
        self._meshes: dict[tuple[int, bool], PosedMesh] = {}
        self.warp = make_warp(cfg.canonical_warp)
        self.length_unit = float(avatar.sdf.half_extent)
        self.exposure: ExposureGain | None = None
        if cfg.exposure != "off":
            self.exposure = ExposureGain(len(self.frames), per_channel=cfg.exposure == "rgb").to(self.device)
        self.pose: PoseRefinement | None = None
        if cfg.pose_refine:
            self.pose = PoseRefinement(sorted({f.timestep for f in self.frames})).to(self.device)
        self.light_albedo: SmoothAlbedoLight | None = None
        if avatar.light is not None and cfg.loss.light_albedo > 0 and cfg.lr.light > 0:
            self.light_albedo = SmoothAlbedoLight(cfg.light_albedo.neighbours, cfg.light_albedo.chroma)
        self.sym_plane: MirrorPlane | None = None
        if cfg.loss.sym_sdf > 0 or cfg.loss.sym_color > 0:
            self.sym_plane = symmetry_plane(avatar)
        self.pseudo_views: list[Any] = []
        self._pseudo: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, RenderCamera]] = []
        self._mirror: Callable[[torch.Tensor], torch.Tensor] | None = None
        self.set_pseudo_views(pseudo_views or [], mirror_index)
        if avatar.attributes == "mlp" and cfg.lr.opacity_offset > 0:
            avatar.surfels.enable_opacity_offset()
        self.optimizer = adam(self._param_groups())
        self._not_mouth = avatar.surfels.region_id != REGION_MOUTH
        self.density: DensityControl | None = None
        self.position_lr_scale = 1.0
        if cfg.densify.enabled:
            centres = torch.stack([torch.as_tensor(f.camera.center, dtype=torch.float64) for f in self.frames])
            self.density = DensityControl(avatar, DensifySchedule.from_config(cfg.densify), scene_extent(centres), self.generator)
            if cfg.densify.position_lr_extent:
                self.position_lr_scale = self.density.extent
        # per-surfel visibility of the step's view: the density statistics and GA's local terms use it
        self._statistics = self.density is not None or cfg.loss.local_position > 0 or cfg.loss.local_scale > 0
        self.registration: RegistrationRounds | None = None
        """The training timestep's registration, when the run makes one (its state is the trainer's)."""

    # ------------------------------------------------------------------ setup
    def _param_groups(self) -> list[dict[str, Any]]:
        av, lr = self.avatar, self.cfg.lr
        groups = [
            {"name": "sdf_mlp", "params": av.sdf.mlp_parameters(), "lr": lr.sdf},
            {"name": "grid", "params": av.sdf.grid_parameters(), "lr": lr.grid},
            {"name": "variance", "params": list(av.variance.parameters()), "lr": lr.variance},
        ] + surfel_param_groups(
            av,
            lr_position=lr.position,
            lr_networks=lr.networks,
            lr_rotation=lr.rotation,
            lr_scale=lr.scale,
            lr_color=lr.color,
            lr_opacity=lr.opacity,
            lr_app_grid=lr.app_grid,
            lr_opacity_offset=lr.opacity_offset,
        )
        if self.exposure is not None:
            groups.append({"name": "exposure", "params": [self.exposure.log_gain], "lr": lr.exposure})
        if av.light is not None and lr.light > 0:
            groups.append({"name": "light", "params": list(av.light.parameters()), "lr": lr.light})
        if self.pose is not None:
            groups.append({"name": "pose_rotation", "params": [self.pose.rotation, self.pose.neck_pose], "lr": lr.pose_rotation})
            groups.append({"name": "pose_translation", "params": [self.pose.translation], "lr": lr.pose_translation})
        return groups

    def set_pseudo_views(self, views: list[Any], mirror_index: torch.Tensor | None = None) -> None:
        """Use these pseudo views (see the class doc); call before training starts."""
        if any(v.mirror for v in views) and mirror_index is None:
            raise ValueError("a mirrored pseudo view needs the vertex mirror index")
        for v in views:
            if not 0 <= int(v.frame_index) < len(self.frames):
                raise ValueError(f"pseudo view {v.name!r}: frame_index {v.frame_index} is not a training frame")
        self.pseudo_views = list(views)
        self._pseudo = [
            (torch.as_tensor(v.image, dtype=torch.float32, device=self.device),
             torch.as_tensor(v.mask, dtype=torch.float32, device=self.device),
             torch.as_tensor(v.weight, dtype=torch.float32, device=self.device),
             RenderCamera.from_camera(v.camera, self.device))
            for v in views
        ]  # fmt: skip
        self._mirror = mirror_transform(mirror_index.to(self.device)) if mirror_index is not None else None

    def _set_lrs(self) -> None:
        c = self.cfg
        t = min(1.0, self.step_count / max(1, c.iterations))
        lr = math.exp((1 - t) * math.log(c.lr.position) + t * math.log(c.lr.position_final)) * self.position_lr_scale
        for g in self.optimizer.param_groups:
            if g["name"] == "mu_loc":
                g["lr"] = lr

    def _ray_pixels(self, i: int, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat indices of the pixels NeuS rays are drawn from in training frame ``i``: its foreground
        (mask (H, W) > 0.5) and the background pixels within ``neus_background_band`` pixels
        (Chebyshev) of it; cached per frame."""
        if i not in self._pixels:
            fg = mask > 0.5
            band = near_mask(fg, int(self.cfg.neus.background_band)) & ~fg
            fg_ids, band_ids = (torch.nonzero(m.reshape(-1)).reshape(-1) for m in (fg, band))
            self._pixels[i] = (fg_ids, band_ids)
        return self._pixels[i]

    def _ssim_target(self, i: int, img: torch.Tensor) -> SSIMTarget:
        """The SSIM target moments of training frame ``i``'s image (H, W, 3): kept per frame (two images'
        worth) for the first frames visited, up to ``SSIM_TARGET_BUDGET`` bytes, made anew for the others."""
        if i in self._ssim_targets:
            return self._ssim_targets[i]
        target = ssim_target(img.permute(2, 0, 1)[None])
        size = 2 * img.numel() * img.element_size()
        if self._ssim_target_bytes + size <= SSIM_TARGET_BUDGET:
            self._ssim_targets[i] = target
            self._ssim_target_bytes += size
        return target

    def _frame(self, i: int) -> tuple[torch.Tensor, torch.Tensor, RenderCamera]:
        if i not in self._cache:
            fr = self.frames[i]
            img = torch.as_tensor(self.data.load_image(fr), device=self.device)
            if fr.mask is not None:
                mask = torch.as_tensor(self.data.load_mask(fr), device=self.device)
            else:
                mask = torch.ones(img.shape[:2], device=self.device)
            cam = RenderCamera.from_camera(fr.camera, self.device)
            self._cache[i] = (img, mask, cam)  # type: ignore[assignment]
        img, mask, cam = self._cache[i]  # type: ignore[misc]
        return img, mask, cam  # type: ignore[return-value]

    def inputs(self, timestep: int) -> dict[str, torch.Tensor]:
        """Cached FLAME kwargs of a timestep (as tracked, without pose corrections)."""
        if timestep not in self._inputs:
            self._inputs[timestep] = self.avatar.frame_inputs(timestep)
            self._rigid[timestep] = self.avatar.rigid_transform(self._inputs[timestep])
        return self._inputs[timestep]

    def register(self, step: int) -> dict[str, Any]:
        """One round of the training timestep's registration (:attr:`registration`), after
        ``step``; drops the cached poses. Returns the round's metrics."""
        assert self.registration is not None
        out = self.registration.fit(self.avatar, step)
        self.forget_poses()
        return out

    def forget_poses(self) -> None:
        """Drop the cached FLAME kwargs, rigid transforms and posed meshes (after the avatar's
        parameters changed: the training timestep's registration)."""
        self._inputs.clear()
        self._rigid.clear()
        self._meshes.clear()

    def rigid(self, timestep: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(R0, t) of a rigidly moved timestep, else None (cached; tracked parameters)."""
        self.inputs(timestep)
        return self._rigid[timestep]

    def _refining(self) -> bool:
        return self.pose is not None and self.step_count >= self.cfg.schedule.pose_refine_from

    def frame_inputs(self, timestep: int) -> tuple[dict[str, torch.Tensor], tuple[torch.Tensor, torch.Tensor] | None]:
        """FLAME kwargs of a timestep with the pose corrections once refinement has started
        (differentiable in the corrections), and its rigid transform (recomputed when corrected)."""
        base = self.inputs(timestep)
        if self.pose is None or not self._refining() or not self.pose.has(timestep):
            return base, self._rigid[timestep]
        inp = self.pose.apply(base, timestep)
        return inp, self.avatar.rigid_transform({k: v.detach() for k, v in inp.items()})

    def posed_mesh(
        self, timestep: int, inputs: dict[str, torch.Tensor], transform: Callable[[torch.Tensor], torch.Tensor] | None
    ) -> PosedMesh | None:
        """The frame-only part of posing (:meth:`Avatar.posed_mesh` of ``inputs`` with the mirror
        ``transform`` or None) of a timestep, kept per timestep and mirroring (about 80 bytes a
        triangle, less than a cached image) while the inputs are constants; None while they carry a
        pose correction's gradient (the avatar then poses the mesh itself)."""
        if any(v.requires_grad for v in inputs.values()):
            return None
        key = (int(timestep), transform is not None)
        if key not in self._meshes:
            with torch.no_grad():
                self._meshes[key] = self.avatar.posed_mesh(inputs, transform)
        return self._meshes[key]

    def _eval_inputs(self, timestep: int) -> dict[str, torch.Tensor]:
        base = self.inputs(timestep)
        if self.pose is None or not self.pose.has(timestep):
            return base
        with torch.no_grad():
            return {k: v.detach() for k, v in self.pose.apply(base, timestep).items()}

    def _randint(self, n: int, size: int) -> torch.Tensor:
        return torch.randint(n, (size,), generator=self.generator)

    # ------------------------------------------------------------------ one step
    def step(self) -> dict[str, float]:
        """One optimisation step; returns the loss terms (:data:`PHASE1_TERMS`) as floats."""
        c, av = self.cfg, self.avatar
        pv_index: int | None = None
        if self._pseudo and c.pseudo.prob > 0:
            if float(torch.rand((), generator=self.generator)) < c.pseudo.prob:
                pv_index = int(self._randint(len(self._pseudo), 1)[0])
        transform = None
        light_transform: torch.Tensor | None = None
        weight: torch.Tensor | None = None
        view_weight = 1.0
        if pv_index is None:
            i: int | None = int(self._randint(len(self.frames), 1)[0])
            fr = self.frames[i]
            img, mask, cam = self._frame(i)
            timestep = fr.timestep
        else:
            i = None
            pv = self.pseudo_views[pv_index]
            img, mask, weight, cam = self._pseudo[pv_index]
            timestep = self.frames[int(pv.frame_index)].timestep
            view_weight = float(pv.view_weight)
            if pv.mirror:
                transform = self._mirror
                light_transform = torch.diag(torch.tensor([-1.0, 1.0, 1.0], device=self.device))
        inputs, rigid = self.frame_inputs(timestep)
        self._set_lrs()
        step = self.step_count
        polish = step >= self.polish_from
        use_sdf = step >= c.schedule.sdf_from and not polish

        canon = av.canonical_state(with_sdf=True, create_graph=use_sdf)
        mesh = self.posed_mesh(timestep, inputs, transform)
        render, posed = av.render(cam, inputs, c.background, canonical=canon, near=c.near, far=c.far, return_statistics=self._statistics,
                                  vertex_transform=transform, light_transform=light_transform, backend=self.render_backend,
                                  mesh=mesh)  # fmt: skip
        if self.density is not None:
            posed.means.retain_grad()
        color = render.color
        if self.exposure is not None and i is not None:
            color = self.exposure.apply(color, render.alpha, i, c.background)
        ctx = Phase1Step(self, step, polish, i, img, mask, cam, weight, view_weight, timestep, inputs, rigid, transform, mesh,
                         canon, render, posed, color)  # fmt: skip
        terms: dict[str, torch.Tensor] = {}
        total = L.add_terms(PHASE1_TERMS, ctx, c.loss, c.schedule, terms)

        self.optimizer.zero_grad(set_to_none=True)
        if total is not None:
            total.backward()
        else:  # every term off at this step: nothing to optimise
            total = color.new_zeros(())
        if self.density is not None:
            assert render.visible is not None
            self.density.accumulate(posed.means, cam, render.visible)
        self.optimizer.step()
        self.step_count += 1
        if self.density is not None:
            terms.update(self._density_step())
        rc = c.relocate
        if rc.enabled and not polish and relocate.due(self.step_count, rc.every, int(rc.until * c.iterations)):
            r = relocate.relocate(self)
            terms["relocated"] = torch.tensor(float(r.moved))
            self._not_mouth = av.surfels.region_id != REGION_MOUTH
            if r.moved and self.light_albedo is not None:
                self.light_albedo.reset()  # its neighbour pairs were built from the old centres
        rebind = c.schedule.rebind_every
        if rebind > 0 and self.step_count % rebind == 0 and self.step_count < c.iterations:
            n = av.surfels.rebind(av.canonical_vertices, av.faces, frames=(av.R_c, av.T_c, av.k_c), optimizer=self.optimizer)
            terms["rebound"] = torch.tensor(float(n))
            self._not_mouth = av.surfels.region_id != REGION_MOUTH
        out = {k: float(v.detach()) for k, v in terms.items()}
        out["loss"] = float(total.detach())
        with torch.no_grad():
            out["psnr"] = float(psnr(color.detach().permute(2, 0, 1), img.permute(2, 0, 1)))
        if pv_index is not None:
            out["pseudo_view"] = float(pv_index)
        return out

    def _density_step(self) -> dict[str, torch.Tensor]:
        """Densify / prune and reset opacities when the schedule says so (after the step count
        advanced); returns the counts as loss-dict entries."""
        assert self.density is not None
        out: dict[str, torch.Tensor] = {}
        sched = self.density.schedule
        if sched.densify_now(self.step_count):
            counts = self.density.densify_and_prune(self.optimizer, self.step_count)
            out = {f"densify_{k}": torch.tensor(float(v)) for k, v in counts.items()}
            self._not_mouth = self.avatar.surfels.region_id != REGION_MOUTH
        if sched.reset_now(self.step_count):
            self.density.reset_opacity(self.optimizer)
        return out

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def render_frame(self, fr: IngestedFrame) -> tuple[torch.Tensor, torch.Tensor]:
        """Render one ingested frame: (render (H, W, 3), ground truth (H, W, 3)). Training frames get
        their exposure gain; every timestep its pose correction, when these are enabled."""
        cam = RenderCamera.from_camera(fr.camera, self.device)
        img, _ = self.avatar.render(cam, self._eval_inputs(fr.timestep), self.cfg.background, near=self.cfg.near, far=self.cfg.far,
                                    return_statistics=False, backend=self.render_backend)  # fmt: skip
        color = img.color
        if self.exposure is not None and fr.role == "train":
            for j, t in enumerate(self.frames):
                if t.timestep == fr.timestep and t.camera_index == fr.camera_index:
                    color = self.exposure.apply(color, img.alpha, j, self.cfg.background)
                    break
        gt = torch.as_tensor(self.data.load_image(fr), device=self.device)
        return color.clamp(0, 1), gt

    @torch.no_grad()
    def evaluate(self, split: str = "val", max_frames: int | None = None, return_images: bool = False) -> dict[str, Any]:
        """Mean PSNR / SSIM of the renders of one role ("train", "val", "test")."""
        frames = self.data.role(split)
        if max_frames is not None:
            frames = frames[:max_frames]
        ps, ss, images = [], [], []
        for fr in frames:
            pred, gt = self.render_frame(fr)
            a, b = pred.permute(2, 0, 1), gt.permute(2, 0, 1)
            ps.append(float(psnr(a, b)))
            ss.append(float(ssim(a, b)))
            if return_images:
                images.append((fr, pred.cpu().numpy(), gt.cpu().numpy()))
        out: dict[str, Any] = {
            "psnr": float(np.mean(ps)) if ps else float("nan"),
            "ssim": float(np.mean(ss)) if ss else float("nan"),
            "n": len(ps),
        }
        if return_images:
            out["images"] = images
        return out

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly: avatar (incl. bindings), optimizer, RNGs, step,
        exposure gains and pose corrections when enabled."""
        st = {
            "format": STATE_FORMAT,
            "step": self.step_count,
            "avatar": {k: v.detach().clone() for k, v in self.avatar.state_dict().items() if not k.startswith("flame.")},
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "rng": rng_state(),
        }
        if self.exposure is not None:
            st["exposure"] = {k: v.detach().clone() for k, v in self.exposure.state_dict().items()}
        if self.pose is not None:
            st["pose"] = {k: v.detach().clone() for k, v in self.pose.state_dict().items()}
        if self.density is not None:
            st["density"] = self.density.state_dict()
        if self.light_albedo is not None:
            st["light_albedo"] = self.light_albedo.state_dict()
        if self.registration is not None:
            st["registration"] = self.registration.state_dict()
        return st

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (same options; the surfel count may differ when densifying)."""
        saved = state["avatar"]
        if saved["surfels.binding"].shape[0] != len(self.avatar.surfels):
            self._resize_surfels(saved)
        self.avatar.load_state_dict(saved, strict=False)
        if self.density is not None and "density" in state:
            self.density.load_state_dict(state["density"])
        if self.exposure is not None and "exposure" in state:
            self.exposure.load_state_dict(state["exposure"])
        if self.pose is not None and "pose" in state:
            self.pose.load_state_dict(state["pose"])
        if self.light_albedo is not None and "light_albedo" in state:
            self.light_albedo.load_state_dict(state["light_albedo"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        set_rng_state(state["rng"])
        self.step_count = int(state["step"])
        self._not_mouth = self.avatar.surfels.region_id != REGION_MOUTH
        if self.registration is not None and "registration" in state:
            self.registration.load_state_dict(state["registration"], self.avatar)
        self.forget_poses()

    def _resize_surfels(self, saved: dict[str, torch.Tensor]) -> None:
        """Reshape the surfel set (and the optimizer over it) to a saved avatar state with another
        surfel count (a densified checkpoint)."""
        from ..avatar.surfels import SurfelSet

        av = self.avatar
        av.surfels = SurfelSet.from_state_dict(_surfel_rows(saved)).to(av.surfels.mu_loc.device)
        av.base_scale = saved["base_scale"].to(av.base_scale)
        self.optimizer = adam(self._param_groups())
        if self.density is not None:
            self.density.clear_statistics()


@dataclass
class NeuSRays:
    """The NeuS side of one step's SDF ray terms: the canonical volume rendering of rays drawn from a
    training frame and what it is compared with.

    out: :func:`render_neus`'s result (with samples); color: its colour after shading and exposure
    (R, 3); gt: the image at the rays' pixels (R, 3); pix: the flat pixel ids (R,); ok: rays the warp
    maps (R,); valid: rays where both the surfels and NeuS are opaque (R,); t_sdf, t_s: NeuS and
    surfel distances along the canonical rays (R,); n_s: the surfel normals in canonical space (R, 3).
    """

    out: Any
    color: torch.Tensor
    gt: torch.Tensor
    pix: torch.Tensor
    ok: torch.Tensor
    valid: torch.Tensor
    t_sdf: torch.Tensor
    t_s: torch.Tensor
    n_s: torch.Tensor


@dataclass
class Phase1Step:
    """What the loss terms of one phase-1 step read (:data:`PHASE1_TERMS`).

    frame: index of the training frame in ``trainer.frames`` (None on a pseudo view); img (H, W, 3),
    mask (H, W), cam: the view; pseudo_weight: a pseudo view's per-pixel weight (H, W) (None on a
    real frame) and view_weight its loss weight; timestep, inputs (FLAME kwargs), rigid (the rigid
    map or None), transform (the mirror of a mirrored pseudo view or None), mesh (the kept posed mesh
    or None): the pose; canon, render, posed: the avatar's canonical state, render and posed
    surfels; color: the render's colour after the exposure gain (H, W, 3). The NeuS rays and the
    symmetry points are drawn when a term first asks for them (:meth:`neus`, :meth:`sym_points`),
    so the generator's draws follow the table's order.
    """

    trainer: Phase1Trainer
    step: int
    polish: bool
    frame: int | None
    img: torch.Tensor
    mask: torch.Tensor
    cam: RenderCamera
    pseudo_weight: torch.Tensor | None
    view_weight: float
    timestep: int
    inputs: dict[str, torch.Tensor]
    rigid: tuple[torch.Tensor, torch.Tensor] | None
    transform: Callable[[torch.Tensor], torch.Tensor] | None
    mesh: PosedMesh | None
    canon: Any
    render: Any
    posed: Any
    color: torch.Tensor
    _neus: NeuSRays | None = None
    _neus_done: bool = False
    _sym_points: torch.Tensor | None = None

    @property
    def real(self) -> bool:
        """Whether the step trains on a training frame (not a pseudo view)."""
        return self.frame is not None

    @property
    def has_mask(self) -> bool:
        """Whether the step trains on a training frame that has a foreground mask."""
        return self.frame is not None and self.trainer.frames[self.frame].mask is not None

    @functools.cached_property
    def mask_keep(self) -> torch.Tensor | None:
        """(H, W) weights of the mask terms on this view: 0 in the band of ``mask_band`` pixels about
        the mask's edge, 1 elsewhere (:func:`mask_edge_keep`); None when ``mask_band`` is 0 (every
        pixel counts). Computed once per step, for both mask terms."""
        band = int(self.trainer.cfg.mask_band)
        return mask_edge_keep(self.mask, band) if band > 0 else None

    def visible_rows(self, x: torch.Tensor) -> torch.Tensor:
        """The rows of a per-surfel tensor x (N, ...) that the rasterizer kept for this view (all rows
        when the render has no visibility), as GaussianAvatars' local terms average over them."""
        vis = self.render.visible
        return x if vis is None else x[vis.to(x.device)]

    def neus(self) -> NeuSRays | None:
        """The NeuS rays of this step (drawn and rendered on the first call), or None on a pseudo
        view or a frame without foreground pixels.

        ``neus.rays_per_step`` foreground pixels and, on frames with masks, ``neus.background_rays``
        times as many pixels of the background band are mapped to canonical rays and volume-rendered;
        the surfel depth (camera z) becomes the distance along the world ray, then the canonical one.
        """
        if self._neus_done:
            return self._neus
        self._neus_done = True
        tr, c, av = self.trainer, self.trainer.cfg, self.trainer.avatar
        fi = self.frame
        if fi is None:
            return None
        fg, bg = tr._ray_pixels(fi, self.mask)
        n = c.neus.rays_per_step
        if fg.numel() == 0 or n <= 0:
            return None
        pix = fg[tr._randint(fg.numel(), n).to(fg.device)]
        n_bg = int(round(c.neus.background_rays * n))
        if n_bg > 0 and tr.frames[fi].mask is not None and bg.numel() > 0:
            pix = torch.cat([pix, bg[tr._randint(bg.numel(), n_bg).to(bg.device)]])
        cr = tr.warp.map(av, {k: v.detach() for k, v in self.inputs.items()}, self.cam, pix, self.rigid)
        o_c, d_c, ratio, rot, ok = cr.origins, cr.dirs, cr.scale, cr.rotation, cr.valid
        # attribute networks: the surfel render may keep the appearance fields to itself, wholly or in
        # part (free surfels' appearance network serves NeuS alone and always learns from it)
        share = (c.neus.appearance_grad_scale if c.neus.appearance_grad else 0.0) if av.attributes == "mlp" else 1.0
        app = av.appearance if share == 1.0 else _scaled_parameter_grad(av.appearance, share)
        out = render_neus(
            av.sdf, app, o_c, d_c, av.variance, c.neus.samples, c.neus.importance, c.neus.up_steps,
            1.0, c.background, length_unit=tr.length_unit, perturb=True, generator=tr.generator, return_samples=True,
        )  # fmt: skip
        gt = self.img.reshape(-1, 3)[pix]
        neus_color = out.color
        if av.light is not None:
            with torch.no_grad():
                n_c = out.normal / out.normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
                n_w = (rot.transpose(-1, -2) @ n_c[..., None]).squeeze(-1)
            neus_color = shade_foreground(neus_color, out.weights_sum, av.light.irradiance(n_w), c.background)
        if tr.exposure is not None:
            neus_color = tr.exposure.apply(neus_color, out.weights_sum, fi, c.background)
        cam, render = self.cam, self.render
        with torch.no_grad():
            Rw = cam.w2c[:3, :3]
            _, d_w = pixel_rays(cam.K, cam.w2c, cam.width, cam.height, pix)
            dz = (d_w @ Rw.T)[:, 2]
            a = render.alpha.reshape(-1)[pix]
            t_s = render.depth.reshape(-1)[pix] / dz.clamp_min(1e-6) * ratio
            n_s = (rot @ render.normal_world.reshape(-1, 3)[pix][..., None]).squeeze(-1)
        wsum = out.weights_sum
        valid = ok & (a > 0.5) & (wsum.detach() > 0.5)
        t_sdf = out.depth / wsum.clamp_min(1e-6)
        self._neus = NeuSRays(out, neus_color, gt, pix, ok, valid, t_sdf, t_s, n_s)
        return self._neus

    def sym_points(self) -> torch.Tensor:
        """The points of this step's symmetry terms (drawn on the first call): ``symmetry.points``
        of them, a ``symmetry.box_fraction`` uniform in the SDF box, the rest surfel centres. (M, 3)."""
        if self._sym_points is None:
            tr, c, av, canon = self.trainer, self.trainer.cfg, self.trainer.avatar, self.canon
            dt, dev = canon.means.dtype, canon.means.device
            m = max(1, c.symmetry.points)
            n_box = int(round(m * min(max(c.symmetry.box_fraction, 0.0), 1.0)))
            n_surf = m - n_box
            parts = []
            if n_surf > 0:
                parts.append(canon.means[tr._randint(canon.means.shape[0], n_surf).to(dev)].detach())
            if n_box > 0:
                u = torch.rand((n_box, 3), generator=tr.generator, dtype=dt).to(dev)
                lo, hi = av.sdf.bbox_min.to(dt), av.sdf.bbox_max.to(dt)
                parts.append(lo + u * (hi - lo))
            self._sym_points = torch.cat(parts, 0)
        return self._sym_points


# ---------------------------------------------------------------------------- phase-1 loss terms


def _rgb(s: Phase1Step) -> torch.Tensor:
    c = s.trainer.cfg
    target = s.trainer._ssim_target(s.frame, s.img) if c.loss.ssim != 0 and s.frame is not None else None
    return L.rgb_loss(s.color, s.img, c.loss.ssim, target)


def _pseudo_rgb(s: Phase1Step) -> torch.Tensor:
    assert s.pseudo_weight is not None
    return weighted_rgb_loss(s.color, s.img, s.pseudo_weight, s.trainer.cfg.loss.ssim)


def _point_sdf(s: Phase1Step) -> torch.Tensor:
    assert s.canon.sdf is not None
    return L.point_sdf_loss(s.canon.sdf[s.trainer._not_mouth], s.trainer.length_unit)


def _align(s: Phase1Step) -> torch.Tensor:
    assert s.canon.sdf_grad is not None
    keep = s.trainer._not_mouth
    return L.align_loss(s.canon.normals[keep], s.canon.sdf_grad[keep])


def _neus_rgb(s: Phase1Step) -> torch.Tensor | None:
    r = s.neus()
    return None if r is None else L.neus_rgb_loss(r.color[r.ok], r.gt[r.ok])


def _neus_mask(s: Phase1Step) -> torch.Tensor | None:
    r = s.neus()
    if r is None:
        return None
    opacity, target = r.out.weights_sum[r.ok], s.mask.reshape(-1)[r.pix][r.ok]
    if s.mask_keep is not None:  # rays in the band about the mask's edge left out
        keep = s.mask_keep.reshape(-1)[r.pix][r.ok] > 0.5
        if not bool(keep.any()):
            return None
        opacity, target = opacity[keep], target[keep]
    return L.mask_bce_loss(opacity, target)


def _depth(s: Phase1Step) -> torch.Tensor | None:
    r = s.neus()
    return None if r is None else L.depth_loss(r.t_sdf, r.t_s, r.valid, s.trainer.length_unit)


def _normal(s: Phase1Step) -> torch.Tensor | None:
    r = s.neus()
    return None if r is None else L.normal_loss(r.out.normal, r.n_s, r.valid)


def _eikonal(s: Phase1Step) -> torch.Tensor:
    """On the NeuS samples of the step's rays (when it has rays) plus the surfel centres."""
    r = s.neus()
    eik = s.canon.means.new_zeros(()) if r is None else L.eikonal_loss(r.out.gradients, r.out.sample_mask)
    return eik + L.eikonal_loss(s.canon.sdf_grad)


def _smooth(s: Phase1Step) -> torch.Tensor:
    tr, c, canon = s.trainer, s.trainer.cfg, s.canon
    n = canon.means.shape[0]
    m = min(n, c.smooth.points)
    sub = tr._randint(n, m).to(canon.means.device)
    delta = (torch.rand((m, 3), generator=tr.generator, dtype=canon.means.dtype) * 2 - 1).to(canon.means.device)
    x2 = canon.means[sub].detach() + delta * c.smooth.delta * tr.length_unit
    _, g2, _ = tr.avatar.sdf.gradient(x2, create_graph=True)
    return L.normal_smoothness_loss(canon.sdf_grad[sub], g2)


def _sym_sdf(s: Phase1Step) -> torch.Tensor:
    tr = s.trainer
    assert tr.sym_plane is not None
    return sdf_symmetry_loss(lambda x: tr.avatar.sdf(x)[0], s.sym_points(), tr.sym_plane, tr.length_unit)


def _sym_color(s: Phase1Step) -> torch.Tensor:
    tr, av = s.trainer, s.trainer.avatar
    assert tr.sym_plane is not None
    pts = s.sym_points()
    dirs = torch.randn((pts.shape[0], 3), generator=tr.generator, dtype=pts.dtype).to(pts.device)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def color(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        _, grad, feat = av.sdf.gradient(x)
        nrm = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        rgb, _ = av.appearance(x, v, nrm, feat)
        return rgb

    return color_symmetry_loss(color, pts, dirs, tr.sym_plane)


def _light_albedo(s: Phase1Step) -> torch.Tensor:
    tr, av = s.trainer, s.trainer.avatar
    assert tr.light_albedo is not None and av.light is not None
    with torch.no_grad():
        frames = s.mesh.R if s.mesh is not None else surfel_frames(s.posed.vertices.detach(), av.faces)[0]
    normals = frames[av.surfels.binding][..., 2]
    return tr.light_albedo.loss(av.light, s.posed.colors, normals, s.canon.means, av.surfels.region_id,
                                tr.cfg.light_albedo.pairs, tr.generator)  # fmt: skip


PHASE1_TERMS: tuple[L.LossTerm[Phase1Step], ...] = (
    L.LossTerm("rgb", None, _rgb, when=lambda s: s.real),
    L.LossTerm("pseudo_rgb", lambda s: s.view_weight, _pseudo_rgb, when=lambda s: not s.real),
    L.LossTerm("mask", "mask", lambda s: L.alpha_mask_loss(s.render.alpha, s.mask, s.mask_keep), polish=False, when=lambda s: s.has_mask),
    L.LossTerm("normal_consistency", "normal_consistency", lambda s: L.normal_consistency_loss(s.render.normal_world, s.render.surf_normal_world),
               start="normal_consistency_from", polish=False),
    L.LossTerm("distortion", "distortion", lambda s: L.distortion_loss(s.render.distortion), start="distortion_from", polish=False),
    L.LossTerm("pt", "pt", _point_sdf, start="sdf_from", polish=False),
    L.LossTerm("align", "align", _align, start="sdf_from", polish=False),
    L.LossTerm("neus_rgb", "neus_rgb", _neus_rgb, start="sdf_from", polish=False, group="sdf"),
    L.LossTerm("neus_mask", "neus_mask", _neus_mask, start="sdf_from", polish=False, when=lambda s: s.has_mask, group="sdf"),
    L.LossTerm("depth", "depth", _depth, start="sdf_from", polish=False, group="sdf"),
    L.LossTerm("normal", "normal", _normal, start="sdf_from", polish=False, group="sdf"),
    L.LossTerm("eikonal", "eikonal", _eikonal, start="sdf_from", polish=False, group="sdf"),
    L.LossTerm("smooth", "smooth", _smooth, start="sdf_from", polish=False, group="sdf"),
    L.LossTerm("sym_sdf", "sym_sdf", _sym_sdf, start="sdf_from", polish=False, when=lambda s: s.trainer.sym_plane is not None, group="symmetry"),
    L.LossTerm("sym_color", "sym_color", _sym_color, start="sdf_from", polish=False, when=lambda s: s.trainer.sym_plane is not None,
               group="symmetry"),
    L.LossTerm("exposure_prior", "exposure_prior", lambda s: s.trainer.exposure.prior(), when=lambda s: s.trainer.exposure is not None),
    L.LossTerm("light_prior", "light_prior", lambda s: s.trainer.avatar.light.mean_prior(), when=lambda s: s.trainer.avatar.light is not None),
    L.LossTerm("light_albedo", "light_albedo", _light_albedo,
               when=lambda s: s.real and s.trainer.light_albedo is not None and s.trainer.avatar.light is not None),
    L.LossTerm("pose_prior", "pose_prior", lambda s: s.trainer.pose.prior(s.trainer.length_unit), start="pose_refine_from",
               when=lambda s: s.trainer.pose is not None),
    L.LossTerm("local_position", "local_position", lambda s: L.local_position_loss(s.visible_rows(s.trainer.avatar.surfels.mu_loc), s.trainer.cfg.free.position_threshold)),
    L.LossTerm("local_scale", "local_scale", lambda s: L.local_scale_loss(s.visible_rows(s.trainer.avatar.surfels.s_loc), s.trainer.cfg.free.scale_threshold)),
)  # fmt: skip
"""Phase 1's objective, in the order its terms are summed (:func:`sage_core.train.losses.add_terms`):
the photometric loss (weight 1 on a training frame, the view's weight on a pseudo view), the mask and
2DGS terms, the SDF terms (the NeuS ray terms, eikonal and smoothness summed as one group), the
symmetry group, and the priors. The polish keeps only the terms with ``polish`` set."""


def _surfel_rows(saved: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k[len("surfels."):]: v for k, v in saved.items() if k.startswith("surfels.")}


def symmetry_plane(avatar: Avatar) -> MirrorPlane | None:
    """The canonical sagittal plane: the template's x = 0 mirror pairs
    (:func:`sage_core.flame.mirror.model_mirror`, teeth and mouth interior included) fitted on the
    canonical mesh; None when the template is not mirror-symmetric."""
    from ..flame.mirror import model_mirror

    mm, _ = model_mirror(avatar.model_data)
    if mm is None:
        return None
    return plane_from_pairs(avatar.canonical_vertices, torch.as_tensor(mm.vertex, device=avatar.canonical_vertices.device))


def one_shot_pseudo_views(data: IngestedData, avatar: Avatar, cfg: Phase1Config) -> tuple[list[Any], torch.Tensor | None]:
    """Pseudo views and the vertex mirror index for a one-shot capture (``sage_core.train.pseudo_views``);
    none for the other regimes."""
    if data.regime != "one-shot":
        return [], None
    from .pseudo_views import build_pseudo_views

    views, mirror_index = build_pseudo_views(data, avatar, cfg)
    return list(views), mirror_index


def registration_decision(data: IngestedData, cfg: Phase1Config) -> tuple[bool, str]:
    """Whether phase 1 ends with the registration of the training timestep
    (:func:`sage_core.train.registration.registration_applies`); an impossible ``mode=on`` is an
    InputError naming the data folder, raised before any training."""
    from .registration import registration_applies

    n_train = len({fr.timestep for fr in data.train})
    try:
        return registration_applies(cfg.registration.mode, data.regime, n_train, cfg.schedule.sdf_from < cfg.iterations, cfg.pose_refine)
    except ValueError as e:
        raise InputError(data.root, str(e)) from None


def registration_rounds(trainer: Phase1Trainer, init_dir: str | Path, decision: tuple[bool, str]) -> RegistrationRounds | None:
    """The registration of the trainer's run when ``decision`` (:func:`registration_decision`) says
    it runs (:class:`sage_core.train.registration.RegistrationRounds`: ``registration.rounds`` fits,
    all but the last evenly spaced over the SDF-trained steps before the polish), else None."""
    from .registration import round_steps

    if not decision[0]:
        return None
    avatar, cfg = trainer.avatar, trainer.cfg
    regions = None
    reg_path = Path(init_dir) / "regions.json"
    if reg_path.is_file():
        regions = Regions.from_dict(json.loads(reg_path.read_text(encoding="utf-8")))
    t0 = avatar.canonical_timestep
    cams = [fr.camera for fr in trainer.data.train if fr.timestep == t0]
    steps = round_steps(cfg.registration.rounds, cfg.schedule.sdf_from, trainer.polish_from)
    return RegistrationRounds(avatar, regions, cams, cfg.registration, steps)


def _mesh_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    import trimesh

    return trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int64), process=False).export(file_type="ply")


def run_phase1(
    data: IngestedData,
    init_dir: str | Path,
    out_dir: str | Path,
    cfg: Phase1Config,
    *,
    device: str = "cpu",
    seed: int = 0,
    checkpoint_dir: str | Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run phase 1 and write ``avatar.pt``, ``renders/``, ``sdf_mesh.ply`` and ``metrics.json`` into
    ``out_dir``; resumes from the newest checkpoint in ``checkpoint_dir``. Returns the metrics."""
    import trimesh

    from ..data.imageio import write_image
    from ..geometry.marching import extract_mesh
    from ..geometry.mesh_metrics import mesh_chamfer, normal_error
    from ..workspace import atomic_write_bytes, atomic_write_json
    from .loop import run_steps

    out_dir = Path(out_dir)
    init_dir = Path(init_dir)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    decision = registration_decision(data, cfg)
    avatar = build_avatar(data, init_dir, cfg, device, gen)
    if cfg.attributes == "free" and cfg.free.mouth_prior:
        from .mouth_start import seed_free_mouth_colors

        seed_free_mouth_colors(avatar, init_dir)
    views, mirror_index = one_shot_pseudo_views(data, avatar, cfg)
    trainer = Phase1Trainer(avatar, data, cfg, device, gen, pseudo_views=views, mirror_index=mirror_index)
    trainer.registration = registration_rounds(trainer, init_dir, decision)
    total = cfg.iterations
    val_psnr = float("nan")

    def after_step(step: int, _out: Any) -> None:
        """A registration round when one is due, then the periodic val evaluation (both before the
        step's checkpoint, so a resumed run has them)."""
        nonlocal val_psnr
        if trainer.registration is not None and trainer.registration.due(step) and step < total:
            trainer.register(step)
        if cfg.schedule.eval_every > 0 and step % cfg.schedule.eval_every == 0 and step < total:
            val_psnr = trainer.evaluate("val", max_frames=4)["psnr"]

    def step_stats(out: Any) -> dict[str, Any]:
        return {"val_psnr": val_psnr, **{k: v for k, v in out.items() if k in ("loss", "rgb", "pt", "depth", "normal", "neus_rgb", "psnr")}}

    loop = run_steps(trainer, total, label="phase 1", progress=progress, checkpoint_dir=checkpoint_dir,
                     checkpoint_every=cfg.schedule.checkpoint_every, state_key="trainer", map_location=device,
                     stats=step_stats, on_step=after_step)  # fmt: skip
    last = dict(loop.last)
    train_time = loop.train_time_s
    steps_run = loop.steps_run
    if trainer.registration is not None:
        trainer.register(total)
        registration = trainer.registration.summary()
    else:
        registration = {"registration": decision[1]}

    if progress is not None:
        progress(total, total, "evaluating")
    val = trainer.evaluate("val", return_images=True)
    train = trainer.evaluate("train", max_frames=16)
    single_camera = data.regime in ("sv-hr", "one-shot")
    test = trainer.evaluate("test") if single_camera else None
    renders = out_dir / "renders"
    renders.mkdir(parents=True, exist_ok=True)
    for fr, pred, gt in val.pop("images"):
        err = np.repeat(np.clip(np.abs(pred - gt).mean(-1, keepdims=True) * 4.0, 0, 1), 3, axis=-1)
        write_image(renders / f"val_t{fr.timestep:05d}_c{fr.camera_index:02d}.png", np.concatenate([gt, pred, err], 1))
    if trainer.pose is not None:
        avatar.params = trainer.pose.bake(avatar.params)
    if trainer.exposure is not None:
        g = trainer.exposure.gains().detach().cpu()
        avatar.set_exposure_gains({(fr.timestep, fr.camera_index): g[j] for j, fr in enumerate(trainer.frames)})
    avatar.save(out_dir / "avatar.pt")

    if progress is not None:
        progress(total, total, "marching cubes")
    mv, mf = extract_mesh(avatar.sdf.sdf, avatar.sdf.bbox_min, avatar.sdf.bbox_max, cfg.mc_resolution, device=device)
    atomic_write_bytes(out_dir / "sdf_mesh.ply", _mesh_bytes(mv, mf))
    head = trimesh.load(init_dir / "head_mesh.ply", process=False)
    hv, hf = np.asarray(head.vertices), np.asarray(head.faces)
    diag = float(np.linalg.norm(hv[np.unique(hf)].max(0) - hv[np.unique(hf)].min(0)))
    chamfer = mesh_chamfer(mv, mf, hv, hf, n_samples=20000, seed=seed)
    nerr = normal_error(mv, mf, hv, hf, n_samples=10000, seed=seed)
    with torch.no_grad():
        canon = avatar.canonical_state(with_sdf=True)
        assert canon.sdf is not None
        keep = avatar.surfels.region_id != REGION_MOUTH
        mean_abs_sdf = float(canon.sdf[keep].abs().mean())
    metrics = {
        "attributes": cfg.attributes,
        "shading": cfg.shading,
        "n_surfels": len(avatar.surfels),
        "iterations": total,
        "render_backend": trainer.render_backend,
        "val_psnr": val["psnr"],
        "val_ssim": val["ssim"],
        "val_images": val["n"],
        "train_psnr": train["psnr"],
        "train_ssim": train["ssim"],
        "chamfer_m": chamfer,
        "chamfer_rel": chamfer / diag if diag > 0 else float("nan"),
        "normal_error_deg": nerr,
        "head_diagonal_m": diag,
        "surfel_mean_abs_sdf_m": mean_abs_sdf,
        "iterations_per_s": steps_run / train_time if train_time > 0 and steps_run > 0 else float("nan"),
        "train_time_s": train_time,
        "final_losses": last,
    }
    if single_camera:
        assert test is not None
        metrics.update({"regime": data.regime, "test_psnr": test["psnr"], "test_ssim": test["ssim"], "test_images": test["n"]})
    if trainer.exposure is not None:
        g = trainer.exposure.gains().detach().cpu()
        metrics["exposure_gains"] = {f"t{fr.timestep:05d}_c{fr.camera_index:02d}": [float(x) for x in g[j]] for j, fr in enumerate(trainer.frames)}
        metrics["exposure_gain_min"] = float(g.min())
        metrics["exposure_gain_max"] = float(g.max())
    if avatar.light is not None:
        metrics["light_mean_irradiance"] = [float(x) for x in avatar.light.mean_irradiance().detach().cpu()]
    if trainer.pose is not None:
        metrics.update(trainer.pose.summary())
    metrics.update(registration)
    if trainer.sym_plane is not None:
        metrics["symmetry_plane_normal"] = [float(x) for x in trainer.sym_plane.normal]
        metrics["symmetry_plane_offset_m"] = float(trainer.sym_plane.offset)
        metrics["symmetry_plane_residual_m"] = trainer.sym_plane.residual
    if data.regime == "one-shot":
        metrics["pseudo_views"] = len(trainer.pseudo_views)
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def _scaled_parameter_grad(module: torch.nn.Module, share: float) -> AppearanceFn:
    """``module`` called with the same parameter values, whose gradients are scaled by ``share``
    (0: detached, gradients reach its inputs only, never its weights)."""
    if share == 0.0:
        params = {k: v.detach() for k, v in module.named_parameters()}
    else:
        params = {k: v.detach() + share * (v - v.detach()) for k, v in module.named_parameters()}
    state = {**params, **dict(module.named_buffers())}
    return lambda *args: torch.func.functional_call(module, state, args)
