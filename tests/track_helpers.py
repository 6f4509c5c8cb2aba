"""Helpers of the ``sage track`` tests: where the MediaPipe face models are (tests that need them skip
without them), the CLI run in-process, and small synthetic inputs."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def _models_dir() -> str | None:
    """The face models where sage finds them ($SAGE_MEDIAPIPE_DIR, then the cache), else the copy
    beside the checkout (../shared/weights/mediapipe, as CI offers it), else None."""
    from sage_core.track.weights import cache_folder, models_available

    candidates = [os.environ.get("SAGE_MEDIAPIPE_DIR") or None, str(cache_folder()),
                  str(REPO.parent / "shared" / "weights" / "mediapipe")]
    for c in candidates:
        if c and Path(c).is_dir() and models_available(c) is None:
            return c
    return None


def _litert() -> str | None:
    from sage_core.track.litert import litert_available

    return litert_available()


MODELS_DIR = _models_dir()
SKIP_REASON = ("MediaPipe face models not found: set SAGE_MEDIAPIPE_DIR or run `sage track-models`" if MODELS_DIR is None
               else _litert())


def models_or_skip() -> Path:
    """The models folder, or skip the test with the reason."""
    if MODELS_DIR is None or SKIP_REASON is not None:
        pytest.skip(SKIP_REASON or "MediaPipe face models not found")
    return Path(MODELS_DIR)


def invoke(args: list[Any], **env: str) -> Any:
    """Run ``sage <args>`` (the full app) in-process with the models folder set; returns typer's Result."""
    from typer.testing import CliRunner

    from sage_cli.app import app

    env = {"SAGE_MEDIAPIPE_DIR": MODELS_DIR or "", "SAGE_LPIPS_WEIGHTS": "", "COLUMNS": "200", **env}
    return CliRunner().invoke(app, [str(a) for a in args], env=env)


def astronaut() -> np.ndarray:
    """``skimage.data.astronaut()`` (a real photograph shipped with scikit-image) as float32 RGB in [0, 1]."""
    from skimage import data

    return (data.astronaut() / 255.0).astype(np.float32)


def write_png(path: Path, image: np.ndarray) -> Path:
    from sage_core.data.imageio import write_image

    write_image(path, image)
    return path
