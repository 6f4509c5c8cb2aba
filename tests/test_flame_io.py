"""FLAME model file IO (chumpy-free pickle, validation, npz round trip) and the teeth extension."""

from __future__ import annotations

import copyreg
import json
import pickle
import struct
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from sage_core.errors import InputError
from sage_core.flame import FlameModel, FlameModelData, add_teeth, load_flame_model, save_flame_npz
from sage_core.flame.model_io import validate_model
from sage_core.flame.teeth import LIP_RING_LOWER, LIP_RING_UPPER, teeth_faces

V, F, J, K = 12, 10, 5, 310


class _FakeCh:
    """Mimics chumpy.ch.Ch when pickled: copyreg._reconstructor + state dict {"x": array}."""

    def __init__(self, x: np.ndarray) -> None:
        self.x = x

    def __reduce_ex__(self, protocol: int):
        return (copyreg._reconstructor, (type(self), object, None), {"x": self.x})


class _FakeSelect:
    """Mimics chumpy.reordering.Select: state {"a", "idxs", "preferred_shape"}."""

    def __init__(self, a, idxs: np.ndarray, preferred_shape: tuple[int, ...]) -> None:
        self.a, self.idxs, self.preferred_shape = a, idxs, preferred_shape

    def __reduce_ex__(self, protocol: int):
        state = {"a": self.a, "idxs": self.idxs, "preferred_shape": self.preferred_shape}
        return (copyreg._reconstructor, (type(self), object, None), state)


class _FakeCsc:
    """Mimics a scipy.sparse.csc.csc_matrix pickled by an old scipy."""

    def __init__(self, dense: np.ndarray) -> None:
        import scipy.sparse

        m = scipy.sparse.csc_matrix(dense)
        self.state = {"data": m.data, "indices": m.indices, "indptr": m.indptr, "_shape": m.shape,
                      "format": "csc", "maxprint": 50}

    def __reduce_ex__(self, protocol: int):
        return (copyreg._reconstructor, (type(self), object, None), self.state)


def _install_fake_modules(monkeypatch: pytest.MonkeyPatch) -> None:
    for cls, module, name in ((_FakeCh, "chumpy.ch", "Ch"), (_FakeSelect, "chumpy.reordering", "Select"),
                              (_FakeCsc, "scipy.sparse.csc", "csc_matrix")):
        cls.__module__, cls.__name__, cls.__qualname__ = module, name, name
        mod = types.ModuleType(module)
        setattr(mod, name, cls)
        monkeypatch.setitem(sys.modules, module, mod)
    monkeypatch.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))


def random_arrays(seed: int = 0, n_comp: int = K) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    weights = rng.random((V, J))
    return {
        "v_template": rng.normal(size=(V, 3)),
        "f": rng.integers(0, V, size=(F, 3)).astype(np.uint32),
        "shapedirs": rng.normal(size=(V, 3, n_comp)) * 1e-2,
        "posedirs": rng.normal(size=(V, 3, 9 * (J - 1))) * 1e-2,
        "J_regressor": rng.random((J, V)) * (rng.random((J, V)) < 0.5),
        "weights": weights / weights.sum(1, keepdims=True),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.uint32),
        "J": rng.normal(size=(J, 3)),
    }


def write_chumpy_pickle(path: Path, arrays: dict[str, np.ndarray], monkeypatch: pytest.MonkeyPatch,
                        select_shapedirs: bool = False) -> None:
    _install_fake_modules(monkeypatch)
    d: dict[str, object] = dict(arrays)
    d["v_template"] = _FakeCh(arrays["v_template"])
    d["posedirs"] = _FakeCh(arrays["posedirs"])
    d["J_regressor"] = _FakeCsc(arrays["J_regressor"])
    if select_shapedirs:
        sd = arrays["shapedirs"]
        flat = _FakeCh(sd.ravel()[::-1].copy())
        d["shapedirs"] = _FakeSelect(flat, np.arange(sd.size)[::-1].copy(), sd.shape)
    else:
        d["shapedirs"] = _FakeCh(arrays["shapedirs"])
    d["bs_style"] = "lbs"
    d["bs_type"] = "lrotmin"
    with open(path, "wb") as fh:
        pickle.dump(d, fh, protocol=2)


