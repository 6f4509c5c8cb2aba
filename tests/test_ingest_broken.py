"""A corpus of broken captures: each must fail with an error naming the offending file (or option)
before anything is written."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from fake_capture import MODEL_V, FakeSpec, make_fake_capture, make_tiny_model, vhap_params
from sage_core.data import ingest, read_capture, write_image
from sage_core.errors import ConfigError, InputError, SageError


def _edit_json(path: Path, fn: Callable[[dict], None]) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def _train_frame(doc: dict, i: int = 0) -> dict:
    return doc["frames"][i]


def missing_transforms(root: Path) -> str:
    (root / "transforms_train.json").unlink()
    return "transforms_train.json"


def missing_all_transforms(root: Path) -> str:
    for s in ("train", "val", "test"):
        (root / f"transforms_{s}.json").unlink()
    return "transforms_train.json"


def invalid_json(root: Path) -> str:
    p = root / "transforms_val.json"
    p.write_text(p.read_text()[:-40])
    return "transforms_val.json"


def missing_fl_x(root: Path) -> str:
    _edit_json(root / "transforms_train.json", lambda d: _train_frame(d, 1).pop("fl_x"))
    return "transforms_train.json"


def non_numeric_cx(root: Path) -> str:
    _edit_json(root / "transforms_test.json", lambda d: _train_frame(d).update(cx="12px"))
    return "transforms_test.json"


def bad_transform_matrix(root: Path) -> str:
    _edit_json(root / "transforms_train.json", lambda d: _train_frame(d).update(transform_matrix=[[1, 0], [0, 1]]))
    return "transforms_train.json"


def missing_image(root: Path) -> str:
    (root / "images" / "00001_01.png").unlink()
    return "00001_01.png"


def garbage_image(root: Path) -> str:
    (root / "images" / "00002_00.png").write_bytes(b"\x00garbage bytes, not an image" * 10)
    return "00002_00.png"


def wrong_image_size(root: Path) -> str:
    write_image(root / "images" / "00000_08.png", np.ones((30, 20, 3), np.float32))
    return "00000_08.png"


def missing_mask(root: Path) -> str:
    (root / "fg_masks" / "00003_01.png").unlink()
    return "00003_01.png"


def npz_missing_expr(root: Path) -> str:
    d = vhap_params(1)
    d.pop("expr")
    np.savez(root / "flame_param" / "00001.npz", **d)
    return "00001.npz"


def npz_with_nan(root: Path) -> str:
    d = vhap_params(2)
    d["jaw_pose"][0, 1] = np.nan
    np.savez(root / "flame_param" / "00002.npz", **d)
    return "00002.npz"


def npz_missing_file(root: Path) -> str:
    (root / "flame_param" / "00003.npz").unlink()
    return "00003.npz"


def npz_changing_shape(root: Path) -> str:
    d = vhap_params(2)
    d["shape"] = d["shape"] + 1.0
    np.savez(root / "flame_param" / "00002.npz", **d)
    return "00002.npz"


def static_offset_rows_incompatible(root: Path) -> str:
    for t in range(4):
        np.savez(root / "flame_param" / f"{t:05d}.npz", **vhap_params(t, n_vertices=MODEL_V + 7))
    return "00000.npz"


def empty_train_split(root: Path) -> str:
    _edit_json(root / "transforms_train.json", lambda d: d.update(frames=[]))
    return "transforms_train.json"


def duplicate_frame(root: Path) -> str:
    _edit_json(root / "transforms_train.json", lambda d: d["frames"].append(dict(d["frames"][0])))
    return "transforms_train.json"


def image_path_escapes_the_capture(root: Path) -> str:
    _edit_json(root / "transforms_train.json", lambda d: _train_frame(d).update(file_path="../../etc/hostname"))
    return "../../etc/hostname"


def absolute_flame_path(root: Path) -> str:
    _edit_json(root / "transforms_train.json", lambda d: _train_frame(d).update(flame_param_path="/etc/hostname"))
    return "/etc/hostname"


def missing_folder(root: Path) -> str:
    import shutil

    shutil.rmtree(root)
    return root.name


CASES = [
    missing_transforms, missing_all_transforms, invalid_json, missing_fl_x, non_numeric_cx, bad_transform_matrix,
    missing_image, garbage_image, wrong_image_size, missing_mask, npz_missing_expr, npz_with_nan,
    npz_missing_file, npz_changing_shape, static_offset_rows_incompatible, empty_train_split, duplicate_frame,
    image_path_escapes_the_capture, absolute_flame_path, missing_folder,
]


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tiny_model(tmp_path_factory.mktemp("model") / "flame.npz")


def _run(root: Path, model: Path, out: Path, **kw) -> None:
    ingest(read_capture(root), model, out, **kw)


@pytest.mark.parametrize("breaker", CASES, ids=[c.__name__ for c in CASES])
def test_broken_capture(tmp_path: Path, model_path: Path, breaker: Callable[[Path], str]) -> None:
    root = make_fake_capture(tmp_path / "seq", FakeSpec(n_train_timesteps=3))
    culprit = breaker(root)
    out = tmp_path / "out"
    with pytest.raises(InputError) as info:
        _run(root, model_path, out)
    msg = str(info.value)
    assert culprit in msg, msg
    assert culprit in str(info.value.path) or culprit in info.value.problem
    assert not out.exists()
    assert "Traceback" not in msg and len(msg) < 4000


def test_unknown_regime(tmp_path: Path, model_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    with pytest.raises(ConfigError, match="unknown regime 'multiview'.*mv-sf"):
        _run(root, model_path, tmp_path / "out", regime="multiview")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("kw, needle", [
    ({"regime": "one-shot"}, "one-shot uses a single image"),
    ({"regime": "sv-hr"}, "sv-hr needs one camera"),
    ({"regime": "mv-sf", "timestep": 99}, "timestep 99"),
    ({"downsample": -1.0}, "downsample"),
    ({"height": 3}, "height"),
    ({"workers": 0}, "workers"),
])
def test_bad_options(tmp_path: Path, model_path: Path, kw: dict, needle: str) -> None:
    root = make_fake_capture(tmp_path / "seq")
    with pytest.raises(ConfigError, match=needle):
        _run(root, model_path, tmp_path / "out", **kw)
    assert not (tmp_path / "out").exists()


def test_missing_model_and_masks(tmp_path: Path, model_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq")
    cap = read_capture(root)
    with pytest.raises(InputError) as info:
        ingest(cap, tmp_path / "nope.pkl", tmp_path / "out")
    assert info.value.path.name == "nope.pkl"
    with pytest.raises(InputError) as info:
        ingest(cap, model_path, tmp_path / "out", masks_path=tmp_path / "FLAME_masks.pkl")
    assert info.value.path.name == "FLAME_masks.pkl"
    assert not (tmp_path / "out").exists()


def test_black_background_without_masks(tmp_path: Path, model_path: Path) -> None:
    root = make_fake_capture(tmp_path / "seq", FakeSpec(with_masks=False))
    with pytest.raises(InputError, match="black background needs foreground masks") as info:
        _run(root, model_path, tmp_path / "out", background="black")
    assert info.value.path.name.startswith("transforms_")
    assert not (tmp_path / "out").exists()


def test_errors_are_sage_errors(tmp_path: Path) -> None:
    with pytest.raises(SageError):
        read_capture(tmp_path / "does-not-exist")
