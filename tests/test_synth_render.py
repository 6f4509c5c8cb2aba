"""Ground-truth rasterizer: depth and silhouette against trimesh ray casting, barycentrics, shading."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sage_core.data.cameras import Camera
from sage_core.data.synthetic import build_head, crease_weights, rasterize, render_head, sample_appearance
from sage_core.data.synthetic.mesh_render import pixel_rays
from sage_core.data.cameras import look_at


@pytest.fixture(scope="module")
def head():
    return build_head(40, 48, 6, 8)


class _BoxTree:
    """Minimal stand-in for the optional rtree index trimesh's ray caster uses (brute-force AABB test)."""

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        tri = mesh.triangles
        self.lo, self.hi = tri.min(1), tri.max(1)
        self.bounds = np.concatenate([self.lo.min(0), self.hi.max(0)])

    def intersection(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b)
        return np.flatnonzero(np.all(self.lo <= b[3:], axis=1) & np.all(self.hi >= b[:3], axis=1))


def _camera(w: int = 48, h: int = 70, yaw: float = 25.0, cx_off: float = 1.3, cy_off: float = -2.1) -> Camera:
    a = np.deg2rad(yaw)
    eye = 0.9 * np.array([np.sin(a), 0.12, np.cos(a)])
    fl = h * 0.9 / 0.34
    K = np.array([[fl, 0.0, w / 2 + cx_off], [0.0, fl * 1.01, h / 2 + cy_off], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(eye, np.array([0.0, -0.01, 0.0])), w, h)


def test_depth_and_mask_match_ray_casting(head) -> None:
    cam = _camera()
    frag = rasterize(head.v_template, head.faces, cam)
    origin, dirs = pixel_rays(cam)
    d = dirs.reshape(-1, 3)
    mesh = trimesh.Trimesh(head.v_template, head.faces, process=False)
    _, ray_idx, locs = trimesh.ray.ray_triangle.ray_triangle_id(
        mesh.triangles, np.broadcast_to(origin, d.shape).copy(), d, mesh.face_normals, tree=_BoxTree(mesh), multiple_hits=True
    )
    zc = (locs - cam.center) @ cam.w2c[2, :3]  # camera-space z of every hit
    ray_depth = np.full(d.shape[0], np.inf)
    np.minimum.at(ray_depth, ray_idx, zc)
    hit = np.isfinite(ray_depth)
    mask = frag.mask.reshape(-1)
    assert hit.sum() > 300
    assert (mask == hit).mean() > 0.995  # silhouettes agree up to pixels grazing an edge
    both = mask & hit
    err = np.abs(frag.depth.reshape(-1)[both] - ray_depth[both])
    assert np.quantile(err, 0.99) < 1e-6
    assert np.all(np.isinf(frag.depth.reshape(-1)[~mask]))


def test_perspective_correct_barycentrics_reproject_to_pixel_centres(head) -> None:
    cam = _camera(yaw=-40.0)
    frag = rasterize(head.v_template, head.faces, cam)
    pts = frag.interpolate(head.v_template, head.faces)
    uv, z = cam.project(pts)
    ys, xs = np.nonzero(frag.mask)
    np.testing.assert_allclose(uv, np.stack([xs + 0.5, ys + 0.5], -1), atol=1e-6)
    np.testing.assert_allclose(z, frag.depth[frag.mask], rtol=1e-9)
    assert np.all(frag.bary[frag.mask] >= -1e-9)
    np.testing.assert_allclose(frag.bary[frag.mask].sum(-1), 1.0, atol=1e-9)


def test_principal_point_shifts_image_exactly(head) -> None:
    a = rasterize(head.v_template, head.faces, _camera(cx_off=0.0, cy_off=0.0))
    b = rasterize(head.v_template, head.faces, _camera(cx_off=3.0, cy_off=-2.0))
    # b's pixel (x, y) sees what a's pixel (x - 3, y + 2) sees
    assert (b.face[:-2, 3:] == a.face[2:, :-3]).mean() > 0.999
    assert (b.face[:-2, 3:] != a.face[:-2, 3:]).any()


def test_supersampling_and_scaled_rendering(head) -> None:
    cam = _camera()
    hi = rasterize(head.v_template, head.faces, cam, scale=2)
    assert hi.face.shape == (2 * cam.height, 2 * cam.width)
    cam2 = Camera(cam.K * np.array([[2], [2], [1]]), cam.w2c, 2 * cam.width, 2 * cam.height)
    ref = rasterize(head.v_template, head.faces, cam2)
    np.testing.assert_array_equal(hi.face, ref.face)
    app = sample_appearance(np.random.default_rng(0))
    r = render_head(head, head.v_template, cam, app, supersample=2, geometry=True)
    assert r.rgb.shape == (cam.height, cam.width, 3) and r.alpha.shape == (cam.height, cam.width)
    assert 0 < ((r.alpha > 0) & (r.alpha < 1)).sum() < (r.alpha > 0).sum()  # soft edges only
    bg = r.alpha == 0
    assert np.all(r.rgb[bg] == 1.0)
    assert r.rgb[r.alpha == 1].mean() < 0.9
    fg = np.isfinite(r.depth)
    n = r.normal[fg]
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    assert np.all(r.normal[~fg] == 0)


def test_render_is_deterministic_and_depends_on_seed(head) -> None:
    cam = _camera(yaw=0.0)
    a = render_head(head, head.v_template, cam, sample_appearance(np.random.default_rng(1)))
    b = render_head(head, head.v_template, cam, sample_appearance(np.random.default_rng(1)))
    c = render_head(head, head.v_template, cam, sample_appearance(np.random.default_rng(2)))
    np.testing.assert_array_equal(a.rgb, b.rgb)
    assert np.abs(a.rgb - c.rgb).mean() > 1e-3


def test_crease_weights_follow_compression(head) -> None:
    v = head.v_template
    assert np.all(crease_weights(v, v, head.faces) == 0)
    squashed = v.copy()
    top = v[:, 1] > 0.04
    squashed[top, 1] = 0.04 + 0.6 * (v[top, 1] - 0.04)
    c = crease_weights(squashed, v, head.faces)
    forehead = top & (v[:, 1] > 0.05) & (v[:, 1] < 0.08) & (v[:, 2] > 0.06)
    assert forehead.sum() > 5 and c[forehead].mean() > 0.8
    assert c[v[:, 1] < 0.0].max() == 0