def _check_matches(data: FlameModelData, arrays: dict[str, np.ndarray]) -> None:
    np.testing.assert_array_equal(data.v_template, arrays["v_template"])
    np.testing.assert_array_equal(data.faces, arrays["f"].astype(np.int64))
    np.testing.assert_array_equal(data.shapedirs, arrays["shapedirs"][..., :300])
    np.testing.assert_array_equal(data.exprdirs, arrays["shapedirs"][..., 300:])
    np.testing.assert_array_equal(data.posedirs, arrays["posedirs"])
    np.testing.assert_array_equal(data.j_regressor, arrays["J_regressor"])
    np.testing.assert_array_equal(data.lbs_weights, arrays["weights"])
    np.testing.assert_array_equal(data.parents, [-1, 0, 1, 1, 1])
    assert data.parents.dtype == np.int64 and data.faces.dtype == np.int64
    assert data.n_base_vertices == V and data.face_table == "flame"


def test_pickle_loads_in_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    arrays = random_arrays()
    path = tmp_path / "generic_model.pkl"
    write_chumpy_pickle(path, arrays, monkeypatch)
    monkeypatch.setitem(sys.modules, "chumpy", None)  # any import of chumpy would now fail
    monkeypatch.setitem(sys.modules, "chumpy.ch", None)
    data = load_flame_model(path)
    _check_matches(data, arrays)
    assert data.version == "flame2020"
    assert data.n_shape == 300 and data.n_expr == K - 300


