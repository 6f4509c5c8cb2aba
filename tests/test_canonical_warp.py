"""Canonical warps: the rigid head map and its round trip, the hit-triangle warp, the automatic choice."""

from __future__ import annotations

import pytest
import torch

from sage_core.avatar.model import Avatar
from sage_core.config import resolve_config
from sage_core.data.dataset import IngestedData
from sage_core.geometry.rotations import axis_angle_to_matrix
from sage_core.render import RenderCamera
from sage_core.render.mesh_raster import points_on_mesh, rasterize_mesh
from sage_core.train.canonical_warp import (
    AutoWarp,
    CanonicalWarp,
    RigidFlameWarp,
    TriangleFrameWarp,
    make_warp,
    rigid_head_map,
    rigid_head_map_inverse,
)
from sage_core.train.warp import warp_pixels_to_canonical


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    """A small sv-hr workspace (monocular synthetic clip, brief SDF pretraining)."""
    from sage_core.data.capture import read_capture
    from sage_core.data.ingest import ingest
    from sage_core.data.synthetic import make_capture
    from sage_core.data.synthetic.config import preset
    from sage_core.train.init_mesh import run_init_mesh

    root = tmp_path_factory.mktemp("warp")
    cap = make_capture(root / "cap", preset("tiny", regime="monocular", width=64, height=92, train_timesteps=4,
                                            test_timesteps=1, novel_views=1, novel_expressions=1))
    ingest(read_capture(cap), cap.model_path, root / "data", regime="sv-hr", workers=1)
    cfg = resolve_config("init-mesh", "tiny", None, {"pretrain.steps": 10, "pretrain.bank_size": 3000, "pretrain.batch_size": 512,
                                                     "mc_resolution": 24, "pretrain.eval_samples": 1000})
    run_init_mesh(IngestedData.open(root / "data"), root / "init", cfg, seed=0)
    return root


@pytest.fixture(scope="module")
def avatar(ws):
    data = IngestedData.open(ws / "data")
    return Avatar.build(ws / "init", data, 300, "free", generator=torch.Generator().manual_seed(0)), data


def test_rigid_head_map_round_trip():
    g = torch.Generator().manual_seed(0)
    R0 = axis_angle_to_matrix(torch.randn(1, 3, generator=g, dtype=torch.float64))[0]
    t = torch.randn(3, generator=g, dtype=torch.float64) * 0.1
    J0 = torch.randn(3, generator=g, dtype=torch.float64) * 0.05
    x = torch.randn(100, 3, generator=g, dtype=torch.float64)
    w = rigid_head_map(x, R0, t, J0)
    assert torch.allclose(rigid_head_map_inverse(w, R0, t, J0), x, atol=1e-12)
    assert torch.allclose(rigid_head_map(rigid_head_map_inverse(x, R0, t, J0), R0, t, J0), x, atol=1e-12)
    # distances are preserved, J0 moves by t only
    assert torch.allclose((w[1:] - w[:-1]).norm(dim=-1), (x[1:] - x[:-1]).norm(dim=-1), atol=1e-12)
    assert torch.allclose(rigid_head_map(J0[None], R0, t, J0)[0], J0 + t, atol=1e-12)


def _rigid_inputs(av, data):
    """Canonical FLAME inputs with a new global rotation and translation: a rigid frame."""
    inp = dict(av.frame_inputs(data.canonical_timestep))
    inp["rotation"] = torch.tensor([[0.1, -0.5, 0.05]])
    inp["translation"] = torch.tensor([[0.01, -0.02, 0.03]])
    return inp


