"""The animatable avatar: FLAME rig, triangle-bound surfels, canonical SDF and attribute networks.

Canonical space is the FLAME mesh of the canonical timestep with zero global rotation and
translation (design.md "Canonical space"). Every surfel has a canonical state (centre x_c, rotation
R_canon, in-plane scales s_c) and is bound to a triangle b. A frame's FLAME mesh poses it through
the triangle's canonical frame (R_c, T_c, k_c) and posed frame (R_p, T_p, k_p) (formats.md §6,
surfel convention):

    μ = k_p·R_p·R_cᵀ·(x_c − T_c)/k_c + T_p,    R = R_p·R_cᵀ·R_canon,    s = s_c·k_p/k_c

Attributes:

* ``attributes="mlp"`` (SAGE): colour and opacity come from the appearance network
  f_app(x_c, v_c, n̂(x_c), ẑ(x_c)) with v_c the world view direction mapped to canonical space
  through the inverse of the surfel's canonical→posed triangle rotation; rotation and scales come
  from the shape network on the hash-grid level features at x_c. The network's symmetric matrix is
  added to the prior I − n_b·n_bᵀ (n_b the bound canonical triangle's normal), so that an untrained
  network yields surfels lying flat on their triangles; its size multiplier is relative to a fixed
  per-surfel base (the initial in-plane scale). Centres stay per-surfel parameters (``mu_loc``).
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
(:func:`~sage_core.avatar.wrinkles.apply_wrinkles`).

Exposure gains: phase 1 stores its per-training-frame gains with the avatar
(:meth:`Avatar.set_exposure_gains`, plain data in the file); :meth:`Avatar.exposure_gain` gives the
gain of a (timestep, camera) training frame, None for any other frame (novel views and expressions
use gain 1).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch
from torch import nn

from ..data.cameras import Camera
from ..errors import InputError
from ..fields.appearance import AppearanceNetwork
from ..fields.sdf import SDFNetwork
from ..fields.shape import ShapeNetwork, frame_from_symmetric, symmetric_from_tril
from ..flame.canonical import canonical_inputs
from ..flame.frames import surfel_frames
from ..flame.lbs import FlameModel
from ..flame.model_io import FlameModelData
from ..flame.params import FlameParams
from ..geometry.rotations import matrix_to_quat, quat_conjugate, quat_multiply, quat_normalize, quat_to_matrix
from ..render import RenderCamera, SurfelRender, rasterize_surfels
from ..geometry.sh import eval_sh_colors
from ..render.volume import SVariance
from .correction import SurfelCorrection
from .init import init_surfels
from .shading import SHADING_MODES, SHIrradiance, orient_outward
from .surfels import SurfelSet
from .wrinkles import apply_wrinkles

AVATAR_FORMAT = 2
"""Format 1 was a torch.save pickle (refused now, ``sage convert FILE --trust`` rewrites it); 2 is a
safetensors file (:mod:`sage_core.serialization`) that may reference the workspace's FLAME model."""
AVATAR_KIND = "sage-avatar"
FLAME_REF_SEARCH_DEPTH = 4
"""How many folders above an avatar file :meth:`Avatar.load` looks for the FLAME model it references."""
_FLAME_KEYS = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")


@dataclass
class PosedSurfels:
    """Surfels of one frame in world space.

    means: (N, 3); quats: (N, 4) unit wxyz; scales: (N, 2) world standard deviations;
    opacities: (N,) in [0, 1]; colors: (N, 3) in [0, 1] for the given camera centre (times the
    irradiance, which may exceed 1, for a shaded avatar);
    vertices: (V, 3) the frame's posed FLAME mesh.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    vertices: torch.Tensor


@dataclass
class CanonicalSurfels:
    """Surfels in canonical space; unpacks as ``means, quats, scales``.

    means: (N, 3); quats: (N, 4) unit wxyz; scales: (N, 2); rotation: (N, 3, 3) = R(quats), the third
    column is the surfel normal t3. With ``with_sdf``: sdf (N,), sdf_grad (N, 3) (differentiable
    when built with ``create_graph``) and feature (N, F_z) of the SDF network at the centres.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    rotation: torch.Tensor
    sdf: torch.Tensor | None = None
    sdf_grad: torch.Tensor | None = None
    feature: torch.Tensor | None = None

    def __iter__(self) -> Iterator[torch.Tensor]:
        return iter((self.means, self.quats, self.scales))

    @property
    def normals(self) -> torch.Tensor:
        """(N, 3) surfel normals t3."""
        return self.rotation[..., 2]


