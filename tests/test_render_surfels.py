"""Analytic scenes, degenerate inputs and API behaviour of the surfel rasterizer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sage_core.data.cameras import Camera, look_at
from sage_core.render import (
    RenderCamera,
    depth_to_normal,
    eval_sh_colors,
    rasterize_surfels,
    sh_basis,
)

F64 = torch.float64


def _cam(W: int = 32, H: int = 32, f: float = 40.0, w2c: torch.Tensor | None = None) -> RenderCamera:
    # principal point on a pixel centre, so the surfel at the origin of x/y lands on pixel (W/2, H/2)
    K = torch.tensor([[f, 0.0, W / 2 + 0.5], [0.0, f, H / 2 + 0.5], [0.0, 0.0, 1.0]], dtype=F64)
    return RenderCamera(K, torch.eye(4, dtype=F64) if w2c is None else w2c, W, H)


def _surfels(means, scales, opac, quats=None, colors=None):
    means = torch.as_tensor(means, dtype=F64).reshape(-1, 3)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=F64) if quats is None else torch.as_tensor(quats, dtype=F64)
    scales = torch.as_tensor(scales, dtype=F64).reshape(n, 2)
    opac = torch.as_tensor(opac, dtype=F64).reshape(n)
    colors = torch.ones(n, 3, dtype=F64) if colors is None else torch.as_tensor(colors, dtype=F64)
    return [means, quats, scales, opac, colors]


# ---------------------------------------------------------------- analytic scenes


def test_fronto_parallel_surfel() -> None:
    z0, f, s, o = 2.0, 40.0, 0.15, 0.8  # σ = f·s/z0 = 3 px
    cam = _cam(f=f)
    out = rasterize_surfels(*_surfels([0.0, 0.0, z0], [s, s], o), cam, far=10.0)
    A = out.alpha
    assert abs(float(A[16, 16]) - o) < 1e-12
    sigma = f * s / z0
    ys, xs = torch.meshgrid(torch.arange(32, dtype=F64), torch.arange(32, dtype=F64), indexing="ij")
    r2 = ((xs - 16) ** 2 + (ys - 16) ** 2) / sigma**2
    expected = o * torch.exp(-0.5 * r2)
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    assert torch.allclose(A, expected, atol=1e-12)
    # footprint: α ≥ 1/255 out to σ·sqrt(2 ln(255 o)) ≈ 3.2σ
    reach = sigma * math.sqrt(2 * math.log(255 * o))
    nz = torch.nonzero(A[16] > 0).flatten()
    assert abs(float(nz.max() - 16) - math.floor(reach)) <= 0 and 3 * sigma - 1 < float(nz.max() - 16) < 3.5 * sigma
    inside = A > 0
    assert torch.allclose(out.depth[inside], torch.full_like(out.depth[inside], z0), atol=1e-12)
    assert torch.all(out.depth[~inside] == 0)
    assert torch.allclose(out.median_depth[inside], torch.full_like(A[inside], z0))
    n = out.normal_cam[inside] / A[inside, None]
    assert torch.allclose(n, torch.tensor([0.0, 0.0, -1.0], dtype=F64).expand_as(n), atol=1e-12)
    assert torch.allclose(out.normal_world, out.normal_cam)
    # depth-normal equals the rendered normal where all four neighbours are covered
    interior = inside.clone()
    interior[1:-1, 1:-1] &= inside[2:, 1:-1] & inside[:-2, 1:-1] & inside[1:-1, 2:] & inside[1:-1, :-2]
    interior[0, :] = interior[-1, :] = False
    interior[:, 0] = interior[:, -1] = False
    assert interior.sum() > 100
    assert torch.allclose(out.surf_normal_cam[interior], out.normal_cam[interior], atol=1e-9)
    assert torch.all(out.distortion.abs() < 1e-15)
    assert int(out.radii[0]) == math.ceil(3 * sigma) and bool(out.visible[0])


def test_tilted_plane_depth_and_normal() -> None:
    f, W = 40.0, 40
    cam = _cam(W=W, H=W, f=f)
    ang = math.radians(30)
    # plane through (0, 0, 3) with normal rotated 30° about y (surfel frame = rotation about y)
    q = torch.tensor([math.cos(ang / 2), 0.0, math.sin(ang / 2), 0.0], dtype=F64)
    tu = torch.tensor([math.cos(ang), 0.0, -math.sin(ang)], dtype=F64)
    tv = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    nrm = torch.tensor([math.sin(ang), 0.0, math.cos(ang)], dtype=F64)
    p0 = torch.tensor([0.0, 0.0, 3.0], dtype=F64)
    g = torch.arange(-10, 11, dtype=F64) * 0.1
    gu, gv = torch.meshgrid(g, g, indexing="ij")
    means = p0 + gu.reshape(-1, 1) * tu + gv.reshape(-1, 1) * tv
    n = means.shape[0]
    params = _surfels(means, torch.full((n, 2), 0.1), torch.full((n,), 0.9), quats=q.expand(n, 4))
    out = rasterize_surfels(*params, cam, far=10.0)
    core = out.alpha > 0.99
    assert core.sum() > 400
    # ray depth to the plane: z such that n·(z·K⁻¹x − p0) = 0
    ys, xs = torch.meshgrid(torch.arange(W, dtype=F64) + 0.5, torch.arange(W, dtype=F64) + 0.5, indexing="ij")
    rays = torch.stack([xs, ys, torch.ones_like(xs)], -1) @ torch.linalg.inv(cam.K).T
    zplane = (nrm @ p0) / (rays @ nrm)
    # intersection depth: exact wherever the 3D branch wins for every contributor (most pixels);
    # near a surfel's screen centre the low-pass branch uses the centre depth (hbb1), a small offset
    err = (out.depth[core] - zplane[core]).abs()
    assert float((err < 1e-9).double().mean()) > 0.8 and float(err.max()) < 3e-3
    centre_depth_err = (out.median_depth[core] - zplane[core]).abs()
    assert float(centre_depth_err.max()) < 3e-3
    flipped = -nrm  # faces the camera
    nr = out.normal_cam[core] / out.alpha[core, None]
    assert torch.allclose(nr, flipped.expand_as(nr), atol=1e-9)
    inner = core.clone()
    inner[1:-1, 1:-1] &= core[2:, 1:-1] & core[:-2, 1:-1] & core[1:-1, 2:] & core[1:-1, :-2]
    sn = out.surf_normal_cam[inner] / out.alpha[inner, None]
    nerr = (sn - flipped).norm(dim=-1)
    assert float((nerr < 1e-9).double().mean()) > 0.5 and float(nerr.max()) < 0.05
    assert float(out.distortion[core].max()) < 1e-7 and float((out.distortion[core] < 1e-15).double().mean()) > 0.8


def _two_surfels(z2: float):
    params = _surfels([[0.0, 0.0, 2.0], [0.0, 0.0, z2]], [[0.1, 0.1], [0.1, 0.1]], [0.6, 0.7])
    return rasterize_surfels(*params, _cam(), near=0.2, far=10.0)


def test_two_surfel_distortion_closed_form_and_growth() -> None:
    near, far = 0.2, 10.0

    def m(z: float) -> float:
        return far / (far - near) * (1 - near / z)

    vals = []
    for z2 in (2.05, 2.2, 2.6, 3.5):
        out = _two_surfels(z2)
        w1 = 0.6
        w2 = 0.7 * (1 - 0.6)
        expect = w1 * w2 * (m(2.0) - m(z2)) ** 2
        assert abs(float(out.distortion[16, 16]) - expect) < 1e-14
        assert abs(float(out.depth_sum[16, 16]) - (w1 * 2.0 + w2 * z2)) < 1e-12
        assert abs(float(out.median_depth[16, 16]) - 2.0) < 1e-12  # T before the second is 0.4 ≤ 0.5
        vals.append(float(out.distortion[16, 16]))
    assert all(a < b for a, b in zip(vals, vals[1:]))


def test_background_only_where_nothing_is_drawn() -> None:
    bg = torch.tensor([0.25, 0.5, 0.75], dtype=F64)
    out = rasterize_surfels(*_surfels([0.1, 0.0, 2.0], [0.05, 0.08], 0.9, colors=[[1.0, 0.0, 0.0]]), _cam(), background=bg)
    empty = out.alpha == 0
    assert empty.sum() > 500 and (~empty).sum() > 20
    assert torch.all(out.color[empty] == bg)
    expect = out.alpha[..., None] * torch.tensor([1.0, 0.0, 0.0], dtype=F64) + (1 - out.alpha[..., None]) * bg
    assert torch.allclose(out.color, expect, atol=1e-12)


def test_behind_camera_and_off_screen_contribute_nothing() -> None:
    base = _surfels([[0.0, 0.0, 2.0], [0.1, 0.05, 2.5]], [[0.1, 0.08], [0.06, 0.1]], [0.7, 0.5])
    extra = _surfels([[0.0, 0.0, -2.0], [5.0, 0.0, 2.0], [0.0, -4.0, 1.0], [0.0, 0.0, 0.1]], [[0.3, 0.3]] * 4, [1.0] * 4)
    both = [torch.cat([a, b]) for a, b in zip(base, extra)]
    a = rasterize_surfels(*base, _cam(), far=10.0)
    b = rasterize_surfels(*both, _cam(), far=10.0)
    for k in ("color", "alpha", "depth", "median_depth", "normal_cam", "distortion"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    assert b.visible.tolist() == [True, True, False, False, False, False]
    assert b.radii[2:].tolist() == [0, 0, 0, 0]


def test_batch_equals_single_calls() -> None:
    g = torch.Generator().manual_seed(0)
    n = 30
    means = torch.randn(n, 3, generator=g, dtype=F64) * 0.2
    params = [
        means,
        torch.randn(n, 4, generator=g, dtype=F64),
        0.03 + 0.05 * torch.rand(n, 2, generator=g, dtype=F64),
        torch.rand(n, generator=g, dtype=F64),
        torch.rand(n, 9, 3, generator=g, dtype=F64) - 0.5,
    ]
    cams = []
    for eye in ([0.0, 0.0, -2.0], [0.8, -0.3, -1.8]):
        c = Camera(np.array([[40.0, 0, 16.0], [0, 42.0, 15.0], [0, 0, 1]]), look_at(np.array(eye), np.zeros(3)), 32, 30)
        cams.append(c)
    batch = RenderCamera.from_cameras(cams, dtype=F64)
    p1 = [p.clone().requires_grad_(True) for p in params]
    out = rasterize_surfels(*p1, batch, background=0.3)
    out.means2d.retain_grad()
    (out.color.sum() + out.depth.sum() + out.distortion.sum()).backward()
    assert out.color.shape == (2, 30, 32, 3) and out.means2d.shape == (2, n, 2) and out.visible.shape == (2, n)
    grads = torch.zeros_like(params[0])
    for i, c in enumerate(cams):
        p2 = [p.clone().requires_grad_(True) for p in params]
        single = rasterize_surfels(*p2, RenderCamera.from_camera(c, dtype=F64), background=0.3)
        single.means2d.retain_grad()
        (single.color.sum() + single.depth.sum() + single.distortion.sum()).backward()
        grads += p2[0].grad
        for k in ("color", "alpha", "depth", "median_depth", "normal_world", "surf_normal_world", "distortion"):
            assert torch.allclose(getattr(out, k)[i], getattr(single, k), atol=1e-12), k
        assert torch.allclose(out.means2d.grad[i], single.means2d.grad, atol=1e-10)
        assert torch.equal(out.radii[i], single.radii)
    assert torch.allclose(p1[0].grad, grads, atol=1e-10)
    assert float(out.alpha[0].detach().sum()) > 10 and float(out.alpha[1].detach().sum()) > 10


# ---------------------------------------------------------------- statistics and SH


def test_means2d_is_projected_centre_and_its_gradient_is_the_screen_proxy() -> None:
    f = 40.0
    params = _surfels([[0.05, -0.02, 2.0], [-0.1, 0.04, 2.6], [3.0, 0.0, 2.0]], [[0.1, 0.07], [0.08, 0.09], [0.1, 0.1]], [0.8, 0.6, 0.9])
    params[0].requires_grad_(True)
    out = rasterize_surfels(*params, _cam(f=f))
    out.means2d.retain_grad()
    (out.color[..., 0] * torch.linspace(0, 1, 32, dtype=F64)).sum().backward()
    m = params[0].detach()
    expect = torch.stack([f * m[:, 0] / m[:, 2] + 16.5, f * m[:, 1] / m[:, 2] + 16.5], -1)
    assert torch.allclose(out.means2d.detach(), expect, atol=1e-12)
    g2 = out.means2d.grad
    assert float(g2[:2].abs().min()) > 0 and torch.all(g2[2] == 0)
    # with an identity camera the x position enters only through Tu[2] = f·x + cx·z
    assert torch.allclose(params[0].grad[:, 0], g2[:, 0] * f / m[:, 2], atol=1e-12)


def test_sh_basis_is_orthonormal() -> None:
    n = 40000
    i = torch.arange(n, dtype=F64) + 0.5
    zc = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = torch.sqrt(1 - zc * zc)
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), zc], -1)
    Y = sh_basis(dirs, 3)
    gram = Y.T @ Y * (4 * math.pi / n)
    assert torch.allclose(gram, torch.eye(16, dtype=F64), atol=2e-3)


def test_sh_colors_render_like_features() -> None:
    g = torch.Generator().manual_seed(1)
    n = 12
    means = torch.randn(n, 3, generator=g, dtype=F64) * 0.15 + torch.tensor([0, 0, 2.0], dtype=F64)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = 0.05 + 0.05 * torch.rand(n, 2, generator=g, dtype=F64)
    opac = torch.rand(n, generator=g, dtype=F64)
    sh = torch.rand(n, 16, 3, generator=g, dtype=F64) - 0.5
    cam = _cam(w2c=torch.as_tensor(look_at(np.array([0.3, 0.2, -0.5]), np.array([0, 0, 2.0]))))
    centre = -(cam.w2c[:3, :3].T @ cam.w2c[:3, 3])
    for deg in (0, 1, 3):
        feats = eval_sh_colors(sh, torch.nn.functional.normalize(means - centre, dim=-1), deg)
        a = rasterize_surfels(means, quats, scales, opac, sh, cam, sh_degree=deg)
        b = rasterize_surfels(means, quats, scales, opac, feats, cam)
        assert torch.allclose(a.color, b.color, atol=1e-12)
    # degree 0 is view independent: Y0·c + 0.5 clamped at 0
    f0 = eval_sh_colors(sh[:, :1], torch.tensor([[0.0, 0.0, 1.0]], dtype=F64).expand(n, 3), 0)
    assert torch.allclose(f0, (0.28209479177387814 * sh[:, 0] + 0.5).clamp_min(0))
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize_surfels(means, quats, scales, opac, sh[:, :4], cam, sh_degree=2)


def test_depth_to_normal_of_planes() -> None:
    K = torch.tensor([[30.0, 0, 12.0], [0, 30.0, 10.0], [0, 0, 1]], dtype=F64)
    flat = depth_to_normal(torch.full((20, 24), 2.0, dtype=F64), K)
    assert torch.allclose(flat[1:-1, 1:-1], torch.tensor([0.0, 0.0, -1.0], dtype=F64).expand(18, 22, 3))
    assert torch.all(flat[0] == 0) and torch.all(flat[:, -1] == 0)
    nrm = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0], dtype=F64), dim=0)
    ys, xs = torch.meshgrid(torch.arange(20, dtype=F64) + 0.5, torch.arange(24, dtype=F64) + 0.5, indexing="ij")
    rays = torch.stack([xs, ys, torch.ones_like(xs)], -1) @ torch.linalg.inv(K).T
    depth = 2.0 / (rays @ nrm)
    n = depth_to_normal(depth, K)[1:-1, 1:-1]
    assert torch.allclose(n, -nrm.expand_as(n), atol=1e-10)


# ---------------------------------------------------------------- degenerate inputs and API


def test_empty_surfel_set_returns_background() -> None:
    params = [torch.zeros(0, 3, dtype=F64), torch.zeros(0, 4, dtype=F64), torch.zeros(0, 2, dtype=F64),
              torch.zeros(0, dtype=F64), torch.zeros(0, 3, dtype=F64)]
    params = [p.requires_grad_(True) for p in params]
    out = rasterize_surfels(*params, _cam(), background=torch.tensor([0.1, 0.2, 0.3], dtype=F64))
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0) and torch.all(out.distortion == 0)
    assert torch.allclose(out.color, torch.tensor([0.1, 0.2, 0.3], dtype=F64).expand(32, 32, 3))
    assert out.visible.shape == (0,) and out.means2d.shape == (0, 2) and int(out.num_pairs) == 0


def test_all_culled_scene_still_backpropagates() -> None:
    params = [p.requires_grad_(True) for p in _surfels([0.0, 0.0, -1.0], [0.1, 0.1], 0.5)]
    out = rasterize_surfels(*params, _cam())
    (out.color.sum() + out.depth.sum()).backward()
    assert torch.all(out.alpha == 0) and params[3].grad is not None and torch.all(params[3].grad == 0)


def test_zero_scales_contribute_nothing() -> None:
    base = _surfels([0.0, 0.0, 2.0], [0.1, 0.1], 0.7)
    zero = _surfels([[0.02, 0.0, 1.5], [0.0, 0.03, 1.8]], [[0.0, 0.0], [0.0, 0.1]], [1.0, 1.0])
    both = [torch.cat([a, b]).requires_grad_(True) for a, b in zip(base, zero)]
    a = rasterize_surfels(*base, _cam())
    b = rasterize_surfels(*both, _cam())
    assert torch.equal(a.color, b.color) and torch.equal(a.depth, b.depth)
    (b.color.sum() + b.depth.sum() + b.distortion.sum()).backward()
    assert all(torch.isfinite(p.grad).all() for p in both)
    only = rasterize_surfels(*zero, _cam())
    assert torch.all(only.alpha == 0)


@pytest.mark.parametrize("index,name", [(0, "means"), (1, "quats"), (2, "scales"), (3, "opacities"), (4, "colors")])
def test_non_finite_inputs_raise(index: int, name: str) -> None:
    params = _surfels([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0]], [[0.1, 0.1]] * 2, [0.5, 0.5])
    params[index] = params[index].clone()
    params[index].view(-1)[0] = float("nan") if index != 3 else float("inf")
    with pytest.raises(ValueError, match=name):
        rasterize_surfels(*params, _cam())


def test_bad_arguments_raise() -> None:
    params = _surfels([0.0, 0.0, 2.0], [0.1, 0.1], 0.5)
    with pytest.raises(ValueError, match="backend"):
        rasterize_surfels(*params, _cam(), backend="cuda-magic")
    with pytest.raises(ValueError, match="opacities"):
        rasterize_surfels(*params[:3], params[3] + 1.0, params[4], _cam())
    with pytest.raises(ValueError, match="quats"):
        rasterize_surfels(params[0], params[1][:, :3], *params[2:], _cam())
    with pytest.raises(ValueError, match="background"):
        rasterize_surfels(*params, _cam(), background=torch.zeros(4, dtype=F64))
    bad_cam = _cam()
    bad_cam.K = bad_cam.K.clone()
    bad_cam.K[0, 0] = float("nan")
    with pytest.raises(ValueError, match="camera.K"):
        rasterize_surfels(*params, bad_cam)
    out = rasterize_surfels(*params, _cam(), return_statistics=False)
    assert out.visible is None and out.radii is None and out.means2d is None


def test_float32_default_and_feature_channels() -> None:
    means = torch.tensor([[0.0, 0.0, 2.0]])
    out = rasterize_surfels(means, torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[0.1, 0.1]]), torch.tensor([0.9]),
                            torch.tensor([[0.5, 1.0, 2.0, -1.0, 3.0]]), RenderCamera.from_camera(
                                Camera(np.array([[40.0, 0, 16.5], [0, 40, 16.5], [0, 0, 1]]), np.eye(4), 32, 32)))
    assert out.color.dtype == torch.float32 and out.color.shape == (32, 32, 5)
    assert torch.allclose(out.color[16, 16], 0.9 * torch.tensor([0.5, 1.0, 2.0, -1.0, 3.0]), atol=1e-6)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    g = torch.Generator().manual_seed(3)
    n = 200
    params = [
        torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0, 0, 2.5]),
        torch.randn(n, 4, generator=g),
        0.02 + 0.05 * torch.rand(n, 2, generator=g),
        torch.rand(n, generator=g),
        torch.rand(n, 3, generator=g),
    ]
    cpu = rasterize_surfels(*params, _cam(64, 48, 50.0).to(dtype=torch.float32))
    gpu = rasterize_surfels(*[p.cuda() for p in params], _cam(64, 48, 50.0).to("cuda", torch.float32))
    for k in ("color", "alpha", "depth", "median_depth", "normal_cam", "distortion"):
        assert torch.allclose(getattr(gpu, k).cpu(), getattr(cpu, k), atol=1e-4), k


def test_progress_callback_reports_candidate_chunks() -> None:
    calls: list[tuple[int, int]] = []
    params = _surfels([[0.0, 0.0, 2.0], [0.1, 0.0, 2.2], [-0.1, 0.05, 2.4]], [[0.1, 0.1]] * 3, [0.5] * 3)
    out = rasterize_surfels(*params, _cam(), chunk_pairs=50, progress=lambda i, n: calls.append((i, n)))
    # a chunk holds whole surfels, so with 50-pair chunks each surfel is its own chunk
    assert calls == [(1, 3), (2, 3), (3, 3)] and int(out.num_pairs) > 100
