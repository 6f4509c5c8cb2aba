"""Synthetic captures: layout, FLAME parameters, self-consistent cameras, determinism, regimes, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from sage_core.data.cameras import camera_from_nerf_frame
from sage_core.data.imageio import image_size, read_image
from sage_core.data.synthetic import capture_model_path, make_capture, preset, write_capture
from sage_core.errors import ConfigError
from sage_core.flame import FlameModel, load_flame_model

NPZ_SHAPES = {
    "translation": (1, 3),
    "rotation": (1, 3),
    "neck_pose": (1, 3),
    "jaw_pose": (1, 3),
    "eyes_pose": (1, 6),
    "expr": (1, 100),
    "shape": (300,),
}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "tiny"
    calls = []
    res = make_capture(out, preset("tiny"), progress=lambda d, t, m: calls.append((d, t)))
    assert calls and calls[-1][0] == calls[-1][1]
    assert res == out and res.model_path == out / "model" / "synth_flame.npz"
    return out


def _load(p: Path) -> dict:
    return json.loads(p.read_text())


def test_layout_and_splits(tiny: Path) -> None:
    cfg = preset("tiny")
    for name in ("transforms.json", "transforms_train.json", "transforms_val.json", "transforms_test.json",
                 "canonical_flame_param.npz", "model/synth_flame.pkl", "model/synth_flame.npz",
                 "model/FLAME_masks.pkl", "gt/canonical.ply", "gt/info.json"):
        assert (tiny / name).is_file(), name
    tr, va, te = (_load(tiny / f"transforms_{s}.json") for s in ("train", "val", "test"))
    n_t = cfg.train_timesteps + cfg.test_timesteps
    assert len(list((tiny / "images").glob("*.png"))) == n_t * cfg.n_cameras
    assert len(list((tiny / "gt" / "meshes").glob("*.ply"))) == n_t
    assert va["camera_indices"] == [8] and va["timestep_indices"] == list(range(cfg.train_timesteps))
    assert 8 not in tr["camera_indices"] and len(tr["camera_indices"]) == cfg.n_cameras - 1
    assert te["camera_indices"] == list(range(cfg.n_cameras))
    assert set(tr["timestep_indices"]).isdisjoint(te["timestep_indices"])
    assert te["timestep_indices"] == list(range(cfg.train_timesteps, n_t))
    every = _load(tiny / "transforms.json")
    assert len(every["frames"]) == len(tr["frames"]) + len(va["frames"]) + len(te["frames"])
    for js in (tr, va, te, every):
        last = js["frames"][-1]
        for k in ("cx", "cy", "fl_x", "fl_y", "h", "w", "camera_angle_x", "camera_angle_y"):
            assert js[k] == last[k]
    f = te["frames"][0]
    for k in ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "camera_index", "camera_id",
              "timestep_index", "timestep_index_original", "timestep_id", "file_path", "fg_mask_path", "flame_param_path",
              "transform_matrix"):
        assert k in f, k
    assert f["file_path"] == f"images/{f['timestep_index']:05d}_{f['camera_index']:02d}.png"
    assert image_size(tiny / f["file_path"]) == (128, 186, 3)
    assert image_size(tiny / f["fg_mask_path"]) == (128, 186, 1)
    assert abs(f["fl_x"] - f["w"] / (2 * np.tan(f["camera_angle_x"] / 2))) < 1e-6
    info = _load(tiny / "gt" / "info.json")
    assert info["counts"]["timesteps"] == n_t and len(info["timesteps"]) == n_t
    assert capture_model_path(tiny).is_file()


def test_flame_params_and_recentring(tiny: Path) -> None:
    n_v = load_flame_model(tiny / "model" / "synth_flame.npz").n_vertices
    trans = []
    for p in sorted((tiny / "flame_param").glob("*.npz")):
        with np.load(p) as z:
            assert set(z.files) == set(NPZ_SHAPES) | {"static_offset"}
            for k, shp in NPZ_SHAPES.items():
                assert z[k].shape == shp and z[k].dtype == np.float32, (p.name, k)
            assert z["static_offset"].shape == (1, n_v, 3)
            trans.append(z["translation"][0])
    np.testing.assert_allclose(np.mean(trans, 0), 0.0, atol=1e-6)
    with np.load(tiny / "canonical_flame_param.npz") as c:
        np.testing.assert_array_equal(c["jaw_pose"], np.array([[0.3, 0, 0]], np.float32))
        for k in ("translation", "rotation", "neck_pose", "eyes_pose", "expr"):
            assert not c[k].any()
        assert c["shape"].any() and c["static_offset"].any()


def test_params_reproduce_gt_meshes_and_land_in_masks(tiny: Path) -> None:
    model = FlameModel(load_flame_model(tiny / "model" / "synth_flame.npz")).double()
    frames = _load(tiny / "transforms.json")["frames"]
    verts = {}
    for ti in sorted({f["timestep_index"] for f in frames}):
        with np.load(tiny / "flame_param" / f"{ti:05d}.npz") as z:
            args = {k: torch.from_numpy(z[k].astype(np.float64)) for k in z.files}
        with torch.no_grad():
            v = model(**args).vertices[0].numpy()
        gt = trimesh.load(tiny / "gt" / "meshes" / f"{ti:05d}.ply", process=False)
        np.testing.assert_allclose(np.asarray(gt.vertices), v, atol=2e-5)
        verts[ti] = v
    inside = total = 0
    for f in frames:
        cam = camera_from_nerf_frame(f)
        mask = read_image(tiny / f["fg_mask_path"])[..., 0]
        uv, z = cam.project(verts[f["timestep_index"]])
        assert np.all(z > 0)
        assert np.all((uv >= 0) & (uv < [cam.width, cam.height]))
        # silhouette vertices sit on the matte's edge: test the 2x2 pixels whose centres surround them
        x0 = np.clip(np.floor(uv[:, 0] - 0.5).astype(int), 0, cam.width - 2)
        y0 = np.clip(np.floor(uv[:, 1] - 0.5).astype(int), 0, cam.height - 2)
        near = np.stack([mask[y0, x0], mask[y0, x0 + 1], mask[y0 + 1, x0], mask[y0 + 1, x0 + 1]], 1).max(1)
        inside += int((near > 0.5).sum())
        total += len(uv)
        img = read_image(tiny / f["file_path"])
        assert np.all(img[mask == 0] == 1.0)  # white outside the matte
    assert inside / total >= 0.99


def test_same_seed_same_bytes_other_seed_differs(tmp_path: Path) -> None:
    cfg = preset("tiny", n_cameras=3, width=48, height=70, train_timesteps=1, test_timesteps=1)
    a = write_capture(tmp_path / "a", cfg)
    b = write_capture(tmp_path / "b", cfg)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    c = write_capture(tmp_path / "c", cfg.with_overrides(seed=1))
    with np.load(a / "flame_param/00000.npz") as za, np.load(c / "flame_param/00000.npz") as zc:
        assert np.abs(za["shape"] - zc["shape"]).max() > 0.1
    assert np.abs(read_image(a / "images/00000_00.png") - read_image(c / "images/00000_00.png")).mean() > 0.01
    with pytest.raises(ConfigError):
        write_capture(tmp_path / "a", cfg)  # not empty and no force


def test_monocular_regime(tmp_path: Path) -> None:
    cfg = preset("tiny", regime="monocular", width=48, height=70, train_timesteps=3, test_timesteps=2,
                 novel_views=2, novel_expressions=1)
    out = write_capture(tmp_path / "mono", cfg)
    tr, va, te = (_load(out / f"transforms_{s}.json") for s in ("train", "val", "test"))
    assert va["frames"] == [] and tr["timestep_indices"] == [0, 1, 2] and te["timestep_indices"] == [3, 4]
    f = tr["frames"][0]
    np.testing.assert_allclose(np.asarray(f["transform_matrix"]), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]], atol=1e-12)
    assert f["cx"] == 24 and f["cy"] == 35 and f["fl_x"] == f["fl_y"]
    rots = []
    for ti in range(5):
        with np.load(out / "flame_param" / f"{ti:05d}.npz") as z:
            assert not z["expr"].any()
            rots.append(z["rotation"][0])
    assert np.ptp(np.array(rots)[:, 1]) > np.deg2rad(60)
    nv = _load(out / "gt" / "novel" / "transforms_test.json")
    assert len(nv["camera_indices"]) == 2 and (out / "gt" / "novel" / nv["frames"][0]["file_path"]).is_file()
    assert (out / "gt" / "novel" / "transforms_val.json").is_file()


def test_oneshot_regime_and_cli(tmp_path: Path) -> None:
    import typer
    from typer.testing import CliRunner

    from sage_cli.commands.synth import synth

    app = typer.Typer()
    app.command()(synth)
    app.command("noop")(lambda: None)
    out = tmp_path / "one"
    args = ["synth", str(out), "--regime", "oneshot", "--preset", "tiny", "--width", "48", "--height", "70", "--preview", "--seed", "3",
            "--set", "novel_around=1"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "sage synth" in res.output and "detailed: " in res.output  # the CLI's default appearance
    assert json.loads((out / "gt" / "info.json").read_text())["novel"]["cameras"] == preset("tiny").novel_views + 1
    tr = _load(out / "transforms_train.json")
    assert len(tr["frames"]) == 1 and _load(out / "transforms_test.json")["frames"] == []
    assert (out / "preview.png").is_file() and (out / "gt" / "novel" / "transforms_test.json").is_file()
    res = CliRunner().invoke(app, args)
    assert res.exit_code == ConfigError.exit_code
    res = CliRunner().invoke(app, [*args, "--force"])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(app, ["synth", str(tmp_path / "x"), "--regime", "stereo", "--preset", "tiny"])
    assert res.exit_code == ConfigError.exit_code