def params_row_inputs(
    params: FlameParams, row: int, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> dict[str, torch.Tensor]:
    """``FlameModel.forward`` kwargs (batch 1) of row ``row`` of any :class:`FlameParams`.

    Shape and static offset come from ``params`` when it carries them.
    """
    p = params.to_torch(device, dtype)
    out: dict[str, torch.Tensor] = {k: p[k][row : row + 1] for k in _FLAME_KEYS}
    if p["shape"].numel():
        out["shape"] = p["shape"][None]
    if "static_offset" in p:
        out["static_offset"] = p["static_offset"]
    if "dynamic_offset" in p:
        out["dynamic_offset"] = p["dynamic_offset"][row : row + 1]
    return out


def _plain(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return obj.copy()
    return obj


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
        shape_args: :class:`ShapeNetwork` kwargs other than in_features and box (mlp mode).
        base_scale: (N,) world base size of each surfel for the shape network (mlp mode); default
            the surfel set's current canonical scale (geometric mean of the two).
        neus_variance: initial NeuS s-variance (``variance`` module, inv_s per SDF box half extent).
        shading: "none" (colour fixed in head space) or "sh2" (albedo × world-space SH irradiance of
            the world normal; adds the ``light`` submodule), see the module doc.
    """

    canonical_vertices: torch.Tensor
    R_c: torch.Tensor
    T_c: torch.Tensor
    k_c: torch.Tensor
    q_c: torch.Tensor
    root_joint: torch.Tensor
    base_scale: torch.Tensor
    flame_source: Path | None = None
    """The workspace FLAME model file the avatar was built from (``WS/init/flame_model.npz``), or None."""

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
    ) -> None:
        super().__init__()
        if attributes not in ("mlp", "free"):
            raise ValueError(f"attributes must be 'mlp' or 'free', got {attributes!r}")
        if shading not in SHADING_MODES:
            raise ValueError(f"shading must be one of {', '.join(SHADING_MODES)}, got {shading!r}")
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
        self.exposure_gains: dict[tuple[int, int], torch.Tensor] = {}
        self.shape: ShapeNetwork | None = None
        if attributes == "mlp":
            self.shape = ShapeNetwork(self.sdf.encoding.output_dim, *box, **self.shape_args).to(device)
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

    # ------------------------------------------------------------------ construction
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
        """
        import json

        from ..flame import load_flame_model
        from ..flame.regions import Regions
        from ..fields.sdf_file import read_sdf_file

        d = Path(ws_init_dir)
        model_path = d / "flame_model.npz"
        if not model_path.is_file():
            raise InputError(model_path, "missing (run `sage init-mesh` first)")
        model_data = load_flame_model(model_path)
        sdf_args, sdf_state = read_sdf_file(d / "sdf.pt")
        regions = None
        reg_path = d / "regions.json"
        if reg_path.is_file():
            try:
                regions = Regions.from_dict(json.loads(reg_path.read_text()))
            except (ValueError, KeyError, TypeError) as e:
                raise InputError(reg_path, f"malformed regions: {e}") from None
        params = data.params
        ct = data.canonical_timestep
        flame = FlameModel(model_data)
        with torch.no_grad():
            out_c = flame(**canonical_inputs(params, ct))
        verts_c = out_c.vertices[0]
        world_from_mesh = _rigid_world_from_canonical(params, params.row_of(ct), out_c.joints[0, 0])
        cams: list[Camera] = []
        seen: set[int] = set()
        for fr in data.train:
            if fr.timestep == ct and fr.camera_index not in seen:
                seen.add(fr.camera_index)
                cams.append(fr.camera)
        if getattr(data, "regime", "") == "sv-hr":
            cams = _clip_cameras_at_canonical(data, params, ct, out_c.joints[0, 0], world_from_mesh)
        init = init_surfels(
            verts_c, flame.faces, n_surfels, regions, cams, world_from_mesh=world_from_mesh,
            generator=generator, device=device, **(init_args or {}),
        )  # fmt: skip
        kw: dict[str, Any] = {"attributes": attributes}
        if attributes == "free":
            kw.update(sh_degree=sh_degree, opacity=init_opacity)
        surfels = SurfelSet.from_init(init, **kw).to(device)
        app = {"hidden": 32, "n_layers": 2, "sh_degree": 2, **(app_args or {})}
        shp = {"hidden": 32, "n_layers": 2, **(shape_args or {})}
        avatar = cls(model_data, params, ct, surfels, sdf_args, attributes, app, shp if attributes == "mlp" else None,
                     neus_variance=neus_variance, shading=shading)
        avatar.sdf.load_state_dict(sdf_state)
        avatar.flame_source = model_path.resolve()
        return avatar.to(device)

    # ------------------------------------------------------------------ FLAME inputs
    def frame_inputs(self, timestep: int) -> dict[str, torch.Tensor]:
        """FLAME kwargs (batch 1) of a dataset timestep of the subject's parameters."""
        return self.params_inputs(self.params, self.params.row_of(timestep))

    def params_inputs(self, params: FlameParams, row: int) -> dict[str, torch.Tensor]:
        """FLAME kwargs (batch 1) of row ``row`` of any FlameParams (e.g. a reenactment sequence);
        the subject's shape and static offset replace the sequence's."""
        dev = self.canonical_vertices.device
        out = params_row_inputs(params, row, dev)
        own = self.params.to_torch(dev)
        out["shape"] = own["shape"][None]
        if "static_offset" in own:
            out["static_offset"] = own["static_offset"]
        else:
            out.pop("static_offset", None)
        return out

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
        s = self.surfels
        b = s.binding
        Rb, Tb, kb = self.R_c[b], self.T_c[b], self.k_c[b]
        means = kb[:, None] * (Rb @ s.mu_loc[..., None]).squeeze(-1) + Tb
        sdf = grad = feature = None
        if self.attributes == "free":
            quats = quat_multiply(self.q_c[b], quat_normalize(s.q_loc))
            scales = kb[:, None] * torch.exp(s.s_loc)
            rot = quat_to_matrix(quats)
            if with_sdf:
                sdf, grad, feature = self.sdf.gradient(means, create_graph=create_graph)
        else:
            if with_sdf:
                sdf, grad, feature, enc = self._sdf_with_encoding(means, create_graph)
            else:
                enc = self.sdf.encoding(means)
            rot, scales = self._shape_forward(means, Rb[..., 2], enc)
            quats = matrix_to_quat(rot)
        return CanonicalSurfels(means, quats, scales, rot, sdf, grad, feature)

    def _sdf_with_encoding(
        self, x: torch.Tensor, create_graph: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """SDFNetwork.forward and its gradient, also returning the hash encoding (M, L·F) of x."""
        net = self.sdf
        with torch.enable_grad():
            xg = x if (x.requires_grad and create_graph) else x.detach().requires_grad_(True)
            enc = net.encoding(xg)
            h = torch.cat([(xg - net.center.to(xg.dtype)) / net.half_extent, enc], -1)
            for layer in net.layers[:-1]:
                h = net.activation(layer(h))
            out = net.layers[-1](h)
            sdf = out[:, 0] * net.half_extent
            (grad,) = torch.autograd.grad(sdf.sum(), xg, create_graph=create_graph)
        feature = out[:, 1:]
        if not create_graph:
            sdf, feature = sdf.detach(), feature.detach()
            enc = net.encoding(x) if torch.is_grad_enabled() else enc.detach()
        return sdf, grad, feature, enc

    def _shape_forward(self, x: torch.Tensor, prior_normal: torch.Tensor, enc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape network with the flat-on-triangle prior.

        x, prior_normal: (N, 3); enc: (N, L·F) hash features at x -> R (N, 3, 3), s (N, 2).
        """
        net = self.shape
        assert net is not None
        xn = (x - net.center.to(x.dtype)) / net.half_extent
        out = net.mlp(torch.cat([xn, enc], -1))
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        prior = eye - prior_normal[:, :, None] * prior_normal[:, None, :]
        a = symmetric_from_tril(out[:, :6]) + prior
        rot, mags = frame_from_symmetric(a, prior_normal, net.eig_gap)
        ratio = mags / (0.5 * mags.sum(-1, keepdim=True) + 1e-12)
        mid = net.s_min + 0.5 * (net.s_max - net.s_min)
        size = (net.s_min + (net.s_max - net.s_min) * torch.sigmoid(out[:, 6])) / mid
        m = size * self.base_scale
        scales = m[:, None] * (net.r_min + (1.0 - net.r_min) * ratio)
        return rot, scales

    # ------------------------------------------------------------------ posing
    def pose_mesh(self, flame_inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """(V, 3) posed FLAME vertices of one frame (batch-1 kwargs)."""
        return self.flame(**flame_inputs).vertices[0]

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
        view of the capture sees the mirror image of the world light: S = diag(−1, 1, 1)).
        """
        if vertices is None:
            verts = self.pose_mesh(flame_inputs)
            if vertex_transform is not None:
                verts = vertex_transform(verts)
        else:
            verts = vertices
        R_p, T_p, k_p = surfel_frames(verts, self.faces)
        cs = canonical if canonical is not None else self.canonical_state(with_sdf=self.attributes == "mlp")
        b = self.surfels.binding
        Rcb, Tcb, kcb = self.R_c[b], self.T_c[b], self.k_c[b]
        Rpb, Tpb, kpb = R_p[b], T_p[b], k_p[b]
        local = (Rcb.transpose(-1, -2) @ (cs.means - Tcb)[..., None]).squeeze(-1) / kcb[:, None]
        means = kpb[:, None] * (Rpb @ local[..., None]).squeeze(-1) + Tpb
        q_rel = quat_multiply(matrix_to_quat(R_p)[b], quat_conjugate(self.q_c[b]))
        quats = quat_multiply(q_rel, cs.quats)
        scales = cs.scales * (kpb / kcb)[:, None]
        if correction is not None:
            with torch.no_grad():
                kappa, dirs, normal = self.sdf.curvature(cs.means.detach())
            res = correction(verts.detach(), b, cs.quats.detach(), normal, kappa, dirs, self.surfels.hair_mask())
            quats, scales = SurfelCorrection.apply(res, quats, scales)
        if camera_center_world is not None:
            view_w = means - camera_center_world.to(means)[None]
            view_w = view_w / view_w.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            # canonical view direction: R_relᵀ·v_w with R_rel = R_p·R_cᵀ of the bound triangle
            view_c = (Rcb @ (Rpb.transpose(-1, -2) @ view_w[..., None])).squeeze(-1)
        else:
            view_c = None
        if self.attributes == "free":
            coeffs = self.surfels.sh_coeffs()
            if view_c is None or self.surfels.sh_degree == 0:
                colors = eval_sh_colors(coeffs, torch.zeros_like(means), 0)
            else:
                colors = eval_sh_colors(coeffs, view_c, self.surfels.sh_degree)
            opac = self.surfels.opacities()
        else:
            if cs.feature is None or cs.sdf_grad is None:
                _, grad, feat = self.sdf.gradient(cs.means)
            else:
                grad, feat = cs.sdf_grad, cs.feature
            n = grad.detach() / grad.detach().norm(dim=-1, keepdim=True).clamp_min(1e-12)
            if view_c is None:
                view_c = -cs.rotation[..., 2].detach()
            colors, opac = self.appearance(cs.means, view_c, n, feat)
        colors = self.surfels.blend_color_prior(colors)
        if self.surfels.wrinkle is not None:
            colors = apply_wrinkles(colors, self.surfels.wrinkle, verts, self.canonical_vertices, self.faces, b)
        if shade and self.light is not None:
            colors = self._shade(colors, quats, Rpb[..., 2], light_transform)
        return PosedSurfels(means, quats, scales, opac, colors, verts)

    def world_normals(self, quats: torch.Tensor, triangle_normals: torch.Tensor) -> torch.Tensor:
        """Outward unit world normals of posed surfels, without gradient.

        quats: (N, 4) posed surfel rotations; triangle_normals: (N, 3) outward normals of their
        posed bound triangles (the third column of the surfel frame) -> (N, 3).
        """
        with torch.no_grad():
            n = quat_to_matrix(quat_normalize(quats.detach()))[..., 2]
            return orient_outward(n, triangle_normals.detach().to(n))

    def _shade(
        self, colors: torch.Tensor, quats: torch.Tensor, triangle_normals: torch.Tensor, light_transform: torch.Tensor | None = None
    ) -> torch.Tensor:
        assert self.light is not None
        n = self.world_normals(quats, triangle_normals)
        if light_transform is not None:
            n = n @ light_transform.to(n).T
        return colors * self.light.irradiance(n)

    def shade_colors(
        self, colors: torch.Tensor, quats: torch.Tensor, vertices: torch.Tensor, light_transform: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Albedo × world irradiance of posed surfels (identity when ``shading`` is "none").

        colors: (N, 3) albedo (``posed(..., shade=False).colors``); quats: (N, 4) posed, possibly
        corrected, surfel rotations; vertices: (V, 3) the posed mesh they are bound to;
        light_transform as in :meth:`posed` -> (N, 3).
        """
        if self.light is None:
            return colors
        R_p, _, _ = surfel_frames(vertices.detach(), self.faces)
        return self._shade(colors, quats, R_p[self.surfels.binding][..., 2], light_transform)

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
        **raster_kwargs: Any,
    ) -> tuple[SurfelRender, PosedSurfels]:
        """Pose and rasterize for one (unbatched) camera; raster_kwargs go to ``rasterize_surfels``;
        vertex_transform, shade and light_transform as in :meth:`posed`."""
        w2c = camera.w2c.to(self.canonical_vertices)
        centre = -(w2c[:3, :3].T @ w2c[:3, 3])
        p = self.posed(flame_inputs, centre, correction=correction, canonical=canonical, vertex_transform=vertex_transform,
                       shade=shade, light_transform=light_transform)  # fmt: skip
        img = rasterize_surfels(p.means, p.quats, p.scales, p.opacities, p.colors, camera, background, **raster_kwargs)
        return img, p

    # ------------------------------------------------------------------ canonical <-> world
    def rigid_transform(self, flame_inputs: dict[str, torch.Tensor], tol: float = 1e-5) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(R0 (3, 3), t (3,)) when the frame differs from canonical only by its global rotation and
        translation (checked numerically on the posed mesh: max vertex error ≤ tol × mesh size),
        else None. Then x_world = R0·(x_c − J0) + J0 + t with J0 = ``root_joint``."""
        from ..geometry.rotations import axis_angle_to_matrix

        with torch.no_grad():
            verts = self.pose_mesh(flame_inputs)
            R0 = axis_angle_to_matrix(flame_inputs["rotation"].reshape(1, 3).to(verts))[0]
            t = flame_inputs["translation"].reshape(3).to(verts)
            J0 = self.root_joint
            pred = (self.canonical_vertices - J0) @ R0.T + J0 + t
            size = float((self.canonical_vertices.max(0).values - self.canonical_vertices.min(0).values).norm())
            if float((pred - verts).norm(dim=-1).max()) > tol * size:
                return None
        return R0, t

    # ------------------------------------------------------------------ IO
    def _args(self) -> dict[str, Any]:
        return {
            "canonical_timestep": self.canonical_timestep,
            "sdf_args": _plain(self.sdf_args),
            "attributes": self.attributes,
            "app_args": _plain(self.app_args),
            "shape_args": _plain(self.shape_args),
            "n_surfels": len(self.surfels),
            "sh_degree": self.surfels.sh_degree,
            "shading": self.shading,
        }

    # ------------------------------------------------------------------ exposure gains
    def set_exposure_gains(self, gains: dict[tuple[int, int], Any]) -> None:
        """Store the per-training-frame exposure gains: {(timestep, camera index): (C,) gain},
        C = 1 or 3 (replaces any stored before; saved with the avatar)."""
        out: dict[tuple[int, int], torch.Tensor] = {}
        for (t, c), g in gains.items():
            v = torch.as_tensor(g, dtype=torch.float32).detach().cpu().reshape(-1).clone()
            if v.numel() not in (1, 3) or not bool(torch.isfinite(v).all()) or bool((v <= 0).any()):
                raise ValueError(f"exposure gain of timestep {t}, camera {c} must be 1 or 3 positive numbers, got {v.tolist()}")
            out[(int(t), int(c))] = v
        self.exposure_gains = out

    def exposure_gain(self, timestep: int, camera_index: int) -> torch.Tensor | None:
        """(C,) exposure gain of a training frame (on the avatar's device), or None when the frame has
        none stored (novel views and expressions: gain 1)."""
        g = self.exposure_gains.get((int(timestep), int(camera_index)))
        return None if g is None else g.to(self.device)

    def _exposure_plain(self) -> list[dict[str, Any]]:
        return [{"timestep": t, "camera": c, "gain": [float(x) for x in g]} for (t, c), g in sorted(self.exposure_gains.items())]

    def _flame_reference(self, path: Path) -> dict[str, Any] | None:
        """``{"file", "sha256"}`` referencing the workspace FLAME model when ``path`` lies in the
        workspace the avatar was built from (``WS/init/flame_model.npz``), else None."""
        src = self.flame_source
        if src is None or src.parent.name != "init" or not src.is_file():
            return None
        root = src.parent.parent
        if not (root / "data").is_dir():
            return None
        try:
            path.resolve().relative_to(root)
        except ValueError:
            return None
        return {"file": src.relative_to(root).as_posix(), "sha256": flame_model_sha256(self.model_data)}

    def save(self, path: str | Path, *, embed_flame: bool | None = None) -> Path:
        """Write the avatar file atomically: constructor data, parameters, state dict without the
        FLAME buffers, and the FLAME model, as a safetensors file (see ``docs/workspace.md``).

        embed_flame: True stores the FLAME model arrays in the file (self-contained, as bundles
        are); False/None (default) stores a reference to the workspace's ``init/flame_model.npz``
        with its content hash when the file is written inside the workspace the avatar was built
        from, and embeds the model otherwise.
        """
        from .. import __version__
        from ..serialization import save_file

        p = Path(path)
        state = {k: v.detach().cpu() for k, v in self.state_dict().items() if not k.startswith("flame.")}
        blob: dict[str, Any] = {
            "format": AVATAR_FORMAT,
            "kind": AVATAR_KIND,
            "version": __version__,
            "args": self._args(),
            "params": _plain(self.params),
            "state": state,
        }
        ref = None if embed_flame else self._flame_reference(p)
        if ref is None:
            blob["flame"] = _plain(self.model_data)
        else:
            blob["flame_ref"] = ref
        if self.exposure_gains:
            blob["exposure_gains"] = self._exposure_plain()
        return save_file(p, blob, AVATAR_KIND, AVATAR_FORMAT)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device = "cpu") -> Avatar:
        """Read a file written by :meth:`save`; InputError when it is not a readable avatar
        (UnsafeFileError for an old pickle avatar file, which is refused without being loaded)."""
        from ..serialization import load_file

        p = Path(path)
        blob, _ = load_file(p, AVATAR_KIND, AVATAR_FORMAT, "avatar file")
        if not isinstance(blob, dict) or blob.get("kind") != AVATAR_KIND:
            raise InputError(p, "not a sage avatar file")
        source: Path | None = None
        try:
            args = blob["args"]
            if "flame_ref" in blob:
                model_data, source = _resolve_flame_ref(p, blob["flame_ref"])
            else:
                model_data = FlameModelData(**blob["flame"])
            params = FlameParams(**blob["params"])
            state = blob["state"]
            surf_state = {k[len("surfels."):]: v for k, v in state.items() if k.startswith("surfels.")}
            surfels = SurfelSet.from_state_dict(surf_state)
            obj = cls(
                model_data, params, args["canonical_timestep"], surfels, args["sdf_args"], args["attributes"],
                args["app_args"], args["shape_args"] or None, base_scale=state["base_scale"],
                shading=args.get("shading", "none"),
            )  # fmt: skip
            missing, unexpected = obj.load_state_dict(state, strict=False)
            obj.set_exposure_gains({(e["timestep"], e["camera"]): e["gain"] for e in blob.get("exposure_gains", [])})
        except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as e:
            raise InputError(p, f"malformed avatar file: {e}") from None
        bad = [k for k in missing if not k.startswith("flame.")]
        if bad or unexpected:
            raise InputError(p, f"avatar state does not match: missing {bad[:5]}, unexpected {list(unexpected)[:5]}")
        obj.flame_source = source
        return obj.to(device)


def flame_model_sha256(md: FlameModelData) -> str:
    """Content hash of a FLAME model: every field's name, dtype, shape and bytes, in field order."""
    import hashlib

    h = hashlib.sha256()
    for f in dataclasses.fields(md):
        v = getattr(md, f.name)
        items = sorted(v.items()) if isinstance(v, dict) else [("", v)]
        for key, x in items:
            h.update(f"{f.name}\0{key}\0".encode())
            if isinstance(x, np.ndarray):
                a = np.ascontiguousarray(x)
                h.update(f"{a.dtype.str}{a.shape}".encode())
                h.update(a.tobytes())
            else:
                h.update(repr(x).encode())
    return h.hexdigest()


def _resolve_flame_ref(path: Path, ref: dict[str, Any]) -> tuple[FlameModelData, Path]:
    """Find and check the FLAME model an avatar file references: ``ref["file"]`` relative to one of
    the folders above the avatar file (its workspace), with the recorded content hash."""
    from ..flame import load_flame_model

    rel = str(ref["file"])
    if Path(rel).is_absolute() or ".." in Path(rel).parts:
        raise InputError(path, f"references the FLAME model {rel!r} outside its workspace")
    for anc in list(path.resolve().parents)[:FLAME_REF_SEARCH_DEPTH]:
        cand = anc / rel
        if cand.is_file():
            md = load_flame_model(cand)
            if flame_model_sha256(md) != ref.get("sha256"):
                raise InputError(path, f"the FLAME model it references ({cand}) changed since the avatar was saved; "
                                       "re-run the stage that wrote the avatar")
            return md, cand
    raise InputError(path, f"references the workspace FLAME model {rel}, which is not found in the folders above it; "
                           "keep avatar files inside their workspace, or export a self-contained bundle "
                           "(`sage export WS --bundle`)")


def _rigid_world_from_canonical(params: FlameParams, row: int, root_joint: torch.Tensor) -> np.ndarray:
    """(4, 4) x_world = R0·(x_c − J0) + J0 + t of FLAME row ``row``."""
    from ..geometry.rotations import axis_angle_to_matrix

    R0 = axis_angle_to_matrix(torch.as_tensor(params.rotation[row], dtype=torch.float64)[None])[0].numpy()
    t = np.asarray(params.translation[row], np.float64)
    J0 = root_joint.detach().cpu().double().numpy()
    M = np.eye(4)
    M[:3, :3] = R0
    M[:3, 3] = J0 - R0 @ J0 + t
    return M


def _clip_cameras_at_canonical(data: Any, params: FlameParams, ct: int, root_joint: torch.Tensor, world_from_mesh: np.ndarray,
                               limit: int = 16) -> list[Camera]:
    """A head-turn clip's camera, once per training timestep (at most ``limit``, evenly spaced), moved
    into the canonical timestep's world so that it sees the head as it did in its own frame:
    w2c' = w2c·W_t·W_ct⁻¹ with W the rigid world-from-canonical map of each timestep."""
    frames = sorted({f.timestep: f for f in data.train}.items())
    if len(frames) > limit:
        keep = np.unique(np.linspace(0, len(frames) - 1, limit).round().astype(int))
        frames = [frames[i] for i in keep]
    inv_ct = np.linalg.inv(world_from_mesh)
    out: list[Camera] = []
    for t, fr in frames:
        W = _rigid_world_from_canonical(params, params.row_of(t), root_joint)
        cam = fr.camera
        out.append(Camera(cam.K.copy(), np.asarray(cam.w2c, np.float64) @ W @ inv_ct, cam.width, cam.height, cam.index, cam.name))
    return out


def canonical_rays_rigid(
    origins: torch.Tensor, dirs: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays to canonical space for a rigidly moved frame: x_c = R0ᵀ(x_w − t − J0) + J0, d_c = R0ᵀ d_w.

    origins, dirs: (R, 3); R0: (3, 3); t, J0: (3,). Distances along the rays are preserved.
    """
    o = (origins - t - J0) @ R0 + J0
    return o, dirs @ R0


def canonical_to_world_rigid(x: torch.Tensor, R0: torch.Tensor, t: torch.Tensor, J0: torch.Tensor) -> torch.Tensor:
    """Inverse of the rigid map: x_w = R0(x_c − J0) + J0 + t. x: (R, 3)."""
    return (x - J0) @ R0.T + J0 + t
