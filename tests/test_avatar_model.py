"""The Avatar: posing through triangle frames, rigid motion, save/load, canonical ray maps."""

from __future__ import annotations

import pytest
import torch

from sage_core.avatar.model import Avatar, canonical_rays_rigid, canonical_to_world_rigid
from sage_core.config import resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.flame.frames import surfel_frames
from sage_core.geometry.rotations import axis_angle_to_matrix, quat_to_matrix
from sage_core.render import RenderCamera
from sage_core.train.phase1 import CanonicalRays


@pytest.fixture(scope="module")
def init_dir(tiny_init_dir):
    return tiny_init_dir


@pytest.fixture(scope="module")
def data(tiny_ws):
    return IngestedData.open(tiny_ws / "data")


def _avatar(init_dir, data, mode, n=400):
    g = torch.Generator().manual_seed(1)
    av = Avatar.build(init_dir, data, n, mode, app_args={"hidden": 16, "sh_degree": 1}, shape_args={"hidden": 16}, sh_degree=1, generator=g)
    # perturb the per-surfel state so that the test is not about the initial values
    with torch.no_grad():
        av.surfels.mu_loc.add_(0.1 * torch.randn(av.surfels.mu_loc.shape, generator=g))
        av.surfels.q_loc.add_(0.2 * torch.randn(av.surfels.q_loc.shape, generator=g))
        if mode == "free":
            av.surfels.sh_rest.add_(0.1 * torch.randn(av.surfels.sh_rest.shape, generator=g))
    return av


def _expressive_inputs(av, data):
    """A test timestep (novel expression, non-rigid relative to canonical)."""
    return av.frame_inputs(data.test[0].timestep)


@pytest.mark.parametrize("mode", ["free", "mlp"])
def test_posing_equals_binding_formula(init_dir, data, mode):
    av = _avatar(init_dir, data, mode)
    inputs = _expressive_inputs(av, data)
    with torch.no_grad():
        cs = av.canonical_state()
        p = av.posed(inputs, torch.tensor([0.1, 0.0, 1.0]))
        verts = av.pose_mesh(inputs)
        R_p, T_p, k_p = surfel_frames(verts, av.faces)
    b = av.surfels.binding
    R_c, T_c, k_c = av.R_c[b], av.T_c[b], av.k_c[b]
    mu = k_p[b, None] * torch.einsum("nij,nkj,nk->ni", R_p[b], R_c, cs.means - T_c) / k_c[:, None] + T_p[b]
    assert torch.allclose(p.means, mu, atol=1e-6)
    R = R_p[b] @ R_c.transpose(-1, -2) @ quat_to_matrix(cs.quats)
    assert torch.allclose(quat_to_matrix(p.quats), R, atol=1e-5)
    assert torch.allclose(p.scales, cs.scales * (k_p[b] / k_c)[:, None], rtol=1e-5)
    assert torch.allclose(p.vertices, verts)
    if mode == "free":  # GaussianAvatars' binding of the local parameters
        m2, q2, s2 = av.surfels.pose(R_p, T_p, k_p)
        assert torch.allclose(p.means, m2, atol=1e-6)
        assert torch.allclose(quat_to_matrix(p.quats), quat_to_matrix(q2), atol=1e-5)
        assert torch.allclose(p.scales, s2, rtol=1e-5)
    assert p.colors.shape == (len(av.surfels), 3) and bool((p.colors >= 0).all()) and bool((p.opacities <= 1).all())


