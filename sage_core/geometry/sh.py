"""Real spherical harmonics of degree 0-3 (orthonormal on the sphere, 3DGS coefficient order),
shared by the surfel rasterizer and the appearance network."""

from __future__ import annotations

import torch

_Y0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
_Y1 = 0.4886025119029199  # sqrt(3 / (4 pi))
_Y2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_Y3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_coeffs(degree: int) -> int:
    """Number of coefficients of a degree-``degree`` expansion: (degree + 1)²."""
    return (degree + 1) ** 2


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Basis values Y_k(d) in the 3DGS coefficient order.

    dirs: (..., 3) unit directions -> (..., (degree+1)²).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, _Y0)]
    if degree >= 1:
        out += [-_Y1 * y, _Y1 * z, -_Y1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            _Y2[0] * x * y,
            _Y2[1] * y * z,
            _Y2[2] * (2 * zz - xx - yy),
            _Y2[3] * x * z,
            _Y2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _Y3[0] * y * (3 * xx - yy),
            _Y3[1] * x * y * z,
            _Y3[2] * y * (4 * zz - xx - yy),
            _Y3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _Y3[4] * x * (4 * zz - xx - yy),
            _Y3[5] * z * (xx - yy),
            _Y3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, -1)


def eval_sh_colors(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """View-dependent colour as in 3DGS: max(Σ_k c_k Y_k(d) + 0.5, 0).

    coeffs: (N, K, 3) with K ≥ (degree+1)²; only the first (degree+1)² are used.
    dirs: (N, 3) unit directions from the camera centre to the surfel. Returns (N, 3).
    """
    n = num_sh_coeffs(degree)
    if coeffs.shape[-2] < n:
        raise ValueError(f"sh_degree {degree} needs {n} coefficients per surfel, got {coeffs.shape[-2]}")
    basis = sh_basis(dirs, degree)  # (N, n)
    rgb = (basis.unsqueeze(-1) * coeffs[..., :n, :]).sum(-2)
    return (rgb + 0.5).clamp_min(0.0)
