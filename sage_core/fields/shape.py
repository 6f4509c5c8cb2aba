"""Shape network f_shape(x, {interp(x, Phi_l)}_l) -> surfel rotation and scales via a symmetric eigensolve.

The MLP predicts the 6 lower-triangular entries of a symmetric 3x3 matrix A (a Hessian-like operator) and a
scalar. ``eigh(A)`` gives three orthonormal eigenvectors: the one with the smallest |eigenvalue| is the
surfel normal (third rotation column), the other two span the tangent plane (first and second columns,
ordered by decreasing |eigenvalue|, so s1 >= s2), and the second tangent is flipped when needed so that
det R = +1. The two tangent |eigenvalues| set the anisotropy, the scalar the overall size.

Gradient guard: ``safe_eigh`` uses eigh's analytic backward with every eigenvalue gap clamped to at least
``eig_gap`` in magnitude, so the 1/(lambda_i - lambda_j) factors stay bounded (<= 1/eig_gap) and the
gradients stay finite at repeated eigenvalues, where torch's own backward returns inf/nan.

Eigensolver backends (``EIGH_BACKENDS``, the ``backend`` argument of ``safe_eigh`` and
``frame_from_symmetric``): ``torch`` is ``torch.linalg.eigh``, the reference (LAPACK, one call per
matrix on the CPU); ``cpp`` is the batched 3x3 Jacobi solver of ``_cpp_eigh`` (CPU float32/float64
(..., 3, 3) only); ``auto`` (the default) takes ``cpp`` where it applies and builds, ``torch``
otherwise (CUDA, other sizes or dtypes; a missing build warns once). The two agree in the eigenvalues
(ascending) to rounding. What may differ is the eigenvectors' sign (``cpp`` makes each one's entry of
largest magnitude positive, LAPACK fixes no sign) and, for repeated eigenvalues, the orthonormal basis
chosen in their eigenspace. In ``frame_from_symmetric`` this changes R only by column signs (det R
stays +1; with a reference normal the normal is the same and (t1, t2) may become (-t1, -t2), a half
turn about the normal) or, for equal tangent |eigenvalues|, by a turn about the normal where s1 = s2:
the surfel, R·diag(s1^2, s2^2, 0)·R^T, and the scales are the same. The quaternion may differ
accordingly. The backward is the same formula for both (:func:`eigh_backward_torch`); after the
``cpp`` solver it runs natively (``_cpp_eigh.eigh3_backward``, the same values bit for bit).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ..geometry.rotations import matrix_to_quat

EIGH_BACKENDS = ("auto", "torch", "cpp")

# column of the tril entries (a00, a10, a11, a20, a21, a22) that holds entry (i, j) of the symmetric matrix
_SYM_FROM_TRIL = torch.tensor([[0, 1, 3], [1, 2, 4], [3, 4, 5]])


def resolve_eigh_backend(backend: str, a: torch.Tensor) -> str:
    """``auto|torch|cpp`` for the symmetric matrices a (..., n, n) -> the solver that runs: ``torch`` or ``cpp``.

    ``auto`` gives ``cpp`` for CPU float32/float64 3x3 matrices when the extension builds (a failed build
    warns once), ``torch`` otherwise; an explicit ``cpp`` raises ValueError when it cannot run.
    """
    if backend not in EIGH_BACKENDS:
        raise ValueError(f"safe_eigh: unknown backend {backend!r} (choose from {', '.join(EIGH_BACKENDS)})")
    if backend == "torch":
        return "torch"
    from . import _cpp_eigh

    why = _cpp_eigh.supports(a)
    if why is not None:
        if backend == "cpp":
            raise ValueError(f"safe_eigh: backend='cpp' cannot take this input: {why}")
        return "torch"
    return _cpp_eigh.EXT.choose(backend, "safe_eigh")


def eigh(a: torch.Tensor, backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """Eigenvalues (..., n) ascending and eigenvectors (..., n, n) (columns) of symmetric a (..., n, n),
    without a gradient, from the solver ``resolve_eigh_backend(backend, a)`` picks (see the module doc)."""
    if resolve_eigh_backend(backend, a) == "cpp":
        from . import _cpp_eigh

        return _cpp_eigh.eigh3(a)
    return torch.linalg.eigh(a.detach())


def eigh_backward_torch(
    evals: torch.Tensor, evecs: torch.Tensor, g_evals: torch.Tensor | None, g_evecs: torch.Tensor | None, gap: float
) -> torch.Tensor:
    """The gap-clamped eigh backward (the reference; ``_cpp_eigh.eigh3_backward`` runs it for the ``cpp``
    solver). evals (..., n), evecs (..., n, n) columns; g_evals, g_evecs their upstream gradients (either
    may be None) -> the gradient of the symmetric input (..., n, n):
    ``sym(V (V^T gV / safe * (1 - I) + diag(gw)) V^T)``, ``safe_ij = sign(l_j - l_i) max(|l_j - l_i|, gap)``."""
    vt = evecs.transpose(-1, -2)
    inner = torch.zeros_like(evecs)
    if g_evecs is not None:
        diff = evals[..., None, :] - evals[..., :, None]  # (.., i, j) = l_j - l_i
        sign = torch.where(diff >= 0, torch.ones_like(diff), -torch.ones_like(diff))
        safe = sign * diff.abs().clamp_min(gap)
        eye = torch.eye(evals.shape[-1], dtype=evals.dtype, device=evals.device)
        inner = (vt @ g_evecs) / safe * (1.0 - eye)
    if g_evals is not None:
        inner = inner + torch.diag_embed(g_evals)
    g_a = evecs @ inner @ vt
    return 0.5 * (g_a + g_a.transpose(-1, -2))


class _SafeEigh(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a: torch.Tensor, gap: float, backend: str):  # type: ignore[override]
        chosen = resolve_eigh_backend(backend, a)
        evals, evecs = eigh(a, chosen)
        ctx.save_for_backward(evals, evecs)
        ctx.gap = gap
        ctx.native = chosen == "cpp"
        return evals, evecs

    @staticmethod
    def backward(ctx, g_evals: torch.Tensor | None, g_evecs: torch.Tensor | None):  # type: ignore[override]
        evals, evecs = ctx.saved_tensors
        if ctx.native:
            from . import _cpp_eigh

            return _cpp_eigh.eigh3_backward(evals, evecs, g_evals, g_evecs, ctx.gap), None, None
        return eigh_backward_torch(evals, evecs, g_evals, g_evecs, ctx.gap), None, None


def safe_eigh(a: torch.Tensor, gap: float = 1e-3, backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """Symmetric eigen-decomposition with a gap-clamped backward.

    a: (..., n, n) symmetric -> eigenvalues (..., n) ascending, eigenvectors (..., n, n) as columns.
    backend: the eigensolver (``auto``, ``torch`` or ``cpp``, see the module doc).
    """
    return _SafeEigh.apply(a, gap, backend)


def symmetric_from_tril(entries: torch.Tensor) -> torch.Tensor:
    """entries (N, 6) in order a00, a10, a11, a20, a21, a22 -> symmetric (N, 3, 3).

    One gather: entry (i, j) and (j, i) both read the same input column, so the values are exact and
    the gradient of an off-diagonal input is the sum of the two mirrored output gradients."""
    return entries[:, _SYM_FROM_TRIL.to(entries.device)]


def frame_from_symmetric(
    a: torch.Tensor, reference_normal: torch.Tensor | None = None, gap: float = 1e-3, backend: str = "auto"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Surfel frame from a symmetric matrix.

    a: (N, 3, 3) symmetric; reference_normal: optional (N, 3), the normal is flipped to face it;
    backend: the eigensolver (see the module doc: the backends may give (t1, t2) opposite signs, the
    same surfel). Returns R (N, 3, 3) with columns (t1, t2, n), det +1, and the tangent |eigenvalues|
    (N, 2), |l1| >= |l2|.
    """
    evals, evecs = safe_eigh(a, gap, backend)
    order = torch.argsort(evals.abs().detach(), dim=-1, descending=True)  # t1, t2, normal
    vecs = torch.gather(evecs, 2, order[:, None, :].expand(-1, 3, -1))
    mags = torch.gather(evals.abs(), 1, order)
    t1, t2, nrm = vecs[:, :, 0], vecs[:, :, 1], vecs[:, :, 2]
    if reference_normal is not None:
        flip = torch.where((nrm * reference_normal).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(nrm.dtype)
        nrm = nrm * flip
    det_sign = torch.where((torch.cross(t1, t2, dim=-1) * nrm).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    t2 = t2 * det_sign.to(t2.dtype)
    rot = torch.stack([t1, t2, nrm], -1)
    return rot, mags[:, :2]


class ShapeNetwork(nn.Module):
    """Surfel rotation (quaternion, wxyz) and two scales from the multi-level hash features at x.

    ``forward(x, level_features, base_scale=None, reference_normal=None)``:
        x: (N, 3) canonical world points (normalized with the box to [-1, 1]).
        level_features: (N, L*F) or (N, L, F) interpolated hash features (``SDFNetwork.encoding(x)``).
        base_scale: optional (N,) per-point size (e.g. the bound triangle's scale); default ``base_scale``.
        reference_normal: optional (N, 3); the surfel normal is oriented to agree with it (e.g. grad f).
    Returns quats (N, 4) wxyz, scales (N, 2) with s1 >= s2 > 0, rotation (N, 3, 3) columns (t1, t2, n).

    Scales: ``m = base * (s_min + (s_max - s_min) * sigmoid(scalar))`` and, with the tangent |eigenvalues|
    a1 >= a2 and r_k = a_k / ((a1 + a2)/2) in [0, 2], ``s_k = m * (r_min + (1 - r_min) * r_k)``, so the
    aspect ratio stays within [r_min, 2 - r_min] relative to m.

    Args:
        in_features: L*F of the hash grid.
        bbox_min, bbox_max: (3,) box used to normalize x.
        hidden: MLP width; n_layers: hidden layers (ReLU).
        base_scale: default size in world units when no per-point base is given.
        s_min, s_max: bounds of the size multiplier.
        r_min: smallest relative tangent scale (anisotropy bound).
        eig_gap: eigenvalue-gap clamp of the eigh backward.

    Presets: ``tiny`` hidden 32, 2 layers; ``default`` hidden 64, 2 layers.
    """

    def __init__(
        self,
        in_features: int,
        bbox_min: Sequence[float] | torch.Tensor,
        bbox_max: Sequence[float] | torch.Tensor,
        hidden: int = 64,
        n_layers: int = 2,
        base_scale: float = 1e-3,
        s_min: float = 0.1,
        s_max: float = 3.0,
        r_min: float = 0.05,
        eig_gap: float = 1e-3,
    ) -> None:
        super().__init__()
        if not 0.0 < s_min < s_max:
            raise ValueError("need 0 < s_min < s_max")
        if not 0.0 < r_min < 1.0:
            raise ValueError("need 0 < r_min < 1")
        lo = torch.as_tensor(bbox_min, dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(bbox_max, dtype=torch.float32).reshape(3)
        self.register_buffer("center", 0.5 * (lo + hi))
        self.half_extent = float(0.5 * (hi - lo).max().item())
        self.in_features = int(in_features)
        self.base_scale = float(base_scale)
        self.s_min, self.s_max, self.r_min = float(s_min), float(s_max), float(r_min)
        self.eig_gap = float(eig_gap)
        dims = [3 + self.in_features] + [hidden] * n_layers + [7]
        layers: list[nn.Module] = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                layers.append(nn.ReLU())
        self.mlp = nn.Sequential(*layers)

    def forward(
        self,
        x: torch.Tensor,
        level_features: torch.Tensor,
        base_scale: torch.Tensor | None = None,
        reference_normal: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """See the class docstring: -> quats (N, 4), scales (N, 2), rotation (N, 3, 3)."""
        feats = level_features.reshape(x.shape[0], -1)
        xn = (x - self.center.to(x.dtype)) / self.half_extent
        out = self.mlp(torch.cat([xn, feats], -1))
        a = symmetric_from_tril(out[:, :6])
        rot, mags = frame_from_symmetric(a, reference_normal, self.eig_gap)
        ratio = mags / (0.5 * mags.sum(-1, keepdim=True) + 1e-12)
        size = self.s_min + (self.s_max - self.s_min) * torch.sigmoid(out[:, 6])
        base = self.base_scale if base_scale is None else base_scale
        m = size * base
        scales = m[:, None] * (self.r_min + (1.0 - self.r_min) * ratio)
        return matrix_to_quat(rot), scales, rot
