"""LPIPS AlexNet v0.1: reference values, weights-path resolution, clear errors on bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from sage_core.errors import InputError
from sage_core.evaluate import (
    ENV_VAR,
    LPIPS,
    find_lpips_weights,
    load_lpips_or_none,
    load_lpips_state_dict,
    lpips_or_none,
    to_nchw,
)
from sage_core.evaluate.lpips import EXPECTED_SHAPES

from helpers import LPIPS_SKIP_REASON, LPIPS_WEIGHTS as WEIGHTS  # noqa: E402
needs_weights = pytest.mark.skipif(WEIGHTS is None, reason=LPIPS_SKIP_REASON)


@pytest.fixture(scope="module")
def astronaut_pairs():
    import skimage.data
    import skimage.filters

    a = skimage.data.astronaut().astype(np.float64) / 255.0
    noisy = np.clip(a + np.random.default_rng(0).normal(0, 0.05, a.shape), 0, 1)
    blur = skimage.filters.gaussian(a, sigma=2, channel_axis=-1)
    ref, noisy, blur = (to_nchw(x.astype(np.float32)) for x in (a, noisy, blur))
    return torch.cat([ref, ref, ref]), torch.cat([noisy, blur, ref])


@needs_weights
def test_reference_values(astronaut_pairs):
    x, y = astronaut_pairs
    model = LPIPS.from_path(WEIGHTS, check_sha256=True)
    with torch.no_grad():
        out = model(x, y)
    np.testing.assert_allclose(out.numpy(), [0.261343, 0.327038, 0.0], atol=1e-4)
    assert float(out[2]) == 0.0


@needs_weights
def test_unit_range_quirk_values(astronaut_pairs):
    x, y = astronaut_pairs
    model = LPIPS.from_path(WEIGHTS, rescale_inputs=False)
    out = lpips_or_none(model, x[:2], y[:2])
    assert out is not None
    np.testing.assert_allclose(out.numpy(), [0.195618, 0.278742], atol=1e-4)


@needs_weights
def test_unbatched_symmetric_and_gradients():
    model = LPIPS.from_path(WEIGHTS)
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 64, 64, generator=g)
    b = (a + 0.1 * torch.rand(3, 64, 64, generator=g)).clamp(0, 1)
    d = model(a, b)
    assert d.dim() == 0 and float(d) > 0
    assert float(model(b, a)) == pytest.approx(float(d), rel=1e-5)
    p = a.clone().requires_grad_(True)
    model(p, b).backward()
    assert p.grad is not None and p.grad.abs().sum() > 0
    assert all(not q.requires_grad for q in model.parameters())


def test_resolution_order(tmp_path, monkeypatch):
    explicit = tmp_path / "explicit.pth"
    env = tmp_path / "env.pth"
    home = tmp_path / "home"
    cached = home / ".cache" / "sage" / "lpips_alex_v0.1.pth"
    for p in (explicit, env, cached):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"x")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv(ENV_VAR, str(env))
    assert find_lpips_weights(explicit) == explicit
    assert find_lpips_weights() == env
    monkeypatch.delenv(ENV_VAR)
    assert find_lpips_weights() == cached
    cached.unlink()
    assert find_lpips_weights() is None
    assert load_lpips_or_none() is None
    assert lpips_or_none(None, torch.zeros(3, 8, 8), torch.zeros(3, 8, 8)) is None


def test_named_missing_file_is_an_error(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    with pytest.raises(InputError, match="not found"):
        find_lpips_weights(tmp_path / "nope.pth")
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "gone.pth"))
    with pytest.raises(InputError, match=ENV_VAR):
        find_lpips_weights()


def _fake_state_dict() -> dict[str, torch.Tensor]:
    return {k: torch.zeros(s) for k, s in EXPECTED_SHAPES.items()}


def test_malformed_weights_give_clear_errors(tmp_path):
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"definitely not a checkpoint")
    with pytest.raises(InputError, match="garbage.pth") as e:
        load_lpips_state_dict(garbage)
    assert e.value.path == garbage

    sd = _fake_state_dict()
    del sd["lin.4.weight"]
    missing = tmp_path / "missing.pth"
    torch.save(sd, missing)
    with pytest.raises(InputError, match="missing keys.*lin.4.weight"):
        LPIPS.from_path(missing)

    sd = _fake_state_dict()
    sd["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    wrong = tmp_path / "wrong.pth"
    torch.save(sd, wrong)
    with pytest.raises(InputError, match="features.3.weight.*shape"):
        LPIPS.from_path(wrong)

    good = tmp_path / "good.pth"
    torch.save(_fake_state_dict(), good)
    assert isinstance(LPIPS.from_path(good), LPIPS)
    with pytest.raises(InputError, match="sha256"):
        LPIPS.from_path(good, check_sha256=True)
    with pytest.raises(InputError, match="not found"):
        load_lpips_or_none(tmp_path / "absent.pth")


@needs_weights
@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu(astronaut_pairs):
    x, y = (t[:2, :, :256, :256] for t in astronaut_pairs)
    cpu = LPIPS.from_path(WEIGHTS)
    gpu = LPIPS.from_path(WEIGHTS, device="cuda")
    with torch.no_grad():
        assert torch.allclose(gpu(x.cuda(), y.cuda()).cpu(), cpu(x, y), atol=1e-4)
