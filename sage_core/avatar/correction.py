"""Surfel shape correction from local stretch and curvature (SAGE §3, "Gaussian surfel correction").

Notation. Every triangle j has a canonical → posed transform, the one that poses surfels bound to
it. Its linear part is measured two ways:

* the *binding* (similarity) part r_j·Q_j with Q_j = R_j^d·(R_j^c)ᵀ and r_j = k_j^d / k_j^c, from the
  per-face frames (R, T, k) of docs/formats.md §6 (the canonical → posed map a bound surfel follows);
* the *affine* part F_j = A_j^d·(A_j^c)⁻¹ with A_j = [v1 − v0 | v2 − v0 | n̂_j] (edges from the first
  vertex and the unit face normal): the exact deformation gradient of the triangle's plane, which
  maps canonical edges to posed edges and the canonical normal to the posed normal. For a triangle
  that moves by a similarity, F_j = (k_j^d R_j^d)(k_j^c R_j^c)⁻¹ = r_j·Q_j.

Stretch. The paper's relative transform of a neighbour j with respect to the query triangle q (the
surfel's bound triangle) is M_j = T_q⁻¹·T_j: posed through j, back through q. Its linear part, in
canonical world coordinates, is L_j = (r_q Q_q)⁻¹·F_j = Q_qᵀ·F_j / r_q. It is the identity under any
motion that the binding already reproduces (rigid motion, uniform scaling); what remains is the
neighbourhood's stretch beyond the binding, with the query's rotation removed. The neighbourhood
N(q) ∪ {q} is combined with normalised weights w_j (the query 1, a neighbour exp(−d_j²/(2σ²)) with d_j
the canonical centroid distance, degenerate triangles 0) and projected on the tangent plane with
P = I − n·nᵀ (n the canonical SDF normal at the surfel):

    G = Eᵀ · P · (Σ_j w_j L_j) · P · E          (2×2, E = [e1 e2] an orthonormal tangent basis, P·E = E)

with e1 the surfel's first axis projected on the plane and e2 = n × e1 (n oriented like the surfel
normal). The polar decomposition G = R·S leaves S = sqrt(GᵀG): the stretch of a tangent direction u
is ‖G·u‖ and the principal stretches are the square roots of the eigenvalues of GᵀG. Using GᵀG
also removes any residual in-plane rotation (under anisotropic stretch Q_q, which follows the first
edge, differs from the polar rotation by a rotation about the normal). The affine F_j is what makes
anisotropic stretch measurable: with the similarity parts alone every L_j, and so their weighted
sum, would be conformal in the plane, forcing σ1 = σ2. The estimate is exact for any affine
deformation of the neighbourhood; where neighbours bend relative to the query by angles Δθ_j, the
tangent projection shortens their contribution by cos Δθ_j ≈ 1 − Δθ_j²/2, a second-order effect
that a small ``radius`` keeps small. :class:`CorrectionResult` reports both the
relative stretch (what scales the posed surfel) and the absolute one (r_q times it: canonical →
posed).

Rotation. Principal curvature directions d1, d2 (canonical, ⊥ n) give the angle α of d1 in the
tangent basis. The surfel turns about its own normal by φ, the angle from e1 to the nearest of
±d1, ±d2: φ = ((α + π/4) mod π/2) − π/4 ∈ [−45°, 45°), well within the ±90° limit, and the same for
d and −d (sign-consistent). Where the surface is nearly umbilic the directions are arbitrary, so φ
is scaled by min(1, |κ1 − κ2| / umbilic_tol), and, with ``anisotropy_tol`` > 0, by
min(1, (σ1 − σ2) / (σ2·anisotropy_tol)) with σ1 ≥ σ2 the principal stretches of G: under an isotropic
deformation (at rest in particular) a surfel keeps the orientation it was fitted with, and the turn
grows with the anisotropy of the stretch that the scale update acts on. The correction quaternion is dq = (cos φ/2, 0, 0,
sin φ/2), a rotation about the local z axis, applied as q' = q ⊗ dq (Hamilton, wxyz): R(q') = R(q)·Rz(φ)
keeps the third column (the normal) and turns the first onto cos φ·t1 + sin φ·t2. It is valid for
the local, canonical or posed quaternion of the surfel alike, as those differ by a left factor.

Affine mode. ``mode="affine"`` replaces the rotation and the axis-wise stretch by the exact image of
the surfel's ellipse under G: with s = (s1, s2) its in-plane scales, the posed ellipse has the
covariance C = G·diag(s)²·Gᵀ, whose eigenvectors and square-rooted eigenvalues are the new axes and
scales. φ is the angle from e1 to the eigenvector nearest to it (|φ| ≤ 45°, the other eigenvector
becomes the second axis) and the factors are the new scales over the old. It is the identity under
any motion the binding reproduces (G = I), needs no curvature, and under anisotropic stretch an
ellipse at any angle to the stretch deforms exactly as the surface under it does; the axis-wise
update of the paper's mode is exact only for axes along the principal stretch directions. The
curvature damping, when curvatures are given, applies along the new axes as below.

Scale. With u1, u2 the corrected axes in the tangent basis, the curvature along u_i is Euler's
κ(u_i) = κ1·cos²θ_i + κ2·sin²θ_i (θ_i the angle from d1), and the paper's update becomes

    s_i' = s_i · σ_i / (1 + w_s·|κ(u_i)|),   σ_i = ‖G·u_i‖ clamped to ``stretch_range``

where s_i is the surfel's posed (binding-scaled) in-plane scale. σ_i equals the principal stretch
when u_i is a principal stretch direction. Curvatures are in inverse world units (1/m), so w_s is a
length (m). Surfels that are flagged hair, whose bound triangle has fewer than ``min_neighbours``
valid neighbours, or whose bound triangle is degenerate get dq = identity and unit factors.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch

from sage_core.avatar.neighbours import triangle_centroids, triangle_neighbours
from sage_core.flame.frames import triangle_frames
from sage_core.geometry.rotations import quat_multiply, quat_to_matrix

_AREA_EPS = 1e-14
CORRECTION_MODES = ("curvature", "affine")


@dataclass
class CorrectionResult:
    """Per-surfel correction (leading dimensions follow the posed vertices' batch shape, then N).

    Attributes:
        quat: (..., N, 4) correction quaternion dq (wxyz), a rotation about the surfel's local z axis;
            apply as q' = q ⊗ dq.
        scale_factor: (..., N, 2) multiply the posed in-plane scales (s1, s2) by this.
        stretch: (..., N, 2) relative stretch σ_i along the corrected axes, clamped (1 = nothing beyond
            the binding).
        principal_stretch: (..., N, 2) absolute canonical → posed principal stretches, largest first.
        angle: (..., N) rotation φ about the normal, radians.
        valid: (N,) bool, surfels the correction applies to.
    """

    quat: torch.Tensor
    scale_factor: torch.Tensor
    stretch: torch.Tensor
    principal_stretch: torch.Tensor
    angle: torch.Tensor
    valid: torch.Tensor


def affine_frames(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Affine triangle frames A = [v1 − v0 | v2 − v0 | n̂] (columns).

    vertices: (..., V, 3); faces: (F, 3). Returns A: (..., F, 3, 3) and twice the triangle areas (..., F).
    """
    tri = vertices[..., faces, :]
    v0, v1, v2 = tri.unbind(-2)
    e1, e2 = v1 - v0, v2 - v0
    c = torch.linalg.cross(e1, e2, dim=-1)
    area2 = c.norm(dim=-1)
    n = c / area2.clamp_min(1e-30).unsqueeze(-1)
    return torch.stack([e1, e2, n], -1), area2


def principal_stretches(G: torch.Tensor, eps: float = 1e-20) -> tuple[torch.Tensor, torch.Tensor]:
    """Principal stretches of 2×2 linear maps via the polar decomposition G = R·S, S = sqrt(GᵀG).

    G: (..., 2, 2). Returns sigma (..., 2) (largest first) and the unit principal directions as the
    columns of (..., 2, 2), in the input (canonical tangent) coordinates.
    """
    sigma, C = _principal_sigma(G, eps)
    a, b, c = C[..., 0, 0], C[..., 0, 1], C[..., 1, 1]
    psi = 0.5 * torch.atan2(2 * b, a - c)
    d1 = torch.stack([torch.cos(psi), torch.sin(psi)], -1)
    d2 = torch.stack([-torch.sin(psi), torch.cos(psi)], -1)
    return sigma, torch.stack([d1, d2], -1)


def _affine_ellipse(G: torch.Tensor, scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The ellipse of in-plane scales ``scales`` (N, 2) (axes e1, e2) mapped by G (..., N, 2, 2).

    Returns φ (..., N), the angle from e1 to the new axis nearest to it (|φ| ≤ π/4), and the new
    scales over the old along the new axes (..., N, 2): (first, second)."""
    s = scales.clamp_min(1e-30)
    M = G * s.unsqueeze(-2)  # G·diag(s): columns scaled
    c00 = (M[..., 0, :] ** 2).sum(-1)
    c11 = (M[..., 1, :] ** 2).sum(-1)
    c01 = (M[..., 0, :] * M[..., 1, :]).sum(-1)
    half_diff = 0.5 * (c00 - c11)
    mean = 0.5 * (c00 + c11)
    root = torch.sqrt(half_diff**2 + c01**2)
    psi = 0.5 * torch.atan2(2 * c01, c00 - c11)  # eigenvector of the larger eigenvalue, (−π/2, π/2]
    big = (mean + root).clamp_min(0).sqrt()
    small = (mean - root).clamp_min(0).sqrt()
    swap = psi.abs() > 0.25 * math.pi
    phi = torch.where(swap, psi - torch.sign(psi) * 0.5 * math.pi, psi)
    first = torch.where(swap, small, big)
    second = torch.where(swap, big, small)
    return phi, torch.stack([first, second], -1) / s


def _principal_sigma(G: torch.Tensor, eps: float = 1e-20) -> tuple[torch.Tensor, torch.Tensor]:
    """The sigma of :func:`principal_stretches` alone, and C = GᵀG (..., 2, 2)."""
    C = G.transpose(-1, -2) @ G
    a, b, c = C[..., 0, 0], C[..., 0, 1], C[..., 1, 1]
    mean = 0.5 * (a + c)
    rad = torch.sqrt(0.25 * (a - c) ** 2 + b * b + eps)
    return torch.stack([(mean + rad).clamp_min(0).sqrt(), (mean - rad).clamp_min(0).sqrt()], -1), C


class SurfelCorrection(torch.nn.Module):
    """Stretch- and curvature-driven surfel correction with neighbour sets computed once.

    Per-triangle state (buffers, move with ``.to(device)``): neighbour indices with the triangle
    itself first, normalised-at-use weights, the inverse canonical affine frames and the canonical
    frame rotations and scales. Per-surfel inputs (binding, canonical rotation, SDF normal,
    curvatures) are given at call time, so rebinding needs no rebuild.

    A call evaluates the neighbourhood sums Σ_j w_j F_j as one sparse (CSR) matrix product
    (:meth:`neighbour_matrix`) and only for the triangles the surfels are bound to; those triangles
    and their matrix are remembered for the last ``binding`` tensor while it is not modified.

    Args:
        canonical_vertices: (V, 3) canonical mesh.
        faces: (F, 3).
        neighbour_idx: (F, K) int64 neighbours of each triangle, −1 padded, excluding itself
            (e.g. :func:`sage_core.avatar.neighbours.triangle_neighbours`).
        sigma: Gaussian weight width in world units (exp(−d²/(2σ²)) in canonical centroid distance).
        w_s: curvature damping length (m), the paper's w_s.
        min_neighbours: a triangle needs at least this many valid neighbours to be corrected.
        stretch_range: clamp (lo, hi) of the relative stretch.
        umbilic_tol: |κ1 − κ2| (1/m) at and above which the rotation is applied in full; 0 disables
            the fade.
        anisotropy_tol: relative anisotropy (σ1 − σ2)/σ2 of the neighbourhood's stretch at and
            above which the rotation is applied in full (it fades linearly to none at an isotropic
            deformation, so that the correction keeps a surfel's fitted orientation at rest); 0
            always applies it in full.
        enabled: False makes every call return the identity correction (``--correction off``).
        mode: ``"curvature"`` (the paper's: rotation towards the principal curvature directions,
            stretch measured along the turned axes) or ``"affine"`` (the exact image of the surfel's
            ellipse under the neighbourhood's stretch; needs the surfels' scales at call time).
    """

    def __init__(
        self,
        canonical_vertices: torch.Tensor,
        faces: torch.Tensor,
        neighbour_idx: torch.Tensor,
        sigma: float,
        w_s: float = 1e-3,
        min_neighbours: int = 1,
        stretch_range: tuple[float, float] = (0.25, 4.0),
        umbilic_tol: float = 1.0,
        enabled: bool = True,
        anisotropy_tol: float = 0.0,
        mode: str = "curvature",
    ) -> None:
        super().__init__()
        if sigma <= 0:
            raise ValueError("sigma must be positive")
        if mode not in CORRECTION_MODES:
            raise ValueError(f"mode must be one of {CORRECTION_MODES}, got {mode!r}")
        device = canonical_vertices.device
        dtype = canonical_vertices.dtype
        faces = faces.to(device=device, dtype=torch.long)
        nbr = neighbour_idx.to(device=device, dtype=torch.long)
        F = faces.shape[0]
        if nbr.dim() != 2 or nbr.shape[0] != F:
            raise ValueError(f"neighbour_idx must be (F, K) with F = {F}, got {tuple(nbr.shape)}")
        A, area2 = affine_frames(canonical_vertices, faces)
        ok = area2 > _AREA_EPS * area2.max().clamp_min(1e-30)
        eye = torch.eye(3, dtype=dtype, device=device).expand(F, 3, 3)
        A_inv = torch.linalg.inv(torch.where(ok[:, None, None], A, eye))
        A_inv = torch.where(ok[:, None, None], A_inv, torch.zeros_like(A_inv))
        R_c, _, k_c = triangle_frames(canonical_vertices, faces)
        centroids = torch.as_tensor(triangle_centroids(canonical_vertices, faces), dtype=dtype, device=device)
        self_idx = torch.arange(F, device=device)
        pad = nbr < 0
        nbr_safe = torch.where(pad, self_idx[:, None], nbr)
        d2 = ((centroids[nbr_safe] - centroids[:, None, :]) ** 2).sum(-1)
        w_nb = torch.exp(-d2 / (2 * sigma * sigma)) * (~pad) * ok[nbr_safe]
        idx = torch.cat([self_idx[:, None], nbr_safe], 1)  # (F, K+1), the triangle itself first
        weights = torch.cat([ok[:, None].to(dtype), w_nb.to(dtype)], 1) * ok[:, None]
        self.register_buffer("faces", faces)
        self.register_buffer("idx", idx)
        self.register_buffer("weights", weights)
        self.register_buffer("A_inv", A_inv)
        self.register_buffer("R_c", R_c.detach())
        self.register_buffer("k_c", k_c.detach())
        self.register_buffer("n_neighbours", ((w_nb > 0).sum(1)).long())
        self.register_buffer("tri_ok", ok)
        self.w_s = float(w_s)
        self.min_neighbours = int(min_neighbours)
        self.stretch_range = (float(stretch_range[0]), float(stretch_range[1]))
        self.umbilic_tol = float(umbilic_tol)
        self.anisotropy_tol = float(anisotropy_tol)
        self.enabled = bool(enabled)
        self.mode = mode
        self._bound_cache: tuple | None = None

    @classmethod
    def from_mesh(
        cls,
        canonical_vertices: torch.Tensor,
        faces: torch.Tensor,
        radius: float,
        max_neighbours: int = 16,
        sigma: float | None = None,
        **kwargs,
    ) -> "SurfelCorrection":
        """Build with a centroid ball query of ``radius`` (sigma defaults to radius / 2)."""
        idx, _ = triangle_neighbours(canonical_vertices, faces, radius, max_neighbours, device=canonical_vertices.device)
        return cls(canonical_vertices, faces, idx, sigma if sigma is not None else 0.5 * radius, **kwargs)

    def triangle_valid(self) -> torch.Tensor:
        """(F,) bool: non-degenerate triangles with at least ``min_neighbours`` valid neighbours."""
        return self.tri_ok & (self.n_neighbours >= self.min_neighbours)

    def neighbour_matrix(self, triangles: torch.Tensor | None = None) -> torch.Tensor:
        """The normalised neighbourhood weights as a sparse CSR matrix (M, F) (row q: w_qj / Σ_j w_qj at
        the columns j of N(q) ∪ {q}, zero weights left out), of every triangle or of ``triangles``
        (M,) int64. ``neighbour_matrix() @ X`` is Σ_j w_j X_j for per-triangle rows X (F, C)."""
        rows = torch.arange(self.idx.shape[0], device=self.idx.device) if triangles is None else triangles.to(self.idx.device)
        w = self.weights[rows]
        w = w / w.sum(1, keepdim=True).clamp_min(1e-30)
        cols = self.idx[rows]
        keep = w != 0
        r = torch.arange(rows.shape[0], device=rows.device)[:, None].expand_as(cols)
        size = (rows.shape[0], self.idx.shape[0])
        with warnings.catch_warnings():  # torch marks sparse CSR support as beta
            warnings.simplefilter("ignore", UserWarning)
            coo = torch.sparse_coo_tensor(torch.stack([r[keep], cols[keep]]), w[keep], size, check_invariants=True)
            return coo.coalesce().to_sparse_csr()

    def _bound_triangles(self, binding: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The distinct triangles of ``binding`` (N,) (M,), each surfel's row among them (N,) and their
        :meth:`neighbour_matrix` (M, F); remembered for the last binding tensor (while unmodified)."""
        key = (binding.data_ptr(), binding._version, tuple(binding.shape), self.weights.data_ptr(), self.weights._version)
        cached = self._bound_cache
        if cached is not None and cached[0] == key and cached[1] is binding:
            return cached[2]
        tri, inv = torch.unique(binding, return_inverse=True)
        out = (tri, inv, self.neighbour_matrix(tri))
        self._bound_cache = (key, binding, out)
        return out

    def relative_deformation(
        self, posed_vertices: torch.Tensor, triangles: torch.Tensor | None = None, neighbours: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-triangle Σ_j w_j L_j (the relative linear maps, canonical coordinates) and r_q.

        posed_vertices: (..., V, 3), computed in the canonical mesh's dtype; triangles: optional (M,)
        int64, the triangles q to compute (default all F), with ``neighbours`` their
        :meth:`neighbour_matrix` when already built. Returns L: (..., M, 3, 3) and r: (..., M) = k^d / k^c.
        """
        posed_vertices = posed_vertices.to(self.A_inv.dtype)
        if neighbours is None:
            neighbours = self.neighbour_matrix(triangles)
        A_d, _ = affine_frames(posed_vertices, self.faces)
        Fj = A_d @ self.A_inv  # (..., F, 3, 3): every triangle, the neighbourhoods reach them all
        batch, n_faces = Fj.shape[:-3], Fj.shape[-3]
        cols = Fj.reshape(-1, n_faces, 9).transpose(0, 1).reshape(n_faces, -1)  # (F, B*9)
        F_bar = (neighbours @ cols).reshape(-1, max(1, math.prod(batch)), 9).transpose(0, 1)
        F_bar = F_bar.reshape(*batch, -1, 3, 3)  # (..., M, 3, 3)
        faces_q = self.faces if triangles is None else self.faces[triangles]
        R_c = self.R_c if triangles is None else self.R_c[triangles]
        k_c = self.k_c if triangles is None else self.k_c[triangles]
        R_d, _, k_d = triangle_frames(posed_vertices, faces_q)
        Q = R_d @ R_c.transpose(-1, -2)
        r = k_d / k_c.clamp_min(1e-30)
        L = Q.transpose(-1, -2) @ F_bar / r[..., None, None].clamp_min(1e-30)
        return L, r

    def forward(
        self,
        posed_vertices: torch.Tensor,
        binding: torch.Tensor,
        rotations: torch.Tensor,
        normals: torch.Tensor,
        curvatures: torch.Tensor | None = None,
        directions: torch.Tensor | None = None,
        hair: torch.Tensor | None = None,
        scales: torch.Tensor | None = None,
    ) -> CorrectionResult:
        """Correction for N surfels.

        posed_vertices: (..., V, 3) posed mesh; binding: (N,) bound triangle; rotations: (N, 4)
        canonical world quaternions (wxyz) of the surfels, q(R_c[binding]) ⊗ q_loc; normals: (N, 3)
        canonical SDF normals (any length, any sign); curvatures: (N, 2) principal curvatures κ1, κ2
        (1/m) and directions: (N, 2, 3) their canonical directions — both None for stretch only (no
        rotation, no damping; in affine mode, no damping); hair: (N,) bool, excluded surfels;
        scales: (N, 2) or (N, 3) the surfels' in-plane scales (any common factor; required in affine
        mode, unused otherwise).
        """
        if self.mode == "affine" and scales is None:
            raise ValueError("the affine correction needs the surfels' scales")
        binding = binding.to(device=self.idx.device, dtype=torch.long)
        N = binding.shape[0]
        dtype = rotations.dtype
        valid = self.triangle_valid()[binding]
        if hair is not None:
            valid = valid & ~hair.to(device=valid.device, dtype=torch.bool)
        batch = posed_vertices.shape[:-2]
        if not self.enabled:
            ident = rotations.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(*batch, N, 4)
            ones = rotations.new_ones(*batch, N, 2)
            return CorrectionResult(ident, ones, ones, ones, rotations.new_zeros(*batch, N), torch.zeros_like(valid))

        tri, row, nbr = self._bound_triangles(binding)
        L, r = self.relative_deformation(posed_vertices, tri, nbr)  # only the bound triangles
        L = L[..., row, :, :]  # (..., N, 3, 3)
        r = r[..., row]
        work = L.dtype
        rotations = rotations.to(work)
        normals = normals.to(work)
        if curvatures is not None and directions is not None:
            curvatures = curvatures.to(work)
            directions = directions.to(work)

        Rs = quat_to_matrix(rotations)
        t1, t3 = Rs[..., 0], Rs[..., 2]
        n = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        n = torch.where((n * t3).sum(-1, keepdim=True) < 0, -n, n)
        e1 = t1 - (t1 * n).sum(-1, keepdim=True) * n
        e1 = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        e2 = torch.linalg.cross(n, e1, dim=-1)
        E = torch.stack([e1, e2], -1)  # (N, 3, 2)
        G = E.transpose(-1, -2) @ L @ E  # (..., N, 2, 2)
        sigma, _ = _principal_sigma(G)  # relative principal stretches, largest first

        curved = curvatures is not None and directions is not None
        if curved:
            d1 = directions[..., 0, :]
            alpha = torch.atan2((d1 * e2).sum(-1), (d1 * e1).sum(-1))  # (N,) angle of d1 from e1
            k1, k2 = curvatures[..., 0], curvatures[..., 1]
        if self.mode == "affine":
            phi, lam = _affine_ellipse(G, scales[..., :2].to(work))
        else:
            if curved:
                phi = torch.remainder(alpha + 0.25 * math.pi, 0.5 * math.pi) - 0.25 * math.pi
                if self.umbilic_tol > 0:
                    phi = phi * ((k1 - k2).abs() / self.umbilic_tol).clamp(max=1.0)
                if self.anisotropy_tol > 0:
                    aniso = (sigma[..., 0] - sigma[..., 1]) / sigma[..., 1].clamp_min(1e-12)
                    phi = phi * (aniso / self.anisotropy_tol).clamp(max=1.0)
            else:
                phi = rotations.new_zeros(N)
            cp, sp = torch.cos(phi), torch.sin(phi)
            U = torch.stack([torch.stack([cp, -sp], -1), torch.stack([sp, cp], -1)], -2)  # columns u1, u2
            GU = G @ U
            lam = (GU * GU).sum(-2).clamp_min(1e-30).sqrt()  # (..., N, 2), ‖G u_i‖
        lam = lam.clamp(*self.stretch_range)
        if curved:  # Euler's curvature along the corrected axes
            theta = alpha - phi
            c2, s2 = torch.cos(theta) ** 2, torch.sin(theta) ** 2
            kappa = torch.stack([k1 * c2 + k2 * s2, k1 * s2 + k2 * c2], -1)
        else:
            kappa = torch.zeros_like(lam)
        factor = lam / (1 + self.w_s * kappa.abs())
        sigma_abs = sigma * r.unsqueeze(-1)

        half = 0.5 * phi
        zero = torch.zeros_like(half)
        dq = torch.stack([torch.cos(half), zero, zero, torch.sin(half)], -1)  # (..., N, 4)
        vq = valid.unsqueeze(-1)
        ident = dq.new_tensor([1.0, 0.0, 0.0, 0.0])
        dq = torch.where(vq, dq, ident).expand(*batch, N, 4)
        factor = torch.where(vq, factor, torch.ones_like(factor))
        lam = torch.where(vq, lam, torch.ones_like(lam))
        angle = torch.where(valid, phi, torch.zeros_like(phi)).expand(*batch, N)
        return CorrectionResult(dq.to(dtype), factor.to(dtype), lam.to(dtype), sigma_abs.to(dtype), angle.to(dtype), valid)

    @staticmethod
    def apply(result: CorrectionResult, quats: torch.Tensor, scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected surfel rotations and scales.

        quats: (..., N, 4) any of the surfel's quaternions (local, canonical or posed; wxyz);
        scales: (..., N, 2) or (..., N, 3) posed scales (a third, normal-axis scale is kept).
        Returns (q ⊗ dq, scales with the in-plane columns multiplied by the factors).
        """
        q = quat_multiply(quats, result.quat)
        s = scales[..., :2] * result.scale_factor
        if scales.shape[-1] > 2:
            s = torch.cat([s, scales[..., 2:]], -1)
        return q, s
