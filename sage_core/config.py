"""Per-stage configuration dataclasses, presets, and their load / merge / save / hash.

Precedence (docs/workspace.md "Stage contract"): preset < config file < command-line flags. A
config file is YAML or JSON; it may hold one section per stage (``ingest:``, ``init_mesh:``, …) or,
when it is given to a single stage, that stage's keys at the top level. Nested fields are addressed
with dots in flags and as nested mappings in files. Unknown keys are errors, never ignored. The
phase configs group their fields in sections shared where both phases have them (:class:`NeuSConfig`,
:class:`LossWeights`, :class:`Schedule`); their flat key names of earlier versions stay accepted
(:func:`legacy_aliases`) and keep the config hash (:func:`canonical_form`).

Every field carries its documentation in ``metadata["help"]`` and what it allows (``choices``,
``ge``/``gt``/``le``/``lt`` bounds, list ``length``; see :func:`_f`); :data:`CONFIG_RULES` ties
fields of one config together. :func:`resolve_config` checks them once, on the merged config, and
raises ConfigError naming the field, the value and what is allowed. Presets live in one table,
:data:`PRESET_OVERRIDES`. This module imports no heavy dependencies.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, TypeVar

from .errors import ConfigError

PRESETS = ("tiny", "small", "default")

REGIMES: tuple[str, ...] = ("mv-sf", "mv-mf", "sv-hr", "one-shot")
"""The reconstruction regimes of ``sage ingest``."""

REGIME_SPELLINGS: dict[str, str] = {"oneshot": "one-shot", "one_shot": "one-shot", "monocular": "sv-hr", "svhr": "sv-hr"}
"""Other spellings accepted for a regime: ``sage synth``'s names of the captures of those regimes
(``oneshot``, ``monocular``) and the unhyphenated forms."""


def canonical_regime(name: str) -> str:
    """A regime name as ``sage ingest`` spells it (``oneshot`` -> ``one-shot``); unknown names are
    returned as given (the caller reports them)."""
    key = str(name).strip().lower()
    return REGIME_SPELLINGS.get(key, key)


RENDER_BACKENDS = ("auto", "torch", "cpp", "triton")
"""Values of the ``render_backend`` field of the stages that render surfels."""


def _f(
    default: Any,
    help: str,
    *,
    choices: tuple[str, ...] | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    length: int | None = None,
    alias: str | None = None,
    added: bool = False,
    spellings: dict[str, str] | None = None,
    **kw: Any,
) -> Any:
    """A dataclass field with its help text and its allowed values.

    choices: the allowed strings of an enum-like field. ge / gt / le / lt: inclusive / exclusive
    lower and upper bounds of a numeric field (of every element of a list field). length: the
    number of elements of a list field. ``None`` passes the checks of an optional field. The
    checks run once, in :func:`resolve_config` (:func:`validate_config`). alias: the field's flat
    key name in the stage config of earlier versions (accepted in files, flags and saved configs,
    and the key of the field in the config hash; see :func:`legacy_aliases`). added: a field added
    after workspaces were written whose default keeps the earlier behaviour; at its default it is
    left out of the config hash, so stages finished before it existed stay up to date. spellings:
    other names of the choices, mapped to them when the value is set.
    """
    meta: dict[str, Any] = {"help": help}
    if added:
        meta["added"] = True
    for key, val in (("choices", choices), ("ge", ge), ("gt", gt), ("le", le), ("lt", lt), ("length", length), ("alias", alias),
                     ("spellings", spellings)):
        if val is not None:
            meta[key] = tuple(val) if key == "choices" else val
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: json.loads(json.dumps(d)), metadata=meta, **kw)
    return field(default=default, metadata=meta, **kw)


def _sub(cls: type, help: str, **defaults: Any) -> Any:
    """A nested config section of type ``cls``; ``defaults`` override the defaults of its fields
    in this place (one section class serves both phases with their own defaults)."""
    return field(default_factory=lambda: cls(**defaults), metadata={"help": help})


# --------------------------------------------------------------------------------------------
# Stage configs
# --------------------------------------------------------------------------------------------


@dataclass
class IngestConfig:
    """``sage ingest``: read a VHAP/GaussianAvatars capture into the workspace."""

    regime: str = _f("mv-sf", "Reconstruction regime: mv-sf (one multiview timestep), mv-mf (all training timesteps), sv-hr (one camera, head turns; also spelled monocular), one-shot (one image; also oneshot).", choices=REGIMES, spellings=REGIME_SPELLINGS)
    timestep: int | None = _f(None, "Training timestep for mv-sf (default: the train timestep closest to a neutral face with the mouth slightly open).", ge=0)
    camera: int | None = _f(None, "Camera index for sv-hr and one-shot when the capture has several cameras.", ge=0)
    height: int | None = _f(None, "Resize images to this height (width keeps the aspect). Exclusive with downsample.", ge=8)
    downsample: float | None = _f(None, "Divide the image size by this factor. Exclusive with height.", gt=0)
    background: str = _f("white", "Background of the stored images: white (as exported) or black (recomposited with the mask).", choices=("white", "black"))
    follow_symlinks: bool = _f(False, "Read capture files through symbolic links whose target lies outside the capture folder (refused by default, like paths that climb out of it).", added=True)


@dataclass
class HashGridConfig:
    """Multi-resolution hash encoding (instant-ngp conventions)."""

    n_levels: int = _f(16, "Number of levels L.", ge=1)
    n_features: int = _f(2, "Features per level F.", ge=1)
    log2_table: int = _f(19, "log2 of the hash table size T per level.", ge=1, le=30)
    base_res: int = _f(16, "Coarsest resolution N_min.", ge=1)
    max_res: int = _f(2048, "Finest resolution N_max.", ge=1)


@dataclass
class SDFNetConfig:
    """SDF MLP on [x, enc(x)]."""

    hidden: int = _f(64, "Hidden width of the SDF MLP.", ge=1)
    n_hidden_layers: int = _f(1, "Number of hidden layers.", ge=1)
    feature_dim: int = _f(13, "Size of the latent feature vector z passed to the appearance network.", ge=1)


@dataclass
class PretrainConfig:
    """SDF pretraining on the canonical FLAME mesh (docs/rendering.md §10)."""

    steps: int = _f(3000, "Optimisation steps.", ge=1)
    batch_size: int = _f(8192, "Sample points per step, split evenly over surface / near-surface / uniform samples.", ge=3)
    bank_size: int = _f(200000, "Samples precomputed once per kind (surface, near, uniform).", ge=1)
    lr_grid: float = _f(1e-2, "Adam learning rate of the hash table.", ge=0)
    lr_mlp: float = _f(1e-3, "Adam learning rate of the MLP.", ge=0)
    near_sigmas: list[float] = _f([0.005, 0.02], "Near-surface noise std, as fractions of the head size (two values).", gt=0, length=2)
    truncation: float | None = _f(0.1, "Truncate |d| at this fraction of the head size in the value loss (none: no truncation).", gt=0)
    w_value: float = _f(1.0, "Weight of the L1 signed-distance term.", ge=0)
    w_normal: float = _f(1.0, "Weight of the normal term (1 - cos between the gradient and the mesh normal) on surface samples.", ge=0)
    w_eikonal: float = _f(0.1, "Weight of the eikonal term.", ge=0)
    confidence_band: float = _f(0.25, "Winding-number band around 0.5 over which a sample's sign weight rises from 0 to 1 (open meshes).", gt=0, le=1)
    eval_samples: int = _f(20000, "Surface samples per mesh for the Chamfer distance.", ge=1)


@dataclass
class InitMeshConfig:
    """``sage init-mesh``: canonical mesh, mouth interior, SDF pretrained on the mesh."""

    mouth_interior: bool = _f(True, "Add the mouth-interior mesh (cavity and teeth) rigged to the jaw.")
    mouth_cavity: bool = _f(True, "With mouth_interior: include the cavity behind the lips (off: only the teeth, FLAME with teeth as GaussianAvatars rigs it; the benchmark's GaussianAvatars rows use this).")
    mouth_tongue: bool = _f(True, "With the cavity: also a tongue on its floor, rigged to the jaw (off: the cavity and teeth of earlier versions).")
    bbox_padding: float = _f(0.25, "The SDF box is a cube around the canonical mesh whose half size is the mesh's largest half size times (1 + bbox_padding).", ge=0)
    sphere_radius: float = _f(0.8, "Radius of the SDF's initial sphere relative to the box half size.", gt=0)
    grid: HashGridConfig = _sub(HashGridConfig, "Hash grid of the SDF.")
    sdf: SDFNetConfig = _sub(SDFNetConfig, "SDF network.")
    pretrain: PretrainConfig = _sub(PretrainConfig, "Pretraining schedule.")
    mc_resolution: int = _f(256, "Marching-cubes grid resolution for the extracted zero level set.", ge=2)
    checkpoint_every: int = _f(500, "Checkpoint interval in steps.", ge=1)


@dataclass
class NeuSConfig:
    """NeuS volume rendering of the canonical SDF along a ray (phase 1's SDF terms, phase 2's NeuS
    teacher)."""

    samples: int = _f(32, "Stratified NeuS samples per ray.", ge=1, alias="neus_samples")
    importance: int = _f(32, "NeuS importance samples per ray.", ge=0, alias="neus_importance")
    up_steps: int = _f(2, "NeuS up-sampling rounds.", ge=0, alias="neus_up_steps")


@dataclass
class Phase1NeuSConfig(NeuSConfig):
    """Phase 1's NeuS rays: which pixels of a training frame become canonical rays each step, and the
    initial s-variance."""

    rays_per_step: int = _f(1024, "Foreground rays per step for NeuS.", ge=1, alias="rays_per_step")
    background_rays: float = _f(0.25, "Extra NeuS rays per step from background pixels within neus.background_band pixels of the silhouette, as a fraction of neus.rays_per_step (frames with masks only). Without them the SDF never sees where the head ends and its zero level set, which the surfel centres follow (L_pt), can sit outside the silhouette.", ge=0, le=4, alias="neus_background_rays")
    background_band: int = _f(6, "Width in pixels of the background band around the foreground mask from which the background NeuS rays are drawn.", ge=1, alias="neus_background_band")
    variance: float = _f(0.4, "Initial NeuS s-variance (inv_s = exp(10 var) per box half extent).", ge=-2, le=2, alias="neus_variance")
    appearance_grad: bool = _f(True, "attributes=mlp: the NeuS colour loss also trains the appearance network and its hash table (true, as in the paper: one albedo from both renders); false: its gradient reaches the SDF (its geometry and feature z) and the s-variance only, and the appearance fields learn from the surfel render alone. With free attributes the appearance network serves NeuS alone and always learns from it. false on three photo-skinned tiny subjects: the val image +0.70, -0.05, +0.65 dB, held-out expressions within a rerun's spread, the back views -0.47 to +0.27 dB, and one subject's irises lost their colour (docs/results.md).", added=True)
    appearance_grad_scale: float = _f(1.0, "attributes=mlp, with appearance_grad: the share of the NeuS colour loss's gradient that reaches the appearance network and its hash table (1: the paper's coupling; 0: as appearance_grad=false). The loss and its gradient to the SDF are unchanged. 0.1 on five tiny subjects (three photo-skinned, two detailed): the val image +0.35 to +0.86 dB and held-out expressions -0.05 to +0.25 dB with lower LPIPS, irises kept in colour, but the side views' LPIPS higher on all five and the back views' on four (docs/results.md).", ge=0, le=1, added=True)


@dataclass
class LossWeights:
    """Weights of the loss terms both phases add (2DGS regularisers). A term whose weight is 0 is not
    computed."""

    normal_consistency: float = _f(0.05, "lambda_n: 2DGS normal consistency between the rendered normals and the normals of the rendered depth (phase 2: of the deformed renders).", ge=0, alias="w_normal_consistency")
    distortion: float = _f(100.0, "lambda_d: 2DGS depth distortion, on the depth normalised between near and far (phase 2: of the deformed renders).", ge=0, alias="w_distortion")


@dataclass
class Schedule:
    """When things happen during a phase, in steps."""

    checkpoint_every: int = _f(1000, "Checkpoint interval in steps.", ge=1, alias="checkpoint_every")


@dataclass
class SurfelLayoutConfig:
    """Phase 1: the initial surfels on the canonical mesh."""

    count: int = _f(150000, "Number of surfels spread over the canonical mesh (no densification).", ge=1, alias="n_surfels")
    layout: str = _f("sampled", "Initial surfels: sampled (surfels.count spread over the triangles by area, region and camera weights; SAGE) or per_face (one surfel at the centroid of every triangle with the triangle's scale, GaussianAvatars' initialisation; surfels.count is unused).", choices=("sampled", "per_face"), alias="init_layout")
    scale_factor: float = _f(1.5, "Initial in-plane scale relative to the disk radius that covers the triangle's share of area.", gt=0, alias="init_scale_factor")
    face_weight: float = _f(3.0, "Surfel density multiplier on the face and eyes.", ge=0, alias="face_weight")
    mouth_weight: float = _f(2.0, "Surfel density multiplier on the mouth interior and teeth.", ge=0, alias="mouth_weight")
    hair_weight: float = _f(0.5, "Surfel density multiplier on the hair (the scalp outside the face and neck, the back of the head included). 1.0 spreads it by area like the ears; on five detailed benchmark subjects that lifted the val image by 0.22 to 0.46 dB at the tiny size and by -0.12 and +0.17 dB at the small size, while held-out expressions moved by -0.07 to +0.05 dB, or by -0.22 and -0.38 dB where the registration's decision flipped with it, so 0.5 stays. Regime default for sv-hr: 1.0 (a head-turn clip sees the back of the head only edge-on; at 6,000 surfels the face showed from behind in 6.3 % of the back views' pixels instead of 10.8 %, and on the suite's three photo-skinned SV-HR subjects at 25,000 held-out expressions +0.04, +0.31 and +0.09 dB and held-out views 22.33 -> 22.40 dB with LPIPS 0.0730 -> 0.0702 (mean), the side views about -0.45 dB; one-shot stays at 0.5: -0.5 dB at 6,000 surfels) (docs/results.md).", ge=0, alias="hair_weight")
    neck_weight: float = _f(0.5, "Surfel density multiplier on the neck.", ge=0, alias="neck_weight")
    camera_weight: float = _f(2.0, "Extra density (up to 1 + camera_weight) on triangles facing a nearby training camera. Regime default for sv-hr: 1.0 (a head-turn clip's cameras face all of the head but its back, so the extra density mostly takes surfels from the back: at 6,000 surfels, two phase-1 seeds, the face showed from behind in 4.6 and 3.7 % of the back views' pixels instead of 6.3 and 5.8 %, held-out views +0.11 and +0.10 dB, held-out expressions -0.16 and +0.11 dB; at 25,000 on the suite's three photo-skinned SV-HR subjects held-out expressions +0.04, +0.20 and +0.19 dB and held-out views 22.40 -> 22.47 dB with LPIPS 0.0702 -> 0.0668 (mean); one-shot, not measured, stays at 2) (docs/results.md).", ge=0, alias="camera_weight")


@dataclass
class FreeSurfelConfig:
    """Phase 1 with ``attributes=free``: the per-surfel attributes and GaussianAvatars' local terms."""

    sh_degree: int = _f(3, "SH degree of the free per-surfel colour (attributes=free); the presets match appearance.sh_degree so that the two attribute modes are compared at equal view dependence.", ge=0, le=3, alias="sh_degree")
    init_opacity: float = _f(0.5, "Initial opacity of free surfels.", gt=0, lt=1, alias="init_opacity")
    position_threshold: float = _f(1.0, "Local offset length (in triangle scales) below which the position term is zero (GA: 1).", ge=0, alias="local_position_threshold")
    scale_threshold: float = _f(0.6, "Local scale (relative to the triangle scale) below which the scale term is zero (GA: 0.6).", ge=0, alias="local_scale_threshold")
    mouth_prior: bool = _f(False, "Mouth-interior surfels start from the pretrained mouth prior's albedo (sage_core.avatar.mouth_prior) instead of grey; the training views refine what they see.", alias="mouth_prior")


