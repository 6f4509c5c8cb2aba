"""The native CPU hash encoding (``HashGrid(backend="cpp")``) against the pure-torch reference.

Values, first derivatives (x and table), second derivatives through a full ``SDFNetwork`` (a loss on
``autograd.grad(sdf.sum(), x, create_graph=True)`` back-propagated to the table, the MLP and x), and
``gradcheck``/``gradgradcheck`` in float64. Every test skips with the build's reason when the
extension cannot be built (a cached build loads in well under a second, a fresh one takes ~20 s).

Tolerances. Values: float64 within 1e-13, float32 within 1e-6 (the kernel follows the reference's
operation order; in practice they are bit-identical). Gradients: within 1e-10 (float64) or 2e-5
(float32) of the largest magnitude of each gradient, since the two sum in different orders.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import warnings

import pytest
import torch

from sage_core.fields import _cpp_hashgrid
from sage_core.fields.hashgrid import HashGrid, resolve_backend
from sage_core.fields.sdf import SDFNetwork

LO, HI = (-0.3, -0.2, -0.1), (0.3, 0.4, 0.5)


@pytest.fixture(scope="module")
def cpp_ext() -> None:
    ok, reason = _cpp_hashgrid.available()
    if not ok:
        pytest.skip(f"the C++ hash-grid extension cannot be built here: {reason}")


def make_grid(dtype: torch.dtype = torch.float32, seed: int = 0, **kw) -> HashGrid:
    """6 levels (3 dense, 3 hashed) with table values large enough to make comparisons meaningful."""
    args = dict(n_levels=6, n_features=2, log2_table=10, base_res=4, max_res=64)
    args.update(kw)
    torch.manual_seed(seed)
    g = HashGrid(LO, HI, **args).to(dtype)
    with torch.no_grad():
        g.table.uniform_(-1, 1)
    return g


def sample_points(n: int, dtype: torch.dtype, seed: int = 1) -> torch.Tensor:
    """Random points in a box 20 % larger than the grid's, plus corners, faces and outside points."""
    gen = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(LO, dtype=dtype), torch.tensor(HI, dtype=dtype)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    x = mid + half * 1.2 * (2 * torch.rand(n, 3, generator=gen, dtype=dtype) - 1)
    special = torch.stack([lo, hi, torch.stack([lo[0], mid[1], hi[2]]), torch.stack([hi[0], lo[1], mid[2]])])
    outside = torch.stack([lo - 0.5, hi + 0.5, torch.stack([lo[0] - 1, hi[1] + 1, hi[2] + 0.2])])
    face = mid.repeat(3, 1)
    face[0, 0], face[1, 1], face[2, 2] = hi[0], lo[1], hi[2]
    return torch.cat([x, special, outside, face])


def both(grid: HashGrid, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    with torch.no_grad():
        grid.backend = "torch"
        a = grid.level_features(x)
        grid.backend = "cpp"
        b = grid.level_features(x)
    return a, b


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))


def test_grid_has_dense_and_hashed_levels() -> None:
    g = make_grid()
    dense = [r**3 <= s for r, s in zip(g.level_resolutions, g.level_sizes)]
    assert any(dense) and not all(dense), dense


@pytest.mark.parametrize("dtype,atol", [(torch.float64, 1e-13), (torch.float32, 1e-6)])
@pytest.mark.parametrize("active", [6, 4])
def test_values_match_reference(cpp_ext: None, dtype: torch.dtype, atol: float, active: int) -> None:
    g = make_grid(dtype)
    g.set_active_levels(active)
    x = sample_points(400, dtype)
    a, b = both(g, x)
    assert b.shape == (x.shape[0], 6, 2) and b.dtype == dtype
    assert float((a - b).abs().max()) <= atol
    assert torch.all(b[:, active:] == 0)
    assert float(b[:, :active].abs().max()) > 0.1


def test_nan_points_give_nan_features_and_stay_in_the_table(cpp_ext: None) -> None:
    g = make_grid(torch.float32)
    x = sample_points(20, torch.float32)
    x[3, 1] = float("nan")
    x[7] = float("nan")
    a, b = both(g, x)
    ok = torch.ones(x.shape[0], dtype=torch.bool)
    ok[[3, 7]] = False
    assert torch.isnan(b[~ok]).all() and torch.isnan(a[~ok]).all()
    assert torch.equal(a[ok], b[ok])


