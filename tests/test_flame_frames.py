"""Per-triangle frames: orthonormal, det +1, normal column, k, local<->world round trip."""

from __future__ import annotations

import torch

from sage_core.flame import surfel_frames, triangle_frames


def _mesh(B: int = 2, V: int = 20, F: int = 15, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    verts = torch.randn(B, V, 3, generator=g, dtype=torch.float64)
    faces = torch.stack([torch.randperm(V, generator=g)[:3] for _ in range(F)])
    return verts, faces


def _face_normal(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    v0, v1, v2 = verts[..., faces[:, 0], :], verts[..., faces[:, 1], :], verts[..., faces[:, 2], :]
    n = torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)
    return n / n.norm(dim=-1, keepdim=True)


def test_triangle_frames_properties() -> None:
    verts, faces = _mesh()
    R, T, k = triangle_frames(verts, faces)
    assert R.shape == (2, 15, 3, 3) and T.shape == (2, 15, 3) and k.shape == (2, 15)
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(2, 15, dtype=torch.float64))
    torch.testing.assert_close(R[..., 1], _face_normal(verts, faces))
    v0, v1, v2 = (verts[:, faces[:, i]] for i in range(3))
    e1 = v1 - v0
    torch.testing.assert_close(R[..., 0], e1 / e1.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(T, (v0 + v1 + v2) / 3)
    area2 = torch.linalg.cross(e1, v2 - v0, dim=-1).norm(dim=-1)
    torch.testing.assert_close(k, 0.5 * (e1.norm(dim=-1) + area2 / e1.norm(dim=-1)))


def test_known_triangle() -> None:
    verts = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.5, 1.0, 0.0]])
    faces = torch.tensor([[0, 1, 2]])
    R, T, k = triangle_frames(verts, faces)
    torch.testing.assert_close(R[0], torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]))
    torch.testing.assert_close(k[0], torch.tensor(1.5))
    Rs, _, _ = surfel_frames(verts, faces)
    torch.testing.assert_close(Rs[0], torch.eye(3))  # a flat triangle in xy gives the identity


def test_surfel_frames_normal_third_column() -> None:
    verts, faces = _mesh(seed=1)
    R, T, k = triangle_frames(verts, faces)
    Rs, Ts, ks = surfel_frames(verts, faces)
    torch.testing.assert_close(Rs[..., 2], _face_normal(verts, faces))
    torch.testing.assert_close(torch.linalg.det(Rs), torch.ones(2, 15, dtype=torch.float64))
    rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)  # Rx(-90°)
    torch.testing.assert_close(Rs, R @ rx)
    torch.testing.assert_close(Ts, T)
    torch.testing.assert_close(ks, k)
    # points of the triangle have a zero third (normal) coordinate in the surfel frame
    v0, v2 = verts[:, faces[:, 0]], verts[:, faces[:, 2]]
    loc = (Rs.transpose(-1, -2) @ (v2 - v0)[..., None])[..., 0]
    assert loc[..., 2].abs().max() < 1e-12


def test_local_world_round_trip() -> None:
    verts, faces = _mesh(seed=2)
    for fn in (triangle_frames, surfel_frames):
        R, T, k = fn(verts, faces)
        mu_loc = torch.randn(2, 15, 3, dtype=torch.float64)
        mu = k[..., None] * (R @ mu_loc[..., None])[..., 0] + T
        back = (R.transpose(-1, -2) @ (mu - T)[..., None])[..., 0] / k[..., None]
        torch.testing.assert_close(back, mu_loc)


def test_frames_follow_a_rigid_motion() -> None:
    verts, faces = _mesh(B=1, seed=3)
    Q, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)))
    if torch.linalg.det(Q) < 0:
        Q = -Q
    t = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    R, T, k = surfel_frames(verts, faces)
    R2, T2, k2 = surfel_frames(verts @ Q.T + t, faces)
    torch.testing.assert_close(R2, Q @ R)
    torch.testing.assert_close(T2, T @ Q.T + t)
    torch.testing.assert_close(k2, k)


def test_gradients_and_float32() -> None:
    verts, faces = _mesh(seed=5)
    verts = verts.float().requires_grad_(True)
    R, T, k = surfel_frames(verts, faces)
    assert R.dtype == torch.float32
    (R.sum() + T.square().sum() + k.sum()).backward()
    assert verts.grad is not None and torch.isfinite(verts.grad).all() and verts.grad.abs().sum() > 0
    v64 = verts.detach().double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: surfel_frames(v, faces[:4]), (v64[:1],))


def test_unbatched_and_degenerate() -> None:
    verts, faces = _mesh(B=1, seed=6)
    R1, T1, k1 = triangle_frames(verts[0], faces.numpy())
    R, T, k = triangle_frames(verts, faces)
    torch.testing.assert_close(R1, R[0])
    torch.testing.assert_close(k1, k[0])
    degenerate = torch.zeros(3, 3)
    R, T, k = triangle_frames(degenerate, torch.tensor([[0, 1, 2]]))
    assert torch.isfinite(R).all() and torch.isfinite(k).all()
