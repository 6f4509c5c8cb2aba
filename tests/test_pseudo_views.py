"""One-shot pseudo-views: mirror view, per-face textures, textured ring, build_pseudo_views.

The one-shot workspace used here (and by tests/test_eval_novel.py) is conftest's ``oneshot_ws``: a
tiny synthetic ``--regime oneshot`` capture (3 held-out cameras, 1 held-out expression) ingested as
``one-shot`` with a reduced init-mesh, built once per test session.
"""

from __future__ import annotations

import copy
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from sage_core.config import PseudoViewConfig
from sage_core.train.pseudo_views import (
    FaceTexture,
    MirrorViewProvider,
    TexturedRingProvider,
    build_pseudo_views,
    head_yaw,
    mirror_camera,
    mirror_index_of,
    mirror_vertices,
    project_input,
    render_texture,
    ring_cameras,
    sample_barycentrics,
    texture_lookup,
)

_D = PseudoViewConfig()  # the defaults the providers read without a config


@pytest.fixture(scope="module")
def setup(oneshot_ws):
    from sage_core.config import resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.train.phase1 import build_avatar
    from sage_core.workspace import Workspace

    w = Workspace(oneshot_ws)
    data = IngestedData.open(w.stage_dir("ingest"))
    cfg = resolve_config("phase1", "tiny", None, {"n_surfels": 300, "app_hidden": 16, "shape_hidden": 16})
    avatar = build_avatar(data, w.stage_dir("init-mesh"), cfg, "cpu", torch.Generator().manual_seed(0))
    mirror_index, reason = mirror_index_of(avatar)
    assert mirror_index is not None, reason
    proj = project_input(data, avatar, 0, 4)
    return SimpleNamespace(data=data, avatar=avatar, mirror_index=mirror_index, proj=proj)


def test_texture_lookup_is_exact_for_linear_functions():
    r = 3
    B = sample_barycentrics(r)
    assert B.shape == ((r + 1) * (r + 2) // 2, 3)
    assert torch.allclose(B.sum(-1), torch.ones(len(B), dtype=B.dtype))
    g = torch.Generator().manual_seed(0)
    F = 5
    A = torch.randn(F, 3, 2, generator=g, dtype=torch.float64)  # per-face linear map of barycentrics
    values = torch.einsum("sk,fkc->fsc", B, A)
    P = 400
    fid = torch.randint(F, (P,), generator=g)
    bary = torch.rand(P, 3, generator=g, dtype=torch.float64) ** 2
    bary = bary / bary.sum(-1, keepdim=True)
    bary[:4] = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.5, 0.5, 0.0]], dtype=torch.float64)
    got = texture_lookup(values, fid, bary, r)
    want = torch.einsum("pk,pkc->pc", bary, A[fid])
    assert torch.allclose(got, want, atol=1e-10)
    # exact at the samples for arbitrary (non-linear) values
    vals = torch.randn(F, len(B), 1, generator=g, dtype=torch.float64)
    f2 = torch.arange(F).repeat_interleave(len(B))
    got = texture_lookup(vals, f2, B.repeat(F, 1), r)
    assert torch.allclose(got, vals.reshape(-1, 1), atol=1e-10)


def test_mirror_view_is_the_flipped_input(setup):
    data, avatar, proj = setup.data, setup.avatar, setup.proj
    prov = MirrorViewProvider(None, proj)
    (view,) = prov.views(data, avatar, setup.mirror_index)
    img = torch.as_tensor(data.load_image(data.train[0]))
    mask = torch.as_tensor(data.load_mask(data.train[0]))
    assert view.mirror is True and view.frame_index == 0 and view.name == "mirror"
    assert torch.equal(view.image, torch.flip(img, dims=[1]))
    assert torch.equal(view.mask, torch.flip(mask, dims=[1]))
    cam = data.train[0].camera
    np.testing.assert_allclose(view.camera.w2c, mirror_camera(cam).w2c)
    assert view.camera.K[0, 2] == pytest.approx(cam.width - cam.K[0, 2])
    assert view.weight.shape == mask.shape and float(view.weight.min()) >= 0.0 and float(view.weight.max()) <= 1.0
    # frontal input: the mirrored surface is already seen, so the foreground keeps little weight
    fg = view.mask > 0.5
    assert float(view.weight[fg].mean()) < 0.5 * (1.0 - _D.mirror_seen_weight)
    assert abs(prov.last_info["yaw_deg"]) < 2.0
    assert view.view_weight == pytest.approx(_D.mirror_weight * _D.mirror_yaw_floor, rel=0.05)
    # no mirror view without a mirror index or with the mirror switched off
    assert prov.views(data, avatar, None) == []
    assert MirrorViewProvider(SimpleNamespace(mirror=False), proj).views(data, avatar, setup.mirror_index) == []


