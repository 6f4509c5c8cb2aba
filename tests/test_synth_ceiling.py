"""The tracking ceiling (:mod:`sage_core.data.synthetic.ceiling`): the ground-truth appearance on the
written model posed with the written parameters reproduces an exact capture and measures the
tracking error of a fitted one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sage_core.data.cameras import Camera
from sage_core.data.synthetic import make_capture, preset
from sage_core.data.synthetic.ceiling import FLAME_KEYS, TrackedTruth
from sage_core.errors import InputError

COARSE = {"head_rows": 40, "head_cols": 48, "eye_rows": 6, "eye_cols": 8}
SMALL = {"n_cameras": 3, "width": 40, "height": 58, "train_timesteps": 2, "test_timesteps": 2, **COARSE}


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("ceiling")
    return {mode: make_capture(root / mode, preset("tiny", tracking=mode, **SMALL)) for mode in ("exact", "fitted")}


def _frames(cap: Path) -> list[tuple[dict, Camera, np.ndarray, dict[str, np.ndarray]]]:
    """Every image of the capture: (nerf frame, OpenCV camera, image (H, W, 3), FLAME params)."""
    from sage_core.data.cameras import camera_from_nerf_frame
    from sage_core.data.imageio import read_image

    doc = json.loads((cap / "transforms.json").read_text())
    out = []
    for fr in doc["frames"]:
        cam = camera_from_nerf_frame(fr)
        with np.load(cap / fr["flame_param_path"]) as z:
            params = {k: z[k] for k in FLAME_KEYS}
        out.append((fr, cam, read_image(cap / fr["file_path"])[..., :3], params))
    return out


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b) ** 2).mean())
    return 10 * np.log10(1.0 / max(mse, 1e-12))


def test_exact_capture_is_reproduced(captures: dict[str, Path]) -> None:
    truth = TrackedTruth.open(captures["exact"])
    for fr, cam, img, params in _frames(captures["exact"]):
        assert _psnr(truth.render(params, cam), img) > 45.0, fr["file_path"]


def test_fitted_capture_costs_what_the_tracking_misses(captures: dict[str, Path]) -> None:
    truth = TrackedTruth.open(captures["fitted"])
    frames = _frames(captures["fitted"])
    scores = np.array([_psnr(truth.render(p, cam), img) for _, cam, img, p in frames])
    assert np.all(np.isfinite(scores)) and np.all(scores < 45.0), scores
    assert 15.0 < scores.mean() < 40.0, scores
    # the written model posed with the written parameters, not the truth: its vertices are the ones
    # the capture reports the tracking error of
    info = json.loads((captures["fitted"] / "gt" / "info.json").read_text())
    import trimesh

    for row in info["tracking"]["timesteps"]:
        ti = row["timestep_index"]
        with np.load(captures["fitted"] / "flame_param" / f"{ti:05d}.npz") as z:
            verts, crease = truth.pose({k: z[k] for k in FLAME_KEYS})
        gt = np.asarray(trimesh.load(captures["fitted"] / "gt" / "meshes" / f"{ti:05d}.ply", process=False).vertices)
        assert abs(1e3 * np.linalg.norm(verts - gt, axis=-1).mean() - row["mean_mm"]) < 2e-3
        assert crease.shape == (verts.shape[0],) and np.all((crease >= 0) & (crease <= 1))


def test_render_is_deterministic_and_follows_the_camera_size(captures: dict[str, Path]) -> None:
    truth = TrackedTruth.open(captures["fitted"])
    _, cam, _, params = _frames(captures["fitted"])[0]
    a, b = truth.render(params, cam), truth.render(params, cam)
    np.testing.assert_array_equal(a, b)
    K = cam.K.copy()
    K[:2] *= 0.5
    half = Camera(K, cam.w2c, cam.width // 2, cam.height // 2, cam.index)
    assert truth.render(params, half).shape == (cam.height // 2, cam.width // 2, 3)


def test_open_rejects_what_is_not_its_capture(captures: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InputError, match="info.json"):
        TrackedTruth.open(tmp_path)
    import shutil

    cap = tmp_path / "cap"
    shutil.copytree(captures["fitted"], cap)
    info_path = cap / "gt" / "info.json"
    info = json.loads(info_path.read_text())
    info["config"]["seed"] = int(info["config"]["seed"]) + 1
    info_path.write_text(json.dumps(info))
    with pytest.raises(InputError, match="differs"):
        TrackedTruth.open(cap)
