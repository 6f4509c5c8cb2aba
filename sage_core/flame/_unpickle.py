"""Read FLAME pickles without chumpy installed.

The official FLAME pickles (``generic_model.pkl``, ``flame2023.pkl``) were written by Python 2 with
chumpy objects and a scipy sparse matrix inside. This module loads them with a restricted
unpickler that replaces those classes by small stand-ins and then turns every value into a plain
numpy array.

What is handled:

- any class from a ``chumpy`` module becomes a :class:`ChumpyStub` that keeps its state dict;
- ``Ch`` (and any other chumpy object whose state has ``x``) evaluates to ``np.asarray(state["x"])``;
- ``chumpy.reordering.Select`` evaluates to ``a.ravel()[idxs].reshape(preferred_shape)`` (``a`` is
  evaluated recursively; without ``preferred_shape`` the result stays flat);
- ``chumpy.reordering.Reshape`` evaluates to ``a.reshape(shape)`` and ``Transpose`` to
  ``a.transpose(axes)``;
- ``scipy.sparse.csc_matrix`` / ``csr_matrix`` under their old (``scipy.sparse.csc``) or new
  (``scipy.sparse._csc``) module names are rebuilt from ``data``, ``indices``, ``indptr`` and
  ``_shape`` and densified.

Any other chumpy expression (for example a lazily evaluated sum) cannot be evaluated without
chumpy's graph machinery and raises :class:`UnsupportedPickle` naming the class. Other globals are
limited to numpy's array reconstruction, ``copyreg._reconstructor``, ``_codecs.encode`` and plain
builtin containers; anything else is refused, so reading a file never runs foreign code.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse


class UnsupportedPickle(ValueError):
    """A pickled object cannot be turned into a plain array."""


class ChumpyStub:
    """Stand-in for any chumpy class: remembers its module, name and state dict."""

    _sage_module: str = "chumpy"
    _sage_name: str = "Ch"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.__dict__["_sage_args"] = args
        self.__dict__.update(kwargs)

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:
            merged: dict[str, Any] = {}
            for part in state:
                if isinstance(part, dict):
                    merged.update(part)
            state = merged
        if isinstance(state, dict):
            self.__dict__.update(state)
        else:
            self.__dict__["_sage_raw_state"] = state

    @property
    def state(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if not k.startswith("_sage_")}


class SparseStub:
    """Stand-in for a pickled scipy sparse matrix (any format with data/indices/indptr)."""

    _sage_format: str = "csc"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.__dict__["_sage_args"] = args

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:
            merged: dict[str, Any] = {}
            for part in state:
                if isinstance(part, dict):
                    merged.update(part)
            state = merged
        if not isinstance(state, dict):
            raise UnsupportedPickle("sparse matrix state is not a dict")
        self.__dict__.update(state)


_chumpy_classes: dict[tuple[str, str], type] = {}
_sparse_classes: dict[str, type] = {}


def _chumpy_class(module: str, name: str) -> type:
    key = (module, name)
    if key not in _chumpy_classes:
        _chumpy_classes[key] = type(name, (ChumpyStub,), {"_sage_module": module, "_sage_name": name})
    return _chumpy_classes[key]


def _sparse_class(fmt: str) -> type:
    if fmt not in _sparse_classes:
        _sparse_classes[fmt] = type(f"{fmt}_matrix", (SparseStub,), {"_sage_format": fmt})
    return _sparse_classes[fmt]


# Globals a model or mask pickle may legitimately name besides chumpy and scipy.sparse; anything
# else (e.g. os.system) is refused, so a hostile file cannot run code while being read.
_NUMPY_NAMES = {"_reconstruct", "scalar", "_frombuffer", "dtype", "ndarray"}
_NUMPY_MODULES = {"numpy", "numpy.core.multiarray", "numpy._core.multiarray", "numpy.core.numeric",
                  "numpy._core.numeric"}
_SAFE_GLOBALS = {
    ("copyreg", "_reconstructor"), ("copy_reg", "_reconstructor"), ("_codecs", "encode"),
    ("collections", "OrderedDict"),
    *(("builtins", n) for n in ("object", "set", "frozenset", "slice", "complex", "bytearray", "list",
                                "dict", "tuple", "int", "float", "str", "bytes", "bool", "range")),
    *(("__builtin__", n) for n in ("object", "set", "frozenset", "slice", "complex", "bytearray", "list",
                                   "dict", "tuple", "int", "float", "str", "bool", "long", "unicode")),
}


class _FlameUnpickler(pickle.Unpickler):
    """Restricted unpickler: chumpy and sparse stand-ins, numpy arrays and plain containers only."""

    def find_class(self, module: str, name: str) -> Any:
        if module == "chumpy" or module.startswith("chumpy."):
            return _chumpy_class(module, name)
        if module.startswith("scipy.sparse") and name in ("csc_matrix", "csr_matrix"):
            return _sparse_class(name[:3])
        allowed = (
            (module in _NUMPY_MODULES and name in _NUMPY_NAMES)
            or module == "numpy.dtypes"
            or (module, name) in _SAFE_GLOBALS
        )
        if not allowed:
            raise pickle.UnpicklingError(f"refusing to load global {module}.{name}")
        return super().find_class(module, name)


def _sparse_to_dense(obj: SparseStub) -> np.ndarray:
    st = obj.__dict__
    try:
        data = np.asarray(st["data"])
        indices = np.asarray(st["indices"])
        indptr = np.asarray(st["indptr"])
    except KeyError as exc:
        raise UnsupportedPickle(f"sparse matrix lacks {exc.args[0]!r}") from None
    shape = st.get("_shape", st.get("shape"))
    if shape is None:
        raise UnsupportedPickle("sparse matrix lacks its shape")
    shape = tuple(int(s) for s in shape)
    cls = scipy.sparse.csc_matrix if obj._sage_format == "csc" else scipy.sparse.csr_matrix
    return np.asarray(cls((data, indices, indptr), shape=shape).toarray())


def _chumpy_to_array(obj: ChumpyStub) -> np.ndarray:
    st = obj.state
    name = obj._sage_name
    if name == "Select" and "a" in st and "idxs" in st:
        base = to_plain(st["a"])
        out = np.asarray(base).ravel()[np.asarray(st["idxs"]).ravel()]
        shape = st.get("preferred_shape")
        return out.reshape(tuple(int(s) for s in shape)) if shape is not None else out
    if name == "Reshape" and "a" in st and "shape" in st:
        return np.asarray(to_plain(st["a"])).reshape(tuple(int(s) for s in st["shape"]))
    if name == "Transpose" and "a" in st:
        axes = st.get("axes")
        arr = np.asarray(to_plain(st["a"]))
        return arr.transpose(tuple(int(a) for a in axes)) if axes is not None else arr.T
    if "x" in st:
        return np.asarray(to_plain(st["x"]))
    raise UnsupportedPickle(f"cannot evaluate chumpy object {obj._sage_module}.{name} without chumpy")


def to_plain(value: Any) -> Any:
    """Recursively turn stubs into numpy arrays; dicts, lists and tuples are walked."""
    if isinstance(value, ChumpyStub):
        return _chumpy_to_array(value)
    if isinstance(value, SparseStub):
        return _sparse_to_dense(value)
    if scipy.sparse.issparse(value):
        return np.asarray(value.toarray())
    if isinstance(value, dict):
        return {k: to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(to_plain(v) for v in value)
    return value


def load_flame_pickle(path: str | Path) -> dict[str, Any]:
    """Load a FLAME-style pickle into a dict of plain values.

    Arrays (including chumpy and sparse values) come back as numpy arrays; strings stay strings.
    Raises ``pickle.UnpicklingError``, ``UnsupportedPickle`` or ``OSError`` on failure.
    """
    with open(path, "rb") as fh:
        raw = _FlameUnpickler(fh, encoding="latin1").load()
    if not isinstance(raw, dict):
        raise UnsupportedPickle(f"expected a dict at the top level, found {type(raw).__name__}")
    out: dict[str, Any] = {}
    for key, value in raw.items():
        value = to_plain(value)
        if isinstance(value, (bytes, str)):
            out[str(key)] = value.decode("latin1") if isinstance(value, bytes) else value
        else:
            try:
                out[str(key)] = np.asarray(value)
            except (ValueError, TypeError):
                out[str(key)] = value
    return out
