"""Canonical ray warping through the hit triangle (sage_core.train.warp)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from sage_core.data.cameras import look_at
from sage_core.flame.frames import surfel_frames
from sage_core.geometry.rotations import axis_angle_to_matrix
from sage_core.render.mesh_raster import rasterize_mesh
from sage_core.train.warp import pixel_rays, rigid_rays_to_canonical, warp_hits_to_canonical, warp_pixels_to_canonical

W, H = 40, 32


def _mesh() -> tuple[torch.Tensor, torch.Tensor]:
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    v = torch.as_tensor(m.vertices, dtype=torch.float64) * torch.tensor([1.0, 1.3, 0.9], dtype=torch.float64)
    return v, torch.as_tensor(m.faces, dtype=torch.long)


def _camera() -> tuple[torch.Tensor, torch.Tensor]:
    w2c = look_at(np.array([0.05, 0.02, 0.6]), np.zeros(3))
    f = 0.5 * H / math.tan(math.radians(15.0))
    K = np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    return torch.as_tensor(K, dtype=torch.float64), torch.as_tensor(w2c, dtype=torch.float64)


def _all_pixels() -> torch.Tensor:
    return torch.arange(W * H)


def test_rigid_motion_warps_to_inverse_rigid_transform():
    verts_c, faces = _mesh()
    R0 = axis_angle_to_matrix(torch.tensor([[0.3, -0.5, 0.2]], dtype=torch.float64))[0]
    J0 = torch.tensor([0.01, -0.03, 0.02], dtype=torch.float64)
    t = torch.tensor([0.02, 0.01, -0.05], dtype=torch.float64)
    verts_p = (verts_c - J0) @ R0.T + J0 + t
    K, w2c = _camera()
    pix = _all_pixels()
    rays = warp_pixels_to_canonical(verts_p, faces, surfel_frames(verts_c, faces), K, w2c, W, H, pix)
    assert 50 < int(rays.valid.sum()) < W * H  # some rays hit, some miss
    o_w, d_w = pixel_rays(K, w2c, W, H, pix)
    ref = rigid_rays_to_canonical(o_w, d_w, R0, t, J0)
    v = rays.valid
    torch.testing.assert_close(rays.origins[v], ref.origins[v], atol=1e-9, rtol=0)
    torch.testing.assert_close(rays.dirs[v], ref.dirs[v], atol=1e-9, rtol=0)
    torch.testing.assert_close(rays.scale[v], torch.ones_like(rays.scale[v]))
    torch.testing.assert_close(rays.rotation[v], R0.T.expand(int(v.sum()), 3, 3), atol=1e-9, rtol=0)
    # the rigid reference is the inverse of the motion: mapping the canonical ray forward gives the world ray
    torch.testing.assert_close((ref.origins - J0) @ R0.T + J0 + t, o_w, atol=1e-12, rtol=0)
    torch.testing.assert_close(ref.dirs @ R0.T, d_w, atol=1e-12, rtol=0)


def test_uniform_scaling_warps_to_inverse_similarity():
    verts_c, faces = _mesh()
    c = torch.tensor([0.0, 0.02, 0.0], dtype=torch.float64)
    s = 1.3
    verts_p = (verts_c - c) * s + c
    K, w2c = _camera()
    pix = _all_pixels()
    rays = warp_pixels_to_canonical(verts_p, faces, surfel_frames(verts_c, faces), K, w2c, W, H, pix)
    o_w, d_w = pixel_rays(K, w2c, W, H, pix)
    v = rays.valid
    assert int(v.sum()) > 50
    torch.testing.assert_close(rays.origins[v], ((o_w - c) / s + c)[v], atol=1e-9, rtol=0)
    torch.testing.assert_close(rays.dirs[v], d_w[v], atol=1e-9, rtol=0)
    torch.testing.assert_close(rays.scale[v], torch.full_like(rays.scale[v], 1 / s))


def test_warped_ray_passes_through_canonical_hit_point():
    """Under a non-rigid deformation each ray goes through the canonical point of its hit."""
    verts_c, faces = _mesh()
    bend = verts_c.clone()
    bend[:, 2] += 0.3 * verts_c[:, 1] ** 2 + 0.1 * verts_c[:, 0]
    K, w2c = _camera()
    raster = rasterize_mesh(bend, faces, K, w2c, W, H)
    pix = _all_pixels()
    rays = warp_pixels_to_canonical(bend, faces, surfel_frames(verts_c, faces), K, w2c, W, H, pix, raster=raster)
    v = rays.valid
    fid = rays.face_id[v]
    bary = raster.bary.reshape(-1, 3)[pix][v]
    hit_c = (bary[..., None] * verts_c[faces[fid]]).sum(-2)  # barycentric point on the canonical triangle
    x = rays.origins[v] + (rays.hit_distance[v] * rays.scale[v])[:, None] * rays.dirs[v]
    # the similarity part of a sheared triangle is not its affine map: the point is within the triangle's size
    err = (x - hit_c).norm(dim=-1)
    edge = (verts_c[faces[fid, 1]] - verts_c[faces[fid, 0]]).norm(dim=-1)
    assert bool((err < edge).all())
    torch.testing.assert_close(rays.dirs.norm(dim=-1), torch.ones(W * H, dtype=torch.float64))
    assert not rays.origins.requires_grad
    assert bool(torch.isinf(rays.hit_distance[~v]).all())


def test_warp_hits_flags_misses():
    verts_c, faces = _mesh()
    frames = surfel_frames(verts_c, faces)
    o = torch.zeros(3, 3, dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=torch.float64)
    hits = torch.tensor([[0.0, 0.0, 0.5]] * 3, dtype=torch.float64)
    fid = torch.tensor([0, -1, 5])
    rays = warp_hits_to_canonical(o, d, hits, fid, frames, frames)
    assert rays.valid.tolist() == [True, False, True]
    # identical posed and canonical frames: the identity map
    torch.testing.assert_close(rays.origins[rays.valid], o[rays.valid])
    assert math.isinf(float(rays.hit_distance[1]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtype_preserved(dtype):
    verts_c, faces = _mesh()
    verts_c = verts_c.to(dtype)
    K, w2c = _camera()
    rays = warp_pixels_to_canonical(verts_c, faces, surfel_frames(verts_c, faces), K.to(dtype), w2c.to(dtype), W, H, _all_pixels()[:64])
    assert rays.origins.dtype == dtype and rays.dirs.dtype == dtype
