"""The rest-appearance teacher of phase 2: lookups through the mesh correspondence."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from sage_core.data.cameras import look_at
from sage_core.flame.frames import surfel_frames
from sage_core.render.mesh_raster import points_on_mesh, rasterize_mesh
from sage_core.train.rest_teacher import RestTeacher
from sage_core.train.warp import pixel_rays

W, H = 64, 56


def _sphere() -> tuple[torch.Tensor, torch.Tensor]:
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    return torch.as_tensor(m.vertices, dtype=torch.float64), torch.as_tensor(m.faces, dtype=torch.long)


def _camera(eye: tuple[float, float, float]) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    K = torch.tensor([[90.0, 0, W / 2], [0, 90.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    w2c = torch.as_tensor(look_at(np.array(eye), np.zeros(3)), dtype=torch.float64)
    return K, w2c, W, H


def _colour_of(points: torch.Tensor) -> torch.Tensor:
    """A smooth colour field on the rest surface: (R, 3) -> (R, 3) in [0, 1]."""
    return (points / 0.2 + 0.5).clamp(0, 1)


def _teacher(verts: torch.Tensor, faces: torch.Tensor, cams: list) -> RestTeacher:
    def render_fn(i: int, _inputs: dict) -> torch.Tensor:
        K, w2c, w, h = cams[i]
        ras = rasterize_mesh(verts, faces, K, w2c, w, h)
        fid = ras.face_id[0].reshape(-1)
        ok = fid >= 0
        pts = points_on_mesh(verts, faces, fid.clamp_min(0), ras.bary[0].reshape(-1, 3))
        col = torch.where(ok[:, None], _colour_of(pts), torch.ones_like(pts))
        return col.reshape(h, w, 3)

    return RestTeacher.build(render_fn, lambda _inputs: verts, faces, cams, [{} for _ in cams])


def _deformed_hits(verts_d: torch.Tensor, faces: torch.Tensor, cam: tuple) -> tuple[torch.Tensor, ...]:
    K, w2c, w, h = cam
    ras = rasterize_mesh(verts_d, faces, K, w2c, w, h)
    fid = ras.face_id[0].reshape(-1)
    pix = (fid >= 0).nonzero().squeeze(-1)
    _, dirs = pixel_rays(K, w2c, w, h, pix)
    return fid[pix], ras.bary[0].reshape(-1, 3)[pix], dirs


def test_rigid_motion_transfers_the_rest_colour() -> None:
    verts, faces = _sphere()
    cams = [_camera((0.0, 0.0, -0.5)), _camera((0.4, 0.0, -0.3))]
    teacher = _teacher(verts, faces, cams)
    # deformed: the sphere turned by 20 degrees about y and moved, seen by the first camera
    a = np.deg2rad(20.0)
    Rm = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], dtype=torch.float64)
    verts_d = verts @ Rm.T + torch.tensor([0.01, -0.005, 0.0], dtype=torch.float64)
    fid, bary, dirs = _deformed_hits(verts_d, faces, cams[0])
    look = teacher.lookup(faces, fid, bary, dirs, surfel_frames(verts_d, faces))
    assert float(look.valid.double().mean()) > 0.8
    expected = _colour_of(points_on_mesh(verts, faces, fid, bary))
    err = (look.color - expected)[look.valid].abs()
    assert float(err.mean()) < 0.01
    assert float(err.max()) < 0.08


def test_points_no_view_sees_are_invalid() -> None:
    verts, faces = _sphere()
    front = [_camera((0.0, 0.0, -0.5))]
    teacher = _teacher(verts, faces, front)
    back = _camera((0.0, 0.0, 0.5))  # the deformed frame looks at the other hemisphere
    fid, bary, dirs = _deformed_hits(verts, faces, back)
    look = teacher.lookup(faces, fid, bary, dirs, surfel_frames(verts, faces))
    z = points_on_mesh(verts, faces, fid, bary)[:, 2]
    assert not bool(look.valid[z > 0.02].any())  # clearly on the hidden side
    assert bool((look.view[~look.valid] == -1).all())
    assert bool((look.color[~look.valid] == 0).all())


def test_the_view_closest_to_the_deformed_ray_is_chosen() -> None:
    verts, faces = _sphere()
    cams = [_camera((0.0, 0.0, -0.5)), _camera((0.35, 0.0, -0.35))]
    teacher = _teacher(verts, faces, cams)
    for want, cam in enumerate(cams):
        fid, bary, dirs = _deformed_hits(verts, faces, cam)
        frames = surfel_frames(verts, faces)
        look = teacher.lookup(faces, fid, bary, dirs, frames)
        # wherever the view that looks along the deformed ray sees the point, it is the one used
        alone = RestTeacher([teacher.views[want]]).lookup(faces, fid, bary, dirs, frames)
        assert int(alone.valid.sum()) > 100
        assert bool((look.view[alone.valid] == want).all())
        assert torch.allclose(look.color[alone.valid], alone.color[alone.valid])


def test_build_needs_views() -> None:
    with pytest.raises(ValueError):
        RestTeacher([])