@dataclass
class AppearanceNetConfig:
    """Phase 1 with ``attributes=mlp``: the appearance network (colour and opacity of a surfel)."""

    hidden: int = _f(64, "Appearance network width.", ge=1, alias="app_hidden")
    layers: int = _f(2, "Appearance network hidden layers.", ge=1, alias="app_layers")
    sh_degree: int = _f(3, "SH degree of the appearance network's view-direction encoding.", ge=0, le=3, alias="app_sh_degree")
    init_opacity: float = _f(0.5, "Initial opacity of every surfel in mlp mode (the appearance network's opacity-logit bias is logit(appearance.init_opacity)). 0.5 (it was 0.88) lowered LPIPS on held-out expressions of both small benchmark subjects and on the SV-HR and one-shot novel views; at the tiny size PSNR moved by -0.06 to -0.12 dB (docs/results.md).", gt=0, lt=1, alias="app_init_opacity")
    grid: bool = _f(True, "Give the appearance network its own hash grid (the grid_* fields) whose features at the surfel centre join the SDF feature z: colour detail then has capacity of its own instead of passing through the SDF network.", alias="app_grid")
    grid_levels: int = _f(16, "Levels of the appearance hash grid.", ge=1, alias="app_grid_levels")
    grid_log2_table: int = _f(19, "log2 of the table entries per level of the appearance hash grid.", ge=8, le=24, alias="app_grid_log2_table")
    grid_max_res: int = _f(2048, "Finest resolution of the appearance hash grid (its coarsest is 16).", ge=16, alias="app_grid_max_res")


@dataclass
class ShapeNetConfig:
    """Phase 1 with ``attributes=mlp``: the shape network (rotation and scale of a surfel)."""

    hidden: int = _f(64, "Shape network width.", ge=1, alias="shape_hidden")
    layers: int = _f(2, "Shape network hidden layers.", ge=1, alias="shape_layers")
    detail_grid: bool = _f(True, "The shape network also reads the appearance hash grid's features (appearance.grid), beside the SDF grid's: surfel size, anisotropy and orientation can then vary at the scale of the colour detail (docs/results.md, \"Detail on heads with real detail\").")


@dataclass
class DensifyConfig:
    """Phase 1: adaptive density control of free surfels (the GaussianAvatars baseline)."""

    enabled: bool = _f(False, "Adaptive density control of free surfels (3DGS clone/split/prune with GaussianAvatars' binding inheritance; sage_core.train.densify). SAGE never densifies; the benchmark's GaussianAvatars rows do.", alias="densify")
    start: int = _f(500, "Densification starts after this step (GaussianAvatars: 1/60 of the run, 10,000 of 600,000 steps).", ge=0, alias="densify_from")
    until: int = _f(30000, "Densification and opacity resets stop at this step (GaussianAvatars: the end of the run; 3DGS: half of it).", ge=0, alias="densify_until")
    every: int = _f(100, "Steps between densifications (GaussianAvatars: 1/300 of the run).", ge=1, alias="densify_every")
    grad_threshold: float = _f(2e-4, "Clone or split surfels whose mean gradient norm w.r.t. their projected centre (NDC units) reaches this (3DGS and GaussianAvatars: 0.0002).", gt=0, alias="densify_grad_threshold")
    percent_dense: float = _f(0.01, "Surfels larger than this fraction of the scene extent are split, smaller ones cloned (3DGS and GaussianAvatars: 0.01).", gt=0, alias="densify_percent_dense")
    prune_opacity: float = _f(0.005, "Densification prunes surfels whose opacity is below this (3DGS and GaussianAvatars: 0.005).", ge=0, lt=1, alias="prune_opacity")
    opacity_reset_every: int = _f(3000, "Steps between opacity resets while densifying (GaussianAvatars: 1/10 of the run; 0: never). Surfels larger than 0.1 x the scene extent are pruned once the step is past this.", ge=0, alias="opacity_reset_every")
    reset_at_start: bool = _f(True, "Also reset the opacities at densify.start (GaussianAvatars does on a white background, as the ingested captures are).", alias="opacity_reset_at_start")
    position_lr_extent: bool = _f(True, "Multiply lr.position and lr.position_final by the scene extent (1.1 x the largest distance of a training camera from their mean), as 3DGS and GaussianAvatars scale their position rate.", alias="densify_position_lr_extent")


