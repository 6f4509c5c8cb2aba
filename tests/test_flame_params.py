"""FLAME parameter files: VHAP per-timestep npz (mixed leading dims), GA T-leading files, stacking."""

from __future__ import annotations

import inspect
from pathlib import Path

import numpy as np
import pytest

from sage_core.errors import InputError
from sage_core.flame.params import (
    FlameParams,
    load_param_npz,
    load_stacked_npz,
    save_param_npz,
    save_stacked_npz,
    stack_params,
)

V = 5023


def vhap_arrays(seed: int, n_vertices: int = V, dynamic: bool = True) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = {
        "translation": rng.normal(size=(1, 3)).astype(np.float32),
        "rotation": rng.normal(size=(1, 3)).astype(np.float32),
        "neck_pose": rng.normal(size=(1, 3)).astype(np.float32),
        "jaw_pose": rng.normal(size=(1, 3)).astype(np.float32),
        "eyes_pose": rng.normal(size=(1, 6)).astype(np.float32),
        "shape": np.linspace(0, 1, 300).astype(np.float32),
        "expr": rng.normal(size=(1, 100)).astype(np.float32),
        "static_offset": np.full((1, n_vertices, 3), 0.001, np.float32),
    }
    if dynamic:
        d["dynamic_offset"] = rng.normal(size=(1, n_vertices, 3)).astype(np.float32) * 1e-3
    return d


def test_vhap_round_trip_exact_shapes(tmp_path: Path) -> None:
    src = vhap_arrays(0)
    np.savez(tmp_path / "00007.npz", **src)
    p = load_param_npz(tmp_path / "00007.npz", timesteps=[7])
    assert p.n_timesteps == 1 and list(p.timesteps) == [7]
    assert p.shape.shape == (300,) and p.expr.shape == (1, 100) and p.eyes_pose.shape == (1, 6)
    assert p.static_offset is not None and p.static_offset.shape == (V, 3)
    assert p.dynamic_offset is not None and p.dynamic_offset.shape == (1, V, 3)
    save_param_npz(tmp_path / "out.npz", p, 0)
    with np.load(tmp_path / "out.npz") as z:
        assert set(z.files) == set(src)
        for k, v in src.items():
            assert z[k].shape == v.shape, k
            assert z[k].dtype == np.float32, k
            np.testing.assert_array_equal(z[k], v)
    assert not list(tmp_path.glob("*.tmp"))


def test_ga_t_leading_file_and_motion_without_shape(tmp_path: Path) -> None:
    T = 4
    rng = np.random.default_rng(1)
    d = {k: rng.normal(size=(T, w)).astype(np.float32) for k, w in
         [("translation", 3), ("rotation", 3), ("neck_pose", 3), ("jaw_pose", 3), ("eyes_pose", 6), ("expr", 50)]}
    d["dynamic_offset"] = np.zeros((T, 20, 3), np.float32)
    np.savez(tmp_path / "motion.npz", **d)
    with pytest.raises(InputError, match="'shape'"):
        load_param_npz(tmp_path / "motion.npz")
    m = load_param_npz(tmp_path / "motion.npz", require_shape=False)
    assert m.n_timesteps == T and m.n_expr == 50 and m.shape.shape == (0,)
    assert list(m.timesteps) == [0, 1, 2, 3] and m.static_offset is None and m.n_offset_vertices == 20
    d["shape"] = np.ones(300, np.float32)
    d["static_offset"] = np.zeros((1, 20, 3), np.float32)
    np.savez(tmp_path / "flame_param.npz", **d)
    g = load_param_npz(tmp_path / "flame_param.npz")
    np.testing.assert_array_equal(g.expr, d["expr"])
    assert g.static_offset is not None and g.static_offset.shape == (20, 3)


@pytest.mark.parametrize(
    "key, value, needle",
    [
        ("expr", None, "lacks key(s) 'expr'"),
        ("rotation", np.zeros((1, 4), np.float32), "key 'rotation' has shape (1,4), expected (1,3)"),
        ("eyes_pose", np.zeros((1, 3), np.float32), "key 'eyes_pose' has shape (1,3), expected (1,6)"),
        ("jaw_pose", np.zeros((2, 3), np.float32), "key 'jaw_pose' has shape (2,3), expected (1,3)"),
        ("shape", np.zeros((2, 300), np.float32), "key 'shape' has shape (2,300)"),
        ("static_offset", np.zeros((1, V, 2), np.float32), "key 'static_offset' has shape (1,5023,2)"),
        ("expr", np.full((1, 100), np.nan, np.float32), "key 'expr' contains 100 NaN or Inf"),
        ("translation", np.array([[0, np.inf, 0]], np.float32), "key 'translation' contains 1 NaN or Inf"),
        ("expr", np.array([["a"] * 100]), "key 'expr' has dtype"),
    ],
)
def test_invalid_files_name_key_and_file(tmp_path: Path, key: str, value, needle: str) -> None:
    d = vhap_arrays(2, n_vertices=V)
    if value is None:
        d.pop(key)
    else:
        d[key] = value
    path = tmp_path / "bad.npz"
    np.savez(path, **d)
    with pytest.raises(InputError) as info:
        load_param_npz(path)
    assert info.value.path == path
    assert needle in str(info.value)


