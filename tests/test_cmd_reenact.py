"""`sage reenact`: self-reenactment reproduces eval's renders, cross-reenactment keeps the identity,
motions are validated before rendering, orbit and EXR output."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from helpers import invoke


@pytest.fixture(scope="module")
def base_ws(cmd_avatar_ws):
    return cmd_avatar_ws


@pytest.fixture
def ws(base_ws, tmp_path):
    dst = tmp_path / "ws"
    shutil.copytree(base_ws, dst)
    return dst


def _frames(folder):
    from sage_core.data.imageio import read_image

    return [read_image(p) for p in sorted(folder.glob("*.png"))]


def test_self_reenactment_reproduces_eval_renders(ws, tiny_capture):
    from sage_core.data.imageio import read_image

    res = invoke(["eval", ws, "--split", "all", "--samples", "100", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    res = invoke(["reenact", ws, "--flame-seq", tiny_capture, "--camera", "8", "--no-video", "--name", "self", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    out = ws / "reenact" / "self"
    rec = json.loads((out / "reenact.json").read_text())
    timesteps = rec["motion"]["timesteps"]
    frames = _frames(out / "frames")
    assert len(frames) == len(timesteps) == rec["report"]["n_frames"]
    assert rec["render_backend"] in ("torch", "cpp")
    assert "rendered FPS" in res.output
    compared = 0
    for split in ("val", "test"):
        for strip_path in sorted((ws / "eval" / "phase1" / split / "images").glob("*_08.png")):
            ts = int(strip_path.name[:5])
            strip = read_image(strip_path)
            w = strip.shape[1] // 3
            render = strip[:, w : 2 * w]  # GT | render | error
            frame = frames[timesteps.index(ts)]
            assert frame.shape == render.shape
            assert np.abs(frame - render).max() <= 1.0 / 255.0 + 1e-6, (split, ts)
            compared += 1
    assert compared >= 3  # val timestep(s) and test timesteps


def _foreign_identity_folder(capture, dst, n=2):
    """A flame_param folder of the capture's first n timesteps with another shape and static offset."""
    dst.mkdir(parents=True)
    rng = np.random.default_rng(3)
    for p in sorted((capture / "flame_param").glob("*.npz"))[:n]:
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["shape"] = arrays["shape"] + rng.normal(0, 1.0, arrays["shape"].shape).astype(np.float32)
        if "static_offset" in arrays:
            arrays["static_offset"] = arrays["static_offset"] + 0.01
        np.savez(dst / p.name, **arrays)
    return dst


def test_cross_reenactment_keeps_the_avatars_identity(ws, tiny_capture, tmp_path):
    from sage_core.avatar.model import params_row_inputs
    from sage_core.data.dataset import IngestedData
    from sage_core.export.motion import load_motion
    from sage_core.flame.params import load_param_npz
    from sage_core.stages.avatars import load_stage_avatar
    from sage_core.stages.motion import with_identity
    from sage_core.workspace import Workspace

    seq = _foreign_identity_folder(tiny_capture, tmp_path / "other" / "flame_param")
    loaded = load_stage_avatar(Workspace(ws), "phase1", IngestedData.open(ws / "data"))
    av = loaded.avatar
    motion = load_motion(seq, n_expr=av.params.n_expr)
    ts = int(motion.timesteps[0])
    with torch.no_grad():
        driven = av.pose_mesh(with_identity(av, motion.frame_inputs(0)))
        own = av.pose_mesh(av.frame_inputs(ts))
        foreign_params = load_param_npz(sorted(seq.glob("*.npz"))[0]).pad_offsets(av.model_data.v_template.shape[0])
        foreign = av.pose_mesh(params_row_inputs(foreign_params, 0))
    assert torch.allclose(driven, own, atol=1e-6)  # the avatar's shape and static offset
    assert (driven - foreign).norm(dim=-1).max() > 1e-3  # not the driving sequence's
    # through the command: the foreign-identity motion renders exactly like the avatar's own one
    args = ["--camera", "8", "--no-video", "--max-frames", "2", "--device", "cpu", "--quiet"]
    res = invoke(["reenact", ws, "--flame-seq", seq, "--name", "cross", *args])
    assert res.exit_code == 0, res.output
    res = invoke(["reenact", ws, "--flame-seq", tiny_capture, "--name", "own", *args])
    assert res.exit_code == 0, res.output
    a, b = _frames(ws / "reenact" / "cross" / "frames"), _frames(ws / "reenact" / "own" / "frames")
    assert len(a) == len(b) == 2
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def _motion_npz(path, T, n_expr=10, **override):
    arrays = {
        "expr": np.zeros((T, n_expr), np.float32), "rotation": np.zeros((T, 3), np.float32),
        "neck_pose": np.zeros((T, 3), np.float32), "jaw_pose": np.zeros((T, 3), np.float32),
        "eyes_pose": np.zeros((T, 6), np.float32), "translation": np.zeros((T, 3), np.float32),
    }  # fmt: skip
    arrays.update(override)
    np.savez(path, **arrays)
    return path


