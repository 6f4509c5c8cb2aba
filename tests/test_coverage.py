"""Coverage diagnostics: camera yaw/pitch relative to the head, range, narrow-clip warning."""

from __future__ import annotations

import numpy as np
import pytest

from sage_core.data.cameras import look_at
from sage_core.geometry.rotations import axis_angle_to_matrix
from sage_core.data.coverage import Coverage, camera_angles, coverage_of_frames


def _rot_y(deg: float) -> np.ndarray:
    import torch

    return axis_angle_to_matrix(torch.tensor([[0.0, np.deg2rad(deg), 0.0]], dtype=torch.float64))[0].numpy()


def test_camera_angles_of_a_turning_head():
    # camera fixed at +z, head turned by yaw ψ about y: the camera is at −ψ in the head's frame
    yaws = np.array([-60.0, -20.0, 0.0, 35.0, 70.0])
    R = np.stack([_rot_y(y) for y in yaws])
    C = np.tile([0.0, 0.0, 1.0], (len(yaws), 1))
    yaw, pitch = camera_angles(C, R, np.zeros((len(yaws), 3)))
    assert np.allclose(yaw, -yaws, atol=1e-9)
    assert np.allclose(pitch, 0.0, atol=1e-9)
    # a camera above the head, off-centre head
    yaw, pitch = camera_angles(np.array([[0.0, 0.6, 0.8]]) + 0.1, np.eye(3)[None], np.array([[0.1, 0.1, 0.1]]))
    assert yaw[0] == pytest.approx(0.0, abs=1e-9) and pitch[0] == pytest.approx(np.degrees(np.arctan2(0.6, 0.8)))
    # the subject's left (+x in FLAME) is positive yaw
    yaw, _ = camera_angles(np.array([[1.0, 0.0, 1.0]]), np.eye(3)[None], np.zeros((1, 3)))
    assert yaw[0] == pytest.approx(45.0)


def test_range_warning_and_round_trip():
    wide = Coverage(np.array([-50.0, 0.0, 48.0]), np.array([-5.0, 0.0, 7.0]), np.array([0, 1, 2]))
    assert not wide.narrow and wide.warning() is None
    assert wide.yaw_range == (-50.0, 48.0) and wide.pitch_range == (-5.0, 7.0)
    one_sided = Coverage(np.array([-10.0, 30.0, 80.0]), np.zeros(3), np.arange(3))
    assert one_sided.narrow
    msg = one_sided.warning()
    assert msg is not None and "-10°" in msg and "+80°" in msg and "±45°" in msg
    m = one_sided.metrics()
    assert m["coverage_yaw_min_deg"] == -10.0 and m["coverage_yaw_max_deg"] == 80.0 and m["coverage_narrow"] is True
    back = Coverage.from_dict(one_sided.to_dict())
    assert np.array_equal(back.yaw, one_sided.yaw) and back.narrow and back.threshold == 45.0
    assert "yaw -10° .. +80°" in one_sided.text()
    assert not Coverage(np.array([-31.0, 31.0]), np.zeros(2), np.arange(2), threshold=30.0).narrow


def test_coverage_of_a_synthetic_clip(tmp_path):
    """The synthetic monocular clip sweeps yaw ±60° in training and ±32° in its test part."""
    from sage_core.data.capture import fit_params_to_model, read_capture
    from sage_core.data.synthetic import make_capture
    from sage_core.data.synthetic.config import preset
    from sage_core.flame import load_flame_model

    cap_dir = make_capture(tmp_path / "cap", preset("tiny", regime="monocular", width=32, height=48, train_timesteps=5,
                                                     test_timesteps=2, novel_views=1, novel_expressions=1))
    cap = read_capture(cap_dir)
    model = load_flame_model(cap_dir.model_path)
    params = fit_params_to_model(cap.params, model.n_vertices, model.n_base_vertices)
    train = coverage_of_frames(model, params, [(f.timestep, f.camera) for f in cap.split("train")])
    lo, hi = train.yaw_range
    assert lo == pytest.approx(-60.0, abs=2.0) and hi == pytest.approx(60.0, abs=2.0)
    assert abs(train.pitch_range[0]) < 10 and abs(train.pitch_range[1]) < 10
    assert not train.narrow
    test = coverage_of_frames(model, params, [(f.timestep, f.camera) for f in cap.split("test")])
    assert test.narrow and test.warning() is not None
    # a camera looking at the head from its left side, with the head unturned
    t0 = int(cap.split("train")[0].timestep)
    side = look_at(np.array([1.0, 0.0, 0.0]), np.zeros(3))
    cam0 = cap.split("train")[0].camera
    from sage_core.data.cameras import Camera

    c = coverage_of_frames(model, params, [(t0, Camera(cam0.K, side, cam0.width, cam0.height))])
    R0 = _rot_y(np.degrees(params.rotation[params.row_of(t0)][1]))
    expected, _ = camera_angles(np.array([[1.0, 0.0, 0.0]]), R0[None], np.zeros((1, 3)))
    assert c.yaw[0] == pytest.approx(expected[0], abs=3.0)
