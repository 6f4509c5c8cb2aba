"""Wrinkle shading: darkening surfels where a deformation compresses the skin (SAGE §6).

Under an expression, skin that is pushed together folds into creases that catch less light. A
surfel avatar fitted to one timestep has no such shading; SAGE darkens Gaussians in regions of
persistently high distortion, which its supplementary material finds to coincide with facial creases
and expression wrinkles. Here this is split into a learned *where* and a geometric *when*:

* where: during phase 2, :class:`FaceDistortionStats` accumulates the per-pixel depth distortion of
  the deformed renders on the posed-mesh triangle each pixel sees. :func:`wrinkle_amplitude` maps each
  triangle's mean to a weight in [0, 1] between two quantiles of the visible, non-excluded
  triangles (e.g. the median and the 90th percentile), times a maximum darkening ``strength``; a
  surfel takes its bound triangle's value;
* when: at render time a surfel is darkened in proportion to how much the surface around it is
  compressed relative to canonical space, :func:`surfel_compression`: the area ratio r of the
  triangles around its bound triangle's vertices (one-ring areas, averaged over the three vertices),
  c = clamp((1 − r) / full, 0, 1), so that c reaches 1 at a ``full`` relative area loss.

The colour of surfel i becomes colour_i · (1 − a_i · c_i) with a_i its amplitude. At rest (r = 1)
and under stretching (r > 1) nothing changes, so the avatar's appearance at the captured expression is
untouched. The per-surfel values live in :attr:`SurfelSet.wrinkle` as (N, 2) rows (a_i, full_i).

Which mesh the compression is measured on is the avatar's ``wrinkle_basis`` (:data:`WRINKLE_BASES`):

* ``expression`` (the default for avatars trained since it was added): FLAME's expression-shaped
  mesh (template + shape + expression blendshapes + offsets, before pose correctives and skinning,
  :attr:`~sage_core.flame.lbs.FlameOutput.v_shaped`) against the same mesh of the canonical frame.
  Creases are what the expression blendshapes push together; the jaw, neck and eye rotations are
  applied by linear blend skinning, whose blend zones (under the chin and along the neck when the
  jaw opens, the neck when the head tilts) lose area as a skinning artefact, not as skin folding;
* ``posed``: the posed mesh against the canonical mesh (avatars trained before the option).
"""

from __future__ import annotations

import torch

__all__ = [
    "WRINKLE_BASES",
    "FaceDistortionStats",
    "apply_wrinkles",
    "face_compression",
    "surfel_compression",
    "vertex_area_ratio",
    "wrinkle_amplitude",
]


WRINKLE_BASES: tuple[str, ...] = ("expression", "posed")
"""Meshes the wrinkle compression can be measured on (see the module doc)."""