def test_float32_table_with_float64_points(cpp_ext: None) -> None:
    g = make_grid(torch.float32)
    x = sample_points(100, torch.float64)
    a, b = both(g, x)
    assert b.dtype == torch.float64 and float((a - b).abs().max()) <= 1e-13


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-10), (torch.float32, 2e-5)])
@pytest.mark.parametrize("active", [6, 3])
@pytest.mark.parametrize("features", [2, 3])
def test_first_gradients_match_reference(
    cpp_ext: None, dtype: torch.dtype, rtol: float, active: int, features: int
) -> None:
    """The gradients of x and the table, and of the table alone (x without a gradient: the kernel's
    table-only pass), for a compiled (2) and a run-time (3) feature count."""
    g = make_grid(dtype, n_features=features)
    g.set_active_levels(active)
    x0 = sample_points(600, dtype)
    upstream = torch.randn(x0.shape[0], 6, features, generator=torch.Generator().manual_seed(5), dtype=dtype)
    grads = {}
    for backend in ("torch", "cpp"):
        g.backend = backend
        g.table.grad = None
        x = x0.clone().requires_grad_(True)
        (g.level_features(x) * upstream).sum().backward()
        (table_alone,) = torch.autograd.grad((g.level_features(x0) * upstream).sum(), g.table)
        grads[backend] = (x.grad, g.table.grad.clone(), table_alone)
    (gx_ref, gt_ref, ta_ref), (gx, gt, ta) = grads["torch"], grads["cpp"]
    assert rel_err(gx, gx_ref) <= rtol and rel_err(gt, gt_ref) <= rtol
    assert torch.equal(ta, gt) and rel_err(ta, ta_ref) <= rtol
    n_special = 10  # the last points of sample_points: 3 outside, then 3 on faces; outside -> no gradient
    assert torch.all(gx[-6:-3] == 0) and float(gx[:-n_special].abs().max()) > 0
    masked_rows = sum(g.level_sizes[:active])
    assert torch.all(gt[masked_rows:] == 0) and float(gt[:masked_rows].abs().max()) > 0


def sdf_pair(dtype: torch.dtype) -> tuple[SDFNetwork, SDFNetwork]:
    """Two identical SDF networks (the tiny preset's grid shape) with random encoding weights."""
    torch.manual_seed(3)
    net = SDFNetwork(LO, HI, n_levels=8, n_features=2, log2_table=14, base_res=16, max_res=256, hidden=32)
    with torch.no_grad():
        net.encoding.table.uniform_(-0.05, 0.05)
        net.layers[0].weight[:, 3:].normal_(0.0, 0.5)  # geometric init zeroes these
    net = net.to(dtype)
    other = SDFNetwork(LO, HI, n_levels=8, n_features=2, log2_table=14, base_res=16, max_res=256, hidden=32).to(dtype)
    other.load_state_dict(net.state_dict())
    net.encoding.backend, other.encoding.backend = "torch", "cpp"
    return net, other


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
@pytest.mark.parametrize("active", [8, 5])
def test_second_order_through_sdf_network(cpp_ext: None, dtype: torch.dtype, rtol: float, active: int) -> None:
    """Eikonal + alignment-style loss on the create_graph gradient: grads of table, MLP and x."""
    nets = sdf_pair(dtype)
    x0 = sample_points(300, dtype, seed=7)
    target = torch.randn(x0.shape[0], 3, generator=torch.Generator().manual_seed(2))
    target = torch.nn.functional.normalize(target, dim=-1).to(dtype)
    results = []
    for net in nets:
        net.encoding.set_active_levels(active)
        x = x0.clone().requires_grad_(True)
        sdf, feat = net(x)
        (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=True)
        eik = ((grad.norm(dim=-1) - 1) ** 2).mean()
        align = (1 - torch.nn.functional.cosine_similarity(grad, target, dim=-1)).mean()
        loss = eik + align + sdf.abs().mean() + 0.1 * feat.square().mean()
        params = [net.encoding.table, *net.mlp_parameters()]
        grads = torch.autograd.grad(loss, [x, *params])
        results.append((loss.detach(), grads))
    (l_ref, g_ref), (l_cpp, g_cpp) = results
    assert abs(float(l_ref - l_cpp)) <= rtol * abs(float(l_ref))
    names = ["x", "table"] + [f"mlp{i}" for i in range(len(g_ref) - 2)]
    for name, a, b in zip(names, g_cpp, g_ref):
        assert rel_err(a, b) <= rtol, (name, rel_err(a, b))
    assert float(g_cpp[1].abs().max()) > 0
    # the second-order part alone (the eikonal term) reaches the table: check it separately
    for net in nets:
        net.encoding.table.grad = None
    eiks = []
    for net in nets:
        x = x0.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(net.sdf(x).sum(), x, create_graph=True)
        ((grad.norm(dim=-1) - 1) ** 2).mean().backward()
        eiks.append(net.encoding.table.grad.clone())
    assert float(eiks[1].abs().max()) > 0 and rel_err(eiks[1], eiks[0]) <= rtol


def tiny_grid() -> HashGrid:
    """3 levels (res 3, 6, 9): the first dense, the others hashed into 64 entries; the last masked."""
    g = make_grid(torch.float64, n_levels=3, log2_table=6, base_res=3, max_res=9)
    g.level_mask[2] = 0.0
    g.backend = "cpp"
    return g


