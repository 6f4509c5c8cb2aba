"""Posing an :class:`Avatar` with the stretch- and curvature-driven surfel correction (SAGE §3).

:class:`CorrectedPosing` owns a :class:`SurfelCorrection` built once from the avatar's canonical mesh
(neighbour sets from a centroid ball query) and poses the surfels of a frame as
:meth:`Avatar.posed` does, then turns and rescales them:

    q' = q ⊗ dq,   s' = s · factor        (see :mod:`sage_core.avatar.correction`)

The correction needs, at every surfel's canonical centre, the SDF normal and the principal
curvatures and directions. In phase 2 the SDF is frozen, so these depend only on the canonical
centres: they are computed once and cached, and recomputed only for the surfels whose canonical
centre moved by more than ``refresh_tolerance`` since (or for all of them after a rebinding changed
the surfel count). Hair surfels (region ``hair``) and surfels whose bound triangle has no valid
neighbours are left untouched. The correction is geometric: it is applied without gradient to the
correction terms themselves (the correction quaternion and scale factors are constants of the step),
while the gradients of the uncorrected surfel parameters flow through ``q ⊗ dq`` and ``s · factor``.

The canonical inputs of the surfels' attribute networks are frozen too while the surfel centres
(``mu_loc``) and the SDF's hash grid take no gradient, as in phase 2 by default: the centres, the
SDF value, gradient and feature there, the hash encoding the shape network reads and the bound
triangles' normals (:class:`FrozenCanonical`). :meth:`CorrectedPosing.canonical_state` then computes
them once and reuses them until one of the tensors they come from is replaced or modified in place
(the centres, the binding, the canonical triangle frames, any SDF parameter or buffer), and only
the trained shape network runs per call. The values are those of the uncached path; the difference
is that no gradient reaches ``mu_loc`` or the SDF table through them, which is why the cache is
only used when neither takes one (or grad mode is off).

With ``enabled=False`` (``--correction off``) :meth:`CorrectedPosing.posed` returns exactly
``Avatar.posed(...)``. With an avatar whose ``shading`` is on, the colours are shaded with the
corrected surfel normals (:meth:`Avatar.shade_colors` after the correction); ``shade=False`` returns
the albedo.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..geometry.rotations import matrix_to_quat
from .correction import CorrectionResult, SurfelCorrection
from .model import Avatar, CanonicalSurfels, PosedSurfels
from .posing import shape_forward


def median_edge_length(vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """Median edge length of a mesh. vertices: (V, 3); faces: (F, 3)."""
    tri = vertices[faces.long()]
    e = torch.cat([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], 0)
    return float(e.norm(dim=-1).median())


@dataclass
class CurvatureCache:
    """SDF geometry at the surfels' canonical centres.

    means: (N, 3) centres it was computed at; kappa: (N, 2) principal curvatures (1/m), κ1 ≥ κ2;
    dirs: (N, 2, 3) principal directions; normal: (N, 3) unit SDF normal.
    """

    means: torch.Tensor
    kappa: torch.Tensor
    dirs: torch.Tensor
    normal: torch.Tensor


@dataclass
class FrozenCanonical:
    """Canonical inputs of the attribute networks that do not change while the surfel centres and the
    SDF are frozen (all detached).

    key: the identity and version of every tensor they depend on; sources: those tensors (held so
    that their identities stay unique); means: (N, 3) canonical centres; prior_normal: (N, 3) normals
    of the bound canonical triangles; encoding: (N, L·F) SDF hash features at the centres (mlp
    attributes, else None); sdf: (N,); sdf_grad: (N, 3); feature: (N, F_z) at the centres.
    """

    key: tuple
    sources: tuple[torch.Tensor, ...]
    means: torch.Tensor
    prior_normal: torch.Tensor
    encoding: torch.Tensor | None
    sdf: torch.Tensor
    sdf_grad: torch.Tensor
    feature: torch.Tensor


def default_radius_edges(attributes: str) -> float:
    """The correction's neighbourhood radius in median edge lengths when none is set: 1.0 for
    surfels whose shapes come from the attribute networks, 2.0 for free surfels, which grow about
    twice as large, so that the neighbourhood covers their footprint (on the small benchmark 1.0
    cost the free-surfel avatar 0.5 dB against 2.0, and gained the network avatar 0.0005 of LPIPS;
    docs/results.md)."""
    return 1.0 if attributes == "mlp" else 2.0


class CorrectedPosing:
    """Surfel correction glue for an :class:`Avatar` (see the module doc).

    Args:
        avatar: the avatar (its SDF should be frozen while the cache is used).
        enabled: False gives the uncorrected ``Avatar.posed``.
        radius: ball-query radius (m) of the triangle neighbour sets; default ``radius_edges`` times
            the canonical mesh's median edge length.
        radius_edges: see ``radius``; None picks :func:`default_radius_edges` for the avatar's
            attributes.
        max_neighbours: neighbours kept per triangle.
        w_s: curvature damping length (m).
        min_neighbours: triangles with fewer valid neighbours are not corrected.
        umbilic_tol: |κ1 − κ2| (1/m) above which the rotation applies in full.
        anisotropy_tol: relative stretch anisotropy above which the rotation applies in full (0:
            always; see :class:`~sage_core.avatar.correction.SurfelCorrection`).
        stretch_range: clamp of the relative stretch.
        refresh_tolerance: a cached curvature is recomputed when its surfel's canonical centre moved
            farther than this (m); default the SDF's finest hash-grid cell size / 4.
        use_curvature: False applies only the stretch part (no rotation, no curvature damping).
        mode: ``"curvature"`` (the paper's rotation towards the principal curvature directions) or
            ``"affine"`` (each surfel's ellipse mapped exactly by the neighbourhood's stretch); see
            :class:`~sage_core.avatar.correction.SurfelCorrection`.
    """

    def __init__(
        self,
        avatar: Avatar,
        enabled: bool = True,
        *,
        radius: float | None = None,
        radius_edges: float | None = None,
        max_neighbours: int = 16,
        w_s: float = 0.0,
        min_neighbours: int = 1,
        umbilic_tol: float = 1.0,
        anisotropy_tol: float = 0.0,
        stretch_range: tuple[float, float] = (0.25, 4.0),
        refresh_tolerance: float | None = None,
        use_curvature: bool = True,
        mode: str = "affine",
    ) -> None:
        self.avatar = avatar
        self.enabled = bool(enabled)
        self.use_curvature = bool(use_curvature)
        verts = avatar.canonical_vertices.detach()
        if radius is None:
            edges = default_radius_edges(avatar.attributes) if radius_edges is None else float(radius_edges)
            radius = edges * median_edge_length(verts, avatar.faces)
        self.radius = float(radius)
        self.correction = SurfelCorrection.from_mesh(
            verts, avatar.faces, self.radius, max_neighbours, w_s=w_s, min_neighbours=min_neighbours,
            stretch_range=stretch_range, umbilic_tol=umbilic_tol, anisotropy_tol=anisotropy_tol, enabled=self.enabled,
            mode=mode,
        )  # fmt: skip
        if refresh_tolerance is None:
            refresh_tolerance = 0.25 * float(avatar.sdf.default_fd_step())
        self.refresh_tolerance = float(refresh_tolerance)
        self._cache: CurvatureCache | None = None
        self.recomputed = 0
        self._frozen: FrozenCanonical | None = None

    # ------------------------------------------------------------------ SDF geometry
    @torch.no_grad()
    def geometry(self, means: torch.Tensor) -> CurvatureCache:
        """Curvatures, directions and normals at canonical centres means: (N, 3), from the cache
        where the centres have not moved by more than ``refresh_tolerance``."""
        means = means.detach()
        c = self._cache
        if c is None or c.means.shape != means.shape or c.means.device != means.device:
            kappa, dirs, normal = self.avatar.sdf.curvature(means)
            self._cache = CurvatureCache(means.clone(), kappa, dirs, normal)
            self.recomputed += means.shape[0]
            return self._cache
        moved = (means - c.means).norm(dim=-1) > self.refresh_tolerance
        if bool(moved.any()):
            idx = moved.nonzero().squeeze(-1)
            kappa, dirs, normal = self.avatar.sdf.curvature(means[idx])
            c.means[idx] = means[idx]
            c.kappa[idx] = kappa.to(c.kappa)
            c.dirs[idx] = dirs.to(c.dirs)
            c.normal[idx] = normal.to(c.normal)
            self.recomputed += int(idx.numel())
        return c

    def cache_state(self) -> dict[str, torch.Tensor] | None:
        """The curvature cache as tensors (for exact resumes), or None when empty."""
        c = self._cache
        if c is None:
            return None
        return {"means": c.means.clone(), "kappa": c.kappa.clone(), "dirs": c.dirs.clone(), "normal": c.normal.clone()}

    def load_cache_state(self, state: dict[str, torch.Tensor] | None) -> None:
        """Restore :meth:`cache_state` (None empties the cache)."""
        if state is None:
            self._cache = None
            return
        dev = self.avatar.device
        self._cache = CurvatureCache(*(state[k].to(dev).clone() for k in ("means", "kappa", "dirs", "normal")))

    def invalidate(self) -> None:
        """Drop the cache (e.g. after the SDF changed)."""
        self._cache = None

    # ------------------------------------------------------------------ posing
    def canonical_state(self) -> CanonicalSurfels:
        """The avatar's canonical surfels with the SDF value, gradient and feature at the centres
        detached (the SDF is frozen; gradients still reach the surfels and the attribute heads).

        While :meth:`frozen_inputs_apply` holds, the centres and the SDF quantities come from
        :meth:`frozen_inputs` (same values, no gradient to ``mu_loc``, which takes none)."""
        av = self.avatar
        if not self.frozen_inputs_apply():
            cs = av.canonical_state(with_sdf=False)
            sdf, grad, feat = av.sdf.gradient(cs.means.detach())
            cs.sdf, cs.sdf_grad, cs.feature = sdf.detach(), grad.detach(), feat.detach()
            return cs
        fz = self.frozen_inputs()
        if fz.encoding is not None:
            rot, scales = shape_forward(av, fz.means, fz.prior_normal, fz.encoding)
            cs = CanonicalSurfels(fz.means, matrix_to_quat(rot), scales, rot)
        else:
            cs = av.canonical_state(with_sdf=False)
        cs.sdf, cs.sdf_grad, cs.feature = fz.sdf, fz.sdf_grad, fz.feature
        return cs

    def frozen_inputs_apply(self) -> bool:
        """Whether :meth:`canonical_state` may use :meth:`frozen_inputs`: grad mode is off, or neither the
        surfel offsets ``mu_loc`` nor the SDF's hash table require a gradient."""
        av = self.avatar
        if not torch.is_grad_enabled():
            return True
        return not av.surfels.mu_loc.requires_grad and not any(p.requires_grad for p in av.sdf.encoding.parameters())

    def _frozen_sources(self) -> tuple[torch.Tensor, ...]:
        av = self.avatar
        s = av.surfels
        return (s.mu_loc, s.binding, av.R_c, av.T_c, av.k_c, *av.sdf.parameters(), *av.sdf.buffers())

    def frozen_inputs(self) -> FrozenCanonical:
        """The :class:`FrozenCanonical` inputs of the current avatar state, computed when a tensor they
        depend on was replaced or modified in place since the last call (see the module doc)."""
        av = self.avatar
        sources = self._frozen_sources()
        key = (av.attributes, *((id(t), t._version, t.data_ptr(), tuple(t.shape), t.dtype) for t in sources))
        fz = self._frozen
        if fz is not None and fz.key == key:
            return fz
        with torch.no_grad():
            cs = av.canonical_state(with_sdf=False)
            means = cs.means.detach()
            enc = av.sdf.encoding(means).detach() if av.attributes == "mlp" else None
            sdf, grad, feat = av.sdf.gradient(means)
        prior = av.R_c[av.surfels.binding][..., 2].detach()
        self._frozen = FrozenCanonical(key, sources, means, prior, enc, sdf.detach(), grad.detach(), feat.detach())
        return self._frozen

    def correct(self, vertices: torch.Tensor, canonical: CanonicalSurfels) -> CorrectionResult:
        """Correction of every surfel for the posed mesh vertices: (V, 3) (no gradient)."""
        av = self.avatar
        with torch.no_grad():
            geo = self.geometry(canonical.means)
            kappa = geo.kappa if self.use_curvature else None
            dirs = geo.dirs if self.use_curvature else None
            return self.correction(
                vertices.detach(), av.surfels.binding, canonical.quats.detach(), geo.normal, kappa, dirs, av.surfels.hair_mask(),
                canonical.scales.detach(),
            )  # fmt: skip

    def posed(
        self,
        flame_inputs: dict[str, torch.Tensor],
        camera_center_world: torch.Tensor | None,
        canonical: CanonicalSurfels | None = None,
        vertices: torch.Tensor | None = None,
        shade: bool = True,
    ) -> tuple[PosedSurfels, CorrectionResult | None]:
        """Posed (and, when enabled, corrected) surfels of one frame and the correction applied.

        Arguments as :meth:`Avatar.posed`; without ``canonical`` it is :meth:`canonical_state` (frozen
        SDF); shade: with the avatar's shading on, colours are albedo × irradiance at the corrected
        normals (False: the albedo). Returns (surfels, correction or None when disabled).
        """
        av = self.avatar
        cs = canonical if canonical is not None else self.canonical_state()
        if not self.enabled:
            return av.posed(flame_inputs, camera_center_world, canonical=cs, vertices=vertices, shade=shade), None
        p = av.posed(flame_inputs, camera_center_world, canonical=cs, vertices=vertices, shade=False)
        res = self.correct(p.vertices, cs)
        quats, scales = SurfelCorrection.apply(res, p.quats, p.scales)
        colors = av.shade_colors(p.colors, quats, p.vertices) if shade else p.colors
        return PosedSurfels(p.means, quats, scales, p.opacities, colors, p.vertices), res
