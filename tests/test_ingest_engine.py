"""Ingest engine: regime selection, resizing with K, written files, IngestedData, end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fake_capture import BLOB, H, MODEL_V, W, FakeSpec, make_fake_capture, make_tiny_model
from sage_core.data import IngestedData, ingest, read_capture, select_frames
from sage_core.data.ingest import NEUTRAL_JAW_WEIGHT, choose_neutral_timestep, neutral_score, target_size
from sage_core.errors import ConfigError, StageError


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # timestep 1 is the neutral one (small expression, jaw 0.3); 3 is test
    return make_fake_capture(tmp_path_factory.mktemp("cap") / "seq", FakeSpec(n_train_timesteps=3))


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tiny_model(tmp_path_factory.mktemp("model") / "flame.npz")


@pytest.fixture(scope="module")
def capture(capture_dir: Path):
    return read_capture(capture_dir)


def _posed_tiny_model(model_path: Path, params, timestep: int) -> np.ndarray:
    """Independent float64 posing of the tiny model (all skinning on joint 1, every joint at the mean
    vertex, no pose correctives): v = R0·R1·(v_shaped − J) + J + t."""
    from scipy.spatial.transform import Rotation

    z = np.load(model_path)
    r = params.row_of(timestep)
    S, E = z["shapedirs"].shape[2], z["exprdirs"].shape[2]
    v = (z["v_template"] + z["shapedirs"] @ params.shape[:S].astype(np.float64)
         + z["exprdirs"] @ params.expr[r, :E].astype(np.float64) + params.static_offset.astype(np.float64))
    J = v.mean(0)
    R = Rotation.from_rotvec(params.rotation[r].astype(np.float64)).as_matrix() @ Rotation.from_rotvec(
        params.neck_pose[r].astype(np.float64)).as_matrix()
    return (v - J) @ R.T + J + params.translation[r].astype(np.float64)


def test_neutral_rule(capture) -> None:
    p = capture.params
    scores = neutral_score(p, [p.row_of(t) for t in (0, 1, 2)])
    assert int(np.argmin(scores)) == 1
    expect0 = np.linalg.norm(p.expr[p.row_of(0)]) + NEUTRAL_JAW_WEIGHT * np.linalg.norm(
        p.jaw_pose[p.row_of(0)] - [0.3, 0, 0])
    assert scores[0] == pytest.approx(expect0, rel=1e-6)
    assert choose_neutral_timestep(p, [0, 1, 2]) == 1
    assert choose_neutral_timestep(p, [2, 0]) == 0  # expression norm 1 beats 3 at equal jaw


def test_mv_sf_picks_one_timestep(capture) -> None:
    sel = select_frames(capture, "mv-sf")
    assert sel.canonical_timestep == 1
    assert {f.timestep for f in sel.train} == {1} and {f.camera_index for f in sel.train} == {0, 1}
    assert [(f.timestep, f.camera_index) for f in sel.val] == [(1, 8)]
    assert {f.timestep for f in sel.test} == {3} and len(sel.test) == 3
    sel2 = select_frames(capture, "mv-sf", timestep=2)
    assert {f.timestep for f in sel2.train} == {2} and sel2.canonical_timestep == 2
    with pytest.raises(ConfigError, match="not a train timestep"):
        select_frames(capture, "mv-sf", timestep=3)
    with pytest.raises(ConfigError, match="sv-hr and one-shot"):
        select_frames(capture, "mv-sf", camera=0)


def test_mv_mf_takes_all_train_timesteps(capture) -> None:
    sel = select_frames(capture, "mv-mf")
    assert {f.timestep for f in sel.train} == {0, 1, 2} and len(sel.train) == 6
    assert len(sel.val) == 3 and sel.canonical_timestep == 1
    assert select_frames(capture, "mv-mf", timestep=0).canonical_timestep == 0


def test_sv_hr_single_camera(capture) -> None:
    with pytest.raises(ConfigError, match="2 train cameras"):
        select_frames(capture, "sv-hr")
    sel = select_frames(capture, "sv-hr", camera=1)
    assert {f.camera_index for f in sel.train} == {1} and len(sel.train) == 3
    assert sel.canonical_timestep == 1
    with pytest.raises(ConfigError, match="camera 5 has no train frames"):
        select_frames(capture, "sv-hr", camera=5)


def test_one_shot_needs_a_single_frame(capture, tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        select_frames(capture, "one-shot")
    assert "one-shot uses a single image" in str(info.value) and "2 train cameras" in str(info.value)
    with pytest.raises(ConfigError, match="3 train timesteps"):
        select_frames(capture, "one-shot", camera=0)
    sel = select_frames(capture, "one-shot", camera=0, timestep=2)
    assert [(f.timestep, f.camera_index) for f in sel.train] == [(2, 0)]
    assert [(f.timestep, f.camera_index) for f in sel.val] == [(2, 8)]
    single = read_capture(make_fake_capture(tmp_path / "one", FakeSpec(n_train_timesteps=1, n_test_timesteps=0,
                                                                         cameras=(8,), val_camera=None)))
    sel = select_frames(single, "one-shot")
    assert len(sel.train) == 1 and sel.val == [] and sel.test == []


def test_unknown_regime(capture) -> None:
    with pytest.raises(ConfigError, match="unknown regime 'mv-xx'"):
        select_frames(capture, "mv-xx")


def test_target_size() -> None:
    assert target_size(550, 802, None, None) == (550, 802)
    assert target_size(550, 802, None, 401) == (275, 401)
    assert target_size(550, 802, 2.0, None) == (275, 401)
    assert target_size(W, H, None, 32) == (24, 32)


def test_ingest_writes_everything(capture, model_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "data"
    calls: list[tuple[int, int, str]] = []
    s = ingest(capture, model_path, out, regime="mv-sf", height=32, progress=lambda d, t, m: calls.append((d, t, m)))
    assert s.regime == "mv-sf" and s.train_timesteps == [1] and s.canonical_timestep == 1
    assert s.counts == {"train": 2, "val": 1, "test": 3} and s.resolution == (24, 32)
    assert s.train_cameras == [0, 1] and s.cameras == [0, 1, 8] and s.has_masks
    assert calls[-1][0] == calls[-1][1] and [c[0] for c in calls] == list(range(1, len(calls) + 1))
    for name in ("cameras.json", "frames.json", "flame_params.npz", "flame_model.npz", "summary.json"):
        assert (out / name).is_file(), name
    assert not (out / "flame_masks.json").exists()
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(
        f"{t:05d}_{c:02d}.png" for t, c in [(1, 0), (1, 1), (1, 8), (3, 0), (3, 1), (3, 8)])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["canonical_timestep"] == 1 and summary["n_vertices"] == MODEL_V
    expect = _posed_tiny_model(model_path, capture.params, 1)
    np.testing.assert_allclose(summary["head_bbox"][0], expect.min(0), atol=1e-5)
    np.testing.assert_allclose(summary["head_bbox"][1], expect.max(0), atol=1e-5)

    data = IngestedData.open(out)
    assert data.canonical_timestep == 1 and data.regime == "mv-sf"
    assert [f.timestep for f in data.train] == [1, 1] and len(data.test) == 3
    assert list(data.params.timesteps) == [1, 3]
    assert data.params.static_offset is not None and data.params.static_offset.shape == (MODEL_V, 3)
    np.testing.assert_array_equal(data.params.expr[0], capture.params.expr[capture.params.row_of(1)])
    for f in data.frames:
        img, mask = data.load_image(f), data.load_mask(f)
        assert img.shape == (32, 24, 3) and img.dtype == np.float32 and mask.shape == (32, 24)
        # K was rescaled with the image: the blob lands where the ingested camera projects it
        uv = f.camera.project(BLOB[None])[0][0]
        ys, xs = np.nonzero(mask > 0.5)
        w = mask[mask > 0.5]
        centre = np.array([(xs * w).sum() / w.sum() + 0.5, (ys * w).sum() / w.sum() + 0.5])
        np.testing.assert_allclose(centre, uv, atol=0.5)
        assert f.camera.K[0, 0] == pytest.approx(60.0 * 24 / W)
        assert f.camera.K[1, 2] == pytest.approx(36.0 * 32 / H)
    assert data.cameras[8].width == 24
    assert data.frame(1, 8).role == "val" and data.frame(3, 0).role == "test"
    assert data.load_model().n_vertices == MODEL_V


def test_black_background_and_masks_json(capture, model_path: Path, tmp_path: Path) -> None:
    import pickle

    model_dir = tmp_path / "model"
    model_dir.mkdir()
    mp = model_dir / "flame.npz"
    mp.write_bytes(model_path.read_bytes())
    with open(model_dir / "FLAME_masks.pkl", "wb") as fh:
        pickle.dump({"face": np.arange(5), "neck": np.array([6, 7])}, fh)
    out = tmp_path / "data"
    ingest(capture, mp, out, regime="one-shot", camera=1, timestep=0, background="black")
    data = IngestedData.open(out)
    assert data.load_masks_json()["neck"].tolist() == [6, 7]
    f = data.train[0]
    img, mask = data.load_image(f), data.load_mask(f)
    assert img.shape == (H, W, 3)
    assert np.all(img[mask == 0] == 0)  # white background removed
    np.testing.assert_allclose(img[mask == 1][0], [0.2, 0.4, 0.6], atol=1 / 255)


def test_output_folder_reuse(capture, model_path: Path, tmp_path: Path) -> None:
    from sage_core.errors import InputError

    out = tmp_path / "data"
    (out / "images").mkdir(parents=True)
    (out / "images" / "stale.png").write_text("x")
    (out / "config.json").write_text("{}")  # the caller's file
    s = ingest(capture, model_path, out, regime="one-shot", camera=0, timestep=0, workers=1)
    assert not (out / "images" / "stale.png").exists() and (out / "config.json").read_text() == "{}"
    assert s.metrics()["train_images"] == 1 and s.metrics()["height"] == H
    assert ("regime", "one-shot") in s.rows()
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        ingest(capture, model_path, tmp_path / "file")


def test_conflicting_options(capture, model_path: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="either"):
        ingest(capture, model_path, tmp_path / "a", downsample=2.0, height=32)
    with pytest.raises(ConfigError, match="background"):
        ingest(capture, model_path, tmp_path / "b", background="green")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_open_rejects_incomplete_folder(capture, model_path: Path, tmp_path: Path) -> None:
    with pytest.raises(StageError, match="run `sage ingest`"):
        IngestedData.open(tmp_path / "nothing")
    out = tmp_path / "data"
    ingest(capture, model_path, out, regime="mv-sf", downsample=2.0)
    (out / "summary.json").unlink()
    with pytest.raises(StageError, match="summary.json"):
        IngestedData.open(out)


def test_teeth_padding_of_offsets(tmp_path: Path) -> None:
    # a model with 6 appended vertices: the capture's offsets have only the base rows
    cap = read_capture(make_fake_capture(tmp_path / "seq", FakeSpec(n_train_timesteps=1, n_vertices=MODEL_V)))
    model = make_tiny_model(tmp_path / "m.npz", n_vertices=MODEL_V + 6, n_base_vertices=MODEL_V)
    s = ingest(cap, model, tmp_path / "data", regime="mv-sf")
    assert any("zero-padded" in w for w in s.warnings)
    data = IngestedData.open(tmp_path / "data")
    off = data.params.static_offset
    assert off is not None and off.shape == (MODEL_V + 6, 3) and np.all(off[MODEL_V:] == 0)


def _synthetic_available() -> bool:
    try:
        from sage_core.data.synthetic import capture_model_path, make_capture  # noqa: F401
    except ImportError:
        return False
    return True


def _above_neck_line(uv: np.ndarray, left: int, right: int, front_bottom: int) -> np.ndarray:
    """VHAP's neck-line test in image space (docs/formats.md §1.1): keep k·x + b − y > 0. (N,) bool."""
    a, b, c = uv[left], uv[right], uv[front_bottom]
    k = (b[1] - a[1]) / (b[0] - a[0])
    return k * uv[:, 0] + (c[1] - k * c[0]) - uv[:, 1] > 0