def _face_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F,) triangle areas. vertices: (..., V, 3) with no leading dims; faces: (F, 3)."""
    tri = vertices[faces]
    return 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=-1)


def vertex_area_ratio(posed: torch.Tensor, canonical: torch.Tensor, faces: torch.Tensor, eps: float = 1e-20) -> torch.Tensor:
    """Posed over canonical one-ring area of every vertex.

    posed, canonical: (V, 3) the same mesh in two states; faces: (F, 3) int64 -> (V,) ratio (1 where a
    vertex has no incident area in canonical space).
    """
    faces = faces.long()
    V = canonical.shape[0]
    a_p = _face_areas(posed, faces)
    a_c = _face_areas(canonical.to(posed), faces)
    sum_p = posed.new_zeros(V).index_add_(0, faces.reshape(-1), a_p.repeat_interleave(3))
    sum_c = posed.new_zeros(V).index_add_(0, faces.reshape(-1), a_c.repeat_interleave(3))
    return torch.where(sum_c > eps, sum_p / sum_c.clamp_min(eps), torch.ones_like(sum_p))


def surfel_compression(
    posed: torch.Tensor, canonical: torch.Tensor, faces: torch.Tensor, binding: torch.Tensor, full: torch.Tensor | float
) -> torch.Tensor:
    """Compression c in [0, 1] of every surfel's neighbourhood (see the module doc).

    posed, canonical: (V, 3); faces: (F, 3); binding: (N,) face ids; full: scalar or (N,) relative area
    loss at which c = 1 -> (N,).
    """
    r_v = vertex_area_ratio(posed, canonical, faces)
    r = r_v[faces.long()[binding]].mean(-1)
    full_t = torch.as_tensor(full, dtype=r.dtype, device=r.device).clamp_min(1e-6)
    return ((1.0 - r) / full_t).clamp(0.0, 1.0)


def apply_wrinkles(
    colors: torch.Tensor, wrinkle: torch.Tensor, posed: torch.Tensor, canonical: torch.Tensor, faces: torch.Tensor,
    binding: torch.Tensor,
) -> torch.Tensor:
    """Darkened colours: colors (N, C) · (1 − a · c) with ``wrinkle`` (N, 2) rows (a, full) and c from
    :func:`surfel_compression` of the posed (V, 3) against the canonical (V, 3) mesh."""
    with torch.no_grad():
        c = surfel_compression(posed.detach(), canonical, faces, binding, wrinkle[:, 1].to(posed))
        factor = 1.0 - wrinkle[:, 0].to(c) * c
    return colors * factor.to(colors)[:, None]


class FaceDistortionStats:
    """Running per-triangle sums of the per-pixel depth distortion of deformed renders.

    n_faces: F. :meth:`update` adds one render; :meth:`mean` is the per-triangle mean over every pixel
    (of every update) whose posed-mesh triangle it was. Sums are float64 so long runs do not lose
    precision. With ``face_compression`` given to :meth:`update`, the pixel-weighted compression of
    each triangle is accumulated too (:meth:`mean_compression`), to check how the distortion relates
    to it.
    """

    def __init__(self, n_faces: int, device: str | torch.device = "cpu") -> None:
        self.sum = torch.zeros(int(n_faces), dtype=torch.float64, device=device)
        self.count = torch.zeros(int(n_faces), dtype=torch.float64, device=device)
        self.comp_sum = torch.zeros(int(n_faces), dtype=torch.float64, device=device)

    @torch.no_grad()
    def update(self, face_id: torch.Tensor, distortion: torch.Tensor, face_compression: torch.Tensor | None = None) -> None:
        """face_id: (H, W) int64 triangle per pixel (−1 none); distortion: (H, W) per-pixel distortion;
        face_compression: optional (F,) compression of every triangle in this render."""
        fid = face_id.reshape(-1)
        hit = fid >= 0
        f = fid[hit].to(self.sum.device)
        self.sum.index_add_(0, f, distortion.detach().reshape(-1)[hit].to(self.sum))
        self.count.index_add_(0, f, torch.ones_like(f, dtype=self.count.dtype))
        if face_compression is not None:
            self.comp_sum.index_add_(0, f, face_compression.detach().to(self.comp_sum)[f])

    def mean(self) -> torch.Tensor:
        """(F,) mean distortion per triangle (0 where never seen)."""
        return torch.where(self.count > 0, self.sum / self.count.clamp_min(1), torch.zeros_like(self.sum))

    def mean_compression(self) -> torch.Tensor:
        """(F,) pixel-weighted mean compression per triangle (0 where never seen)."""
        return torch.where(self.count > 0, self.comp_sum / self.count.clamp_min(1), torch.zeros_like(self.sum))

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"sum": self.sum.clone(), "count": self.count.clone(), "comp_sum": self.comp_sum.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.sum = state["sum"].to(self.sum).clone()
        self.count = state["count"].to(self.count).clone()
        self.comp_sum = state["comp_sum"].to(self.comp_sum).clone()


def face_compression(posed: torch.Tensor, canonical: torch.Tensor, faces: torch.Tensor, full: float) -> torch.Tensor:
    """(F,) compression of every triangle: :func:`surfel_compression` with one surfel per triangle."""
    F = faces.shape[0]
    return surfel_compression(posed, canonical, faces, torch.arange(F, device=faces.device), full)


def wrinkle_amplitude(
    face_mean: torch.Tensor,
    face_count: torch.Tensor,
    excluded: torch.Tensor,
    strength: float,
    quantiles: tuple[float, float] = (0.5, 0.9),
    min_count: float = 1.0,
) -> torch.Tensor:
    """Per-triangle darkening amplitude in [0, strength].

    face_mean, face_count: (F,) from :class:`FaceDistortionStats`; excluded: (F,) bool triangles that
    never darken (hair); the weight rises linearly from 0 at the ``quantiles[0]`` to 1 at the
    ``quantiles[1]`` quantile of the means of the triangles seen at least ``min_count`` pixels and not
    excluded -> (F,).
    """
    lo_q, hi_q = quantiles
    if not 0.0 <= lo_q < hi_q <= 1.0:
        raise ValueError(f"quantiles must satisfy 0 <= lo < hi <= 1, got {quantiles}")
    ok = (face_count >= min_count) & ~excluded.to(face_count.device)
    out = torch.zeros_like(face_mean)
    if int(ok.sum()) < 2:
        return out
    vals = face_mean[ok]
    lo, hi = torch.quantile(vals, lo_q), torch.quantile(vals, hi_q)
    span = (hi - lo).clamp_min(1e-30)
    out[ok] = ((vals - lo) / span).clamp(0.0, 1.0) * float(strength)
    return out
