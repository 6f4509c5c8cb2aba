"""benchmarks/training_pose.py on an exact capture: the one-timestep bound is the ground truth, the
oracle changes nothing, and the registration report reads the avatar's parameters."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import load_benchmark


def _module():
    return load_benchmark("training_pose")


def test_bound_oracle_and_registration_on_an_exact_capture(tiny_capture, tiny_avatar_ws, tmp_path, one_thread):
    tp = _module()
    ws = tmp_path / "ws"
    shutil.copytree(tiny_avatar_ws, ws)
    b = tp.bound(Path(tiny_capture), ws, rigid_fixed=True, lpips_weights=None)
    assert b["training_error_mm"] < 1e-3 and b["rigid_fix"]["translation_mm"] < 1e-3
    assert b["test"]["count"] == 64 and b["test"]["psnr"] > 40.0
    o = tp.oracle(Path(tiny_capture), ws)
    assert o["remaining_error_mm"] < 1e-2
    assert np.allclose(o["before"]["translation"], o["after"]["translation"], atol=1e-6)
    from sage_core.avatar.model import Avatar

    av = Avatar.load(ws / "phase1" / "avatar.pt")
    moved = av.params.translation.copy()
    moved[av.params.row_of(av.canonical_timestep)] += np.array([0.002, 0.0, 0.0], moved.dtype)
    av.params = dataclasses.replace(av.params, translation=moved)
    av.save(ws / "phase1" / "avatar.pt")
    r = tp.registration(Path(tiny_capture), ws, "phase1")
    assert r["tracked"]["all_mm"] < 1e-2
    assert r["registered"]["all_mm"] == pytest.approx(2.0, abs=1e-2)
    assert tp.main(["registration", str(tiny_capture), str(ws)]) == 0
    assert json.loads(json.dumps(r)) == r
