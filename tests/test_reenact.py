"""Driving motions (GA npz, folder of per-timestep npz, capture), orbit cameras and reenactment output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from sage_core.data.cameras import Camera
from sage_core.data.imageio import read_image
from sage_core.errors import InputError
from sage_core.export.motion import DEFAULT_FPS, load_motion, orbit_cameras
from sage_core.export.reenact import reenact
from sage_core.flame.params import load_param_npz

V = 7


def _ga_arrays(T: int, E: int = 10, seed: int = 0, offsets: bool = True) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = {
        "expr": rng.normal(size=(T, E)),
        "rotation": rng.normal(scale=0.1, size=(T, 3)),
        "neck_pose": rng.normal(scale=0.1, size=(T, 3)),
        "jaw_pose": np.stack([np.linspace(0.0, 0.5, T), np.zeros(T), np.zeros(T)], 1),
        "eyes_pose": rng.normal(scale=0.1, size=(T, 6)),
        "translation": rng.normal(scale=0.01, size=(T, 3)),
    }
    if offsets:
        a["dynamic_offset"] = rng.normal(scale=1e-3, size=(T, V, 3))
    return {k: v.astype(np.float32) for k, v in a.items()}


def _camera(w: int = 20, h: int = 14) -> Camera:
    K = np.array([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]])
    return Camera(K, np.eye(4), w, h)


# --- motion sources ------------------------------------------------------------------------------


def test_ga_npz_round_trip(tmp_path):
    a = _ga_arrays(5)
    path = tmp_path / "motion.npz"
    np.savez(path, **a, shape=np.ones(300, np.float32), static_offset=np.ones((1, V, 3), np.float32),
             fps=np.float32(30.0))
    m = load_motion(path)
    assert m.source_kind == "npz" and m.n_frames == 5 and m.fps == 30.0 and m.cameras is None
    assert m.params.shape.shape == (0,) and m.params.static_offset is None  # identity ignored
    for k in ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation", "dynamic_offset"):
        np.testing.assert_array_equal(getattr(m.params, k), a[k])
    inp = m.frame_inputs(3, "cpu")
    assert set(inp) == {"expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation", "dynamic_offset"}
    assert inp["expr"].shape == (1, 10) and inp["eyes_pose"].shape == (1, 6)
    assert inp["dynamic_offset"].shape == (1, V, 3) and inp["jaw_pose"].dtype == torch.float32
    np.testing.assert_array_equal(inp["jaw_pose"].numpy(), a["jaw_pose"][3:4])
    with pytest.raises(IndexError):
        m.frame_inputs(5)


def test_ga_npz_default_fps_and_expr_fit(tmp_path):
    path = tmp_path / "m.npz"
    a = _ga_arrays(3, E=10, offsets=False)
    np.savez(path, **a)
    with pytest.raises(InputError, match="expression components"):  # non-zero columns are never dropped
        load_motion(path, n_expr=4)
    a["expr"][:, 4:] = 0
    np.savez(path, **a)
    m = load_motion(path, n_expr=4)
    assert m.fps == DEFAULT_FPS and m.params.expr.shape == (3, 4) and m.params.dynamic_offset is None
    np.testing.assert_array_equal(m.params.expr, a["expr"][:, :4])
    m = load_motion(path, n_expr=12)
    np.testing.assert_array_equal(m.params.expr[:, 10:], 0)
    assert "dynamic_offset" not in m.frame_inputs(0)


def test_t_mismatch_names_file_and_keys(tmp_path):
    a = _ga_arrays(5)
    a["jaw_pose"] = a["jaw_pose"][:4]
    a["dynamic_offset"] = a["dynamic_offset"][:3]
    path = tmp_path / "bad.npz"
    np.savez(path, **a)
    with pytest.raises(InputError) as err:
        load_motion(path)
    assert err.value.path == path
    msg = err.value.problem
    assert "'jaw_pose' has 4" in msg and "'dynamic_offset' has 3" in msg and "'expr' has 5" in msg


@pytest.mark.parametrize(
    "edit, needle",
    [
        (lambda a: a.pop("eyes_pose"), "lacks key(s) 'eyes_pose'"),
        (lambda a: a.__setitem__("rotation", np.zeros((5, 4), np.float32)), "'rotation' has shape (5, 4)"),
        (lambda a: a["expr"].__setitem__((2, 1), np.nan), "NaN"),
        (lambda a: a.__setitem__("fps", np.float32(-1)), "fps"),
    ],
)
def test_bad_motion_files(tmp_path, edit, needle):
    a = _ga_arrays(5)
    edit(a)
    path = tmp_path / "bad.npz"
    np.savez(path, **a)
    with pytest.raises(InputError) as err:
        load_motion(path)
    assert err.value.path == path and needle in err.value.problem


def test_missing_source(tmp_path):
    with pytest.raises(InputError):
        load_motion(tmp_path / "nope.npz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no FLAME parameter files"):
        load_motion(tmp_path / "empty")


def _write_folder(folder: Path, a: dict[str, np.ndarray], names: list[str]) -> None:
    folder.mkdir(parents=True)
    for i, name in enumerate(names):
        row = {k: v[i : i + 1] for k, v in a.items()}
        np.savez(folder / name, **row, shape=np.full(300, i, np.float32))  # shape varies: ignored


def test_folder_of_npz(tmp_path):
    a = _ga_arrays(4)
    names = ["00010.npz", "00002.npz", "00005.npz", "00007.npz"]
    _write_folder(tmp_path / "seq" / "flame_param", a, names)
    order = np.argsort(names)
    for src in (tmp_path / "seq", tmp_path / "seq" / "flame_param"):
        m = load_motion(src)
        assert m.source_kind == "flame_param_folder" and m.n_frames == 4
        np.testing.assert_array_equal(m.timesteps, [2, 5, 7, 10])
        np.testing.assert_array_equal(m.params.jaw_pose, a["jaw_pose"][order])
        np.testing.assert_array_equal(m.params.dynamic_offset, a["dynamic_offset"][order])
        assert m.params.shape.shape == (0,)


def test_folder_with_multi_row_file_rejected(tmp_path):
    a = _ga_arrays(3)
    folder = tmp_path / "f"
    folder.mkdir()
    np.savez(folder / "00000.npz", **{k: v[:1] for k, v in a.items()})
    np.savez(folder / "00001.npz", **a)
    with pytest.raises(InputError) as err:
        load_motion(folder)
    assert err.value.path == folder / "00001.npz" and "3 rows" in err.value.problem


def test_capture_source(tiny_capture):
    m = load_motion(tiny_capture)
    assert m.source_kind == "capture" and m.cameras is not None and len(m.cameras) == 16
    files = sorted((Path(tiny_capture) / "flame_param").glob("*.npz"))
    assert m.n_frames == len(files)
    np.testing.assert_array_equal(m.timesteps, np.arange(len(files)))
    for i, f in enumerate(files):
        ref = load_param_npz(f)
        np.testing.assert_allclose(m.params.expr[i], ref.expr[0])
        np.testing.assert_allclose(m.params.jaw_pose[i], ref.jaw_pose[0])
    assert m.params.static_offset is None and m.params.shape.shape == (0,)
    assert "shape" not in m.frame_inputs(0) and "static_offset" not in m.frame_inputs(0)


def test_orbit_cameras_look_at_centre():
    center = np.array([0.01, 0.02, -0.03])
    K = np.array([[200.0, 0, 31.0], [0, 210.0, 45.0], [0, 0, 1]])
    for elev, arc in ((0.0, 360.0), (20.0, 90.0), (-15.0, 360.0)):
        cams = orbit_cameras(center, 0.8, 12, K, 64, 90, elevation_deg=elev, arc_deg=arc)
        assert len(cams) == 12
        for c in cams:
            uv, z = c.project(center[None])
            np.testing.assert_allclose(uv[0], K[:2, 2], atol=1e-9)
            assert z[0] == pytest.approx(0.8)
            assert np.linalg.norm(c.center - center) == pytest.approx(0.8)
            R = c.w2c[:3, :3]
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0)
            # image "up" (-y) agrees with world up
            assert (-R[1]) @ np.array([0.0, 1.0, 0.0]) > 0
            assert (c.center - center)[1] == pytest.approx(0.8 * np.sin(np.radians(elev)))
    front = orbit_cameras(center, 1.0, 4, K, 64, 90)
    np.testing.assert_allclose(front[0].center, center + [0, 0, 1.0], atol=1e-12)  # starts in front (+z)
    np.testing.assert_allclose(front[2].center, center + [0, 0, -1.0], atol=1e-12)  # no repeated endpoint
    arc = orbit_cameras(center, 1.0, 3, K, 64, 90, arc_deg=90.0)
    np.testing.assert_allclose(arc[1].center, center + [0, 0, 1.0], atol=1e-12)  # centred on the front
    with pytest.raises(ValueError):
        orbit_cameras(center, 1.0, 3, K, 64, 90, elevation_deg=90.0)


# --- reenactment ---------------------------------------------------------------------------------


def _jaw_render(inputs: dict[str, torch.Tensor], cam: Camera) -> torch.Tensor:
    """Flat colour from the jaw value: red = 2·jaw_x, green 0.5, blue = 1 − 2·jaw_x."""
    j = float(inputs["jaw_pose"][0, 0]) * 2.0
    assert inputs["expr"].shape[0] == 1 and "shape" not in inputs
    return torch.tensor([j, 0.5, 1.0 - j]).expand(cam.height, cam.width, 3).clone()


def _motion(tmp_path: Path, T: int = 6):
    path = tmp_path / "motion.npz"
    np.savez(path, **_ga_arrays(T))
    return load_motion(path)


def test_reenact_png_and_video(tmp_path):
    import imageio_ffmpeg

    m = _motion(tmp_path)
    out = tmp_path / "out"
    calls: list[int] = []
    rep = reenact(_jaw_render, m, _camera(), out, frames_format="png", video=True,
                  progress=lambda d, n, msg: calls.append(d))
    assert rep.n_frames == 6 and rep.render_fps > 0 and rep.total_fps > 0 and rep.fps == DEFAULT_FPS
    assert rep.total_seconds >= rep.render_seconds
    assert calls == [1, 2, 3, 4, 5, 6]
    files = sorted((out / "frames").iterdir())
    assert [f.name for f in files] == [f"{i:05d}.png" for i in range(6)]
    for i, f in enumerate(files):
        img = read_image(f)
        assert img.shape == (14, 20, 3)
        j = 2.0 * float(m.params.jaw_pose[i, 0])
        np.testing.assert_allclose(img[5, 5], [j, 0.5, 1 - j], atol=1 / 255 + 1e-6)
    assert rep.video_path == out / "video.mp4"
    n, _ = imageio_ffmpeg.count_frames_and_secs(str(rep.video_path))
    assert n == 6
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary leftovers


def test_reenact_exr_per_frame_cameras(tmp_path):
    """EXR frames keep float values: off the 8-bit grid and above 1."""
    m = _motion(tmp_path)
    cams = [_camera(12, 10) for _ in range(6)]

    def render(inputs, cam):
        v = 0.1234 + 0.1 * float(inputs["jaw_pose"][0, 0])
        return torch.tensor([v, 0.5, 1.5]).expand(cam.height, cam.width, 3).clone()

    rep = reenact(render, m, cams, tmp_path / "o", frames_format="exr", video=False, fps=10)
    assert rep.video_path is None and not (tmp_path / "o" / "video.mp4").exists()
    assert rep.fps == 10 and rep.frame_format == "exr"
    files = sorted((tmp_path / "o" / "frames").glob("*.exr"))
    assert [f.name for f in files] == [f"{i:05d}.exr" for i in range(6)]
    for i in (0, 3, 5):
        img = read_image(files[i])
        assert img.dtype == np.float32 and img.shape == (10, 12, 3)
        v = 0.1234 + 0.1 * float(m.params.jaw_pose[i, 0])
        np.testing.assert_allclose(img[4, 7], [v, 0.5, 1.5], atol=1e-4)
        assert abs(round(v * 255) / 255 - v) > 2e-4  # an 8-bit file could not hold it


def test_reenact_replaces_old_frames(tmp_path):
    out = tmp_path / "o"
    (out / "frames").mkdir(parents=True)
    (out / "frames" / "00099.png").write_bytes(b"stale")
    reenact(_jaw_render, _motion(tmp_path, T=2), _camera(), out, video=False)
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["00000.png", "00001.png"]


def test_interrupted_run_leaves_no_video_or_partial_frames(tmp_path):
    m = _motion(tmp_path)
    out = tmp_path / "o"

    def failing(inputs, cam):
        if float(inputs["jaw_pose"][0, 0]) > 0.25:
            raise RuntimeError("boom")
        return _jaw_render(inputs, cam)

    with pytest.raises(RuntimeError, match="boom"):
        reenact(failing, m, _camera(), out)
    assert not (out / "video.mp4").exists() and not (out / "frames").exists()
    assert list(out.iterdir()) == []


def test_reenact_argument_errors(tmp_path):
    m = _motion(tmp_path)
    with pytest.raises(ValueError, match="cameras"):
        reenact(_jaw_render, m, [_camera()] * 5, tmp_path / "a")
    with pytest.raises(ValueError, match="frame size"):
        reenact(_jaw_render, m, [_camera()] * 5 + [_camera(22, 14)], tmp_path / "a")
    with pytest.raises(ValueError, match="nothing to write"):
        reenact(_jaw_render, m, _camera(), tmp_path / "a", frames_format="none", video=False)
    with pytest.raises(ValueError, match="frames_format"):
        reenact(_jaw_render, m, _camera(), tmp_path / "a", frames_format="jpg")
    with pytest.raises(ValueError, match="shape"):
        reenact(lambda i, c: torch.zeros(3, 3, 3), m, _camera(), tmp_path / "b", video=False)
    assert not (tmp_path / "b" / "frames").exists()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_reenact_on_cuda(tmp_path):
    m = _motion(tmp_path, T=3)

    def render(inputs, cam):
        assert inputs["jaw_pose"].is_cuda
        return _jaw_render(inputs, cam).cuda()

    rep = reenact(render, m, _camera(), tmp_path / "o", device="cuda")
    assert rep.n_frames == 3 and rep.render_fps > 0 and len(list((tmp_path / "o" / "frames").iterdir())) == 3
