"""Image metrics (PSNR, SSIM, LPIPS AlexNet v0.1) and the evaluation protocol.

PSNR and SSIM live in :mod:`sage_core.image_metrics` (training uses them too) and are re-exported here.
"""

from ..image_metrics import (
    mean_psnr,
    psnr,
    psnr_per_channel_mean,
    ssim,
    ssim_map,
    to_nchw,
)
from .lpips import (
    DEFAULT_CACHE_PATH,
    ENV_VAR,
    LPIPS,
    LPIPS_ALEX_SHA256,
    find_lpips_weights,
    load_lpips_or_none,
    load_lpips_state_dict,
    lpips_or_none,
)
from .novel import NovelReport, NovelSet, evaluate_novel, open_novel_set, region_metrics, training_face_visibility, visible_region
from .protocol import EvalReport, ImageMetrics, MetricMeans, evaluate_frames

__all__ = [
    "NovelReport",
    "NovelSet",
    "evaluate_novel",
    "open_novel_set",
    "region_metrics",
    "training_face_visibility",
    "visible_region",
    "DEFAULT_CACHE_PATH",
    "EvalReport",
    "ImageMetrics",
    "MetricMeans",
    "evaluate_frames",
    "ENV_VAR",
    "LPIPS",
    "LPIPS_ALEX_SHA256",
    "find_lpips_weights",
    "load_lpips_or_none",
    "load_lpips_state_dict",
    "lpips_or_none",
    "mean_psnr",
    "psnr",
    "psnr_per_channel_mean",
    "ssim",
    "ssim_map",
    "to_nchw",
]
