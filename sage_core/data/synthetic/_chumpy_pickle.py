"""Write a FLAME-layout pickle the way the official files look: chumpy ``Ch`` arrays and an old-style
``scipy.sparse.csc.csc_matrix`` joint regressor, protocol 2, readable with ``encoding="latin1"``.

Neither chumpy nor a real sparse matrix is needed: stand-in classes carrying the official module
and class names are pickled while temporary module entries make them findable by the pickler.
"""

from __future__ import annotations

import io
import pickle
import sys
import threading
import types
from typing import Any

import numpy as np
import scipy.sparse

_LOCK = threading.Lock()


class Ch:
    """Stand-in for ``chumpy.ch.Ch``; its pickled state is ``{"x": ndarray}``."""

    def __init__(self, x: np.ndarray) -> None:
        self.x = np.asarray(x)

    def __getstate__(self) -> dict[str, Any]:
        return {"x": self.x}


Ch.__module__ = "chumpy.ch"
Ch.__qualname__ = "Ch"


class csc_matrix:  # noqa: N801 - the pickled class name must match scipy's
    """Stand-in for the pre-1.8 ``scipy.sparse.csc.csc_matrix`` (state: data, indices, indptr, _shape)."""

    def __init__(self, dense: np.ndarray) -> None:
        m = scipy.sparse.csc_matrix(np.asarray(dense))
        self._shape = tuple(int(s) for s in m.shape)
        self.data = np.asarray(m.data)
        self.indices = np.asarray(m.indices, dtype=np.int32)
        self.indptr = np.asarray(m.indptr, dtype=np.int32)
        self.maxprint = 50

    def __getstate__(self) -> dict[str, Any]:
        return {"_shape": self._shape, "maxprint": self.maxprint, "indices": self.indices,
                "indptr": self.indptr, "data": self.data}


csc_matrix.__module__ = "scipy.sparse.csc"
csc_matrix.__qualname__ = "csc_matrix"


def dumps_flame_pickle(d: dict[str, Any]) -> bytes:
    """Pickle a FLAME dict (values may be :class:`Ch`, :class:`csc_matrix`, arrays, str) -> bytes."""
    names = ("chumpy", "chumpy.ch", "scipy.sparse.csc")
    with _LOCK:
        saved = {n: sys.modules.get(n) for n in names}
        try:
            pkg = types.ModuleType("chumpy")
            pkg.__path__ = []  # type: ignore[attr-defined]
            mod = types.ModuleType("chumpy.ch")
            mod.Ch = Ch  # type: ignore[attr-defined]
            pkg.ch = mod  # type: ignore[attr-defined]
            sp = types.ModuleType("scipy.sparse.csc")
            sp.csc_matrix = csc_matrix  # type: ignore[attr-defined]
            sys.modules["chumpy"] = pkg
            sys.modules["chumpy.ch"] = mod
            sys.modules["scipy.sparse.csc"] = sp
            buf = io.BytesIO()
            pickle.Pickler(buf, protocol=2).dump(d)
            return buf.getvalue()
        finally:
            for n, m in saved.items():
                if m is None:
                    sys.modules.pop(n, None)
                else:
                    sys.modules[n] = m