@dataclass
class Phase1Rates:
    """Phase 1: Adam learning rates of the parameter groups (0 leaves a group fixed)."""

    sdf: float = _f(1e-4, "Adam learning rate of the SDF MLP (paper: 1e-4).", ge=0, alias="lr_sdf")
    grid: float = _f(1e-4, "Adam learning rate of the hash grid (paper: 1e-4).", ge=0, alias="lr_grid")
    variance: float = _f(1e-3, "Adam learning rate of the NeuS s-variance.", ge=0, alias="lr_variance")
    networks: float = _f(1e-4, "Adam learning rate of the appearance and shape networks (paper: 1e-4).", ge=0, alias="lr_networks")
    app_grid: float = _f(1e-2, "Adam learning rate of the appearance hash table.", ge=0, alias="lr_app_grid")
    position: float = _f(5e-3, "Initial learning rate of the surfel offsets mu_loc (k-normalised triangle units), decayed exponentially to lr.position_final.", ge=0, alias="lr_position")
    position_final: float = _f(5e-5, "Final learning rate of mu_loc.", ge=0, alias="lr_position_final")
    color: float = _f(2.5e-3, "Learning rate of free SH colour (DC; the rest uses 1/20).", ge=0, alias="lr_color")
    opacity: float = _f(5e-2, "Learning rate of free opacity logits.", ge=0, alias="lr_opacity")
    opacity_offset: float = _f(0.0, "attributes=mlp: learning rate of a per-surfel opacity offset, a logit added to the appearance network's opacity (0: none, the default). Trained in phase 1 only and stored in the avatar; a relocated surfel's restarts at 0. Lets an edge surfel fade on its own where the network's opacity is a smooth field; at 5e-3, over seven runs on four detailed benchmark subjects (tiny and small), the val image moved by -0.08 to +0.45 dB (+0.3 to +0.45 on the first two tiny subjects) and held-out expressions by -0.13 to +0.15 dB; 5e-2 overrode the network and raised held-out LPIPS (docs/results.md).", ge=0, added=True)
    scale: float = _f(1.7e-2, "Learning rate of free log scales s_loc.", ge=0, alias="lr_scale")
    rotation: float = _f(1e-3, "Learning rate of free rotations q_loc.", ge=0, alias="lr_rotation")
    exposure: float = _f(2e-3, "Adam learning rate of the log exposure gains.", ge=0, alias="lr_exposure")
    light: float = _f(5e-3, "Adam learning rate of the SH light coefficients (shading=sh2).", ge=0, alias="lr_light")
    pose_rotation: float = _f(1e-4, "Adam learning rate of the rotation and neck corrections (axis-angle, rad).", ge=0, alias="lr_pose_rotation")
    pose_translation: float = _f(1e-5, "Adam learning rate of the translation corrections (m).", ge=0, alias="lr_pose_translation")


@dataclass
class Phase1Losses(LossWeights):
    """Phase 1: weights of the loss terms (``sage_core.train.phase1.PHASE1_TERMS``). A term whose
    weight is 0 is not computed."""

    ssim: float = _f(0.2, "L_rgb = (1 - w) L1 + w (1 - SSIM).", ge=0, le=1, alias="ssim_weight")
    mask: float = _f(3.0, "L1 between the surfel render's alpha and the foreground mask on real frames with masks: pulls the silhouette of the surfels onto the mask, where the photometric loss alone leaves a halo of about 0.2 alpha one pixel outside (docs/results.md).", ge=0, alias="w_mask")
    pt: float = _f(1.0, "lambda_pt: mean |f(x_G)| at canonical surfel centres, in units of the SDF box half extent.", ge=0, alias="w_pt")
    align: float = _f(0.1, "lambda_align: mean |1 - |t3 . n(x_G)||.", ge=0, alias="w_align")
    neus_rgb: float = _f(1.0, "L1 of the NeuS rendering of sampled rays against the image.", ge=0, alias="w_neus_rgb")
    neus_mask: float = _f(0.1, "Binary cross-entropy of the NeuS ray opacity (sum of the weights) against the foreground mask, on the foreground and background rays (NeuS 'with mask').", ge=0, alias="w_neus_mask")
    depth: float = _f(0.1, "lambda_D: L1 between NeuS and surfel depth along canonical rays, in units of the SDF box half extent (MonoSDF depth weight).", ge=0, alias="w_depth")
    normal: float = _f(0.05, "lambda_N: MonoSDF normal loss (L1 + angular) between NeuS and surfel normals (MonoSDF weight).", ge=0, alias="w_normal")
    eikonal: float = _f(0.1, "Eikonal weight on NeuS samples and surfel centres.", ge=0, alias="w_eikonal")
    smooth: float = _f(0.005, "SDF normal smoothness ||n(x) - n(x + delta)|| (MonoSDF).", ge=0, alias="w_smooth")
    sym_sdf: float = _f(0.0, "Soft left-right symmetry of the canonical SDF: mean |f(x) - f(Sx)| (box half-extent units), S the reflection across the head's sagittal plane. Regime default for sv-hr and one-shot: 0.1.", ge=0, alias="w_sym_sdf")
    sym_color: float = _f(0.0, "Soft left-right symmetry of the appearance network colour: mean |c(x) - c(Sx)|. Regime default for sv-hr and one-shot: 0.05.", ge=0, alias="w_sym_color")
    exposure_prior: float = _f(0.01, "Weak prior mean((log gain)^2) holding the exposure gains near 1.", ge=0, alias="w_exposure_prior")
    light_prior: float = _f(0.01, "Weak prior mean((mean irradiance - 1)^2) on the light's band-0 term (shading=sh2), fixing the albedo/light brightness scale.", ge=0, alias="w_light_prior")
    light_albedo: float = _f(1.0, "Smooth-albedo light prior (shading=sh2; sage_core.train.light_prior): weight of the term that picks, among the lights the images cannot tell apart, the one under which neighbouring face and neck surfels of similar chromaticity have the most similar albedo. Its gradient reaches only the light (0: off). From one multiview timestep it let the light follow the capture's shading and raised held-out PSNR on the benchmark subjects (docs/results.md).", ge=0, alias="w_light_albedo")
    pose_prior: float = _f(1.0, "Weight of mean(correction^2) (rad^2, and translations in SDF box half extents squared) keeping the pose corrections small.", ge=0, alias="w_pose_prior")
    local_position: float = _f(0.0, "GaussianAvatars' position term: mean relu(|mu_loc| - free.position_threshold), local offsets in units of the triangle scale (GA: 0.01).", ge=0, alias="w_local_position")
    local_scale: float = _f(0.0, "GaussianAvatars' scale term: mean |relu(exp(s_loc) - free.scale_threshold)| of the local scales (GA: 1).", ge=0, alias="w_local_scale")


@dataclass
class Phase1Schedule(Schedule):
    """Phase 1: the first steps of the loss terms that start late, the polish, and the intervals."""

    sdf_from: int = _f(0, "First step of the SDF terms (L_pt, L_align, L_D, L_N, NeuS).", ge=0, alias="sdf_from")
    normal_consistency_from: int = _f(7000, "First step of the normal-consistency loss.", ge=0, alias="normal_consistency_from")
    distortion_from: int = _f(3000, "First step of the distortion loss.", ge=0, alias="distortion_from")
    pose_refine_from: int = _f(1000, "First step of the pose refinement (after the geometry has settled).", ge=0, alias="pose_refine_from")
    polish_fraction: float = _f(0.2, "The last fraction of phase 1's iterations trains on the photometric loss alone, with only the weak priors on light, exposure and pose (no SDF terms: L_pt, L_align, NeuS, eikonal, smoothness, symmetry; no 2DGS normal consistency, distortion or mask term), so appearance sharpens on the settled geometry (0: off). With phase 2's correction.w_s=0 it lowered held-out LPIPS on three small benchmark subjects (docs/results.md).", ge=0, lt=1, alias="polish_fraction")
    rebind_every: int = _f(1000, "Rebind surfels to their nearest canonical triangle every K steps (0: never).", ge=0, alias="rebind_every")
    eval_every: int = _f(1000, "Validation PSNR every N steps for the progress display (0: only at the end).", ge=0, alias="eval_every")


@dataclass
class RelocateConfig:
    """Phase 1: surfel relocation (sage_core.train.relocate): a fixed budget moved from surfels that
    no training view sees to where the renders are furthest from the images, on the SDF's surface."""

    enabled: bool = _f(True, "Relocate surfels during phase 1 (the paper keeps every surfel where it was spread; relocation lets them reach surface the FLAME mesh lacks, such as hair off the scalp). On by default in the multiview regimes, off in sv-hr and one-shot (docs/method.md, docs/results.md).")
    every: int = _f(150, "Steps between relocations.", ge=1, added=True)
    until: float = _f(0.8, "No relocation after this fraction of the iterations.", ge=0, le=1, added=True)
    fraction: float = _f(0.08, "At most this fraction of the surfels moves at each relocation.", gt=0, le=1, added=True)
    views: int = _f(6, "Training frames scanned for the contribution of every surfel and for the error.", ge=1, added=True)
    floor: float = _f(0.05, "A surfel contributing less alpha than this many pixels, summed over the scanned frames, may move.", ge=0, added=True)


REGISTRATION_REGIONS: tuple[str, ...] = ("face", "neck", "left_ear", "right_ear", "ears", "forehead", "nose", "lips", "eye_region",
                                         "left_eye_region", "right_eye_region", "boundary", "scalp", "skin")
"""FLAME mask regions (and sage's derived ``ears`` and ``skin``) the registration may fit."""


@dataclass
class RegistrationConfig:
    """Phase 1: registration of a single training timestep's tracked pose to the reconstructed
    surface (sage_core.train.registration), after the last step (and in earlier rounds)."""

    mode: str = _f("auto", "Register the training timestep's tracked FLAME mesh to the SDF phase 1 reconstructed and re-anchor the avatar to it (its content moved by the opposite translation, the timestep's FLAME translation baked into the avatar, so the training views render as before): auto (for one multiview timestep, mv-sf, with the SDF terms on and no pose refinement), on (the same conditions, refused otherwise) or off. On the tracked tiny benchmark subject whose training timestep was 1.8 mm off it raised held-out PSNR by 0.35 dB; on the subject 0.8 mm off it moved it by -0.05 dB (docs/results.md).", choices=("auto", "on", "off"))
    regions: list[str] = _f(["face", "neck", "left_ear", "right_ear"], "FLAME vertex regions (comma-separated on the command line) whose canonical vertices are fitted to the SDF's zero level set: skin the images show, not the scalp, which hair covers. Regions the model lacks are left out.", choices=REGISTRATION_REGIONS)
    robust_scale: float = _f(0.008, "Robust scale of the fit (Cauchy weights), as a fraction of the SDF box's half extent (0.008: 1.5 mm for a 37 cm box): vertices much further from the surface, such as ears under hair, hardly count.", gt=0)
    min_pixels: float = _f(0.5, "Smallest translation applied, in pixels of the training views at the head (the median over their cameras of distance over focal length): a shift the images resolve less well than this is within the reconstruction's own error. On the tiny benchmark subject whose training mesh was 0.8 mm off (0.35 px), applying the fitted 0.56 mm lowered held-out PSNR by 0.13 dB; on the one 1.8 mm off (0.8 px) the fit gained (docs/results.md).", ge=0)
    max_translation: float = _f(0.05, "Largest translation applied, as a fraction of the SDF box's half extent; a fit beyond it is reported and not applied.", gt=0)
    iterations: int = _f(50, "Gauss-Newton steps of the fit at most.", ge=1)
    rounds: int = _f(1, "Fits in all: 1 fits once after the last step; n > 1 also fits n - 1 times while the SDF trains (evenly spaced between schedule.sdf_from and the polish), so the rest of phase 1 (rebinding, relocation, the priors that hold content near the mesh) works on the re-anchored mesh. A round applies when its own fit reaches min_pixels; once one has, the later rounds refine it whatever their size. Two rounds on the detailed benchmark subjects, held-out PSNR against one fit: +0.15 and +0.14 dB on the two subjects whose training mesh was 1.5 mm off (tiny and small), unchanged where both fits stayed under half a pixel, but -0.25 dB on the small subject 0.8 mm off, whose first round crossed half a pixel (docs/results.md).", ge=1, le=16, added=True)


