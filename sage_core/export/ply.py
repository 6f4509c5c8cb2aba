"""World-space 3DGS PLY in the INRIA layout (docs/formats.md §7.1), its reader, and ``.splat``.

:func:`encode_ply` is a pure function returning the file's bytes; :func:`decode_ply` inverts it
(reading by property name, any SH degree, any scalar property types); :func:`write_ply` and
:func:`read_ply` add atomic file IO and error messages that name the file.

Input conventions (world space, one row per Gaussian):
    means (N, 3); quats (N, 4) wxyz, any norm; scales (N, 2) for surfels or (N, 3), **linear**
    standard deviations; opacities (N,) **linear** in [0, 1] (written as logits); sh_dc (N, 3);
    sh_rest (N, K, 3) with K = (deg+1)² − 1, or None.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .._version import __version__
from ..errors import InputError
from ..workspace import atomic_write_bytes

SH_C0 = 0.28209479177387814
MIN_OPACITY = 1.0 / 255.0
SURFEL_THICKNESS = 1e-3  # third scale = SURFEL_THICKNESS · min(s0, s1)
_OPACITY_MAX = 1.0 - 1e-6  # keeps the logit finite for opacity 1

ArrayLike = Any  # numpy array or torch tensor


def _np(x: ArrayLike) -> np.ndarray:
    """Tensor or array -> float64 numpy (detached, on CPU)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _check_rows(a: np.ndarray, name: str, n: int, tail: tuple[int, ...]) -> None:
    if a.shape != (n, *tail):
        want = ", ".join(["N", *map(str, tail)])
        raise ValueError(f"{name}: expected shape ({want}) with N = {n}, got {a.shape}")


def sh_degree_from_rest(k: int) -> int:
    """SH degree from the number of non-DC coefficients K = (deg+1)² − 1."""
    deg = int(round(np.sqrt(k + 1))) - 1
    if (deg + 1) ** 2 - 1 != k:
        raise ValueError(f"{k} higher SH coefficients is not (deg+1)^2 - 1 for any degree")
    return deg


def pad_sh_rest(sh_rest: ArrayLike | None, n: int, degree: int) -> np.ndarray:
    """Higher SH coefficients zero-padded up to ``degree`` (0..3): (N, K, 3) or None -> (N, (deg+1)² − 1, 3).

    Padding with zeros leaves every colour unchanged; strict INRIA loaders expect degree 3 (45
    ``f_rest`` values). A degree below the input's raises ValueError (that would drop coefficients).
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    rest = np.zeros((n, 0, 3)) if sh_rest is None else _np(sh_rest)
    want = (degree + 1) ** 2 - 1
    if rest.shape[1] > want:
        raise ValueError(f"cannot pad {rest.shape[1]} higher SH coefficients down to degree {degree}")
    return np.concatenate([rest, np.zeros((n, want - rest.shape[1], 3))], axis=1)


def property_names(n_rest: int) -> list[str]:
    """Vertex property names in INRIA order for K = ``n_rest`` higher SH coefficients."""
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _surfel_scales(scales: np.ndarray) -> np.ndarray:
    """(N, 2) surfel std devs -> (N, 3) with a thin third axis ``1e-3·min(s0, s1)``."""
    eps = SURFEL_THICKNESS * np.minimum(scales[:, 0], scales[:, 1])
    return np.concatenate([scales, eps[:, None]], axis=1)


def _prepare(
    means: ArrayLike,
    quats: ArrayLike,
    scales: ArrayLike,
    opacities: ArrayLike,
    sh_dc: ArrayLike,
    sh_rest: ArrayLike | None,
) -> dict[str, np.ndarray]:
    """Validate inputs and return float64 arrays (scales always (N, 3), linear)."""
    mu = _np(means)
    if mu.ndim != 2 or mu.shape[1] != 3:
        raise ValueError(f"means: expected shape (N, 3), got {mu.shape}")
    n = mu.shape[0]
    q = _np(quats)
    _check_rows(q, "quats", n, (4,))
    s = _np(scales)
    if s.ndim != 2 or s.shape[0] != n or s.shape[1] not in (2, 3):
        raise ValueError(f"scales: expected shape (N, 2) or (N, 3) with N = {n}, got {s.shape}")
    if s.shape[1] == 2:
        s = _surfel_scales(s)
    o = _np(opacities)
    if o.ndim == 2 and o.shape[1] == 1:  # (N, 1) as many trainers store it
        o = o[:, 0]
    _check_rows(o, "opacities", n, ())
    dc = _np(sh_dc)
    if dc.ndim == 3 and dc.shape[1] == 1:  # (N, 1, 3) as many trainers store it
        dc = dc[:, 0]
    _check_rows(dc, "sh_dc", n, (3,))
    if sh_rest is None:
        rest = np.zeros((n, 0, 3))
    else:
        rest = _np(sh_rest)
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
            raise ValueError(f"sh_rest: expected shape (N, K, 3) with N = {n}, got {rest.shape}")
        if rest.shape[1] > 0:
            try:
                sh_degree_from_rest(rest.shape[1])
            except ValueError as e:
                raise ValueError(f"sh_rest: {e}") from None
    return {"means": mu, "quats": q, "scales": s, "opacities": o, "sh_dc": dc, "sh_rest": rest}


def _keep_mask(rows: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """Rows to keep: all values finite and linear opacity >= 1/255."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(rows).all(axis=1) & (opacity >= MIN_OPACITY)


