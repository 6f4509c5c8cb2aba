"""Evaluation protocol: render every frame of a split and compare it with its ground truth.

Protocol (docs/formats.md §8): the caller's ``render_fn`` poses the avatar with the frame's FLAME
parameters and renders it with the frame's camera on the dataset background (white). The render
and the ground-truth PNG are both clamped to [0, 1] and compared over the full image, without a
mask. Per image this computes

- ``psnr``: standard PSNR, ``10·log10(1 / MSE)`` with the MSE over all pixels × 3 channels;
- ``psnr_ga``: the GaussianAvatars ``train.py`` variant (PSNR per channel, then their mean), which is
  >= the standard value; it is reported beside it, labelled, never in its place;
- ``ssim``: 11×11 Gaussian window, σ = 1.5, mean over the map;
- ``lpips``: AlexNet v0.1, or None when no LPIPS weights are available (reported as unavailable,
  never as a number).

Split means average over all images. Identical images have an infinite PSNR: with
``psnr_cap=None`` the means are then +inf as well, and :meth:`EvalReport.to_dict` writes every
infinite value as the string ``"inf"`` (and a NaN, e.g. from a render holding NaN, as ``null``);
with a number every per-image PSNR is capped at it before averaging, so everything stays finite.

Frames are processed one at a time: at most one render and one ground-truth image are in memory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import numpy as np
import torch

from ..data.dataset import sample_indices
from ..errors import InputError
from ..image_metrics import psnr, psnr_per_channel_mean, ssim
from .lpips import LPIPS

if TYPE_CHECKING:
    from ..data.dataset import IngestedData, IngestedFrame

RenderFn = Callable[["IngestedFrame"], torch.Tensor]
"""``render_fn(frame) -> (H, W, 3)`` float tensor in [0, 1] (any device)."""

Progress = Callable[[int, int, str], None]
"""``progress(done, total, message)``."""

FRONTAL_CAMERA = 8
"""Camera index of the frontal view in NeRSemble exports (the paper's "frontal" column)."""

ERROR_GAIN = 4.0
"""Sample strips show ``min(1, ERROR_GAIN · mean_c |render − gt|)`` as grey: white = a mean
absolute error of 0.25 or more, black = no error."""

PSNR_LABEL = "standard: per image 10*log10(1/MSE), MSE over all pixels x 3 channels, max 1"
PSNR_GA_LABEL = "GaussianAvatars train.py variant: per-channel PSNR, then their mean"
METRICS_FILE = "metrics.json"
SAMPLES_DIR = "images"


@dataclass
class ImageMetrics:
    """Metrics of one evaluated image (PSNR values capped when the report has a cap)."""

    timestep: int
    camera: int
    psnr: float
    psnr_ga: float
    ssim: float
    lpips: float | None


@dataclass
class MetricMeans:
    """Means over a group of images; ``lpips`` is None when LPIPS is unavailable or the group is empty."""

    count: int
    psnr: float
    psnr_ga: float
    ssim: float
    lpips: float | None

    @staticmethod
    def of(images: list[ImageMetrics]) -> MetricMeans:
        """Means of ``images`` (NaN for an empty list). Images whose PSNR is NaN (a region metric over an
        empty region, e.g. a view of the back of the head that no training view saw) are left out;
        ``count`` is the number of images in the means."""
        def mean(values: list[float]) -> float:
            return float(np.mean(np.asarray(values, dtype=np.float64))) if values else math.nan

        images = [m for m in images if not math.isnan(m.psnr)]
        lp = [m.lpips for m in images]
        return MetricMeans(
            count=len(images),
            psnr=mean([m.psnr for m in images]),
            psnr_ga=mean([m.psnr_ga for m in images]),
            ssim=mean([m.ssim for m in images]),
            lpips=mean([float(v) for v in lp]) if lp and all(v is not None for v in lp) else None,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "count": self.count,
            "psnr": _json_float(self.psnr),
            "psnr_ga": _json_float(self.psnr_ga),
            "ssim": _json_float(self.ssim),
            "lpips": _json_float(self.lpips),
        }


def _json_float(v: float | None) -> float | str | None:
    """JSON-safe number: +inf/-inf -> "inf"/"-inf", NaN and None -> None."""
    if v is None or math.isnan(v):
        return None
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return float(v)


def _fmt(v: float | None, digits: int) -> str:
    if v is None:
        return "n/a"
    if math.isnan(v):
        return "nan"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.{digits}f}"