@dataclass
class SmoothnessConfig:
    """Phase 1: where the SDF normal smoothness term (weight ``loss.smooth``) is measured."""

    points: int = _f(1024, "Surfel centres per step for the smoothness term.", ge=1, alias="smooth_points")
    delta: float = _f(0.005, "Half width of the smoothness offset delta, relative to the SDF box half extent.", gt=0, alias="smooth_delta")


@dataclass
class SymmetryConfig:
    """Phase 1: where the symmetry terms (weights ``loss.sym_sdf``, ``loss.sym_color``) are measured."""

    points: int = _f(512, "Points per step for the symmetry terms (surfel centres and uniform points of the SDF box).", ge=1, alias="sym_points")
    box_fraction: float = _f(0.25, "Fraction of the symmetry points drawn uniformly in the SDF box (the rest are surfel centres).", ge=0, le=1, alias="sym_box_fraction")


@dataclass
class LightAlbedoConfig:
    """Phase 1: the smooth-albedo light prior (weight ``loss.light_albedo``)."""

    neighbours: int = _f(128, "Smooth-albedo light prior: neighbours per face or neck surfel (canonical space).", ge=1, alias="light_albedo_neighbours")
    pairs: int = _f(65536, "Smooth-albedo light prior: neighbour pairs drawn per step (all of them when fewer).", ge=1, alias="light_albedo_pairs")
    chroma: float = _f(0.02, "Smooth-albedo light prior: chromaticity difference sigma of the pair weight exp(-|dchroma|^2/sigma^2).", gt=0, alias="light_albedo_chroma")


@dataclass
class PseudoViewConfig:
    """Phase 1 on a one-shot capture: the synthesized pseudo views."""

    prob: float = _f(0.5, "One-shot: probability that a step trains on a synthesized pseudo view instead of the input image (weighted photometric loss, no SDF ray terms).", ge=0, le=1, alias="pseudo_view_prob")
    mirror: bool = _f(True, "One-shot: add the mirror pseudo-view (camera S·c2w·S, flipped image, mirrored mesh).", alias="pseudo_mirror")
    mirror_weight: float = _f(0.5, "One-shot: loss weight of the mirror view relative to the input view.", ge=0, alias="pseudo_mirror_weight")
    mirror_yaw_full_deg: float = _f(30.0, "One-shot: head yaw (deg) at which the mirror view reaches its full weight.", gt=0, le=180, alias="pseudo_mirror_yaw_full_deg")
    mirror_yaw_floor: float = _f(0.25, "One-shot: fraction of the mirror view's weight kept for a frontal head.", ge=0, le=1, alias="pseudo_mirror_yaw_floor")
    mirror_seen_weight: float = _f(0.1, "One-shot: per-pixel mirror weight where the input already sees that surface.", ge=0, le=1, alias="pseudo_mirror_seen_weight")
    mirror_background_weight: float = _f(0.5, "One-shot: per-pixel mirror weight on the background.", ge=0, le=1, alias="pseudo_mirror_background_weight")
    mirror_tolerance: float = _f(1e-3, "One-shot: mirror-partner tolerance relative to the template's bounding-box diagonal.", gt=0, alias="pseudo_mirror_tolerance")
    ring_views: int = _f(8, "One-shot: textured-FLAME views on a yaw/pitch ring around the head (0: none).", ge=0, alias="pseudo_ring_views")
    ring_yaw_deg: float = _f(60.0, "One-shot: largest yaw (deg) of the ring views.", ge=0, le=180, alias="pseudo_ring_yaw_deg")
    ring_pitch_deg: float = _f(20.0, "One-shot: largest pitch (deg) of the ring views.", ge=0, lt=90, alias="pseudo_ring_pitch_deg")
    ring_weight: float = _f(0.2, "One-shot: loss weight of each ring view.", ge=0, alias="pseudo_ring_weight")
    ring_background_weight: float = _f(0.0, "One-shot: per-pixel ring weight on the background.", ge=0, le=1, alias="pseudo_ring_background_weight")
    ring_supersample: int = _f(2, "One-shot: per-axis supersampling of the ring renders.", ge=1, le=8, alias="pseudo_ring_supersample")
    texture_resolution: int = _f(4, "One-shot: barycentric texture samples per face edge of the back-projected texture.", ge=1, alias="pseudo_texture_resolution")
    texture_mirror_confidence: float = _f(0.5, "One-shot: confidence of texels filled from their mirror partners.", ge=0, le=1, alias="pseudo_texture_mirror_confidence")
    texture_inpaint_confidence: float = _f(0.0, "One-shot: confidence of inpainted texels (0: never supervise).", ge=0, le=1, alias="pseudo_texture_inpaint_confidence")


@dataclass
class Phase1Config:
    """``sage phase1``: joint optimisation of the surfels, the canonical SDF and the attribute networks.

    The flat key names of earlier versions (``w_light_albedo``, ``n_surfels``, ``rays_per_step``, ...)
    are accepted as aliases of the nested fields (:func:`legacy_aliases`)."""

    attributes: str = _f("mlp", "Surfel attributes: mlp (appearance and shape networks, SAGE) or free (per-surfel colour, opacity, rotation, scale).", choices=("mlp", "free"))
    iterations: int = _f(30000, "Optimisation steps.", ge=1)
    shading: str = _f("sh2", "Colour model: sh2 (the default in every regime: the colour is an albedo times the irradiance of a light fixed in the world, order-2 spherical harmonics of the surfel's outward world normal, so shading follows head turns and expressions; the NeuS colour is shaded the same way with its SDF normal mapped to the world) or none (view-independent colour fixed in head space). On the tracked benchmark captures sh2 scored +1.6 dB (SV-HR) and +0.5 dB (one-shot) on held-out views and expressions, with a lower LPIPS; on one multiview timestep within 0.1 dB of none (docs/results.md).", choices=("none", "sh2"))
    exposure: str = _f("off", "Per-training-frame exposure gain on the surfel and NeuS renders: off, gain (one scalar per frame) or rgb (one gain per channel). Regime default for sv-hr and one-shot: gain.", choices=("off", "gain", "rgb"))
    pose_refine: bool = _f(False, "Refine small per-frame corrections of the FLAME global rotation, neck pose and translation of the training timesteps (single-camera clips), from schedule.pose_refine_from on; they are saved in checkpoints and baked into the avatar's parameters.")
    canonical_warp: str = _f("auto", "How training pixels become canonical rays for the SDF terms: auto (the exact rigid head map where a frame differs from canonical only by global rotation/translation, else the hit-triangle warp; rays missing the mesh are dropped), rigid (rigid frames only) or triangle (always the hit-triangle warp).", choices=("auto", "rigid", "triangle"))
    near: float = _f(0.2, "Near plane (m): culls surfels and sets the distortion's normalised depth.", gt=0)
    far: float = _f(3.0, "Far plane (m) of the distortion's normalised depth (heads at about 1 m).", gt=0)
    background: float = _f(1.0, "Background grey level of the renders (the ingested images are on white).", ge=0, le=1)
    mask_band: int = _f(0, "Pixels on either side of the foreground mask's edge that the mask terms (the surfel alpha's and NeuS's) leave out: a mask from a segmentation is uncertain there by a pixel or two, and a mask one pixel too wide taught the outline to render the background's colour opaque; inside the band the photometric loss alone decides. Regime default for one-shot: 1 (a synthetic photo whose mask was one pixel too wide: held-out views 18.52 -> 19.34 dB, its own viewpoint 19.79 -> 22.57 dB; with the exact mask within 0.1 dB). A head-turn clip sees the outline from many sides: there the band cost 0.14-0.23 dB with exact masks and gained 0.4-0.7 dB with masks one pixel too wide, so its default stays 0 (set 1 for a clip with loose masks).", ge=0, added=True)
    mc_resolution: int = _f(256, "Marching-cubes resolution of the extracted SDF mesh.", ge=2)
    render_backend: str = _f("auto", "Surfel rasterizer backend: auto (triton on CUDA, the native C++ backend on CPU when it is available, else torch), torch (packed pure torch, the reference), cpp (native CPU, OpenMP) or triton (CUDA tile kernels). The backend actually used is recorded in the manifest.", choices=RENDER_BACKENDS)
    surfels: SurfelLayoutConfig = _sub(SurfelLayoutConfig, "The initial surfels.")
    appearance: AppearanceNetConfig = _sub(AppearanceNetConfig, "Appearance network (attributes=mlp).")
    shape: ShapeNetConfig = _sub(ShapeNetConfig, "Shape network (attributes=mlp).")
    free: FreeSurfelConfig = _sub(FreeSurfelConfig, "Free per-surfel attributes (attributes=free).")
    densify: DensifyConfig = _sub(DensifyConfig, "Adaptive density control (attributes=free).")
    lr: Phase1Rates = _sub(Phase1Rates, "Learning rates.")
    loss: Phase1Losses = _sub(Phase1Losses, "Loss weights.")
    schedule: Phase1Schedule = _sub(Phase1Schedule, "Start steps and intervals.")
    neus: Phase1NeuSConfig = _sub(Phase1NeuSConfig, "NeuS rays of the SDF terms.")
    relocate: RelocateConfig = _sub(RelocateConfig, "Surfel relocation.")
    registration: RegistrationConfig = _sub(RegistrationConfig, "Registration of the training timestep's pose.")
    smooth: SmoothnessConfig = _sub(SmoothnessConfig, "SDF normal smoothness samples.")
    symmetry: SymmetryConfig = _sub(SymmetryConfig, "Symmetry samples.")
    light_albedo: LightAlbedoConfig = _sub(LightAlbedoConfig, "Smooth-albedo light prior.")
    pseudo: PseudoViewConfig = _sub(PseudoViewConfig, "One-shot pseudo views.")


