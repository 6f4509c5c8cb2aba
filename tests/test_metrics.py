"""PSNR and SSIM: closed forms, the GA per-channel variant, skimage agreement, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from sage_core.image_metrics import (
    gaussian_window_1d,
    mean_psnr,
    psnr,
    psnr_per_channel_mean,
    ssim,
    ssim_map,
    ssim_target,
    to_nchw,
)


def _rand(shape, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g, dtype=dtype)


def test_psnr_constant_offset_closed_form():
    gt = torch.full((2, 3, 8, 9), 0.5)
    pred = gt + 0.1
    expected = 10 * math.log10(1 / 0.01)  # 20 dB
    out = psnr(pred, gt)
    assert out.shape == (2,)
    assert torch.allclose(out, torch.full((2,), expected), atol=1e-4)


def test_psnr_clamps_to_unit_range():
    gt = torch.ones(3, 4, 4)
    pred = torch.full((3, 4, 4), 1.7)  # clamps to 1 -> identical
    assert math.isinf(float(psnr(pred, gt)))
    pred2 = torch.full((3, 4, 4), -0.5)  # clamps to 0 -> MSE 1 -> 0 dB
    assert float(psnr(pred2, gt)) == pytest.approx(0.0, abs=1e-6)


def test_psnr_identical_inf_and_cap():
    x = _rand((2, 3, 5, 5))
    assert torch.isinf(psnr(x, x)).all()
    assert torch.equal(psnr(x, x, cap=100.0), torch.full((2,), 100.0, dtype=x.dtype))
    vals = [30.0, float("inf")]
    assert math.isinf(mean_psnr(vals))
    assert mean_psnr(vals, cap=100.0) == pytest.approx(65.0)
    assert math.isnan(mean_psnr([]))


def test_psnr_per_channel_mean_ga_variant():
    gt = torch.zeros(1, 3, 4, 4)
    offs = torch.tensor([0.1, 0.2, 0.3]).view(1, 3, 1, 1)
    pred = gt + offs
    per_channel = [10 * math.log10(1 / o**2) for o in (0.1, 0.2, 0.3)]
    assert float(psnr_per_channel_mean(pred, gt)[0]) == pytest.approx(
        sum(per_channel) / 3, abs=1e-4
    )
    standard = 10 * math.log10(1 / ((0.01 + 0.04 + 0.09) / 3))
    assert float(psnr(pred, gt)[0]) == pytest.approx(standard, abs=1e-4)
    # Jensen: the GA variant is >= the standard PSNR, equal for equal channel errors
    assert float(psnr_per_channel_mean(pred, gt)[0]) > float(psnr(pred, gt)[0])
    same = gt + 0.2
    assert torch.allclose(psnr_per_channel_mean(same, gt), psnr(same, gt), atol=1e-4)


def test_to_nchw_and_unbatched_shapes():
    hwc = np.random.default_rng(0).random((6, 7, 3)).astype(np.float32)
    t = to_nchw(hwc)
    assert t.shape == (1, 3, 6, 7)
    assert torch.equal(t[0, 1], torch.from_numpy(hwc[..., 1]))
    assert psnr(t[0], t[0] * 0.5).dim() == 0
    assert ssim(t[0], t[0]).dim() == 0
    with pytest.raises(ValueError):
        psnr(t, t[:, :2])


def test_ssim_identical_is_one():
    x = _rand((2, 3, 20, 17), dtype=torch.float32)
    out = ssim(x, x)
    assert torch.allclose(out, torch.ones(2), atol=1e-6)
    flat = torch.full((1, 3, 16, 16), 0.3)
    assert torch.allclose(ssim(flat, flat), torch.ones(1), atol=1e-6)


def test_ssim_symmetric_and_bounded():
    a, b = _rand((2, 3, 24, 24), 1), _rand((2, 3, 24, 24), 2)
    assert torch.allclose(ssim(a, b), ssim(b, a), atol=1e-12)
    s = ssim(a, 0.5 * a + 0.5 * b)
    assert (s < 1).all() and (s > ssim(a, b)).all()


def _ssim_reference_2d(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Direct 11×11 zero-padded 2D convolution, as the 3DGS code does it."""
    c = a.shape[1]
    g = gaussian_window_1d(11, 1.5, dtype=a.dtype)
    w = torch.outer(g, g).expand(c, 1, 11, 11)

    def blur(x):
        return F.conv2d(x, w, padding=5, groups=c)

    mu1, mu2 = blur(a), blur(b)
    s11 = blur(a * a) - mu1**2
    s22 = blur(b * b) - mu2**2
    s12 = blur(a * b) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))


def test_ssim_separable_matches_2d_convolution():
    a, b = _rand((1, 3, 19, 23), 3), _rand((1, 3, 19, 23), 4)
    assert torch.allclose(ssim_map(a, b), _ssim_reference_2d(a, b), atol=1e-12)