@dataclass
class EvalReport:
    """Result of :func:`evaluate_frames`.

    Attributes:
        images: one row per evaluated image, in evaluation order.
        per_camera: camera index -> means over that camera's images.
        overall: means over all images.
        frontal: means over the images of camera 8, or None when it was not evaluated.
        n_timesteps, n_cameras: distinct timesteps / cameras evaluated.
        lpips_available: False when no LPIPS model was given (every ``lpips`` is then None).
        lpips_inputs: "[-1,1]" (standard) or "[0,1]" (GaussianAvatars quirk), None without LPIPS.
        psnr_cap: the cap applied to every per-image PSNR, or None (infinite values kept).
        samples: paths of the written sample strips.
        metrics_path: the written ``metrics.json``, or None.
    """

    images: list[ImageMetrics]
    per_camera: dict[int, MetricMeans]
    overall: MetricMeans
    frontal: MetricMeans | None
    n_timesteps: int
    n_cameras: int
    lpips_available: bool
    lpips_inputs: str | None = None
    psnr_cap: float | None = None
    samples: list[Path] = field(default_factory=list)
    metrics_path: Path | None = None

    COLUMNS: ClassVar[tuple[str, ...]] = ("group", "images", "PSNR", "PSNR (GA)", "SSIM", "LPIPS")

    @property
    def n_images(self) -> int:
        return len(self.images)

    @staticmethod
    def build(images: list[ImageMetrics], *, lpips_available: bool, lpips_inputs: str | None = None,
              psnr_cap: float | None = None) -> EvalReport:
        """Aggregate per-image rows into per-camera, frontal and overall means."""
        cams = sorted({m.camera for m in images})
        per_camera = {c: MetricMeans.of([m for m in images if m.camera == c]) for c in cams}
        return EvalReport(
            images=list(images),
            per_camera=per_camera,
            overall=MetricMeans.of(images),
            frontal=per_camera.get(FRONTAL_CAMERA),
            n_timesteps=len({m.timestep for m in images}),
            n_cameras=len(cams),
            lpips_available=lpips_available,
            lpips_inputs=lpips_inputs,
            psnr_cap=psnr_cap,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe form: infinite PSNR as the string "inf", NaN and unavailable LPIPS as null."""
        return {
            "protocol": {
                "background": "as rendered by the caller (dataset background)",
                "clamp": [0.0, 1.0],
                "mask": None,
                "psnr": PSNR_LABEL,
                "psnr_ga": PSNR_GA_LABEL,
                "psnr_cap": self.psnr_cap,
                "infinite_values": "written as the string 'inf'",
                "ssim": "11x11 Gaussian window, sigma 1.5, C1=0.01^2, C2=0.03^2, zero-padded",
                "lpips": "AlexNet v0.1" if self.lpips_available else "unavailable (no weights)",
                "lpips_inputs": self.lpips_inputs,
            },
            "counts": {"images": self.n_images, "timesteps": self.n_timesteps, "cameras": self.n_cameras},
            "lpips_available": self.lpips_available,
            "overall": self.overall.to_dict(),
            "frontal_camera": FRONTAL_CAMERA,
            "frontal": None if self.frontal is None else self.frontal.to_dict(),
            "per_camera": {str(c): m.to_dict() for c, m in self.per_camera.items()},
            "images": [
                {
                    "timestep": m.timestep,
                    "camera": m.camera,
                    "psnr": _json_float(m.psnr),
                    "psnr_ga": _json_float(m.psnr_ga),
                    "ssim": _json_float(m.ssim),
                    "lpips": _json_float(m.lpips),
                }
                for m in self.images
            ],
            "samples": sample_refs(self.samples, self.metrics_path),
        }

    def rows(self) -> list[tuple[str, ...]]:
        """Table rows matching :attr:`COLUMNS`: one per camera, then "frontal (cam 8)" and "all"."""
        def row(name: str, m: MetricMeans) -> tuple[str, ...]:
            return (name, str(m.count), _fmt(m.psnr, 2), _fmt(m.psnr_ga, 2), _fmt(m.ssim, 4), _fmt(m.lpips, 4))

        out = [row(f"camera {c}", m) for c, m in self.per_camera.items()]
        if self.frontal is not None:
            out.append(row(f"frontal (cam {FRONTAL_CAMERA})", self.frontal))
        out.append(row("all", self.overall))
        return out


def sample_refs(samples: list[Path], metrics_path: Path | None) -> list[str]:
    """Sample-strip paths as written into ``metrics.json``: relative to its folder (so they stay valid
    when the result folder moves), absolute when a strip lies elsewhere or there is no file."""
    out: list[str] = []
    for p in samples:
        try:
            out.append(Path(p).relative_to(metrics_path.parent).as_posix() if metrics_path is not None else str(p))
        except ValueError:
            out.append(str(p))
    return out


def error_strip(gt: torch.Tensor, render: torch.Tensor) -> np.ndarray:
    """Side-by-side ``GT | render | error`` image.

    gt, render: (H, W, 3) in [0, 1] -> (H, 3W, 3) float32 numpy; the error panel is grey
    ``min(1, ERROR_GAIN · mean_c |render − gt|)``.
    """
    err = ((render - gt).abs().mean(-1, keepdim=True) * ERROR_GAIN).clamp(0.0, 1.0).expand_as(gt)
    strip = torch.cat([gt, render, err], dim=1)
    return strip.detach().to(torch.float32).cpu().numpy()


def _lpips_device(model: LPIPS) -> torch.device:
    buf = next(iter(model.buffers()), None)
    return buf.device if buf is not None else torch.device("cpu")


def _check_render(frame: IngestedFrame, render: Any, gt_shape: tuple[int, ...]) -> torch.Tensor:
    if not isinstance(render, torch.Tensor):
        raise TypeError(f"render_fn returned {type(render).__name__}, expected a torch.Tensor (H, W, 3)")
    if tuple(render.shape) != gt_shape:
        raise ValueError(
            f"render_fn returned shape {tuple(render.shape)} for timestep {frame.timestep}, camera "
            f"{frame.camera_index}; the ground truth is {gt_shape}"
        )
    return render


@torch.no_grad()
def evaluate_frames(
    render_fn: RenderFn,
    data: IngestedData,
    frames: list[IngestedFrame],
    *,
    lpips: LPIPS | None,
    out_dir: Path | None,
    n_samples: int = 8,
    psnr_cap: float | None = None,
    progress: Progress | None = None,
) -> EvalReport:
    """Evaluate ``render_fn`` on ``frames`` with the protocol of docs/formats.md §8.

    render_fn: ``frame -> (H, W, 3)`` float tensor in [0, 1], H×W the frame's ground-truth size.
        It runs under ``torch.no_grad()`` (use ``torch.enable_grad()`` inside if it needs autograd).
    data: the ingested data the frames belong to (ground-truth images).
    frames: the frames to evaluate (e.g. ``data.val`` for novel views, ``data.test`` for
        self-reenactment).
    lpips: the LPIPS model, or None (LPIPS reported as unavailable).
    out_dir: when given, writes ``out_dir/metrics.json`` (atomically, last) and sample strips
        ``out_dir/images/{ti:05d}_{ci:02d}.png`` (GT | render | error, see :data:`ERROR_GAIN`) for
        ``n_samples`` evenly spaced frames.
    psnr_cap: None keeps infinite PSNR (identical images); a number caps each per-image PSNR.
    progress: ``progress(done, total, message)`` after each frame.
    Raises InputError when a ground-truth image cannot be read or has another size than the
    frame's camera, ValueError when ``frames`` is empty or a render has the wrong shape.
    """
    if not frames:
        raise ValueError("evaluate_frames needs at least one frame")
    samples = set(sample_indices(len(frames), n_samples if out_dir is not None else 0))
    lp_device = _lpips_device(lpips) if lpips is not None else None
    rows: list[ImageMetrics] = []
    written: list[Path] = []
    total = len(frames)
    for i, frame in enumerate(frames):
        gt_np = data.load_image(frame)
        h, w = gt_np.shape[:2]
        if (w, h) != (frame.camera.width, frame.camera.height):
            raise InputError(frame.image, f"image is {w}x{h} but its camera is "
                                          f"{frame.camera.width}x{frame.camera.height}")
        render = _check_render(frame, render_fn(frame), gt_np.shape)
        render = render.detach().to(torch.float32).clamp(0.0, 1.0)
        gt = torch.from_numpy(gt_np).to(render.device).clamp(0.0, 1.0)
        pred_c = render.permute(2, 0, 1)
        gt_c = gt.permute(2, 0, 1)
        lp_val: float | None = None
        if lpips is not None:
            lp_val = float(lpips(pred_c.to(lp_device), gt_c.to(lp_device)))
        m = ImageMetrics(
            timestep=int(frame.timestep),
            camera=int(frame.camera_index),
            psnr=float(psnr(pred_c, gt_c, cap=psnr_cap)),
            psnr_ga=float(psnr_per_channel_mean(pred_c, gt_c, cap=psnr_cap)),
            ssim=float(ssim(pred_c, gt_c)),
            lpips=lp_val,
        )
        rows.append(m)
        if i in samples:
            from ..data.imageio import write_image

            assert out_dir is not None
            path = Path(out_dir) / SAMPLES_DIR / f"{frame.timestep:05d}_{frame.camera_index:02d}.png"
            write_image(path, error_strip(gt, render))
            written.append(path)
        del render, gt, gt_np
        if progress is not None:
            progress(i + 1, total, f"timestep {frame.timestep} camera {frame.camera_index}: PSNR {_fmt(m.psnr, 2)}")

    report = EvalReport.build(
        rows,
        lpips_available=lpips is not None,
        lpips_inputs=None if lpips is None else ("[-1,1]" if lpips.rescale_inputs else "[0,1]"),
        psnr_cap=psnr_cap,
    )
    report.samples = written
    if out_dir is not None:
        from ..workspace import atomic_write_json

        report.metrics_path = Path(out_dir) / METRICS_FILE
        atomic_write_json(report.metrics_path, report.to_dict())
    return report
