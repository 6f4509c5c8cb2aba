"""FLAME LBS against an independent float64 numpy per-vertex reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sage_core.flame import FlameModel, FlameModelData


def random_model(V: int = 30, parents: tuple[int, ...] = (-1, 0, 1, 1, 1), S: int = 8, E: int = 10,
                 seed: int = 0) -> FlameModelData:
    rng = np.random.default_rng(seed)
    J = len(parents)
    w = rng.random((V, J)) ** 3
    jr = rng.random((J, V))
    return FlameModelData(
        v_template=rng.normal(size=(V, 3)) * 0.1,
        faces=rng.integers(0, V, size=(V, 3)),
        shapedirs=rng.normal(size=(V, 3, S)) * 0.01,
        exprdirs=rng.normal(size=(V, 3, E)) * 0.01,
        posedirs=rng.normal(size=(V, 3, 9 * (J - 1))) * 0.01,
        j_regressor=jr / jr.sum(1, keepdims=True),
        lbs_weights=w / w.sum(1, keepdims=True),
        parents=np.array(parents, dtype=np.int64),
        n_base_vertices=V,
    )


def _rodrigues(theta: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(theta + 1e-8)
    k = theta / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def reference_lbs(d: FlameModelData, shape, expr, pose, trans, offset) -> tuple[np.ndarray, np.ndarray]:
    """One batch item: plain loops in float64. pose: (J, 3). Returns vertices (V,3), joints (J,3)."""
    V, J = d.n_vertices, d.n_joints
    beta = np.zeros(d.n_shape)
    beta[: min(len(shape), d.n_shape)] = shape[: d.n_shape]
    psi = np.zeros(d.n_expr)
    psi[: min(len(expr), d.n_expr)] = expr[: d.n_expr]
    v_shaped = np.zeros((V, 3))
    for i in range(V):
        v_shaped[i] = d.v_template[i] + d.shapedirs[i] @ beta + d.exprdirs[i] @ psi + offset[i]
    joints = np.zeros((J, 3))
    for j in range(J):
        for i in range(V):
            joints[j] += d.j_regressor[j, i] * v_shaped[i]
    R = [_rodrigues(pose[j]) for j in range(J)]
    feat = np.concatenate([(R[j] - np.eye(3)).reshape(-1) for j in range(1, J)]) if J > 1 else np.zeros(0)
    v_posed = np.array([v_shaped[i] + d.posedirs[i] @ feat for i in range(V)])
    G = []
    for j in range(J):
        local = np.eye(4)
        local[:3, :3] = R[j]
        p = d.parents[j]
        local[:3, 3] = joints[j] - (joints[p] if p >= 0 else 0.0)
        G.append(local if p < 0 else G[p] @ local)
    A = []
    for j in range(J):
        rest = np.eye(4)
        rest[:3, 3] = -joints[j]
        A.append(G[j] @ rest)
    out = np.zeros((V, 3))
    for i in range(V):
        T = sum(d.lbs_weights[i, j] * A[j] for j in range(J))
        out[i] = T[:3, :3] @ v_posed[i] + T[:3, 3] + trans
    return out, np.array([g[:3, 3] + trans for g in G])


def _inputs(B: int, V: int, seed: int = 1, dtype=torch.float32) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s, scale=1.0: (torch.randn(*s, generator=g, dtype=torch.float64) * scale).to(dtype)  # noqa: E731
    return {
        "shape": r(6),  # shorter than S = 8, shared over the batch
        "expr": r(B, 12),  # longer than E = 10
        "rotation": r(B, 3, scale=0.4),
        "neck_pose": r(B, 3, scale=0.3),
        "jaw_pose": r(B, 3, scale=0.3),
        "eyes_pose": r(B, 6, scale=0.2),
        "translation": r(B, 3, scale=0.1),
        "static_offset": r(V - 4, 3, scale=0.01),  # fewer rows than the model
        "dynamic_offset": r(B, V, 3, scale=0.01),
    }


def _reference_batch(d: FlameModelData, inp: dict[str, torch.Tensor]) -> tuple[np.ndarray, np.ndarray]:
    n = {k: v.double().numpy() for k, v in inp.items()}
    B = n["rotation"].shape[0]
    V, J = d.n_vertices, d.n_joints
    verts, joints = [], []
    for b in range(B):
        full = np.concatenate([n["rotation"][b], n["neck_pose"][b], n["jaw_pose"][b], n["eyes_pose"][b]]).reshape(5, 3)
        pose = np.zeros((J, 3))
        pose[: min(J, 5)] = full[: min(J, 5)]
        offset = np.zeros((V, 3))
        offset[: n["static_offset"].shape[0]] += n["static_offset"]
        offset += n["dynamic_offset"][b]
        v, j = reference_lbs(d, n["shape"], n["expr"][b], pose, n["translation"][b], offset)
        verts.append(v)
        joints.append(j)
    return np.stack(verts), np.stack(joints)


def test_matches_reference_float32() -> None:
    d = random_model()
    model = FlameModel(d)
    assert model.v_template.dtype == torch.float32
    inp = _inputs(3, d.n_vertices)
    out = model(**inp)
    ref_v, ref_j = _reference_batch(d, inp)
    assert out.vertices.shape == (3, d.n_vertices, 3) and out.A.shape == (3, 5, 4, 4)
    np.testing.assert_allclose(out.vertices.detach().numpy(), ref_v, atol=1e-5)
    np.testing.assert_allclose(out.joints.detach().numpy(), ref_j, atol=1e-5)


@pytest.mark.parametrize("parents", [(-1, 0, 1, 1, 1), (-1, 0, 0), (-1, 0, 1, 2, 0, 4, 2)])
def test_matches_reference_float64_any_tree(parents: tuple[int, ...]) -> None:
    d = random_model(parents=parents, seed=len(parents))
    model = FlameModel(d, dtype=torch.float64)
    inp = _inputs(2, d.n_vertices, seed=2, dtype=torch.float64)
    out = model(**inp)
    ref_v, ref_j = _reference_batch(d, inp)
    np.testing.assert_allclose(out.vertices.detach().numpy(), ref_v, atol=1e-10)
    np.testing.assert_allclose(out.joints.detach().numpy(), ref_j, atol=1e-10)


def test_v_shaped_and_A_consistent() -> None:
    d = random_model()
    model = FlameModel(d, dtype=torch.float64)
    inp = _inputs(2, d.n_vertices, seed=3, dtype=torch.float64)
    out = model(**inp)
    static = torch.zeros(d.n_vertices, 3, dtype=torch.float64)
    static[: d.n_vertices - 4] = inp["static_offset"]
    canon = model(shape=inp["shape"], expr=inp["expr"], static_offset=static, dynamic_offset=inp["dynamic_offset"])
    torch.testing.assert_close(out.v_shaped, canon.v_shaped)
    # zero pose: posed = v_shaped, A = identity
    torch.testing.assert_close(canon.vertices, canon.v_shaped, atol=1e-7, rtol=0)
    eye = torch.eye(4, dtype=torch.float64).expand(2, 5, 4, 4)
    torch.testing.assert_close(canon.A, eye, atol=1e-7, rtol=0)


def test_root_rotation_pivots_about_j0_and_translation_last() -> None:
    d = random_model()
    model = FlameModel(d, dtype=torch.float64)
    shape = torch.randn(8, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    rest = model(shape=shape, static_offset=torch.full((d.n_vertices, 3), 0.5, dtype=torch.float64))
    assert rest.joints[0, 0].norm() > 0.5
    aa = torch.tensor([[0.2, -0.5, 0.3]], dtype=torch.float64)
    rot = model(shape=shape, rotation=aa, static_offset=torch.full((d.n_vertices, 3), 0.5, dtype=torch.float64))
    from sage_core.geometry import axis_angle_to_matrix

    R0 = axis_angle_to_matrix(aa)[0]
    J0 = rest.joints[0, 0]
    expected = (rest.vertices[0] - J0) @ R0.T + J0
    torch.testing.assert_close(rot.vertices[0], expected, atol=1e-10, rtol=0)
    torch.testing.assert_close(rot.joints[0, 0], J0, atol=1e-12, rtol=0)
    # rotation about the origin would differ (J0 is not the origin)
    assert (rest.vertices[0] @ R0.T - expected).abs().max() > 1e-3
    t = torch.tensor([[0.3, -0.1, 0.7]], dtype=torch.float64)
    jaw = torch.tensor([[0.2, 0.0, 0.0]], dtype=torch.float64)
    a = model(shape=shape, rotation=aa, jaw_pose=jaw)
    b = model(shape=shape, rotation=aa, jaw_pose=jaw, translation=t)
    torch.testing.assert_close(b.vertices, a.vertices + t[:, None], atol=1e-12, rtol=0)
    torch.testing.assert_close(b.joints, a.joints + t[:, None], atol=1e-12, rtol=0)
    torch.testing.assert_close(b.A, a.A)


def test_offset_padding_and_coefficient_truncation() -> None:
    d = random_model()
    model = FlameModel(d, dtype=torch.float64)
    V = d.n_vertices
    g = torch.Generator().manual_seed(3)
    off = torch.randn(V - 5, 3, generator=g, dtype=torch.float64) * 0.01
    padded = torch.cat([off, torch.zeros(5, 3, dtype=torch.float64)])
    a = model(static_offset=off)
    b = model(static_offset=padded[None])
    assert a.vertices.shape == (1, V, 3)
    torch.testing.assert_close(a.vertices, b.vertices)
    assert (a.v_shaped[0, : V - 5] - model.v_template[: V - 5] - off).abs().max() < 1e-12
    e = torch.randn(1, 40, generator=g, dtype=torch.float64)
    torch.testing.assert_close(model(expr=e).vertices, model(expr=e[:, :10]).vertices)
    s = torch.randn(3, generator=g, dtype=torch.float64)
    torch.testing.assert_close(model(shape=s).vertices, model(shape=torch.cat([s, s.new_zeros(5)])).vertices)
    with pytest.raises(ValueError, match="static_offset"):
        model(static_offset=torch.zeros(V + 1, 3, dtype=torch.float64))


def test_gradients_reach_every_input() -> None:
    d = random_model()
    model = FlameModel(d)
    inp = {k: v.clone().requires_grad_(True) for k, v in _inputs(2, d.n_vertices, seed=5).items()}
    out = model(**inp)
    (out.vertices.square().sum() + out.joints.square().sum()).backward()
    for name, t in inp.items():
        assert t.grad is not None and torch.isfinite(t.grad).all(), name
        assert t.grad.abs().sum() > 0, name


def test_gradcheck_small() -> None:
    d = random_model(V=8, S=3, E=2)
    model = FlameModel(d, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    args = [torch.randn(1, n, generator=g, dtype=torch.float64, requires_grad=True) * s
            for n, s in ((3, 1.0), (2, 1.0), (3, 0.3), (3, 0.3), (3, 0.3), (6, 0.3), (3, 0.1))]
    args = [a.detach().requires_grad_(True) for a in args]
    assert torch.autograd.gradcheck(lambda *a: model(*a).vertices, args)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    d = random_model()
    inp = _inputs(3, d.n_vertices)
    cpu = FlameModel(d)(**inp).vertices
    gpu = FlameModel(d).to("cuda")(**{k: v.cuda() for k, v in inp.items()}).vertices
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-5, rtol=0)
