"""Surfel ↔ triangle binding maths: local ↔ world transforms and nearest-triangle queries.

Frames are sage's surfel frames (:func:`sage_core.flame.surfel_frames`): per face f a rotation
R_f (3, 3) whose first two columns span the triangle's plane and whose third column is the face
normal, the centroid T_f and the scale k_f (docs/formats.md §6). For a surfel bound to face b:

    μ = k_b·R_b·μ_loc + T_b,    s = k_b·exp(ŝ_loc)  (two in-plane axes),    q = q(R_b) ⊗ normalize(q_loc)

so R(q) = R_b·R(q_loc) and a surfel with q_loc = identity lies flat on its triangle (its normal,
the third column of R(q), is the face normal). Quaternions are wxyz (Hamilton product).
"""

from __future__ import annotations

import numpy as np
import torch

from ..geometry.rotations import matrix_to_quat, quat_conjugate, quat_multiply, quat_normalize

_K_MIN = 1e-12
_AREA_EPS = 1e-30


def _gather_faces(x: torch.Tensor, binding: torch.Tensor, tail: int) -> torch.Tensor:
    """x: (..., F, *tail dims) -> (..., N, *tail dims), rows picked by ``binding`` (N,)."""
    dim = x.dim() - 1 - tail
    return torch.index_select(x, dim, binding.to(device=x.device, dtype=torch.long))


