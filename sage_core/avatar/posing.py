"""Posing an :class:`~sage_core.avatar.model.Avatar`: canonical surfels, FLAME posing, the rigid map.

Canonical state (:func:`canonical_state` -> :class:`CanonicalSurfels`): every surfel's canonical
centre x_c = k_c·R_c·μ_loc + T_c on its bound triangle b, and its rotation and in-plane scales: in
"free" mode from the per-surfel ``q_loc`` / ``s_loc``, in "mlp" mode from the shape network on the
hash-grid features at x_c, whose symmetric matrix is added to the flat-on-triangle prior
I − n_b·n_bᵀ (:func:`shape_forward`).

Posing (:func:`posed` -> :class:`PosedSurfels`): a frame's FLAME mesh (:func:`pose_mesh`) moves the
surfels through the canonical (R_c, T_c, k_c) and posed (R_p, T_p, k_p) triangle frames (docs/formats.md
§6, surfel convention):

    μ = k_p·R_p·R_cᵀ·(x_c − T_c)/k_c + T_p,    R = R_p·R_cᵀ·R_canon,    s = s_c·k_p/k_c

The part that depends on the frame only (the posed mesh and its triangles' frames) is a
:class:`PosedMesh` (:func:`posed_mesh`), which a caller that poses one frame many times (a trainer)
may keep. Posing then applies the optional surfel-correction hook (a :class:`SurfelCorrection`,
phase 2), computes the colours for the camera centre (view direction mapped to canonical space by the
bound triangle's rotation), the phase-2 colour prior and wrinkle shading, and the optional
world-light shading (:func:`sage_core.avatar.shading.shade`).

Rigid frames (:func:`rigid_transform`): a frame that differs from canonical only in global rotation
and translation maps by the rigid head map of :mod:`sage_core.geometry.rigid`.

Shapes: N surfels, V mesh vertices, F faces; FLAME inputs are ``FlameModel.forward`` keyword
arguments of batch 1 (``expr`` (1, E), ``rotation`` (1, 3), ...).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterator

import torch

from ..fields.shape import frame_from_symmetric, symmetric_from_tril
from ..flame.frames import surfel_frames
from ..flame.params import FlameParams
from ..geometry.rigid import canonical_to_world, rigid_from_flame
from ..geometry.rotations import matrix_to_quat, quat_conjugate, quat_multiply, quat_normalize, quat_to_matrix
from ..geometry.sh import eval_sh_colors
from .correction import SurfelCorrection
from .shading import shade
from .wrinkles import apply_wrinkles

if TYPE_CHECKING:
    from .model import Avatar

FLAME_KEYS: tuple[str, ...] = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
"""The per-frame FLAME parameters of a :class:`FlameParams` row."""


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
    app_encoding: (N, L·F) the appearance network's hash-grid features at the centres when the shape
    network read them (:attr:`Avatar.shape_reads_detail`), so the appearance network reuses them.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    rotation: torch.Tensor
    sdf: torch.Tensor | None = None
    sdf_grad: torch.Tensor | None = None
    feature: torch.Tensor | None = None
    app_encoding: torch.Tensor | None = None

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
    out: dict[str, torch.Tensor] = {k: p[k][row : row + 1] for k in FLAME_KEYS}
    if p["shape"].numel():
        out["shape"] = p["shape"][None]
    if "static_offset" in p:
        out["static_offset"] = p["static_offset"]
    if "dynamic_offset" in p:
        out["dynamic_offset"] = p["dynamic_offset"][row : row + 1]
    return out


def identity_inputs(avatar: Avatar, params: FlameParams, row: int) -> dict[str, torch.Tensor]:
    """FLAME kwargs (batch 1) of row ``row`` of any FlameParams (e.g. a reenactment sequence) on the
    avatar's device; the avatar's own shape and static offset replace the sequence's."""
    dev = avatar.canonical_vertices.device
    out = params_row_inputs(params, row, dev)
    own = avatar.params.to_torch(dev)
    out["shape"] = own["shape"][None]
    if "static_offset" in own:
        out["static_offset"] = own["static_offset"]
    else:
        out.pop("static_offset", None)
    return out