def test_ssim_matches_skimage_on_interior():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    base = rng.random((40, 36, 3))
    a = np.clip(base, 0, 1)
    b = np.clip(base + rng.normal(0, 0.1, base.shape), 0, 1)
    mean_sk, full_sk = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
        data_range=1, channel_axis=-1, full=True,
    )  # fmt: skip
    ours = ssim_map(to_nchw(a), to_nchw(b))[0].permute(1, 2, 0).numpy()
    # skimage filters with reflection and averages over the map cropped by 5 px; inside that
    # crop the 11×11 window never reaches the border, so both maps agree there exactly
    crop = (slice(5, -5), slice(5, -5))
    np.testing.assert_allclose(ours[crop], full_sk[crop], atol=1e-10)
    assert float(ours[crop].mean()) == pytest.approx(mean_sk, abs=1e-10)
    # over the full image the border handling differs (zero padding vs reflection)
    assert abs(float(ssim(to_nchw(a), to_nchw(b))) - mean_sk) < 0.05


def test_ssim_gradients_flow_as_loss():
    gt = _rand((1, 3, 16, 16), 5)
    pred = (gt + 0.1 * _rand((1, 3, 16, 16), 6)).requires_grad_(True)
    loss = 0.8 * (pred - gt).abs().mean() + 0.2 * (1 - ssim(pred, gt).mean())
    loss.backward()
    assert pred.grad is not None and torch.isfinite(pred.grad).all()
    assert pred.grad.abs().sum() > 0
    # SSIM alone against a finite difference
    small_gt = gt[..., :8, :8].contiguous()
    x = pred[..., :8, :8].detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: ssim(y, small_gt), (x,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ssim_against_a_kept_target_is_ssim_against_the_image(dtype):
    """A target's moments computed once (a training image) give the same map and gradients, batched
    or not; a target of another window is refused."""
    gt = _rand((1, 3, 21, 17), 16, dtype)
    target = ssim_target(gt)
    for pred0 in (_rand((1, 3, 21, 17), 17, dtype), _rand((3, 21, 17), 18, dtype)):
        grads = []
        for against in (gt[0] if pred0.dim() == 3 else gt, target):
            pred = pred0.clone().requires_grad_(True)
            m = ssim_map(pred, against)
            (g,) = torch.autograd.grad((m * m).sum(), pred)
            grads.append((m, g))
        (m1, g1), (m2, g2) = grads
        assert m1.shape == pred0.shape and torch.equal(m1, m2) and torch.equal(g1, g2)
    assert torch.equal(ssim(gt, target), ssim(gt, gt))
    with pytest.raises(ValueError, match="window"):
        ssim_map(gt, target, window_size=7)
    with pytest.raises(ValueError, match="shapes differ"):
        ssim_map(gt[..., :-1], target)


def _native_blur_or_skip():
    from sage_core import image_metrics as im

    ok, reason = im.BLUR_EXT.available()
    if not ok:
        pytest.skip(f"native SSIM blur unavailable: {reason}")
    return im


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-13), (torch.float32, 2e-6)])
def test_native_blur_matches_the_convolution_values_and_gradients(dtype, tol):
    im = _native_blur_or_skip()
    g = gaussian_window_1d(dtype=dtype)
    for shape in ((1, 15, 37, 29), (2, 3, 5, 4), (1, 1, 1, 13)):
        x = _rand(shape, 9, dtype).requires_grad_(True)
        w = _rand(shape, 10, dtype)
        y = im._blur(x, g)
        (gx,) = torch.autograd.grad((y * w).sum(), x)
        xr = x.detach().clone().requires_grad_(True)
        yr = im._blur_conv(xr, g)
        (gr,) = torch.autograd.grad((yr * w).sum(), xr)
        assert torch.allclose(y, yr, atol=tol, rtol=0), shape
        assert torch.allclose(gx, gr, atol=tol * 10, rtol=0), shape
    x = _rand((1, 2, 9, 7), 11).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: im._blur(t, gaussian_window_1d(dtype=torch.float64)), (x,))


def test_native_blur_is_thread_count_independent_and_used_by_ssim():
    im = _native_blur_or_skip()
    a, b = _rand((1, 3, 40, 33), 12, torch.float32), _rand((1, 3, 40, 33), 13, torch.float32)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = ssim_map(a, b)
        torch.set_num_threads(2)
        two = ssim_map(a, b)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one, two)
    calls = []
    orig = im._NativeBlur.apply
    try:
        im._NativeBlur.apply = lambda *args: calls.append(1) or orig(*args)  # type: ignore[method-assign]
        ssim(a, b)
    finally:
        im._NativeBlur.apply = orig  # type: ignore[method-assign]
    assert calls


def test_blur_falls_back_to_the_convolution_without_the_extension(monkeypatch):
    from sage_core import image_metrics as im

    monkeypatch.setattr(im.BLUR_EXT, "state", {"ok": False, "reason": "no compiler (test)"})
    monkeypatch.setattr(im.BLUR_EXT, "warned", False)
    a, b = _rand((1, 3, 16, 16), 14), _rand((1, 3, 16, 16), 15)
    with pytest.warns(RuntimeWarning, match="no compiler"):
        out = ssim_map(a, b)
    assert torch.allclose(out, _ssim_reference_2d(a, b), atol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_metrics_on_cuda_match_cpu():
    a, b = _rand((2, 3, 32, 32), 7, torch.float32), _rand((2, 3, 32, 32), 8, torch.float32)
    assert torch.allclose(ssim(a.cuda(), b.cuda()).cpu(), ssim(a, b), atol=1e-5)
    assert torch.allclose(psnr(a.cuda(), b.cuda()).cpu(), psnr(a, b), atol=1e-4)
