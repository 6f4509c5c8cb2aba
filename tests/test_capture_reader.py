"""Capture reader: VHAP single-sequence and union layouts, per-frame cameras, fallbacks.

The fake VHAP exports and the tiny fake FLAME model come from tests/fake_capture.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fake_capture import (
    BLOB,
    CX,
    CY_CV,
    FX,
    MODEL_V,
    N_EXPR,
    N_SHAPE,
    FakeSpec,
    H,
    W,
    make_camera,
    make_fake_capture,
    make_fake_union,
    project_manual,
    vhap_params,
    write_transforms,
)
from sage_core.data import read_capture
from sage_core.errors import InputError

# --------------------------------------------------------------------------------------------- tests


def test_single_sequence(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    cap = read_capture(root)
    assert cap.root == root.resolve()
    assert len(cap.split("train")) == 3 * 2 and len(cap.split("val")) == 3 and len(cap.split("test")) == 3
    assert cap.timesteps("train") == [0, 1, 2] and cap.timesteps("test") == [3]
    assert cap.camera_indices("train") == [0, 1] and cap.camera_indices("val") == [8]
    assert cap.params.n_timesteps == 4 and list(cap.params.timesteps) == [0, 1, 2, 3]
    assert cap.params.static_offset is not None and cap.params.static_offset.shape == (MODEL_V, 3)
    assert cap.params.shape.shape == (N_SHAPE,) and cap.params.expr.shape == (4, N_EXPR)
    ref = vhap_params(2)
    np.testing.assert_array_equal(cap.params.rotation[cap.params.row_of(2)], ref["rotation"][0])
    assert cap.canonical is not None and cap.canonical.jaw_pose[0, 0] == pytest.approx(0.3)
    assert cap.image_size == (W, H)
    assert cap.varying_cameras == [] and cap.warnings == []
    f = cap.split("train")[0]
    assert f.image_path == root.resolve() / "images" / f"{f.timestep:05d}_{f.camera_index:02d}.png"
    assert f.mask_path is not None and f.mask_path.is_file()
    assert f.param_path.name == f"{f.timestep:05d}.npz"
    assert f.camera_id == f"cam{f.camera_index:02d}"


def test_camera_conversion_honours_principal_point(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    cap = read_capture(root)
    for f in cap.frames:
        truth = make_camera(f.camera_index, 9)
        cam = f.camera
        # per-frame intrinsics (the top level says fl_x = 999), cy un-flipped, cx kept
        np.testing.assert_allclose(cam.K, truth.K, atol=1e-9)
        assert cam.K[1, 2] == pytest.approx(CY_CV) and cam.K[0, 2] == pytest.approx(CX)
        np.testing.assert_allclose(cam.w2c, truth.w2c, atol=1e-9)
        uv, z = cam.project(BLOB[None])
        assert z[0] > 0
        np.testing.assert_allclose(uv[0], project_manual(truth, BLOB), atol=1e-6)
        # the drawn blob is centred on that pixel in the stored image
        from sage_core.data import read_image

        img = read_image(f.image_path)
        dark = img[:, :, 0] < 0.5
        ys, xs = np.nonzero(dark)
        np.testing.assert_allclose([xs.mean() + 0.5, ys.mean() + 0.5], uv[0], atol=0.6)


def test_flipped_cy_is_not_the_opencv_value(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    doc = json.loads((root / "transforms_train.json").read_text())
    assert doc["frames"][0]["cy"] == pytest.approx(H - CY_CV)  # stored OpenGL-flipped
    cap = read_capture(root)
    assert cap.frames[0].camera.K[1, 2] == pytest.approx(CY_CV)


def test_union_layout(tmp_path: Path) -> None:
    union = make_fake_union(tmp_path, FakeSpec(n_train_timesteps=2))
    cap = read_capture(union)
    assert cap.timesteps("train") == [0, 1] and cap.timesteps("test") == [2, 3]
    for f in cap.frames:
        assert ".." not in f.image_path.parts
        assert f.image_path.is_file() and f.param_path.is_file()
        seq = "seq0" if f.split != "test" else "seq1"
        assert f.image_path.parent.parent == (tmp_path / seq).resolve()
    assert cap.params.n_timesteps == 4
    assert cap.canonical is not None


def test_fallback_to_transforms_json(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    frames = []
    for s in ("train", "val", "test"):
        p = root / f"transforms_{s}.json"
        frames += json.loads(p.read_text())["frames"]
        p.unlink()
    write_transforms(root / "transforms.json", frames)
    cap = read_capture(root)
    assert len(cap.split("train")) == len(frames) and cap.split("val") == []
    assert any("transforms.json" in w for w in cap.warnings)


def test_missing_val_file_is_a_warning(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    (root / "transforms_val.json").unlink()
    cap = read_capture(root)
    assert cap.split("val") == [] and any("transforms_val.json" in w for w in cap.warnings)


def test_per_frame_cameras_when_they_vary(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    p = root / "transforms_train.json"
    doc = json.loads(p.read_text())
    moved = [fr for fr in doc["frames"] if fr["camera_index"] == 1 and fr["timestep_index"] == 2][0]
    moved["fl_x"] += 5.0
    p.write_text(json.dumps(doc))
    cap = read_capture(root)
    assert cap.varying_cameras == [1]
    f = [f for f in cap.frames if f.camera_index == 1 and f.timestep == 2][0]
    assert f.camera.K[0, 0] == pytest.approx(FX + 5.0)
    assert cap.cameras[1].K[0, 0] == pytest.approx(FX)


def test_no_masks(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq", FakeSpec(with_masks=False))
    cap = read_capture(root)
    assert all(f.mask_path is None for f in cap.frames)


def test_several_problems_are_listed(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    (root / "images" / "00000_00.png").unlink()
    (root / "images" / "00001_01.png").write_bytes(b"not a png at all")
    with pytest.raises(InputError) as info:
        read_capture(root)
    msg = str(info.value)
    assert "00000_00.png" in msg and "00001_01.png" in msg and "2 problems" in msg


def test_offset_rows_against_model(tmp_path: Path) -> None:
    from sage_core.data.capture import fit_params_to_model, offset_rows_compatible, validate_against_model

    assert offset_rows_compatible(5143, 5143, 5023) == "same"
    assert offset_rows_compatible(5023, 5143, 5023) == "pad"
    assert offset_rows_compatible(5143, 5023, 5023) == "trim"
    assert offset_rows_compatible(5000, 5143, 5023) is None
    assert offset_rows_compatible(5143, 6000, 5023) is None
    cap = read_capture(make_fake_capture(tmp_path / "seq"))
    assert validate_against_model(cap, MODEL_V, MODEL_V) == []
    notes = validate_against_model(cap, MODEL_V + 3, MODEL_V)
    assert len(notes) == 2 and all("zero-padded" in n for n in notes)  # per-timestep files + canonical
    with pytest.raises(InputError) as info:
        validate_against_model(cap, MODEL_V + 3, MODEL_V + 1)
    assert info.value.path.name == "00000.npz" and "static_offset" in info.value.problem
    padded = fit_params_to_model(cap.params, MODEL_V + 3, MODEL_V)
    assert padded.static_offset is not None and padded.static_offset.shape == (MODEL_V + 3, 3)


def test_absent_mask_folder_is_a_warning(tmp_path: Path) -> None:
    import shutil

    root = make_fake_capture(tmp_path / "seq")
    shutil.rmtree(root / "fg_masks")
    cap = read_capture(root)
    assert all(f.mask_path is None for f in cap.frames)
    assert any("mask" in w for w in cap.warnings)


def test_numbers_beyond_float_range_and_deep_nesting_are_named_problems(tmp_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    split = root / "transforms_train.json"
    doc = json.loads(split.read_text())
    doc["frames"][0]["fl_x"] = 10**400  # valid JSON; float() of it overflows
    doc["frames"][1]["cx"] = [[[[[[[[[[1]]]]]]]]]]
    split.write_text(json.dumps(doc))
    with pytest.raises(InputError) as info:
        read_capture(root)
    msg = str(info.value)
    assert str(split) in msg and "fl_x=100000" in msg and "(expected a finite positive number)" in msg
    assert "cx=[[[[[[[...]]]]]]] (expected a finite number)" in msg  # shortened past six levels
    assert len(msg) < 1000  # the 401-digit number is shortened

    split.write_text('{"frames": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(InputError, match="invalid JSON: nested too deeply to read") as info:
        read_capture(root)
    assert info.value.path == split
