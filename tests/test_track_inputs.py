"""What ``sage track`` reads (images, folders, videos, camera rigs with COLMAP or transforms.json
calibrations), the crop windows and output cameras, the split rule and the capture files it writes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from track_helpers import write_png

from sage_core.data.cameras import Camera, camera_to_nerf_frame, look_at
from sage_core.errors import ConfigError, InputError
from sage_core.track.camera_files import read_cameras
from sage_core.track.config import resolve_track_config
from sage_core.track.inputs import read_rgb, read_source
from sage_core.track.observe import MONOCULAR_W2C, crop_window


def _img(h: int = 48, w: int = 32, v: float = 0.5) -> np.ndarray:
    rng = np.random.default_rng(0)
    return np.clip(rng.random((h, w, 3)) * 0.2 + v, 0, 1).astype(np.float32)


def test_single_image_folder_and_sizes(tmp_path):
    p = write_png(tmp_path / "me.png", _img())
    src = read_source(p)
    assert src.kind == "image" and src.timesteps == ["me"] and (src.views[0].width, src.views[0].height) == (32, 48)
    (tmp_path / "seq").mkdir()
    for i in range(3):
        write_png(tmp_path / "seq" / f"f{i:02d}.png", _img())
    src = read_source(tmp_path / "seq", max_frames=2)
    assert src.kind == "images" and src.timesteps == ["f00", "f02"]
    t, img = next(src.frames(0))
    assert t == "f00" and img.shape == (48, 32, 3) and img.dtype == np.float32
    write_png(tmp_path / "seq" / "f03.png", _img(40, 40))
    with pytest.raises(InputError, match="differ in size"):
        read_source(tmp_path / "seq")
    with pytest.raises(InputError, match="input not found"):
        read_source(tmp_path / "missing.png")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="unknown input type") as e:
        read_source(tmp_path / "notes.txt")
    assert "HEIF" not in str(e.value)
    (tmp_path / "IMG_0001.HEIC").write_bytes(b"\x00\x00\x00\x18ftypheic")
    with pytest.raises(InputError, match="export it as JPEG"):
        read_source(tmp_path / "IMG_0001.HEIC")
    with pytest.raises(ConfigError, match="cameras file goes with a folder"):
        read_source(p, cameras=tmp_path / "transforms.json")


def test_exif_focal_and_orientation_from_a_jpeg(tmp_path):
    import OpenImageIO as oiio

    img = (_img(40, 60) * 255).astype(np.uint8)
    path = tmp_path / "phone.jpg"
    spec = oiio.ImageSpec(60, 40, 3, oiio.UINT8)
    spec.attribute("Orientation", 6)
    spec.attribute("Exif:FocalLengthIn35mmFilm", 26)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(img)
    out.close()
    pixels = read_rgb(path)
    assert pixels.shape == (60, 40, 3) and pixels.dtype == np.float32  # stored landscape, shown portrait
    src = read_source(path)
    assert (src.views[0].width, src.views[0].height) == (40, 60) and src.views[0].exif_focal == pytest.approx(26 / 36 * 60)


def test_images_with_alpha_or_grey_become_rgb_on_white(tmp_path):
    from sage_core.data.imageio import write_image

    rgba = np.zeros((4, 6, 4), np.float32)
    rgba[..., :3] = 0.2
    rgba[:, :3, 3] = 1.0  # left half opaque, right half transparent
    write_image(tmp_path / "cut_out.png", rgba, bits=16)
    rgb = read_rgb(tmp_path / "cut_out.png")
    assert rgb.shape == (4, 6, 3) and np.allclose(rgb[:, :3], 0.2, atol=1e-4) and np.allclose(rgb[:, 3:], 1.0)
    ga = np.stack([np.full((4, 6), 0.4), rgba[..., 3]], -1).astype(np.float32)
    write_image(tmp_path / "grey_alpha.png", ga, bits=16)
    grey = read_rgb(tmp_path / "grey_alpha.png")
    assert grey.shape == (4, 6, 3) and np.allclose(grey[:, :3], 0.4, atol=1e-4) and np.allclose(grey[:, 3:], 1.0)
    write_image(tmp_path / "grey.png", ga[..., 0], bits=16)
    assert read_rgb(tmp_path / "grey.png").shape == (4, 6, 3)
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(40))
    with pytest.raises(InputError) as e:
        read_rgb(tmp_path / "broken.png")
    assert e.value.path == tmp_path / "broken.png" and "image" in str(e.value)


def test_video_frames_fps_and_corrupt_files(tmp_path):
    from sage_core.export.video import VideoWriter

    path = tmp_path / "clip.mp4"
    with VideoWriter(path, fps=10, width=32, height=24) as vw:
        for i in range(10):
            vw.write(np.full((24, 32, 3), i / 10, np.float32))
    src = read_source(path, fps=5)
    assert src.kind == "video" and src.video_frames == [0, 2, 4, 6, 8] and src.fps == pytest.approx(5)
    frames = list(src.frames(0))
    assert [t for t, _ in frames] == ["frame_00000", "frame_00002", "frame_00004", "frame_00006", "frame_00008"]
    assert frames[1][1].mean() == pytest.approx(0.2, abs=0.03)
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 20)
    with pytest.raises(InputError) as e:
        read_source(bad)
    assert e.value.path == bad
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 3])
    with pytest.raises(InputError):
        read_source(cut)


def test_phone_video_with_display_rotation_comes_upright(tmp_path, caplog):
    """A phone films portrait as a landscape stream with a display rotation: frames come as shown."""
    import logging
    import subprocess

    import imageio_ffmpeg

    from sage_core.export.video import VideoWriter

    coded = np.zeros((32, 48, 3), np.float32)
    coded[:, :, 0] = np.linspace(0, 1, 48)[None, :]  # red rises to the right
    coded[:, :, 1] = np.linspace(0, 1, 32)[:, None]  # green rises downwards
    landscape = tmp_path / "coded.mp4"
    with VideoWriter(landscape, fps=10, width=48, height=32) as vw:
        for _ in range(3):
            vw.write(coded)
    phone = tmp_path / "phone.mp4"
    run = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-display_rotation", "90", "-i", str(landscape),
                          "-c", "copy", str(phone)], capture_output=True, check=False)
    if run.returncode != 0:
        pytest.skip("this ffmpeg cannot set a display rotation")
    with caplog.at_level(logging.WARNING):
        src = read_source(phone)
        (_, img), *_ = list(src.frames(0))
    assert img.shape == (48, 32, 3)
    # 90 degrees counter-clockwise: the coded image's right edge is now at the top
    assert np.abs(img - np.rot90(coded, 1)).mean() < 0.05
    assert not [r for r in caplog.records if r.name.startswith("imageio_ffmpeg")]


def _rig(n: int = 3) -> list[Camera]:
    cams = []
    for i in range(n):
        yaw = math.radians(-20 + 20 * i)
        eye = np.array([math.sin(yaw), 0.05, math.cos(yaw)])
        K = np.array([[300.0 + i, 0, 31.5], [0, 301.0, 40.2], [0, 0, 1]])
        cams.append(Camera(K, look_at(eye, np.zeros(3)), 64, 80, i, f"cam{i}"))
    return cams


def _rig_folders(root, cams, timesteps=("00000", "00001")):
    for c in cams:
        for t in timesteps:
            write_png(root / f"cam_{c.index:02d}" / f"{t}.png", _img(c.height, c.width))


def test_vhap_transforms_rig(tmp_path):
    cams = _rig()
    frames = [{"timestep_index": 0, "camera_index": c.index, "camera_id": f"22{c.index}", **camera_to_nerf_frame(c),
               "file_path": f"images/00000_{c.index:02d}.png"} for c in cams]
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames}))
    _rig_folders(tmp_path / "in", cams)
    src = read_source(tmp_path / "in", cameras=tmp_path / "transforms.json")
    assert src.kind == "multiview" and src.metric is True and src.timesteps == ["00000", "00001"]
    for c, v in zip(cams, src.views):
        assert v.index == c.index and np.allclose(v.calibrated.K, c.K) and np.allclose(v.calibrated.w2c, c.w2c)
    (tmp_path / "in" / "cam_09").mkdir()
    write_png(tmp_path / "in" / "cam_09" / "00000.png", _img(80, 64))
    with pytest.raises(InputError, match="no camera of"):
        read_source(tmp_path / "in", cameras=tmp_path / "transforms.json")


def test_nerf_transforms_with_shared_intrinsics(tmp_path):
    cams = _rig(2)
    frames = []
    for c in cams:
        c2w = np.linalg.inv(c.w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"images/cam{c.index}/00000.png", "transform_matrix": c2w.tolist()})
    doc = {"fl_x": 300.0, "fl_y": 301.0, "cx": 31.5, "cy": 40.2, "w": 64, "h": 80, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    cs = read_cameras(tmp_path / "transforms.json")
    assert cs.metric is False and [c.names[0] for c in cs.cameras] == ["cam0", "cam1"]
    assert np.allclose(cs.cameras[1].camera.w2c, cams[1].w2c) and cs.cameras[0].camera.K[1, 2] == pytest.approx(40.2)


def _quat(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def test_colmap_text_model(tmp_path):
    cams = _rig()
    lines_c = ["# Camera list", "1 PINHOLE 64 80 300 301 31.5 40.2", "2 SIMPLE_RADIAL 64 80 302 32 40 0.01"]
    lines_i = ["# Image list"]
    for k, c in enumerate(cams):
        q = _quat(c.w2c[:3, :3])
        t = c.w2c[:3, 3]
        cid = 1 if k < 2 else 2
        lines_i.append(f"{k + 1} {' '.join(map(str, q))} {' '.join(map(str, t))} {cid} cam_{k:02d}/00000.png")
        lines_i.append("10.0 20.0 -1 11.5 21.25 7")
    model = tmp_path / "sparse"
    model.mkdir()
    (model / "cameras.txt").write_text("\n".join(lines_c) + "\n")
    (model / "images.txt").write_text("\n".join(lines_i) + "\n")
    cs = read_cameras(model)
    assert [c.names[0] for c in cs.cameras] == ["cam_00", "cam_01", "cam_02"] and not cs.metric
    for c, ref in zip(cs.cameras, cams):
        assert np.allclose(c.camera.w2c, ref.w2c, atol=1e-9)
    assert cs.cameras[0].distortion is None and cs.cameras[2].distortion[0] == pytest.approx(0.01)
    assert cs.cameras[2].camera.K[0, 0] == pytest.approx(302)
    _rig_folders(tmp_path / "in", cams)
    src = read_source(tmp_path / "in", cameras=model / "images.txt")
    assert [v.index for v in src.views] == [0, 1, 2] and src.metric is False
    (model / "cameras.txt").write_text("1 FISHEYE 64 80 300 31 40 0.1\n")
    with pytest.raises(InputError, match="not supported"):
        read_cameras(model)


def test_camera_folders_need_a_cameras_file(tmp_path):
    _rig_folders(tmp_path / "in", _rig())
    with pytest.raises(InputError, match="no cameras file"):
        read_source(tmp_path / "in")


def test_crop_window_and_output_camera():
    cfg = resolve_track_config("default", None, {"max_height": 200})
    boxes = [np.array([300.0, 200.0, 400.0, 330.0]), np.array([310.0, 205.0, 410.0, 335.0])]
    win = crop_window(boxes, (1280, 720), cfg)
    assert win.out_h == 200 and 0 <= win.x0 and win.x0 + win.w <= 1280 and 0 <= win.y0 and win.y0 + win.h <= 720
    assert abs(win.w / win.h - cfg.crop_aspect) < 0.02
    for b in boxes:  # every face inside the window
        assert win.x0 <= b[0] and b[2] <= win.x0 + win.w and win.y0 <= b[1] and b[3] <= win.y0 + win.h
    K = np.array([[900.0, 0, 640], [0, 900, 360], [0, 0, 1]])
    cam = win.camera(K, MONOCULAR_W2C, 0, "monocular")
    src = Camera(K, MONOCULAR_W2C, 1280, 720)
    pts = np.array([[0.01, 0.02, 0.1], [-0.05, 0.03, -0.02]])
    uv_in, _ = src.project(pts)
    uv_out, _ = cam.project(pts)
    assert np.allclose(win.points(uv_in), uv_out)
    img = np.zeros((720, 1280, 3), np.float32)
    assert win.apply(img).shape == (win.out_h, win.out_w, 3)
    whole = crop_window(boxes, (1280, 720), resolve_track_config("default", None, {"crop": "false"}))
    assert (whole.x0, whole.y0, whole.w, whole.h, whole.out_h) == (0, 0, 1280, 720, 720)


def test_split_rule_and_written_capture_reads_back(tmp_path):
    from sage_core.data.capture import read_capture
    from sage_core.flame.params import FlameParams
    from sage_core.track.capture_writer import OutFrame, split_of, write_flame_params, write_transforms

    assert [split_of(t, 10, 0.7, 0, None) for t in range(10)] == ["train"] * 7 + ["test"] * 3
    assert split_of(1, 6, 1 / 3, 0, None) == "train" and split_of(2, 6, 1 / 3, 0, None) == "test"
    assert split_of(0, 4, 0.7, 8, 8) == "val" and split_of(3, 4, 0.7, 8, 8) == "test"
    cams = _rig(2)
    T = 3
    frames = [OutFrame(t, c.index, c.name, c, f"f{t}", t) for t in range(T) for c in cams]
    for f in frames:
        write_png(tmp_path / "images" / f"{f.name}.png", _img(80, 64))
        write_png(tmp_path / "fg_masks" / f"{f.name}.png", np.ones((80, 64), np.float32))
    rng = np.random.default_rng(1)
    params = FlameParams(shape=rng.normal(size=300).astype(np.float32), expr=rng.normal(size=(T, 100)).astype(np.float32),
                         **{k: rng.normal(size=(T, 3)).astype(np.float32) * 0.1 for k in ("rotation", "neck_pose", "jaw_pose", "translation")},
                         eyes_pose=np.zeros((T, 6), np.float32), static_offset=np.zeros((10, 3), np.float32), dynamic_offset=None,
                         timesteps=np.arange(T))
    write_flame_params(tmp_path, params)
    counts = write_transforms(tmp_path, frames, T, 0.7, 1)
    assert counts == {"train": 3, "val": 3, "test": 0}
    cap = read_capture(tmp_path)
    assert cap.params.n_timesteps == T and np.allclose(cap.params.expr, params.expr)
    assert np.allclose(cap.cameras[1].K, cams[1].K) and np.allclose(cap.cameras[0].w2c, cams[0].w2c)
    assert {f.split for f in cap.frames if f.camera_index == 1} == {"val"}
    assert cap.canonical is not None and np.allclose(cap.canonical.jaw_pose, [[0.3, 0, 0]])
    doc = json.loads((tmp_path / "transforms_train.json").read_text())
    assert doc["frames"][0]["timestep_id"] == "f0" and doc["frames"][0]["fg_mask_path"].startswith("fg_masks/")


class _Source:
    """A stand-in for TrackSource: ``kind`` and frames of one view."""

    def __init__(self, kind: str, n: int, views: int = 1) -> None:
        from sage_core.track.inputs import SourceView

        self.kind, self.path = kind, Path("input")
        self.views = [SourceView(f"v{i}", i, 8, 8, files={f"t{k}": Path(f"t{k}.png") for k in range(n)}) for i in range(views)]
        self.timesteps = [f"t{k}" for k in range(n)]

    def frames(self, view: int):
        for t in self.timesteps:
            yield t, np.zeros((8, 8, 3), np.float32)


class _Observer:
    """Records what each call was given; frame t1 is cut off by the image's edge."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, bool, str]] = []

    def __call__(self, img, near, previous, follow):
        from sage_core.track.detector import Detection
        from sage_core.track.faces import FaceObservation, FaceProblem

        t = f"t{len(self.calls) % 3}"
        self.calls.append((t, previous is not None, follow))
        if t == "t1":
            raise FaceProblem("cut-off", "the face runs out of the 8x8 image")
        lm = np.full((468, 2), 4.0)
        return FaceObservation(lm, 0.9, Detection(0.9, np.array([2.0, 2, 6, 6]), np.zeros((6, 2))))


def test_a_sequences_frames_are_followed_and_cut_off_frames_dropped():
    """A video or folder of frames hands each frame the last kept landmarks and the follow mode; a
    frame cut off by the edge is dropped with its kind; a rig is never followed; one photo cut off is
    an input error naming it."""
    from sage_core.track.observe import observe

    cfg = resolve_track_config("tiny", None, {})
    for kind in ("video", "images"):
        obs = _Observer()
        res = observe(_Source(kind, 3), obs, cfg)
        assert obs.calls == [("t0", False, "fallback"), ("t1", True, "fallback"), ("t2", True, "fallback")]
        assert res.kept == ["t0", "t2"] and [(d.timestep_id, d.kind) for d in res.dropped] == [("t1", "cut-off")]
    obs = _Observer()
    observe(_Source("video", 3), obs, resolve_track_config("tiny", None, {"follow_landmarks": "first"}))
    assert {c[2] for c in obs.calls} == {"first"}
    obs = _Observer()
    observe(_Source("multiview", 3, views=2), obs, cfg)
    assert {c[2] for c in obs.calls} == {"off"}
    with pytest.raises(InputError, match="runs out of"):
        observe(_Source("image", 2), _Observer(), cfg)
