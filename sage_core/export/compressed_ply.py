"""PlayCanvas' compressed PLY (``.compressed.ply``): 256-splat chunks of quantised Gaussians.

A binary little-endian PLY with three elements (the layout SuperSplat and splat-transform write
and read):

``chunk`` (one row per 256 splats, in file order), 18 floats:
    ``min_x min_y min_z max_x max_y max_z`` (centres), ``min_scale_{x,y,z} max_scale_{x,y,z}``
    (log scales), ``min_r min_g min_b max_r max_g max_b`` (colours ``0.5 + C0·f_dc``).
``vertex`` (one row per splat), four uint32 words:
    ``packed_position``: x, y, z as 11, 10, 11-bit unorms of the chunk's centre range (x in the top
    bits); ``packed_rotation``: the index (2 bits, of w x y z) of the quaternion's largest
    component, made positive, then the other three in order as 10-bit unorms of
    [−1/√2, 1/√2]; ``packed_scale``: log scales as 11, 10, 11-bit unorms of the chunk's range;
    ``packed_color``: r, g, b as 8-bit unorms of the chunk's colour range and the linear opacity
    as 8 bits (r in the top byte, opacity in the low byte).
``sh`` (one row per splat, only with SH degree > 0 and some non-zero coefficient; the byte
    encoding cannot represent 0 exactly, so all-zero padding is left out): ``f_rest_0 …`` as
    uchar, ``floor((f/8 + 0.5)·256)`` clamped to 0..255, in the INRIA channel-major order.

Splats are Morton-sorted before chunking (tight chunk ranges). Rows that :func:`encode_ply` would
drop (non-finite, opacity < 1/255) are dropped.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .ply import (
    SH_C0,
    ArrayLike,
    _default_comments,
    _keep_mask,
    _morton_order,
    _prepare,
    _parse_header,
)

CHUNK = 256
CHUNK_PROPERTIES: tuple[str, ...] = (
    "min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
    "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
    "min_r", "min_g", "min_b", "max_r", "max_g", "max_b",
)  # fmt: skip
VERTEX_PROPERTIES: tuple[str, ...] = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
LOG_SCALE_RANGE = (-20.0, 20.0)
_ROT_RANGE = np.sqrt(0.5)  # the three smallest components of a unit quaternion lie in ±1/√2
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])  # components kept beside the largest


def _unorm(v: np.ndarray, lo: np.ndarray, hi: np.ndarray, bits: int) -> np.ndarray:
    """Quantise v to ``bits``-bit unorms of [lo, hi] (a zero range gives 0). Arrays broadcast."""
    top = (1 << bits) - 1
    span = hi - lo
    t = np.where(span > 0, (v - lo) / np.where(span > 0, span, 1.0), 0.0)
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _chunk_ranges(x: np.ndarray, n_chunks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk min and max of x (N, C) -> (n_chunks, C) each (the last chunk may be short)."""
    n, c = x.shape
    pad = n_chunks * CHUNK - n
    lo = np.concatenate([x, np.full((pad, c), np.inf)]).reshape(n_chunks, CHUNK, c).min(1)
    hi = np.concatenate([x, np.full((pad, c), -np.inf)]).reshape(n_chunks, CHUNK, c).max(1)
    return lo, hi


