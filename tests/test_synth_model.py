"""The procedural head: geometry, rig, blendshapes, and its FLAME-layout files."""

from __future__ import annotations

import pickle
import pickletools
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sage_core.data.synthetic import EXPRESSION_NAMES, IDENTITY_NAMES, build_head, write_model_files
from sage_core.data.synthetic.config import PRESETS
from sage_core.data.synthetic.head import PART_LEFT_EYE, PART_RIGHT_EYE
from sage_core.flame import FlameModel, load_flame_model, load_masks

TINY = PRESETS["tiny"]


@pytest.fixture(scope="module")
def head():
    return build_head(TINY.head_rows, TINY.head_cols, TINY.eye_rows, TINY.eye_cols)


@pytest.fixture(scope="module")
def model_dir(head, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("model")
    write_model_files(head, d)
    return d


def _edges_used_once(faces: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    assert cnt.max() <= 2, "non-manifold edge"
    return uniq[cnt == 1]


def test_geometry_scale_and_topology(head) -> None:
    v, f = head.v_template, head.faces
    assert 3000 <= len(v) <= 5000
    assert f.min() >= 0 and f.max() < len(v)
    skin = head.part == 0
    width = v[skin, 0].max() - v[skin, 0].min()
    top, chin = v[:, 1].max(), v[head.masks["face"], 1].min()
    assert 0.15 <= width <= 0.2  # skull plus ears
    assert 0.18 <= top - chin <= 0.26
    assert np.all(np.abs(v.mean(0)) < 0.06)
    nose_tip = v[head.masks["nose"]][np.argmax(v[head.masks["nose"], 2])]
    assert nose_tip[2] > 0.09 and abs(nose_tip[0]) < 0.005  # the face looks towards +z
    # the only open boundary is the neck base ring
    open_edges = _edges_used_once(f)
    assert set(np.unique(open_edges)) == set(head.masks["boundary"].tolist())
    # outward winding: signed volume of the eyeballs and (closed-up) head is positive
    tri = v[f]
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    assert vol > 0


def test_rig_weights_and_joints(head) -> None:
    w = head.weights
    assert w.shape == (head.n_vertices, 5) and np.all(w >= -1e-12)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(head.j_regressor.sum(1), 1.0, atol=1e-12)
    J = head.joints
    for j, code in ((3, PART_LEFT_EYE), (4, PART_RIGHT_EYE)):
        ids = np.flatnonzero(head.part == code)
        assert np.all(w[ids, j] == 1.0)
        r = np.linalg.norm(head.v_template[ids] - J[j], axis=1)
        assert r.std() < 1e-9  # joint at the eyeball centre
    assert J[3, 0] > 0 > J[4, 0]  # joint 3 is the left eye (+x)
    assert J[0, 1] < J[1, 1] < J[2, 1] < J[3, 1]  # root at the neck base, jaw below the eyes
    vt = head.v_template
    lower_lip = (head.side < 0) & (head.part == 0) & (np.abs(vt[:, 0]) < 0.01) & (vt[:, 1] > head.mouth_y - 0.01) & (vt[:, 2] > 0.05)
    assert lower_lip.any() and np.all(w[lower_lip, 2] > 0.95)
    forehead = head.masks["forehead"]
    assert np.all(w[forehead, 2] == 0)


def test_blendshape_columns(head) -> None:
    S = head.shapedirs
    assert S.shape == (head.n_vertices, 3, 400)
    nz = np.abs(S).reshape(-1, 400).max(0) > 1e-6
    assert np.array_equal(np.flatnonzero(nz[:300]), np.arange(len(IDENTITY_NAMES)))
    assert np.array_equal(np.flatnonzero(nz[300:]), np.arange(len(EXPRESSION_NAMES)))
    assert len(EXPRESSION_NAMES) >= 10
    eyes = (head.part == PART_LEFT_EYE) | (head.part == PART_RIGHT_EYE)
    assert np.all(S[eyes, :, 300:] == 0)
    # identity moves each eyeball rigidly
    for code in (PART_LEFT_EYE, PART_RIGHT_EYE):
        d = S[head.part == code, :, :300]
        assert np.abs(d - d[:1]).max() < 1e-12


def test_pickle_layout_without_chumpy(head, model_dir) -> None:
    raw = (model_dir / "synth_flame.pkl").read_bytes()
    globals_ = set()
    for op, arg, _ in pickletools.genops(raw):
        if op.name in ("GLOBAL", "STACK_GLOBAL"):
            globals_.add(arg)
    assert "chumpy.ch Ch" in globals_
    assert "scipy.sparse.csc csc_matrix" in globals_
    assert raw[:2] == b"\x80\x02"  # protocol 2
    assert "chumpy" not in sys.modules
    data = load_flame_model(model_dir / "synth_flame.pkl")
    assert "chumpy" not in sys.modules
    np.testing.assert_allclose(data.v_template, head.v_template)
    np.testing.assert_array_equal(data.faces, head.faces)
    np.testing.assert_allclose(data.j_regressor, head.j_regressor)
    np.testing.assert_allclose(data.lbs_weights, head.weights)
    np.testing.assert_allclose(data.exprdirs, head.shapedirs[:, :, 300:], atol=1e-7)
    assert data.parents.tolist() == [-1, 0, 1, 1, 1]


def test_pickle_dict_keys(model_dir) -> None:
    class _Stub:
        def __init__(self, *a):
            pass

        def __setstate__(self, st):
            self.__dict__.update(st)

    class _U(pickle.Unpickler):
        def find_class(self, module, name):
            if module.startswith("chumpy") or module.startswith("scipy.sparse.csc"):
                return type(name, (_Stub,), {})
            return super().find_class(module, name)

    with open(model_dir / "synth_flame.pkl", "rb") as fh:
        d = _U(fh, encoding="latin1").load()
    assert {"v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "J", "bs_style", "bs_type"} <= set(d)
    assert d["kintree_table"][0].tolist() == [4294967295, 0, 1, 1, 1]
    assert d["bs_style"] == "lbs" and d["bs_type"] == "lrotmin"
    assert d["shapedirs"].x.shape[1:] == (3, 400) and d["posedirs"].x.shape[1:] == (3, 36)
    assert set(d["J_regressor"].__dict__) >= {"data", "indices", "indptr", "_shape"}


def test_npz_and_masks(head, model_dir) -> None:
    a = load_flame_model(model_dir / "synth_flame.npz")
    np.testing.assert_array_equal(a.v_template, head.v_template)
    np.testing.assert_array_equal(a.shapedirs, head.shapedirs[:, :, :300])
    masks = load_masks(model_dir / "FLAME_masks.pkl")
    need = {"face", "scalp", "neck", "lips", "eye_region", "left_eye_region", "right_eye_region", "left_eyeball",
            "right_eyeball", "nose", "forehead", "left_ear", "right_ear", "boundary", "left_iris", "right_iris"}
    assert need <= set(masks)
    for k in need:
        assert masks[k].size > 0 and masks[k].max() < head.n_vertices, k
    assert np.all(head.part[masks["left_eyeball"]] == PART_LEFT_EYE)
    assert np.all(head.v_template[masks["left_ear"], 0] > 0.05)


@pytest.fixture(scope="module")
def flame(model_dir):
    return FlameModel(load_flame_model(model_dir / "synth_flame.npz")).double()


def test_lbs_jaw_opens_lips_and_keeps_forehead(head, flame) -> None:
    rest = flame().vertices[0].numpy()
    with torch.no_grad():
        out = flame(jaw_pose=torch.tensor([[0.3, 0.0, 0.0]], dtype=torch.float64)).vertices[0].numpy()
    assert np.all(np.isfinite(out))
    d = np.linalg.norm(out - rest, axis=1)
    assert d[head.masks["forehead"]].max() < 1e-9
    chin = head.masks["face"][head.v_template[head.masks["face"], 1] < head.mouth_y - 0.02]
    assert d[chin].mean() > 0.01
    # the mouth slit opens: lower copies of the slit move away from the upper ones
    up, lo = head.slit_pairs[:, 0], head.slit_pairs[:, 1]
    assert len(up) >= 3
    assert np.abs(rest[up] - rest[lo]).max() < 1e-12
    assert np.all(head.side[up] > 0) and np.all(head.side[lo] < 0)
    gap = np.linalg.norm(out[lo] - out[up], axis=1)
    assert gap.max() > 0.01


def test_lbs_eyes_and_expressions(head, flame) -> None:
    rest = flame().vertices[0].numpy()
    J = flame().joints[0].numpy()
    with torch.no_grad():
        eyes = flame(eyes_pose=torch.tensor([[0.0, 0.3, 0.0, 0.0, 0.3, 0.0]], dtype=torch.float64)).vertices[0].numpy()
    for j, code in ((3, PART_LEFT_EYE), (4, PART_RIGHT_EYE)):
        ids = head.part == code
        assert np.abs(eyes[ids] - rest[ids]).max() > 1e-3
        np.testing.assert_allclose(np.linalg.norm(eyes[ids] - J[j], axis=1), np.linalg.norm(rest[ids] - J[j], axis=1), atol=1e-12)
    skin = head.part == 0
    assert np.abs(eyes[skin] - rest[skin]).max() < 1e-12
    for k, name in enumerate(EXPRESSION_NAMES):
        e = torch.zeros(1, 100, dtype=torch.float64)
        e[0, k] = 1.0
        with torch.no_grad():
            v = flame(expr=e).vertices[0].numpy()
        assert np.linalg.norm(v - rest, axis=1).max() > 1e-3, name
    # blinking closes the lid over the eyeball: the lid skin moves forward by more than the socket depth
    e = torch.zeros(1, 100, dtype=torch.float64)
    e[0, EXPRESSION_NAMES.index("blink")] = 1.0
    with torch.no_grad():
        v = flame(expr=e).vertices[0].numpy()
    lid = head.masks["left_eye_region"]
    assert (v[lid, 2] - rest[lid, 2]).max() > 0.008