def test_mirror_view_weighs_more_when_the_head_is_turned(setup):
    """A turned head (input re-rendered from the textured mesh) reveals surface the input does not
    see: the mirror view then carries more per-pixel weight and a larger view weight."""
    from sage_core.train.pseudo_views import InputProjection, backproject_texture

    data, avatar, proj = setup.data, setup.avatar, setup.proj
    tex = TexturedRingProvider(None, proj).complete_texture(data, avatar, setup.mirror_index, proj)
    base = avatar.frame_inputs(data.train[0].timestep)
    turned_inputs = dict(base)
    turned_inputs["rotation"] = torch.tensor([[0.0, math.radians(40.0), 0.0]])
    turned = copy.copy(avatar)
    turned.frame_inputs = lambda timestep: turned_inputs
    with torch.no_grad():
        verts = avatar.pose_mesh(turned_inputs)
    img, cover, _ = render_texture(verts, avatar.faces, tex, proj.camera, 1.0, 0.0, 1)
    tex2, pix2 = backproject_texture(verts, avatar.faces, proj.camera, img, cover, 4)
    proj2 = InputProjection(verts, tex2, pix2, img, cover, proj.camera, 0)
    front = MirrorViewProvider(None, proj)
    side = MirrorViewProvider(None, proj2)
    (vf,) = front.views(data, avatar, setup.mirror_index)
    (vs,) = side.views(data, turned, setup.mirror_index)
    assert abs(side.last_info["yaw_deg"]) == pytest.approx(40.0, abs=2.0)
    assert side.last_info["unseen_fraction"] > front.last_info["unseen_fraction"] + 0.1
    assert vs.view_weight == pytest.approx(_D.mirror_weight)  # beyond the full-weight yaw
    assert vs.view_weight > vf.view_weight
    fg_f, fg_s = vf.mask > 0.5, vs.mask > 0.5
    assert float(vs.weight[fg_s].mean()) > float(vf.weight[fg_f].mean()) + 0.1


def test_mirrored_mesh_seen_by_the_mirror_camera_matches_the_flipped_input(setup):
    """Depth of the mirrored posed mesh from the mirror camera = the input's depth, columns flipped."""
    from sage_core.render.mesh_raster import rasterize_mesh

    proj, avatar = setup.proj, setup.avatar
    cam, mc = proj.camera, mirror_camera(proj.camera)
    vm = mirror_vertices(proj.vertices, setup.mirror_index)
    d0 = rasterize_mesh(proj.vertices, avatar.faces, torch.as_tensor(cam.K).float(), torch.as_tensor(cam.w2c).float(), cam.width, cam.height).depth[0]
    d1 = rasterize_mesh(vm, avatar.faces, torch.as_tensor(mc.K).float(), torch.as_tensor(mc.w2c).float(), mc.width, mc.height).depth[0]
    d0 = torch.flip(d0, dims=[1])
    both = torch.isfinite(d0) & torch.isfinite(d1)
    assert float((torch.isfinite(d0) == torch.isfinite(d1)).float().mean()) > 0.998
    assert float((d1 - d0)[both].abs().median()) < 1e-4


def test_head_yaw_follows_the_global_rotation(setup):
    avatar, data = setup.avatar, setup.data
    inputs = avatar.frame_inputs(data.train[0].timestep)
    cam = data.train[0].camera
    assert abs(head_yaw(avatar, inputs, cam)) < math.radians(2.0)
    turned = dict(inputs)
    turned["rotation"] = torch.tensor([[0.0, math.radians(35.0), 0.0]])
    assert abs(abs(head_yaw(avatar, turned, cam)) - math.radians(35.0)) < math.radians(2.0)


def test_backprojected_texture_reproduces_the_input(setup):
    data, avatar, proj = setup.data, setup.avatar, setup.proj
    tex = TexturedRingProvider(None, proj).complete_texture(data, avatar, setup.mirror_index, proj)
    img, cover, w = render_texture(proj.vertices, avatar.faces, tex, proj.camera, 1.0, 0.0, 1)
    conf = w > 0.5
    assert int(conf.sum()) > 2000
    mse = ((img - proj.image)[conf] ** 2).mean()
    assert float(-10.0 * torch.log10(mse)) > 33.0
    # the coverage agrees with the ground-truth matte of the synthetic capture
    assert float(((cover > 0.5) == (proj.mask > 0.5)).float().mean()) > 0.97


