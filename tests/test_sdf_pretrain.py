"""Mesh signed distance, marching cubes, mesh metrics and SDF pretraining on a mesh."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from sage_core.fields.pretrain import PretrainConfig, SDFPretrainer
from sage_core.fields.sdf import SDFNetwork
from sage_core.geometry.marching import extract_mesh
from sage_core.geometry.mesh_metrics import chamfer_distance, mesh_chamfer, normal_error
from sage_core.geometry.mesh_sdf import (
    sample_surface,
    sign_confidence,
    signed_distance,
    vertex_normals,
    winding_number,
)

AXES = np.array([0.08, 0.10, 0.12])
BOX = 0.2


def ellipsoid(subdiv: int = 3) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdiv, radius=1.0)
    return np.asarray(m.vertices) * AXES, np.asarray(m.faces)


def sphere(r: float = 0.1, subdiv: int = 4) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdiv, radius=r)
    return np.asarray(m.vertices), np.asarray(m.faces)


def tiny_sdf(seed: int = 0) -> SDFNetwork:
    torch.manual_seed(seed)
    return SDFNetwork(
        [-BOX] * 3, [BOX] * 3, n_levels=8, n_features=2, log2_table=14, base_res=8, max_res=128,
        hidden=32, feature_dim=4, sphere_radius=0.5,
    )  # fmt: skip


# ---- mesh signed distance -------------------------------------------------------------------


def test_signed_distance_sphere_negative_inside():
    v, f = sphere(0.1)
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.2, 0.2, (2000, 3))
    s, closest, fid = signed_distance(p, v, f)
    exact = np.linalg.norm(p, axis=1) - 0.1
    assert np.abs(s - exact).max() < 1e-3  # polygonal approximation error of the icosphere
    assert np.all(np.sign(s[np.abs(exact) > 2e-3]) == np.sign(exact[np.abs(exact) > 2e-3]))
    assert np.abs(np.linalg.norm(p - closest, axis=1) - np.abs(s)).max() < 1e-9
    assert fid.shape == (2000,) and fid.min() >= 0 and fid.max() < len(f)
    s_t, _, _ = signed_distance(torch.as_tensor(p, dtype=torch.float32), torch.as_tensor(v), torch.as_tensor(f))
    assert np.abs(s_t - s).max() < 1e-6
    with pytest.raises(ValueError):
        signed_distance(p[:, :2], v, f)


def test_winding_number_and_confidence_on_open_mesh():
    v, f = sphere(0.1)
    keep = v[f].mean(1)[:, 2] < 0.07  # cut a cap off: a hole around +z
    f_open = f[keep]
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3], [0.0, 0.0, 0.07], [0.0, 0.0, -0.05]])
    w_closed = winding_number(pts, v, f)
    assert w_closed[0] == pytest.approx(1.0, abs=1e-2) and abs(w_closed[1]) < 1e-2
    w_open = winding_number(pts, v, f_open)
    conf = sign_confidence(w_open)
    assert conf[2] < 0.5  # next to the hole: ambiguous sign
    assert conf[3] == pytest.approx(1.0) and conf[1] == pytest.approx(1.0)
    assert sign_confidence(np.array([0.5]))[0] == 0.0


def test_sample_surface_area_weighted_and_on_mesh():
    v, f = ellipsoid()
    rng = np.random.default_rng(1)
    pts, nrm, fid = sample_surface(v, f, 5000, rng, return_faces=True)
    s, _, _ = signed_distance(pts, v, f)
    assert np.abs(s).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, rtol=1e-9)
    assert np.mean(np.sum(nrm * pts, axis=1) > 0) > 0.99  # outward
    # area weighting: fraction of samples with z > 0 is ~0.5 for a symmetric mesh
    assert abs(np.mean(pts[:, 2] > 0) - 0.5) < 0.03
    vn = vertex_normals(v, f)
    assert np.mean(np.sum(vn * v, axis=1) > 0) == 1.0


# ---- marching cubes and metrics -----------------------------------------------------------


def test_extract_mesh_sphere_volume_outward_and_world_coords():
    c = torch.tensor([0.02, -0.01, 0.03])
    fn = lambda x: (x - c).norm(dim=-1) - 0.1  # noqa: E731
    v, f = extract_mesh(fn, [-0.2] * 3, [0.2] * 3, 96, chunk=10000)
    m = trimesh.Trimesh(v, f, process=False)
    assert m.volume == pytest.approx(4 / 3 * np.pi * 0.1**3, rel=0.01)  # positive: outward faces
    np.testing.assert_allclose(v.mean(0), c.numpy(), atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(v - c.numpy(), axis=1), 0.1, atol=1e-3)
    v2, f2 = extract_mesh(fn, [-0.2] * 3, [0.2] * 3, (96, 96, 96), chunk=1 << 20)
    np.testing.assert_allclose(v2, v)
    ve, fe = extract_mesh(lambda x: x.norm(dim=-1) + 1.0, [-0.2] * 3, [0.2] * 3, 16)
    assert ve.shape == (0, 3) and fe.shape == (0, 3)


def test_chamfer_and_normal_error():
    a = np.random.default_rng(0).normal(size=(500, 3))
    assert chamfer_distance(a, a) == 0.0
    assert chamfer_distance(a, a + np.array([0.01, 0, 0])) == pytest.approx(0.01, rel=1e-6)
    assert chamfer_distance(a, np.zeros((0, 3))) == float("inf")
    v, f = sphere(0.1)
    v2, f2 = sphere(0.102)
    assert mesh_chamfer(v, f, v2, f2, 20000) == pytest.approx(0.002, abs=7e-4)
    assert normal_error(v, f, v2, f2) < 3.0
    assert normal_error(v, f, v2, f2[:, ::-1]) > 170.0  # flipped orientation


# ---- pretraining -------------------------------------------------------------------------


def test_pretraining_fits_ellipsoid(one_thread):
    v, f = ellipsoid()
    net = tiny_sdf()
    cfg = PretrainConfig(steps=200, batch_size=2048, bank_size=20000, eval_resolution=64, eval_samples=5000)
    trainer = SDFPretrainer(net, v, f, cfg, torch.Generator().manual_seed(0))
    before = trainer.evaluate()
    calls = []
    losses = trainer.run(progress=lambda i, n, l: calls.append(i))
    assert calls[-1] == 200 and len(calls) == 200
    assert set(losses) == {"loss", "value", "normal", "eikonal"}
    after = trainer.evaluate()
    diag = np.linalg.norm(2 * AXES)
    assert after["mean_abs_sdf_vertices"] < 0.005 * diag
    assert after["mean_abs_sdf_rel"] < 0.005
    assert after["mean_abs_sdf_vertices"] < 0.2 * before["mean_abs_sdf_vertices"]
    assert after["normal_cos"] > 0.99
    assert after["chamfer"] < 0.004  # 64^3 grid over 0.4 m: 6 mm voxels
    assert after["chamfer"] < before["chamfer"]


def test_pretraining_resumes_exactly(one_thread):
    v, f = ellipsoid(2)
    cfg = PretrainConfig(steps=6, batch_size=300, bank_size=2000)

    def make() -> SDFPretrainer:
        return SDFPretrainer(tiny_sdf(1), v, f, cfg, torch.Generator().manual_seed(7))

    straight = make()
    for _ in range(6):
        straight.step()
    first = make()
    for _ in range(3):
        first.step()
    state = first.state_dict()
    assert state["step"] == 3 and state["config"]["batch_size"] == 300
    resumed = make()
    resumed.load_state_dict(state)
    for _ in range(3):
        resumed.step()
    assert resumed.step_count == 6
    for (name, a), (_, b) in zip(straight.net.state_dict().items(), resumed.net.state_dict().items()):
        assert torch.equal(a, b), name
    torch.testing.assert_close(
        straight.optimizer.state_dict()["state"][0]["exp_avg"], resumed.optimizer.state_dict()["state"][0]["exp_avg"]
    )
    other = SDFPretrainer(tiny_sdf(1), v, f, PretrainConfig(bank_size=1000), torch.Generator().manual_seed(7))
    with pytest.raises(ValueError, match="bank_size"):
        other.load_state_dict(state)


def test_open_mesh_is_down_weighted():
    v, f = sphere(0.1, 3)
    keep = v[f].mean(1)[:, 2] < 0.07
    trainer = SDFPretrainer(tiny_sdf(2), v, f[keep], PretrainConfig(bank_size=4000), torch.Generator().manual_seed(0))
    conf = trainer.bank_off_conf.numpy()
    pts = trainer.bank_off.numpy()
    # the opening: a disc of radius ~0.07 at z = 0.07
    near_hole = (np.abs(pts[:, 2] - 0.07) < 0.01) & (np.linalg.norm(pts[:, :2], axis=1) < 0.05)
    assert near_hole.sum() >= 3
    assert conf[near_hole].mean() < 0.6 < conf[~near_hole].mean()