@dataclass
class EvalConfig:
    """``sage eval``: PSNR / SSIM / LPIPS of an avatar on the evaluation splits (docs/formats.md §8)."""

    stage: str = _f("auto", "Avatar to evaluate: auto (the latest finished of phase2, phase1), phase1 or phase2.", choices=("auto", "phase1", "phase2"))
    split: str = _f("test", "Split: test (self-reenactment), val (novel view) or all (both).", choices=("test", "val", "all", "novel"))
    samples: int = _f(8, "Sample strips (GT | render | error) written per split.", ge=0)
    psnr_cap: float | None = _f(None, "Cap every per-image PSNR at this value before averaging (none: identical images give inf).", gt=0)
    render_backend: str = _f("auto", "Surfel rasterizer backend: auto (triton on CUDA, the native C++ backend on CPU when it is available, else torch), torch (packed pure torch, the reference), cpp (native CPU, OpenMP) or triton (CUDA tile kernels). The backend actually used is recorded in the manifest.", choices=RENDER_BACKENDS)


@dataclass
class ExportConfig:
    """``sage export``: world-space 3DGS PLY, meshes and the avatar bundle."""

    stage: str = _f("auto", "Avatar to export: auto (the latest finished of phase2, phase1), phase1 or phase2.", choices=("auto", "phase1", "phase2"))
    mc_resolution: int = _f(256, "Marching-cubes resolution of the SDF mesh.", ge=8)
    color_camera: int | None = _f(None, "Bake the view-dependent colours as seen from this camera of the capture (none: each surfel seen along its normal).", ge=0)
    up_axis: str = _f("y", "Vertical axis written in the PLY comment (VHAP worlds are roughly y-up).", choices=("x", "y", "z", "-x", "-y", "-z"))
    orientation: str = _f("viewer", "World of the viewer files: viewer (y-down OpenCV convention, turned 180 degrees about x, as splat viewers expect) or flame (sage's y-up world).", choices=("viewer", "flame"))
    sh_degree: int = _f(0, "SH degree of the viewer PLY: 0, or up to 3 with zero padding for strict INRIA loaders.", choices=(0, 1, 2, 3))
    render_backend: str = _f("auto", "Surfel rasterizer backend: auto (triton on CUDA, the native C++ backend on CPU when it is available, else torch), torch (packed pure torch, the reference), cpp (native CPU, OpenMP) or triton (CUDA tile kernels). The backend actually used is recorded in the manifest.", choices=RENDER_BACKENDS)


@dataclass
class CorrectionConfig:
    """Phase 2: the surfel correction from the local stretch while posing (SAGE §3)."""

    enabled: bool = _f(True, "Surfel correction from the local stretch while posing (SAGE §3; correction.mode says how).", alias="correction")
    mode: str = _f("affine", "How the correction reshapes a surfel: affine (the default: map its ellipse exactly by the neighbourhood's stretch beyond the binding; the identity at rest, an anisotropic stretch followed at any angle to the surfel) or curvature (the paper's: turn it towards the principal curvature directions as far as the stretch is anisotropic, then scale its axes by the stretch along them). w_s damps along the new axes in both. On the three small benchmark subjects affine lowered held-out LPIPS against curvature at the same radius (0.0426 -> 0.0421, 0.0594 -> 0.0589, 0.0451 -> 0.0442; docs/results.md).", choices=("affine", "curvature"), alias="correction_mode")
    radius_edges: float | None = _f(None, "Ball-query radius of the correction's triangle neighbours, in median canonical edge lengths (the Gaussian weight's width is half of it). None (the default): 1.0 for attribute-network surfels, 2.0 for free surfels. On the small benchmark 1.0 lowered held-out LPIPS against 2.0 for the network avatar on three subjects, and cost the free-surfel avatar 0.5 dB; 0.5 leaves many triangles with too few neighbours to measure a stretch (docs/results.md).", gt=0, alias="correction_radius_edges")
    max_neighbours: int = _f(16, "Neighbours kept per triangle.", ge=1, alias="correction_max_neighbours")
    w_s: float = _f(0.0, "Curvature damping length w_s (m): s' = s*sigma/(1 + w_s*|kappa|). 0 (the default) keeps the stretch alone: at 1e-3 the damping shrank surfels on curved skin at rest and smoothed the texture that phase 1's polish sharpens (docs/results.md).", ge=0, alias="correction_w_s")
    umbilic_tol: float = _f(1.0, "Curvature mode: |k1 - k2| (1/m) above which the curvature-aligned rotation applies in full.", ge=0, alias="correction_umbilic_tol")
    anisotropy_tol: float = _f(0.1, "Curvature mode: relative stretch anisotropy (s1 - s2)/s2 above which the curvature-aligned rotation applies in full; it fades to none under isotropic deformation, so surfels keep their fitted orientation at rest (0: always in full).", ge=0, alias="correction_anisotropy_tol")


@dataclass
class Phase2Rates:
    """Phase 2: learning rates of the fine-tuned groups (0 leaves a group frozen) and their schedule."""

    schedule: str = _f("cosine", "Learning-rate schedule of every group: cosine (falls from the set rate to 0 over the phase's iterations, so a longer phase ends as settled as a shorter one) or constant. On a tracked tiny capture a constant rate drifted: 3x the length lost 0.25 dB; cosine lost 0.08 dB (docs/results.md).", choices=("constant", "cosine"), alias="lr_schedule")
    position: float = _f(0.0, "Learning rate of the surfel offsets mu_loc (0: the phase-1 positions are kept; the self-supervised terms otherwise move surfels off the fitted surface and cost quality at rest as well as under expressions; the paper fine-tunes them).", ge=0, alias="lr_position")
    networks: float = _f(0.0, "Learning rate of the appearance network (0: frozen, the default; the paper fine-tunes it). On the tracked tiny-suite capture with 25,000 surfels, 1e-4 cost 0.6 dB on held-out expressions and 3.2 dB on the novel view: the self-supervised appearance terms pull f_app off its photometric fit (docs/results.md).", ge=0, alias="lr_networks")
    shape: float = _f(3e-6, "Learning rate of the shape network (mlp attributes; 0: frozen). On the tracked small-suite capture 1e-5 drifted (3x the preset's length lost 0.27 dB); at 3e-6 3x the length is within 0.01 dB, and the preset's length scores as frozen in PSNR with a lower LPIPS (docs/results.md).", ge=0, alias="lr_shape")
    color: float = _f(1e-3, "Learning rate of free SH colour (DC; the rest uses 1/20).", ge=0, alias="lr_color")
    opacity: float = _f(0.0, "Learning rate of free opacity logits (0: frozen; free surfels collapse when the self-supervised terms move their opacity, scale and rotation).", ge=0, alias="lr_opacity")
    scale: float = _f(0.0, "Learning rate of free log scales (0: frozen; the correction adapts scales under deformation).", ge=0, alias="lr_scale")
    rotation: float = _f(0.0, "Learning rate of free rotations (0: frozen; the correction adapts rotations under deformation).", ge=0, alias="lr_rotation")


@dataclass
class Phase2Losses(LossWeights):
    """Phase 2: weights of the loss terms (``sage_core.train.phase2.PHASE2_TERMS``). A term whose
    weight is 0 is not computed."""

    appearance: float = _f(1.0, "lambda_a: squared error between the surfel colour and the teacher colour on sampled pixels.", ge=0, alias="w_appearance")
    photometric: float = _f(0.0, "Weight of an optional L_rgb term on a captured training frame (0: phase 2 uses no images).", ge=0, alias="w_photometric")


@dataclass
class Phase2Schedule(Schedule):
    """Phase 2: intervals."""

    photometric_every: int = _f(1, "Add the photometric term every N steps (when loss.photometric > 0).", ge=1, alias="photometric_every")
    curve_steps: int = _f(100, "Steps of the distortion curve written to distortion_curve.json.", ge=0, alias="curve_steps")


@dataclass
class RestTeacherConfig:
    """Phase 2: the rest teacher (the phase-1 avatar's renders of the training views at rest)."""

    max_views: int = _f(64, "Rest teacher: at most this many training views (evenly spaced).", ge=1, alias="teacher_max_views")
    depth_tol: float = _f(0.01, "Rest teacher: relative depth slack of the visibility test.", ge=0, alias="teacher_depth_tol")


@dataclass
class PixelSamplingConfig:
    """Phase 2: the pixels of the appearance term."""

    per_step: int = _f(1024, "Pixels per step for the appearance term.", ge=1, alias="rays_per_step")
    error_floor: float = _f(0.5, "Pixel sampling weight = e_n/mean(e_n) + e_d/mean(e_d) + error_floor (errors of the posed render).", ge=0, alias="error_floor")


@dataclass
class MouthPriorConfig:
    """Phase 2: prior colours of the mouth interior no training view sees (SAGE's mouth prior)."""

    enabled: bool = _f(True, "Teach the mouth interior that no training view sees prior colours (SAGE's mouth-interior prior): see prior.", alias="mouth_prior")
    prior: str = _f("table", "Where the prior colours come from: table (one cavity_color and one teeth_color, darkened by occlusion_jaw) or learned (the pretrained mouth-interior prior shipped with sage, albedo grids over subject-independent mouth coordinates fitted on synthetic mouths; sage_core.avatar.mouth_prior). table is the default: on the open-jaw test frames of the tiny multiview capture the learned prior's mouth error was 15 % higher (docs/results.md).", choices=("learned", "table"), alias="mouth_prior_source")
    cavity_color: list[float] = _f([0.30, 0.12, 0.12], "Prior RGB of the unobserved mouth cavity.", ge=0, le=1, length=3, alias="mouth_cavity_color")
    teeth_color: list[float] = _f([0.85, 0.82, 0.75], "Prior RGB of unobserved teeth.", ge=0, le=1, length=3, alias="teeth_color")
    visibility: str = _f("surfels", "Which mouth surfels take the prior: surfels (the default: those bound to mouth triangles that themselves contribute less than half a pixel to the training views at rest, so mouth surfels that show at rest, e.g. on the lips, keep their fitted colour) or faces (those bound to mouth-interior or teeth triangles that no training view sees at rest, whether or not the surfels show). On the second small-suite subject faces cost 1.2 dB on the novel view and raised LPIPS on held-out expressions from 0.0609 to 0.0669 (docs/results.md).", choices=("faces", "surfels"), alias="mouth_prior_visibility")
    occlusion_jaw: float = _f(0.2, "prior=table: darken the prior colours by their ambient visibility (1 - ambient occlusion) computed with the jaw opened this far (rad); 0: no darkening. The learned prior carries its own darkening.", ge=0, alias="mouth_occlusion_jaw")


