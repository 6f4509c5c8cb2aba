"""Image metrics: PSNR (standard and the GaussianAvatars per-channel variant) and SSIM.

One low-level module (torch, numpy and the native SSIM blur) shared by training (the SSIM loss, PSNR on the
validation views) and evaluation (:mod:`sage_core.evaluate`, which adds LPIPS and the protocol).

Canonical layout: batched channels-first tensors ``(B, C, H, W)``; a single ``(C, H, W)`` image
is also accepted and gives a 0-d result. Images stored channels-last (``(H, W, C)`` or
``(B, H, W, C)``, as :func:`sage_core.data.imageio.read_image` returns) go through
:func:`to_nchw` first. Values are in [0, 1] (data range 1).

Protocol (docs/formats.md §8): PSNR clamps both images to [0, 1] itself. SSIM does not clamp, because it
is also a training loss (``0.8·L1 + 0.2·(1 − SSIM)``) and clamping would cut gradients; the
evaluation caller clamps renders before calling it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .native_build import native_extension

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def to_nchw(image: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Channels-last image(s) to the canonical layout.

    image: (H, W, C) or (B, H, W, C), numpy or torch -> (1, C, H, W) or (B, C, H, W) torch tensor
    (numpy arrays become CPU tensors of the same dtype; integer arrays are not rescaled).
    """
    t = torch.from_numpy(np.ascontiguousarray(image)) if isinstance(image, np.ndarray) else image
    if t.dim() == 3:
        t = t.unsqueeze(0)
    if t.dim() != 4:
        raise ValueError(f"expected (H, W, C) or (B, H, W, C), got shape {tuple(t.shape)}")
    return t.permute(0, 3, 1, 2).contiguous()


def _check_pair(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Validate a pair and return them as (B, C, H, W) plus whether the input was unbatched."""
    if pred.shape != gt.shape:
        raise ValueError(f"image shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    if pred.dim() == 3:
        return pred.unsqueeze(0), gt.unsqueeze(0), True
    if pred.dim() != 4:
        raise ValueError(f"expected (B, C, H, W) or (C, H, W), got shape {tuple(pred.shape)}")
    return pred, gt, False


def _mse_to_psnr(mse: torch.Tensor, cap: float | None) -> torch.Tensor:
    out = 10.0 * torch.log10(1.0 / mse)  # mse == 0 -> +inf
    if cap is not None:
        out = out.clamp_max(cap)
    return out


def psnr(pred: torch.Tensor, gt: torch.Tensor, cap: float | None = None) -> torch.Tensor:
    """Standard PSNR per image, ``10·log10(1 / MSE)`` with max 1 (docs/formats.md §8).

    Both images are clamped to [0, 1]; the MSE is over all pixels × channels.

    pred, gt: (B, C, H, W) or (C, H, W) -> (B,) or 0-d, in dB.
    cap: None gives +inf for identical images; a number (e.g. 100.0) caps every value at it.
    """
    pred, gt, single = _check_pair(pred, gt)
    diff = pred.clamp(0.0, 1.0) - gt.clamp(0.0, 1.0)
    mse = diff.square().flatten(1).mean(1)
    out = _mse_to_psnr(mse, cap)
    return out[0] if single else out


def psnr_per_channel_mean(
    pred: torch.Tensor, gt: torch.Tensor, cap: float | None = None
) -> torch.Tensor:
    """GaussianAvatars ``train.py`` variant: PSNR of each channel separately, then their mean.

    This is >= :func:`psnr` (Jensen) and equal only when the channel MSEs are equal. Report it
    labelled as the GA variant. Clamps to [0, 1] like :func:`psnr`.

    pred, gt: (B, C, H, W) or (C, H, W) -> (B,) or 0-d, in dB. cap: as in :func:`psnr`, applied
    to each channel's PSNR (so an identical channel contributes ``cap`` instead of +inf).
    """
    pred, gt, single = _check_pair(pred, gt)
    diff = pred.clamp(0.0, 1.0) - gt.clamp(0.0, 1.0)
    mse = diff.square().flatten(2).mean(2)  # (B, C)
    out = _mse_to_psnr(mse, cap).mean(1)
    return out[0] if single else out


def mean_psnr(values: torch.Tensor | Sequence[float], cap: float | None = None) -> float:
    """Mean of per-image PSNR values over a split.

    values: (M,) per-image PSNR in dB (may contain +inf for identical pairs).
    cap: None reports +inf when any image is identical (the honest mean); a number caps each value
    at ``cap`` dB before averaging, so the mean stays finite. An empty input gives NaN.
    """
    v = torch.as_tensor(values, dtype=torch.float64).flatten()
    if v.numel() == 0:
        return math.nan
    if cap is not None:
        v = v.clamp_max(cap)
    return float(v.mean())


def gaussian_window_1d(
    size: int = SSIM_WINDOW,
    sigma: float = SSIM_SIGMA,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Normalised 1D Gaussian taps centred on the middle sample. -> (size,)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


BLUR_EXT = native_extension(__file__, "blur_cpu", probe_op="gaussian_blur", what="SSIM blur", fallback="convolution for the SSIM windows")
"""The native separable blur of the SSIM windows on CPU tensors (compiled on first use)."""


class _NativeBlur(torch.autograd.Function):
    """The native separable blur of (P, H, W) planes; with symmetric taps the blur is self-adjoint,
    so its backward is the same blur of the output gradient."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(g)
        return torch.ops.sage_blur_cpu.gaussian_blur(x.contiguous(), g.contiguous())

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, None]:  # type: ignore[override]
        (g,) = ctx.saved_tensors
        return _NativeBlur.apply(grad.contiguous(), g), None