def test_unreadable_and_missing_file(tmp_path: Path) -> None:
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 garbage")
    with pytest.raises(InputError, match="cannot read npz"):
        load_param_npz(tmp_path / "junk.npz")
    with pytest.raises(InputError, match="not found"):
        load_param_npz(tmp_path / "none.npz")


def _one(seed: int, t: int, **kw) -> FlameParams:
    from sage_core.flame.params import params_from_arrays

    return params_from_arrays(f"{t:05d}.npz", vhap_arrays(seed, n_vertices=30, **kw), timesteps=np.array([t]))


def test_stack_select_and_stacked_round_trip(tmp_path: Path) -> None:
    items = [_one(s, t, dynamic=(t != 5)) for s, t in [(0, 3), (1, 5), (2, 9)]]
    st = stack_params(items, [f"{t:05d}.npz" for t in (3, 5, 9)])
    assert st.n_timesteps == 3 and list(st.timesteps) == [3, 5, 9]
    np.testing.assert_array_equal(st.expr[1], items[1].expr[0])
    assert st.dynamic_offset is not None and st.dynamic_offset.shape == (3, 30, 3)
    assert np.all(st.dynamic_offset[1] == 0)  # missing dynamic offset -> zeros
    np.testing.assert_array_equal(st.dynamic_offset[2], items[2].dynamic_offset[0])
    assert st.row_of(9) == 2
    with pytest.raises(KeyError):
        st.row_of(4)
    sub = st.select([2, 0])
    assert list(sub.timesteps) == [9, 3]
    np.testing.assert_array_equal(sub.jaw_pose[0], st.jaw_pose[2])
    np.testing.assert_array_equal(st.select_timesteps([5]).rotation[0], items[1].rotation[0])

    save_stacked_npz(tmp_path / "flame_params.npz", st)
    back = load_stacked_npz(tmp_path / "flame_params.npz")
    assert list(back.timesteps) == [3, 5, 9]
    for k in ("shape", "expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation",
              "static_offset", "dynamic_offset"):
        np.testing.assert_array_equal(getattr(back, k), getattr(st, k), err_msg=k)
    with np.load(tmp_path / "flame_params.npz") as z:
        assert z["static_offset"].shape == (1, 30, 3) and z["dynamic_offset"].shape == (3, 30, 3)


def test_stack_rejects_changing_identity() -> None:
    a, b = _one(0, 0), _one(1, 1)
    b.shape = b.shape + 0.5
    with pytest.raises(InputError) as info:
        stack_params([a, b], ["flame_param/00000.npz", "flame_param/00001.npz"])
    assert info.value.path == Path("flame_param/00001.npz") and "'shape'" in str(info.value)
    c = _one(2, 2)
    assert c.static_offset is not None
    c.static_offset = c.static_offset + 0.01
    with pytest.raises(InputError, match="'static_offset' differs"):
        stack_params([a, c], ["a.npz", "c.npz"])


def test_pad_and_trim_offsets() -> None:
    p = _one(0, 0)
    padded = p.pad_offsets(45)
    assert padded.static_offset is not None and padded.static_offset.shape == (45, 3)
    np.testing.assert_array_equal(padded.static_offset[:30], p.static_offset)
    assert np.all(padded.static_offset[30:] == 0)
    assert padded.dynamic_offset is not None and padded.dynamic_offset.shape == (1, 45, 3)
    assert np.all(padded.dynamic_offset[:, 30:] == 0)
    with pytest.raises(ValueError):
        p.pad_offsets(10)
    trimmed = padded.trim_offsets(30)
    np.testing.assert_array_equal(trimmed.static_offset, p.static_offset)


def test_to_torch_matches_flame_forward() -> None:
    import torch

    from sage_core.flame import FlameModel, FlameModelData

    names = set(inspect.signature(FlameModel.forward).parameters) - {"self"}
    st = stack_params([_one(0, 0), _one(1, 1)])
    tensors = st.to_torch("cpu")
    assert set(tensors) <= names and {"shape", "expr", "rotation", "translation"} <= set(tensors)
    assert tensors["expr"].dtype == torch.float32 and tensors["expr"].shape == (2, 100)
    assert tensors["dynamic_offset"].shape == (2, 30, 3)
    rng = np.random.default_rng(0)
    Vm, J = 30, 5
    data = FlameModelData(
        v_template=rng.normal(size=(Vm, 3)) * 0.1, faces=np.zeros((1, 3), np.int64),
        shapedirs=rng.normal(size=(Vm, 3, 8)) * 0.01, exprdirs=rng.normal(size=(Vm, 3, 8)) * 0.01,
        posedirs=np.zeros((Vm, 3, 36)), j_regressor=np.full((J, Vm), 1.0 / Vm),
        lbs_weights=np.eye(J)[np.zeros(Vm, int)], parents=np.array([-1, 0, 1, 1, 1]), n_base_vertices=Vm,
    )
    out = FlameModel(data)(**tensors)
    assert out.vertices.shape == (2, Vm, 3)
    # only the root joint skins: vertices = R0 (v_shaped − J0) + J0 + t for row 1
    v_shaped = out.v_shaped[1].double()
    from sage_core.geometry.rotations import axis_angle_to_matrix

    R0 = axis_angle_to_matrix(tensors["rotation"][1].double())
    J0 = v_shaped.mean(0)
    expect = (v_shaped - J0) @ R0.T + J0 + tensors["translation"][1].double()
    np.testing.assert_allclose(out.vertices[1].double().numpy(), expect.numpy(), atol=1e-5)