@pytest.mark.slow
@pytest.mark.skipif(not _synthetic_available(), reason="sage_core.data.synthetic is not available")
def test_end_to_end_synthetic_mesh_inside_masks(tmp_path: Path) -> None:
    """Synthetic capture -> ingest (resized) -> the ground-truth meshes project into the ingested masks.

    Vertices below the capture's neck line are blanked out of the masks by design and are not
    counted; a vertex on the silhouette may land on the neighbouring pixel (1-pixel tolerance).
    """
    import cv2
    import torch
    import trimesh

    from sage_core.data.synthetic import capture_model_path, make_capture, preset
    from sage_core.flame import FlameModel, load_flame_model

    cfg = preset("tiny", n_cameras=4, train_timesteps=2, test_timesteps=1, novel_views=1, novel_expressions=1)
    cap_dir = make_capture(tmp_path / "synth", cfg)
    neck = json.loads((cap_dir / "gt" / "info.json").read_text())["model"]["neck_line_vertices"]
    cap = read_capture(cap_dir)
    s = ingest(cap, capture_model_path(cap_dir), tmp_path / "data", regime="mv-mf", height=96)
    assert s.resolution[1] == 96 and s.counts["train"] == len(cap.split("train"))
    data = IngestedData.open(tmp_path / "data")
    flame = FlameModel(load_flame_model(data.model_path)).double()
    inside = total = 0
    for f in data.frames:
        gt = np.asarray(trimesh.load(cap_dir / "gt" / "meshes" / f"{f.timestep:05d}.ply", process=False).vertices)
        # the ingested FLAME parameters and model reproduce the ground-truth mesh
        with torch.no_grad():
            posed = flame(**data.params.select([data.params.row_of(f.timestep)]).to_torch("cpu", torch.float64))
        np.testing.assert_allclose(posed.vertices[0].numpy(), gt, atol=1e-4)
        uv, z = f.camera.project(gt)
        mask = cv2.dilate((data.load_mask(f) > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
        h, w = mask.shape
        px = np.floor(uv).astype(int)
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        px = np.clip(px, 0, [w - 1, h - 1])
        keep = _above_neck_line(uv, neck["left"], neck["right"], neck["front_bottom"])
        hit = ok & (mask[px[:, 1], px[:, 0]] > 0)
        inside += int(hit[keep].sum())
        total += int(keep.sum())
    assert total > 0.5 * len(gt) * len(data.frames)
    assert inside / total >= 0.99, inside / total