# ---------------------------------------------------------------------- canonical state
def canonical_state(avatar: Avatar, with_sdf: bool = False, create_graph: bool = False) -> CanonicalSurfels:
    """Canonical centres, rotations and scales of all surfels (see :class:`CanonicalSurfels`).

    with_sdf: also evaluate the SDF, its gradient (differentiable with ``create_graph``) and the
    geometry feature at the centres; in mlp mode the hash encoding is shared with the shape network.
    """
    s = avatar.surfels
    b = s.binding
    Rb, Tb, kb = avatar.R_c[b], avatar.T_c[b], avatar.k_c[b]
    means = kb[:, None] * (Rb @ s.mu_loc[..., None]).squeeze(-1) + Tb
    sdf = grad = feature = app_enc = None
    if avatar.attributes == "free":
        quats = quat_multiply(avatar.q_c[b], quat_normalize(s.q_loc))
        scales = kb[:, None] * torch.exp(s.s_loc)
        rot = quat_to_matrix(quats)
        if with_sdf:
            sdf, grad, feature = avatar.sdf.gradient(means, create_graph=create_graph)
    else:
        if with_sdf:
            sdf, grad, feature, enc = sdf_with_encoding(avatar, means, create_graph)
        else:
            enc = avatar.sdf.encoding(means)
        if avatar.shape_reads_detail:
            app_enc = avatar.appearance.grid(means)
        rot, scales = shape_forward(avatar, means, Rb[..., 2], enc, app_enc)
        quats = matrix_to_quat(rot)
    return CanonicalSurfels(means, quats, scales, rot, sdf, grad, feature, app_enc)


