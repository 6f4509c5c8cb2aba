"""The Triton surfel backend against the packed torch backend (values and gradients).

Without a GPU the kernels run in Triton's CPU interpreter: TRITON_INTERPRET=1 is set before triton
and the backend module are imported, and again while this module's tests run, so the same kernel
code is checked with numpy semantics. With CUDA the module is imported compiled and the ``cuda``
tests run the parity checks on the GPU.

Tolerances. Interpreter, float64: values 1e-10 absolute, gradients 1e-9 relative to the largest
gradient of each input (the two backends do the same arithmetic in a different order). Interpreter,
float32: values 2e-5 absolute, gradients 1e-4 relative to the largest gradient. CUDA (float32 and
float64): values within 1e-4 except on at most 0.5 % of the pixels (a last-bit difference in exp can
flip a 1/255 cut or a termination there), and gradients with ‖Δg‖ ≤ 1e-3·‖g‖ per input.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
import torch

from sage_core.render import RenderCamera, rasterize_surfels
from sage_core.render._dense_reference import random_test_scene, render_dense_reference

from render_parity import OUTPUTS, PARAMS, check_tile_binning, compare_backends, render_with_grads, scene_tensors


def _import_backend():
    if torch.cuda.is_available():
        import sage_core.render._triton_surfels as ts

        return ts
    old = os.environ.get("TRITON_INTERPRET")
    os.environ["TRITON_INTERPRET"] = "1"
    try:
        import sage_core.render._triton_surfels as ts
    finally:
        if old is None:
            del os.environ["TRITON_INTERPRET"]
        else:
            os.environ["TRITON_INTERPRET"] = old
    return ts


try:
    ts = _import_backend()
except ImportError as exc:  # pragma: no cover - depends on the environment
    pytest.skip(f"triton is not installed ({exc})", allow_module_level=True)


@pytest.fixture(autouse=True, scope="module")
def _interpreter_env():
    """Keep TRITON_INTERPRET=1 while this module's tests run (triton checks it again at launch)."""
    if not ts.INTERPRETED:
        yield
        return
    old = os.environ.get("TRITON_INTERPRET")
    os.environ["TRITON_INTERPRET"] = "1"
    yield
    if old is None:
        del os.environ["TRITON_INTERPRET"]
    else:
        os.environ["TRITON_INTERPRET"] = old


interpreted = pytest.mark.skipif(
    not ts.INTERPRETED, reason="the Triton backend was imported with compiled kernels; the cuda tests cover it"
)



def _compare(params, cam, atol: float, grad_rtol: float, **kw) -> tuple:
    """The backend under test against the torch backend (see ``compare_backends``)."""
    return compare_backends(params, cam, "triton", atol, grad_rtol, **kw)


@interpreted
@pytest.mark.parametrize("seed", [0, 1])
def test_float64_parity_with_torch_backend(seed: int) -> None:
    scene = random_test_scene(seed, num=60, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float64, "cpu")
    kw = dict(background=torch.tensor([0.1, 0.9, 0.3, 0.5], dtype=torch.float64), near=0.2, far=10.0)
    a, b = _compare(params, cam, atol=1e-10, grad_rtol=1e-9, **kw)
    ref = render_dense_reference(*(scene[k] for k in PARAMS), scene["K"], scene["w2c"], 24, 20, near=0.2, far=10.0)
    counts = ref["counts"]
    # the scene terminates pixels, uses the low-pass branch and spans all 2×2 tiles
    assert counts["terminated"] > 0 and counts["lowpass"] > 0
    alpha = b.alpha.detach()
    tiles = [(r, c) for r in (slice(0, 16), slice(16, 20)) for c in (slice(0, 16), slice(16, 24))]
    assert all(float(alpha[r, c].max()) > 0.1 for r, c in tiles)
    assert float(b.distortion.detach().max()) > 1e-6
    # the kernel counts composited pairs; the packed backend also counts pairs behind terminated pixels
    assert int(b.num_pairs) == counts["contributions"] < int(a.num_pairs)


@interpreted
def test_float32_parity_many_overlapping_surfels() -> None:
    scene = random_test_scene(4, num=200, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float32, "cpu")
    _, b = _compare(params, cam, atol=2e-5, grad_rtol=1e-4, near=0.2, far=10.0, background=0.25)
    assert b.color.dtype == torch.float32 and int(b.num_pairs) > 3000