def test_motion_is_validated_before_rendering(ws, tmp_path):
    bad_t = _motion_npz(tmp_path / "bad_t.npz", 5, jaw_pose=np.zeros((4, 3), np.float32))
    res = invoke(["reenact", ws, "--flame-seq", bad_t, "--name", "bad", "--device", "cpu", "--quiet"])
    assert res.exit_code == 2 and "bad_t.npz" in res.output and "jaw_pose" in res.output
    assert not (ws / "reenact" / "bad").exists()
    bad_v = _motion_npz(tmp_path / "bad_v.npz", 3, dynamic_offset=np.zeros((3, 10, 3), np.float32))
    res = invoke(["reenact", ws, "--flame-seq", bad_v, "--name", "bad", "--device", "cpu", "--quiet"])
    assert res.exit_code == 2 and "dynamic_offset" in res.output and "10 vertices" in res.output
    assert not (ws / "reenact" / "bad").exists()
    res = invoke(["reenact", ws, "--flame-seq", bad_v, "--orbit", "--camera", "8", "--quiet"])
    assert res.exit_code == 3


def test_orbit_with_exr_frames(ws, tmp_path):
    from sage_core.data.imageio import read_image
    from sage_core.data.dataset import IngestedData

    data = IngestedData.open(ws / "data")
    motion = _motion_npz(tmp_path / "still.npz", 4, n_expr=data.params.n_expr,
                         translation=np.repeat(data.params.translation[:1], 4, 0))  # fmt: skip
    res = invoke(["reenact", ws, "--flame-seq", motion, "--orbit", "--orbit-arc", "90", "--format", "exr", "--no-video",
                  "--name", "orbit", "--device", "cpu", "--quiet"])  # fmt: skip
    assert res.exit_code == 0, res.output
    frames = sorted((ws / "reenact" / "orbit" / "frames").glob("*.exr"))
    assert len(frames) == 4
    imgs = [read_image(p)[..., :3] for p in frames]
    ref = data.val[0].camera
    assert imgs[0].shape == (ref.height, ref.width, 3)
    assert np.abs(imgs[0] - imgs[3]).max() > 0.1  # -45 deg vs +45 deg
    assert np.abs(imgs[0][:, ::-1] - imgs[3]).mean() < np.abs(imgs[0] - imgs[3]).mean()  # roughly mirrored views
    assert not (ws / "reenact" / "orbit" / "video.mp4").exists()


def test_an_out_folder_of_other_files_is_refused_unless_forced(ws, tmp_path):
    from sage_core.data.dataset import IngestedData

    data = IngestedData.open(ws / "data")
    motion = _motion_npz(tmp_path / "still.npz", 2, n_expr=data.params.n_expr,
                         translation=np.repeat(data.params.translation[:1], 2, 0))  # fmt: skip
    out = tmp_path / "mine"
    (out / "frames").mkdir(parents=True)
    (out / "frames" / "keep.txt").write_text("mine")
    (out / "video.mp4").write_text("my video")
    args = ["reenact", ws, "--flame-seq", motion, "--out", out, "--device", "cpu", "--quiet"]
    res = invoke(args)
    assert res.exit_code == 3, res.output
    assert "holds files and no reenact.json" in " ".join(res.output.split()) and "--force" in res.output
    assert (out / "frames" / "keep.txt").read_text() == "mine" and (out / "video.mp4").read_text() == "my video"
    assert sorted(p.name for p in out.iterdir()) == ["frames", "video.mp4"]

    res = invoke([*args, "--force"])
    assert res.exit_code == 0, res.output
    assert (out / "reenact.json").is_file() and not (out / "frames" / "keep.txt").exists()
    assert len(list((out / "frames").glob("*.png"))) == 2
    res = invoke([*args, "--no-video"])  # an earlier reenactment's folder is reused without --force
    assert res.exit_code == 0, res.output


def test_a_name_too_long_for_a_folder_is_refused_before_anything_is_written(ws, tmp_path):
    motion = _motion_npz(tmp_path / "m.npz", 2)
    res = invoke(["reenact", ws, "--flame-seq", motion, "--name", "n" * 300, "--device", "cpu", "--quiet"])
    assert res.exit_code == 3, res.output
    assert "--name is 300 bytes long; a folder name holds at most 255" in " ".join(res.output.split())
    assert not (ws / "reenact").exists()
    res = invoke(["reenact", ws, "--flame-seq", motion, "--name", "é" * 128, "--device", "cpu", "--quiet"])
    assert res.exit_code == 3 and "256 bytes long" in res.output, res.output
    from pathlib import Path

    from sage_core.stages.reenact import seq_label

    label = seq_label(Path("é" * 120 + ".npz"))  # a name derived from a long motion file still fits with its camera
    assert 0 < len(label.encode("utf-8")) <= 200 and set(label) == {"é"}
