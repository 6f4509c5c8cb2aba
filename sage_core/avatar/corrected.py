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

With ``enabled=False`` (``--correction off``) :meth:`CorrectedPosing.posed` returns exactly
``Avatar.posed(...)``. With an avatar whose ``shading`` is on, the colours are shaded with the
corrected surfel normals (:meth:`Avatar.shade_colors` after the correction); ``shade=False`` returns
the albedo.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .correction import CorrectionResult, SurfelCorrection
from .model import Avatar, CanonicalSurfels, PosedSurfels


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


class CorrectedPosing:
    """Surfel correction glue for an :class:`Avatar` (see the module doc).

    Args:
        avatar: the avatar (its SDF should be frozen while the cache is used).
        enabled: False gives the uncorrected ``Avatar.posed``.
        radius: ball-query radius (m) of the triangle neighbour sets; default ``radius_edges`` times
            the canonical mesh's median edge length.
        radius_edges: see ``radius``.
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
    """

    def __init__(
        self,
        avatar: Avatar,
        enabled: bool = True,
        *,
        radius: float | None = None,
        radius_edges: float = 2.0,
        max_neighbours: int = 16,
        w_s: float = 1e-3,
        min_neighbours: int = 1,
        umbilic_tol: float = 1.0,
        anisotropy_tol: float = 0.0,
        stretch_range: tuple[float, float] = (0.25, 4.0),
        refresh_tolerance: float | None = None,
        use_curvature: bool = True,
    ) -> None:
        self.avatar = avatar
        self.enabled = bool(enabled)
        self.use_curvature = bool(use_curvature)
        verts = avatar.canonical_vertices.detach()
        if radius is None:
            radius = radius_edges * median_edge_length(verts, avatar.faces)
        self.radius = float(radius)
        self.correction = SurfelCorrection.from_mesh(
            verts, avatar.faces, self.radius, max_neighbours, w_s=w_s, min_neighbours=min_neighbours,
            stretch_range=stretch_range, umbilic_tol=umbilic_tol, anisotropy_tol=anisotropy_tol, enabled=self.enabled,
        )  # fmt: skip
        if refresh_tolerance is None:
            refresh_tolerance = 0.25 * float(avatar.sdf.default_fd_step())
        self.refresh_tolerance = float(refresh_tolerance)
        self._cache: CurvatureCache | None = None
        self.recomputed = 0

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
        detached (the SDF is frozen; gradients still reach the surfels and the attribute heads)."""
        av = self.avatar
        cs = av.canonical_state(with_sdf=False)
        sdf, grad, feat = av.sdf.gradient(cs.means.detach())
        cs.sdf, cs.sdf_grad, cs.feature = sdf.detach(), grad.detach(), feat.detach()
        return cs

    def correct(self, vertices: torch.Tensor, canonical: CanonicalSurfels) -> CorrectionResult:
        """Correction of every surfel for the posed mesh vertices: (V, 3) (no gradient)."""
        av = self.avatar
        with torch.no_grad():
            geo = self.geometry(canonical.means)
            kappa = geo.kappa if self.use_curvature else None
            dirs = geo.dirs if self.use_curvature else None
            return self.correction(
                vertices.detach(), av.surfels.binding, canonical.quats.detach(), geo.normal, kappa, dirs, av.surfels.hair_mask()
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
