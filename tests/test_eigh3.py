"""The native batched 3x3 eigensolver (``_cpp_eigh``, ``safe_eigh(backend="cpp")``) against ``torch.linalg.eigh``.

Every case runs in float32 and float64. Tolerances are relative to the matrix's largest |entry| (the
scale of both solvers' backward errors): eigenvalues and reconstructions V·diag(w)·Vᵀ within 1e-12
(float64) or 2e-6 (float32), orthonormality of V within 1e-13 or 1e-6. Eigenvectors are compared
up to sign, and only where their eigenvalue is separated from the others (elsewhere the eigenspace's
projector is compared). Gradients of safe_eigh through a sign-invariant loss: within 1e-3 (float32) or
5e-10 (float64) of the largest entry. Surfel frames of the shape network's near-prior matrices: scales,
covariance and normal within 2e-5 / 1e-11, tangents (up to a common sign) and gradients within 5e-4 /
1e-10 (relative to the largest gradient entry), as the two tangent eigenvalues are close. The
one-gather symmetric_from_tril is compared bit for bit with the formula it replaced. The tests skip
with the build's reason when the extension cannot be built.
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from sage_core.fields import _cpp_eigh
from sage_core.fields import shape as shape_mod
from sage_core.fields.shape import frame_from_symmetric, safe_eigh, symmetric_from_tril

DTYPES = (torch.float32, torch.float64)
TOL = {torch.float32: 2e-6, torch.float64: 1e-12}
ORTHO = {torch.float32: 1e-6, torch.float64: 1e-13}


@pytest.fixture(scope="module", autouse=True)
def cpp_ext() -> None:
    ok, reason = _cpp_eigh.available()
    if not ok:
        pytest.skip(f"the C++ eigensolver extension cannot be built here: {reason}")


def random_rotations(n: int, dtype: torch.dtype, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    return q.to(dtype)


def with_spectrum(evals: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Q·diag(evals)·Qᵀ for random rotations Q. evals: (N, 3) -> (N, 3, 3), built in float64."""
    q = random_rotations(evals.shape[0], torch.float64, seed)
    a = q @ torch.diag_embed(evals.to(torch.float64)) @ q.transpose(-1, -2)
    return 0.5 * (a + a.transpose(-1, -2))