def _header(names: Sequence[str], n: int, comments: Sequence[str]) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0"]
    for c in comments:
        if "\n" in c or "\r" in c:
            raise ValueError("PLY comments must be single lines")
        lines.append(f"comment {c}")
    lines.append(f"element vertex {n}")
    lines += [f"property float {p}" for p in names]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _default_comments(up_axis: str | None, comments: Sequence[str] | None) -> list[str]:
    out = [f"Generated by sage {__version__}"]
    if up_axis is not None:
        out.append(f"Vertical Axis: {up_axis}")
    return out + list(comments or [])


def encode_ply(
    means: ArrayLike,
    quats: ArrayLike,
    scales: ArrayLike,
    opacities: ArrayLike,
    sh_dc: ArrayLike,
    sh_rest: ArrayLike | None = None,
    comments: Sequence[str] | None = None,
    up_axis: str | None = "y",
) -> tuple[bytes, int]:
    """Encode Gaussians as a viewer PLY (binary little-endian, float32, INRIA property order).

    means: (N, 3) world positions. quats: (N, 4) wxyz (normalised on write).
    scales: (N, 2) surfel or (N, 3) linear std devs (written as logs; surfels get a third scale
    ``1e-3·min(s0, s1)`` on the normal axis, the 3rd column of R(q)).
    opacities: (N,) linear in [0, 1] (written as logits; values above 1 − 1e-6 are clamped).
    sh_dc: (N, 3) raw DC coefficients. sh_rest: (N, K, 3) or None; written channel-major.
    comments: extra ``comment`` lines after ``Generated by sage <version>`` and the up axis.
    up_axis: written as ``Vertical Axis: <up_axis>``; None omits that comment.

    Rows with a NaN/Inf attribute (including zero scales or quaternions) or opacity < 1/255 are
    dropped. Returns (file bytes, number of rows dropped).
    """
    a = _prepare(means, quats, scales, opacities, sh_dc, sh_rest)
    n, k = a["means"].shape[0], a["sh_rest"].shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        qn = a["quats"] / np.linalg.norm(a["quats"], axis=1, keepdims=True)
        o = np.minimum(a["opacities"], _OPACITY_MAX)
        logit = np.log(o) - np.log1p(-o)
        log_s = np.log(a["scales"])
    rest = a["sh_rest"].transpose(0, 2, 1).reshape(n, 3 * k)  # (N, 3, K): channel-major
    rows = np.concatenate(
        [a["means"], np.zeros((n, 3)), a["sh_dc"], rest, logit[:, None], log_s, qn], axis=1
    ).astype("<f4")
    keep = _keep_mask(rows, a["opacities"])
    rows = np.ascontiguousarray(rows[keep])
    names = property_names(k)
    header = _header(names, rows.shape[0], _default_comments(up_axis, comments))
    return header + rows.tobytes(), int(n - keep.sum())


