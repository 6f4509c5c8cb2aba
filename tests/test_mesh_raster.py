"""Mesh rasterizer vs brute-force ray casting, ray generation and ray warping through triangle frames."""

from __future__ import annotations

import math
import time

import pytest
import torch

from sage_core.data.cameras import look_at
from sage_core.flame.frames import surfel_frames, triangle_frames
from sage_core.geometry.rotations import axis_angle_to_matrix
from sage_core.render.mesh_raster import (
    points_on_mesh,
    rasterize_mesh,
    ray_directions,
    warp_directions_to_canonical,
    warp_points_to_canonical,
    warp_rays_to_canonical,
)


def _camera(width: int, height: int, dtype=torch.float64, eye=(0.05, -0.03, 1.0)):
    K = torch.tensor([[1.3 * width, 0.0, 0.52 * width], [0.0, 1.25 * width, 0.47 * height], [0.0, 0.0, 1.0]], dtype=dtype)
    w2c = torch.as_tensor(look_at(eye, (0.0, 0.0, 0.0)), dtype=dtype)
    return K, w2c


def _random_mesh(n_faces: int, seed: int, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(n_faces, 1, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([0.5, 0.5, 0.3], dtype=dtype)
    verts = (centres + 0.3 * (torch.rand(n_faces, 3, 3, generator=g, dtype=dtype) - 0.5)).reshape(-1, 3)
    faces = torch.arange(3 * n_faces).reshape(n_faces, 3)
    return verts, faces


def _brute_force(verts, faces, K, w2c, width, height):
    """Möller–Trumbore for every pixel-centre ray against every triangle; nearest hit.

    Returns face (H*W,), bary (H*W, 3), depth (H*W,) and the gap between the two nearest hits."""
    origins, dirs = ray_directions(K, w2c, width, height)
    o = origins[0].reshape(-1, 1, 3)
    d = dirs[0].reshape(-1, 1, 3)
    tri = verts[faces]  # (F, 3, 3)
    v0, v1, v2 = tri[:, 0][None], tri[:, 1][None], tri[:, 2][None]
    e1, e2 = (v1 - v0).expand(d.shape[0], -1, -1), (v2 - v0).expand(d.shape[0], -1, -1)
    d = d.expand_as(e2)
    p = torch.linalg.cross(d, e2, dim=-1)
    det = (e1 * p).sum(-1)
    inv = 1.0 / det
    s = (o - v0).expand_as(e1)
    u = (s * p).sum(-1) * inv
    q = torch.linalg.cross(s, e1, dim=-1)
    v = (d * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    hit = (det.abs() > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = torch.where(hit, t, torch.full_like(t, float("inf")))
    top2 = torch.topk(t, 2, dim=1, largest=False)
    best = top2.indices[:, 0]
    tbest = top2.values[:, 0]
    gap = torch.nan_to_num(top2.values[:, 1] - tbest, nan=float("inf"))
    rows = torch.arange(t.shape[0])
    bary = torch.stack([1 - u[rows, best] - v[rows, best], u[rows, best], v[rows, best]], -1)
    face = torch.where(torch.isfinite(tbest), best, torch.full_like(best, -1))
    dir_cam_z = (dirs[0].reshape(-1, 3) @ w2c[:3, :3].T)[:, 2]
    depth = tbest * dir_cam_z
    return face, bary, depth, gap


@pytest.mark.parametrize("seed", [0, 1])
def test_matches_brute_force_ray_casting(seed):
    W, H = 40, 30
    verts, faces = _random_mesh(20, seed)
    K, w2c = _camera(W, H)
    out = rasterize_mesh(verts, faces, K, w2c, W, H, max_pairs=257)  # small chunks exercise the chunk merge
    face_bf, bary_bf, depth_bf, gap = _brute_force(verts, faces, K, w2c, W, H)
    face = out.face_id[0].reshape(-1)
    bary = out.bary[0].reshape(-1, 3)
    depth = out.depth[0].reshape(-1)
    # pixels whose centre lies on an edge or where two surfaces are at nearly the same depth are ambiguous
    clear = (gap > 1e-6) & ((bary_bf.min(-1).values > 1e-7) | (face_bf < 0))
    assert clear.float().mean() > 0.9
    assert (face_bf >= 0).sum() > 150 and (face_bf < 0).sum() > 50
    assert torch.equal(face[clear], face_bf[clear])
    fg = clear & (face_bf >= 0)
    assert torch.allclose(bary[fg], bary_bf[fg], atol=1e-9)
    assert torch.allclose(depth[fg], depth_bf[fg], rtol=1e-10, atol=1e-12)
    bg = face < 0
    assert torch.all(torch.isinf(depth[bg])) and torch.all(bary[bg] == 0)
    assert torch.allclose(bary[~bg].sum(-1), torch.ones(int((~bg).sum()), dtype=bary.dtype))


def test_batched_views_and_broadcast():
    W, H = 24, 20
    verts, faces = _random_mesh(8, 3)
    K, w2c = _camera(W, H)
    _, w2c2 = _camera(W, H, eye=(-0.3, 0.1, 0.9))
    single = [rasterize_mesh(verts, faces, K, m, W, H) for m in (w2c, w2c2)]
    both = rasterize_mesh(verts, faces, K, torch.stack([w2c, w2c2]), W, H)
    assert both.face_id.shape == (2, H, W) and both.bary.shape == (2, H, W, 3) and both.depth.shape == (2, H, W)
    for b in range(2):
        assert torch.equal(both.face_id[b], single[b].face_id[0])
        assert torch.allclose(both.bary[b], single[b].bary[0])
    # a batch of meshes with one camera: frame 1 moved away from the camera is further in depth
    shifted = torch.stack([verts, verts - 0.2 * torch.tensor([0.05, -0.03, 1.0], dtype=verts.dtype)])
    frames = rasterize_mesh(shifted, faces, K, w2c, W, H)
    assert frames.face_id.shape == (2, H, W)
    assert torch.equal(frames.face_id[0], single[0].face_id[0])
    assert frames.mask[1].sum() < frames.mask[0].sum()


def test_background_and_behind_camera():
    W, H = 16, 12
    verts, faces = _random_mesh(5, 4)
    K, w2c = _camera(W, H)
    behind = verts + torch.tensor([0.05, -0.03, 1.0], dtype=verts.dtype) * 3.0  # the mesh moved behind the camera
    out = rasterize_mesh(behind, faces, K, w2c, W, H)
    assert torch.all(out.face_id == -1) and torch.all(torch.isinf(out.depth))


def test_depth_points_lie_on_mesh_and_gradients_flow():
    W, H = 32, 24
    verts, faces = _random_mesh(10, 5)
    verts.requires_grad_(True)
    K, w2c = _camera(W, H)
    out = rasterize_mesh(verts, faces, K, w2c, W, H)
    m = out.mask[0]
    origins, dirs = ray_directions(K, w2c, W, H)
    dir_z = (dirs[0] @ w2c[:3, :3].T)[..., 2]
    hit = origins[0] + dirs[0] * (out.depth[0] / dir_z).unsqueeze(-1)
    on_mesh = points_on_mesh(verts, faces, out.face_id[0][m], out.bary[0][m])
    assert torch.allclose(hit[m], on_mesh, atol=1e-9)
    out.depth[0][m].sum().backward()
    assert verts.grad is not None and torch.isfinite(verts.grad).all() and verts.grad.abs().sum() > 0


def test_ray_directions_project_to_pixel_centres():
    W, H = 9, 7
    K, w2c = _camera(W, H)
    origins, dirs = ray_directions(K, w2c, W, H)
    assert origins.shape == (1, H, W, 3) and dirs.shape == (1, H, W, 3)
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(1, H, W, dtype=dirs.dtype))
    pts = (origins + 0.7 * dirs)[0].reshape(-1, 3)
    Xc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = (Xc @ K.T)[:, :2] / (Xc @ K.T)[:, 2:]
    jj, ii = torch.meshgrid(torch.arange(W, dtype=K.dtype) + 0.5, torch.arange(H, dtype=K.dtype) + 0.5, indexing="xy")
    assert torch.allclose(uv, torch.stack([jj, ii], -1).reshape(-1, 2), atol=1e-9)
    assert torch.allclose(Xc[:, 2] > 0, torch.ones_like(Xc[:, 2], dtype=torch.bool))


@pytest.mark.parametrize("frame_fn", [triangle_frames, surfel_frames])
def test_ray_warp_inverts_rigid_motion(frame_fn):
    verts, faces = _random_mesh(12, 6)
    Q = axis_angle_to_matrix(torch.tensor([0.3, -0.5, 0.2], dtype=verts.dtype))
    t = torch.tensor([0.1, -0.2, 0.05], dtype=verts.dtype)
    moved = verts @ Q.T + t
    fc = frame_fn(verts, faces)
    fd = frame_fn(moved, faces)
    g = torch.Generator().manual_seed(0)
    face_id = torch.randint(0, faces.shape[0], (50,), generator=g)
    pts = torch.randn(50, 3, generator=g, dtype=verts.dtype)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=verts.dtype), dim=-1)
    pc, dc = warp_rays_to_canonical(pts, dirs, face_id, fd, fc)
    assert torch.allclose(pc, (pts - t) @ Q, atol=1e-10)
    assert torch.allclose(dc, dirs @ Q, atol=1e-10)


def test_ray_warp_similarity_maps_hit_points_to_canonical_surface():
    verts, faces = _random_mesh(6, 7)
    Q = axis_angle_to_matrix(torch.tensor([-0.2, 0.4, 0.1], dtype=verts.dtype))
    moved = 1.7 * verts @ Q.T + torch.tensor([0.0, 0.1, -0.1], dtype=verts.dtype)
    fc, fd = triangle_frames(verts, faces), triangle_frames(moved, faces)
    g = torch.Generator().manual_seed(1)
    face_id = torch.randint(0, faces.shape[0], (20,), generator=g)
    bary = torch.distributions.Dirichlet(torch.ones(3, dtype=verts.dtype)).sample((20,))
    pd = points_on_mesh(moved, faces, face_id, bary)
    pc = warp_points_to_canonical(pd, face_id, fd, fc)
    assert torch.allclose(pc, points_on_mesh(verts, faces, face_id, bary), atol=1e-10)
    raw = warp_directions_to_canonical(pd - moved[faces[face_id, 0]], face_id, fd, fc, normalize=False)
    assert torch.allclose(raw, pc - verts[faces[face_id, 0]], atol=1e-10)
    with pytest.raises(ValueError):
        warp_points_to_canonical(pd, torch.full_like(face_id, -1), fd, fc)


def test_full_resolution_speed():
    """A 10k-face closed surface at 550×802 in float32 finishes quickly and covers the expected area."""
    n_lat, n_lon = 50, 100
    lat = torch.linspace(0.0, math.pi, n_lat + 1)
    lon = torch.linspace(0.0, 2 * math.pi, n_lon + 1)[:-1]
    la, lo = torch.meshgrid(lat, lon, indexing="ij")
    r = 0.1
    verts = torch.stack([r * torch.sin(la) * torch.cos(lo), r * torch.cos(la), r * torch.sin(la) * torch.sin(lo)], -1).reshape(-1, 3)
    idx = torch.arange((n_lat + 1) * n_lon).reshape(n_lat + 1, n_lon)
    a, b = idx[:-1], idx[1:]
    a2, b2 = torch.roll(a, -1, 1), torch.roll(b, -1, 1)
    faces = torch.cat([torch.stack([a, b, b2], -1).reshape(-1, 3), torch.stack([a, b2, a2], -1).reshape(-1, 3)])
    W, H = 550, 802
    K = torch.tensor([[2000.0, 0, 275.0], [0, 2000.0, 401.0], [0, 0, 1.0]])
    w2c = torch.as_tensor(look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0)), dtype=torch.float32)
    t0 = time.perf_counter()
    out = rasterize_mesh(verts, faces, K, w2c, W, H)
    elapsed = time.perf_counter() - t0
    # silhouette of a sphere of radius r at distance 1: a disc of radius f·r/sqrt(1 − r²)
    rad = 2000.0 * r / math.sqrt(1 - r * r)
    expected = math.pi * rad * rad
    assert abs(out.mask.sum().item() - expected) / expected < 0.02
    assert out.depth[out.mask].min() > 0.89 and out.depth[out.mask].max() < 1.0
    assert elapsed < 20.0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    W, H = 64, 48
    verts, faces = _random_mesh(30, 8, dtype=torch.float32)
    K, w2c = _camera(W, H, dtype=torch.float32)
    cpu = rasterize_mesh(verts, faces, K, w2c, W, H)
    gpu = rasterize_mesh(verts.cuda(), faces.cuda(), K.cuda(), w2c.cuda(), W, H)
    same = gpu.face_id.cpu() == cpu.face_id
    assert same.float().mean() > 0.995
    m = same & cpu.mask
    assert torch.allclose(gpu.bary.cpu()[m], cpu.bary[m], atol=1e-4)
    assert torch.allclose(gpu.depth.cpu()[m], cpu.depth[m], rtol=1e-5)
