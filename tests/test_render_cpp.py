"""The native CPU surfel backend (``backend="cpp"``) against the packed torch backend and the dense
float64 reference (values and gradients).

The backend has two paths: the whole render in the extension (projection, depth order, compositing,
image outputs and their backward; the default), and, when the camera itself requires grad, the torch
projection with only the compositing in the extension. Both are checked.

The extension is built once per session (``cpp_ext`` fixture; a cached build loads in well under a
second, a fresh one takes about 10–60 s on 2 cores). Every test skips with the build's reason when
it cannot be built.

Tolerances. float64: values within 1e-10 of the packed backend and 1e-9 of the dense reference,
gradients within 1e-9 of the largest gradient of each input. float32: values within 2e-5 of both,
gradients within 1e-4 of the largest gradient of each input (the backends sum in different orders;
the C++ sums images in float64 and runs the per-pair gradient chain in the input dtype, as torch).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap
import time
import warnings

import numpy as np
import pytest
import torch

from sage_core.render import RenderCamera, rasterize_surfels, resolve_backend
from sage_core.render import _cpp_surfels
from sage_core.render._dense_reference import random_test_scene, render_dense_reference

from render_parity import OUTPUTS, PARAMS, check_tile_binning, compare_backends, render_with_grads, scene_tensors

REF_OUTPUTS = OUTPUTS  # the dense reference returns every image output


@pytest.fixture(scope="session")
def cpp_ext() -> float:
    """Build (or load the cached build of) the extension once; returns the seconds it took."""
    t0 = time.perf_counter()
    ok, reason = _cpp_surfels.available()
    if not ok:
        pytest.skip(f"the C++ surfel extension cannot be built here: {reason}")
    return time.perf_counter() - t0


def _compare(params, cam, atol: float, grad_rtol: float, **kw) -> tuple:
    """The backend under test against the torch backend (see ``compare_backends``)."""
    return compare_backends(params, cam, "cpp", atol, grad_rtol, **kw)


def _check_reference(
    out, scene: dict, atol: float, cam_index: int | None = None, atol_by_name: dict | None = None, **kw
) -> dict:
    ref = render_dense_reference(
        *(scene[k] for k in PARAMS), scene["K"], scene["w2c"], scene["width"], scene["height"], **kw
    )
    for name in REF_OUTPUTS:
        v = getattr(out, name).detach()
        v = v if cam_index is None else v[cam_index]
        err = float(np.abs(v.double().numpy() - ref[name]).max())
        assert err <= (atol_by_name or {}).get(name, atol), (name, err)
    return ref


def _tilted_scene(seed: int) -> dict:
    """random_test_scene plus edge-on and steeply tilted surfels, large ones crossing tile borders."""
    scene = random_test_scene(seed, num=70, width=40, height=36)
    rng = np.random.default_rng(100 + seed)
    z = scene["means"][:, 2]
    # edge-on: the normal (third rotation column) perpendicular to the viewing ray of the centre
    for i in range(10, 16):
        ray = scene["means"][i] / np.linalg.norm(scene["means"][i])
        t_u = np.cross(ray, [0.0, 1.0, 0.0])
        t_u /= np.linalg.norm(t_u)
        # rotation whose t_w lies in the plane orthogonal to the ray: rotate about the ray by a random angle
        t_w = np.cross(ray, t_u)
        ang = rng.random() * math.pi
        t_w = math.cos(ang) * t_w + math.sin(ang) * t_u
        t_w += 1e-3 * ray  # nearly edge-on, so h_z stays non-zero at most pixels
        t_w /= np.linalg.norm(t_w)
        t_v = np.cross(t_w, ray)
        t_v /= np.linalg.norm(t_v)
        t_u = np.cross(t_v, t_w)
        R = np.stack([t_u, t_v, t_w], 1)
        w = math.sqrt(max(1e-12, 1.0 + np.trace(R))) / 2.0
        scene["quats"][i] = [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    # large tilted surfels centred on the tile borders (x = 16, 32 px; y = 16, 32 px)
    f = scene["K"][0, 0]
    for k, i in enumerate(range(16, 22)):
        px, py = (16.0, 16.0, 32.0, 16.0, 32.0, 24.0)[k], (16.0, 32.0, 16.0, 24.0, 32.0, 16.0)[k]
        scene["means"][i, 0] = (px - scene["K"][0, 2]) / f * z[i]
        scene["means"][i, 1] = (py - scene["K"][1, 2]) / scene["K"][1, 1] * z[i]
        scene["scales"][i] = [0.12 + 0.05 * rng.random(), 0.03 + 0.02 * rng.random()]
        scene["opacities"][i] = 0.6
    return scene


@pytest.mark.parametrize("seed", [0, 1])
def test_float64_parity_with_packed_and_reference(cpp_ext: float, seed: int) -> None:
    scene = random_test_scene(seed, num=60, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float64)
    bg = np.array([0.1, 0.9, 0.3, 0.5])
    kw = dict(near=0.2, far=10.0)
    a, b = _compare(params, cam, atol=1e-10, grad_rtol=1e-9, background=torch.tensor(bg), **kw)
    ref = _check_reference(b, scene, 1e-9, background=bg, **kw)
    counts = ref["counts"]
    # the scene terminates pixels, uses the low-pass branch and spans all 2×2 tiles
    assert counts["terminated"] > 0 and counts["lowpass"] > 0
    alpha = b.alpha.detach()
    tiles = [(r, c) for r in (slice(0, 16), slice(16, 20)) for c in (slice(0, 16), slice(16, 24))]
    assert all(float(alpha[r, c].max()) > 0.1 for r, c in tiles)
    assert float(b.distortion.detach().max()) > 1e-6 and float(b.median_depth.detach().max()) > 0
    # num_pairs counts composited pairs; the packed backend also counts pairs behind terminated pixels
    assert int(b.num_pairs) == counts["contributions"] < int(a.num_pairs)


@pytest.mark.parametrize("seed", [2, 3])
def test_tilted_edge_on_and_tile_crossing_surfels(cpp_ext: float, seed: int) -> None:
    scene = _tilted_scene(seed)
    params, cam = scene_tensors(scene, torch.float64)
    kw = dict(near=0.2, far=10.0, background=0.4)
    _, b = _compare(params, cam, atol=1e-10, grad_rtol=1e-9, **kw)
    ref = _check_reference(b, scene, 1e-9, **kw)
    assert ref["counts"]["lowpass"] > 0 and int(b.num_pairs) == ref["counts"]["contributions"]
    # the border surfels cover the 2×2 pixels straddling each tile border they sit on
    alpha = b.alpha.detach()
    for y, x in ((16, 16), (32, 16), (16, 32), (24, 16), (16, 24)):
        assert float(alpha[y - 1 : y + 1, x - 1 : x + 1].min()) > 0.01, (y, x)


def test_float32_parity_many_overlapping_surfels(cpp_ext: float) -> None:
    scene = random_test_scene(4, num=200, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float32)
    kw = dict(near=0.2, far=10.0, background=0.25)
    _, b = _compare(params, cam, atol=2e-5, grad_rtol=1e-4, **kw)
    _check_reference(b, scene, 2e-5, **kw)
    assert b.color.dtype == torch.float32 and int(b.num_pairs) > 3000


def test_near_plane_and_surfels_behind_camera(cpp_ext: float) -> None:
    scene = random_test_scene(5, num=50, width=24, height=20)
    scene["means"][40:44, 2] = [-1.0, -0.3, 0.05, 0.15]
    scene["scales"][42] = [0.4, 0.4]
    params, cam = scene_tensors(scene, torch.float64)
    _, b = _compare(params, cam, atol=1e-10, grad_rtol=1e-9, near=2.65, far=10.0)
    ref = _check_reference(b, scene, 1e-9, near=2.65, far=10.0)
    assert ref["counts"]["near_skipped"] > 0
    assert not bool(b.visible[40:44].any())
    assert float(b.depth.detach()[b.alpha.detach() > 0].min()) >= 2.65


def test_spherical_harmonics_and_camera_batch(cpp_ext: float) -> None:
    scene = random_test_scene(8, num=40, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float64)
    g = torch.Generator().manual_seed(1)
    params[4] = torch.rand(40, 4, 3, generator=g, dtype=torch.float64) - 0.3
    w2c2 = cam.w2c.clone()
    w2c2[:3, 3] += torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    batch = RenderCamera(torch.stack([cam.K, cam.K]), torch.stack([cam.w2c, w2c2]), 24, 20)
    a, b = _compare(params, batch, atol=1e-10, grad_rtol=1e-9, near=0.2, far=10.0, background=0.2)
    assert b.color.shape == (2, 20, 24, 3) and b.num_pairs.shape == (2,)
    assert bool((b.num_pairs > 0).all()) and bool((b.num_pairs <= a.num_pairs).all())


def test_empty_scene_gives_background_and_zero_gradients(cpp_ext: float) -> None:
    scene = random_test_scene(6, num=30, width=40, height=36)
    params, cam = scene_tensors(scene, torch.float64)
    params[0] = params[0] * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # all behind the camera
    ps = [p.clone().requires_grad_(True) for p in params]
    out = rasterize_surfels(*ps, cam, backend="cpp", background=0.5)
    assert float(out.color.detach().sub(0.5).abs().max()) == 0.0 and int(out.num_pairs) == 0
    out.color.sum().backward()
    assert all(float(p.grad.abs().max()) == 0.0 for p in ps if p.grad is not None)


def _tiny_scene(width: int = 16, height: int = 12) -> tuple[list[torch.Tensor], RenderCamera]:
    scene = random_test_scene(11, num=8, width=width, height=height, num_features=2)
    scene["opacities"] = np.clip(scene["opacities"], 0.3, 0.9)  # away from the 0.99 clamp
    return scene_tensors(scene, torch.float64)


def test_gradcheck_float64_tiny_scene(cpp_ext: float) -> None:
    """gradcheck (fast mode: random projections) of every output w.r.t. every surfel parameter."""
    params, cam = _tiny_scene()
    ps = tuple(p.clone().requires_grad_(True) for p in params)

    def render(*args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = rasterize_surfels(*args, cam, backend="cpp", near=0.2, far=10.0, background=0.3)
        return (out.color, out.alpha, out.depth_sum, out.median_depth, out.normal_cam, out.distortion)

    out = render(*ps)
    assert float(out[1].detach().max()) > 0.5 and float(out[5].detach().max()) > 0
    assert torch.autograd.gradcheck(render, ps, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_gradcheck_float64_compositing_full_jacobian(cpp_ext: float) -> None:
    """Full-Jacobian gradcheck of the compositing-only node w.r.t. the per-surfel table and payload
    (the node that runs when the camera requires grad, so the render here differentiates K)."""
    from sage_core.render import surfels as surfels_mod

    params, cam = _tiny_scene(8, 6)  # every output pixel is one backward call of the full Jacobian
    cam = RenderCamera(cam.K.clone().requires_grad_(True), cam.w2c, cam.width, cam.height)
    captured: dict = {}
    real = _cpp_surfels.composite_cpp

    def spy(table, payload, boxes, W, H, near, far, progress=None):  # noqa: ANN001, ANN202
        captured.update(table=table.detach(), payload=payload.detach(), boxes=boxes, size=(W, H, near, far))
        return real(table, payload, boxes, W, H, near, far, progress)

    _cpp_surfels.composite_cpp = spy
    try:
        rasterize_surfels(*params, cam, backend="cpp", near=0.2, far=10.0)
    finally:
        _cpp_surfels.composite_cpp = real
    assert surfels_mod is not None and captured["table"].shape[1] == 8
    W, H, near, far = captured["size"]

    def composite(table: torch.Tensor, payload: torch.Tensor) -> tuple[torch.Tensor, ...]:
        img = _cpp_surfels.composite_cpp(table, payload, captured["boxes"], W, H, near, far)
        return (img.features, img.alpha, img.depth_sum, img.normal, img.median, img.distortion)

    inputs = (captured["table"].clone().requires_grad_(True), captured["payload"].clone().requires_grad_(True))
    out = composite(*inputs)
    alpha = out[1].detach()
    assert float((alpha > 0).double().mean()) > 0.5 and float(alpha.max()) > 0.5 and float(out[5].detach().max()) > 0
    assert torch.autograd.gradcheck(composite, inputs, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_gradients_do_not_depend_on_the_thread_count(cpp_ext: float) -> None:
    scene = random_test_scene(7, num=120, width=40, height=36)
    params, cam = scene_tensors(scene, torch.float32)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        a, ga = render_with_grads(params, cam, "cpp")
        torch.set_num_threads(2)
        b, gb = render_with_grads(params, cam, "cpp")
    finally:
        torch.set_num_threads(old)
    assert torch.equal(a.color, b.color) and torch.equal(a.distortion, b.distortion)
    assert all(torch.equal(x, y) for x, y in zip(ga, gb))


def test_bin_tiles_lists_each_surfel_in_its_tiles(cpp_ext: float) -> None:
    check_tile_binning(_cpp_surfels.bin_tiles)


def test_auto_resolves_to_cpp_on_cpu(cpp_ext: float) -> None:
    assert resolve_backend("auto", "cpu") == "cpp"
    assert resolve_backend("cpp", torch.device("cpu")) == "cpp"
    assert resolve_backend("torch", "cpu") == "torch"
    scene = random_test_scene(2, num=30, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float32)
    a = rasterize_surfels(*params, cam, backend="auto", far=10.0)
    b = rasterize_surfels(*params, cam, backend="cpp", far=10.0)
    assert torch.equal(a.color, b.color) and int(a.num_pairs) == int(b.num_pairs)
    with pytest.raises(ValueError, match="unknown backend"):
        resolve_backend("fast", "cpu")


def test_unavailable_extension_errors_for_cpp_and_warns_once_for_auto(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_cpp_surfels.EXT, "state", {"ok": False, "reason": "no C++ compiler ('c++') on PATH"})
    monkeypatch.setattr(_cpp_surfels.EXT, "warned", False)
    with pytest.raises(ValueError, match="backend='cpp' is unavailable: no C\\+\\+ compiler"):
        resolve_backend("cpp", "cpu")
    scene = random_test_scene(2, num=20, width=16, height=16)
    params, cam = scene_tensors(scene, torch.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert resolve_backend("auto", "cpu") == "torch"
        out = rasterize_surfels(*params, cam, backend="auto", far=10.0)
    ref = rasterize_surfels(*params, cam, backend="torch", far=10.0)
    assert torch.equal(out.color, ref.color)
    msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "native CPU rasterizer is unavailable" in msgs[0]


def test_importing_the_package_compiles_nothing() -> None:
    code = textwrap.dedent(
        """
        import torch
        import sage_core, sage_core.render
        from sage_core.render import _cpp_surfels
        assert _cpp_surfels.EXT.state == {}, _cpp_surfels.EXT.state
        assert not hasattr(torch.ops.sage_surfels_cpu, "forward")
        print("lazy")
        """
    )
    env = dict(os.environ, SAGE_CACHE_DIR="/nonexistent-sage-cache")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "lazy", proc.stderr[-2000:]


@pytest.mark.parametrize("dtype,atol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_depth_normals_match_torch(cpp_ext: float, dtype: torch.dtype, atol: float) -> None:
    from sage_core.render.surfels import depth_to_normal

    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[30.0, 0.2, 12.3], [0.0, 31.0, 9.7], [0.0, 0.0, 1.0]], dtype=dtype)
    depth = torch.rand(20, 24, generator=g, dtype=dtype) + 2.0
    depth[3:6, 4:9] = 0.0  # an uncovered patch: zero depth, degenerate normals at its edges
    d1, d2 = depth.clone().requires_grad_(True), depth.clone().requires_grad_(True)
    a, b = depth_to_normal(d1, K), _cpp_surfels.depth_to_normal_cpp(d2, K)
    weight = torch.rand(20, 24, 3, generator=g, dtype=dtype) * (depth > 0).unsqueeze(-1)
    (a * weight).sum().backward()
    (b * weight).sum().backward()
    assert b.dtype == dtype and float((a - b).detach().abs().max()) <= atol
    assert float((d1.grad - d2.grad).abs().max()) <= atol * float(d1.grad.abs().max())
    small = (torch.rand(7, 6, generator=g, dtype=torch.float64) + 2.0).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: _cpp_surfels.depth_to_normal_cpp(x, K.double()), (small,))


# ------------------------------------------------------------------------------------------------
# The whole render in the extension: edge cases, every differentiable input, builds and threads.


def _edge_case_scene(seed: int) -> dict:
    """random_test_scene plus surfels behind the camera, between the camera and the near plane,
    crossing the camera plane, off-screen (far out, and across each image border), with zero scales,
    one zero scale, and an opacity below 1/255. Surfel indices: behind 50, before near 51, crossing
    the camera plane 52, far off-screen 53-54, across the borders 55-58, degenerate 59-61."""
    scene = random_test_scene(seed, num=70, width=40, height=28)
    K, W, H = scene["K"], scene["width"], scene["height"]

    def at_pixel(i: int, px: float, py: float, z: float) -> None:
        # the camera's rotation and offset are small; place the centre on the pixel in camera terms
        cam = np.array([(px - K[0, 2]) / K[0, 0] * z, (py - K[1, 2]) / K[1, 1] * z, z])
        R, t = scene["w2c"][:3, :3], scene["w2c"][:3, 3]
        scene["means"][i] = R.T @ (cam - t)

    scene["means"][50] = [0.1, 0.0, -1.0]
    scene["means"][51] = [0.0, 0.02, 0.05]
    at_pixel(52, 20.0, 14.0, 0.3)
    scene["scales"][52] = [0.6, 0.6]
    scene["quats"][52] = [0.7, 0.7, 0.0, 0.0]
    at_pixel(53, -40.0, 10.0, 3.0)
    at_pixel(54, W + 50.0, 10.0, 3.0)
    for i, (px, py) in zip(range(55, 59), ((-1.0, 12.0), (W + 1.0, 5.0), (8.0, -1.5), (30.0, H + 1.0))):
        at_pixel(i, px, py, 2.5)
        scene["scales"][i] = [0.1, 0.07]
        scene["opacities"][i] = 0.8
    scene["scales"][59] = [0.0, 0.0]
    scene["scales"][60] = [0.0, 0.07]
    scene["opacities"][61] = 1.0 / 512
    return scene


@pytest.mark.parametrize("dtype,atol,grad_rtol,ref_atol", [(torch.float64, 1e-10, 1e-9, 1e-9), (torch.float32, 2e-5, 1e-4, 2e-5)])
def test_edge_cases_match_torch_and_reference(cpp_ext: float, dtype: torch.dtype, atol: float, grad_rtol: float, ref_atol: float) -> None:
    scene = _edge_case_scene(9)
    params, cam = scene_tensors(scene, dtype)
    kw = dict(near=0.2, far=10.0, background=0.3)
    _, b = _compare(params, cam, atol=atol, grad_rtol=grad_rtol, **kw)
    # in float32 the normals from depth difference rounded depths of neighbouring pixels (the torch
    # backend is as far from the float64 reference there)
    loose = {} if dtype == torch.float64 else {"surf_normal_cam": 1e-4, "surf_normal_world": 1e-4}
    _check_reference(b, scene, ref_atol, atol_by_name=loose, **kw)
    visible = b.visible.tolist()
    assert not any(visible[i] for i in (50, 51, 53, 54))  # behind, before the near plane, far off-screen
    assert all(visible[i] for i in range(55, 59))  # across the borders: partly on screen
    alpha = b.alpha.detach()
    W, H = scene["width"], scene["height"]
    assert float(alpha[:, 0].max()) > 0.05 and float(alpha[:, W - 1].max()) > 0.05
    assert float(alpha[0, :].max()) > 0.05 and float(alpha[H - 1, :].max()) > 0.05


def test_off_screen_only_scene_renders_the_background(cpp_ext: float) -> None:
    scene = _edge_case_scene(10)
    keep = [50, 51, 53, 54, 59, 61]  # nothing of these reaches a pixel
    for key in ("means", "quats", "scales", "opacities", "features"):
        scene[key] = scene[key][keep]
    params, cam = scene_tensors(scene, torch.float64)
    ps = [p.clone().requires_grad_(True) for p in params]
    out = rasterize_surfels(*ps, cam, backend="cpp", near=0.2, far=10.0, background=0.25)
    assert int(out.num_pairs) == 0 and float((out.color.detach() - 0.25).abs().max()) == 0.0
    assert float(out.alpha.detach().abs().max()) == 0.0 and float(out.surf_normal_cam.detach().abs().max()) == 0.0
    (out.color.sum() + out.depth.sum() + out.distortion.sum()).backward()
    assert all(float(p.grad.abs().max()) == 0.0 for p in ps)


def test_no_surfels(cpp_ext: float) -> None:
    scene = random_test_scene(3, num=10, width=20, height=18)
    _, cam = scene_tensors(scene, torch.float32)
    params = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 2), torch.zeros(0), torch.zeros(0, 3)]
    ps = [p.clone().requires_grad_(True) for p in params]
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = rasterize_surfels(*ps, cam, backend="cpp", background=bg)
    ref = rasterize_surfels(*params, cam, backend="torch", background=bg)
    for name in OUTPUTS:
        assert torch.equal(getattr(out, name).detach(), getattr(ref, name)), name
    assert out.visible.shape == (0,) and out.means2d.shape == (0, 2) and int(out.num_pairs) == 0
    (out.color.sum() + out.alpha.sum()).backward()
    assert [tuple(p.grad.shape) for p in ps] == [tuple(p.shape) for p in params]


@pytest.mark.parametrize("name", OUTPUTS)
def test_gradients_of_each_output_alone(cpp_ext: float, name: str) -> None:
    """The backward with only one output in the loss (the others get no gradient), once with a
    weighted sum and once with a plain sum, whose gradient arrives as an expanded tensor."""
    scene = random_test_scene(12, num=60, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float64)
    grads = {}
    for backend in ("torch", "cpp"):
        ps = [p.clone().requires_grad_(True) for p in params]
        out = rasterize_surfels(*ps, cam, backend=backend, near=0.2, far=10.0, background=0.3)
        out.means2d.retain_grad()
        v = getattr(out, name)
        w = torch.rand(v.shape, generator=torch.Generator().manual_seed(5), dtype=v.dtype)
        ((v * w).sum() + v.sum()).backward()
        grads[backend] = [p.grad for p in ps] + [out.means2d.grad]
    for label, x, y in zip(PARAMS + ("means2d",), grads["torch"], grads["cpp"]):
        x = torch.zeros_like(y) if x is None else x  # torch leaves inputs its loss does not reach at None
        y = torch.zeros_like(x) if y is None else y
        # relative to the input's largest gradient, with an absolute floor for gradients that are
        # zero up to rounding (e.g. of the median depth w.r.t. scales)
        scale = float(x.abs().max())
        assert float((x - y).abs().max()) <= 1e-9 * scale + 1e-13, (name, label, float((x - y).abs().max()), scale)


@pytest.mark.parametrize("camera_grad", [False, True])
def test_background_and_camera_gradients(cpp_ext: float, camera_grad: bool) -> None:
    """Gradients of a differentiable background, and of K and w2c (which switches the cpp backend to
    the torch projection with the native compositing), against the torch backend."""
    scene = random_test_scene(13, num=50, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float64)
    res = {}
    for backend in ("torch", "cpp"):
        ps = [p.clone().requires_grad_(True) for p in params]
        bg = torch.tensor([0.2, 0.5, 0.1, 0.7], dtype=torch.float64, requires_grad=True)
        K = cam.K.clone().requires_grad_(camera_grad)
        w2c = cam.w2c.clone().requires_grad_(camera_grad)
        out = rasterize_surfels(*ps, RenderCamera(K, w2c, 24, 20), backend=backend, near=0.2, far=10.0, background=bg)
        g = torch.Generator().manual_seed(8)
        loss = sum((getattr(out, n) * torch.rand(getattr(out, n).shape, generator=g, dtype=torch.float64)).sum() for n in OUTPUTS)
        loss.backward()
        res[backend] = [p.grad for p in ps] + [bg.grad] + ([K.grad, w2c.grad] if camera_grad else [])
    for x, y in zip(res["torch"], res["cpp"]):
        assert float((x - y).abs().max()) <= 1e-9 * float(x.abs().max())


def test_gradcheck_float64_full_render_full_jacobian(cpp_ext: float) -> None:
    """Full-Jacobian gradcheck of the whole cpp render w.r.t. every surfel input and the background.
    The normals from depth are left out: they are multiplied by alpha.detach() by design."""
    params, cam = _tiny_scene(8, 6)
    bg = torch.tensor([0.3, 0.6], dtype=torch.float64)
    inputs = tuple(p.clone().requires_grad_(True) for p in params) + (bg.requires_grad_(True),)
    names = [n for n in OUTPUTS if not n.startswith("surf_normal")]

    def render(m, q, s, o, f, b):  # noqa: ANN001, ANN202
        out = rasterize_surfels(m, q, s, o, f, cam, backend="cpp", near=0.2, far=10.0, background=b)
        return tuple(getattr(out, n) for n in names)

    out = render(*inputs)
    assert float(out[1].detach().max()) > 0.5 and float(out[-1].detach().max()) > 0
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def _assert_identical(a, ga, b, gb) -> None:
    """Two renders (outputs and input gradients) are bit-identical."""
    assert all(torch.equal(getattr(a, n), getattr(b, n)) for n in OUTPUTS)
    assert len(ga) == len(gb) and all(torch.equal(x, y) for x, y in zip(ga, gb))


def test_image_outputs_are_the_image_fields_of_surfel_render() -> None:
    from dataclasses import fields

    from sage_core.render._packed import IMAGE_OUTPUTS
    from sage_core.render.surfels import SurfelRender

    per_surfel = ("visible", "radii", "means2d", "num_pairs")
    assert IMAGE_OUTPUTS == tuple(f.name for f in fields(SurfelRender) if f.name not in per_surfel)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_avx2_and_sse2_builds_agree_exactly(cpp_ext: float, dtype: torch.dtype) -> None:
    """The tile loops are built for AVX2 and for SSE2 from one source; both give identical results
    (on a CPU without AVX2 both runs use the SSE2 build)."""
    ops = torch.ops.sage_surfels_cpu
    scene = random_test_scene(14, num=150, width=40, height=36)
    params, cam = scene_tensors(scene, dtype)
    before = ops.use_avx2(True)
    try:
        a, ga = render_with_grads(params, cam, "cpp", far=10.0)
        ops.use_avx2(False)
        b, gb = render_with_grads(params, cam, "cpp", far=10.0)
    finally:
        ops.use_avx2(before)
    _assert_identical(a, ga, b, gb)


def test_thread_count_invariance_float64_batch_and_sh(cpp_ext: float) -> None:
    scene = random_test_scene(15, num=150, width=40, height=36)
    params, cam = scene_tensors(scene, torch.float64)
    params[4] = torch.rand(150, 4, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) - 0.3
    w2c2 = cam.w2c.clone()
    w2c2[:3, 3] += torch.tensor([0.04, 0.01, -0.05], dtype=torch.float64)
    batch = RenderCamera(torch.stack([cam.K, cam.K]), torch.stack([cam.w2c, w2c2]), 40, 36)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        a, ga = render_with_grads(params, batch, "cpp", far=10.0)
        torch.set_num_threads(2)
        b, gb = render_with_grads(params, batch, "cpp", far=10.0)
    finally:
        torch.set_num_threads(old)
    _assert_identical(a, ga, b, gb)


def test_larger_scene_parity_float32(cpp_ext: float) -> None:
    """Many tiles (some partial), deep overlap and terminated pixels: values and gradients against
    the torch backend in float32."""
    g = torch.Generator().manual_seed(21)
    n, W, H = 1500, 70, 50
    f = 1.2 * W
    z = 3.0 + 0.6 * (torch.rand(n, generator=g) - 0.5)
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * ((W / 2) / f * z)[:, None] * 1.1
    params = [
        torch.cat([xy, z[:, None]], 1),
        torch.randn(n, 4, generator=g),
        0.01 + 0.05 * torch.rand(n, 2, generator=g),
        0.1 + 0.8 * torch.rand(n, generator=g),
        torch.rand(n, 3, generator=g),
    ]
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    cam = RenderCamera(K, torch.eye(4), W, H)
    _, b = _compare(params, cam, atol=2e-5, grad_rtol=1e-4, background=1.0)
    assert int(b.num_pairs) > 10_000 and float(b.alpha.detach().max()) > 0.99