def random_symmetric(n: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    return (a + a.transpose(-1, -2)).to(dtype)


def check_decomposition(a: torch.Tensor, w: torch.Tensor, v: torch.Tensor) -> None:
    """Eigenvalues against torch, reconstruction, orthonormality, sign rule, ascending order."""
    dtype = a.dtype
    scale = a.abs().amax(dim=(-1, -2)).clamp_min(torch.finfo(dtype).tiny)
    w_ref, _ = torch.linalg.eigh(a.to(torch.float64))
    tol = TOL[dtype]
    assert w.dtype == v.dtype == dtype and w.shape == a.shape[:-1] and v.shape == a.shape
    assert bool((((w.double() - w_ref).abs().amax(-1)) <= tol * scale.double()).all())
    rec = v.double() @ torch.diag_embed(w.double()) @ v.double().transpose(-1, -2)
    assert bool((((rec - a.double()).abs().amax(dim=(-1, -2))) <= 4 * tol * scale.double()).all())
    eye = torch.eye(3, dtype=torch.float64)
    assert float((v.double().transpose(-1, -2) @ v.double() - eye).abs().max()) <= ORTHO[dtype]
    assert bool((w[..., 1:] >= w[..., :-1]).all())
    assert bool((v.amax(-2) == v.abs().amax(-2)).all())  # an entry of largest magnitude is positive


def projector(v: torch.Tensor, cols: list[int]) -> torch.Tensor:
    p = v[..., :, cols]
    return p @ p.transpose(-1, -2)


@pytest.mark.parametrize("dtype", DTYPES)
def test_random_matrices_match_torch(dtype):
    a = random_symmetric(2000, dtype, seed=1)
    w, v = _cpp_eigh.eigh3(a)
    check_decomposition(a, w, v)
    _, v_ref = torch.linalg.eigh(a)
    w64 = torch.linalg.eigvalsh(a.double())
    gap = torch.minimum(w64[:, 1] - w64[:, 0], w64[:, 2] - w64[:, 1]) / a.abs().amax(dim=(-1, -2)).double()
    sep = gap > 1e-2  # eigenvectors are determined (up to sign) to about eps / gap
    align = (v * v_ref).sum(-2).abs()[sep]
    assert int(sep.sum()) > 1500
    torch.testing.assert_close(align, torch.ones_like(align), atol=100 * ORTHO[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_batch_shapes_and_lower_triangle_only(dtype):
    a = random_symmetric(24, dtype, seed=2).reshape(2, 3, 4, 3, 3)
    w, v = _cpp_eigh.eigh3(a)
    assert w.shape == (2, 3, 4, 3) and v.shape == (2, 3, 4, 3, 3)
    w_flat, v_flat = _cpp_eigh.eigh3(a.reshape(-1, 3, 3))
    torch.testing.assert_close(w.reshape(-1, 3), w_flat, atol=0, rtol=0)
    torch.testing.assert_close(v.reshape(-1, 3, 3), v_flat, atol=0, rtol=0)
    garbage = a.clone()
    iu = torch.triu_indices(3, 3, offset=1)
    garbage[..., iu[0], iu[1]] = 123.0  # the strict upper triangle is never read (torch's UPLO="L")
    w2, v2 = _cpp_eigh.eigh3(garbage)
    torch.testing.assert_close(w2, w, atol=0, rtol=0)
    torch.testing.assert_close(v2, v, atol=0, rtol=0)
    w_ref = torch.linalg.eigvalsh(garbage)
    torch.testing.assert_close(w2, w_ref, atol=10 * TOL[dtype] * 123, rtol=0)
    noncontig = a.transpose(-1, -2)  # symmetric, so the same matrices, as a strided view
    w3, v3 = _cpp_eigh.eigh3(noncontig)
    torch.testing.assert_close(w3, w, atol=0, rtol=0)
    torch.testing.assert_close(v3, v, atol=0, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_repeated_and_nearly_repeated_eigenvalues(dtype):
    spectra = torch.tensor(
        [
            [1.0, 1.0, 1.0],
            [0.0, 1.0, 1.0],
            [-1.0, 2.0, 2.0],
            [-3.0, -3.0, 5.0],
            [1.0, 1.0 + 1e-9, 3.0],
            [1.0, 1.0 + 1e-6, 1.0 + 2e-6],
            [0.0, 0.0, 0.0],
            [-2.0, -2.0, -2.0 + 1e-12],
            [1e-3, 1.0, 1.0 + 1e-7],
        ],
        dtype=torch.float64,
    )
    a = with_spectrum(spectra.repeat(20, 1), seed=3).to(dtype)
    w, v = _cpp_eigh.eigh3(a)
    check_decomposition(a, w, v)
    _, v_ref = torch.linalg.eigh(a.double())
    # the separated eigenvalue's eigenvector and the double eigenspace's projector agree with torch
    for row, (single, pair) in {1: (0, [1, 2]), 2: (0, [1, 2]), 3: (2, [0, 1]), 4: (2, [0, 1])}.items():
        idx = torch.arange(row, a.shape[0], spectra.shape[0])
        torch.testing.assert_close(
            projector(v[idx].double(), pair), projector(v_ref[idx], pair), atol=100 * ORTHO[dtype], rtol=0
        )
        torch.testing.assert_close(
            projector(v[idx].double(), [single]), projector(v_ref[idx], [single]), atol=100 * ORTHO[dtype], rtol=0
        )


@pytest.mark.parametrize("dtype", DTYPES)
def test_diagonal_and_zero_matrices(dtype):
    diag = torch.tensor([[3.0, -1.0, 2.0], [0.0, 5.0, 0.0], [-4.0, -4.0, 1.0], [2.0, 2.0, 2.0], [1e-20, 0.0, -1e-20]], dtype=dtype)
    a = torch.diag_embed(diag)
    w, v = _cpp_eigh.eigh3(a)
    check_decomposition(a, w, v)
    torch.testing.assert_close(w, diag.sort(-1).values, atol=0, rtol=0)  # exact: no rotation happens
    assert bool(((v == 0) | (v == 1)).all())  # signed permutations with the sign rule: permutations
    order = diag.sort(stable=True, dim=-1).indices
    expect = torch.eye(3, dtype=dtype)[:, order].permute(1, 0, 2)
    torch.testing.assert_close(v, expect, atol=0, rtol=0)
    z, vz = _cpp_eigh.eigh3(torch.zeros(4, 3, 3, dtype=dtype))
    assert bool((z == 0).all())
    torch.testing.assert_close(vz, torch.eye(3, dtype=dtype).expand(4, 3, 3), atol=0, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_ill_conditioned_and_extreme_scales(dtype):
    graded = with_spectrum(torch.tensor([[1e-8, 1.0, 1e8], [-1e6, 1e-6, 1.0], [1e-7, 2e-7, 1.0]], dtype=torch.float64), seed=4)
    a = graded.to(dtype)
    w, v = _cpp_eigh.eigh3(a)
    check_decomposition(a, w, v)
    rnd = random_symmetric(50, torch.float64, seed=5)
    exps = (-30.0, 30.0) if dtype == torch.float32 else (-300.0, 300.0)
    for e in exps:
        scaled = (rnd * 10.0**e).to(dtype)
        ws, vs = _cpp_eigh.eigh3(scaled)
        check_decomposition(scaled, ws, vs)
        w1, v1 = _cpp_eigh.eigh3(rnd.to(dtype))
        torch.testing.assert_close(ws.double() / 10.0**e, w1.double(), atol=10 * TOL[dtype] * 10, rtol=10 * TOL[dtype])
    if dtype == torch.float64:
        sub = rnd[:5] * 1e-310  # subnormal entries: scaled up exactly by a power of two
        ws, vs = _cpp_eigh.eigh3(sub)
        assert bool(torch.isfinite(ws).all() and torch.isfinite(vs).all())
        eye = torch.eye(3, dtype=dtype)
        assert float((vs.transpose(-1, -2) @ vs - eye).abs().max()) < 1e-12
        mixed = torch.tensor([[[1.0, 0.0, 0.0], [1e-200, 0.0, 0.0], [0.0, 0.0, 0.0]]], dtype=dtype)
        wm, vm = _cpp_eigh.eigh3(mixed)
        check_decomposition(mixed, wm, vm)


@pytest.mark.parametrize("dtype", DTYPES)
def test_non_finite_inputs_give_nan(dtype):
    a = random_symmetric(3, dtype, seed=6)
    a[0, 1, 0] = float("nan")
    a[1, 2, 2] = float("inf")
    w, v = _cpp_eigh.eigh3(a)
    assert bool(torch.isnan(w[:2]).all() and torch.isnan(v[:2]).all())
    check_decomposition(a[2:], w[2:], v[2:])


def test_thread_count_does_not_change_results():
    a = random_symmetric(20000, torch.float64, seed=7)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        w1, v1 = _cpp_eigh.eigh3(a)
        torch.set_num_threads(2)
        w2, v2 = _cpp_eigh.eigh3(a)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(w1, w2) and torch.equal(v1, v2)


@pytest.mark.parametrize("dtype", DTYPES)
def test_safe_eigh_backends_agree_in_values_and_gradients(dtype):
    a = random_symmetric(200, dtype, seed=8).requires_grad_(True)
    g = torch.Generator().manual_seed(9)
    w_l = torch.randn(200, 3, generator=g, dtype=dtype)
    w_v = torch.randn(200, 3, 3, 3, generator=g, dtype=dtype)

    def loss(backend: str) -> tuple[torch.Tensor, torch.Tensor]:
        lam, vec = safe_eigh(a, 1e-3, backend)
        outer = vec[..., :, None, :] * vec[..., None, :, :]  # (N, 3, 3, k) v_k v_kᵀ: sign-invariant
        val = (lam * w_l).sum() + (outer.permute(0, 3, 1, 2) * w_v).sum()
        (grad,) = torch.autograd.grad(val, a)
        return val.detach(), grad

    v_cpp, g_cpp = loss("cpp")
    v_ref, g_ref = loss("torch")
    tol = TOL[dtype] * 50
    torch.testing.assert_close(v_cpp, v_ref, atol=tol * float(v_ref.abs()), rtol=0)
    scale = float(g_ref.abs().max())
    torch.testing.assert_close(g_cpp, g_ref, atol=tol * scale * 10, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_native_backward_is_the_torch_formula_bit_for_bit(cpp_ext, dtype):
    """eigh3_backward against shape.eigh_backward_torch on eigh3 solutions: random spectra, repeated and
    nearly repeated eigenvalues (the gap clamp), either upstream gradient absent, a batch shape."""
    a = torch.cat([random_symmetric(300, dtype, seed=11),
                   with_spectrum(torch.tensor([[1.0, 1.0, 2.0], [0.5, 0.5 + 1e-4, 0.7], [0.0, 0.0, 0.0]],
                                              dtype=torch.float64), seed=12).to(dtype)])  # fmt: skip
    w, v = _cpp_eigh.eigh3(a.reshape(-1, 3, 3, 3))
    g = torch.Generator().manual_seed(13)
    g_w = torch.randn(w.shape, generator=g, dtype=dtype)
    g_v = torch.randn(v.shape, generator=g, dtype=dtype).transpose(-1, -2)  # a non-contiguous upstream
    for up_w, up_v in ((g_w, g_v), (None, g_v), (g_w, None)):
        native = _cpp_eigh.eigh3_backward(w, v, up_w, up_v, 1e-3)
        assert native.shape == v.shape
        assert torch.equal(native, shape_mod.eigh_backward_torch(w, v, up_w, up_v, 1e-3))
    # safe_eigh with the cpp solver runs it
    x = a.clone().requires_grad_(True)
    lam, vec = safe_eigh(x, 1e-3, "cpp")
    (grad,) = torch.autograd.grad((lam * g_w.reshape(-1, 3)).sum() + (vec * g_v.reshape(-1, 3, 3)).sum(), x)
    lam0, vec0 = _cpp_eigh.eigh3(a)
    assert torch.equal(grad, shape_mod.eigh_backward_torch(lam0, vec0, g_w.reshape(-1, 3), g_v.reshape(-1, 3, 3), 1e-3))


@pytest.mark.parametrize("dtype", DTYPES)
def test_gap_clamped_backward_is_finite_at_repeated_eigenvalues(dtype):
    a = with_spectrum(torch.tensor([[1.0, 1.0, 0.0], [2.0, 2.0, 2.0], [0.0, 0.0, 0.0]], dtype=torch.float64), seed=10)
    a = a.to(dtype).requires_grad_(True)
    lam, vec = safe_eigh(a, 1e-3, "cpp")
    (grad,) = torch.autograd.grad(lam.sum() + vec.abs().sum(), a)
    assert bool(torch.isfinite(grad).all())


def near_prior_matrices(n: int, dtype: torch.dtype, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The shape network's matrices: I − n·nᵀ plus a small symmetric output, and the prior normals."""
    g = torch.Generator().manual_seed(seed)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    small = symmetric_from_tril(0.05 * torch.randn(n, 6, generator=g, dtype=torch.float64))
    a = torch.eye(3, dtype=torch.float64) - nrm[:, :, None] * nrm[:, None, :] + small
    return a.to(dtype), nrm.to(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_frames_from_both_backends_give_the_same_surfels(dtype):
    a, nrm = near_prior_matrices(3000, dtype, seed=11)
    a = a.requires_grad_(True)
    out = {}
    for backend in ("cpp", "torch"):
        rot, mags = frame_from_symmetric(a, nrm, 1e-3, backend)
        cov = rot[..., :2] @ torch.diag_embed(mags**2) @ rot[..., :2].transpose(-1, -2)  # the surfel's covariance
        val = (cov * torch.arange(9, dtype=dtype).reshape(3, 3)).sum() + mags.sum() + rot[..., 2].sum()
        (grad,) = torch.autograd.grad(val, a)
        out[backend] = (rot.detach(), mags.detach(), cov.detach(), grad)
    (r_c, m_c, c_c, g_c), (r_t, m_t, c_t, g_t) = out["cpp"], out["torch"]
    tol = TOL[dtype] * 10
    torch.testing.assert_close(m_c, m_t, atol=tol, rtol=0)
    torch.testing.assert_close(c_c, c_t, atol=tol, rtol=0)  # the surfel's covariance
    torch.testing.assert_close(r_c[..., 2], r_t[..., 2], atol=tol, rtol=0)  # normal: sign fixed by the reference
    assert bool((torch.linalg.det(r_c.double()) > 0.999).all())
    # the tangents agree up to one common sign per surfel (a half turn about the normal), each to about
    # eps / gap: the two tangent eigenvalues are close (the prior gives both 1)
    s = torch.sign((r_c[..., 0] * r_t[..., 0]).sum(-1, keepdim=True))
    loose = 5e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(r_c[..., :2] * s[..., None], r_t[..., :2], atol=loose, rtol=0)
    torch.testing.assert_close(g_c, g_t, atol=loose * float(g_t.abs().max()), rtol=0)


def test_auto_backend_choice_and_fallback(monkeypatch):
    a = random_symmetric(5, torch.float32, seed=12)
    assert shape_mod.resolve_eigh_backend("auto", a) == "cpp"
    assert shape_mod.resolve_eigh_backend("torch", a) == "torch"
    assert shape_mod.resolve_eigh_backend("auto", a.half()) == "torch"
    four = torch.randn(2, 4, 4, dtype=torch.float64)
    four = four + four.transpose(-1, -2)
    assert shape_mod.resolve_eigh_backend("auto", four) == "torch"
    w4, v4 = safe_eigh(four)  # any size still works through torch
    w4_ref, v4_ref = torch.linalg.eigh(four)
    assert torch.equal(w4, w4_ref) and torch.equal(v4, v4_ref)
    with pytest.raises(ValueError, match="cannot take"):
        shape_mod.resolve_eigh_backend("cpp", four)
    with pytest.raises(ValueError, match="unknown backend"):
        safe_eigh(a, 1e-3, "lapack")
    monkeypatch.setattr(_cpp_eigh.EXT, "state", {"ok": False, "reason": "no compiler (test)"})
    monkeypatch.setattr(_cpp_eigh.EXT, "warned", False)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        w, v = safe_eigh(a)
        safe_eigh(a)
    assert sum("3x3 eigensolver" in str(r.message) for r in rec) == 1
    w_ref, v_ref = torch.linalg.eigh(a)
    assert torch.equal(w, w_ref) and torch.equal(v, v_ref)
    with pytest.raises(ValueError, match="unavailable"):
        safe_eigh(a, 1e-3, "cpp")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_uses_torch():
    a = random_symmetric(5, torch.float32, seed=13).cuda()
    assert shape_mod.resolve_eigh_backend("auto", a) == "torch"
    w, _ = safe_eigh(a)
    torch.testing.assert_close(w, torch.linalg.eigvalsh(a))


def test_speed_sanity():
    """Not a benchmark: the batched solver must not be slower than LAPACK on a phase-sized batch."""
    import time

    a = random_symmetric(6000, torch.float32, seed=14)

    def best(fn) -> float:
        times = []
        for _ in range(5):
            t = time.perf_counter()
            fn(a)
            times.append(time.perf_counter() - t)
        return min(times)

    assert best(_cpp_eigh.eigh3) < best(torch.linalg.eigh)
    assert math.isfinite(best(_cpp_eigh.eigh3))


@pytest.mark.parametrize("dtype", DTYPES)
def test_symmetric_from_tril_is_exact_in_values_and_gradients(dtype):
    """The one-gather symmetric_from_tril against the scatter-and-mirror formula it replaced: bitwise."""
    g = torch.Generator().manual_seed(15)
    e = torch.randn(500, 6, generator=g, dtype=dtype).requires_grad_(True)
    rows, cols = torch.tensor([0, 1, 1, 2, 2, 2]), torch.tensor([0, 0, 1, 0, 1, 2])
    low = e.new_zeros(500, 3, 3).index_put((torch.arange(500)[:, None], rows[None], cols[None]), e)
    ref = low + low.transpose(1, 2) - torch.diag_embed(torch.diagonal(low, dim1=1, dim2=2))
    out = symmetric_from_tril(e)
    assert torch.equal(out, ref)
    w = torch.randn(500, 3, 3, generator=g, dtype=dtype)
    (g_out,) = torch.autograd.grad((out * w).sum(), e)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), e)
    assert torch.equal(g_out, g_ref)