@pytest.mark.parametrize("mode", ["free", "mlp"])
def test_posing_with_a_kept_mesh_is_posing_from_scratch(init_dir, data, mode):
    """A PosedMesh computed once (as a trainer keeps it) poses bit-identically, gradients included,
    also for a transformed (mirrored) mesh."""
    av = _avatar(init_dir, data, mode)
    inputs = _expressive_inputs(av, data)
    flip = torch.tensor([-1.0, 1.0, 1.0])
    for transform in (None, lambda v: v * flip):
        with torch.no_grad():
            mesh = av.posed_mesh(inputs, transform)
        outs = []
        for kept in (None, mesh):
            av.zero_grad(set_to_none=True)
            p = av.posed(inputs, torch.tensor([0.1, 0.0, 1.0]), vertex_transform=transform, mesh=kept)
            (p.means.sum() + p.quats.sum() + p.scales.sum() + p.colors.sum() + p.opacities.sum()).backward()
            outs.append((p, av.surfels.mu_loc.grad.clone()))
        (a, ga), (b, gb) = outs
        for name in ("means", "quats", "scales", "colors", "opacities", "vertices"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert torch.equal(ga, gb)


@pytest.mark.parametrize("mode", ["free", "mlp"])
def test_rigid_flame_motion_moves_surfels_rigidly(init_dir, data, mode):
    av = _avatar(init_dir, data, mode)
    inputs = _expressive_inputs(av, data)
    moved = dict(inputs)
    aa = torch.tensor([[0.3, -0.2, 0.1]])
    t = torch.tensor([[0.02, -0.01, 0.03]])
    moved["rotation"] = aa
    moved["translation"] = t
    base = dict(inputs)
    base["rotation"] = torch.zeros(1, 3)
    base["translation"] = torch.zeros(1, 3)
    cam0 = torch.tensor([0.05, 0.02, 1.0])
    R0 = axis_angle_to_matrix(aa)[0]
    J0 = av.root_joint
    cam1 = canonical_to_world_rigid(cam0[None], R0, t[0], J0)[0]
    with torch.no_grad():
        p0 = av.posed(base, cam0)
        p1 = av.posed(moved, cam1)
    assert torch.allclose(p1.means, canonical_to_world_rigid(p0.means, R0, t[0], J0), atol=2e-6)
    assert torch.allclose(quat_to_matrix(p1.quats), R0 @ quat_to_matrix(p0.quats), atol=1e-5)
    assert torch.allclose(p1.scales, p0.scales, rtol=1e-4)
    # view-dependent colour sees the same relative view direction
    assert torch.allclose(p1.colors, p0.colors, atol=1e-5)
    assert torch.allclose(p1.opacities, p0.opacities, atol=1e-6)
    # the rigid test: a novel expression is not a rigid motion of canonical space, while the
    # canonical timestep under any global rotation and translation is
    assert av.rigid_transform(moved) is None
    canon_moved = dict(av.frame_inputs(data.canonical_timestep), rotation=aa, translation=t)
    rt = av.rigid_transform(canon_moved)
    assert rt is not None and torch.allclose(rt[0], R0, atol=1e-6) and torch.allclose(rt[1], t[0])


@pytest.mark.parametrize("mode", ["free", "mlp"])
def test_save_load_round_trip_renders_identically(init_dir, data, mode, tmp_path):
    av = _avatar(init_dir, data, mode)
    with torch.no_grad():
        av.surfels.mu_loc.add_(0.05)
    fr = data.val[0]
    cam = RenderCamera.from_camera(fr.camera)
    inputs = av.frame_inputs(fr.timestep)
    with torch.no_grad():
        img0, _ = av.render(cam, inputs, 1.0)
    path = av.save(tmp_path / "avatar.pt")
    av2 = Avatar.load(path)
    assert av2.attributes == mode and len(av2.surfels) == len(av.surfels)
    assert torch.equal(av2.surfels.binding, av.surfels.binding)
    with torch.no_grad():
        img1, _ = av2.render(cam, av2.frame_inputs(fr.timestep), 1.0)
    assert float(img0.alpha.max()) > 0.5
    assert torch.equal(img0.color, img1.color)
    assert torch.equal(img0.depth, img1.depth)


def test_load_rejects_foreign_file(tmp_path):
    from sage_core.errors import InputError, UnsafeFileError
    from sage_core.serialization import save_file

    p = tmp_path / "x.pt"
    save_file(p, {"something": torch.ones(1)}, "sage-sdf", 2)
    with pytest.raises(InputError, match="not a sage avatar"):
        Avatar.load(p)
    torch.save({"something": 1}, p)  # an old pickle file is refused without being loaded
    with pytest.raises(UnsafeFileError, match="old pickle format"):
        Avatar.load(p)


def test_rigid_canonical_ray_map_round_trip(init_dir, data):
    av = _avatar(init_dir, data, "free")
    fr = data.train[0]
    inputs = av.frame_inputs(fr.timestep)
    rt = av.rigid_transform(inputs)
    assert rt is not None, "the MV-SF training frame differs from canonical only rigidly"
    R0, t = rt
    J0 = av.root_joint
    with torch.no_grad():
        verts_w = av.pose_mesh(inputs)
    # posed vertices map exactly onto the canonical vertices
    v_c, _ = canonical_rays_rigid(verts_w, torch.zeros_like(verts_w), R0, t, J0)
    assert torch.allclose(v_c, av.canonical_vertices, atol=2e-6)
    o = torch.randn(50, 3)
    d = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    o_c, d_c = canonical_rays_rigid(o, d, R0, t, J0)
    assert torch.allclose(canonical_to_world_rigid(o_c, R0, t, J0), o, atol=1e-6)
    assert torch.allclose(d_c.norm(dim=-1), torch.ones(50), atol=1e-6)
    # the triangle warp agrees with the rigid map on a rigid frame (same line, same direction)
    cam = RenderCamera.from_camera(fr.camera)
    mapper = CanonicalRays(av)
    pix = torch.arange(0, cam.width * cam.height, 37)
    o1, d1, r1, rot1, ok1 = mapper.map(inputs, cam, pix, rt)
    o2, d2, r2, rot2, ok2 = mapper.map(inputs, cam, pix, None)
    assert bool(ok1.all()) and 10 < int(ok2.sum()) < len(pix)
    assert torch.allclose(d1[ok2], d2[ok2], atol=1e-4)
    assert torch.allclose(r2[ok2], torch.ones_like(r2[ok2]), atol=1e-4)
    assert torch.allclose(rot1[ok2], rot2[ok2], atol=1e-4)
    assert torch.allclose(o1[ok2], o2[ok2], atol=1e-4)


def test_shape_network_reading_the_detail_grid(init_dir, data, tmp_path):
    """``detail_grid``: the shape network's input holds the appearance grid's features at the surfel
    centres, its gradient reaches that grid, and the flag survives saving."""
    g = torch.Generator().manual_seed(3)
    app = {"hidden": 16, "sh_degree": 1, "grid": {"n_levels": 4, "n_features": 2, "log2_table": 10, "base_res": 8, "max_res": 64}}
    av = Avatar.build(init_dir, data, 300, "mlp", app_args=app, shape_args={"hidden": 16, "detail_grid": True}, generator=g)
    plain = Avatar.build(init_dir, data, 300, "mlp", app_args=app, shape_args={"hidden": 16}, generator=g)
    assert av.shape_reads_detail and not plain.shape_reads_detail
    assert av.shape.in_features == av.sdf.encoding.output_dim + av.appearance.grid.output_dim
    assert plain.shape.in_features == plain.sdf.encoding.output_dim
    with torch.no_grad():
        av.appearance.grid.table.normal_(0, 1, generator=g)
        av.shape.mlp[-1].weight.normal_(0, 1, generator=g)
    cs = av.canonical_state()
    cs.scales.sum().backward()
    assert av.appearance.grid.table.grad is not None and av.appearance.grid.table.grad.abs().sum() > 0
    with torch.no_grad():  # the shape depends on the detail grid: changing it changes the scales
        before = av.canonical_state().scales.clone()
        av.appearance.grid.table.mul_(-1)
        assert not torch.allclose(av.canonical_state().scales, before)
    av.save(tmp_path / "a.pt", embed_flame=True)
    back = Avatar.load(tmp_path / "a.pt")
    assert back.shape_reads_detail
    with torch.no_grad():
        assert torch.equal(back.canonical_state().scales, av.canonical_state().scales)


def test_appearance_reuses_the_grid_features_the_shape_network_read(init_dir, data):
    """With ``detail_grid`` the appearance grid is evaluated once per canonical state: the posed
    colours from the reused features equal those of a fresh evaluation, values and gradients."""
    g = torch.Generator().manual_seed(5)
    app = {"hidden": 16, "sh_degree": 1, "grid": {"n_levels": 4, "n_features": 2, "log2_table": 10, "base_res": 8, "max_res": 64}}
    av = Avatar.build(init_dir, data, 300, "mlp", app_args=app, shape_args={"hidden": 16, "detail_grid": True}, generator=g)
    with torch.no_grad():
        av.appearance.grid.table.normal_(0, 1, generator=g)
    cs = av.canonical_state(with_sdf=True)
    assert cs.app_encoding is not None and torch.equal(cs.app_encoding, av.appearance.grid(cs.means))
    n = torch.nn.functional.normalize(cs.sdf_grad.detach(), dim=-1)
    view = -cs.rotation[..., 2].detach()
    shared, _ = av.appearance(cs.means, view, n, cs.feature, grid_features=cs.app_encoding)
    fresh, _ = av.appearance(cs.means, view, n, cs.feature)
    assert torch.allclose(shared, fresh, atol=0, rtol=0)
    (ga,) = torch.autograd.grad(shared.sum(), av.appearance.grid.table, retain_graph=True)
    (gb,) = torch.autograd.grad(fresh.sum(), av.appearance.grid.table)
    assert torch.allclose(ga, gb, atol=1e-6) and ga.abs().sum() > 0
