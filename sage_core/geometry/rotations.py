"""Rotation helpers: quaternions (w, x, y, z), rotation matrices and axis-angle.

All functions are batched over leading dimensions, differentiable and device-agnostic.
"""

from __future__ import annotations

import torch


def quat_normalize(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit quaternions. q: (..., 4) wxyz -> (..., 4)."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from (possibly unnormalised) quaternions.

    q: (..., 4) wxyz -> (..., 3, 3); columns are the rotated x, y, z axes.
    """
    q = quat_normalize(q)
    w, x, y, z = q.unbind(-1)
    row0 = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    row1 = torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)
    row2 = torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return torch.stack([row0, row1, row2], -2)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Quaternions (wxyz, w >= 0) from proper rotation matrices.

    R: (..., 3, 3) -> (..., 4). Uses the numerically stable branch per element (largest diagonal
    term), so it is accurate for every rotation angle.
    """
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cands = torch.stack(
        [
            torch.stack([1 + tr, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
            torch.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
            torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
        ],
        -2,
    )  # (..., 4 candidates, 4)
    diag = torch.stack([tr, m00, m11, m22], -1)
    best = diag.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = quat_normalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a ⊗ b, so that R(a ⊗ b) = R(a)·R(b). a, b: (..., 4) wxyz -> (..., 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse of a unit quaternion). q: (..., 4) -> (..., 4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def axis_angle_to_matrix(aa: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Rodrigues' formula as FLAME/SMPL use it.

    aa: (..., 3) axis-angle in radians -> (..., 3, 3). The angle is ``|aa + eps|`` (eps added
    elementwise before the norm), which keeps the gradient finite at zero rotation.
    """
    angle = (aa + eps).norm(dim=-1, keepdim=True)  # (..., 1)
    k = aa / angle
    kx, ky, kz = k.unbind(-1)
    zero = torch.zeros_like(kx)
    K = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], -1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(K)
    s = torch.sin(angle)[..., None]
    c = torch.cos(angle)[..., None]
    return eye + s * K + (1 - c) * (K @ K)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle (..., 3) from rotation matrices (..., 3, 3), via the quaternion."""
    q = matrix_to_quat(R)
    w = q[..., :1].clamp(-1.0, 1.0)
    v = q[..., 1:]
    sin_half = v.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(sin_half, w)
    scale = torch.where(sin_half > 1e-8, angle / sin_half.clamp_min(1e-12), torch.full_like(angle, 2.0))
    return v * scale
