"""FLAME vertex/face regions (docs/formats.md §5): official masks, derived sets, face clusters."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from ..errors import InputError, require_file
from ._unpickle import read_flame_pickle

REGIONS_FORMAT = "sage-regions-v1"


def load_masks(path: str | Path) -> dict[str, np.ndarray]:
    """Read ``FLAME_masks.pkl``: a pickled dict name -> vertex ids (latin1, Python 2 era).

    Returns name -> (n,) int64 sorted unique ids. Raises InputError(path, ...) if the file is
    missing, unreadable, not a dict, or a value is not a 1-D array of non-negative integers.
    """
    path = Path(path)
    require_file(path, "FLAME mask file")
    raw = read_flame_pickle(path, "mask pickle", "the mask file")
    out: dict[str, np.ndarray] = {}
    for name, ids in raw.items():
        arr = np.asarray(ids)
        if arr.ndim != 1 or not (np.issubdtype(arr.dtype, np.integer) or arr.size == 0):
            raise InputError(path, f"mask '{name}' is not a 1-D integer array (shape {arr.shape}, dtype {arr.dtype})")
        if arr.size and arr.min() < 0:
            raise InputError(path, f"mask '{name}' holds negative vertex ids")
        out[name] = np.unique(arr.astype(np.int64))
    return out


def _union(sets: Iterable[np.ndarray | None]) -> np.ndarray | None:
    present = [s for s in sets if s is not None]
    if not present:
        return None
    return np.unique(np.concatenate(present)).astype(np.int64)


class Regions:
    """Named vertex sets and face sets of one mesh topology.

    Built from the official masks plus the model's appended ``vertex_groups``. Derived sets (when
    their inputs exist): ``all``; ``hair = scalp \\ (face ∪ neck)``; ``ears``; ``left_eye`` /
    ``right_eye`` (eye region ∪ eyeball); ``eyeballs``; ``irises`` and ``sclerae`` (if iris masks
    exist); ``teeth`` (teeth_upper ∪ teeth_lower); ``mouth_interior`` (union of every ``mouth_*``
    mask or group, a ``mouth_interior`` mask included);
    ``skin = all \\ (eyeballs ∪ hair ∪ lips_tight-or-lips ∪ boundary ∪ teeth ∪ mouth_interior)``.
    A face belongs to a region iff all 3 of its vertices do. Regions that cannot be derived are
    absent (:meth:`has`).
    """

    def __init__(
        self,
        masks: Mapping[str, np.ndarray],
        faces: np.ndarray,
        n_vertices: int,
        vertex_groups: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        faces = np.asarray(faces, dtype=np.int64)
        self.n_vertices = int(n_vertices)
        self.n_faces = int(faces.shape[0])
        vs: dict[str, np.ndarray] = {}
        for name, ids in list(masks.items()) + list((vertex_groups or {}).items()):
            ids = np.unique(np.asarray(ids, dtype=np.int64))
            vs[name] = ids[(ids >= 0) & (ids < self.n_vertices)]
        self._vertex_sets = self._derive(vs)
        in_face = {}
        for name, ids in self._vertex_sets.items():
            mask = np.zeros(self.n_vertices, dtype=bool)
            mask[ids] = True
            inside = mask[faces].all(axis=1) if faces.size else np.zeros(0, dtype=bool)
            in_face[name] = np.nonzero(inside)[0].astype(np.int64)
        self._face_sets = in_face

    def _derive(self, vs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        g = vs.get
        out = dict(vs)
        out["all"] = np.arange(self.n_vertices, dtype=np.int64)
        if "scalp" in vs:
            keep = _union([g("face"), g("neck")])
            out["hair"] = vs["scalp"] if keep is None else np.setdiff1d(vs["scalp"], keep)
        derived = {
            "ears": _union([g("right_ear"), g("left_ear")]),
            "eyeballs": _union([g("left_eyeball"), g("right_eyeball")]),
            "irises": _union([g("left_iris"), g("right_iris")]),
            "teeth": _union([g("teeth_upper"), g("teeth_lower")]),
        }
        mouth = _union([v for k, v in vs.items() if k.startswith("mouth_")])
        if mouth is not None:
            out["mouth_interior"] = mouth
        for side in ("left", "right"):
            if f"{side}_eye_region" in vs or f"{side}_eyeball" in vs:
                derived[f"{side}_eye"] = _union([g(f"{side}_eye_region"), g(f"{side}_eyeball")])
        for name, ids in derived.items():
            if ids is not None and name not in out:
                out[name] = ids
        if "eyeballs" in out and "irises" in out and "sclerae" not in out:
            out["sclerae"] = np.setdiff1d(out["eyeballs"], out["irises"])
        if "teeth" in out:
            for half in ("left_half", "right_half"):
                if half in out:
                    out[half] = np.union1d(out[half], out["teeth"])
        lips = g("lips_tight", g("lips"))
        excluded = _union([out.get("eyeballs"), out.get("hair"), lips, g("boundary"), out.get("teeth"),
                           out.get("mouth_interior")])
        out["skin"] = out["all"] if excluded is None else np.setdiff1d(out["all"], excluded)
        return out

    @property
    def names(self) -> list[str]:
        """Sorted names of the regions present."""
        return sorted(self._vertex_sets)

    def has(self, name: str) -> bool:
        return name in self._vertex_sets

    def _get(self, table: dict[str, np.ndarray], name: str) -> np.ndarray:
        if name not in table:
            raise KeyError(f"region '{name}' is not available (have: {', '.join(self.names)})")
        return table[name]

    def vertex_ids(self, name: str) -> np.ndarray:
        """(n,) int64 sorted vertex ids of a region."""
        return self._get(self._vertex_sets, name)

    def face_ids(self, name: str) -> np.ndarray:
        """(m,) int64 sorted ids of the faces whose 3 vertices all lie in the region."""
        return self._get(self._face_sets, name)

    def vertex_mask(self, name: str) -> np.ndarray:
        """(V,) bool."""
        mask = np.zeros(self.n_vertices, dtype=bool)
        mask[self.vertex_ids(name)] = True
        return mask

    def face_mask(self, name: str) -> np.ndarray:
        """(F,) bool."""
        mask = np.zeros(self.n_faces, dtype=bool)
        mask[self.face_ids(name)] = True
        return mask

    def face_labels(self, names: Iterable[str]) -> np.ndarray:
        """(F,) int64 cluster ids: 1 = in none of ``names``, then 2, 3, … in list order.

        0 is reserved for background (pixels that hit no face). A face in several listed regions
        takes the first one's label. Unknown names raise KeyError.
        """
        labels = np.ones(self.n_faces, dtype=np.int64)
        assigned = np.zeros(self.n_faces, dtype=bool)
        for k, name in enumerate(names):
            m = self.face_mask(name) & ~assigned
            labels[m] = k + 2
            assigned |= m
        return labels

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe plain data (ints and lists only)."""
        return {
            "format": REGIONS_FORMAT,
            "n_vertices": self.n_vertices,
            "n_faces": self.n_faces,
            "vertex_sets": {k: [int(i) for i in v] for k, v in sorted(self._vertex_sets.items())},
            "face_sets": {k: [int(i) for i in v] for k, v in sorted(self._face_sets.items())},
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Regions:
        """Inverse of :meth:`to_dict`; raises ValueError on malformed data."""
        if d.get("format") != REGIONS_FORMAT:
            raise ValueError(f"regions data format is {d.get('format')!r}, expected {REGIONS_FORMAT!r}")
        obj = cls.__new__(cls)
        obj.n_vertices = int(d["n_vertices"])
        obj.n_faces = int(d["n_faces"])
        obj._vertex_sets = {k: np.asarray(v, dtype=np.int64).reshape(-1) for k, v in d["vertex_sets"].items()}
        obj._face_sets = {k: np.asarray(v, dtype=np.int64).reshape(-1) for k, v in d["face_sets"].items()}
        if set(obj._vertex_sets) != set(obj._face_sets):
            raise ValueError("regions data: vertex_sets and face_sets name different regions")
        for k, v in obj._vertex_sets.items():
            if v.size and (v.min() < 0 or v.max() >= obj.n_vertices):
                raise ValueError(f"regions data: region '{k}' has vertex ids out of range")
        for k, v in obj._face_sets.items():
            if v.size and (v.min() < 0 or v.max() >= obj.n_faces):
                raise ValueError(f"regions data: region '{k}' has face ids out of range")
        return obj