def _use_native_blur(x: torch.Tensor) -> bool:
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return False
    ok, reason = BLUR_EXT.available()
    if not ok:
        BLUR_EXT.warn_unavailable_once(reason)
    return ok


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable zero-padded 'same' Gaussian blur, per channel. x: (B, C, H, W) -> (B, C, H, W).

    Equal to a 2D convolution with the outer-product window and zero padding. CPU tensors use the
    native blur (``csrc/blur_cpu.cpp``) when it builds; :func:`_blur_conv` is the reference.
    """
    if _use_native_blur(x):
        b, c, h, w = x.shape
        return _NativeBlur.apply(x.reshape(b * c, h, w), g.to(x.dtype)).reshape(b, c, h, w)
    return _blur_conv(x, g)


def _blur_conv(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """:func:`_blur` by two grouped 1D convolutions (any device; the reference)."""
    c = x.shape[1]
    k = g.numel()
    pad = k // 2
    wx = g.view(1, 1, 1, k).expand(c, 1, 1, k)
    wy = g.view(1, 1, k, 1).expand(c, 1, k, 1)
    x = F.conv2d(x, wx, padding=(0, pad), groups=c)
    return F.conv2d(x, wy, padding=(pad, 0), groups=c)


@dataclass(frozen=True)
class SSIMTarget:
    """The part of SSIM that depends on the target image only, kept for a target that is compared with
    many predictions (a training image): the image (B, C, H, W) and its window means of x and x²
    (B, C, H, W each), for the window ``window_size``, ``sigma``. Made by :func:`ssim_target`."""

    image: torch.Tensor
    mean: torch.Tensor
    mean_sq: torch.Tensor
    window_size: int
    sigma: float


def ssim_target(gt: torch.Tensor, window_size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> SSIMTarget:
    """:class:`SSIMTarget` of a target image (B, C, H, W) or (C, H, W) (kept batched)."""
    gt = gt.unsqueeze(0) if gt.dim() == 3 else gt
    if gt.dim() != 4:
        raise ValueError(f"expected (B, C, H, W) or (C, H, W), got shape {tuple(gt.shape)}")
    g = gaussian_window_1d(window_size, sigma, dtype=gt.dtype, device=gt.device)
    mean, mean_sq = _blur(torch.cat([gt, gt * gt], dim=1), g).split(gt.shape[1], dim=1)
    return SSIMTarget(gt, mean, mean_sq, window_size, sigma)


def ssim_map(
    pred: torch.Tensor,
    gt: torch.Tensor | SSIMTarget,
    window_size: int = SSIM_WINDOW,
    sigma: float = SSIM_SIGMA,
) -> torch.Tensor:
    """Per-pixel, per-channel SSIM map (docs/formats.md §8).

    Gaussian window ``window_size``² with std ``sigma``, zero-padded 'same' convolution as in the
    3DGS code, ``C1 = 0.01²``, ``C2 = 0.03²`` (data range 1). No clamping; differentiable in pred.

    pred: (B, C, H, W) or (C, H, W); gt: the target of the same shape, or its :class:`SSIMTarget`
    (of the same window; batched) -> the shape of pred.
    """
    target = gt if isinstance(gt, SSIMTarget) else ssim_target(gt, window_size, sigma)
    if (target.window_size, target.sigma) != (window_size, sigma):
        raise ValueError(f"SSIM target of window {target.window_size}/{target.sigma}, asked for {window_size}/{sigma}")
    single = pred.dim() == 3
    pred = pred.unsqueeze(0) if single else pred
    if pred.shape != target.image.shape:
        raise ValueError(f"image shapes differ: {tuple(pred.shape)} vs {tuple(target.image.shape)}")
    g = gaussian_window_1d(window_size, sigma, dtype=pred.dtype, device=pred.device)
    c = pred.shape[1]
    # blur the prediction's three moment images in one grouped call: (B, 3C, H, W)
    mu1, e11, e12 = _blur(torch.cat([pred, pred * pred, pred * target.image], dim=1), g).split(c, dim=1)
    mu2, e22 = target.mean, target.mean_sq
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s11 = e11 - mu1_sq
    s22 = e22 - mu2_sq
    s12 = e12 - mu12
    num = (2.0 * mu12 + SSIM_C1) * (2.0 * s12 + SSIM_C2)
    den = (mu1_sq + mu2_sq + SSIM_C1) * (s11 + s22 + SSIM_C2)
    out = num / den
    return out[0] if single else out


def ssim(
    pred: torch.Tensor,
    gt: torch.Tensor | SSIMTarget,
    window_size: int = SSIM_WINDOW,
    sigma: float = SSIM_SIGMA,
) -> torch.Tensor:
    """SSIM per image: mean of :func:`ssim_map` over channels and pixels.

    pred, gt: (B, C, H, W) or (C, H, W) (gt may be its :class:`SSIMTarget`) -> (B,) or 0-d. Identical
    images give exactly 1.
    As a training loss use ``1 - ssim(pred, gt).mean()``.
    """
    m = ssim_map(pred, gt, window_size, sigma)
    return m.flatten(-3).mean(-1)