@interpreted
def test_near_plane_and_surfels_behind_camera() -> None:
    scene = random_test_scene(5, num=50, width=24, height=20)
    # a few surfels behind the camera, one straddling the camera plane, one centred just past near
    scene["means"][40:44, 2] = [-1.0, -0.3, 0.05, 0.15]
    scene["scales"][42] = [0.4, 0.4]
    params, cam = scene_tensors(scene, torch.float64, "cpu")
    a, b = _compare(params, cam, atol=1e-10, grad_rtol=1e-9, near=2.65, far=10.0)
    ref = render_dense_reference(*(scene[k] for k in PARAMS), scene["K"], scene["w2c"], 24, 20, near=2.65, far=10.0)
    assert ref["counts"]["near_skipped"] > 0
    assert not bool(b.visible[40:44].any())
    vis = b.depth.detach()[b.alpha.detach() > 0]
    assert float(vis.min()) >= 2.65


@interpreted
def test_empty_tiles_and_empty_scene() -> None:
    scene = random_test_scene(6, num=30, width=40, height=36)
    # squeeze every surfel into the top-left tile (pixels 0..15), far from the other tiles
    z = scene["means"][:, 2]
    scene["means"][:, 0] = scene["means"][:, 0] * 0.1 + (8.0 - scene["K"][0, 2]) / scene["K"][0, 0] * z
    scene["means"][:, 1] = scene["means"][:, 1] * 0.1 + (8.0 - scene["K"][1, 2]) / scene["K"][1, 1] * z
    scene["scales"] *= 0.2
    params, cam = scene_tensors(scene, torch.float64, "cpu")
    a, b = _compare(params, cam, atol=1e-10, grad_rtol=1e-9, near=0.2, far=10.0)
    alpha = b.alpha.detach()
    assert float(alpha[:16, :16].max()) > 0.5 and float(alpha[20:, :].abs().max()) == 0.0
    assert float(alpha[:, 20:].abs().max()) == 0.0

    params[0] = params[0] * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # all behind the camera
    ps = [p.clone().requires_grad_(True) for p in params]
    out = rasterize_surfels(*ps, cam, backend="triton", background=0.5)
    assert float(out.color.detach().sub(0.5).abs().max()) == 0.0 and int(out.num_pairs) == 0
    out.color.sum().backward()
    assert all(float(p.grad.abs().max()) == 0.0 for p in ps if p.grad is not None)


@interpreted
def test_spherical_harmonics_and_camera_batch() -> None:
    scene = random_test_scene(8, num=40, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float64, "cpu")
    g = torch.Generator().manual_seed(1)
    params[4] = torch.rand(40, 4, 3, generator=g, dtype=torch.float64) - 0.3
    w2c2 = cam.w2c.clone()
    w2c2[:3, 3] += torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    batch = RenderCamera(torch.stack([cam.K, cam.K]), torch.stack([cam.w2c, w2c2]), 24, 20)
    a, b = _compare(params, batch, atol=1e-10, grad_rtol=1e-9, near=0.2, far=10.0, background=0.2)
    assert b.color.shape == (2, 20, 24, 3) and b.num_pairs.shape == (2,)


@interpreted
def test_bin_tiles_lists_each_surfel_in_its_tiles() -> None:
    _, offsets, lst = check_tile_binning(ts.bin_tiles)
    assert int(offsets[5]) == int(offsets[4]) and lst.shape[0] > 40


@interpreted
def test_auto_backend_never_picks_interpreted_triton_for_cpu_tensors() -> None:
    from sage_core.render import resolve_backend

    scene = random_test_scene(2, num=30, width=24, height=20)
    params, cam = scene_tensors(scene, torch.float64, "cpu")
    chosen = resolve_backend("auto", "cpu")  # the native CPU backend when it builds, else torch
    assert chosen in ("cpp", "torch")
    a = rasterize_surfels(*params, cam, backend="auto", far=10.0)
    b = rasterize_surfels(*params, cam, backend=chosen, far=10.0)
    c = rasterize_surfels(*params, cam, backend="triton", far=10.0)
    assert int(a.num_pairs) == int(b.num_pairs) and torch.equal(a.color, b.color)
    assert float((a.color - c.color).abs().max()) < 1e-10


