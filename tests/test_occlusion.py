"""Ambient visibility: analytic sphere occluder, open and enclosed points, determinism."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sage_core.geometry.occlusion import ambient_visibility, hemisphere_directions


def _sphere(centre, radius=1.0):
    m = trimesh.creation.icosphere(5, radius=radius)
    return np.asarray(m.vertices, float) + np.asarray(centre, float), np.asarray(m.faces, np.int64)


def test_directions_are_cosine_weighted_unit_and_upper():
    d = hemisphere_directions(4096)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert d[:, 2].min() > 0
    assert d[:, 2].mean() == pytest.approx(2.0 / 3.0, abs=1e-3)  # E[cos θ] under the cosine weight
    assert np.abs(d[:, :2].mean(0)).max() < 5e-3


@pytest.mark.parametrize("h", [2.0, 3.0])
def test_sphere_above_a_point_occludes_sin2_of_its_half_angle(h):
    V, F = _sphere([0.0, 0.0, h])
    vis = ambient_visibility(V, F, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), samples=2048)
    assert vis[0] == pytest.approx(1.0 - (1.0 / h) ** 2, abs=0.01)


def test_open_enclosed_facing_away_and_deterministic():
    V, F = _sphere([0.0, 0.0, 0.0])
    pts = np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 0.2], [0.0, 0.0, -1.5]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.3, 0.1, 1.0], [0.0, 0.0, -1.0]])
    vis = ambient_visibility(V, F, pts, nrm, samples=256, offset=1e-6)
    np.testing.assert_allclose(vis, [1.0, 0.0, 1.0])
    a = ambient_visibility(V, F, pts + [0.0, 1.2, 0.0], nrm, samples=128)
    b = ambient_visibility(V, F, pts + [0.0, 1.2, 0.0], nrm, samples=128)
    np.testing.assert_array_equal(a, b)
    assert ambient_visibility(V, F, np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