def test_ring_weight_is_zero_where_nothing_is_known(setup):
    data, avatar, proj = setup.data, setup.avatar, setup.proj
    prov = TexturedRingProvider(None, proj)
    tex = prov.complete_texture(data, avatar, setup.mirror_index, proj)
    known = ((tex.source == FaceTexture.SEEN) | (tex.source == FaceTexture.MIRROR)).float()
    assert float(known.mean()) > 0.1 and float((tex.source == FaceTexture.INPAINTED).float().mean()) > 0.3
    indicator = FaceTexture(known[..., None].expand(-1, -1, 3).contiguous(), tex.confidence, tex.source, tex.resolution)
    nb = int(avatar.model_data.n_base_vertices)
    v = proj.vertices[:nb]
    centre = (0.5 * (v.max(0).values + v.min(0).values)).double().numpy()
    (back,) = ring_cameras(proj.camera, centre, 1, 180.0, 0.0)
    img, cover, w = render_texture(proj.vertices, avatar.faces, tex, back, 1.0, 0.0, 1)
    ind, _, _ = render_texture(proj.vertices, avatar.faces, indicator, back, 0.0, 0.0, 1)
    nothing = (cover > 0) & (ind[..., 0] == 0)
    assert float(nothing.float().sum()) > 0.5 * float((cover > 0).float().sum())  # the back of the head is unknown
    assert float(w[nothing].abs().max()) == 0.0
    assert float(w[cover == 0].abs().max()) == 0.0  # background weight 0 by default
    # from the input camera most of the head is constrained
    _, cover0, w0 = render_texture(proj.vertices, avatar.faces, tex, proj.camera, 1.0, 0.0, 1)
    assert float((w0[cover0 > 0] > 0.5).float().mean()) > 0.7


def test_build_pseudo_views_and_the_non_symmetric_fallback(setup):
    data, avatar = setup.data, setup.avatar
    cfg = SimpleNamespace(ring_views=2, ring_weight=0.3, ring_supersample=1)
    views, idx = build_pseudo_views(data, avatar, cfg)
    assert idx is not None and torch.equal(idx, setup.mirror_index)
    assert [v.name for v in views] == ["mirror", "ring00", "ring01"]
    H, W = data.train[0].camera.height, data.train[0].camera.width
    for v in views:
        assert v.image.shape == (H, W, 3) and v.mask.shape == (H, W) and v.weight.shape == (H, W)
        assert v.image.dtype == torch.float32 and v.weight.dtype == torch.float32
        assert float(v.image.min()) >= 0.0 and float(v.image.max()) <= 1.0
        assert v.frame_index == 0 and (v.camera.width, v.camera.height) == (W, H)
    ring = views[1:]
    assert all(not v.mirror and v.view_weight == pytest.approx(0.3) for v in ring)
    yaws = [v.camera.extra["yaw_deg"] for v in ring]
    assert yaws == pytest.approx([_D.ring_yaw_deg, -_D.ring_yaw_deg])
    # same distance to the head and the same intrinsics as the input
    c0 = data.train[0].camera
    for v in ring:
        np.testing.assert_allclose(v.camera.K, c0.K)
    # a model whose template is not symmetric: no mirror index, no mirror view, the ring still comes
    asym = copy.copy(avatar)
    md = copy.deepcopy(avatar.model_data)
    md.v_template[7, 0] += 0.01
    asym.model_data = md
    views2, idx2 = build_pseudo_views(data, asym, cfg)
    assert idx2 is None
    assert [v.name for v in views2] == ["ring00", "ring01"]


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_pseudo_views_on_cuda_match_cpu(setup):
    cfg = SimpleNamespace(ring_views=1, ring_supersample=1)
    cpu_views, _ = build_pseudo_views(setup.data, setup.avatar, cfg)
    gpu_avatar = copy.deepcopy(setup.avatar).to("cuda")
    gpu_views, idx = build_pseudo_views(setup.data, gpu_avatar, cfg)
    assert idx is not None and idx.device.type == "cuda"
    assert [v.name for v in gpu_views] == [v.name for v in cpu_views]
    for a, b in zip(cpu_views, gpu_views):
        assert b.image.device.type == "cuda" and b.weight.device.type == "cuda"
        assert float((a.image - b.image.cpu()).abs().mean()) < 2e-3
        assert float((a.weight - b.weight.cpu()).abs().mean()) < 2e-3