def _pack_rotation(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit wxyz -> (N,) uint32 'largest three' words."""
    largest = np.abs(q).argmax(1)
    q = np.where(q[np.arange(q.shape[0]), largest][:, None] < 0, -q, q)
    others = np.take_along_axis(q, _OTHERS[largest], axis=1)
    u = _unorm(others, -_ROT_RANGE, _ROT_RANGE, 10)
    return (largest.astype(np.uint32) << 30) | (u[:, 0] << 20) | (u[:, 1] << 10) | u[:, 2]


def encode_compressed_ply(
    means: ArrayLike,
    quats: ArrayLike,
    scales: ArrayLike,
    opacities: ArrayLike,
    sh_dc: ArrayLike,
    sh_rest: ArrayLike | None = None,
    comments: Sequence[str] | None = None,
    up_axis: str | None = "y",
) -> tuple[bytes, int]:
    """Encode Gaussians as a PlayCanvas compressed PLY (module doc). Inputs as :func:`encode_ply`
    (world space, linear scales (N, 2) or (N, 3), linear opacities). Returns (bytes, rows dropped)."""
    a = _prepare(means, quats, scales, opacities, sh_dc, sh_rest)
    n_in, k = a["means"].shape[0], a["sh_rest"].shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        qn = a["quats"] / np.linalg.norm(a["quats"], axis=1, keepdims=True)
        log_s = np.log(a["scales"])
    check = np.concatenate([a["means"], a["sh_dc"], a["opacities"][:, None], log_s, qn], axis=1)
    keep = _keep_mask(check, a["opacities"])
    if k:
        keep &= np.isfinite(a["sh_rest"]).all(axis=(1, 2))
    order = _morton_order(a["means"][keep])
    mu = a["means"][keep][order]
    q = qn[keep][order]
    ls = np.clip(log_s[keep][order], *LOG_SCALE_RANGE)
    rgb = 0.5 + SH_C0 * a["sh_dc"][keep][order]
    alpha = np.clip(a["opacities"][keep][order], 0.0, 1.0)
    rest = a["sh_rest"][keep][order].transpose(0, 2, 1).reshape(order.shape[0], 3 * k)  # channel-major
    if not rest.any():  # all-zero SH (e.g. zero padding) is left out: a byte cannot hold 0 exactly
        k, rest = 0, rest[:, :0]
    n = mu.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    chunk_of = np.arange(n) // CHUNK
    lo_p, hi_p = _chunk_ranges(mu, n_chunks)
    lo_s, hi_s = _chunk_ranges(ls, n_chunks)
    lo_c, hi_c = _chunk_ranges(rgb, n_chunks)
    chunks = np.concatenate([lo_p, hi_p, lo_s, hi_s, lo_c, hi_c], axis=1).astype("<f4")

    def pack111011(v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        lo, hi = lo[chunk_of], hi[chunk_of]
        x = _unorm(v[:, 0], lo[:, 0], hi[:, 0], 11)
        y = _unorm(v[:, 1], lo[:, 1], hi[:, 1], 10)
        z = _unorm(v[:, 2], lo[:, 2], hi[:, 2], 11)
        return (x << 21) | (y << 11) | z

    c8 = _unorm(rgb, lo_c[chunk_of], hi_c[chunk_of], 8)
    a8 = np.clip(np.floor(alpha * 255.0 + 0.5), 0, 255).astype(np.uint32)
    vertex = np.stack(
        [pack111011(mu, lo_p, hi_p), _pack_rotation(q), pack111011(ls, lo_s, hi_s),
         (c8[:, 0] << 24) | (c8[:, 1] << 16) | (c8[:, 2] << 8) | a8],
        axis=1,
    ).astype("<u4")  # fmt: skip
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in _default_comments(up_axis, comments)]
    lines.append(f"element chunk {n_chunks}")
    lines += [f"property float {p}" for p in CHUNK_PROPERTIES]
    lines.append(f"element vertex {n}")
    lines += [f"property uint {p}" for p in VERTEX_PROPERTIES]
    body = chunks.tobytes() + vertex.tobytes()
    if k:
        lines.append(f"element sh {n}")
        lines += [f"property uchar f_rest_{i}" for i in range(3 * k)]
        sh = np.clip(np.floor((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)
        body += sh.tobytes()
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    return header + body, int(n_in - n)


def is_compressed_ply(data: bytes) -> bool:
    """True when ``data`` is a PLY whose vertex element is the packed (compressed) layout."""
    try:
        _, elements, _, _ = _parse_header(data)
    except ValueError:
        return False
    return any(name == "vertex" and any(p == "packed_position" for p, _ in props) for name, _, props in elements)


def decode_compressed_ply(data: bytes) -> dict[str, np.ndarray]:
    """Dequantise a compressed PLY to the arrays of :func:`decode_ply` (float32): ``means`` (N, 3),
    ``quats`` (N, 4) wxyz, ``scales`` (N, 3) linear, ``opacities`` (N,), ``sh_dc`` (N, 3),
    ``sh_rest`` (N, K, 3). Raises ValueError for another layout."""
    fmt, elements, _, offset = _parse_header(data)
    if fmt != "binary_little_endian":
        raise ValueError(f"compressed PLY must be binary_little_endian, got {fmt!r}")
    arrays: dict[str, np.ndarray] = {}
    for name, count, props in elements:
        dt = np.dtype([(p, "<" + t) for p, t in props])
        if len(data) - offset < dt.itemsize * count:
            raise ValueError(f"element {name!r} truncated")
        arrays[name] = np.frombuffer(data, dtype=dt, count=count, offset=offset)
        offset += dt.itemsize * count
    if "chunk" not in arrays or "vertex" not in arrays:
        raise ValueError("not a compressed PLY (no 'chunk' and 'vertex' elements)")
    ch, v = arrays["chunk"], arrays["vertex"]
    n = v.shape[0]
    if ch.shape[0] * CHUNK < n:
        raise ValueError(f"{ch.shape[0]} chunks for {n} splats")
    ci = np.arange(n) // CHUNK

    def col(name: str) -> np.ndarray:
        return ch[name].astype(np.float64)[ci]

    def unorm(word: np.ndarray, shift: int, bits: int) -> np.ndarray:
        return ((word.astype(np.uint64) >> np.uint64(shift)) & np.uint64((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)

    def lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
        return lo + (hi - lo) * t

    pp, pr, ps, pc = (v[p] for p in VERTEX_PROPERTIES)
    means = np.stack([lerp(col(f"min_{a}"), col(f"max_{a}"), unorm(pp, s, b)) for a, s, b in (("x", 21, 11), ("y", 11, 10), ("z", 0, 11))], 1)
    log_s = np.stack([lerp(col(f"min_scale_{a}"), col(f"max_scale_{a}"), unorm(ps, s, b)) for a, s, b in (("x", 21, 11), ("y", 11, 10), ("z", 0, 11))], 1)
    small = np.stack([(unorm(pr, s, 10) - 0.5) * 2.0 * _ROT_RANGE for s in (20, 10, 0)], 1)
    big = np.sqrt(np.clip(1.0 - (small**2).sum(1), 0.0, None))
    largest = (pr >> 30).astype(np.int64)
    quats = np.zeros((n, 4))
    for i in range(4):
        rows = largest == i
        others = [j for j in range(4) if j != i]
        quats[rows, i] = big[rows]
        quats[np.ix_(rows, others)] = small[rows]
    rgb_t = np.stack([unorm(pc, s, 8) for s in (24, 16, 8)], 1)
    if "min_r" in ch.dtype.names:
        rgb = np.stack([lerp(col(f"min_{c}"), col(f"max_{c}"), rgb_t[:, i]) for i, c in enumerate("rgb")], 1)
    else:
        rgb = rgb_t
    out = {
        "means": means,
        "quats": quats,
        "scales": np.exp(log_s),
        "opacities": unorm(pc, 0, 8),
        "sh_dc": (rgb - 0.5) / SH_C0,
    }
    if "sh" in arrays:
        sh = arrays["sh"]
        names = list(sh.dtype.names or ())
        k3 = len(names)
        raw = np.stack([sh[f"f_rest_{i}"] for i in range(k3)], 1).astype(np.float64)
        nrm = np.where(raw == 0, 0.0, np.where(raw == 255, 1.0, (raw + 0.5) / 256.0))
        out["sh_rest"] = ((nrm - 0.5) * 8.0).reshape(n, 3, k3 // 3).transpose(0, 2, 1)
    else:
        out["sh_rest"] = np.zeros((n, 0, 3))
    return {key: np.ascontiguousarray(val, dtype=np.float32) for key, val in out.items()}
