"""Regions: mask file reading, derived sets, the all-3-vertices face rule, cluster labels."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from sage_core.errors import InputError
from sage_core.flame import Regions, load_masks

# A strip of 10 vertices 0..9 with faces (i, i+1, i+2): face i uses vertices i, i+1, i+2.
N_V = 12  # 10 strip vertices + 2 "teeth" vertices
FACES = np.array([[i, i + 1, i + 2] for i in range(8)] + [[10, 11, 9]])


def _masks() -> dict[str, np.ndarray]:
    return {
        "scalp": np.array([0, 1, 2, 3]),
        "face": np.array([3, 4, 5, 6]),
        "neck": np.array([2]),
        "lips": np.array([5, 6, 7]),
        "boundary": np.array([9]),
        "left_eyeball": np.array([8]),
        "right_eyeball": np.array([7]),
        "left_eye_region": np.array([6]),
        "left_ear": np.array([0]),
        "left_half": np.array([0, 1, 2, 3, 4]),
        "right_half": np.array([5, 6, 7, 8, 9]),
    }


def _regions(with_teeth: bool = True) -> Regions:
    groups = {"teeth_upper": np.array([10]), "teeth_lower": np.array([11])} if with_teeth else {}
    return Regions(_masks(), FACES, N_V, groups)


def test_load_masks_py2_style(tmp_path: Path) -> None:
    path = tmp_path / "FLAME_masks.pkl"
    masks = {k: v.astype(np.uint32)[::-1] for k, v in _masks().items()}
    with open(path, "wb") as fh:
        pickle.dump(masks, fh, protocol=2)
    back = load_masks(path)
    assert set(back) == set(masks)
    for k, v in _masks().items():
        np.testing.assert_array_equal(back[k], np.sort(v))
        assert back[k].dtype == np.int64


def test_load_masks_rejects_bad_files(tmp_path: Path) -> None:
    bad = tmp_path / "bad.pkl"
    with open(bad, "wb") as fh:
        pickle.dump({"face": np.zeros((2, 2), dtype=np.int64)}, fh)
    with pytest.raises(InputError, match="face"):
        load_masks(bad)
    with open(bad, "wb") as fh:
        pickle.dump([1, 2, 3], fh)
    with pytest.raises(InputError, match="bad.pkl"):
        load_masks(bad)
    with pytest.raises(InputError, match="not found"):
        load_masks(tmp_path / "none.pkl")


def test_derived_vertex_sets() -> None:
    r = _regions()
    np.testing.assert_array_equal(r.vertex_ids("hair"), [0, 1])
    np.testing.assert_array_equal(r.vertex_ids("eyeballs"), [7, 8])
    np.testing.assert_array_equal(r.vertex_ids("left_eye"), [6, 8])
    np.testing.assert_array_equal(r.vertex_ids("ears"), [0])
    np.testing.assert_array_equal(r.vertex_ids("teeth"), [10, 11])
    # skin = all \ (eyeballs ∪ hair ∪ lips ∪ boundary ∪ teeth)
    np.testing.assert_array_equal(r.vertex_ids("skin"), [2, 3, 4])
    # teeth join both halves
    assert r.vertex_mask("left_half")[[10, 11]].all() and r.vertex_mask("right_half")[[10, 11]].all()
    assert not r.has("right_eye") or r.vertex_ids("right_eye").tolist() == [7]
    assert not r.has("irises") and not r.has("sclerae")


def test_face_rule_all_three_vertices() -> None:
    r = _regions()
    # face i = (i, i+1, i+2); region "face" = {3,4,5,6} holds faces 3 and 4 only
    np.testing.assert_array_equal(r.face_ids("face"), [3, 4])
    np.testing.assert_array_equal(r.face_ids("skin"), [2])
    np.testing.assert_array_equal(r.face_ids("teeth"), [])
    fm = r.face_mask("scalp")
    assert fm.shape == (9,) and fm.tolist() == [True, True] + [False] * 7
    assert r.vertex_mask("lips").sum() == 3 and r.vertex_mask("lips").shape == (N_V,)


def test_face_labels() -> None:
    r = _regions()
    labels = r.face_labels(["face", "hair", "scalp"])
    assert labels.shape == (9,)
    # hair = {0,1}: no face has all three vertices in it; scalp holds faces 0, 1
    assert labels.tolist() == [4, 4, 1, 2, 2, 1, 1, 1, 1]
    assert r.face_labels([]).tolist() == [1] * 9
    with pytest.raises(KeyError):
        r.face_labels(["no_such_region"])


def test_missing_masks_degrade() -> None:
    r = Regions({"face": np.array([0, 1, 2, 50])}, FACES, N_V)
    assert not r.has("hair") and not r.has("eyeballs") and not r.has("teeth")
    assert r.has("skin") and r.has("all") and r.has("face")
    np.testing.assert_array_equal(r.vertex_ids("face"), [0, 1, 2])  # out-of-range ids dropped
    np.testing.assert_array_equal(r.vertex_ids("skin"), np.arange(N_V))
    with pytest.raises(KeyError, match="hair"):
        r.vertex_mask("hair")


def test_mouth_interior_groups_excluded_from_skin() -> None:
    groups = {"mouth_upper": np.array([3]), "mouth_lower": np.array([4])}
    r = Regions(_masks(), FACES, N_V, groups)
    np.testing.assert_array_equal(r.vertex_ids("mouth_interior"), [3, 4])
    assert not r.vertex_mask("skin")[[3, 4]].any()
    masks = dict(_masks(), mouth_interior=np.array([1]))
    r = Regions(masks, FACES, N_V, groups)
    np.testing.assert_array_equal(r.vertex_ids("mouth_interior"), [1, 3, 4])
    np.testing.assert_array_equal(r.vertex_ids("mouth_upper"), [3])


def test_dict_round_trip_json() -> None:
    r = _regions()
    d = json.loads(json.dumps(r.to_dict()))
    back = Regions.from_dict(d)
    assert back.names == r.names
    for name in r.names:
        np.testing.assert_array_equal(back.vertex_ids(name), r.vertex_ids(name))
        np.testing.assert_array_equal(back.face_mask(name), r.face_mask(name))
    d["vertex_sets"]["face"] = [0, 99]
    with pytest.raises(ValueError, match="face"):
        Regions.from_dict(d)