def sdf_with_encoding(
    avatar: Avatar, x: torch.Tensor, create_graph: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The avatar's SDFNetwork.forward and its gradient at x (M, 3), also returning the hash encoding
    of x: sdf (M,), grad (M, 3), feature (M, F_z), encoding (M, L·F) (the fused native path on CPU,
    :meth:`SDFNetwork.gradient_with_encoding`)."""
    return avatar.sdf.gradient_with_encoding(x, create_graph)


def shape_forward(
    avatar: Avatar, x: torch.Tensor, prior_normal: torch.Tensor, enc: torch.Tensor, app_enc: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The avatar's shape network with the flat-on-triangle prior (mlp mode).

    x, prior_normal: (N, 3); enc: (N, L·F) hash features at x -> R (N, 3, 3), s (N, 2); the size
    multiplier is relative to ``avatar.base_scale`` (N,). With :attr:`Avatar.shape_reads_detail` the
    appearance grid's features at x join ``enc`` (``app_enc`` (N, L·F) when already computed).
    """
    net = avatar.shape
    assert net is not None
    if avatar.shape_reads_detail:
        enc = torch.cat([enc, avatar.appearance.grid(x) if app_enc is None else app_enc], -1)
    xn = (x - net.center.to(x.dtype)) / net.half_extent
    out = net.mlp(torch.cat([xn, enc], -1))
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    prior = eye - prior_normal[:, :, None] * prior_normal[:, None, :]
    a = symmetric_from_tril(out[:, :6]) + prior
    rot, mags = frame_from_symmetric(a, prior_normal, net.eig_gap)
    ratio = mags / (0.5 * mags.sum(-1, keepdim=True) + 1e-12)
    mid = net.s_min + 0.5 * (net.s_max - net.s_min)
    size = (net.s_min + (net.s_max - net.s_min) * torch.sigmoid(out[:, 6])) / mid
    m = size * avatar.base_scale
    scales = m[:, None] * (net.r_min + (1.0 - net.r_min) * ratio)
    return rot, scales


# ---------------------------------------------------------------------- posing
@dataclass(frozen=True)
class PosedMesh:
    """A frame's posed mesh and what posing needs of each of its triangles (the frame-only part of
    :func:`posed`).

    vertices: (V, 3); R: (F, 3, 3), T: (F, 3), k: (F,) the triangles' surfel frames (R_p, T_p, k_p);
    ratio: (F,) k_p/k_c; quat: (F, 4) q(R_p) ⊗ q̄_c, the canonical → posed rotation R_p·R_cᵀ as a unit
    quaternion (wxyz); shaped: (V, 3) the frame's expression-shaped mesh (FLAME's ``v_shaped``, before
    pose correctives and skinning) when the mesh came from FLAME inputs, else None.
    """

    vertices: torch.Tensor
    R: torch.Tensor
    T: torch.Tensor
    k: torch.Tensor
    ratio: torch.Tensor
    quat: torch.Tensor
    shaped: torch.Tensor | None = None


def pose_mesh(avatar: Avatar, flame_inputs: dict[str, torch.Tensor]) -> torch.Tensor:
    """(V, 3) posed FLAME vertices of one frame (batch-1 kwargs)."""
    return avatar.flame(**flame_inputs).vertices[0]


def posed_mesh(
    avatar: Avatar, flame_inputs: dict[str, torch.Tensor], vertex_transform: Callable[[torch.Tensor], torch.Tensor] | None = None
) -> PosedMesh:
    """The :class:`PosedMesh` of one frame's FLAME mesh (batch-1 kwargs), with ``vertex_transform``
    (V, 3) -> (V, 3) applied as in :func:`posed`."""
    out = avatar.flame(**flame_inputs)
    verts = out.vertices[0]
    return mesh_map(avatar, verts if vertex_transform is None else vertex_transform(verts), out.v_shaped[0].detach())


def mesh_map(avatar: Avatar, vertices: torch.Tensor, shaped: torch.Tensor | None = None) -> PosedMesh:
    """The :class:`PosedMesh` of posed vertices (V, 3) of the avatar's mesh (differentiable in them);
    shaped: the frame's expression-shaped mesh (V, 3) when known."""
    R_p, T_p, k_p = surfel_frames(vertices, avatar.faces)
    quat = quat_multiply(matrix_to_quat(R_p), quat_conjugate(avatar.q_c))
    return PosedMesh(vertices, R_p, T_p, k_p, k_p / avatar.k_c, quat, shaped)


def wrinkle_meshes(avatar: Avatar, vertices: torch.Tensor, shaped: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """(deformed (V, 3), rest (V, 3)): the meshes wrinkle shading compares for a frame, by the
    avatar's ``wrinkle_basis`` (:mod:`sage_core.avatar.wrinkles`): the frame's expression-shaped mesh
    ``shaped`` against the canonical frame's, or the posed ``vertices`` against the canonical mesh for
    ``posed`` and when ``shaped`` is None (a mesh given as vertices alone, without FLAME inputs)."""
    if avatar.wrinkle_basis == "expression" and shaped is not None:
        return shaped, avatar.canonical_shaped
    return vertices, avatar.canonical_vertices


def posed(
    avatar: Avatar,
    flame_inputs: dict[str, torch.Tensor],
    camera_center_world: torch.Tensor | None,
    correction: SurfelCorrection | None = None,
    canonical: CanonicalSurfels | None = None,
    vertices: torch.Tensor | None = None,
    vertex_transform: Callable[[torch.Tensor], torch.Tensor] | None = None,
    shade_colors: bool = True,
    light_transform: torch.Tensor | None = None,
    mesh: PosedMesh | None = None,
) -> PosedSurfels:
    """World-space surfels of one frame (the arguments of :meth:`Avatar.posed`; ``shade_colors`` is
    its ``shade``)."""
    if mesh is None:
        mesh = posed_mesh(avatar, flame_inputs, vertex_transform) if vertices is None else mesh_map(avatar, vertices)
    verts = mesh.vertices
    cs = canonical if canonical is not None else canonical_state(avatar, with_sdf=avatar.attributes == "mlp")
    b = avatar.surfels.binding
    Rcb, Tcb, kcb = avatar.R_c[b], avatar.T_c[b], avatar.k_c[b]
    Rpb, Tpb, kpb = mesh.R[b], mesh.T[b], mesh.k[b]
    local = (Rcb.transpose(-1, -2) @ (cs.means - Tcb)[..., None]).squeeze(-1) / kcb[:, None]
    means = kpb[:, None] * (Rpb @ local[..., None]).squeeze(-1) + Tpb
    quats = quat_multiply(mesh.quat[b], cs.quats)
    scales = cs.scales * mesh.ratio[b][:, None]
    if correction is not None:
        with torch.no_grad():
            kappa, dirs, normal = avatar.sdf.curvature(cs.means.detach())
        res = correction(verts.detach(), b, cs.quats.detach(), normal, kappa, dirs, avatar.surfels.hair_mask())
        quats, scales = SurfelCorrection.apply(res, quats, scales)
    if camera_center_world is not None:
        view_w = means - camera_center_world.to(means)[None]
        view_w = view_w / view_w.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        # canonical view direction: R_relᵀ·v_w with R_rel = R_p·R_cᵀ of the bound triangle
        view_c = (Rcb @ (Rpb.transpose(-1, -2) @ view_w[..., None])).squeeze(-1)
    else:
        view_c = None
    if avatar.attributes == "free":
        coeffs = avatar.surfels.sh_coeffs()
        if view_c is None or avatar.surfels.sh_degree == 0:
            colors = eval_sh_colors(coeffs, torch.zeros_like(means), 0)
        else:
            colors = eval_sh_colors(coeffs, view_c, avatar.surfels.sh_degree)
        opac = avatar.surfels.opacities()
    else:
        if cs.feature is None or cs.sdf_grad is None:
            _, grad, feat = avatar.sdf.gradient(cs.means)
        else:
            grad, feat = cs.sdf_grad, cs.feature
        n = grad.detach() / grad.detach().norm(dim=-1, keepdim=True).clamp_min(1e-12)
        if view_c is None:
            view_c = -cs.rotation[..., 2].detach()
        colors, opac = avatar.appearance(cs.means, view_c, n, feat, grid_features=cs.app_encoding)
        opac = avatar.surfels.offset_opacities(opac)
    colors = avatar.surfels.blend_color_prior(colors)
    opac, scales = avatar.surfels.apply_unseen_floor(opac, scales)
    if avatar.surfels.wrinkle is not None:
        deformed, rest = wrinkle_meshes(avatar, verts, mesh.shaped)
        colors = apply_wrinkles(colors, avatar.surfels.wrinkle, deformed, rest, avatar.faces, b)
    if shade_colors and avatar.light is not None:
        colors = shade(avatar.light, colors, quats, Rpb[..., 2], light_transform)
    return PosedSurfels(means, quats, scales, opac, colors, verts)


# ---------------------------------------------------------------------- rigid frames
def rigid_transform(
    avatar: Avatar, flame_inputs: dict[str, torch.Tensor], tol: float = 1e-5
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(R0 (3, 3), t (3,)) when the frame differs from canonical only by its global rotation and
    translation (checked numerically on the posed mesh: max vertex error ≤ tol × mesh size), else
    None. Then x_world = R0·(x_c − J0) + J0 + t with J0 = ``avatar.root_joint``
    (:func:`sage_core.geometry.rigid.canonical_to_world`)."""
    with torch.no_grad():
        verts = pose_mesh(avatar, flame_inputs)
        R0, t = rigid_from_flame(flame_inputs["rotation"].to(verts), flame_inputs["translation"].to(verts))
        cv = avatar.canonical_vertices
        pred = canonical_to_world(cv, R0, t, avatar.root_joint)
        size = float((cv.max(0).values - cv.min(0).values).norm())
        if float((pred - verts).norm(dim=-1).max()) > tol * size:
            return None
    return R0, t
