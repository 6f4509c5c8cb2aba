"""The animatable avatar: FLAME rig, triangle-bound surfels, canonical SDF and attribute networks.

Canonical space is the FLAME mesh of the canonical timestep with zero global rotation and
translation (docs/method.md §2). Every surfel has a canonical state (centre x_c, rotation
R_canon, in-plane scales s_c) and is bound to a triangle b. A frame's FLAME mesh poses it through
the triangle's canonical frame (R_c, T_c, k_c) and posed frame (R_p, T_p, k_p) (docs/formats.md §6,
surfel convention):

    μ = k_p·R_p·R_cᵀ·(x_c − T_c)/k_c + T_p,    R = R_p·R_cᵀ·R_canon,    s = s_c·k_p/k_c

Attributes:

* ``attributes="mlp"`` (SAGE): colour and opacity come from the appearance network
  f_app(x_c, v_c, n̂(x_c), ẑ(x_c)) with v_c the world view direction mapped to canonical space
  through the inverse of the surfel's canonical→posed triangle rotation; rotation and scales come
  from the shape network on the hash-grid level features at x_c. The network's symmetric matrix is
  added to the prior I − n_b·n_bᵀ (n_b the bound canonical triangle's normal), so that an untrained
  network yields surfels lying flat on their triangles; its size multiplier is relative to a fixed
  per-surfel base (the initial in-plane scale). Centres stay per-surfel parameters (``mu_loc``),
  and so does the optional opacity offset (a logit added to the network's opacity,
  :meth:`SurfelSet.offset_opacities`; phase 1's ``lr.opacity_offset``).
* ``attributes="free"`` (GaussianAvatars-style): per-surfel SH colour, opacity, ``q_loc`` and
  ``s_loc`` of the :class:`SurfelSet`. Unlike GaussianAvatars, the SH is evaluated with the
  canonical view direction (as in mlp mode), so a rigid head motion does not change the colours. The appearance network is still built: it colours the NeuS
  volume rendering of the canonical field.

Shading (``shading``): with "none" (the default) the colour above is the surfel's colour, fixed in
head space. With "sh2" it is an albedo, multiplied by the irradiance of a light fixed in the world
(:class:`~sage_core.avatar.shading.SHIrradiance`, submodule ``light``) at the surfel's world normal:

    c = albedo · E(n_w),   n_w = ±R[:, 2] of the posed (and corrected) surfel rotation,

with the sign chosen towards the outward normal of the posed bound triangle (the third column of its
surfel frame). n_w is used without gradient: the light and the albedo learn from the images, the
surfel orientation from its own geometric terms. ``posed(..., shade=False)`` returns the albedo.

Phase-2 additions, applied to the attribute colour before the shading when the surfel set carries
them: the colour prior of unobserved mouth-interior surfels (:meth:`SurfelSet.blend_color_prior`) and
wrinkle shading, a darkening by the frame's surface compression
(:func:`~sage_core.avatar.wrinkles.apply_wrinkles`), measured on the mesh ``wrinkle_basis`` names
(:data:`~sage_core.avatar.wrinkles.WRINKLE_BASES`).

Exposure gains: phase 1 stores its per-training-frame gains with the avatar
(:meth:`Avatar.set_exposure_gains`, plain data in the file); :meth:`Avatar.exposure_gain` gives the
gain of a (timestep, camera) training frame, None for any other frame (novel views and expressions
use gain 1).

Where each job lives (this module holds the data: the :class:`Avatar` module with its buffers and
networks, and thin methods that call the others):

* :mod:`~sage_core.avatar.build` — :meth:`Avatar.build` from a workspace's init-mesh outputs;
* :mod:`~sage_core.avatar.storage` — :meth:`Avatar.save` / :meth:`Avatar.load` (the avatar file);
* :mod:`~sage_core.avatar.posing` — :meth:`Avatar.canonical_state`, :meth:`Avatar.posed`,
  :meth:`Avatar.pose`, :meth:`Avatar.pose_mesh`, :meth:`Avatar.posed_mesh`, :meth:`Avatar.rigid_transform` and
  the correction hook;
* :mod:`~sage_core.avatar.rendering` — :meth:`Avatar.render`, :meth:`Avatar.shade_colors` and the
  exposure gains; :mod:`~sage_core.avatar.shading` — the world light.

Public surface (shapes; N surfels, V vertices, F faces, flame_inputs = ``FlameModel.forward``
kwargs of batch 1):

* ``Avatar.build(ws_init_dir, data, n_surfels, attributes, ...)`` -> Avatar; ``Avatar.load(path,
  device)`` -> Avatar; ``avatar.save(path)`` -> Path;
* ``avatar.frame_inputs(timestep)``, ``avatar.params_inputs(params, row)``, ``avatar.flame_inputs(flame,
  row, **overrides)`` -> flame_inputs;
* ``avatar.pose_mesh(flame_inputs)`` -> (V, 3); ``avatar.posed_mesh(flame_inputs)`` -> :class:`PosedMesh`
  (the posed mesh and each triangle's canonical → posed map); ``avatar.canonical_state()`` -> :class:`CanonicalSurfels`
  (means (N, 3), quats (N, 4), scales (N, 2)); ``avatar.posed(flame_inputs, camera_centre (3,))`` and
  ``avatar.pose(flame, row, **overrides)`` -> :class:`PosedSurfels` (means (N, 3), quats (N, 4),
  scales (N, 2), opacities (N,), colors (N, 3), vertices (V, 3));
* ``avatar.render(RenderCamera, flame_inputs, background, **raster_kwargs)`` -> (SurfelRender: color
  (H, W, 3), alpha (H, W), depth (H, W), ...; PosedSurfels);
* ``avatar.rigid_transform(flame_inputs)`` -> (R0 (3, 3), t (3,)) or None; ``avatar.faces`` (F, 3);
  ``avatar.canonical_vertices`` (V, 3); ``avatar.root_joint`` (3,).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from ..fields.appearance import AppearanceNetwork
from ..fields.sdf import SDFNetwork
from ..fields.shape import ShapeNetwork
from ..flame.canonical import canonical_inputs
from ..flame.frames import surfel_frames
from ..flame.lbs import FlameModel
from ..flame.model_data import FlameModelData
from ..flame.params import FlameParams
from ..geometry.rigid import canonical_to_world as canonical_to_world_rigid
from ..geometry.rigid import rays_world_to_canonical as canonical_rays_rigid
from ..geometry.rotations import matrix_to_quat
from ..render import RenderCamera, SurfelRender
from ..render.volume import SVariance
from . import build as _build
from . import posing as _posing
from . import rendering as _rendering
from . import storage as _storage
from .build import clip_cameras_at_canonical as _clip_cameras_at_canonical
from .build import rigid_world_from_canonical as _rigid_world_from_canonical
from .correction import SurfelCorrection
from .posing import CanonicalSurfels, PosedMesh, PosedSurfels, params_row_inputs
from .shading import SHADING_MODES, SHIrradiance, world_normals
from .wrinkles import WRINKLE_BASES
from .storage import AVATAR_FORMAT, AVATAR_KIND, FLAME_REF_SEARCH_DEPTH, flame_model_sha256
from .surfels import SurfelSet

__all__ = [
    "AVATAR_FORMAT",
    "AVATAR_KIND",
    "FLAME_REF_SEARCH_DEPTH",
    "Avatar",
    "CanonicalSurfels",
    "PosedSurfels",
    "canonical_rays_rigid",
    "canonical_to_world_rigid",
    "flame_model_sha256",
    "params_row_inputs",
]
# canonical_rays_rigid / canonical_to_world_rigid: the rigid head map of sage_core.geometry.rigid,
# under the names this module has always exported; _rigid_world_from_canonical and
# _clip_cameras_at_canonical likewise name sage_core.avatar.build's functions.
_COMPAT = (_clip_cameras_at_canonical, _rigid_world_from_canonical, canonical_rays_rigid, canonical_to_world_rigid)


class Avatar(nn.Module):
    """FLAME-driven surfel avatar with a canonical SDF (see the module doc).

    Args:
        model_data: the FLAME model (with teeth / mouth interior as init-mesh wrote it).
        params: the subject's FLAME parameters (all ingested timesteps).
        canonical_timestep: dataset timestep that defines canonical space.
        surfels: the :class:`SurfelSet` (its ``attributes`` must equal ``attributes``).
        sdf_args: :class:`SDFNetwork` constructor kwargs (plain data).
        attributes: "mlp" or "free".
        app_args: :class:`AppearanceNetwork` kwargs other than the feature size and box.
        shape_args: :class:`ShapeNetwork` kwargs other than in_features and box (mlp mode), and
            ``detail_grid``: the shape network also reads the appearance network's hash-grid
            features (:attr:`shape_reads_detail`).
        base_scale: (N,) world base size of each surfel for the shape network (mlp mode); default
            the surfel set's current canonical scale (geometric mean of the two).
        neus_variance: initial NeuS s-variance (``variance`` module, inv_s per SDF box half extent).
        shading: "none" (colour fixed in head space) or "sh2" (albedo × world-space SH irradiance of
            the world normal; adds the ``light`` submodule), see the module doc.
        wrinkle_basis: the mesh wrinkle shading measures compression on, "expression" (FLAME's
            expression-shaped mesh, before skinning) or "posed"; see :mod:`sage_core.avatar.wrinkles`.
    """

    canonical_vertices: torch.Tensor
    canonical_shaped: torch.Tensor
    """(V, 3) FLAME's expression-shaped mesh of the canonical frame (template + shape + its expression
    + offsets, before pose correctives and skinning): the rest state of the ``expression`` wrinkle basis."""
    R_c: torch.Tensor
    T_c: torch.Tensor
    k_c: torch.Tensor
    q_c: torch.Tensor
    root_joint: torch.Tensor
    base_scale: torch.Tensor
    flame_source: Path | None = None
    """The workspace FLAME model file the avatar was built from (``WS/init/flame_model.npz``), or None."""
    render_settings: Any = None
    """How the avatar is meant to be rendered (a :class:`sage_core.export.bundle.RenderSettings`: near,
    far, background, surfel correction) when :func:`sage_core.load_avatar` loaded it, else None."""

    def __init__(
        self,
        model_data: FlameModelData,
        params: FlameParams,
        canonical_timestep: int,
        surfels: SurfelSet,
        sdf_args: dict[str, Any],
        attributes: str = "mlp",
        app_args: dict[str, Any] | None = None,
        shape_args: dict[str, Any] | None = None,
        base_scale: torch.Tensor | None = None,
        neus_variance: float = 0.3,
        shading: str = "none",
        wrinkle_basis: str = "expression",
    ) -> None:
        super().__init__()
        if attributes not in ("mlp", "free"):
            raise ValueError(f"attributes must be 'mlp' or 'free', got {attributes!r}")
        if shading not in SHADING_MODES:
            raise ValueError(f"shading must be one of {', '.join(SHADING_MODES)}, got {shading!r}")
        if wrinkle_basis not in WRINKLE_BASES:
            raise ValueError(f"wrinkle_basis must be one of {', '.join(WRINKLE_BASES)}, got {wrinkle_basis!r}")
        if surfels.attributes != attributes:
            raise ValueError(f"surfel set has attributes={surfels.attributes!r}, avatar {attributes!r}")
        self.model_data = model_data
        self.params = params
        self.canonical_timestep = int(canonical_timestep)
        self.attributes = attributes
        self.sdf_args = dict(sdf_args)
        self.app_args = dict(app_args or {})
        self.shape_args = dict(shape_args or {})
        device = surfels.mu_loc.device
        self.flame = FlameModel(model_data).to(device)
        self.surfels = surfels
        self.sdf = SDFNetwork(**self.sdf_args).to(device)
        box = (self.sdf.bbox_min.detach().cpu(), self.sdf.bbox_max.detach().cpu())
        self.appearance = AppearanceNetwork(self.sdf.feature_dim, *box, **self.app_args).to(device)
        self.variance = SVariance(neus_variance).to(device)
        self.shading = shading
        self.light: SHIrradiance | None = SHIrradiance().to(device) if shading != "none" else None
        self.wrinkle_basis = wrinkle_basis
        self.exposure_gains: dict[tuple[int, int], torch.Tensor] = {}
        self.shape: ShapeNetwork | None = None
        if attributes == "mlp":
            net_args = {k: v for k, v in self.shape_args.items() if k != "detail_grid"}
            in_features = self.sdf.encoding.output_dim + (self.appearance.grid.output_dim if self.shape_reads_detail else 0)
            self.shape = ShapeNetwork(in_features, *box, **net_args).to(device)
            with torch.no_grad():
                last = self.shape.mlp[-1]
                assert isinstance(last, nn.Linear)
                last.weight.mul_(0.01)
                last.bias.zero_()
        with torch.no_grad():
            out = self.flame(**canonical_inputs(params, self.canonical_timestep, device))
            verts = out.vertices[0]
            R, T, k = surfel_frames(verts, self.flame.faces)
        self.register_buffer("canonical_vertices", verts.clone())
        # the rest state of the expression wrinkle basis; derived, so not stored in avatar files
        self.register_buffer("canonical_shaped", out.v_shaped[0].detach().clone(), persistent=False)
        self.register_buffer("root_joint", out.joints[0, 0].clone())
        self.register_buffer("R_c", R.clone())
        self.register_buffer("T_c", T.clone())
        self.register_buffer("k_c", k.clone())
        self.register_buffer("q_c", matrix_to_quat(R).clone())
        if base_scale is None:
            with torch.no_grad():
                _, _, s = surfels.pose(R, T, k)
                base_scale = s.prod(-1).sqrt()
        self.register_buffer("base_scale", base_scale.detach().to(device=device, dtype=verts.dtype).clone())

    # ------------------------------------------------------------------ construction and files
    @classmethod
    def build(
        cls,
        ws_init_dir: str | Path,
        data: Any,
        n_surfels: int,
        attributes: str = "mlp",
        *,
        app_args: dict[str, Any] | None = None,
        shape_args: dict[str, Any] | None = None,
        sh_degree: int = 0,
        init_opacity: float = 0.5,
        init_args: dict[str, Any] | None = None,
        neus_variance: float = 0.3,
        shading: str = "none",
        device: str | torch.device = "cpu",
        generator: torch.Generator | None = None,
    ) -> Avatar:
        """Initialise from init-mesh outputs (``flame_model.npz``, ``sdf.pt``, ``regions.json``).

        data: :class:`sage_core.data.dataset.IngestedData`. Surfels are spread over the canonical mesh
        (mouth interior included) by :func:`init_surfels`, with the training cameras mapped into
        canonical space through the canonical timestep's global rotation and translation.
        init_args: extra keyword arguments of :func:`init_surfels` (region and camera weights, ...).
        Free-mode surfels start with the initial opacity and 0.5 grey. shading: see the class doc.
        See :func:`sage_core.avatar.build.build_avatar`.
        """
        return _build.build_avatar(
            cls, ws_init_dir, data, n_surfels, attributes, app_args=app_args, shape_args=shape_args, sh_degree=sh_degree,
            init_opacity=init_opacity, init_args=init_args, neus_variance=neus_variance, shading=shading, device=device,
            generator=generator,
        )  # fmt: skip

    def save(self, path: str | Path, *, embed_flame: bool | None = None) -> Path:
        """Write the avatar file atomically: constructor data, parameters, state dict without the
        FLAME buffers, and the FLAME model, as a safetensors file (see ``docs/workspace.md``).

        embed_flame: True stores the FLAME model arrays in the file (self-contained, as bundles
        are); False/None (default) stores a reference to the workspace's ``init/flame_model.npz``
        with its content hash when the file is written inside the workspace the avatar was built
        from, and embeds the model otherwise. See :mod:`sage_core.avatar.storage`.
        """
        return _storage.save_avatar(self, path, embed_flame=embed_flame)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device = "cpu", flame_model: FlameModelData | None = None) -> Avatar:
        """Read a file written by :meth:`save`; InputError when it is not a readable avatar
        (UnsafeFileError for an old pickle avatar file, which is refused without being loaded).
        flame_model: the model of a file that does not carry it (an avatar bundle's)."""
        return _storage.load_avatar_file(cls, path, device, flame_model)

    # ------------------------------------------------------------------ FLAME inputs
    def frame_inputs(self, timestep: int) -> dict[str, torch.Tensor]:
        """FLAME kwargs (batch 1) of a dataset timestep of the subject's parameters."""
        return self.params_inputs(self.params, self.params.row_of(timestep))

    def params_inputs(self, params: FlameParams, row: int) -> dict[str, torch.Tensor]:
        """FLAME kwargs (batch 1) of row ``row`` of any FlameParams (e.g. a reenactment sequence);
        the subject's shape and static offset replace the sequence's."""
        return _posing.identity_inputs(self, params, row)

    def flame_inputs(
        self, flame: FlameParams | dict[str, Any] | int | None = None, row: int = 0, **overrides: Any
    ) -> dict[str, torch.Tensor]:
        """FLAME kwargs (batch 1, on the avatar's device) of one frame, with the avatar's identity.

        flame: None (the canonical timestep of the subject's own parameters), a dataset timestep
        (int), any :class:`FlameParams` (row ``row``; e.g. a loaded motion) or FLAME kwargs (a dict
        of arrays/tensors of batch 1, used as given; the avatar's shape is added when it has none).
        overrides: per-frame parameters that replace the frame's, e.g. ``expr`` (E,) or (1, E),
        ``jaw_pose`` (3,), ``rotation`` (3,), ``translation`` (3,), ``neck_pose`` (3,),
        ``eyes_pose`` (6,); an ``expr`` shorter than the model's is padded with zeros.
        """
        if flame is None:
            inp = self.frame_inputs(self.canonical_timestep)
        elif isinstance(flame, (int, np.integer)):
            inp = self.frame_inputs(int(flame))
        elif isinstance(flame, FlameParams):
            inp = self.params_inputs(flame, row)
        else:
            dev = self.device
            inp = {k: torch.as_tensor(v, dtype=torch.float32, device=dev) for k, v in flame.items()}
            if "shape" not in inp:
                own = self.params.to_torch(dev)
                inp["shape"] = own["shape"][None]
                if "static_offset" in own:
                    inp["static_offset"] = own["static_offset"]
        for key, value in overrides.items():
            if key not in _posing.FLAME_KEYS:
                raise ValueError(f"unknown FLAME parameter {key!r} (choose from {', '.join(_posing.FLAME_KEYS)})")
            v = torch.as_tensor(value, dtype=torch.float32, device=self.device).reshape(1, -1)
            want = inp[key].shape[-1]
            if key == "expr" and v.shape[-1] < want:
                v = torch.nn.functional.pad(v, (0, want - v.shape[-1]))
            if v.shape[-1] != want:
                raise ValueError(f"FLAME parameter {key!r} needs {want} numbers, got {v.shape[-1]}")
            inp[key] = v
        if overrides:
            inp.pop("dynamic_offset", None)
        return inp

    @property
    def faces(self) -> torch.Tensor:
        """(F, 3) int64 faces of the FLAME model."""
        return self.flame.faces

    @property
    def device(self) -> torch.device:
        return self.canonical_vertices.device

    # ------------------------------------------------------------------ canonical state
    def sdf_at(self, x: torch.Tensor, create_graph: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SDF at canonical points. x: (M, 3) -> sdf (M,), grad (M, 3), feature (M, F_z)."""
        return self.sdf.gradient(x, create_graph=create_graph)

    def canonical_state(self, with_sdf: bool = False, create_graph: bool = False) -> CanonicalSurfels:
        """Canonical centres, rotations and scales of all surfels (see :class:`CanonicalSurfels`).

        with_sdf: also evaluate the SDF, its gradient (differentiable with ``create_graph``) and the
        geometry feature at the centres; in mlp mode the hash encoding is shared with the shape network.
        """
        return _posing.canonical_state(self, with_sdf, create_graph)

    # ------------------------------------------------------------------ posing
    def pose_mesh(self, flame_inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """(V, 3) posed FLAME vertices of one frame (batch-1 kwargs)."""
        return _posing.pose_mesh(self, flame_inputs)

    @property
    def shape_reads_detail(self) -> bool:
        """Whether the shape network reads the appearance hash grid's features beside the SDF's
        (``shape_args["detail_grid"]``; needs an appearance grid)."""
        return bool(self.shape_args.get("detail_grid")) and self.appearance.grid is not None

    def posed(
        self,
        flame_inputs: dict[str, torch.Tensor],
        camera_center_world: torch.Tensor | None,
        correction: SurfelCorrection | None = None,
        canonical: CanonicalSurfels | None = None,
        vertices: torch.Tensor | None = None,
        vertex_transform: Callable[[torch.Tensor], torch.Tensor] | None = None,
        shade: bool = True,
        light_transform: torch.Tensor | None = None,
        mesh: PosedMesh | None = None,
    ) -> PosedSurfels:
        """World-space surfels of one frame.

        flame_inputs: FlameModel kwargs of batch 1; camera_center_world: (3,) for view-dependent
        colour (None: view along the surfel normal); correction: optional surfel correction
        (phase 2); canonical: a precomputed :meth:`canonical_state` (with SDF values for mlp mode to
        avoid a second SDF pass); vertices: the posed mesh if already computed (used as given);
        vertex_transform: (V, 3) -> (V, 3) applied to the FLAME-posed mesh before the surfels are
        posed on it (e.g. a left-right mirror with its vertex permutation), so that surfels bound to
        triangle b follow the transformed triangle b; shade: with shading on, multiply the colours
        by the world irradiance at the (corrected) surfel normals (False: the albedo; no effect when
        ``shading`` is "none"); light_transform: (3, 3) orthogonal map applied to the world normals
        before the irradiance, for a render that should see a transformed light (a left-right mirror
        view of the capture sees the mirror image of the world light: S = diag(−1, 1, 1)); mesh: the
        frame's :meth:`posed_mesh` if already computed (then ``vertices`` and ``vertex_transform`` are
        not used), e.g. kept by a trainer that poses one frame many times.
        """
        return _posing.posed(self, flame_inputs, camera_center_world, correction, canonical, vertices, vertex_transform,
                             shade, light_transform, mesh)  # fmt: skip

    def posed_mesh(
        self, flame_inputs: dict[str, torch.Tensor], vertex_transform: Callable[[torch.Tensor], torch.Tensor] | None = None
    ) -> PosedMesh:
        """The frame-only part of posing (:class:`~sage_core.avatar.posing.PosedMesh`: the posed mesh
        and each triangle's canonical → posed map) of one frame, ``vertex_transform`` as in :meth:`posed`."""
        return _posing.posed_mesh(self, flame_inputs, vertex_transform)

    def pose(
        self,
        flame: FlameParams | dict[str, Any] | int | None = None,
        row: int = 0,
        *,
        view_from: torch.Tensor | None = None,
        **overrides: Any,
    ) -> PosedSurfels:
        """World-space surfels of one frame given by FLAME parameters (:meth:`flame_inputs`), without
        gradients: means (N, 3), quats (N, 4), scales (N, 2), opacities (N,), colors (N, 3) for a camera
        at ``view_from`` (3,) (None: each surfel seen along its normal), vertices (V, 3).

        Example: ``avatar.pose(expr=torch.randn(10) * 0.5, jaw_pose=[0.2, 0, 0])`` poses the canonical
        frame with another expression and an open jaw. No surfel correction is applied
        (:func:`sage_core.render` applies the one a phase-2 avatar was trained with).
        """
        inputs = self.flame_inputs(flame, row, **overrides)
        with torch.no_grad():
            centre = None if view_from is None else torch.as_tensor(view_from, dtype=torch.float32, device=self.device)
            return self.posed(inputs, centre)

    def world_normals(self, quats: torch.Tensor, triangle_normals: torch.Tensor) -> torch.Tensor:
        """Outward unit world normals of posed surfels, without gradient.

        quats: (N, 4) posed surfel rotations; triangle_normals: (N, 3) outward normals of their
        posed bound triangles (the third column of the surfel frame) -> (N, 3).
        """
        return world_normals(quats, triangle_normals)

    def shade_colors(
        self, colors: torch.Tensor, quats: torch.Tensor, vertices: torch.Tensor, light_transform: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Albedo × world irradiance of posed surfels (identity when ``shading`` is "none").

        colors: (N, 3) albedo (``posed(..., shade=False).colors``); quats: (N, 4) posed, possibly
        corrected, surfel rotations; vertices: (V, 3) the posed mesh they are bound to;
        light_transform as in :meth:`posed` -> (N, 3).
        """
        return _rendering.shade_colors(self, colors, quats, vertices, light_transform)

    def render(
        self,
        camera: RenderCamera,
        flame_inputs: dict[str, torch.Tensor],
        background: torch.Tensor | float = 1.0,
        correction: SurfelCorrection | None = None,
        canonical: CanonicalSurfels | None = None,
        vertex_transform: Callable[[torch.Tensor], torch.Tensor] | None = None,
        shade: bool = True,
        light_transform: torch.Tensor | None = None,
        mesh: PosedMesh | None = None,
        **raster_kwargs: Any,
    ) -> tuple[SurfelRender, PosedSurfels]:
        """Pose and rasterize for one (unbatched) camera; raster_kwargs go to ``rasterize_surfels``;
        vertex_transform, shade, light_transform and mesh as in :meth:`posed`."""
        return _rendering.render(self, camera, flame_inputs, background, correction, canonical, vertex_transform, shade,
                                 light_transform, mesh, **raster_kwargs)  # fmt: skip

    # ------------------------------------------------------------------ canonical <-> world
    def rigid_transform(self, flame_inputs: dict[str, torch.Tensor], tol: float = 1e-5) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(R0 (3, 3), t (3,)) when the frame differs from canonical only by its global rotation and
        translation (checked numerically on the posed mesh: max vertex error ≤ tol × mesh size),
        else None. Then x_world = R0·(x_c − J0) + J0 + t with J0 = ``root_joint``
        (:mod:`sage_core.geometry.rigid`)."""
        return _posing.rigid_transform(self, flame_inputs, tol)

    # ------------------------------------------------------------------ exposure gains
    def set_exposure_gains(self, gains: dict[tuple[int, int], Any]) -> None:
        """Store the per-training-frame exposure gains: {(timestep, camera index): (C,) gain},
        C = 1 or 3 (replaces any stored before; saved with the avatar)."""
        self.exposure_gains = _rendering.check_exposure_gains(gains)

    def exposure_gain(self, timestep: int, camera_index: int) -> torch.Tensor | None:
        """(C,) exposure gain of a training frame (on the avatar's device), or None when the frame has
        none stored (novel views and expressions: gain 1)."""
        return _rendering.exposure_gain(self, timestep, camera_index)
