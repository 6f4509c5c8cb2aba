"""Smooth-albedo light prior: which world light explains the shading a capture shows.

With ``shading=sh2`` a surfel's colour is albedo × E(n_w), E the irradiance of a light fixed in the
world. Seen from one timestep, any light can be traded for an albedo that carries the opposite
shading, so the photometric loss alone leaves the light where it starts (flat), the albedo bakes the
capture's shading in, and a new expression that turns the surface (the chin when the jaw opens)
keeps the shading of the captured one.

Skin albedo changes slowly across the surface except at features (brows, lips), and those change
its chromaticity; shading changes with the normal and leaves the chromaticity alone. Of all the
(albedo, light) pairs that render a frame alike this term picks the light under which neighbouring
skin surfels of similar chromaticity have the most similar albedo:

    L = Σ_ij w_ij Σ_c (Δ_ij log C_c − Δ_ij log E_c(n))² / (3 Σ_ij w_ij),
    w_ij = exp(−‖χ_i − χ_j‖² / σ²),

over the pairs (i, j) of every face or neck surfel and its ``k`` nearest face or neck surfels in
canonical space, with C the surfels' rendered colours (albedo × E, held fixed: no gradient reaches
the albedo, so the texture is untouched), χ = C / ΣC their chromaticity, Δ_ij x = x_i − x_j, and n
the outward normals of the surfels' posed triangles (smoother than the surfels' own). The gradient
reaches the light coefficients alone; the photometric loss then fits the albedo to the images under
that light. The light's mean stays fixed by its own prior (:meth:`SHIrradiance.mean_prior`).
"""

from __future__ import annotations

import torch

from ..avatar.init import REGION_FACE, REGION_NECK
from ..avatar.shading import SHIrradiance
from ..geometry.knn import nearest_indices

__all__ = ["SmoothAlbedoLight", "neighbour_pairs"]

def neighbour_pairs(points: torch.Tensor, k: int) -> torch.Tensor:
    """(M·k', 2) int64 pairs (i, j) of every point i and its k' = min(k, M − 1) nearest other points.

    points: (M, 3). Exact (:func:`sage_core.geometry.knn.nearest_indices`).
    """
    M = int(points.shape[0])
    k = min(int(k), M - 1)
    if k <= 0:
        return torch.zeros(0, 2, dtype=torch.long, device=points.device)
    rows = torch.arange(M, device=points.device)
    nn = nearest_indices(points, points, k, exclude=rows)
    return torch.stack([rows[:, None].expand(-1, k), nn], -1).reshape(-1, 2)


class SmoothAlbedoLight:
    """The smooth-albedo light term (module doc) for one avatar's surfel set.

    neighbours: k; chroma_sigma: σ of the chromaticity weight. The pairs are built from the canonical
    centres on the first call of :meth:`loss` and again whenever the number of surfels changes or
    :meth:`reset` was called (surfels moved, e.g. by relocation); the centres and eligible surfels they
    were built from are its state (:meth:`state_dict`).
    """

    def __init__(self, neighbours: int = 128, chroma_sigma: float = 0.02) -> None:
        if neighbours < 1:
            raise ValueError(f"neighbours must be at least 1, got {neighbours}")
        if not chroma_sigma > 0:
            raise ValueError(f"chroma_sigma must be positive, got {chroma_sigma}")
        self.neighbours = int(neighbours)
        self.chroma_sigma = float(chroma_sigma)
        self._built: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self._points: torch.Tensor | None = None
        self._eligible: torch.Tensor | None = None

    @staticmethod
    def eligible(region_id: torch.Tensor) -> torch.Tensor:
        """(N,) bool surfels of the face and neck regions."""
        return (region_id == REGION_FACE) | (region_id == REGION_NECK)

    def pairs(self, canonical_means: torch.Tensor, region_id: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(used (U,) surfel indices, i (P,), j (P,) pair ends as positions in ``used``), rebuilt when
        the number of surfels changes. canonical_means: (N, 3); region_id: (N,)."""
        if self._points is None or self._eligible is None or self._points.shape[0] != canonical_means.shape[0]:
            self._points = canonical_means.detach().clone()
            self._eligible = self.eligible(region_id).detach().clone()
            self._built = None
        if self._built is None:
            used = self._eligible.to(canonical_means.device).nonzero().squeeze(-1)
            local = neighbour_pairs(self._points.to(canonical_means)[used], self.neighbours)
            self._built = (used, local[:, 0].contiguous(), local[:, 1].contiguous())
        return self._built

    def reset(self) -> None:
        """Forget the pairs: the next :meth:`loss` builds them from the centres it is given."""
        self._points = self._eligible = self._built = None

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The canonical centres and the eligible surfels the pairs were built from (empty before the
        first build), so that a resumed run uses the same pairs."""
        if self._points is None or self._eligible is None:
            return {}
        return {"points": self._points.clone(), "eligible": self._eligible.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self._points, self._eligible = state.get("points"), state.get("eligible")
        self._built = None

    def loss(
        self, light: SHIrradiance, colors: torch.Tensor, normals: torch.Tensor, canonical_means: torch.Tensor,
        region_id: torch.Tensor, sample: int | None = None, generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """0-d term. colors: (N, 3) rendered surfel colours (used without gradient); normals: (N, 3)
        outward unit world normals; canonical_means: (N, 3) and region_id: (N,) for the pairs; sample:
        use this many pairs drawn uniformly with replacement (``generator``, on the CPU) instead of all."""
        used, i, j = self.pairs(canonical_means, region_id)
        if i.numel() == 0:
            return light.coeffs.sum() * 0.0
        if sample is not None and sample < i.numel():
            pick = torch.randint(i.numel(), (int(sample),), generator=generator).to(i.device)
            i, j = i[pick], j[pick]
        c = colors.detach()[used].clamp_min(1e-3)
        log_c = c.log()
        chroma = c / c.sum(-1, keepdim=True)
        w = torch.exp(-((chroma[i] - chroma[j]) ** 2).sum(-1) / self.chroma_sigma**2)
        log_e = light.irradiance(normals.detach()[used]).log()
        r = (log_c[i] - log_c[j]) - (log_e[i] - log_e[j])
        return (w[:, None] * r**2).sum() / (3.0 * w.sum().clamp_min(1e-12))
