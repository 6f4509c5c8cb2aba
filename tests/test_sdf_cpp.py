"""The fused native SDF network (``SDFNetwork(backend="cpp")``) against the autograd reference.

The reference is ``backend="torch"`` with the pure-torch hash encoding. Compared: sdf, gradient and
feature values, and the gradients of x, the hash table and every MLP weight and bias through losses of
the training kind (eikonal on the gradient, |sdf|, 1 - |n . t|, a loss on the feature), the
second-order terms included; ``gradcheck`` in float64; masked levels, points outside the box, NaN
points, N = 0 and N = 1; bit-identical results for 1 and 2 threads and for the AVX2 and portable
builds; the backend choice and the fallback without a compiler. Tests that need the extension skip
with the build's reason when it cannot be built (a fresh build takes about a minute).

Tolerances, relative to the largest magnitude of each compared tensor: float64 within 1e-10 (values
and gradients agree to ~1e-15 in practice); float32 values within 2e-6 and gradients within 1e-4 (the
kernel sums in other orders than MKL and uses its own exp/log approximations, within 2 ulp).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import warnings

import pytest
import torch

from sage_core.fields import _cpp_sdf
from sage_core.fields.sdf import SDFNetwork

LO, HI = (-0.3, -0.2, -0.1), (0.3, 0.4, 0.5)
NET = dict(n_levels=6, n_features=2, log2_table=10, base_res=4, max_res=64, hidden=32, feature_dim=5)
TOL = {torch.float64: (1e-10, 1e-10), torch.float32: (2e-6, 1e-4)}  # (values, gradients)


@pytest.fixture(scope="module")
def cpp_ext() -> None:
    ok, reason = _cpp_sdf.available()
    if not ok:
        pytest.skip(f"the C++ SDF extension cannot be built here: {reason}")


def make_pair(dtype: torch.dtype = torch.float64, seed: int = 0, **kw) -> tuple[SDFNetwork, SDFNetwork]:
    """(reference, fused): the same weights, a random table and encoding weights (both zero at init)."""
    args = dict(NET, **kw)
    torch.manual_seed(seed)
    ref = SDFNetwork(LO, HI, backend="torch", **args)
    with torch.no_grad():
        ref.encoding.table.uniform_(-0.3, 0.3)
        ref.layers[0].weight[:, 3:].normal_(0.0, 0.5)
        ref.layers[0].bias.normal_(0.0, 0.3)
        ref.layers[-1].bias.normal_(0.0, 0.1)
    ref = ref.to(dtype)
    ref.encoding.backend = "torch"
    fused = SDFNetwork(LO, HI, backend="cpp", **args).to(dtype)
    fused.load_state_dict(ref.state_dict())
    return ref, fused


def sample_points(n: int, dtype: torch.dtype, seed: int = 1) -> torch.Tensor:
    """Random points in a box 20 % larger than the grid's, then corners, 3 far outside, 3 on faces."""
    gen = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(LO, dtype=dtype), torch.tensor(HI, dtype=dtype)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    x = mid + half * 1.2 * (2 * torch.rand(n, 3, generator=gen, dtype=dtype) - 1)
    special = torch.stack([lo, hi, torch.stack([lo[0], mid[1], hi[2]]), torch.stack([hi[0], lo[1], mid[2]])])
    outside = torch.stack([lo - 0.5, hi + 0.5, torch.stack([lo[0] - 1, hi[1] + 1, hi[2] + 0.2])])
    face = mid.repeat(3, 1)
    face[0, 0], face[1, 1], face[2, 2] = hi[0], lo[1], hi[2]
    return torch.cat([x, special, outside, face])


def unit_targets(n: int, dtype: torch.dtype, seed: int = 2) -> torch.Tensor:
    t = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    return torch.nn.functional.normalize(t, dim=-1)