def test_rigid_map_matches_flame_and_triangle_warp(avatar):
    av, data = avatar
    inp = _rigid_inputs(av, data)
    rt = av.rigid_transform(inp)
    assert rt is not None
    R0, t = rt
    with torch.no_grad():
        verts = av.pose_mesh(inp)
    # the posed mesh is the rigid head map of the canonical mesh, and back
    assert torch.allclose(rigid_head_map(av.canonical_vertices, R0, t, av.root_joint), verts, atol=2e-6)
    assert torch.allclose(rigid_head_map_inverse(verts, R0, t, av.root_joint), av.canonical_vertices, atol=2e-6)
    cam = RenderCamera.from_camera(data.train[0].camera)
    pix = torch.arange(0, cam.width * cam.height, 7)
    rig = RigidFlameWarp().map(av, inp, cam, pix, rt)
    assert bool(rig.valid.all())
    rig2 = RigidFlameWarp().map(av, inp, cam, pix)  # computes the rigid transform itself
    assert torch.allclose(rig.origins, rig2.origins) and torch.allclose(rig.dirs, rig2.dirs)
    tri = TriangleFrameWarp().map(av, inp, cam, pix, rt)
    ok = tri.valid
    assert 10 < int(ok.sum()) < len(pix)
    # the same canonical line and direction, unit scale, same rotation where the ray hits the mesh
    assert torch.allclose(rig.dirs[ok], tri.dirs[ok], atol=1e-4)
    assert torch.allclose(rig.origins[ok], tri.origins[ok], atol=1e-4)
    assert torch.allclose(tri.scale[ok], torch.ones_like(tri.scale[ok]), atol=1e-4)
    assert torch.allclose(rig.rotation[ok], tri.rotation[ok], atol=1e-4)
    auto = AutoWarp()
    a = auto.map(av, inp, cam, pix, rt)
    assert torch.equal(a.origins, rig.origins) and bool(a.valid.all())
    b = auto.map(av, inp, cam, pix, None)
    assert torch.equal(b.valid, tri.valid)


def test_triangle_warp_lands_on_the_canonical_mesh(avatar):
    """On a non-rigid frame (a test head pose with eye motion), a hit maps to the same triangle and
    barycentrics of the canonical mesh, and agrees with the ray-warp reference of ``train.warp``."""
    av, data = avatar
    fr = data.train[1]
    inp = av.frame_inputs(fr.timestep)
    assert av.rigid_transform(inp) is None
    with pytest.raises(ValueError, match="not a rigid motion"):
        RigidFlameWarp().map(av, inp, RenderCamera.from_camera(fr.camera), torch.arange(4))
    cam = RenderCamera.from_camera(fr.camera)
    pix = torch.arange(0, cam.width * cam.height, 5)
    r = TriangleFrameWarp().map(av, inp, cam, pix)
    ok = r.valid
    assert int(ok.sum()) > 20 and not bool(ok.all())
    assert torch.equal(r.face_id >= 0, ok)
    assert torch.isinf(r.hit_distance[~ok]).all()
    with torch.no_grad():
        verts = av.pose_mesh(inp)
        ras = rasterize_mesh(verts, av.faces, cam.K, cam.w2c, cam.width, cam.height)
    bary = ras.bary.reshape(-1, 3)[pix][ok]
    hit_c = points_on_mesh(av.canonical_vertices, av.faces, r.face_id[ok], bary)
    on_ray = r.origins[ok] + (r.hit_distance[ok] * r.scale[ok])[:, None] * r.dirs[ok]
    assert torch.allclose(on_ray, hit_c, atol=1e-5)
    assert torch.allclose(r.dirs.norm(dim=-1), torch.ones(len(pix)), atol=1e-5)
    ref = warp_pixels_to_canonical(verts, av.faces, (av.R_c, av.T_c, av.k_c), cam.K, cam.w2c, cam.width, cam.height, pix)
    assert torch.equal(ref.valid, ok)
    assert torch.allclose(ref.origins[ok], r.origins[ok], atol=1e-5)
    assert torch.allclose(ref.dirs[ok], r.dirs[ok], atol=1e-5)
    assert torch.allclose(ref.scale[ok], r.scale[ok], atol=1e-5)
    assert torch.allclose(ref.rotation[ok], r.rotation[ok], atol=1e-5)
    # the automatic warp picks the triangle warp for this frame
    assert torch.equal(AutoWarp().map(av, inp, cam, pix, None).origins, r.origins)


def test_phase1_adapter_and_factory(avatar):
    from sage_core.train.phase1 import CanonicalRays

    av, data = avatar
    fr = data.train[0]
    inp = av.frame_inputs(fr.timestep)
    cam = RenderCamera.from_camera(fr.camera)
    pix = torch.arange(0, cam.width * cam.height, 11)
    o, d, s, rot, ok = CanonicalRays(av).map(inp, cam, pix, None)
    ref = TriangleFrameWarp().map(av, inp, cam, pix)
    assert torch.equal(o, ref.origins) and torch.equal(ok, ref.valid) and torch.equal(rot, ref.rotation)
    for name, cls in (("auto", AutoWarp), ("rigid", RigidFlameWarp), ("triangle", TriangleFrameWarp)):
        w = make_warp(name)
        assert isinstance(w, cls) and isinstance(w, CanonicalWarp)
    with pytest.raises(ValueError, match="unknown canonical warp"):
        make_warp("learned")