@dataclass
class UnseenFillConfig:
    """Phase 2: colours and opacities of the other surfels no training view sees."""

    enabled: bool = _f(False, "Surfels that no training view sees at rest (less than half a pixel of blending weight) and that the mouth prior does not colour take the continuation, over the surfel graph of their region group, of the albedos of the group's seen surfels (eyes, face, neck, mouth each alone; the hair only with unseen_fill.hair): what no view saw continues what the views showed instead of the appearance network's extrapolation. Regime default for sv-hr and one-shot: true.", alias="unseen_fill")
    neighbours: int = _f(8, "Neighbours of each surfel in the group graph the colours propagate over.", ge=1, alias="unseen_fill_neighbours")
    hair: bool = _f(False, "Fill the hair too, with the rest of the scalp (the back of the head below the scalp mask, the ears) as one group whose skin-coloured seen surfels pass nothing on: the unseen back of the head continues the seen hair, never the face. Regime default for sv-hr and one-shot: true.", alias="unseen_fill_hair")
    source_min: float = _f(0.5, "Pixels of blending weight over the training views a seen surfel needs to pass its colour on (at least the seen threshold of half a pixel).", ge=0, alias="unseen_fill_source_min")
    grazing_cos: float = _f(0.3, "With hair: a seen surfel of the hair group whose colour is skin and that the views saw only at grazing angles (weighted mean |cos| between its normal and the view direction below this) is filled like an unseen one (0: never).", ge=0, le=1, alias="unseen_fill_grazing_cos")
    cover: bool = _f(True, "Keep the unseen surface covered: a filled surfel's opacity is raised to at least the median opacity of its group's sources and its in-plane scales grow (at most 4x) until their geometric mean reaches 0.75 times the distance to its 4th nearest surfel of the group, but no further than a third of its distance to the mesh's open boundary (the cut at the bottom of the neck), stored in the avatar: no gap in the unseen back shows the inside of the face, and no disc stands out of the surface's edge. Near the seen surface the growth stops at 0.15 times the distance to the nearest seen surfel that some training view faces (a surfel seen only edge-on at an outline, its triangle turned away from every camera, holds nothing back): a head-turn clip sees the back of the head only that way (at 6,000 surfels, held-out views +0.16 dB and the face showing from behind in 5.3 % of the back views' pixels instead of 8.5 %). Applies to the hair group, and to the neck with cover_neck.", alias="unseen_fill_cover")
    cover_away: bool = _f(False, "With cover: in the covered groups, also give the opacity floor and the scale gain to the seen surfels that no training view faces (their triangle turned away from every camera; their colours kept): a head-turn clip sees the back of the head only edge-on, so nothing trained those surfels to cover it from behind, and at few surfels the face shows through the gaps. Regime default for sv-hr and one-shot: true (a synthetic clip's avatar at 6,000 surfels: held-out views +0.07 dB, back views +0.17 dB, the face showing from behind in 10.8 % of the back views' pixels instead of 12.1 %; the suite's SV-HR and one-shot rows at 25,000 surfels and a one-shot avatar at 6,000 within 0.01 dB).", alias="unseen_fill_cover_away", added=True)
    cover_neck: bool = _f(False, "With cover: cover the unseen neck too, whose gaps below the hairline otherwise show the mouth's interior and the inside of the face from behind (a real photograph's one-shot avatar). Regime default for sv-hr and one-shot: true (synthetic one-shot avatars, held-out views: -0.05 dB at 6,000 surfels with the back views +0.10 dB, unchanged at 25,000; SV-HR within 0.02 dB).", alias="unseen_fill_cover_neck", added=True)


@dataclass
class WrinkleConfig:
    """Phase 2: wrinkle shading, stored in the avatar."""

    enabled: bool = _f(True, "Wrinkle shading (after SAGE's darkening of high-distortion regions): darken surfels where an expression compresses the surface (region says which may, basis on which mesh; stored in the avatar). On the tracked MV-SF benchmark captures it added 0.24-0.26 dB and lowered LPIPS on held-out expressions (docs/results.md).", alias="wrinkle_shading")
    strength: float = _f(0.3, "Wrinkle shading: darkening at full compression (0..1); with region=distortion, of the most distorted triangles.", ge=0, le=1, alias="wrinkle_strength")
    full_compression: float = _f(0.25, "Wrinkle shading: relative one-ring area loss at which the darkening is full.", gt=0, le=1, alias="wrinkle_full_compression")
    basis: str = _f("expression", "Wrinkle shading: the mesh the compression is measured on: expression (FLAME's expression-shaped mesh before pose correctives and skinning, against the canonical frame's, so that the area the skinning of the jaw, neck and eyes loses in its blend zones, e.g. under the chin when the jaw opens, does not darken) or posed (the posed mesh, the rule before this option). On three small benchmark subjects expression scored +0.04 to +0.05 dB over posed with a lower LPIPS (region=distortion; docs/results.md).", choices=("expression", "posed"), alias="wrinkle_basis")
    region: str = _f("skin", "Wrinkle shading: which triangles may darken: skin (the default: every non-hair triangle outside the mouth prior, at full strength) or distortion (ramped by their mean distortion during phase 2, SAGE's rule). With the expression basis skin scored +0.14 to +0.18 dB over distortion with a lower LPIPS on three small benchmark subjects (docs/results.md).", choices=("distortion", "skin"), alias="wrinkle_region")
    quantiles: list[float] = _f([0.5, 0.9], "Wrinkle shading: the triangle weight rises from 0 to 1 between these quantiles of the per-triangle mean distortion.", ge=0, le=1, length=2, alias="wrinkle_quantiles")


@dataclass
class ExpressionSamplingConfig:
    """Phase 2: the sampled expressions and pose jitters of the deformed renders."""

    target: float = _f(0.01, "Sampled expression component std: a 1-sigma coefficient moves its most-affected vertex by this many metres.", ge=0, alias="expr_target")
    active: int = _f(8, "A synthetic expression activates between 1 and this many components.", ge=1, alias="expr_active")
    clip_sigma: float = _f(2.5, "Synthetic coefficients and jitters are clipped at this many std.", gt=0, alias="expr_clip_sigma")
    jaw_max: float = _f(0.4, "Largest sampled jaw opening (rad).", ge=0, alias="jaw_max")
    eye_range: float = _f(0.2, "Largest sampled gaze angle (rad).", ge=0, alias="eye_range")
    neck_std: float = _f(0.05, "Neck pose jitter std (rad).", ge=0, alias="neck_std")
    rotation_std: float = _f(0.05, "Global rotation jitter std (rad), composed with the training frame's.", ge=0, alias="rotation_std")
    translation_std: float = _f(0.005, "Global translation jitter std (m).", ge=0, alias="translation_std")
    observed_weight: float = _f(0.3, "Probability of starting from one of the capture's training expressions.", ge=0, le=1, alias="observed_weight")
    observed_noise: float = _f(0.2, "Noise on observed expressions, relative to the component std.", ge=0, alias="observed_noise")
    rest_fraction: float = _f(0.0, "Probability that a step poses the training frame exactly as captured (no sampled expression or jitter): the appearance term then anchors the avatar to its own phase-1 renders.", ge=0, le=1, alias="rest_fraction")


@dataclass
class Phase2Config:
    """``sage phase2``: self-supervised fine-tuning under sampled expressions, SDF and hash grid frozen.

    The flat key names of earlier versions (``correction_mode``, ``w_appearance``, ``teacher_max_views``,
    ...) are accepted as aliases of the nested fields (:func:`legacy_aliases`)."""

    iterations: int = _f(5000, "Optimisation steps.", ge=1)
    teacher: str = _f("rest", "Appearance teacher: rest (the phase-1 avatar's own renders of the training views at rest, looked up through the mesh correspondence) or neus (canonical NeuS volume rendering of the warped ray).", choices=("rest", "neus"))
    near: float = _f(0.2, "Near plane (m) of the surfel renders.", gt=0)
    far: float = _f(3.0, "Far plane (m) of the distortion's normalised depth.", gt=0)
    background: float = _f(1.0, "Background grey level.", ge=0, le=1)
    eval_phase1: bool = _f(True, "Also evaluate the phase-1 avatar (no correction) on the test split, for comparison.")
    eval_frames: int = _f(0, "Evaluate at most this many evenly spaced frames per split (0: all).", ge=0)
    render_backend: str = _f("auto", "Surfel rasterizer backend: auto (triton on CUDA, the native C++ backend on CPU when it is available, else torch), torch (packed pure torch, the reference), cpp (native CPU, OpenMP) or triton (CUDA tile kernels). The backend actually used is recorded in the manifest.", choices=RENDER_BACKENDS)
    correction: CorrectionConfig = _sub(CorrectionConfig, "Surfel correction.")
    lr: Phase2Rates = _sub(Phase2Rates, "Learning rates.")
    loss: Phase2Losses = _sub(Phase2Losses, "Loss weights.")
    schedule: Phase2Schedule = _sub(Phase2Schedule, "Intervals.", checkpoint_every=500)
    neus: NeuSConfig = _sub(NeuSConfig, "NeuS teacher (teacher=neus).")
    rest_teacher: RestTeacherConfig = _sub(RestTeacherConfig, "Rest teacher (teacher=rest).")
    pixels: PixelSamplingConfig = _sub(PixelSamplingConfig, "Pixels of the appearance term.")
    mouth: MouthPriorConfig = _sub(MouthPriorConfig, "Mouth-interior prior.")
    unseen_fill: UnseenFillConfig = _sub(UnseenFillConfig, "Colours of unseen surfels.")
    wrinkles: WrinkleConfig = _sub(WrinkleConfig, "Wrinkle shading.")
    expressions: ExpressionSamplingConfig = _sub(ExpressionSamplingConfig, "Sampled expressions and poses.")