_COMPILE_CHECK = textwrap.dedent(
    """
    import os
    os.environ.pop("TRITON_INTERPRET", None)
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource
    import sage_core.render._triton_surfels as ts
    from sage_core.render._packed import ALPHA_MAX, T_MIN
    from sage_core.render._project import ALPHA_MIN
    assert not ts.INTERPRETED
    common = dict(W="i32", H="i32", GX="i32", P="i32", near="fp32", cm="fp32")
    consts = dict(ALPHA_MAX_C=ALPHA_MAX, ALPHA_MIN_C=ALPHA_MIN, TILE_C=16, BLOCK=256, CP=8)
    for fp in ("fp32", "fp64"):
        f = "*" + fp
        fwd = dict(tab_ptr=f, pay_ptr=f, off_ptr="*i32", lst_ptr="*i32", out_pay_ptr=f, out_s_ptr=f, aux_ptr=f,
                   tfin_ptr="*fp64", auxi_ptr="*i32", **common)
        bwd = dict(tab_ptr=f, pay_ptr=f, off_ptr="*i32", lst_ptr="*i32", out_s_ptr=f, aux_ptr=f, tfin_ptr="*fp64",
                   auxi_ptr="*i32", g_pay_ptr=f, g_s_ptr=f, gtab_ptr=f, gpay_ptr=f, **common)
        kernels = ((ts._forward_kernel, fwd, dict(T_MIN_C=T_MIN, CHUNK=ts._CHUNK)), (ts._backward_kernel, bwd, {}))
        for fn, sig, extra in kernels:
            c = dict(consts, **extra)
            sig = dict(sig, **{k: "constexpr" for k in c})
            k = triton.compile(ASTSource(fn=fn, signature=sig, constexprs=c), target=GPUTarget("cuda", 90, 32),
                               options={"num_warps": 8, "enable_fp_fusion": False})
            assert len(k.asm["cubin"]) > 1000
    import torch
    from sage_core.render import RenderCamera, rasterize_surfels
    if not torch.cuda.is_available():  # compiled kernels refuse CPU tensors with a clear error
        cam = RenderCamera(torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]), torch.eye(4), 16, 16)
        surfel = (torch.tensor([[0.0, 0, 2]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 2), 0.1),
                  torch.tensor([0.5]), torch.ones(1, 3))
        try:
            rasterize_surfels(*surfel, cam, backend="triton")
            raise AssertionError("no error")
        except ValueError as e:
            assert "CUDA tensors" in str(e) and "TRITON_INTERPRET" in str(e), e
    print("compiled")
    """
)


def test_kernels_compile_for_sm90_without_a_gpu() -> None:
    """Compiled mode in a fresh process: both kernels build for sm_90; CPU tensors are refused."""
    pytest.importorskip("triton.backends.nvidia", reason="triton without its NVIDIA backend")
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    proc = subprocess.run([sys.executable, "-c", _COMPILE_CHECK], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("compiled"), proc.stderr[-3000:]


def _cuda_parity(scene: dict, dtype: torch.dtype, **kw) -> None:
    params, cam = scene_tensors(scene, dtype, "cuda")
    a, ga = render_with_grads(params, cam, "torch", **kw)
    b, gb = render_with_grads(params, cam, "triton", **kw)
    for name in OUTPUTS:
        x, y = getattr(a, name).detach(), getattr(b, name).detach()
        bad = (x - y).abs() > 1e-4
        if bad.dim() == 3:  # (H, W, ch): a pixel is off when any channel is
            bad = bad.any(-1)
        assert float(bad.float().mean()) <= 0.005, (name, float(bad.float().mean()))
    for name, x, y in zip(PARAMS + ("means2d",), ga, gb):
        assert float((x - y).norm()) <= 1e-3 * float(x.norm()), name


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_parity_small_scenes(seed: int, dtype: torch.dtype) -> None:
    _cuda_parity(random_test_scene(seed, num=200, width=24, height=20), dtype, near=0.2, far=10.0, background=0.3)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_parity_larger_scene_and_auto() -> None:
    scene = random_test_scene(9, num=3000, width=160, height=120)
    _cuda_parity(scene, torch.float32, near=0.2, far=10.0)
    params, cam = scene_tensors(scene, torch.float32, "cuda")
    a = rasterize_surfels(*params, cam, backend="auto", far=10.0)
    b = rasterize_surfels(*params, cam, backend="triton", far=10.0)
    assert torch.equal(a.color, b.color)