def test_gradcheck_and_gradgradcheck(cpp_ext: None) -> None:
    g = tiny_grid()
    assert g.level_resolutions[0] ** 3 <= g.level_sizes[0] and g.level_resolutions[1] ** 3 > g.level_sizes[1] == 64
    # points inside the box, away from cell borders (finite differences must not cross a kink)
    x = torch.tensor(
        [[-0.21, 0.013, 0.07], [0.12, 0.31, 0.42], [0.27, -0.13, -0.03], [0.0371, 0.1172, 0.2263]],
        dtype=torch.float64,
    )
    table = g.table.detach().clone()

    def fn(xx: torch.Tensor, tt: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(g, {"table": tt}, (xx,))

    inputs = (x.clone().requires_grad_(True), table.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7)
    assert torch.autograd.gradgradcheck(fn, inputs, eps=1e-6, atol=1e-7)
    x_only = (x.clone().requires_grad_(True),)
    assert torch.autograd.gradgradcheck(lambda xx: fn(xx, table), x_only, eps=1e-6, atol=1e-7)


def test_results_are_independent_of_the_thread_count(cpp_ext: None) -> None:
    """Values, first and second-order gradients are bit-identical with 1 and 2 threads."""
    g = make_grid(torch.float32)
    x = sample_points(3000, torch.float32)
    up = torch.randn(x.shape[0], 6, 2, generator=torch.Generator().manual_seed(4))
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            xr = x.clone().requires_grad_(True)
            g.table.grad = None
            feats = g.level_features(xr)
            (gx,) = torch.autograd.grad((feats.square() * up).sum(), xr, create_graph=True)
            (gx.square().sum() + (feats * up).sum()).backward()
            out.append((feats.detach(), gx.detach(), xr.grad, g.table.grad.clone()))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*out):
        assert torch.equal(a, b)
    assert float(out[0][3].abs().max()) > 0 and float(out[0][2].abs().max()) > 0


def test_third_derivative_is_refused(cpp_ext: None) -> None:
    g = tiny_grid()
    x = torch.tensor([[0.01, 0.02, 0.03]], dtype=torch.float64, requires_grad=True)
    (gx,) = torch.autograd.grad(g(x).square().sum(), x, create_graph=True)
    (gxx,) = torch.autograd.grad(gx.square().sum(), x, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        gxx.sum().backward()


def test_backend_selection(cpp_ext: None) -> None:
    assert resolve_backend("auto", "cpu") == "cpp"
    assert resolve_backend("cpp", torch.device("cpu")) == "cpp"
    assert resolve_backend("torch", "cpu") == "torch"
    assert resolve_backend("cpp", "cuda") == "torch" and resolve_backend("auto", "cuda") == "torch"
    with pytest.raises(ValueError, match="unknown backend"):
        resolve_backend("fast", "cpu")
    with pytest.raises(ValueError, match="unknown backend"):
        HashGrid(LO, HI, backend="fast")
    g = make_grid()
    assert g.backend == "auto" and "backend" not in str(list(g.state_dict()))
    x = sample_points(50, torch.float32)
    g.backend = "auto"
    a = g(x)
    g.backend = "cpp"
    assert torch.equal(a, g(x))


def test_unavailable_extension_errors_for_cpp_and_warns_once_for_auto(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_cpp_hashgrid.EXT, "state", {"ok": False, "reason": "no C++ compiler ('c++') on PATH"})
    monkeypatch.setattr(_cpp_hashgrid.EXT, "warned", False)
    with pytest.raises(ValueError, match="backend='cpp' is unavailable: no C\\+\\+ compiler"):
        resolve_backend("cpp", "cpu")
    g = make_grid()
    x = sample_points(30, torch.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = g(x)
        g(x)
    g.backend = "torch"
    assert torch.equal(out, g(x))
    msgs = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(msgs) == 1 and "native CPU hash-grid encoding is unavailable" in msgs[0], msgs


def test_building_a_grid_compiles_nothing() -> None:
    code = textwrap.dedent(
        """
        import torch
        from sage_core.fields import HashGrid, SDFNetwork, _cpp_hashgrid
        HashGrid([0, 0, 0], [1, 1, 1], n_levels=2, log2_table=8, base_res=2, max_res=4)
        SDFNetwork([0, 0, 0], [1, 1, 1], n_levels=2, log2_table=8, base_res=2, max_res=4, hidden=8)
        assert _cpp_hashgrid.EXT.state == {}, _cpp_hashgrid.EXT.state
        assert not hasattr(torch.ops.sage_hashgrid_cpu, "forward")
        print("lazy")
        """
    )
    env = dict(os.environ, SAGE_CACHE_DIR="/nonexistent-sage-cache")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "lazy", proc.stderr[-2000:]