STAGE_CONFIGS: dict[str, type] = {
    "ingest": IngestConfig,
    "init-mesh": InitMeshConfig,
    "phase1": Phase1Config,
    "phase2": Phase2Config,
    "eval": EvalConfig,
    "export": ExportConfig,
}

# Preset overrides per stage, as dotted-key mappings applied over the dataclass defaults
# (the dataclass defaults are the ``default`` preset).
PRESET_OVERRIDES: dict[str, dict[str, dict[str, Any]]] = {
    "default": {},
    "tiny": {
        "ingest": {},
        "init-mesh": {
            "grid.n_levels": 8,
            "grid.log2_table": 14,
            "grid.base_res": 16,
            "grid.max_res": 256,
            "pretrain.steps": 600,
            "pretrain.batch_size": 4096,
            "pretrain.bank_size": 60000,
            "mc_resolution": 128,
            "checkpoint_every": 100,
        },
        "phase1": {
            "iterations": 1500,
            "surfels.count": 6000,
            "appearance.sh_degree": 2,
            "free.sh_degree": 2,
            "appearance.grid_levels": 8,
            "appearance.grid_log2_table": 15,
            "appearance.grid_max_res": 512,
            "lr.sdf": 1e-3,
            "lr.grid": 1e-3,
            "lr.networks": 1e-3,
            "lr.color": 1e-2,
            "schedule.normal_consistency_from": 300,
            "schedule.distortion_from": 300,
            "neus.rays_per_step": 256,
            "smooth.points": 256,
            "neus.samples": 24,
            "neus.importance": 16,
            "schedule.rebind_every": 250,
            "schedule.eval_every": 250,
            "mc_resolution": 128,
            "schedule.checkpoint_every": 250,
        },
        "phase2": {
            "iterations": 300,
            "pixels.per_step": 256,
            "neus.samples": 24,
            "neus.importance": 16,
            "schedule.checkpoint_every": 100,
        },
        "eval": {},
        "export": {"mc_resolution": 128},
    },
    "small": {
        "ingest": {},
        "init-mesh": {
            "grid.n_levels": 12,
            "grid.log2_table": 16,
            "grid.base_res": 16,
            "grid.max_res": 512,
            "pretrain.steps": 800,
            "pretrain.batch_size": 4096,
            "pretrain.bank_size": 100000,
            "mc_resolution": 192,
            "checkpoint_every": 200,
        },
        "phase1": {
            "iterations": 4000,
            "surfels.count": 20000,
            "appearance.hidden": 64,
            "appearance.sh_degree": 2,
            "free.sh_degree": 2,
            "appearance.grid_levels": 12,
            "appearance.grid_log2_table": 17,
            "appearance.grid_max_res": 1024,
            "shape.hidden": 32,
            "lr.sdf": 1e-3,
            "lr.grid": 1e-3,
            "lr.networks": 1e-3,
            "lr.color": 1e-2,
            "schedule.normal_consistency_from": 800,
            "schedule.distortion_from": 800,
            "neus.rays_per_step": 512,
            "smooth.points": 512,
            "neus.samples": 24,
            "neus.importance": 16,
            "schedule.rebind_every": 500,
            "schedule.eval_every": 500,
            "mc_resolution": 192,
            "schedule.checkpoint_every": 500,
        },
        "phase2": {
            "iterations": 800,
            "pixels.per_step": 512,
            "neus.samples": 24,
            "neus.importance": 16,
            "schedule.checkpoint_every": 200,
        },
        "eval": {},
        "export": {"mc_resolution": 192},
    },
}

# Regime-dependent defaults, applied over the preset (and under a config file and flags) when the
# workspace's ingested regime is known. mv-sf and mv-mf keep the plain defaults.
REGIME_OVERRIDES: dict[str, dict[str, dict[str, Any]]] = {
    "sv-hr": {"phase1": {"appearance.sh_degree": 0, "free.sh_degree": 0, "exposure": "gain", "loss.sym_sdf": 0.1, "loss.sym_color": 0.05,
                         "relocate.enabled": False, "surfels.hair_weight": 1.0, "surfels.camera_weight": 1.0},
              "phase2": {"unseen_fill.enabled": True, "unseen_fill.hair": True, "unseen_fill.cover_neck": True,
                         "unseen_fill.cover_away": True}},
    "one-shot": {"phase1": {"appearance.sh_degree": 0, "free.sh_degree": 0, "exposure": "gain", "loss.sym_sdf": 0.1, "loss.sym_color": 0.05,
                            "relocate.enabled": False, "mask_band": 1},
                 "phase2": {"unseen_fill.enabled": True, "unseen_fill.hair": True, "unseen_fill.cover_neck": True,
                            "unseen_fill.cover_away": True}},
}

# Rules that tie several fields of one config together: (check, fields named in the error, what is
# wrong). validate_config applies them after the per-field choices and ranges.
CONFIG_RULES: dict[type, tuple[tuple[Callable[[Any], bool], tuple[str, ...], str], ...]] = {
    IngestConfig: ((lambda c: c.height is None or c.downsample is None, ("height", "downsample"), "give either height or downsample, not both"),),
    HashGridConfig: ((lambda c: c.base_res <= c.max_res, ("base_res", "max_res"), "base_res must not exceed max_res"),),
    Phase1Config: (
        (lambda c: c.near < c.far, ("near", "far"), "near must be smaller than far"),
        (lambda c: not c.densify.enabled or c.attributes == "free", ("densify.enabled", "attributes"),
         "adaptive density control needs free surfel attributes (attributes=free)"),
        (lambda c: c.attributes == "free" or (c.loss.local_position == 0 and c.loss.local_scale == 0),
         ("loss.local_position", "loss.local_scale", "attributes"), "the local position and scale terms act on free surfel attributes only (attributes=free)"),
    ),
    Phase2Config: (
        (lambda c: c.near < c.far, ("near", "far"), "near must be smaller than far"),
    ),
    WrinkleConfig: (
        (lambda c: c.quantiles[0] < c.quantiles[1], ("quantiles",), "the first quantile must be below the second"),
    ),
}

T = TypeVar("T")


# --------------------------------------------------------------------------------------------
# Machinery
# --------------------------------------------------------------------------------------------


def section_name(stage: str) -> str:
    """The config-file section of a stage: ``init-mesh`` -> ``init_mesh``."""
    return stage.replace("-", "_")


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict of a config dataclass (JSON/YAML-safe)."""
    return dataclasses.asdict(cfg)


def legacy_aliases(cls: type) -> dict[str, str]:
    """Flat key of earlier versions -> dotted field name, for a stage config class.

    The phase-1 and phase-2 configs were flat (``w_light_albedo``, ``n_surfels``); their fields now
    sit in sections (``loss.light_albedo``, ``surfels.count``) and carry the old name as
    ``metadata["alias"]`` (:func:`_f`). Config files, ``--set`` flags and saved configs may use
    either name."""
    return dict(_aliases(cls))


def _aliases(cls: type) -> tuple[tuple[str, str], ...]:
    cached = _ALIAS_CACHE.get(cls)
    if cached is None:
        out: list[tuple[str, str]] = []

        def walk(tp: type, prefix: str) -> None:
            for f in dataclasses.fields(tp):
                sub = _field_types(tp)[f.name]
                if dataclasses.is_dataclass(sub):
                    walk(sub, f"{prefix}{f.name}.")
                elif "alias" in f.metadata:
                    out.append((f.metadata["alias"], f"{prefix}{f.name}"))

        walk(cls, "")
        cached = _ALIAS_CACHE[cls] = tuple(out)
    return cached


_ALIAS_CACHE: dict[type, tuple[tuple[str, str], ...]] = {}


def canonical_form(cfg: Any) -> dict[str, Any]:
    """The form of a config that :func:`config_hash` hashes: the nested plain dict, except that a
    field with a legacy flat name (:func:`legacy_aliases`) sits at the top level under that name,
    fields added later (``added``) are left out at their default, and sections left empty by this
    are dropped. A config whose values did not change since its
    stage's fields were nested therefore keeps its hash, and stages a workspace finished before stay
    up to date."""
    flat: dict[str, Any] = {}

    def walk(obj: Any) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                sub = walk(value)
                if sub:
                    out[f.name] = sub
            elif f.metadata.get("added") and value == f.default:
                continue
            elif "alias" in f.metadata:
                flat[f.metadata["alias"]] = json.loads(json.dumps(value))
            else:
                out[f.name] = json.loads(json.dumps(value))
        return out

    nested = walk(cfg)
    clash = set(flat) & set(nested)
    if clash:  # a legacy name may not also be a field or a non-empty section at the top level
        raise ConfigError(f"{type(cfg).__name__}: legacy name(s) {', '.join(sorted(clash))} clash with top-level fields")
    return {**nested, **flat}


def config_hash(cfg: Any) -> str:
    """Stable sha256 (hex, 16 chars) of the canonical JSON form (:func:`canonical_form`) of a config."""
    blob = json.dumps(canonical_form(cfg), sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


TRUE_WORDS = ("true", "yes", "on", "1")
FALSE_WORDS = ("false", "no", "off", "0")


def parse_bool(value: Any) -> bool:
    """A flag as configs and ``--set`` spell it: a bool, 0 / 1, or (any case, spaces around)
    true/yes/on/1 and false/no/off/0. Anything else raises ValueError."""
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str):
        s = value.strip().lower()
        if s in TRUE_WORDS:
            return True
        if s in FALSE_WORDS:
            return False
    raise ValueError(f"not a true/false value: {value!r}")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Convert a file/flag value to the annotated type, or raise ConfigError naming the key."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value is None or (isinstance(value, str) and value.lower() in ("none", "null")):
            if type(None) in args:
                return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, key)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(f"{key}: cannot interpret {value!r} as {tp}")
    if origin in (list, tuple):
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        inner = args[0] if args else Any
        return [(_coerce(v, inner, key) if inner is not Any else v) for v in value]
    if tp is bool:
        try:
            return parse_bool(value)
        except ValueError:
            raise ConfigError(f"{key}: expected true/false, got {value!r}") from None
    if tp is int:
        return _coerce_int(value, key)
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{key}: expected a number, got {value!r}") from None
    if tp is str:
        if not isinstance(value, (str, int, float)):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return str(value)
    return value


EXACT_INT_LIMIT = 2**53
"""Magnitude up to which a number written as a float (``1e4``, ``2.0``) is taken as an integer: the
floats beyond it are not all whole numbers, and ``1e23`` would become 99999999999999991611392."""

INT_MAX = 2**31 - 1
"""Upper bound of every integer field that declares none (:func:`validate_config`): counts and step
numbers beyond it are mistakes, not settings."""


def _coerce_int(value: Any, key: str) -> int:
    """An integer from an int, an integer string (``"500"``) or a whole number written as a float
    (``1e4``, ``"2.0"``) of magnitude at most :data:`EXACT_INT_LIMIT`; ConfigError otherwise."""
    if isinstance(value, bool):
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        try:
            return int(value.strip().replace("_", ""))
        except ValueError:
            pass
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key}: expected an integer, got {value!r}") from None
    if not math.isfinite(f) or not f.is_integer():
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    if abs(f) > EXACT_INT_LIMIT:
        raise ConfigError(f"{key}: {value!r} is too large for an integer setting (at most {INT_MAX} for most fields)")
    return int(f)


def _apply(cfg: Any, key: str, value: Any, where: str) -> None:
    """Set a dotted key on a (nested) config dataclass, with type checks. A legacy flat key of the
    stage config (:func:`legacy_aliases`) stands for its dotted field; a legacy name that is also a
    section (``densify``, ``correction``) sets the section's field when given a plain value."""
    if "." not in key:
        alias = dict(_aliases(type(cfg))).get(key)
        if alias is not None:
            types = _field_types(type(cfg))
            if key not in types or (dataclasses.is_dataclass(types[key]) and not isinstance(value, dict)):
                key = alias
    parts = key.split(".")
    obj = cfg
    for i, p in enumerate(parts):
        types = _field_types(type(obj))
        if p not in types:
            known = ", ".join(sorted(types))
            raise ConfigError(f"{where}: unknown option '{'.'.join(parts[: i + 1])}' for {type(obj).__name__} (known: {known})")
        if i == len(parts) - 1:
            tp = types[p]
            if dataclasses.is_dataclass(tp):
                if not isinstance(value, dict):
                    raise ConfigError(f"{where}: '{key}' is a section; give a mapping")
                for k, v in value.items():
                    _apply(getattr(obj, p), str(k), v, where)
            else:
                v = _coerce(value, tp, f"{where}: {key}")
                meta = next(f.metadata for f in dataclasses.fields(obj) if f.name == p)
                if "spellings" in meta and isinstance(v, str):  # other names of the choices, any case
                    low = v.strip().lower()
                    v = meta["spellings"].get(low, low if low in meta.get("choices", ()) else v)
                setattr(obj, p, v)
        else:
            obj = getattr(obj, p)
            if not dataclasses.is_dataclass(obj):
                raise ConfigError(f"{where}: '{'.'.join(parts[: i + 1])}' is not a section")


