"""Binding maths (local ↔ world), nearest-triangle queries and the SurfelSet (posing, rebinding,
state dicts, pruning with optimizer state)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from sage_core.avatar.binding import (
    local_to_world,
    nearest_triangles,
    point_triangle_distance,
    world_to_local,
)
from sage_core.avatar.init import REGION_HAIR, face_region_labels, init_surfels
from sage_core.avatar.surfels import SurfelSet
from sage_core.flame import Regions, surfel_frames
from sage_core.geometry.rotations import axis_angle_to_matrix, quat_to_matrix

DT = torch.float64


def _sphere(subdiv: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return torch.tensor(m.vertices, dtype=DT), torch.tensor(m.faces, dtype=torch.long)


def _bumpy_sphere(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    V, F = _sphere(2)
    g = torch.Generator().manual_seed(seed)
    V = V * (1.0 + 0.15 * torch.rand(V.shape[0], 1, generator=g, dtype=DT))
    return V, F


def _fake_regions(V: torch.Tensor, F: torch.Tensor) -> Regions:
    v = V.numpy()
    masks = {
        "face": np.nonzero(v[:, 2] > 0.2)[0],
        "scalp": np.nonzero(v[:, 1] > 0.3)[0],
        "neck": np.nonzero(v[:, 1] < -0.8)[0],
    }
    return Regions(masks, F.numpy(), V.shape[0])


def _random_local(N: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    mu = torch.randn(N, 3, generator=g, dtype=DT) * 0.5
    q = torch.randn(N, 4, generator=g, dtype=DT) * 2.0
    s = torch.randn(N, 2, generator=g, dtype=DT) * 0.3 - 1.0
    return mu, q, s


def _surfel_set(seed: int = 0, n: int = 600, **kw) -> tuple[SurfelSet, torch.Tensor, torch.Tensor]:
    V, F = _bumpy_sphere(seed)
    init = init_surfels(V, F, n, _fake_regions(V, F), generator=torch.Generator().manual_seed(seed), dtype=DT)
    return SurfelSet.from_init(init, **kw), V, F


# ---------------------------------------------------------------------------- local ↔ world


def test_local_world_round_trip():
    V, F = _bumpy_sphere()
    R, T, k = surfel_frames(V, F)
    g = torch.Generator().manual_seed(1)
    N = 500
    binding = torch.randint(0, F.shape[0], (N,), generator=g)
    mu, q, s = _random_local(N, g)
    means, quats, scales = local_to_world(mu, q, s, binding, R, T, k)
    assert torch.allclose(quats.norm(dim=-1), torch.ones(N, dtype=DT))
    mu2, q2, s2 = world_to_local(means, quats, scales, binding, R, T, k)
    assert torch.allclose(mu2, mu, atol=1e-12)
    assert torch.allclose(s2, s, atol=1e-12)
    qn = q / q.norm(dim=-1, keepdim=True)
    assert torch.allclose(quat_to_matrix(q2), quat_to_matrix(qn), atol=1e-12)
    # and world -> local -> world
    means3, quats3, scales3 = local_to_world(mu2, q2, s2, binding, R, T, k)
    assert torch.allclose(means3, means, atol=1e-12)
    assert torch.allclose(scales3, scales, atol=1e-12)
    assert torch.allclose(quat_to_matrix(quats3), quat_to_matrix(quats), atol=1e-12)


def test_local_to_world_matches_formula():
    V, F = _bumpy_sphere()
    R, T, k = surfel_frames(V, F)
    g = torch.Generator().manual_seed(2)
    binding = torch.randint(0, F.shape[0], (50,), generator=g)
    mu, q, s = _random_local(50, g)
    means, quats, scales = local_to_world(mu, q, s, binding, R, T, k)
    for i in range(0, 50, 7):
        b = binding[i]
        assert torch.allclose(means[i], k[b] * R[b] @ mu[i] + T[b], atol=1e-12)
        assert torch.allclose(scales[i], k[b] * torch.exp(s[i]), atol=1e-12)
        assert torch.allclose(quat_to_matrix(quats[i]), R[b] @ quat_to_matrix(q[i]), atol=1e-12)


def test_identity_rotation_lies_flat_on_triangle():
    V, F = _bumpy_sphere()
    R, T, k = surfel_frames(V, F)
    N = F.shape[0]
    binding = torch.arange(N)
    g = torch.Generator().manual_seed(3)
    mu = torch.randn(N, 3, generator=g, dtype=DT) * 0.2
    mu[:, 2] = 0.0
    q = torch.zeros(N, 4, dtype=DT)
    q[:, 0] = 1.0
    means, quats, _ = local_to_world(mu, q, torch.zeros(N, 2, dtype=DT), binding, R, T, k)
    tri = V[F]
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    rot = quat_to_matrix(quats)
    assert torch.allclose(rot[:, :, 2], n, atol=1e-12)  # surfel normal = face normal (outward)
    assert (n * tri.mean(1)).sum(-1).min() > 0  # sanity: the icosphere's winding is outward
    # the surfel's centre and both tangent axes lie in the triangle's plane
    assert ((means - tri[:, 0]) * n).sum(-1).abs().max() < 1e-12
    assert (rot[:, :, :2] * n[:, :, None]).sum(1).abs().max() < 1e-12


def test_rigid_and_similarity_motion():
    V, F = _bumpy_sphere()
    g = torch.Generator().manual_seed(4)
    N = 300
    binding = torch.randint(0, F.shape[0], (N,), generator=g)
    mu, q, s = _random_local(N, g)
    Rot = axis_angle_to_matrix(torch.tensor([0.3, -1.1, 0.7], dtype=DT))
    t = torch.tensor([0.2, -0.5, 1.5], dtype=DT)
    for c in (1.0, 1.7):
        V2 = c * V @ Rot.T + t
        m1, q1, s1 = local_to_world(mu, q, s, binding, *surfel_frames(V, F))
        m2, q2, s2 = local_to_world(mu, q, s, binding, *surfel_frames(V2, F))
        assert torch.allclose(m2, c * m1 @ Rot.T + t, atol=1e-12)
        assert torch.allclose(quat_to_matrix(q2), Rot @ quat_to_matrix(q1), atol=1e-12)
        assert torch.allclose(s2, c * s1, atol=1e-12)


def test_batched_pose_equals_single_frames():
    V, F = _bumpy_sphere()
    g = torch.Generator().manual_seed(5)
    N = 100
    binding = torch.randint(0, F.shape[0], (N,), generator=g)
    mu, q, s = _random_local(N, g)
    V2 = V + 0.05 * torch.randn(V.shape, generator=g, dtype=DT)
    R, T, k = surfel_frames(torch.stack([V, V2]), F)
    mb, qb, sb = local_to_world(mu, q, s, binding, R, T, k)
    assert mb.shape == (2, N, 3) and qb.shape == (2, N, 4) and sb.shape == (2, N, 2)
    for i, Vi in enumerate((V, V2)):
        m, qq, ss = local_to_world(mu, q, s, binding, *surfel_frames(Vi, F))
        assert torch.allclose(mb[i], m, atol=1e-14)
        assert torch.allclose(qb[i], qq, atol=1e-14)
        assert torch.allclose(sb[i], ss, atol=1e-14)


def test_local_to_world_gradients():
    V, F = _bumpy_sphere()
    g = torch.Generator().manual_seed(6)
    N = 6
    binding = torch.randint(0, F.shape[0], (N,), generator=g)
    mu, q, s = _random_local(N, g)
    used = torch.unique(F[binding])
    base = V.clone()

    def fn(mu_, q_, s_, vsub):
        Vx = base.index_put((used,), vsub)
        m, qq, ss = local_to_world(mu_, q_, s_, binding, *surfel_frames(Vx, F))
        # q and −q are the same rotation: compare through the rotation matrix
        return m, quat_to_matrix(qq), ss

    inputs = tuple(x.clone().requires_grad_(True) for x in (mu, q, s, V[used]))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6)


# ---------------------------------------------------------------------------- distances


def _brute_sq_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, n_samples: int = 200) -> float:
    """Approximate squared distance by dense barycentric sampling (upper bound, test-only)."""
    u, v = np.meshgrid(np.linspace(0, 1, n_samples), np.linspace(0, 1, n_samples))
    m = u + v <= 1
    pts = a + u[m, None] * (b - a) + v[m, None] * (c - a)
    return float(((pts - p) ** 2).sum(-1).min())


def test_point_triangle_distance_cases():
    a = torch.tensor([0.0, 0.0, 0.0], dtype=DT)
    b = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    c = torch.tensor([0.0, 1.0, 0.0], dtype=DT)
    cases = {
        (0.2, 0.2, 0.5): 0.5,  # above the interior
        (-1.0, -1.0, 0.0): math.sqrt(2.0),  # vertex region of a
        (0.5, -2.0, 1.0): math.sqrt(5.0),  # edge ab
        (1.0, 1.0, 0.0): math.sqrt(0.5),  # edge bc
        (3.0, 0.0, -4.0): math.sqrt(4.0 + 16.0),  # vertex b
    }
    for p, d in cases.items():
        got = point_triangle_distance(torch.tensor(p, dtype=DT), a, b, c)
        assert abs(float(got) - d) < 1e-12
    # degenerate triangle (collinear): distance to the segment
    got = point_triangle_distance(torch.tensor([0.5, 1.0, 0.0], dtype=DT), a, b, 2 * b)
    assert abs(float(got) - 1.0) < 1e-12


def test_point_triangle_distance_vs_sampling():
    g = np.random.default_rng(7)
    for _ in range(20):
        a, b, c, p = (g.normal(size=3) for _ in range(4))
        d2 = float(point_triangle_distance(*(torch.tensor(x) for x in (p, a, b, c)))) ** 2
        approx = _brute_sq_distance(p, a, b, c)
        assert d2 <= approx + 1e-12
        assert approx - d2 < 0.02 * (1 + approx)


def test_nearest_triangles_igl_vs_torch_bruteforce():
    V, F = _bumpy_sphere()
    g = torch.Generator().manual_seed(8)
    pts = torch.randn(400, 3, generator=g, dtype=DT) * 0.8
    f_igl, d_igl = nearest_triangles(pts, V, F, method="igl")
    f_t, d_t = nearest_triangles(pts, V, F, method="torch", chunk_pairs=5000)
    tri = V[F]
    all_d = point_triangle_distance(pts[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    best = all_d.min(dim=1).values
    assert torch.allclose(d_igl, best, atol=1e-10)
    assert torch.allclose(d_t, best, atol=1e-12)
    # among exact ties (points nearest to a shared vertex or edge) any face may be returned
    assert torch.allclose(all_d[torch.arange(400), f_t], best, atol=1e-12)
    assert torch.allclose(all_d[torch.arange(400), f_igl], best, atol=1e-10)
    two = all_d.topk(2, dim=1, largest=False).values
    unique = two[:, 1] - two[:, 0] > 1e-9
    assert unique.sum() > 100 and torch.equal(f_igl[unique], f_t[unique])


@pytest.mark.parametrize("method", ["igl", "torch"])
def test_nearest_triangles_candidates(method):
    V, F = _bumpy_sphere()
    g = torch.Generator().manual_seed(9)
    pts = torch.randn(200, 3, generator=g, dtype=DT)
    mask = V[F][:, :, 2].mean(1) > 0  # front half only
    fid, d = nearest_triangles(pts, V, F, candidates=mask, method=method)
    assert mask[fid].all()
    sub = torch.nonzero(mask).reshape(-1)
    tri = V[F[sub]]
    best = point_triangle_distance(pts[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]).min(1).values
    assert torch.allclose(d, best, atol=1e-10)
    fid2, d2 = nearest_triangles(pts, V, F, candidates=sub, method=method)
    assert torch.allclose(d2, d, atol=1e-12)
    with pytest.raises(ValueError):
        nearest_triangles(pts, V, F, candidates=torch.zeros(F.shape[0], dtype=torch.bool), method=method)


def test_nearest_distance_gradient():
    V, F = _bumpy_sphere()
    g = torch.Generator().manual_seed(10)
    pts = (torch.randn(50, 3, generator=g, dtype=DT) * 1.5).requires_grad_(True)
    _, d = nearest_triangles(pts, V, F)
    d.sum().backward()
    import igl

    sq, _, closest = igl.point_mesh_squared_distance(pts.detach().numpy(), V.numpy(), F.numpy())
    assert np.allclose(d.detach().numpy(), np.sqrt(sq), atol=1e-10)
    expected = (pts.detach().numpy() - closest) / np.sqrt(sq)[:, None]
    assert np.allclose(pts.grad.numpy(), expected, atol=1e-6)


# ---------------------------------------------------------------------------- SurfelSet


def test_surfel_set_pose_and_canonical_positions():
    S, V, F = _surfel_set()
    R, T, k = surfel_frames(V, F)
    means, quats, scales = S.pose(R, T, k)
    assert means.shape == (len(S), 3) and quats.shape == (len(S), 4) and scales.shape == (len(S), 2)
    assert torch.allclose(S.canonical_positions(R, T, k), means, atol=1e-14)
    means.sum().backward()
    assert S.mu_loc.grad is not None and S.mu_loc.grad.abs().sum() > 0


def test_rebind_preserves_canonical_pose_and_picks_nearest():
    S, V, F = _surfel_set(seed=11)
    R, T, k = surfel_frames(V, F)
    g = torch.Generator().manual_seed(12)
    with torch.no_grad():
        S.mu_loc.add_(torch.randn(S.mu_loc.shape, generator=g, dtype=DT) * 1.5)
        S.q_loc.copy_(torch.randn(S.q_loc.shape, generator=g, dtype=DT))
        S.s_loc.add_(torch.randn(S.s_loc.shape, generator=g, dtype=DT) * 0.2)
    with torch.no_grad():
        m0, q0, s0 = S.pose(R, T, k)
    old = S.binding.clone()
    n = S.rebind(V, F)
    assert n == int((S.binding != old).sum()) and n > len(S) // 4
    with torch.no_grad():
        m1, q1, s1 = S.pose(R, T, k)
    assert torch.allclose(m1, m0, atol=1e-12)
    assert torch.allclose(s1, s0, atol=1e-12)
    assert torch.allclose(quat_to_matrix(q1), quat_to_matrix(q0), atol=1e-12)
    tri = V[F]
    all_d = point_triangle_distance(m0[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    bound_d = all_d[torch.arange(len(S)), S.binding]
    assert torch.allclose(bound_d, all_d.min(1).values, atol=1e-6)
    # labels follow the triangle; a second pass changes nothing
    assert torch.equal(S.region_id, S.face_region[S.binding])
    assert S.rebind(V, F) == 0


def test_rebind_resets_optimizer_rows_of_moved_surfels():
    S, V, F = _surfel_set(seed=18)
    opt = torch.optim.Adam(S.parameters(), lr=1e-3)
    loss = sum((p ** 2).sum() for p in S.parameters())
    loss.backward()
    opt.step()
    with torch.no_grad():
        S.mu_loc[::2] += 2.0
    old = S.binding.clone()
    before = {n: {k: v.clone() for k, v in opt.state[p].items()} for n, p in S.named_parameters()}
    assert S.rebind(V, F, optimizer=opt) > 0
    moved = S.binding != old
    for name in ("mu_loc", "q_loc", "s_loc"):
        st = opt.state[getattr(S, name)]
        assert (st["exp_avg"][moved] == 0).all() and (st["exp_avg_sq"][moved] == 0).all()
        assert torch.equal(st["exp_avg"][~moved], before[name]["exp_avg"][~moved])
    assert torch.equal(opt.state[S.opacity]["exp_avg"], before["opacity"]["exp_avg"])


def test_rebind_allowed_faces_and_ties():
    S, V, F = _surfel_set(seed=13)
    R, T, k = surfel_frames(V, F)
    # surfels initialised on their triangles: nothing moves, even those on shared edges
    assert S.rebind(V, F) == 0
    with torch.no_grad():
        m0 = S.canonical_positions(R, T, k)
    labels = torch.as_tensor(face_region_labels(_fake_regions(V, F), F.shape[0]))
    allowed = labels != REGION_HAIR
    n_hair = int(S.hair_mask().sum())
    assert n_hair > 0
    n = S.rebind(V, F, allowed_faces=allowed)
    assert n == n_hair
    assert allowed[S.binding].all()
    assert not S.hair_mask().any()
    with torch.no_grad():
        assert torch.allclose(S.canonical_positions(R, T, k), m0, atol=1e-12)


def test_state_dict_keeps_binding():
    S, V, F = _surfel_set(seed=14, sh_degree=2)
    with torch.no_grad():
        S.mu_loc.add_(0.8)
    assert S.rebind(V, F) > 0
    state = S.state_dict()
    assert "binding" in state and "region_id" in state and "sh_rest" in state
    T2, _, _ = _surfel_set(seed=14, sh_degree=2)
    assert not torch.equal(T2.binding, S.binding)
    T2.load_state_dict(state)
    assert torch.equal(T2.binding, S.binding) and torch.equal(T2.region_id, S.region_id)
    S.prune(torch.arange(len(S)) % 3 == 0)
    U = SurfelSet.from_state_dict(S.state_dict())
    assert len(U) == len(S) and U.sh_degree == 2 and U.attributes == "free"
    for name, x in S.state_dict().items():
        assert torch.equal(U.state_dict()[name], x)


def test_attribute_modes():
    S, _, _ = _surfel_set(attributes="mlp")
    names = {n for n, _ in S.named_parameters()}
    assert names == {"mu_loc", "q_loc", "s_loc"}
    with pytest.raises(AttributeError):
        S.opacities()
    U = SurfelSet.from_state_dict(S.state_dict())
    assert U.attributes == "mlp"
    rgb = torch.rand(600, 3, dtype=DT, generator=torch.Generator().manual_seed(0))
    S3, _, _ = _surfel_set(sh_degree=3, rgb=rgb, opacity=0.3)
    assert S3.sh_coeffs().shape == (600, 16, 3)
    assert torch.allclose(S3.opacities(), torch.full((600,), 0.3, dtype=DT))
    assert torch.allclose(0.5 + 0.28209479177387814 * S3.sh_dc[:, 0], rgb)


def test_prune_keeps_rows_and_adam_state_aligned():
    A, _, _ = _surfel_set(seed=15, sh_degree=1)
    B, _, _ = _surfel_set(seed=15, sh_degree=1)
    opt_a = torch.optim.Adam(A.parameters(), lr=1e-2)
    opt_b = torch.optim.Adam(B.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(16)
    targets = {n: torch.randn(p.shape, generator=g, dtype=DT) for n, p in A.named_parameters()}

    def step(S, opt):
        opt.zero_grad()
        loss = sum(((p - targets_rows[n]) ** 2 * weights_rows[n]).sum() for n, p in S.named_parameters())
        loss.backward()
        opt.step()

    weights = {n: torch.rand(t.shape, generator=g, dtype=DT) for n, t in targets.items()}
    targets_rows, weights_rows = targets, weights
    for _ in range(3):
        step(A, opt_a)
        step(B, opt_b)
    remove = torch.rand(len(A), generator=g) < 0.3
    keep = ~remove
    binding_before = A.binding.clone()
    assert A.prune(remove, opt_a) == int(remove.sum())
    assert len(A) == int(keep.sum()) and torch.equal(A.binding, binding_before[keep])
    params = list(A.parameters())
    assert all(any(p is q for q in opt_a.param_groups[0]["params"]) for p in params)
    assert torch.equal(opt_a.state[A.mu_loc]["exp_avg"], opt_b.state[B.mu_loc]["exp_avg"][keep])
    targets_rows = {n: t[keep] for n, t in targets.items()}
    weights_rows = {n: w[keep] for n, w in weights.items()}
    step(A, opt_a)
    targets_rows, weights_rows = targets, weights
    step(B, opt_b)
    for (n, pa), (_, pb) in zip(A.named_parameters(), B.named_parameters()):
        assert torch.allclose(pa, pb[keep], atol=1e-14), n
    # explicit row order
    A.index_select(torch.tensor([2, 0, 1]))
    assert len(A) == 3 and A.mu_loc.shape == (3, 3) and A.opacity.shape == (3,)


def test_surfel_set_validates_shapes():
    with pytest.raises(ValueError):
        SurfelSet(torch.zeros(3, dtype=torch.long), torch.zeros(3, 3), torch.zeros(2, 4), torch.zeros(3, 2))
    with pytest.raises(ValueError):
        SurfelSet(torch.zeros(3, dtype=torch.long), torch.zeros(3, 3), torch.zeros(3, 4), torch.zeros(3, 2),
                  attributes="other")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_pose_and_rebind_on_cuda():
    S, V, F = _surfel_set(seed=17)
    with torch.no_grad():
        S.mu_loc.add_(0.7)
    Sc = SurfelSet.from_state_dict({k: v.cuda() for k, v in S.state_dict().items()})
    Vc, Fc = V.cuda(), F.cuda()
    Rc, Tc, kc = surfel_frames(Vc, Fc)
    mc, _, _ = Sc.pose(Rc, Tc, kc)
    m, _, _ = S.pose(*surfel_frames(V, F))
    assert mc.device.type == "cuda"
    assert torch.allclose(mc.cpu(), m, atol=1e-10)
    n_cpu = S.rebind(V, F, method="torch")
    n_gpu = Sc.rebind(Vc, Fc, method="torch")
    assert n_cpu == n_gpu and torch.equal(Sc.binding.cpu(), S.binding)


def test_opacity_offset_adds_to_the_network_logit_with_its_gradient():
    """offset_opacities(a) = sigmoid(logit(a) + o), values and gradients (float64 against the logit
    form), exact at a = 0 and a = 1; only attribute-network sets have one; state dicts carry it."""
    n = 6
    s = SurfelSet(torch.arange(n), torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.zeros(n, 2),
                  attributes="mlp").double()
    a = torch.tensor([0.0, 1e-3, 0.3, 0.5, 0.9, 1.0], dtype=torch.float64)
    assert torch.equal(s.offset_opacities(a), a)  # none yet
    s.enable_opacity_offset()
    with torch.no_grad():
        s.opacity_offset.copy_(torch.tensor([2.0, -1.0, 0.7, -3.0, 1.5, -2.0], dtype=torch.float64))
    out = s.offset_opacities(a)
    inner = slice(1, 5)
    ref = torch.sigmoid(torch.logit(a[inner]) + s.opacity_offset.detach()[inner])
    assert torch.allclose(out[inner], ref, atol=1e-12)
    assert float(out[0].detach()) == 0.0 and float(out[-1].detach()) == 1.0
    ai = a[inner].clone().requires_grad_(True)
    (g_off, g_a) = torch.autograd.grad((s.offset_opacities(torch.cat([a[:1], ai, a[5:]]))[inner] * torch.arange(1.0, 5.0, dtype=torch.float64)).sum(),
                                       [s.opacity_offset, ai])
    o = s.opacity_offset.detach()[inner].clone().requires_grad_(True)
    ai2 = a[inner].clone().requires_grad_(True)
    (r_off, r_a) = torch.autograd.grad((torch.sigmoid(torch.logit(ai2) + o) * torch.arange(1.0, 5.0, dtype=torch.float64)).sum(), [o, ai2])
    assert torch.allclose(g_off[inner], r_off, atol=1e-12) and torch.allclose(g_a, r_a, atol=1e-10)
    back = SurfelSet.from_state_dict(s.state_dict())
    assert torch.equal(back.opacity_offset, s.opacity_offset)
    free = SurfelSet(torch.arange(n), torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.zeros(n, 2))
    with pytest.raises(AttributeError):
        free.enable_opacity_offset()
    assert "opacity_offset" not in free.state_dict()
