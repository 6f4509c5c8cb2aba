"""Capture reader: VHAP single-sequence and union layouts, per-frame cameras, fallbacks.

The helpers at the top build tiny fake VHAP exports (a handful of 48×64 frames) and a tiny fake
FLAME model; the ingest tests import them from here.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from sage_core.data import Camera, camera_to_nerf_frame, read_capture, write_image
from sage_core.data.cameras import look_at
from sage_core.errors import InputError

W, H = 48, 64
FX, FY = 60.0, 63.0
CX, CY_CV = 21.5, 36.0  # deliberately off-centre
N_SHAPE, N_EXPR = 300, 100
MODEL_V = 14
BLOB = np.array([0.02, 0.03, 0.01])  # a world point drawn into every image


def make_camera(ci: int, n_cameras: int) -> Camera:
    """Cameras on an arc at 1 m looking at the origin; index ``ci`` of ``n_cameras``."""
    ang = np.deg2rad(-40 + 80 * ci / max(n_cameras - 1, 1))
    eye = np.array([np.sin(ang), 0.05 * (ci % 3), np.cos(ang)])
    K = np.array([[FX, 0, CX], [0, FY, CY_CV], [0, 0, 1.0]])
    return Camera(K, look_at(eye, np.zeros(3)), W, H, ci, f"cam{ci:02d}")


def project_manual(cam: Camera, X: np.ndarray) -> np.ndarray:
    """Independent pinhole projection of one point: (2,) pixel coordinates."""
    Xc = cam.w2c[:3, :3] @ X + cam.w2c[:3, 3]
    return np.array([cam.K[0, 0] * Xc[0] / Xc[2] + cam.K[0, 2], cam.K[1, 1] * Xc[1] / Xc[2] + cam.K[1, 2]])


def blob_image(cam: Camera, radius: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """White image with a dark disc around the projection of BLOB, and its mask. (H,W,3), (H,W)."""
    uv = project_manual(cam, BLOB)
    yy, xx = np.mgrid[0:cam.height, 0:cam.width] + 0.5  # pixel centres
    mask = ((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= radius**2).astype(np.float32)
    img = np.ones((cam.height, cam.width, 3), np.float32)
    img[mask > 0] = np.array([0.2, 0.4, 0.6], np.float32)
    return img, mask


def vhap_params(t: int, n_vertices: int = MODEL_V, expr_scale: float = 1.0, jaw: float = 0.0,
                dynamic: bool = False) -> dict[str, np.ndarray]:
    """One per-timestep npz in the exact VHAP shapes."""
    rng = np.random.default_rng(100 + t)
    d = {
        "translation": (rng.normal(size=(1, 3)) * 0.005).astype(np.float32),
        "rotation": (rng.normal(size=(1, 3)) * 0.02).astype(np.float32),
        "neck_pose": (rng.normal(size=(1, 3)) * 0.02).astype(np.float32),
        "jaw_pose": np.array([[jaw, 0.0, 0.0]], np.float32),
        "eyes_pose": np.zeros((1, 6), np.float32),
        "shape": np.linspace(-1, 1, N_SHAPE).astype(np.float32),
        "expr": (np.ones((1, N_EXPR)) * expr_scale / np.sqrt(N_EXPR)).astype(np.float32),
        "static_offset": (np.arange(n_vertices * 3).reshape(1, n_vertices, 3) * 1e-4).astype(np.float32),
    }
    if dynamic:
        d["dynamic_offset"] = np.full((1, n_vertices, 3), 1e-3 * (t + 1), np.float32)
    return d


@dataclass
class FakeSpec:
    """What a fake sequence holds."""

    n_train_timesteps: int = 3
    n_test_timesteps: int = 1
    cameras: tuple[int, ...] = (0, 1, 8)
    val_camera: int | None = 8
    with_masks: bool = True
    n_vertices: int = MODEL_V
    # timestep -> (expression norm, jaw x-angle); default: the middle train timestep is the neutral one
    expressions: dict[int, tuple[float, float]] = field(default_factory=dict)


def _frame_entry(cam: Camera, ti: int, prefix: str) -> dict:
    fr = camera_to_nerf_frame(cam)
    fr.update({
        "timestep_index": ti,
        "timestep_index_original": ti,
        "timestep_id": f"frame_{ti:05d}",
        "camera_index": cam.index,
        "camera_id": cam.name,
        "file_path": f"{prefix}images/{ti:05d}_{cam.index:02d}.png",
        "fg_mask_path": f"{prefix}fg_masks/{ti:05d}_{cam.index:02d}.png",
        "flame_param_path": f"{prefix}flame_param/{ti:05d}.npz",
    })
    return fr


def _write_transforms(path: Path, frames: list[dict]) -> None:
    doc = {
        # top-level intrinsics are deliberately wrong: readers must use the per-frame values
        "cx": 1.0, "cy": 1.0, "fl_x": 999.0, "fl_y": 999.0, "h": 7, "w": 5,
        "camera_angle_x": 0.1, "camera_angle_y": 0.1,
        "timestep_indices": sorted({f["timestep_index"] for f in frames}),
        "camera_indices": sorted({f["camera_index"] for f in frames}),
        "frames": frames,
    }
    path.write_text(json.dumps(doc, indent=1))


def write_sequence(seq: Path, spec: FakeSpec, t0: int = 0, prefix: str = "") -> dict[str, list[dict]]:
    """Write images, masks and FLAME files of one sequence; return its frames per split.

    t0: first timestep index (unions re-base timesteps cumulatively); prefix: path prefix for the
    frame entries (``../<seq>/`` in unions).
    """
    seq.mkdir(parents=True, exist_ok=True)
    n_cams = max(spec.cameras) + 1
    T = spec.n_train_timesteps + spec.n_test_timesteps
    splits: dict[str, list[dict]] = {"train": [], "val": [], "test": []}
    for k in range(T):
        ti = t0 + k
        norm, jaw = spec.expressions.get(ti, (0.1 if k == spec.n_train_timesteps // 2 else 1.0 + k,
                                              0.3 if k == spec.n_train_timesteps // 2 else 0.0))
        np.savez(_mkdir(seq / "flame_param") / f"{ti:05d}.npz", **vhap_params(ti, spec.n_vertices, norm, jaw))
        for ci in spec.cameras:
            cam = make_camera(ci, n_cams)
            img, mask = blob_image(cam)
            write_image(seq / "images" / f"{ti:05d}_{ci:02d}.png", img)
            if spec.with_masks:
                write_image(seq / "fg_masks" / f"{ti:05d}_{ci:02d}.png", mask)
            fr = _frame_entry(cam, ti, prefix)
            if not spec.with_masks:
                fr.pop("fg_mask_path")
            if k >= spec.n_train_timesteps:
                splits["test"].append(fr)
            elif ci == spec.val_camera:
                splits["val"].append(fr)
            else:
                splits["train"].append(fr)
    canon = vhap_params(0, spec.n_vertices, 0.0, 0.3)
    canon["translation"][:] = 0
    canon["rotation"][:] = 0
    canon["neck_pose"][:] = 0
    np.savez(seq / "canonical_flame_param.npz", **canon)
    return splits


def _mkdir(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


def make_fake_capture(root: Path, spec: FakeSpec | None = None) -> Path:
    """A single-sequence VHAP export in ``root``; returns root."""
    spec = spec or FakeSpec()
    splits = write_sequence(root, spec)
    for s, frames in splits.items():
        _write_transforms(root / f"transforms_{s}.json", frames)
    return root


def make_fake_union(parent: Path, spec: FakeSpec | None = None, n_sequences: int = 2) -> Path:
    """Sibling sequences ``seq0..`` plus a union folder ``UNION`` whose paths start with ``../seqK/``.

    The last sequence is the test sequence (all cameras); the others give train/val.
    """
    spec = spec or FakeSpec()
    union = _mkdir(parent / "UNION")
    merged: dict[str, list[dict]] = {"train": [], "val": [], "test": []}
    t0 = 0
    for k in range(n_sequences):
        is_test = k == n_sequences - 1
        sub = FakeSpec(**{**spec.__dict__, "n_train_timesteps": 0 if is_test else spec.n_train_timesteps,
                          "n_test_timesteps": 2 if is_test else 0})
        splits = write_sequence(parent / f"seq{k}", sub, t0=t0, prefix=f"../seq{k}/")
        for s in merged:
            for fr in splits[s]:
                fr.pop("timestep_index_original")
                fr.pop("timestep_id")
            merged[s] += splits[s]
        t0 += sub.n_train_timesteps + sub.n_test_timesteps
    for s, frames in merged.items():
        _write_transforms(union / f"transforms_{s}.json", frames)
    (union / "canonical_flame_param.npz").write_bytes((parent / "seq0" / "canonical_flame_param.npz").read_bytes())
    return union


def make_tiny_model(path: Path, n_vertices: int = MODEL_V, n_base_vertices: int | None = None) -> Path:
    """A tiny FLAME-style model (5 joints) written with the project's npz writer."""
    from sage_core.flame import FlameModelData, save_flame_npz

    rng = np.random.default_rng(7)
    V, J = n_vertices, 5
    dirs = rng.normal(size=(V, 3))
    v = 0.1 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    w = np.zeros((V, J))
    w[:, 1] = 1.0
    data = FlameModelData(
        v_template=v,
        faces=np.stack([np.arange(V), (np.arange(V) + 1) % V, (np.arange(V) + 2) % V], 1).astype(np.int64),
        shapedirs=rng.normal(size=(V, 3, 10)) * 1e-3,
        exprdirs=rng.normal(size=(V, 3, 10)) * 1e-3,
        posedirs=np.zeros((V, 3, 9 * (J - 1))),
        j_regressor=np.full((J, V), 1.0 / V),
        lbs_weights=w,
        parents=np.array([-1, 0, 1, 1, 1], dtype=np.int64),
        n_base_vertices=V if n_base_vertices is None else n_base_vertices,
    )
    return save_flame_npz(data, path)


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
    _write_transforms(root / "transforms.json", frames)
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
