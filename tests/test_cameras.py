"""OpenCV cameras and the VHAP (OpenGL c2w, flipped cy) conversion."""

from __future__ import annotations

import numpy as np

from sage_core.data.cameras import Camera, camera_from_nerf_frame, camera_to_nerf_frame, look_at


def _camera():
    w2c = look_at(np.array([0.25, 0.05, 1.0]), np.array([0.0, 0.02, 0.0]))
    K = np.array([[520.0, 0, 61.0], [0, 530.0, 97.0], [0, 0, 1]])
    return Camera(K, w2c, 128, 186, index=3, name="cam3")


def test_nerf_round_trip_and_flipped_cy():
    cam = _camera()
    frame = camera_to_nerf_frame(cam)
    assert frame["cy"] == 186 - 97.0 and frame["cx"] == 61.0
    back = camera_from_nerf_frame({**frame, "camera_index": 3})
    assert np.allclose(back.w2c, cam.w2c) and np.allclose(back.K, cam.K) and back.index == 3


def test_opengl_axes_convention():
    # An OpenGL c2w with identity rotation at z = 1 looks down -z: the origin is in front of it.
    frame = {"transform_matrix": np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1.0], [0, 0, 0, 1]]).tolist(),
             "fl_x": 100.0, "fl_y": 100.0, "cx": 50.0, "cy": 30.0, "w": 100, "h": 80}
    cam = camera_from_nerf_frame(frame)
    uv, z = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]]))
    assert z[0] == 1.0
    assert np.allclose(uv[0], [50.0, 80 - 30.0])  # principal point with cy un-flipped
    assert uv[1, 1] < uv[0, 1]  # world +y (up) goes up in the image (smaller v)


def test_resize_rescales_intrinsics():
    cam = _camera()
    pts = np.random.default_rng(0).normal(0, 0.05, (20, 3))
    uv, _ = cam.project(pts)
    small = cam.resized(64, 93)
    uv2, _ = small.project(pts)
    assert np.allclose(uv2[:, 0], uv[:, 0] * 0.5) and np.allclose(uv2[:, 1], uv[:, 1] * 93 / 186)


def test_look_at_centre_and_dict_round_trip():
    cam = _camera()
    assert np.allclose(cam.center, [0.25, 0.05, 1.0])
    uv, z = cam.project(np.array([[0.0, 0.02, 0.0]]))
    assert z[0] > 0 and np.allclose(uv[0], cam.K[:2, 2])
    assert np.allclose(Camera.from_dict(cam.to_dict()).w2c, cam.w2c)


def test_look_at_keeps_world_up_up_and_right_right():
    w2c = look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3))
    cam = Camera(np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]), w2c, 100, 100)
    uv, _ = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [0.1, 0.0, 0.0]]))
    assert uv[1, 1] < uv[0, 1]  # +y (up) is higher in the image
    assert uv[2, 0] > uv[0, 0]  # +x is to the right for a camera on +z
    assert np.isclose(np.linalg.det(w2c[:3, :3]), 1.0)