def get_field(cfg: Any, key: str) -> Any:
    """The value of a dotted field of a config (``get_field(cfg, "loss.pt")``)."""
    obj = cfg
    for p in key.split("."):
        obj = getattr(obj, p)
    return obj


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        out[key] = v
    return out


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML or JSON config file into a mapping; errors name the file."""
    from .errors import InputError, require_file

    p = Path(path)
    require_file(p, "config file")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise InputError(p, f"cannot read config: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except OSError as e:
        raise InputError(p, f"cannot read config: {e.strerror or e}") from None
    try:
        if p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as e:  # noqa: BLE001 - report any parser failure as an input error
        raise InputError(p, f"cannot parse config: {e}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(p, "config file must hold a mapping")
    return data


def resolve_config(
    stage: str,
    preset: str = "default",
    file_data: dict[str, Any] | None = None,
    flags: dict[str, Any] | None = None,
    file_label: str = "config file",
    regime: str | None = None,
) -> Any:
    """Build a stage's config: dataclass defaults < preset < regime defaults < file section < flags.

    Args:
        stage: stage name (key of ``STAGE_CONFIGS``).
        preset: ``tiny`` or ``default``.
        file_data: parsed config file (sectioned by stage, or flat for this stage).
        flags: dotted-key overrides from the command line; ``None`` values are ignored (unset flags).
        regime: the workspace's ingested regime; its :data:`REGIME_OVERRIDES` apply (none: no
            regime defaults).
    """
    if stage not in STAGE_CONFIGS:
        raise ConfigError(f"unknown stage '{stage}'")
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset '{preset}' (choose from {', '.join(PRESETS)})")
    cfg = STAGE_CONFIGS[stage]()
    for k, v in PRESET_OVERRIDES[preset].get(stage, {}).items():
        _apply(cfg, k, v, f"preset {preset}")
    for k, v in REGIME_OVERRIDES.get(regime or "", {}).get(stage, {}).items():
        _apply(cfg, k, v, f"regime {regime}")
    if file_data:
        sections = {section_name(s) for s in STAGE_CONFIGS}
        if any(k in sections for k in file_data):
            unknown = [k for k in file_data if k not in sections]
            if unknown:
                raise ConfigError(f"{file_label}: unknown section(s) {', '.join(map(repr, unknown))} (stages: {', '.join(sorted(sections))})")
            section = file_data.get(section_name(stage)) or {}
        else:
            section = file_data
        if not isinstance(section, dict):
            raise ConfigError(f"{file_label}: section '{section_name(stage)}' must be a mapping")
        for k, v in section.items():
            _apply(cfg, str(k), v, file_label)
    for k, v in (flags or {}).items():
        if v is None:
            continue
        _apply(cfg, k, v, "command line")
    validate_config(cfg, f"{stage} config")
    return cfg


def allowed_text(meta: Any) -> str:
    """The allowed values of a field, from its metadata: ``one of a, b``, ``>= 1``, ``0 < x <= 1``
    (list fields: ``3 values, each in [0, 1]``); empty when the field declares none."""
    if "choices" in meta:
        return "one of " + ", ".join(str(c) for c in meta["choices"])
    lo = (f"{_num(meta['ge'])} <= " if "ge" in meta else f"{_num(meta['gt'])} < " if "gt" in meta else "")
    hi = (f" <= {_num(meta['le'])}" if "le" in meta else f" < {_num(meta['lt'])}" if "lt" in meta else "")
    rng = ""
    if lo and hi:
        rng = f"{lo}x{hi}"
    elif lo:
        rng = (">= " if "ge" in meta else "> ") + lo.split(" ")[0]
    elif hi:
        rng = hi.strip()
    if "length" in meta:
        return f"{meta['length']} values" + (f", each {rng}" if rng else "")
    return rng


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{v:g}"


def _check_value(value: Any, meta: Any, key: str) -> None:
    """Raise ConfigError naming ``key``, the value and what is allowed, if ``value`` breaks ``meta``."""
    if value is None:
        return
    allowed = allowed_text(meta)
    items = value if isinstance(value, (list, tuple)) else [value]
    if "choices" in meta and any(x not in meta["choices"] for x in items):
        raise ConfigError(f"{key} = {value!r} is not allowed (allowed: {allowed})")
    if "length" in meta and isinstance(value, (list, tuple)) and len(value) != meta["length"]:
        raise ConfigError(f"{key} = {value!r} has {len(value)} value(s) (allowed: {allowed})")
    for x in items:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            continue
        bad = x != x  # NaN is never in range
        bad = bad or ("ge" in meta and not x >= meta["ge"]) or ("gt" in meta and not x > meta["gt"])
        bad = bad or ("le" in meta and not x <= meta["le"]) or ("lt" in meta and not x < meta["lt"])
        if bad:
            raise ConfigError(f"{key} = {value!r} is out of range (allowed: {allowed})")


def validate_config(cfg: Any, where: str = "", prefix: str = "") -> None:
    """Check every field of a (nested) config dataclass against its declared choices and range.

    Raises ConfigError naming the dotted field, the value and the allowed values or range
    (``init-mesh config: pretrain.steps = 0 is out of range (allowed: >= 1)``).
    :func:`resolve_config` calls it once, after all sources are merged.
    """
    types = _field_types(type(cfg))
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            validate_config(value, where, prefix=f"{key}.")
            continue
        name = f"{where}: {key}" if where else key
        _check_value(value, f.metadata, name)
        if _is_int(types[f.name]) and "le" not in f.metadata and "lt" not in f.metadata and value is not None and value > INT_MAX:
            raise ConfigError(f"{name} = {value!r} is out of range (allowed: at most {INT_MAX})")
    for check, names, problem in CONFIG_RULES.get(type(cfg), ()):
        if not check(cfg):
            got = ", ".join(f"{prefix}{n} = {get_field(cfg, n)!r}" for n in names)
            raise ConfigError(f"{where + ': ' if where else ''}{problem} (got {got})")


def _is_int(tp: Any) -> bool:
    """Whether a field's annotation is ``int`` or ``int | None``."""
    args = [a for a in typing.get_args(tp) if a is not type(None)] if typing.get_origin(tp) in (typing.Union, getattr(__import__("types"), "UnionType", None)) else [tp]
    return args == [int]


def from_dict(cls: type[T], data: dict[str, Any]) -> T:
    """Rebuild a config dataclass from its plain dict (e.g. a saved resolved config)."""
    cfg = cls()
    for k, v in data.items():
        _apply(cfg, k, v, f"saved {cls.__name__}")
    return cfg


def describe(cls: type, prefix: str = "") -> list[tuple[str, str, Any]]:
    """(dotted name, help, default) for every field, for docs and ``--help`` listings."""
    return _describe(cls(), prefix)


def _describe(obj: Any, prefix: str) -> list[tuple[str, str, Any]]:
    rows: list[tuple[str, str, Any]] = []
    for f in dataclasses.fields(obj):
        val = getattr(obj, f.name)
        if dataclasses.is_dataclass(val):
            rows.extend(_describe(val, f"{prefix}{f.name}."))
        else:
            rows.append((f"{prefix}{f.name}", f.metadata.get("help", ""), val))
    return rows


def describe_allowed(cls: type, prefix: str = "") -> dict[str, str]:
    """Dotted field name -> its allowed values (:func:`allowed_text`; empty when unconstrained)."""
    out: dict[str, str] = {}
    for f in dataclasses.fields(cls):
        tp = _field_types(cls)[f.name]
        if dataclasses.is_dataclass(tp):
            out.update(describe_allowed(tp, prefix=f"{prefix}{f.name}."))
        else:
            text = allowed_text(f.metadata)
            if text and typing.get_origin(tp) in (typing.Union, getattr(__import__("types"), "UnionType", None)):
                text += " or none"
            out[f"{prefix}{f.name}"] = text
    return out
