"""Evaluation protocol: metrics per image / camera / split, JSON, sample strips, LPIPS availability."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from sage_core.data.dataset import IngestedData, IngestedFrame
from sage_core.data.imageio import read_image
from sage_core.evaluate.lpips import LPIPS
from sage_core.evaluate.protocol import (
    ERROR_GAIN,
    FRONTAL_CAMERA,
    EvalReport,
    ImageMetrics,
    error_strip,
    evaluate_frames,
    sample_indices,
)
from sage_core.errors import InputError
from helpers import LPIPS_WEIGHTS



@pytest.fixture(scope="module")
def data(tiny_ws) -> IngestedData:
    return IngestedData.open(tiny_ws / "data")


@pytest.fixture(scope="module")
def frames(data) -> list[IngestedFrame]:
    """The novel-view frame (camera 8) and six self-reenactment frames over three cameras."""
    test = [f for f in data.test if f.camera_index in (0, 8, 15)]
    ts = sorted({f.timestep for f in test})[:2]
    picked = [f for f in test if f.timestep in ts]
    assert len(picked) == 6
    return data.val + picked


@pytest.fixture(scope="module")
def lpips_model() -> LPIPS | None:
    if LPIPS_WEIGHTS is None:
        return None
    return LPIPS.from_path(LPIPS_WEIGHTS)


def _gt(data: IngestedData, frame: IngestedFrame) -> torch.Tensor:
    return torch.from_numpy(data.load_image(frame))


def _pm_noise(gt: torch.Tensor, sigma: torch.Tensor, seed: int) -> torch.Tensor:
    """gt + s·sigma with random signs s = ±1, the sign flipped where the result would leave [0, 1].

    |render − gt| = sigma exactly in every pixel, so each channel's MSE is sigma² (no clamping).
    """
    g = torch.Generator().manual_seed(seed)
    s = torch.where(torch.rand(gt.shape, generator=g) < 0.5, -1.0, 1.0)
    out = gt + s * sigma
    flip = (out < 0) | (out > 1)
    return torch.where(flip, gt - s * sigma, out)


def test_identity_render_is_perfect(data, frames, lpips_model, tmp_path):
    report = evaluate_frames(lambda f: _gt(data, f), data, frames, lpips=lpips_model, out_dir=tmp_path, n_samples=3)
    assert report.n_images == len(frames) == 7
    assert all(math.isinf(m.psnr) and m.psnr > 0 for m in report.images)
    assert all(math.isinf(m.psnr_ga) for m in report.images)
    assert all(m.ssim == pytest.approx(1.0, abs=1e-6) for m in report.images)
    assert math.isinf(report.overall.psnr)
    if lpips_model is None:
        assert not report.lpips_available and report.overall.lpips is None
    else:
        assert report.lpips_available
        assert all(m.lpips is not None and abs(m.lpips) < 1e-6 for m in report.images)
        assert report.overall.lpips == pytest.approx(0.0, abs=1e-6)

    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert doc["overall"]["psnr"] == "inf" and doc["images"][0]["psnr_ga"] == "inf"
    assert doc["overall"]["ssim"] == pytest.approx(1.0, abs=1e-6)
    assert doc["counts"] == {"images": 7, "timesteps": 3, "cameras": 3}
    assert doc["frontal"]["count"] == 3  # val + two test frames of camera 8


def test_capped_psnr_is_finite(data, frames, tmp_path):
    calls: list[tuple[int, int]] = []
    report = evaluate_frames(lambda f: _gt(data, f), data, frames[:2], lpips=None, out_dir=tmp_path,
                             n_samples=0, psnr_cap=60.0, progress=lambda d, n, msg: calls.append((d, n)))
    assert calls == [(1, 2), (2, 2)]
    assert all(m.psnr == 60.0 and m.psnr_ga == 60.0 for m in report.images)
    assert report.overall.psnr == 60.0
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert doc["overall"]["psnr"] == 60.0 and doc["protocol"]["psnr_cap"] == 60.0
    assert not (tmp_path / "images").exists()


def test_known_noise_gives_closed_form_psnr(data, frames):
    """Per-camera sigma; per-channel sigmas differ, so the GA variant exceeds the standard PSNR."""
    sig = {0: 0.02, 8: 0.05, 15: 0.1}
    ratios = torch.tensor([1.0, 0.5, 1.5])

    def render(f: IngestedFrame) -> torch.Tensor:
        return _pm_noise(_gt(data, f), sig[f.camera_index] * ratios, seed=f.timestep * 100 + f.camera_index)

    report = evaluate_frames(render, data, frames, lpips=None, out_dir=None)
    for cam, means in report.per_camera.items():
        s2 = (sig[cam] * ratios.double()) ** 2
        want = -10.0 * math.log10(float(s2.mean()))
        want_ga = float((-10.0 * torch.log10(s2)).mean())
        assert means.psnr == pytest.approx(want, abs=1e-3)
        assert means.psnr_ga == pytest.approx(want_ga, abs=1e-3)
        assert means.psnr_ga > means.psnr
        assert means.lpips is None
    assert report.per_camera[0].count == 2 and report.per_camera[8].count == 3
    assert report.frontal is report.per_camera[FRONTAL_CAMERA]
    overall = np.mean([m.psnr for m in report.images])
    assert report.overall.psnr == pytest.approx(overall)
    # more noise, lower SSIM
    assert report.per_camera[0].ssim > report.per_camera[8].ssim > report.per_camera[15].ssim
    assert not report.lpips_available
    names = [r[0] for r in report.rows()]
    assert names == ["camera 0", "camera 8", "camera 15", "frontal (cam 8)", "all"]
    assert report.rows()[-1][-1] == "n/a" and len(report.rows()[0]) == len(EvalReport.COLUMNS)


def test_render_is_clamped_before_comparison(data, frames):
    """Values beyond [0, 1] on a white background are clamped back onto the ground truth."""
    report = evaluate_frames(lambda f: _gt(data, f) * 3.0 - 1.0,
                             data, frames[:1], lpips=None, out_dir=None, psnr_cap=100.0)
    gt = _gt(data, frames[0])
    pred = (gt * 3.0 - 1.0).clamp(0, 1)
    want = -10.0 * math.log10(float((pred - gt).square().mean()))
    assert report.images[0].psnr == pytest.approx(want, rel=1e-5)


def test_sample_strips(data, frames, tmp_path):
    report = evaluate_frames(lambda f: _pm_noise(_gt(data, f), torch.tensor(0.1), 0), data, frames,
                             lpips=None, out_dir=tmp_path, n_samples=3)
    assert sample_indices(len(frames), 3) == [0, 3, 6]
    assert len(report.samples) == 3
    for idx, path in zip([0, 3, 6], report.samples):
        f = frames[idx]
        assert path == tmp_path / "images" / f"{f.timestep:05d}_{f.camera_index:02d}.png"
        img = read_image(path)
        assert img.shape == (f.camera.height, 3 * f.camera.width, 3)
        w = f.camera.width
        np.testing.assert_allclose(img[:, :w], data.load_image(f), atol=1 / 255)
        # error panel: |diff| = 0.1 everywhere, magnified
        np.testing.assert_allclose(img[:, 2 * w:], min(1.0, 0.1 * ERROR_GAIN), atol=1.5 / 255)
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert len(doc["samples"]) == 3 and doc["lpips_available"] is False
    # written relative to the metrics file, so they survive moving the result folder
    assert doc["samples"] == [p.relative_to(tmp_path).as_posix() for p in report.samples]
    assert all((tmp_path / s).is_file() for s in doc["samples"])
    assert doc["overall"]["lpips"] is None and doc["protocol"]["lpips"].startswith("unavailable")


def test_error_strip_layout():
    gt = torch.zeros(4, 5, 3)
    render = torch.full((4, 5, 3), 0.1)
    strip = error_strip(gt, render)
    assert strip.shape == (4, 15, 3)
    np.testing.assert_allclose(strip[:, 10:], 0.1 * ERROR_GAIN, rtol=1e-6)


def test_lpips_positive_for_noise(data, frames, lpips_model):
    if lpips_model is None:
        pytest.skip("LPIPS weights not available")
    report = evaluate_frames(lambda f: _pm_noise(_gt(data, f), torch.tensor(0.1), 1), data, frames[:2],
                             lpips=lpips_model, out_dir=None)
    assert report.lpips_available and report.overall.lpips is not None and report.overall.lpips > 0.01
    assert report.to_dict()["protocol"]["lpips_inputs"] == "[-1,1]"


def test_bad_render_shape_and_empty(data, frames):
    with pytest.raises(ValueError, match="shape"):
        evaluate_frames(lambda f: torch.zeros(3, 3, 3), data, frames[:1], lpips=None, out_dir=None)
    with pytest.raises(ValueError):
        evaluate_frames(lambda f: torch.zeros(3, 3, 3), data, [], lpips=None, out_dir=None)


def test_gt_size_mismatch_names_the_image(data, frames):
    f = frames[0]
    cam = f.camera.resized(f.camera.width // 2, f.camera.height // 2)
    bad = IngestedFrame(f.role, f.split, f.timestep, f.camera_index, f.camera_id, f.image, f.mask, cam)
    with pytest.raises(InputError) as err:
        evaluate_frames(lambda fr: torch.zeros(cam.height, cam.width, 3), data, [bad], lpips=None, out_dir=None)
    assert err.value.path == f.image


def test_report_aggregation_without_frontal():
    rows = [ImageMetrics(0, 1, 20.0, 21.0, 0.9, None), ImageMetrics(1, 1, 30.0, 31.0, 0.8, None),
            ImageMetrics(0, 2, float("inf"), float("inf"), 1.0, None)]
    rep = EvalReport.build(rows, lpips_available=False)
    assert rep.frontal is None and rep.n_cameras == 2 and rep.n_timesteps == 2
    assert rep.per_camera[1].psnr == 25.0 and rep.per_camera[1].ssim == pytest.approx(0.85)
    d = rep.to_dict()
    assert d["frontal"] is None and d["per_camera"]["2"]["psnr"] == "inf"
    json.dumps(d, allow_nan=False)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_renders_and_lpips(data, frames, lpips_model):
    """Renders on the GPU (and LPIPS there when available) give the CPU numbers."""
    lp_gpu = None if lpips_model is None else LPIPS.from_path(LPIPS_WEIGHTS, device="cuda")

    def render(f: IngestedFrame) -> torch.Tensor:
        return _pm_noise(_gt(data, f), torch.tensor(0.05), f.camera_index)

    cpu = evaluate_frames(render, data, frames[:3], lpips=lpips_model, out_dir=None)
    gpu = evaluate_frames(lambda f: render(f).cuda(), data, frames[:3], lpips=lp_gpu, out_dir=None)
    for a, b in zip(cpu.images, gpu.images):
        assert a.psnr == pytest.approx(b.psnr, abs=1e-3) and a.ssim == pytest.approx(b.ssim, abs=1e-4)
        if a.lpips is not None:
            assert a.lpips == pytest.approx(b.lpips, abs=1e-3)


def test_means_leave_out_images_with_an_empty_region():
    """A region metric over an empty region is NaN (a back view no training view saw); the means are
    over the other images and count says how many."""
    from sage_core.evaluate.protocol import ImageMetrics, MetricMeans

    rows = [ImageMetrics(0, 0, 20.0, 20.0, 0.9, 0.1), ImageMetrics(0, 1, math.nan, math.nan, math.nan, None),
            ImageMetrics(1, 0, 30.0, 30.0, 0.7, 0.3)]
    m = MetricMeans.of(rows)
    assert m.count == 2 and m.psnr == pytest.approx(25.0) and m.ssim == pytest.approx(0.8) and m.lpips == pytest.approx(0.2)
    assert math.isnan(MetricMeans.of(rows[1:2]).psnr) and MetricMeans.of(rows[1:2]).count == 0
