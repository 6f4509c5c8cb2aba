"""Wrinkle shading: area ratios, compression, darkening, distortion statistics, amplitudes, storage."""

from __future__ import annotations

import math

import pytest
import torch

from sage_core.avatar.surfels import SurfelSet
from sage_core.avatar.wrinkles import (
    FaceDistortionStats,
    apply_wrinkles,
    face_compression,
    surfel_compression,
    vertex_area_ratio,
    wrinkle_amplitude,
)
from sage_core.geometry.rotations import axis_angle_to_matrix


def _grid(n: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """A bumpy (n×n)-vertex grid mesh: vertices (n², 3) float64, faces (2(n−1)², 3)."""
    ii, jj = torch.meshgrid(torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij")
    z = 0.1 * torch.sin(ii) * torch.cos(0.7 * jj)
    v = torch.stack([ii, jj, z], -1).reshape(-1, 3)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            f += [[a, b, d], [a, d, c]]
    return v, torch.tensor(f)


def test_area_ratio_of_scaling_and_rigid_motion():
    v, f = _grid()
    torch.testing.assert_close(vertex_area_ratio(1.3 * v, v, f), torch.full((v.shape[0],), 1.69, dtype=torch.float64))
    R = axis_angle_to_matrix(torch.tensor([[0.3, -0.5, 0.9]], dtype=torch.float64))[0]
    moved = v @ R.T + torch.tensor([0.2, 1.0, -3.0], dtype=torch.float64)
    torch.testing.assert_close(vertex_area_ratio(moved, v, f), torch.ones(v.shape[0], dtype=torch.float64))


def test_compression_zero_at_rest_and_under_stretch_linear_under_shrink():
    v, f = _grid()
    b = torch.arange(f.shape[0])
    assert float(surfel_compression(v, v, f, b, 0.25).abs().max()) == 0.0
    assert float(surfel_compression(1.2 * v, v, f, b, 0.25).abs().max()) == 0.0
    s = math.sqrt(0.9)  # area ratio 0.9: 10 % loss, 0.4 of a 25 % full scale
    torch.testing.assert_close(surfel_compression(s * v, v, f, b, 0.25), torch.full((f.shape[0],), 0.4, dtype=torch.float64))
    torch.testing.assert_close(face_compression(0.5 * v, v, f, 0.25), torch.ones(f.shape[0], dtype=torch.float64))


def test_apply_wrinkles_darkens_only_compressed_surfels_with_amplitude():
    v, f = _grid()
    N = f.shape[0]
    b = torch.arange(N)
    colors = torch.rand(N, 3, dtype=torch.float64)
    wr = torch.stack([torch.linspace(0, 0.5, N, dtype=torch.float64), torch.full((N,), 0.25, dtype=torch.float64)], -1)
    torch.testing.assert_close(apply_wrinkles(colors, wr, v, v, f, b), colors)
    out = apply_wrinkles(colors, wr, 0.5 * v, v, f, b)  # area ratio 0.25: full compression
    torch.testing.assert_close(out, colors * (1 - wr[:, :1]))
    # only the squeezed half of the grid darkens
    sq = v.clone()
    sq[:, 0] = torch.where(sq[:, 0] <= 2, 0.7 * sq[:, 0], sq[:, 0] - 0.6)
    out = apply_wrinkles(colors, wr, sq, v, f, b)
    first = v[f[:, 0], 0] < 1.5
    last = v[f].min(1).values[:, 0] >= 2.5
    assert bool((out[first] < colors[first]).any(-1)[wr[first, 0] > 0].all())
    torch.testing.assert_close(out[last], colors[last])


def test_distortion_stats_means_and_resume():
    st = FaceDistortionStats(4)
    fid = torch.tensor([[0, 0, 1], [-1, 2, 2]])
    st.update(fid, torch.tensor([[1.0, 3.0, 5.0], [9.0, 2.0, 4.0]]), torch.tensor([0.5, 0.0, 1.0, 0.2]))
    st.update(torch.tensor([[1, -1]]), torch.tensor([[7.0, 100.0]]))
    torch.testing.assert_close(st.mean(), torch.tensor([2.0, 6.0, 3.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(st.count, torch.tensor([2.0, 2.0, 2.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(st.mean_compression(), torch.tensor([0.5, 0.0, 1.0, 0.0], dtype=torch.float64))
    other = FaceDistortionStats(4)
    other.load_state_dict(st.state_dict())
    torch.testing.assert_close(other.mean(), st.mean())


def test_amplitude_quantile_ramp_excludes_and_unseen():
    mean = torch.arange(11, dtype=torch.float64)  # 0..10
    count = torch.ones(11, dtype=torch.float64)
    count[10] = 0  # unseen
    excluded = torch.zeros(11, dtype=torch.bool)
    excluded[0] = True
    amp = wrinkle_amplitude(mean, count, excluded, 0.4, (0.5, 1.0))
    # quantiles over 1..9: median 5, max 9
    expect = ((mean - 5) / 4).clamp(0, 1) * 0.4
    expect[0] = expect[10] = 0
    torch.testing.assert_close(amp, expect)
    with pytest.raises(ValueError):
        wrinkle_amplitude(mean, count, excluded, 0.4, (0.9, 0.5))


def test_surfel_set_wrinkle_round_trip_and_pruning():
    N = 6
    s = SurfelSet(torch.arange(N), torch.zeros(N, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(N, 1), torch.zeros(N, 2), attributes="mlp")
    assert s.wrinkle is None and "wrinkle" not in s.state_dict()
    w = torch.stack([torch.linspace(0, 0.5, N), torch.full((N,), 0.25)], -1)
    s.set_wrinkle(w)
    t = SurfelSet.from_state_dict(s.state_dict())
    torch.testing.assert_close(t.wrinkle, w)
    t.prune(torch.tensor([True, False, False, True, False, False]))
    torch.testing.assert_close(t.wrinkle, w[[1, 2, 4, 5]])
    with pytest.raises(ValueError):
        t.set_wrinkle(torch.zeros(N, 2))