def test_pickle_loads_without_chumpy_in_subprocess(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    arrays = random_arrays(seed=1)
    path = tmp_path / "flame2023.pkl"
    write_chumpy_pickle(path, arrays, monkeypatch, select_shapedirs=True)
    code = (
        "import sys, json\n"
        "sys.modules['chumpy'] = None\n"
        "from sage_core.flame.model_io import load_flame_model\n"
        f"d = load_flame_model({str(path)!r})\n"
        "assert 'chumpy.ch' not in sys.modules or sys.modules['chumpy.ch'] is None\n"
        "print(json.dumps({'v': d.v_template.tolist(), 'sd': d.shapedirs[..., :3].tolist(),"
        " 'ed': d.exprdirs.tolist(), 'jr': d.j_regressor.tolist(), 'p': d.parents.tolist(),"
        " 'version': d.version}))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    np.testing.assert_array_equal(out["v"], arrays["v_template"])
    np.testing.assert_array_equal(out["sd"], arrays["shapedirs"][..., :3])
    np.testing.assert_array_equal(out["ed"], arrays["shapedirs"][..., 300:])
    np.testing.assert_array_equal(out["jr"], arrays["J_regressor"])
    assert out["p"] == [-1, 0, 1, 1, 1]
    assert out["version"] == "flame2023"


def test_select_is_evaluated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    arrays = random_arrays(seed=2)
    path = tmp_path / "model.pkl"
    write_chumpy_pickle(path, arrays, monkeypatch, select_shapedirs=True)
    data = load_flame_model(path)
    _check_matches(data, arrays)


def test_no_expression_columns_when_k_at_most_300(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    arrays = random_arrays(seed=3, n_comp=20)
    path = tmp_path / "model.pkl"
    write_chumpy_pickle(path, arrays, monkeypatch)
    data = load_flame_model(path)
    assert data.shapedirs.shape == (V, 3, 20)
    assert data.exprdirs.shape == (V, 3, 0)


def test_plain_pickle_and_npz_round_trip_exact(tmp_path: Path) -> None:
    arrays = random_arrays(seed=4)
    path = tmp_path / "plain.pkl"
    with open(path, "wb") as fh:
        pickle.dump(arrays, fh)
    data = load_flame_model(path)
    _check_matches(data, arrays)
    data.vertex_groups["extra"] = np.array([1, 5, 7])
    data.face_table = "flame+custom"
    npz = save_flame_npz(data, tmp_path / "sub" / "model.npz")
    assert not any(p.name.endswith(".tmp") for p in npz.parent.iterdir())
    back = load_flame_model(npz)
    for key in ("v_template", "faces", "shapedirs", "exprdirs", "posedirs", "j_regressor", "lbs_weights", "parents"):
        a, b = getattr(data, key), getattr(back, key)
        assert a.dtype == b.dtype and np.array_equal(a, b), key
    assert back.n_base_vertices == data.n_base_vertices
    assert back.face_table == "flame+custom" and back.version == data.version
    assert set(back.vertex_groups) == {"extra"}
    np.testing.assert_array_equal(back.vertex_groups["extra"], [1, 5, 7])


def _write_plain(tmp_path: Path, arrays: dict) -> Path:
    path = tmp_path / "bad.pkl"
    with open(path, "wb") as fh:
        pickle.dump(arrays, fh)
    return path


def test_missing_key_is_named(tmp_path: Path) -> None:
    arrays = random_arrays()
    del arrays["posedirs"]
    with pytest.raises(InputError, match="posedirs"):
        load_flame_model(_write_plain(tmp_path, arrays))


def test_wrong_shape_names_key_and_shapes(tmp_path: Path) -> None:
    arrays = random_arrays()
    arrays["weights"] = arrays["weights"][:, :4]
    with pytest.raises(InputError) as info:
        load_flame_model(_write_plain(tmp_path, arrays))
    msg = str(info.value)
    assert "weights" in msg and f"({V},4)" in msg and f"({V},{J})" in msg
    assert info.value.path.name == "bad.pkl"


def test_non_finite_is_rejected(tmp_path: Path) -> None:
    arrays = random_arrays()
    arrays["v_template"][3, 1] = np.nan
    with pytest.raises(InputError, match="v_template.*NaN"):
        load_flame_model(_write_plain(tmp_path, arrays))


def test_garbage_and_missing_files(tmp_path: Path) -> None:
    junk = tmp_path / "junk.pkl"
    junk.write_bytes(b"\x00\x01 not a pickle")
    with pytest.raises(InputError, match="junk.pkl"):
        load_flame_model(junk)
    with pytest.raises(InputError, match="not found"):
        load_flame_model(tmp_path / "missing.pkl")
    npz = tmp_path / "other.npz"
    np.savez(npz, a=np.zeros(3))
    with pytest.raises(InputError, match="format"):
        load_flame_model(npz)


def test_validate_rejects_bad_parents_and_faces() -> None:
    arrays = random_arrays()
    data = FlameModelData(
        v_template=arrays["v_template"], faces=arrays["f"].astype(np.int64),
        shapedirs=arrays["shapedirs"][..., :300], exprdirs=arrays["shapedirs"][..., 300:],
        posedirs=arrays["posedirs"], j_regressor=arrays["J_regressor"], lbs_weights=arrays["weights"],
        parents=np.array([-1, 0, 3, 1, 1]), n_base_vertices=V,
    )
    with pytest.raises(InputError, match="parents"):
        validate_model(data)
    data.parents = np.array([-1, 0, 1, 1, 1])
    validate_model(data)
    data.faces = data.faces.copy()
    data.faces[0, 0] = V
    with pytest.raises(InputError, match="faces"):
        validate_model(data)


# --- teeth extension (docs/formats.md §4) on a random 5023-vertex model ---

V0 = 5023


def flame_sized_model(seed: int = 0) -> FlameModelData:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(V0, 3)) * 0.1
    x = np.linspace(-0.025, 0.025, 15)
    v[LIP_RING_UPPER] = np.stack([x, 0.006 + 0.001 * rng.random(15), 0.09 + 0.01 * np.cos(x * 40)], 1)
    v[LIP_RING_LOWER] = np.stack([x, -0.006 - 0.001 * rng.random(15), 0.09 + 0.01 * np.cos(x * 40)], 1)
    w = rng.random((V0, 5)) ** 4
    jr = rng.random((5, V0))
    return FlameModelData(
        v_template=v,
        faces=rng.integers(0, V0, size=(200, 3)),
        shapedirs=rng.normal(size=(V0, 3, 4)) * 0.01,
        exprdirs=rng.normal(size=(V0, 3, 3)) * 0.01,
        posedirs=rng.normal(size=(V0, 3, 36)) * 0.001,
        j_regressor=jr / jr.sum(1, keepdims=True),
        lbs_weights=w / w.sum(1, keepdims=True),
        parents=np.array([-1, 0, 1, 1, 1]),
        n_base_vertices=V0,
        version="test",
    )


def test_counts_groups_and_buffers() -> None:
    d = flame_sized_model()
    t = add_teeth(d)
    assert t.n_vertices == 5143 and t.n_faces == 200 + 168
    assert t.n_base_vertices == V0 and t.face_table == "flame+sage-teeth-v1"
    np.testing.assert_array_equal(t.v_template[:V0], d.v_template)
    np.testing.assert_array_equal(t.faces[:200], d.faces)
    up, lo = t.vertex_groups["teeth_upper"], t.vertex_groups["teeth_lower"]
    assert len(up) == 60 and len(lo) == 60 and set(up) | set(lo) == set(range(V0, 5143))
    ring = (d.shapedirs[LIP_RING_UPPER] + d.shapedirs[LIP_RING_LOWER]) / 2
    for g in range(8):
        np.testing.assert_allclose(t.shapedirs[V0 + 15 * g: V0 + 15 * (g + 1)], ring)
    assert not t.exprdirs[V0:].any() and not t.posedirs[V0:].any() and not t.j_regressor[:, V0:].any()
    np.testing.assert_array_equal(t.lbs_weights[up], np.eye(5)[[1] * 60])
    np.testing.assert_array_equal(t.lbs_weights[lo], np.eye(5)[[2] * 60])
    np.testing.assert_array_equal(up, V0 + np.r_[0:15, 30:45, 60:90])


def test_vertex_positions_follow_the_recipe() -> None:
    d = flame_sized_model(1)
    t = add_teeth(d)
    U, L = d.v_template[LIP_RING_UPPER], d.v_template[LIP_RING_LOWER]
    dd = np.linalg.norm(U - L, axis=1).mean()
    mid = (U + L) / 2
    mid[:, 1] = mid[:, 1].mean()
    mid[:, 2] -= 1.5 * dd
    new = t.v_template[V0:].reshape(8, 15, 3)
    upper_edge = mid + [0, 0.1 * dd, 0]
    lower_edge = mid + [0, -0.1 * dd, -0.4 * dd]
    np.testing.assert_allclose(new[2], upper_edge)
    np.testing.assert_allclose(new[0], upper_edge + [0, 2 * dd, 0])
    np.testing.assert_allclose(new[3], lower_edge)
    np.testing.assert_allclose(new[1], lower_edge - [0, 2 * dd, 0])
    for back, front in ((4, 0), (5, 2), (6, 1), (7, 3)):
        np.testing.assert_allclose(new[back], new[front] - [0, 0, dd])


def test_face_orientation_with_ring_towards_plus_x() -> None:
    t = add_teeth(flame_sized_model(2))
    f = teeth_faces()
    assert f.shape == (168, 3) and f.min() >= V0 and f.max() < 5143
    assert len({tuple(sorted(x)) for x in f.tolist()}) == 168
    v = t.v_template
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    expected_axes = [(2, 1), (2, -1), (1, -1), (2, 1), (2, -1), (1, 1)]  # upper: front, back, bite; lower
    for s, (axis, sign) in enumerate(expected_axes):
        block = n[28 * s: 28 * (s + 1)]
        assert (sign * block[:, axis] > 0.9).all(), s


def test_skinning_of_teeth_groups() -> None:
    t = add_teeth(flame_sized_model(3))
    model = FlameModel(t, dtype=torch.float64)
    up = torch.as_tensor(t.vertex_groups["teeth_upper"])
    lo = torch.as_tensor(t.vertex_groups["teeth_lower"])
    rest = model()
    jaw = model(jaw_pose=torch.tensor([[0.3, 0.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(jaw.vertices[0, up], rest.vertices[0, up])
    assert (jaw.vertices[0, lo] - rest.vertices[0, lo]).norm(dim=-1).min() > 1e-4
    # lower teeth move rigidly with the jaw transform
    A2 = jaw.A[0, 2]
    expected = rest.vertices[0, lo] @ A2[:3, :3].T + A2[:3, 3]
    torch.testing.assert_close(jaw.vertices[0, lo], expected)
    neck = model(neck_pose=torch.tensor([[0.0, 0.4, 0.0]], dtype=torch.float64))
    assert (neck.vertices[0, up] - rest.vertices[0, up]).norm(dim=-1).min() > 1e-4
    # a VHAP-style 5143-row static offset lines up
    off = torch.zeros(1, 5143, 3, dtype=torch.float64)
    off[0, up] = 0.01
    shifted = model(static_offset=off)
    torch.testing.assert_close(shifted.v_shaped[0, up], rest.v_shaped[0, up] + 0.01)


def test_load_adds_teeth_only_for_5023(tmp_path: Path) -> None:
    d = flame_sized_model(4)
    raw = {
        "v_template": d.v_template, "f": d.faces.astype(np.uint32),
        "shapedirs": np.concatenate([d.shapedirs, np.zeros((V0, 3, 296)), d.exprdirs], axis=2),
        "posedirs": d.posedirs, "J_regressor": d.j_regressor, "weights": d.lbs_weights,
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]]),
    }
    path = tmp_path / "flame2023.pkl"
    with open(path, "wb") as fh:
        pickle.dump(raw, fh, protocol=2)
    auto = load_flame_model(path)
    assert auto.n_vertices == 5143 and auto.n_shape == 300 and auto.n_expr == 3
    plain = load_flame_model(path, add_teeth=False)
    assert plain.n_vertices == V0 and plain.face_table == "flame"
    npz = save_flame_npz(auto, tmp_path / "m.npz")
    again = load_flame_model(npz)  # already has teeth: nothing appended
    assert again.n_vertices == 5143 and again.face_table == auto.face_table
    np.testing.assert_array_equal(again.vertex_groups["teeth_lower"], auto.vertex_groups["teeth_lower"])
    small = save_flame_npz(FlameModelData(
        v_template=d.v_template[:10], faces=np.array([[0, 1, 2]]), shapedirs=d.shapedirs[:10],
        exprdirs=d.exprdirs[:10], posedirs=d.posedirs[:10], j_regressor=d.j_regressor[:, :10],
        lbs_weights=d.lbs_weights[:10], parents=d.parents, n_base_vertices=10), tmp_path / "s.npz")
    assert load_flame_model(small).n_vertices == 10
    with pytest.raises(InputError, match="5023"):
        load_flame_model(small, add_teeth=True)


# --- hostile and unsupported pickles ---


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo should-not-run",))


def test_foreign_globals_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "evil.pkl"
    arrays = random_arrays()
    arrays["J"] = _Evil()
    with open(path, "wb") as fh:
        pickle.dump(arrays, fh, protocol=2)
    with pytest.raises(InputError, match="refusing to load global"):
        load_flame_model(path)


class _FakeAdd:
    def __reduce_ex__(self, protocol: int):
        return (copyreg._reconstructor, (type(self), object, None), {"a": 1, "b": 2})


def test_unsupported_chumpy_expression_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _FakeAdd.__module__, _FakeAdd.__name__, _FakeAdd.__qualname__ = "chumpy.ch_ops", "add", "add"
    mod = types.ModuleType("chumpy.ch_ops")
    mod.add = _FakeAdd  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "chumpy", types.ModuleType("chumpy"))
    monkeypatch.setitem(sys.modules, "chumpy.ch_ops", mod)
    arrays: dict = random_arrays()
    arrays["posedirs"] = _FakeAdd()
    path = tmp_path / "lazy.pkl"
    with open(path, "wb") as fh:
        pickle.dump(arrays, fh, protocol=2)
    with pytest.raises(InputError, match="chumpy.ch_ops.add"):
        load_flame_model(path)


# --- pickles built to exhaust memory, time or the stack ---

_PROTO2, _STOP = b"\x80\x02", b"."


def _unicode(s: str) -> bytes:
    """BINUNICODE."""
    b = s.encode("utf-8")
    return b"X" + len(b).to_bytes(4, "little") + b


def _array_ops(a: np.ndarray) -> bytes:
    """The opcodes that push ``a`` (protocol 2, without PROTO and STOP)."""
    return pickle.dumps(a, protocol=2)[2:-1]


def _laughs(levels: int) -> bytes:
    """{"v_template": L} with L0 = [] and Li = [L(i-1), L(i-1)] through the memo: a file of a few
    hundred bytes that expands to 2**(levels+1) - 1 lists."""
    out = bytearray(_PROTO2 + b"}" + _unicode("v_template") + b"]q\x01")
    for i in range(1, levels + 1):
        out += b"0](h" + bytes([i]) + b"h" + bytes([i]) + b"eq" + bytes([i + 1])  # POP, [GET i, GET i], PUT i+1
    return bytes(out + b"s" + _STOP)


def test_shared_memo_entries_are_not_expanded_exponentially(tmp_path: Path) -> None:
    import time

    from sage_core.flame._unpickle import MAX_NODES

    path = tmp_path / "laughs.pkl"
    path.write_bytes(_laughs(20))  # 2**21 - 1 lists, just past the cap
    assert 2 ** 21 - 1 > MAX_NODES and len(path.read_bytes()) < 300
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=r"laughs\.pkl: .*expands to more than"):
        load_flame_model(path)
    path.write_bytes(_laughs(50))  # unbounded without the cap: 2**51 lists
    with pytest.raises(InputError, match="expands to more than"):
        load_flame_model(path)
    assert time.perf_counter() - t0 < 10


def test_an_array_shared_by_several_keys_is_read_once_for_each(tmp_path: Path) -> None:
    from sage_core.flame._unpickle import load_flame_pickle

    arrays = random_arrays()
    shared = arrays["J"]
    d = {**arrays, "J_copy": shared, "twice": [shared, shared]}  # pickle writes one array and memo references
    path = tmp_path / "shared.pkl"
    with open(path, "wb") as fh:
        pickle.dump(d, fh, protocol=2)
    import pickletools

    gets = [op.name for op, _arg, _pos in pickletools.genops(path.read_bytes()) if op.name.endswith("GET")]
    assert len(gets) >= 3
    out = load_flame_pickle(path)
    np.testing.assert_array_equal(out["J_copy"], shared)
    assert out["twice"].shape == (2, *shared.shape)
    np.testing.assert_array_equal(out["twice"][1], shared)
    _check_matches(load_flame_model(path), arrays)


def _sparse_pickle(rows: int, cols: int) -> bytes:
    """{"J_regressor": csc_matrix} with no entries and the declared shape (rows, cols)."""
    out = bytearray(_PROTO2 + b"}" + _unicode("J_regressor") + b"cscipy.sparse.csc\ncsc_matrix\n)\x81}(")
    for key, a in (("data", np.zeros(0)), ("indices", np.zeros(0, np.int32)), ("indptr", np.zeros(cols + 1, np.int32))):
        out += _unicode(key) + _array_ops(a)
    out += _unicode("_shape") + b"J" + rows.to_bytes(4, "little") + b"J" + cols.to_bytes(4, "little") + b"\x86ub"
    return bytes(out + b"s" + _STOP)


def test_a_sparse_matrix_too_large_to_densify_is_refused(tmp_path: Path) -> None:
    from sage_core.flame._unpickle import MAX_DENSE_ELEMENTS, load_flame_pickle

    small = tmp_path / "small.pkl"
    small.write_bytes(_sparse_pickle(5, 5143))  # FLAME's J_regressor with teeth
    assert load_flame_pickle(small)["J_regressor"].shape == (5, 5143)
    path = tmp_path / "huge_sparse.pkl"
    path.write_bytes(_sparse_pickle(200_000, 200_000))  # 298 GiB dense
    assert 200_000 ** 2 > MAX_DENSE_ELEMENTS
    with pytest.raises(InputError, match=r"huge_sparse\.pkl: .*sparse matrix of shape 200000x200000 is too large"):
        load_flame_model(path)


def _reshape_pickle(shape_item: float) -> bytes:
    """{"v_template": chumpy Reshape(a=zeros(3), shape=[shape_item])}."""
    out = bytearray(_PROTO2 + b"}" + _unicode("v_template") + b"cchumpy.reordering\nReshape\n)\x81}(")
    out += _unicode("a") + _array_ops(np.zeros(3))
    out += _unicode("shape") + b"]G" + struct.pack(">d", shape_item) + b"aub"
    return bytes(out + b"s" + _STOP)


@pytest.mark.parametrize("item", [float("inf"), float("nan")])
def test_a_chumpy_shape_out_of_range_is_malformed(tmp_path: Path, item: float) -> None:
    from sage_core.flame.regions import load_masks

    path = tmp_path / "reshape.pkl"
    path.write_bytes(_reshape_pickle(item))
    with pytest.raises(InputError, match=r"reshape\.pkl: .*malformed Reshape shape"):
        load_flame_model(path)
    with pytest.raises(InputError, match=r"reshape\.pkl: not a readable mask pickle: malformed Reshape shape"):
        load_masks(path)


def test_an_array_shape_nested_100000_deep_is_malformed_not_a_recursion_error(tmp_path: Path) -> None:
    n = 100_000
    out = bytearray(_PROTO2 + b"}" + _unicode("v_template"))
    out += b"cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R"  # an array builder
    out += b"(K\x01" + b"]" * n + b"a" * (n - 1)  # state: version 1, shape [[[...]]] (APPEND n-1 times)
    out += b"cnumpy\ndtype\n" + _unicode("f8") + b"K\x00K\x01\x87R"
    out += b"(K\x03" + _unicode("<") + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb"  # the dtype's state
    out += b"\x89C\x00tb"  # not Fortran, no bytes; BUILD
    path = tmp_path / "deep_shape.pkl"
    path.write_bytes(bytes(out + b"s" + _STOP))
    with pytest.raises(InputError, match=r"deep_shape\.pkl: .*malformed array shape \[\[\[") as ei:
        load_flame_model(path)
    assert len(str(ei.value)) < 400
