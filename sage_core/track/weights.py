"""The three MediaPipe face models ``sage track`` runs: where they are found, how they are checked
and how they are installed from the ``mediapipe`` wheel.

sage never downloads anything at run time. The models are found through ``$SAGE_MEDIAPIPE_DIR``
(a folder), then the cache folder ``~/.cache/sage/mediapipe/`` (``$SAGE_CACHE_DIR/mediapipe`` when
that variable is set); every file is checked against its SHA-256 before use. :func:`install_models`
copies them out of the ``mediapipe`` 0.10.21 wheel (Apache-2.0), which ``sage track-models``
fetches with ``pip download`` once, on request.

Only the standard library is imported here.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..atomic import atomic_write_bytes
from ..errors import InputError
from ..pip_fetch import download_wheel as pip_download
from ..workspace import file_sha256

ENV_VAR = "SAGE_MEDIAPIPE_DIR"
WHEEL_REQUIREMENT = "mediapipe==0.10.21"
WHEEL_TAGS = ("--python-version", "3.11", "--platform", "manylinux_2_28_x86_64", "--only-binary=:all:")
"""One fixed wheel (the same bytes on every machine); only three files are taken out of it."""


@dataclass(frozen=True)
class ModelFile:
    """One model: its file name, its path inside the wheel and its SHA-256."""

    name: str
    wheel_path: str
    sha256: str


DETECTOR = ModelFile("face_detection_short_range.tflite",
                     "mediapipe/modules/face_detection/face_detection_short_range.tflite",
                     "bbff11cebd1eb27a1e004cae0b0e63ec8c551cbf34a4451148b4908b8db3eca8")
LANDMARKS = ModelFile("face_landmark.tflite", "mediapipe/modules/face_landmark/face_landmark.tflite",
                      "1055cb9d4a9ca8b8c688902a3a5194311138ba256bcc94e336d8373a5f30c814")
SEGMENTER = ModelFile("selfie_segmentation.tflite", "mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite",
                      "9ee168ec7c8f2a16c56fe8e1cfbc514974cbbb7e434051b455635f1bd1462f5c")
MODEL_FILES: tuple[ModelFile, ...] = (DETECTOR, LANDMARKS, SEGMENTER)
LICENSE_NAME = "LICENSE"
INSTALL_HINT = "install them with `sage track-models` (fetches the mediapipe 0.10.21 wheel with pip and checks the hashes)"


def cache_folder() -> Path:
    """``$SAGE_CACHE_DIR/mediapipe`` or ``~/.cache/sage/mediapipe`` (not created)."""
    root = os.environ.get("SAGE_CACHE_DIR")
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "sage"
    return base / "mediapipe"




@dataclass(frozen=True)
class ModelPaths:
    """The verified model files: ``detector``, ``landmarks``, ``segmenter`` and their folder."""

    folder: Path
    detector: Path
    landmarks: Path
    segmenter: Path


def _check_folder(folder: Path, source: str) -> ModelPaths:
    """Verify every model file in ``folder`` (InputError naming the first missing or altered one)."""
    paths = {}
    for mf in MODEL_FILES:
        p = folder / mf.name
        if not p.is_file():
            raise InputError(p, f"MediaPipe model file not found ({source}); {INSTALL_HINT}")
        digest = file_sha256(p)
        if digest != mf.sha256:
            raise InputError(p, f"SHA-256 {digest[:16]}… differs from the expected {mf.sha256[:16]}… (a damaged or "
                                f"different file); {INSTALL_HINT}")
        paths[mf.name] = p
    return ModelPaths(folder, paths[DETECTOR.name], paths[LANDMARKS.name], paths[SEGMENTER.name])


def find_models(explicit: str | Path | None = None) -> ModelPaths:
    """Locate and verify the three models.

    Order: ``explicit`` (a folder), then ``$SAGE_MEDIAPIPE_DIR``, then :func:`cache_folder`. A folder
    the user named that lacks a file or holds an altered one raises InputError naming the file; so
    does an empty cache, with the command that installs the models.
    """
    if explicit is not None and str(explicit) != "":
        return _check_folder(Path(explicit).expanduser(), "folder given on the command line")
    env = os.environ.get(ENV_VAR, "")
    if env:
        return _check_folder(Path(env).expanduser(), f"folder named by ${ENV_VAR}")
    return _check_folder(cache_folder(), "sage's cache folder")


def models_available(explicit: str | Path | None = None) -> str | None:
    """None when :func:`find_models` succeeds, else the reason it does not (one sentence)."""
    try:
        find_models(explicit)
    except InputError as err:
        return str(err)
    return None


def install_from_wheel(wheel: str | Path, dest: str | Path | None = None) -> ModelPaths:
    """Copy the three models (and the wheel's LICENSE) out of a ``mediapipe`` wheel into ``dest``.

    wheel: the ``.whl`` file (a zip archive). dest: target folder (default :func:`cache_folder`).
    Every file's SHA-256 is checked before anything is written; InputError names the wheel and the
    file when one is missing or differs. Files are written atomically. Returns the verified paths.
    """
    wheel = Path(wheel)
    target = Path(dest).expanduser() if dest is not None else cache_folder()
    if not wheel.is_file():
        raise InputError(wheel, "wheel file not found")
    try:
        zf = zipfile.ZipFile(wheel)
    except (zipfile.BadZipFile, OSError) as exc:
        raise InputError(wheel, f"not a wheel (zip) archive: {exc}") from None
    blobs: dict[str, bytes] = {}
    with zf:
        names = zf.namelist()
        for mf in MODEL_FILES:
            if mf.wheel_path not in names:
                raise InputError(wheel, f"the wheel holds no {mf.wheel_path} (is it mediapipe 0.10.21?)")
            data = zf.read(mf.wheel_path)
            digest = hashlib.sha256(data).hexdigest()
            if digest != mf.sha256:
                raise InputError(wheel, f"{mf.wheel_path} has SHA-256 {digest[:16]}…, expected {mf.sha256[:16]}…")
            blobs[mf.name] = data
        lic = [n for n in names if n.endswith(".dist-info/" + LICENSE_NAME)]
        license_text = zf.read(lic[0]) if lic else None
    target.mkdir(parents=True, exist_ok=True)
    for name, data in blobs.items():
        atomic_write_bytes(target / name, data)
    if license_text is not None:
        atomic_write_bytes(target / LICENSE_NAME, license_text)
    return _check_folder(target, "just installed")


def download_wheel(folder: str | Path, pip: list[str] | None = None) -> Path:
    """Fetch the mediapipe wheel with ``pip download`` into ``folder``; returns the wheel's path.

    pip: the command that runs pip (default: this interpreter's ``-m pip``). Raises InputError with
    pip's last lines when the download fails (no network, no index).
    """
    return pip_download(WHEEL_REQUIREMENT, folder, "mediapipe-*.whl", WHEEL_TAGS, pip)


def install_models(dest: str | Path | None = None, wheel: str | Path | None = None) -> ModelPaths:
    """Install the models into ``dest`` (default :func:`cache_folder`): from ``wheel`` when given,
    else from a wheel fetched with :func:`download_wheel` into a temporary folder (removed after)."""
    if wheel is not None:
        return install_from_wheel(wheel, dest)
    tmp = Path(tempfile.mkdtemp(prefix="sage-mediapipe-"))
    try:
        return install_from_wheel(download_wheel(tmp), dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