def local_to_world(
    mu_loc: torch.Tensor,
    q_loc: torch.Tensor,
    s_loc: torch.Tensor,
    binding: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    k: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose bound surfels with per-face frames of one frame or a batch of frames.

    mu_loc: (N, 3) positions in k-normalised face coordinates; q_loc: (N, 4) wxyz, need not be
    unit; s_loc: (N, 2) log in-plane scales relative to k; binding: (N,) face ids.
    R: (..., F, 3, 3) surfel frames (normal = 3rd column); T: (..., F, 3); k: (..., F).
    Returns means (..., N, 3), quats (..., N, 4) unit wxyz, scales (..., N, 2) world standard
    deviations (not log). Differentiable in every floating input.
    """
    Rb = _gather_faces(R, binding, 2)  # (..., N, 3, 3)
    Tb = _gather_faces(T, binding, 1)  # (..., N, 3)
    kb = _gather_faces(k, binding, 0).clamp_min(_K_MIN)  # (..., N)
    qb = _gather_faces(matrix_to_quat(R), binding, 1)  # (..., N, 4)
    means = kb[..., None] * (Rb @ mu_loc[..., None]).squeeze(-1) + Tb
    quats = quat_multiply(qb, quat_normalize(q_loc).expand_as(qb))
    scales = kb[..., None] * torch.exp(s_loc)
    return means, quats, scales


def world_to_local(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    binding: torch.Tensor,
    R: torch.Tensor,
    T: torch.Tensor,
    k: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inverse of :func:`local_to_world` for one frame.

    means: (N, 3); quats: (N, 4) wxyz (normalised here); scales: (N, 2) world standard deviations
    (> 0); binding: (N,); R: (F, 3, 3); T: (F, 3); k: (F,).
    Returns mu_loc = R_bᵀ(μ − T_b)/k_b (N, 3), q_loc = q(R_b)⁻¹ ⊗ q (N, 4, unit) and
    s_loc = log(s/k_b) (N, 2).
    """
    Rb = _gather_faces(R, binding, 2)
    Tb = _gather_faces(T, binding, 1)
    kb = _gather_faces(k, binding, 0).clamp_min(_K_MIN)
    qb = _gather_faces(matrix_to_quat(R), binding, 1)
    mu_loc = (Rb.transpose(-1, -2) @ (means - Tb)[..., None]).squeeze(-1) / kb[..., None]
    q_loc = quat_multiply(quat_conjugate(qb), quat_normalize(quats))
    s_loc = torch.log(scales) - torch.log(kb)[..., None]
    return mu_loc, q_loc, s_loc


def point_triangle_distance(
    points: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
) -> torch.Tensor:
    """Exact Euclidean distance from points to triangles (broadcasting).

    points, a, b, c: (..., 3), the triangle's corners. Returns (...,). The closest point is the
    projection on the plane when it falls inside the triangle, otherwise the closest point of the
    three edges; degenerate (zero-area) triangles reduce to their edges. Differentiable.
    """
    return point_triangle_sq_distance(points, a, b, c).clamp_min(0).sqrt()


def _segment_sq_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    ab = b - a
    denom = (ab * ab).sum(-1)
    t = ((p - a) * ab).sum(-1) / torch.where(denom > 0, denom, torch.ones_like(denom))
    t = torch.where(denom > 0, t.clamp(0.0, 1.0), torch.zeros_like(t))
    d = p - (a + t[..., None] * ab)
    return (d * d).sum(-1)


def point_triangle_sq_distance(
    points: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
) -> torch.Tensor:
    """Squared version of :func:`point_triangle_distance`; (..., 3) inputs -> (...,)."""
    ab = b - a
    ac = c - a
    ap = points - a
    n = torch.linalg.cross(ab, ac, dim=-1)
    nn = (n * n).sum(-1)
    ok = nn > _AREA_EPS
    safe_nn = torch.where(ok, nn, torch.ones_like(nn))
    beta = (n * torch.linalg.cross(ap, ac, dim=-1)).sum(-1) / safe_nn
    gamma = (n * torch.linalg.cross(ab, ap, dim=-1)).sum(-1) / safe_nn
    inside = ok & (beta >= 0) & (gamma >= 0) & (beta + gamma <= 1)
    plane = (ap * n).sum(-1) ** 2 / safe_nn
    edges = torch.minimum(
        torch.minimum(_segment_sq_distance(points, a, b), _segment_sq_distance(points, b, c)),
        _segment_sq_distance(points, c, a),
    )
    return torch.where(inside, plane, edges)


def _candidate_faces(candidates: torch.Tensor | np.ndarray | None, n_faces: int, device: torch.device) -> torch.Tensor:
    """Face ids (M,) int64 allowed by ``candidates`` ((F,) bool mask or ids; None = all)."""
    if candidates is None:
        return torch.arange(n_faces, device=device)
    c = torch.as_tensor(candidates, device=device)
    if c.dtype == torch.bool:
        if c.shape != (n_faces,):
            raise ValueError(f"candidate mask must have shape ({n_faces},), got {tuple(c.shape)}")
        c = torch.nonzero(c, as_tuple=False).reshape(-1)
    c = c.to(torch.long).reshape(-1)
    if c.numel() and (int(c.min()) < 0 or int(c.max()) >= n_faces):
        raise ValueError(f"candidate face ids must lie in [0, {n_faces})")
    if c.numel() == 0:
        raise ValueError("no candidate faces")
    return c


def _nearest_torch(points: torch.Tensor, tri: torch.Tensor, chunk_pairs: int) -> torch.Tensor:
    """Brute force over all triangles. points: (N, 3); tri: (M, 3, 3). Returns (N,) row ids."""
    M = tri.shape[0]
    a, b, c = (x[None] for x in tri.unbind(1))  # (1, M, 3)
    step = max(1, chunk_pairs // max(M, 1))
    out = []
    for i in range(0, points.shape[0], step):
        p = points[i : i + step, None, :]
        out.append(point_triangle_sq_distance(p, a, b, c).argmin(dim=1))
    if not out:
        return torch.zeros(0, dtype=torch.long, device=points.device)
    return torch.cat(out)


def _nearest_igl(points: torch.Tensor, tri_faces: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    import igl

    P = points.detach().to("cpu", torch.float64).numpy()
    V = vertices.detach().to("cpu", torch.float64).numpy()
    Fc = np.ascontiguousarray(tri_faces.detach().to("cpu", torch.long).numpy())
    _, idx, _ = igl.point_mesh_squared_distance(P, V, Fc)
    return torch.as_tensor(np.asarray(idx, dtype=np.int64), device=points.device)


def _have_igl() -> bool:
    try:
        import igl  # noqa: F401
    except ImportError:
        return False
    return True


def nearest_triangles(
    points: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    candidates: torch.Tensor | np.ndarray | None = None,
    method: str = "auto",
    chunk_pairs: int = 1 << 22,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest triangle of every point (exact point–triangle distance).

    points: (N, 3); vertices: (V, 3); faces: (F, 3); candidates: None (all faces), an (F,) bool
    mask or an (M,) array of allowed face ids. method: "igl" (libigl's AABB tree on the CPU),
    "torch" (chunked brute force on the points' device, at most ``chunk_pairs`` point–triangle
    pairs at once) or "auto" (igl when importable, else torch).
    Returns face_id (N,) int64 into ``faces`` and distance (N,) on the points' device. The search
    is not differentiable; the distance is recomputed for the chosen faces in torch and is
    differentiable in ``points`` and ``vertices``. Among equally near faces any one may be returned.
    """
    if method not in ("auto", "igl", "torch"):
        raise ValueError(f"unknown method {method!r}; use auto, igl or torch")
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")
    device = points.device
    faces = faces.to(device=device, dtype=torch.long)
    vertices = vertices.to(device=device, dtype=points.dtype)
    allowed = _candidate_faces(candidates, faces.shape[0], device)
    sub = faces[allowed]
    use_igl = method == "igl" or (method == "auto" and _have_igl())
    with torch.no_grad():
        if points.shape[0] == 0:
            rows = torch.zeros(0, dtype=torch.long, device=device)
        elif use_igl:
            rows = _nearest_igl(points, sub, vertices)
        else:
            rows = _nearest_torch(points.detach(), vertices.detach()[sub], chunk_pairs)
    face_id = allowed[rows]
    tri = vertices[faces[face_id]]  # (N, 3, 3)
    distance = point_triangle_distance(points, tri[:, 0], tri[:, 1], tri[:, 2])
    return face_id, distance
