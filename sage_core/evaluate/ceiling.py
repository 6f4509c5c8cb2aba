"""The tracking ceiling of a workspace on a synthetic capture, under the evaluation protocol.

:class:`~sage_core.data.synthetic.ceiling.TrackedTruth` renders the capture's ground-truth
appearance on its written model posed with the workspace's FLAME parameters: the avatar every
FLAME-driven method would be if it learned the head perfectly. Evaluated like an avatar
(docs/formats.md §8: the same frames, ground truth, PSNR / SSIM / LPIPS), it tells how much of a row's
error on held-out expressions is the tracking's and how much the method's. On the training
timesteps it is no reference: an avatar fitted to those images absorbs their tracking error, the
ceiling does not.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..data.dataset import IngestedData
from ..data.synthetic.ceiling import FLAME_KEYS, TrackedTruth
from .lpips import load_lpips_or_none
from .protocol import EvalReport, Progress, evaluate_frames

if TYPE_CHECKING:
    from ..data.dataset import IngestedFrame

CEILING_STAGE = "ceiling"
"""Folder name of the ceiling's results under ``WS/eval/`` (beside the avatar stages')."""


def ceiling_render_fn(truth: TrackedTruth, data: IngestedData):
    """``frame -> (H, W, 3)`` tensor: the ceiling render of an ingested frame with its FLAME
    parameters and (resized) camera."""

    def render(frame: IngestedFrame) -> torch.Tensor:
        row = data.params.row_of(frame.timestep)
        params = {k: np.asarray(getattr(data.params, k)[row]) for k in FLAME_KEYS}
        return torch.from_numpy(truth.render(params, frame.camera))

    return render


def evaluate_ceiling(
    capture: str | Path,
    workspace: str | Path,
    split: str = "test",
    lpips_weights: str | Path | None = None,
    n_samples: int = 8,
    progress: Progress | None = None,
) -> EvalReport:
    """Evaluate the tracking ceiling of ``capture`` on ``split`` ("test", "val" or "train") of the
    data ingested in ``workspace`` and write ``WS/eval/ceiling/<split>/metrics.json`` with sample
    strips. LPIPS weights are found as ``sage eval`` finds them. Raises InputError when the capture
    is not a ``sage synth`` capture or the split is empty."""
    from ..errors import InputError

    ws = Path(workspace)
    data = IngestedData.open(ws / "data")
    frames = data.role(split)
    if not frames:
        raise InputError(ws / "data", f"the {split} split has no frames")
    truth = TrackedTruth.open(capture)
    lpips = load_lpips_or_none(lpips_weights)
    out = ws / "eval" / CEILING_STAGE / split
    return evaluate_frames(ceiling_render_fn(truth, data), data, frames, lpips=lpips, out_dir=out, n_samples=n_samples, progress=progress)
