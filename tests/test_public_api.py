"""The flat public API (``import sage_core as sage``): cheap import, loading, posing and rendering an
avatar through it, and agreement with the lower-level calls it wraps."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import sage_core as sage


def test_import_is_cheap_and_names_load_lazily():
    code = (
        "import sys, sage_core as sage\n"
        "assert 'torch' not in sys.modules, 'import sage_core pulled in torch'\n"
        "assert sage.PRESETS and 'tiny' in sage.PRESETS\n"
        "assert 'torch' not in sys.modules, 'config access pulled in torch'\n"
        "assert callable(sage.load_avatar) and callable(sage.render_avatar)\n"
        "import sage_core.render\n"
        "assert callable(sage.render_avatar)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    for name in sage.__all__:
        assert getattr(sage, name) is not None, name
    with pytest.raises(AttributeError):
        sage.no_such_name  # noqa: B018


def test_public_names_are_documented():
    for name in ("load_avatar", "render_avatar", "load_cameras", "reference_camera", "load_flame_params"):
        doc = getattr(sage, name).__doc__ or ""
        assert len(doc) > 80, name
    assert "(H, W, 3)" in (sage.RenderOutput.__doc__ or "")
    assert "(N, 3)" in (sage.Avatar.pose.__doc__ or "")


def test_stage_names_are_the_stage_functions():
    from sage_core import stages

    assert sage.run_pipeline is stages.run_pipeline and sage.StageSettings is stages.StageSettings
    assert sage.workspace_regime is stages.workspace_regime and sage.StageEvent is stages.StageEvent


def test_config_names_are_the_engines():
    from sage_core import config

    assert sage.resolve_config is config.resolve_config
    assert sage.load_config is config.load_config_file
    assert sage.resolve_config("phase1", "tiny") == config.resolve_config("phase1", "tiny")


@pytest.fixture(scope="module")
def avatar(tiny_avatar_ws):
    return sage.load_avatar(tiny_avatar_ws)


def _lower_level(avatar, camera, inputs, background=None):
    """The same frame through Avatar.render with the stage's render settings."""
    s = avatar.render_settings
    cam = sage.RenderCamera.from_camera(camera)
    bg = s.background if background is None else background
    with torch.no_grad():
        out, _ = avatar.render(cam, inputs, bg, near=s.near, far=s.far, backend="torch")
    return out


def test_load_avatar_from_a_workspace_and_from_its_file(tiny_avatar_ws, avatar):
    assert isinstance(avatar, sage.Avatar)
    assert not avatar.training
    assert avatar.render_settings is not None and avatar.render_settings.correction is None
    again = sage.load_avatar(tiny_avatar_ws / "phase1" / "avatar.pt")
    assert torch.equal(again.surfels.mu_loc, avatar.surfels.mu_loc)
    with pytest.raises(sage.InputError):
        sage.load_avatar(tiny_avatar_ws / "nothing-here")


def test_cameras(tiny_avatar_ws):
    cams = sage.load_cameras(tiny_avatar_ws)
    assert cams and all(isinstance(c, sage.Camera) for c in cams.values())
    ref = sage.reference_camera(tiny_avatar_ws)
    assert ref.index in cams


def test_render_has_the_right_shapes_and_matches_avatar_render(tiny_avatar_ws, avatar):
    cam = sage.reference_camera(tiny_avatar_ws)
    out = sage.render_avatar(avatar, cam, backend="torch")
    H, W = cam.height, cam.width
    assert out.image.shape == (H, W, 3) and out.alpha.shape == (H, W)
    assert out.depth.shape == (H, W) and out.normal.shape == (H, W, 3)
    assert out.image.dtype == torch.float32
    fg = out.alpha > 0.5
    assert int(fg.sum()) > 20, "the avatar should cover part of the image"
    assert torch.allclose(out.normal[fg].norm(dim=-1), torch.ones(int(fg.sum())), atol=1e-4)
    assert float(out.depth[fg].min()) > 0
    ref = _lower_level(avatar, cam, avatar.frame_inputs(avatar.canonical_timestep))
    assert torch.allclose(out.image, ref.color, atol=1e-6)
    assert torch.allclose(out.alpha, ref.alpha, atol=1e-6)
    assert torch.allclose(out.depth, ref.depth, atol=1e-6)


def test_expression_overrides_pose_and_render_like_flame_inputs(tiny_avatar_ws, avatar):
    cam = sage.reference_camera(tiny_avatar_ws)
    E = avatar.params.n_expr
    expr = np.zeros(E, np.float32)
    expr[:3] = [1.5, -1.0, 0.8]
    jaw = [0.25, 0.0, 0.0]
    out = sage.render_avatar(avatar, cam, expr=expr[:3], jaw_pose=jaw, backend="torch")
    inputs = avatar.frame_inputs(avatar.canonical_timestep)
    inputs.pop("dynamic_offset", None)
    inputs["expr"] = torch.as_tensor(expr)[None]
    inputs["jaw_pose"] = torch.tensor([jaw])
    ref = _lower_level(avatar, cam, inputs)
    assert torch.allclose(out.image, ref.color, atol=1e-6)
    neutral = sage.render_avatar(avatar, cam, backend="torch")
    assert float((out.image - neutral.image).abs().max()) > 1e-3, "the expression should change the image"
    posed = avatar.pose(expr=expr[:3], jaw_pose=jaw)
    with torch.no_grad():
        assert torch.allclose(posed.vertices, avatar.pose_mesh(inputs), atol=1e-6)
    assert posed.means.shape == (len(avatar.surfels), 3) and posed.colors.shape == (len(avatar.surfels), 3)
    with pytest.raises(ValueError, match="jaw_pose"):
        avatar.pose(jaw_pose=[0.1, 0.2])
    with pytest.raises(ValueError, match="unknown FLAME parameter"):
        avatar.pose(smile=1.0)


def test_flame_params_of_a_motion_file(tiny_avatar_ws, avatar, tmp_path):
    E = avatar.params.n_expr
    T = 3
    rng = np.random.default_rng(0)
    arrays = {k: np.zeros((T, 3), np.float32) for k in ("rotation", "neck_pose", "jaw_pose", "translation")}
    arrays["expr"] = (0.5 * rng.standard_normal((T, E))).astype(np.float32)
    arrays["eyes_pose"] = np.zeros((T, 6), np.float32)
    np.savez(tmp_path / "motion.npz", **arrays)
    params = sage.load_flame_params(tmp_path / "motion.npz", n_expr=E)
    assert isinstance(params, sage.FlameParams) and params.n_timesteps == T
    cam = sage.reference_camera(tiny_avatar_ws)
    out = sage.render_avatar(avatar, cam, params, row=2, backend="torch")
    ref = _lower_level(avatar, cam, avatar.params_inputs(params, 2))
    assert torch.allclose(out.image, ref.color, atol=1e-6)
    p = avatar.pose(params, 1)
    with torch.no_grad():
        assert torch.allclose(p.means, avatar.posed(avatar.params_inputs(params, 1), None).means)
