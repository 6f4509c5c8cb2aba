"""Deterministic, atomic file writers (no timestamps inside files: same input ⇒ same bytes)."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ...atomic import atomic_write_bytes

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` atomically (temp file in the same folder + rename)."""
    return atomic_write_bytes(path, data)


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An uncompressed ``.npz`` (as ``np.savez`` would write) with fixed zip timestamps."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for key, val in arrays.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_DATE)
            info.external_attr = 0o600 << 16
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(val), allow_pickle=False)
    return buf.getvalue()


def write_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> Path:
    """Write arrays as a deterministic ``.npz``, atomically."""
    return write_bytes(path, npz_bytes(arrays))


def normalize_zip(path: str | Path, compress: bool = True) -> Path:
    """Rewrite a zip (e.g. an npz from ``np.savez``) with fixed timestamps, keeping member order.

    compress: deflate every member (``np.load`` reads compressed npz files transparently).
    """
    path = Path(path)
    buf = io.BytesIO()
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(buf, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            new = zipfile.ZipInfo(info.filename, date_time=_ZIP_DATE)
            new.compress_type = zipfile.ZIP_DEFLATED if compress else info.compress_type
            new.external_attr = 0o600 << 16
            dst.writestr(new, data)
    return write_bytes(path, buf.getvalue())


def write_json(path: str | Path, obj: Any) -> Path:
    """Write JSON (indent 2, trailing newline) atomically."""
    return write_bytes(path, (json.dumps(obj, indent=2) + "\n").encode("utf-8"))


def ply_bytes(vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> bytes:
    """Binary little-endian PLY of a triangle mesh. vertices: (V, 3) float32, faces: (F, 3) int32."""
    v = np.ascontiguousarray(vertices, dtype="<f4")
    f = np.asarray(faces, dtype="<i4")
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header.append(f"comment {comment}")
    header += [f"element vertex {len(v)}", "property float x", "property float y", "property float z",
               f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    rec = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"] = 3
    rec["i"] = f
    return ("\n".join(header) + "\n").encode("ascii") + v.tobytes() + rec.tobytes()


def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> Path:
    """Write a triangle mesh as binary PLY, atomically."""
    return write_bytes(path, ply_bytes(vertices, faces, comment))
