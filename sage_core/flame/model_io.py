"""FLAME model files: the official pickle (read without chumpy) and the project's ``.npz``.

Layout of the project's npz (all arrays, ``allow_pickle=False``):

- ``format`` = "sage-flame-v1", ``face_table``, ``version`` (0-d str arrays);
- ``v_template (V,3) f64``, ``faces (F,3) i64``, ``shapedirs (V,3,S) f64``, ``exprdirs (V,3,E) f64``,
  ``posedirs (V,3,P) f64``, ``j_regressor (J,V) f64``, ``lbs_weights (V,J) f64``, ``parents (J,) i64``,
  ``n_base_vertices`` (0-d i64);
- one ``group:<name>`` int64 array per entry of ``vertex_groups``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_writer
from ..errors import InputError, require_file
from ..npz import read_npz, shape_str
from ._unpickle import read_flame_pickle
from .model_data import FlameModelData
from .teeth import FLAME_N_VERTICES, add_teeth as _add_teeth, has_teeth

NPZ_FORMAT = "sage-flame-v1"
N_SHAPE_MAX = 300  # expression columns of the official shapedirs start here
_GROUP_PREFIX = "group:"


def _check_shape(path: Path, key: str, arr: np.ndarray, expected: tuple[int | None, ...]) -> None:
    """Raise InputError unless arr.shape matches expected (None = any size)."""
    ok = arr.ndim == len(expected) and all(e is None or e == s for e, s in zip(expected, arr.shape))
    if not ok:
        exp = "(" + ",".join("?" if e is None else str(e) for e in expected) + ")"
        raise InputError(path, f"key '{key}' has shape {shape_str(arr.shape)}, expected {exp}")


def _check_finite(path: Path, key: str, arr: np.ndarray) -> None:
    if arr.size and not np.all(np.isfinite(arr)):
        raise InputError(path, f"key '{key}' contains NaN or Inf values")


def _as_float(path: Path, key: str, value: object) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"key '{key}' is not a numeric array") from None
    return arr


def validate_model(data: FlameModelData, path: str | Path = "<flame model>") -> None:
    """Check shapes, index ranges and finiteness; raises InputError(path, ...) naming the key."""
    path = Path(path)
    v = data.v_template
    _check_shape(path, "v_template", v, (None, 3))
    V = v.shape[0]
    if V == 0:
        raise InputError(path, "key 'v_template' has no vertices")
    J = data.parents.shape[0] if data.parents.ndim == 1 else -1
    _check_shape(path, "parents", data.parents, (None,))
    if J < 1:
        raise InputError(path, "key 'parents' is empty")
    _check_shape(path, "faces", data.faces, (None, 3))
    _check_shape(path, "shapedirs", data.shapedirs, (V, 3, None))
    _check_shape(path, "exprdirs", data.exprdirs, (V, 3, None))
    _check_shape(path, "posedirs", data.posedirs, (V, 3, 9 * (J - 1)))
    _check_shape(path, "j_regressor", data.j_regressor, (J, V))
    _check_shape(path, "lbs_weights", data.lbs_weights, (V, J))
    for key in ("v_template", "shapedirs", "exprdirs", "posedirs", "j_regressor", "lbs_weights"):
        _check_finite(path, key, getattr(data, key))
    if data.faces.size and (data.faces.min() < 0 or data.faces.max() >= V):
        raise InputError(path, f"key 'faces' indexes vertices outside [0, {V})")
    if data.parents[0] != -1:
        raise InputError(path, f"key 'parents': joint 0 must be the root (-1), found {data.parents[0]}")
    for j in range(1, J):
        if not 0 <= data.parents[j] < j:
            raise InputError(path, f"key 'parents': joint {j} has parent {data.parents[j]}, expected 0..{j - 1}")
    if not 0 < data.n_base_vertices <= V:
        raise InputError(path, f"n_base_vertices {data.n_base_vertices} is outside 1..{V}")
    for name, ids in data.vertex_groups.items():
        if ids.ndim != 1 or (ids.size and (ids.min() < 0 or ids.max() >= V)):
            raise InputError(path, f"vertex group '{name}' holds ids outside [0, {V})")


def _version_label(path: Path) -> str:
    stem = path.stem.lower()
    if "2023" in stem:
        return "flame2023" + ("_no_jaw" if "no_jaw" in stem else "")
    if "generic_model" in stem or "2020" in stem:
        return "flame2020"
    return path.stem


def _from_pickle_dict(path: Path, d: dict) -> FlameModelData:
    required = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
    missing = [k for k in required if k not in d]
    if missing:
        raise InputError(path, f"FLAME pickle lacks key(s) {', '.join(repr(k) for k in missing)}")
    v_template = _as_float(path, "v_template", d["v_template"])
    _check_shape(path, "v_template", v_template, (None, 3))
    V = v_template.shape[0]
    kintree = np.asarray(d["kintree_table"])
    _check_shape(path, "kintree_table", kintree, (2, None))
    J = kintree.shape[1]
    parents = kintree[0].astype(np.int64)  # uint32 4294967295 -> large positive, fixed below
    parents[0] = -1
    # Joints are numbered by column: the kintree's row 1 must be 0..J-1 in order.
    if not np.array_equal(kintree[1].astype(np.int64), np.arange(J)):
        raise InputError(path, "key 'kintree_table' row 1 is not 0..J-1 in order")
    shapedirs_all = _as_float(path, "shapedirs", d["shapedirs"])
    _check_shape(path, "shapedirs", shapedirs_all, (V, 3, None))
    K = shapedirs_all.shape[2]
    shapedirs = shapedirs_all[..., : min(K, N_SHAPE_MAX)]
    exprdirs = shapedirs_all[..., N_SHAPE_MAX:] if K > N_SHAPE_MAX else np.zeros((V, 3, 0))
    posedirs = _as_float(path, "posedirs", d["posedirs"])
    _check_shape(path, "posedirs", posedirs, (V, 3, 9 * (J - 1)))
    j_reg = _as_float(path, "J_regressor", d["J_regressor"])
    _check_shape(path, "J_regressor", j_reg, (J, V))
    weights = _as_float(path, "weights", d["weights"])
    _check_shape(path, "weights", weights, (V, J))
    faces_raw = np.asarray(d["f"])
    _check_shape(path, "f", faces_raw, (None, 3))
    if not np.issubdtype(faces_raw.dtype, np.integer):
        raise InputError(path, f"key 'f' has dtype {faces_raw.dtype}, expected integers")
    data = FlameModelData(
        v_template=v_template,
        faces=faces_raw.astype(np.int64),
        shapedirs=np.ascontiguousarray(shapedirs),
        exprdirs=np.ascontiguousarray(exprdirs),
        posedirs=posedirs,
        j_regressor=j_reg,
        lbs_weights=weights,
        parents=parents,
        n_base_vertices=V,
        face_table="flame",
        version=_version_label(path),
    )
    validate_model(data, path)
    return data


def _str_item(path: Path, z: dict[str, np.ndarray], key: str) -> str:
    if key not in z:
        raise InputError(path, f"npz lacks key '{key}'")
    return str(z[key].item() if z[key].ndim == 0 else z[key])


def _numeric(path: Path, key: str, arr: np.ndarray) -> np.ndarray:
    if arr.dtype.kind not in "biuf":
        raise InputError(path, f"key '{key}' has dtype {arr.dtype}, expected numbers")
    return arr


def _from_npz(path: Path) -> FlameModelData:
    z = read_npz(path, "FLAME model file")
    fmt = _str_item(path, z, "format")
    if fmt != NPZ_FORMAT:
        raise InputError(path, f"npz format is '{fmt}', expected '{NPZ_FORMAT}'")
    arrays = {}
    for key in ("v_template", "faces", "shapedirs", "exprdirs", "posedirs", "j_regressor",
                "lbs_weights", "parents", "n_base_vertices"):
        if key not in z:
            raise InputError(path, f"npz lacks key '{key}'")
        arrays[key] = _numeric(path, key, z[key])
    groups = {k[len(_GROUP_PREFIX):]: _numeric(path, k, z[k]).astype(np.int64) for k in z if k.startswith(_GROUP_PREFIX)}
    face_table = _str_item(path, z, "face_table")
    version = _str_item(path, z, "version")
    if arrays["n_base_vertices"].size != 1:
        raise InputError(path, "key 'n_base_vertices' is not a single number")
    data = FlameModelData(
        v_template=arrays["v_template"].astype(np.float64),
        faces=arrays["faces"].astype(np.int64),
        shapedirs=arrays["shapedirs"].astype(np.float64),
        exprdirs=arrays["exprdirs"].astype(np.float64),
        posedirs=arrays["posedirs"].astype(np.float64),
        j_regressor=arrays["j_regressor"].astype(np.float64),
        lbs_weights=arrays["lbs_weights"].astype(np.float64),
        parents=arrays["parents"].astype(np.int64),
        n_base_vertices=int(arrays["n_base_vertices"]),
        face_table=face_table,
        version=version,
        vertex_groups=groups,
    )
    validate_model(data, path)
    return data


def _from_pickle_file(path: Path) -> FlameModelData:
    """A FLAME pickle read by the restricted reader; InputError naming ``path`` for any problem."""
    return _from_pickle_dict(path, read_flame_pickle(path, "FLAME pickle", "the FLAME model"))


def load_flame_model(path: str | Path, add_teeth: bool | None = None, *, npz_only: bool = False) -> FlameModelData:
    """Load a FLAME model from the official pickle or the project's npz.

    path: ``.pkl`` (FLAME 2020 ``generic_model.pkl``, FLAME 2023 ``flame2023.pkl``; read by the
        restricted reader of :mod:`sage_core.flame._unpickle`, chumpy is not needed) or ``.npz``
        written by :func:`save_flame_npz` (loaded exactly). A file named ``.npz`` is read only as a
        zip archive of plain arrays; another name is read by its content (zip or pickle).
    add_teeth: append the 120 teeth vertices (docs/formats.md §4). None = only when the model
        has the plain 5023-vertex FLAME topology; True on any other topology raises InputError.
    npz_only: accept only the project's npz, whatever the file's name (for files sage wrote itself).
    Raises InputError(path, ...) for a missing file, bad keys, shapes or values.
    """
    path = Path(path)
    require_file(path, "FLAME model file")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    is_zip = magic.startswith(b"PK")
    if (npz_only or path.suffix.lower() == ".npz") and not is_zip:
        raise InputError(path, "not a zip archive: an .npz FLAME model must be the project's npz "
                               "(sage reads pickles only from .pkl files)")
    try:
        data = _from_npz(path) if is_zip else _from_pickle_file(path)
    except MemoryError:
        raise InputError(path, "the FLAME model's arrays do not fit in memory (a FLAME model takes a few hundred MB "
                               "at most; the file declares more)") from None

    if add_teeth is None:
        add_teeth = data.n_vertices == FLAME_N_VERTICES and not has_teeth(data)
    if add_teeth and not has_teeth(data):
        if data.n_vertices != FLAME_N_VERTICES:
            raise InputError(path, f"teeth need the {FLAME_N_VERTICES}-vertex FLAME topology, "
                                   f"the model has {data.n_vertices} vertices")
        data = _add_teeth(data)
    return data


def save_flame_npz(data: FlameModelData, path: str | Path) -> Path:
    """Write the model as the project's npz, atomically (temp file + rename). Returns the path."""
    path = Path(path)
    validate_model(data, path)
    arrays: dict[str, np.ndarray] = {
        "format": np.array(NPZ_FORMAT),
        "face_table": np.array(data.face_table),
        "version": np.array(data.version),
        "v_template": np.asarray(data.v_template, dtype=np.float64),
        "faces": np.asarray(data.faces, dtype=np.int64),
        "shapedirs": np.asarray(data.shapedirs, dtype=np.float64),
        "exprdirs": np.asarray(data.exprdirs, dtype=np.float64),
        "posedirs": np.asarray(data.posedirs, dtype=np.float64),
        "j_regressor": np.asarray(data.j_regressor, dtype=np.float64),
        "lbs_weights": np.asarray(data.lbs_weights, dtype=np.float64),
        "parents": np.asarray(data.parents, dtype=np.int64),
        "n_base_vertices": np.array(int(data.n_base_vertices), dtype=np.int64),
    }
    for name, ids in data.vertex_groups.items():
        arrays[_GROUP_PREFIX + name] = np.asarray(ids, dtype=np.int64)
    with atomic_writer(path) as fh:
        np.savez(fh, **arrays)
    return path
