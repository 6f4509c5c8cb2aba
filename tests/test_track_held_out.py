"""The synthetic photo's held-out set moved into a tracked capture's world (``held_out_for_tracked``)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from sage_core.data.cameras import camera_from_nerf_frame
from sage_core.errors import InputError
from sage_core.flame import FlameModel, load_flame_model
from sage_core.flame.params import load_param_npz
from sage_core.track.truth import held_out_for_tracked

SHIFT = np.array([0.03, -0.02, 0.05])
"""How far the stand-in tracked capture's world is moved (m): its head and cameras alike."""


def _shifted_copy(cap: Path, out: Path, d: np.ndarray, zoom: float = 1.0) -> Path:
    """The capture with its world moved by ``d``: the head's translation and every camera's centre
    (the images stay what they are): a tracked capture whose world differs from the truth's;
    ``zoom`` scales its focal lengths too."""
    shutil.copytree(cap, out, ignore=shutil.ignore_patterns("gt"))
    for jpath in out.glob("transforms*.json"):
        doc = json.loads(jpath.read_text())
        for fr in doc["frames"]:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
            m[:3, 3] += d
            fr["transform_matrix"] = m.tolist()
            fr["fl_x"], fr["fl_y"] = fr["fl_x"] * zoom, fr["fl_y"] * zoom
        jpath.write_text(json.dumps(doc))
    for npz in (out / "flame_param").glob("*.npz"):
        arrays = dict(np.load(npz))
        arrays["translation"] = (arrays["translation"] + d).astype(np.float32)
        np.savez(npz, **arrays)
    return out


def _projected(cap_or_set: Path, model: FlameModel, split: str) -> list[np.ndarray]:
    """(V, 2) pixels of each held-out frame's posed FLAME mesh seen by its camera."""
    doc = json.loads((cap_or_set / f"transforms_{split}.json").read_text())
    out = []
    for fr in doc["frames"]:
        p = load_param_npz(cap_or_set / fr["flame_param_path"])
        with torch.no_grad():
            kw = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in p.to_torch(dtype=torch.float64).items()}
            v = model(**kw).vertices.numpy()[0]
        out.append(camera_from_nerf_frame(fr).project(v)[0])
    return out


@pytest.mark.parametrize("anchor", ["photo", "mesh"])
def test_the_held_out_set_follows_the_tracked_world(oneshot_ws, tmp_path, anchor):
    cap = Path(oneshot_ws).parent / "cap"
    model = FlameModel(load_flame_model(cap / "model" / "synth_flame.npz"), dtype=torch.float64)
    same = _shifted_copy(cap, tmp_path / "same", np.zeros(3))
    moved = _shifted_copy(cap, tmp_path / "moved", SHIFT)
    a = held_out_for_tracked(same, cap, anchor)
    b = held_out_for_tracked(moved, cap, anchor)
    n = sum(len(json.loads((cap / "gt" / "novel" / f"transforms_{s}.json").read_text())["frames"]) for s in ("val", "test"))
    assert a["frames"] == b["frames"] == n > 0
    # the shift is found: same rotation and scale, the translation moved by R·shift
    np.testing.assert_allclose(b["rotation"], a["rotation"], atol=1e-6)
    assert b["scale"] == pytest.approx(a["scale"], abs=1e-6)
    np.testing.assert_allclose(np.asarray(b["translation"]) - np.asarray(a["translation"]),
                               -np.asarray(a["rotation"]) @ SHIFT * a["scale"], atol=1e-6)
    for split in ("val", "test"):
        truth = _projected(cap / "gt" / "novel", model, split)
        pa = _projected(same / "gt" / "novel", model, split)
        pb = _projected(moved / "gt" / "novel", model, split)
        for t, x, y in zip(truth, pa, pb):
            # the moved world renders the same pixels as the unmoved one
            np.testing.assert_allclose(y, x, atol=1e-4)
            # and the capture's own parameters, moved onto the true mesh, land where the truth's do
            assert np.linalg.norm(x - t, axis=1).mean() < 1.5
    # a held-out expression carries the capture's own change: with the tracked parameters equal to
    # the capture's own, its expression is the held-out one's
    test = json.loads((cap / "gt" / "novel" / "transforms_test.json").read_text())["frames"][0]
    mine = json.loads((same / "gt" / "novel" / "transforms_test.json").read_text())["frames"][0]
    want = load_param_npz(cap / "gt" / "novel" / test["flame_param_path"])
    got = load_param_npz(same / "gt" / "novel" / mine["flame_param_path"])
    np.testing.assert_allclose(got.expr, want.expr, atol=1e-5)
    np.testing.assert_allclose(got.jaw_pose, want.jaw_pose, atol=1e-6)
    assert np.abs(want.expr).max() > 0.1
    # the view groups come along; images are copied, not linked
    info = json.loads((same / "gt" / "info.json").read_text())["novel"]
    assert info["alignment"]["scale"] == pytest.approx(a["scale"])
    assert (same / "gt" / "novel" / mine["file_path"]).is_file()
    assert not (same / "gt" / "novel" / mine["file_path"]).is_symlink()


def test_a_capture_of_several_timesteps_is_refused(tiny_capture, oneshot_ws, tmp_path):
    cap = Path(oneshot_ws).parent / "cap"
    before = sorted(str(p) for p in Path(tiny_capture).rglob("*"))
    with pytest.raises(InputError, match="one-image"):
        held_out_for_tracked(tiny_capture, cap)
    assert sorted(str(p) for p in Path(tiny_capture).rglob("*")) == before  # nothing written


def _relative(frames: list[dict], i: int, j: int) -> np.ndarray:
    """Rotation of camera ``j`` relative to camera ``i`` (world-to-camera rotations of two frames)."""
    wi, wj = (camera_from_nerf_frame(frames[k]).w2c[:3, :3] for k in (i, j))
    return wj @ wi.T


def test_the_photo_anchor_keeps_the_views_around_the_photos_camera(oneshot_ws, tmp_path):
    """Anchored at the photo, the held-out cameras keep their rotations relative to the photo's camera
    and take the tracked focal length's ratio to the true one; anchored at the mesh they keep the true
    focal lengths."""
    cap = Path(oneshot_ws).parent / "cap"
    zoomed = _shifted_copy(cap, tmp_path / "zoomed", SHIFT, zoom=1.25)
    photo_t = json.loads((cap / "transforms_train.json").read_text())["frames"][0]
    photo_r = json.loads((zoomed / "transforms_train.json").read_text())["frames"][0]
    truth = json.loads((cap / "gt" / "novel" / "transforms_val.json").read_text())["frames"]
    a = held_out_for_tracked(zoomed, cap, "photo")
    moved = json.loads((zoomed / "gt" / "novel" / "transforms_val.json").read_text())["frames"]
    assert a["focal_ratio"] == pytest.approx(1.25)
    for ft, fm in zip(truth, moved):
        assert fm["fl_x"] == pytest.approx(1.25 * ft["fl_x"])
        np.testing.assert_allclose(_relative([photo_r, fm], 0, 1), _relative([photo_t, ft], 0, 1), atol=1e-9)
    b = held_out_for_tracked(zoomed, cap, "mesh")
    moved = json.loads((zoomed / "gt" / "novel" / "transforms_val.json").read_text())["frames"]
    assert b["focal_ratio"] == 1.0 and moved[0]["fl_x"] == pytest.approx(truth[0]["fl_x"])
    with pytest.raises(ValueError, match="anchor"):
        held_out_for_tracked(zoomed, cap, "camera")