def write_ply(
    path: str | Path,
    means: ArrayLike,
    quats: ArrayLike,
    scales: ArrayLike,
    opacities: ArrayLike,
    sh_dc: ArrayLike,
    sh_rest: ArrayLike | None = None,
    comments: Sequence[str] | None = None,
    up_axis: str | None = "y",
) -> int:
    """Encode with :func:`encode_ply` and write atomically. Returns the number of rows dropped."""
    data, dropped = encode_ply(means, quats, scales, opacities, sh_dc, sh_rest, comments, up_axis)
    atomic_write_bytes(path, data)
    return dropped


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


_Element = tuple[str, int, list[tuple[str, str]]]  # (name, count, [(property, dtype code)])


def _parse_header(data: bytes) -> tuple[str, list[_Element], list[str], int]:
    """-> (format, [(element, count, [(prop, dtype code)])], comments, byte offset of the body)."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY file (no 'ply' magic or no 'end_header')")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise ValueError("truncated PLY header")
    text = data[:end].decode("ascii", errors="replace").replace("\r", "")
    fmt = ""
    elements: list[_Element] = []
    comments: list[str] = []
    for line in text.split("\n")[1:]:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else ""
        elif parts[0] == "comment":
            comments.append(line[len("comment ") :].strip())
        elif parts[0] == "element":
            if len(parts) != 3:
                raise ValueError(f"malformed element line {line!r}")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError("property before any element")
            if parts[1] == "list":
                elements[-1][2].append((parts[-1], "list"))
            else:
                if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                    raise ValueError(f"unsupported property line {line!r}")
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    return fmt, elements, comments, nl + 1


def decode_ply_properties(data: bytes) -> tuple[dict[str, np.ndarray], list[str]]:
    """Raw vertex properties of a binary PLY, by name.

    Returns ({name: (N,) array in the file's type}, comment lines). Raises ValueError when the file
    is not a binary PLY with a scalar-only vertex element reachable from the start of the body.
    """
    fmt, elements, comments, offset = _parse_header(data)
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise ValueError(f"unsupported PLY format {fmt!r} (binary only)")
    order = "<" if fmt == "binary_little_endian" else ">"
    for name, count, props in elements:
        if any(t == "list" for _, t in props):
            raise ValueError(f"element {name!r} has list properties before the vertex data")
        dt = np.dtype([(p, order + t) for p, t in props])
        if name == "vertex":
            size = dt.itemsize * count
            if len(data) - offset < size:
                raise ValueError(
                    f"vertex data truncated: {len(data) - offset} bytes for {count} vertices "
                    f"of {dt.itemsize} bytes"
                )
            arr = np.frombuffer(data, dtype=dt, count=count, offset=offset)
            return {p: arr[p].copy() for p, _ in props}, comments
        offset += dt.itemsize * count
    raise ValueError("no 'vertex' element")


def decode_ply(data: bytes) -> dict[str, np.ndarray]:
    """Invert :func:`encode_ply`: activated Gaussian attributes from a 3DGS PLY.

    Returns float32 arrays: ``means`` (N, 3), ``quats`` (N, 4) wxyz normalised, ``scales`` (N, 3)
    linear (exp of the stored logs; 2-scale files give (N, 2)), ``opacities`` (N,) linear
    (sigmoid), ``sh_dc`` (N, 3), ``sh_rest`` (N, K, 3) (K = 0 without ``f_rest``). Properties are
    looked up by name, so any order and extra properties (e.g. ``binding_0``) are accepted.
    """
    props, _ = decode_ply_properties(data)

    def cols(names: Sequence[str]) -> np.ndarray:
        missing = [p for p in names if p not in props]
        if missing:
            raise ValueError(f"missing vertex properties {missing}")
        return np.stack([props[p].astype(np.float64) for p in names], axis=1)

    n_rest3 = 0
    while f"f_rest_{n_rest3}" in props:
        n_rest3 += 1
    if n_rest3 % 3:
        raise ValueError(f"{n_rest3} f_rest properties is not a multiple of 3")
    k = n_rest3 // 3
    if k:
        sh_degree_from_rest(k)
    n_scales = 3 if "scale_2" in props else 2
    means = cols(["x", "y", "z"])
    n = means.shape[0]
    q = cols([f"rot_{i}" for i in range(4)])
    with np.errstate(divide="ignore", invalid="ignore"):
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
    rest = cols([f"f_rest_{i}" for i in range(n_rest3)]) if k else np.zeros((n, 0))
    out = {
        "means": means,
        "quats": q,
        "scales": np.exp(cols([f"scale_{i}" for i in range(n_scales)])),
        "opacities": 1.0 / (1.0 + np.exp(-cols(["opacity"])[:, 0])),
        "sh_dc": cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
        "sh_rest": rest.reshape(n, 3, k).transpose(0, 2, 1),
    }
    return {key: np.ascontiguousarray(v, dtype=np.float32) for key, v in out.items()}


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY file with :func:`decode_ply`; a bad file raises InputError naming it."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read PLY file ({e.strerror or e})") from e
    try:
        return decode_ply(data)
    except ValueError as e:
        raise InputError(path, f"not a readable 3DGS PLY: {e}") from e


# --------------------------------------------------------------------------------------------
# .splat (32 bytes per splat, no SH)
# --------------------------------------------------------------------------------------------


SPLAT_DTYPE = np.dtype(
    [("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)]
)  # 32 bytes


def _morton_order(means: np.ndarray, bits: int = 10) -> np.ndarray:
    """Order of points along a 3D Morton (Z-order) curve over their bounding box. (N, 3) -> (N,)."""
    if means.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    lo, hi = means.min(0), means.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    grid = np.clip(((means - lo) / span * (2**bits - 1)).round(), 0, 2**bits - 1).astype(np.uint64)
    code = np.zeros(means.shape[0], dtype=np.uint64)
    for b in range(bits):
        for axis in range(3):
            bit = (grid[:, axis] >> np.uint64(b)) & np.uint64(1)
            code |= bit << np.uint64(3 * b + axis)
    return np.argsort(code, kind="stable")


def encode_splat(
    means: ArrayLike,
    quats: ArrayLike,
    scales: ArrayLike,
    opacities: ArrayLike,
    sh_dc: ArrayLike,
) -> tuple[bytes, int]:
    """Encode Gaussians in the 32-byte ``.splat`` layout (docs/formats.md §7.1), Morton-sorted.

    Per splat: float32 x y z, float32 linear scales (3; surfels get the same thin third axis as
    the PLY), uint8 R G B A with RGB = clip(0.5 + C0·f_dc) and A = opacity, uint8 quaternion wxyz
    ``q·128 + 128`` (normalised, clipped to 0..255). Inputs as in :func:`encode_ply` (no SH rest).
    Rows that :func:`encode_ply` would drop are dropped. Returns (bytes, number dropped).
    """
    a = _prepare(means, quats, scales, opacities, sh_dc, None)
    n = a["means"].shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        qn = a["quats"] / np.linalg.norm(a["quats"], axis=1, keepdims=True)
        log_s = np.log(a["scales"])
    check = np.concatenate([a["means"], a["sh_dc"], a["opacities"][:, None], log_s, qn], axis=1)
    keep = _keep_mask(check, a["opacities"])
    mu, s, q = a["means"][keep], a["scales"][keep], qn[keep]
    rgb = np.clip(0.5 + SH_C0 * a["sh_dc"][keep], 0.0, 1.0)
    alpha = np.clip(a["opacities"][keep], 0.0, 1.0)
    order = _morton_order(mu)
    rec = np.zeros(mu.shape[0], dtype=SPLAT_DTYPE)
    rec["pos"] = mu[order]
    rec["scale"] = s[order]
    rec["rgba"] = np.round(np.concatenate([rgb, alpha[:, None]], 1)[order] * 255.0)
    rec["rot"] = np.clip(np.round(q[order] * 128.0 + 128.0), 0, 255)
    return rec.tobytes(), int(n - keep.sum())