def training_loss(sdf: torch.Tensor, grad: torch.Tensor, feat: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Eikonal + |sdf| + normal alignment 1 - |n . t| + feature terms (one couples feature and sdf)."""
    norm = grad.norm(dim=-1)
    normal = grad / norm[:, None].clamp_min(1e-12)
    eik = ((norm - 1) ** 2).mean()
    align = (1 - (normal * target).sum(-1).abs()).mean()
    return eik + sdf.abs().mean() + align + 0.3 * feat.square().mean() + (feat[:, 0] * sdf).mean()


def params_of(net: SDFNetwork) -> list[torch.Tensor]:
    return [net.encoding.table, *net.mlp_parameters()]


NAMES = ["x", "table", "w0", "b0", "w1", "b1"]


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))


def run_loss(net: SDFNetwork, x0: torch.Tensor, loss_fn) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Values (sdf, grad, feature) and the gradients of loss_fn(sdf, grad, feat) for x and the parameters."""
    x = x0.clone().requires_grad_(True)
    sdf, grad, feat = net.gradient(x, create_graph=True)
    grads = torch.autograd.grad(loss_fn(sdf, grad, feat), [x, *params_of(net)], allow_unused=True)
    grads = [torch.zeros_like(p) if g is None else g for g, p in zip(grads, [x, *params_of(net)])]
    return [sdf.detach(), grad.detach(), feat.detach()], grads


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("active", [6, 4])
def test_values_and_gradients_match_reference(cpp_ext: None, dtype: torch.dtype, active: int) -> None:
    ref, fused = make_pair(dtype)
    for net in (ref, fused):
        net.encoding.set_active_levels(active)
    x0 = sample_points(500, dtype)
    target = unit_targets(x0.shape[0], dtype)
    vals_r, grads_r = run_loss(ref, x0, lambda s, g, f: training_loss(s, g, f, target))
    vals_f, grads_f = run_loss(fused, x0, lambda s, g, f: training_loss(s, g, f, target))
    vtol, gtol = TOL[dtype]
    for name, a, b in zip(["sdf", "grad", "feature"], vals_f, vals_r):
        assert a.dtype == dtype and a.shape == b.shape and rel_err(a, b) <= vtol, (name, rel_err(a, b))
    for name, a, b in zip(NAMES, grads_f, grads_r):
        assert float(b.abs().max()) > 0, name
        assert rel_err(a, b) <= gtol, (name, rel_err(a, b))
    # inactive levels: no table gradient at all
    active_rows = sum(fused.encoding.level_sizes[:active])
    assert torch.all(grads_f[1][active_rows:] == 0) and torch.all(grads_r[1][active_rows:] == 0)


@pytest.mark.parametrize("output", ["sdf", "grad", "feature"])
def test_each_output_alone(cpp_ext: None, output: str) -> None:
    """A random linear loss on one output at a time, so no term can hide another (float64)."""
    ref, fused = make_pair(torch.float64, seed=4)
    x0 = sample_points(300, torch.float64, seed=5)
    gen = torch.Generator().manual_seed(6)
    up = {"sdf": torch.randn(x0.shape[0], generator=gen, dtype=torch.float64),
          "grad": torch.randn(x0.shape[0], 3, generator=gen, dtype=torch.float64),
          "feature": torch.randn(x0.shape[0], NET["feature_dim"], generator=gen, dtype=torch.float64)}  # fmt: skip
    index = {"sdf": 0, "grad": 1, "feature": 2}[output]

    def loss(*outs: torch.Tensor) -> torch.Tensor:
        return (outs[index] * up[output]).sum()

    _, grads_r = run_loss(ref, x0, loss)
    _, grads_f = run_loss(fused, x0, loss)
    for name, a, b in zip(NAMES, grads_f, grads_r):
        assert rel_err(a, b) <= 1e-10, (output, name, rel_err(a, b))
    assert float(grads_f[0].abs().max()) > 0 and float(grads_f[1].abs().max()) > 0


def tiny_pair() -> tuple[SDFNetwork, SDFNetwork]:
    """3 levels (res 3, 6, 9; the first dense, the others hashed into 64 rows), hidden 8, float64."""
    return make_pair(torch.float64, seed=7, n_levels=3, log2_table=6, base_res=3, max_res=9, hidden=8, feature_dim=2)


def test_gradcheck(cpp_ext: None) -> None:
    _, fused = tiny_pair()
    assert fused.encoding.level_resolutions[1] ** 3 > fused.encoding.level_sizes[1] == 64
    fused.encoding.level_mask[2] = 0.0  # a masked level too
    layout = fused.fused_layout(torch.float64)
    # points away from cell borders (finite differences must not cross a kink), one outside the box
    x = torch.tensor([[-0.21, 0.013, 0.07], [0.12, 0.31, 0.42], [0.27, -0.13, -0.03], [0.0371, 0.1172, 0.2263],
                      [0.5, 0.1, 0.2]], dtype=torch.float64)  # fmt: skip
    inputs = [x, *[p.detach().clone() for p in params_of(fused)]]

    def fn(*args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return _cpp_sdf.evaluate(*args, layout=layout, with_grad=True, with_encoding=True)

    inputs = [t.requires_grad_(True) for t in inputs]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_third_derivative_is_refused(cpp_ext: None) -> None:
    _, fused = tiny_pair()
    x = torch.tensor([[0.01, 0.02, 0.03]], dtype=torch.float64, requires_grad=True)
    _, grad, _ = fused.gradient(x, create_graph=True)
    (gx,) = torch.autograd.grad(grad.square().sum(), x, create_graph=True)
    with pytest.raises(RuntimeError, match="once_differentiable"):
        gx.sum().backward()


def test_nan_points_stay_in_their_rows(cpp_ext: None) -> None:
    """NaN rows give NaN values as in the reference; the other rows are exactly those computed without them."""
    ref, fused = make_pair(torch.float32)
    x = sample_points(40, torch.float32)
    x[3, 1] = float("nan")
    x[17] = float("nan")
    ok = ~torch.isnan(x).any(-1)
    with torch.no_grad():
        outs_f = fused.gradient(x)
        outs_r = ref.gradient(x)
        clean = fused.gradient(x[ok])
    for a, b, c in zip(outs_f, outs_r, clean):
        rows = a.reshape(a.shape[0], -1)
        assert torch.isnan(rows[~ok]).all() and torch.isnan(b.reshape(b.shape[0], -1)[~ok]).all()
        assert torch.equal(a[ok], c)


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single_point(cpp_ext: None, n: int) -> None:
    ref, fused = make_pair(torch.float64)
    x0 = sample_points(5, torch.float64)[:n]
    target = unit_targets(max(n, 1), torch.float64)[:n]

    def loss(s: torch.Tensor, g: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        return training_loss(s, g, f, target) if n else s.sum() + g.sum() + f.sum()

    vals_r, grads_r = run_loss(ref, x0, loss)
    vals_f, grads_f = run_loss(fused, x0, loss)
    for a, b in zip(vals_f + grads_f, vals_r + grads_r):
        assert a.shape == b.shape
        if a.numel():
            assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)
    if n:
        assert float(grads_f[2].abs().max()) > 0


def test_results_are_independent_of_the_thread_count(cpp_ext: None) -> None:
    """Values and every gradient bit-identical with 1 and 2 threads (several chunks and levels in parallel)."""
    _, fused = make_pair(torch.float32)
    x0 = sample_points(3000, torch.float32)
    target = unit_targets(x0.shape[0], torch.float32)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            vals, grads = run_loss(fused, x0, lambda s, g, f: training_loss(s, g, f, target))
            out.append(vals + grads)
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*out):
        assert torch.equal(a, b)
    assert float(out[0][4].abs().max()) > 0


def test_avx2_and_portable_builds_agree(cpp_ext: None) -> None:
    ops = torch.ops.sage_sdf_cpu
    if not bool(ops.avx2()):
        pytest.skip("no AVX2 build on this CPU")
    _, fused = make_pair(torch.float32)
    x0 = sample_points(700, torch.float32)
    target = unit_targets(x0.shape[0], torch.float32)
    out = []
    try:
        for portable in (False, True):
            ops.force_portable(portable)
            assert bool(ops.avx2()) != portable
            vals, grads = run_loss(fused, x0, lambda s, g, f: training_loss(s, g, f, target))
            out.append(vals + grads)
    finally:
        ops.force_portable(False)
    for a, b in zip(*out):
        assert torch.equal(a, b)


def test_plain_forward_and_detached_gradient(cpp_ext: None) -> None:
    """forward()/sdf() and gradient(create_graph=False): values, and the parameters' gradients through
    sdf and feature (the gradient itself detached)."""
    ref, fused = make_pair(torch.float64)
    x0 = sample_points(200, torch.float64)
    with torch.no_grad():
        for a, b in zip(fused(x0), ref(x0)):
            assert rel_err(a, b) <= 1e-12
    results = []
    for net in (ref, fused):
        sdf, feat = net(x0)
        g1 = torch.autograd.grad((sdf.square() + feat.sum(-1)).sum(), params_of(net))
        s2, grad, f2 = net.gradient(x0.clone().requires_grad_(True), create_graph=False)
        assert not grad.requires_grad and s2.grad_fn is not None and f2.grad_fn is not None
        g2 = torch.autograd.grad((s2 * f2[:, 1]).sum(), params_of(net))
        results.append((grad, g1 + g2))
    (grad_r, g_r), (grad_f, g_f) = results
    assert rel_err(grad_f, grad_r) <= 1e-10
    for a, b in zip(g_f, g_r):
        assert float(b.abs().max()) > 0 and rel_err(a, b) <= 1e-10
    assert type(fused(x0)[0].grad_fn).__name__ == "_SDFEvalBackward"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_sdf_alone_is_the_forward_sdf(cpp_ext: None, dtype: torch.dtype) -> None:
    """sdf() runs the kernel without the feature rows of the last layer: the values of forward()[0] and
    the parameters' gradients through them, bit for bit, in the portable and (where the CPU has it) the
    AVX2 build."""
    _, fused = make_pair(dtype)
    x0 = sample_points(300, dtype)
    ops = torch.ops.sage_sdf_cpu
    try:
        for portable in (False, True):
            ops.force_portable(portable)
            with torch.no_grad():
                assert torch.equal(fused.sdf(x0), fused(x0)[0])
            grads = [torch.autograd.grad(s.square().sum(), params_of(fused), allow_unused=True)
                     for s in (fused.sdf(x0), fused(x0)[0])]  # fmt: skip
            for a, b in zip(*grads):
                assert (a is None and b is None) or torch.equal(a, b)
    finally:
        ops.force_portable(False)


def test_forward_with_a_differentiable_x_stays_twice_differentiable(cpp_ext: None) -> None:
    """forward() on an x that requires a gradient runs the torch path, so autograd.grad(..., create_graph)
    followed by a loss on that gradient still works (the pattern of external callers)."""
    ref, fused = make_pair(torch.float64)
    x0 = sample_points(100, torch.float64)
    outs = []
    for net in (ref, fused):
        x = x0.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(net.sdf(x).sum(), x, create_graph=True)
        outs.append(torch.autograd.grad(((g.norm(dim=-1) - 1) ** 2).sum(), net.encoding.table)[0])
    assert rel_err(outs[1], outs[0]) <= 1e-10 and float(outs[0].abs().max()) > 0


@pytest.mark.parametrize("create_graph", [True, False])
def test_gradient_with_encoding(cpp_ext: None, create_graph: bool) -> None:
    """The shared-encoding variant: values, and gradients through all four outputs (create_graph) or through
    the encoding alone (sdf, grad and feature detached)."""
    ref, fused = make_pair(torch.float64)
    x0 = sample_points(200, torch.float64)
    target = unit_targets(x0.shape[0], torch.float64)
    w = torch.randn(x0.shape[0], 12, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    results = []
    for net in (ref, fused):
        x = x0.clone().requires_grad_(True)
        sdf, grad, feat, enc = net.gradient_with_encoding(x, create_graph=create_graph)
        assert enc.shape == (x0.shape[0], 12)
        loss = (enc * w).sum()
        if create_graph:
            loss = loss + training_loss(sdf, grad, feat, target)
        else:
            assert not (sdf.requires_grad or grad.requires_grad or feat.requires_grad)
        grads = torch.autograd.grad(loss, [x, *params_of(net)], allow_unused=True)
        results.append(([sdf, grad, feat, enc], grads))
    (vals_r, grads_r), (vals_f, grads_f) = results
    for a, b in zip(vals_f, vals_r):
        assert rel_err(a.detach(), b.detach()) <= 1e-10
    for name, a, b in zip(NAMES, grads_f, grads_r):
        assert (a is None) == (b is None), name
        if b is not None:
            assert rel_err(a, b) <= 1e-10, (name, rel_err(a, b))
    assert grads_f[1] is not None and float(grads_f[1].abs().max()) > 0
    if not create_graph:
        assert all(g is None for g in grads_f[2:])  # the encoding does not reach the MLP


def test_backend_selection(cpp_ext: None) -> None:
    _, fused = make_pair(torch.float32)
    x = sample_points(20, torch.float32)
    assert SDFNetwork(LO, HI, **NET).backend == "auto" and "backend" not in str(list(fused.state_dict()))
    fused.backend = "auto"
    assert fused.resolve_backend(x) == "cpp"
    assert type(fused.gradient(x, create_graph=True)[1].grad_fn).__name__ == "_SDFEvalBackward"
    assert fused.resolve_backend(x.double()) == "torch"  # mixed dtypes: the reference (which then raises)
    assert fused.resolve_backend(torch.empty(4, 3, device="meta")) == "torch"  # other devices
    fused.backend = "torch"
    assert fused.resolve_backend(x) == "torch"
    with pytest.raises(ValueError, match="unknown backend"):
        SDFNetwork(LO, HI, backend="fast", **NET)
    deep = SDFNetwork(LO, HI, n_hidden_layers=2, **NET)
    assert deep.resolve_backend(x) == "torch"
    deep.backend = "cpp"
    with pytest.raises(ValueError, match="2 hidden layers"):
        deep.gradient(x)


def test_unavailable_extension_errors_for_cpp_and_warns_once_for_auto(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_cpp_sdf.EXT, "state", {"ok": False, "reason": "no C++ compiler ('c++') on PATH"})
    monkeypatch.setattr(_cpp_sdf.EXT, "warned", False)
    ref, auto = make_pair(torch.float64)
    auto.backend = "auto"
    x = sample_points(30, torch.float64)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        a = auto.gradient(x)
        auto.gradient(x)
    msgs = [str(w.message) for w in caught if "SDF network" in str(w.message)]
    assert len(msgs) == 1 and "native CPU SDF network is unavailable" in msgs[0], msgs
    for u, v in zip(a, ref.gradient(x)):
        assert rel_err(u, v) <= 1e-10
    auto.backend = "cpp"
    with pytest.raises(ValueError, match="backend='cpp' is unavailable: no C\\+\\+ compiler"):
        auto.gradient(x)


def test_building_a_network_compiles_nothing() -> None:
    code = textwrap.dedent(
        """
        import torch
        from sage_core.fields import SDFNetwork, _cpp_sdf
        SDFNetwork([0, 0, 0], [1, 1, 1], n_levels=2, log2_table=8, base_res=2, max_res=4, hidden=8, backend="cpp")
        assert _cpp_sdf.EXT.state == {}, _cpp_sdf.EXT.state
        assert not hasattr(torch.ops.sage_sdf_cpu, "forward")
        print("lazy")
        """
    )
    env = dict(os.environ, SAGE_CACHE_DIR="/nonexistent-sage-cache")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "lazy", proc.stderr[-2000:]
