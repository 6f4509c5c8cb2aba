"""FLAME parameter files: VHAP per-timestep npz, GaussianAvatars T-leading npz, stacked workspace npz.

All arrays are float32 numpy with the timestep axis first (docs/formats.md §1.3, §7.2):

- VHAP ``flame_param/{ti:05d}.npz`` (one timestep): ``translation, rotation, neck_pose, jaw_pose
  (1,3)``, ``eyes_pose (1,6)``, ``expr (1,E)``, ``shape (S,)``, optional ``static_offset (1,V,3)``
  and ``dynamic_offset (1,V,3)``.
- GaussianAvatars ``flame_param.npz`` / motion files: the same keys with T rows and
  ``dynamic_offset (T,V,3)``; a motion file may lack ``shape`` and ``static_offset``.
- The workspace's stacked file adds ``timesteps (T,)`` int64.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from ..atomic import atomic_writer
from ..errors import InputError
from ..npz import read_npz, shape_str

if TYPE_CHECKING:
    import torch

POSE_KEYS: tuple[str, ...] = ("rotation", "neck_pose", "jaw_pose", "translation")
"""Per-timestep (T, 3) keys."""

DYNAMIC_KEYS: tuple[str, ...] = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
"""Keys that hold one row per timestep (besides ``dynamic_offset``)."""

STACKED_FORMAT = "sage-flame-params-v1"


@dataclass
class FlameParams:
    """FLAME parameters for T timesteps of one subject.

    Attributes:
        shape: (S,) identity coefficients; (0,) when the source file carries none (motion files).
        expr: (T, E) expression coefficients.
        rotation, neck_pose, jaw_pose, translation: (T, 3) axis-angle (radians) / metres.
        eyes_pose: (T, 6) two eye rotations, ``[:3]`` joint 3 and ``[3:]`` joint 4.
        static_offset: (V, 3) canonical per-vertex offsets, or None.
        dynamic_offset: (T, V, 3) per-timestep offsets, or None.
        timesteps: (T,) int64 dataset ``timestep_index`` of each row.
    """

    shape: np.ndarray
    expr: np.ndarray
    rotation: np.ndarray
    neck_pose: np.ndarray
    jaw_pose: np.ndarray
    eyes_pose: np.ndarray
    translation: np.ndarray
    static_offset: np.ndarray | None
    dynamic_offset: np.ndarray | None
    timesteps: np.ndarray

    @property
    def n_timesteps(self) -> int:
        return int(self.expr.shape[0])

    @property
    def n_expr(self) -> int:
        return int(self.expr.shape[1])

    @property
    def n_shape(self) -> int:
        return int(self.shape.shape[0])

    @property
    def n_offset_vertices(self) -> int | None:
        """Rows of the offsets (V), or None when the parameters carry no offsets."""
        if self.static_offset is not None:
            return int(self.static_offset.shape[0])
        if self.dynamic_offset is not None:
            return int(self.dynamic_offset.shape[1])
        return None

    def row_of(self, timestep: int) -> int:
        """The row holding dataset timestep ``timestep``; KeyError if absent."""
        hits = np.nonzero(self.timesteps == int(timestep))[0]
        if hits.size == 0:
            raise KeyError(f"timestep {timestep} is not in these FLAME parameters")
        return int(hits[0])

    def select(self, rows: Sequence[int] | np.ndarray) -> FlameParams:
        """A copy holding only ``rows`` (row positions, not timestep values), in that order."""
        idx = np.asarray(rows, dtype=np.int64).reshape(-1)
        return FlameParams(
            shape=self.shape.copy(),
            expr=self.expr[idx].copy(),
            rotation=self.rotation[idx].copy(),
            neck_pose=self.neck_pose[idx].copy(),
            jaw_pose=self.jaw_pose[idx].copy(),
            eyes_pose=self.eyes_pose[idx].copy(),
            translation=self.translation[idx].copy(),
            static_offset=None if self.static_offset is None else self.static_offset.copy(),
            dynamic_offset=None if self.dynamic_offset is None else self.dynamic_offset[idx].copy(),
            timesteps=self.timesteps[idx].copy(),
        )

    def select_timesteps(self, timesteps: Sequence[int] | np.ndarray) -> FlameParams:
        """A copy holding the rows of the given dataset timesteps, in that order (KeyError if absent)."""
        return self.select([self.row_of(int(t)) for t in np.asarray(timesteps).reshape(-1)])

    def pad_offsets(self, n_vertices: int) -> FlameParams:
        """A copy whose offsets have ``n_vertices`` rows, zero-padded at the end.

        A 5023-row FLAME offset becomes 5143 rows for the teeth-extended model (the teeth vertices are
        appended after the FLAME ones, docs/formats.md §4). Raises ValueError when there are more rows.
        """
        def pad(arr: np.ndarray, axis: int) -> np.ndarray:
            rows = arr.shape[axis]
            if rows > n_vertices:
                raise ValueError(f"offsets have {rows} rows, more than {n_vertices}")
            if rows == n_vertices:
                return arr.copy()
            widths = [(0, 0)] * arr.ndim
            widths[axis] = (0, n_vertices - rows)
            return np.pad(arr, widths)

        return replace(
            self,
            static_offset=None if self.static_offset is None else pad(self.static_offset, 0),
            dynamic_offset=None if self.dynamic_offset is None else pad(self.dynamic_offset, 1),
        )

    def trim_offsets(self, n_vertices: int) -> FlameParams:
        """A copy whose offsets keep only their first ``n_vertices`` rows (drops appended teeth rows)."""
        return replace(
            self,
            static_offset=None if self.static_offset is None else self.static_offset[:n_vertices].copy(),
            dynamic_offset=None if self.dynamic_offset is None else self.dynamic_offset[:, :n_vertices].copy(),
        )

    def to_torch(self, device: str | torch.device = "cpu", dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
        """Tensors named as the arguments of ``FlameModel.forward``.

        Returns ``shape (S,)``, ``expr (T,E)``, ``rotation``,
        ``neck_pose``, ``jaw_pose``, ``translation (T,3)``, ``eyes_pose (T,6)``, and when present
        ``static_offset (V,3)`` and ``dynamic_offset (T,V,3)``. ``dtype`` defaults to float32.
        """
        import torch

        dt = torch.float32 if dtype is None else dtype

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a), device=device).to(dt)

        out: dict[str, torch.Tensor] = {
            "shape": t(self.shape),
            "expr": t(self.expr),
            "rotation": t(self.rotation),
            "neck_pose": t(self.neck_pose),
            "jaw_pose": t(self.jaw_pose),
            "eyes_pose": t(self.eyes_pose),
            "translation": t(self.translation),
        }
        if self.static_offset is not None:
            out["static_offset"] = t(self.static_offset)
        if self.dynamic_offset is not None:
            out["dynamic_offset"] = t(self.dynamic_offset)
        return out


EXPR_DROP_TOL = 1e-6
"""Largest |coefficient| beyond a model's expression count that may be dropped without a word."""


def expr_overflow(params: FlameParams, n_expr: int) -> str | None:
    """Why ``params.expr`` does not fit a FLAME model with ``n_expr`` expression components, or None.

    The model zero-pads fewer coefficients and cuts extra ones. Extra columns that are all zero
    (|c| <= :data:`EXPR_DROP_TOL`, e.g. a tracker's fixed-width array) lose nothing and fit;
    extra columns with non-zero values would be dropped silently, changing the expressions, so
    they are reported (the caller raises InputError naming its file). params.expr: (T, E).
    """
    e = params.expr
    if e.ndim != 2 or e.shape[1] <= n_expr:
        return None
    extra = np.abs(np.asarray(e[:, n_expr:], dtype=np.float64))
    if extra.size == 0 or float(extra.max()) <= EXPR_DROP_TOL:
        return None
    cols = np.nonzero(extra.max(axis=0) > EXPR_DROP_TOL)[0] + n_expr
    return (
        f"'expr' has {e.shape[1]} coefficients but the FLAME model has {n_expr} expression components; "
        f"coefficients {int(cols[0])}..{int(cols[-1])} are non-zero (largest |value| {float(extra.max()):.4g}) and the "
        f"model would ignore them: use a FLAME model with at least {int(cols[-1]) + 1} expression components, or zero them"
    )


def _numeric(path: Path, key: str, value: np.ndarray) -> np.ndarray:
    if not (np.issubdtype(value.dtype, np.floating) or np.issubdtype(value.dtype, np.integer)):
        raise InputError(path, f"key '{key}' has dtype {value.dtype}, expected float32")
    arr = value.astype(np.float32)
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise InputError(path, f"key '{key}' contains {bad} NaN or Inf value(s)")
    return arr


def _rows(path: Path, key: str, arr: np.ndarray, width: int | None, T: int | None) -> np.ndarray:
    """Check a (T, width) array; width None = any positive width."""
    exp_w = "E" if width is None else str(width)
    exp_t = "T" if T is None else str(T)
    ok = arr.ndim == 2 and (width is None or arr.shape[1] == width) and arr.shape[1] > 0
    ok = ok and (T is None or arr.shape[0] == T) and arr.shape[0] > 0
    if not ok:
        raise InputError(path, f"key '{key}' has shape {shape_str(arr.shape)}, expected ({exp_t},{exp_w})")
    return arr


def params_from_arrays(path: str | Path, arrays: dict[str, np.ndarray], timesteps: np.ndarray | None = None,
                       require_shape: bool = True) -> FlameParams:
    """Validate raw npz arrays and build :class:`FlameParams` (see :func:`load_param_npz`).

    path: only used to name the source in errors. timesteps: (T,) override; otherwise the
    ``timesteps`` array when present, else ``arange(T)``.
    """
    path = Path(path)
    required = list(DYNAMIC_KEYS) + (["shape"] if require_shape else [])
    missing = [k for k in required if k not in arrays]
    if missing:
        raise InputError(path, "FLAME parameter file lacks key(s) " + ", ".join(f"'{k}'" for k in missing))
    vals = {k: _numeric(path, k, np.asarray(arrays[k])) for k in DYNAMIC_KEYS}
    expr = _rows(path, "expr", vals["expr"], None, None)
    T = expr.shape[0]
    for key in POSE_KEYS:
        _rows(path, key, vals[key], 3, T)
    _rows(path, "eyes_pose", vals["eyes_pose"], 6, T)

    if "shape" in arrays:
        shape = _numeric(path, "shape", np.asarray(arrays["shape"]))
        raw_shape = shape.shape
        if shape.ndim == 2 and shape.shape[0] == 1:
            shape = shape[0]
        if shape.ndim != 1 or shape.shape[0] == 0:
            raise InputError(path, f"key 'shape' has shape {shape_str(raw_shape)}, expected (S,) e.g. (300,)")
    else:
        shape = np.zeros((0,), np.float32)

    static = None
    if "static_offset" in arrays:
        static = _numeric(path, "static_offset", np.asarray(arrays["static_offset"]))
        raw_shape = static.shape
        if static.ndim == 3 and static.shape[0] == 1:
            static = static[0]
        if static.ndim != 2 or static.shape[1] != 3 or static.shape[0] == 0:
            raise InputError(path, f"key 'static_offset' has shape {shape_str(raw_shape)}, expected (1,V,3)")
    dynamic = None
    if "dynamic_offset" in arrays:
        dynamic = _numeric(path, "dynamic_offset", np.asarray(arrays["dynamic_offset"]))
        raw_shape = dynamic.shape
        if dynamic.ndim == 2 and T == 1:
            dynamic = dynamic[None]
        if dynamic.ndim != 3 or dynamic.shape[0] != T or dynamic.shape[2] != 3 or dynamic.shape[1] == 0:
            raise InputError(path, f"key 'dynamic_offset' has shape {shape_str(raw_shape)}, expected ({T},V,3)")
    if static is not None and dynamic is not None and static.shape[0] != dynamic.shape[1]:
        raise InputError(path, f"key 'dynamic_offset' has {dynamic.shape[1]} vertices but 'static_offset' has "
                               f"{static.shape[0]}")

    if timesteps is None and "timesteps" in arrays:
        timesteps = np.asarray(arrays["timesteps"])
        if not np.issubdtype(timesteps.dtype, np.integer):
            raise InputError(path, f"key 'timesteps' has dtype {timesteps.dtype}, expected integers")
    ts = np.arange(T, dtype=np.int64) if timesteps is None else np.asarray(timesteps, dtype=np.int64).reshape(-1)
    if ts.shape[0] != T:
        raise InputError(path, f"key 'timesteps' has {ts.shape[0]} entries, expected {T}")
    if np.unique(ts).shape[0] != T:
        raise InputError(path, "key 'timesteps' holds duplicate timesteps")
    return FlameParams(shape=shape, expr=expr, rotation=vals["rotation"], neck_pose=vals["neck_pose"],
                       jaw_pose=vals["jaw_pose"], eyes_pose=vals["eyes_pose"], translation=vals["translation"],
                       static_offset=static, dynamic_offset=dynamic, timesteps=ts)


def load_param_npz(path: str | Path, timesteps: Sequence[int] | np.ndarray | None = None,
                   require_shape: bool = True) -> FlameParams:
    """Read one FLAME parameter npz: a VHAP per-timestep file (T = 1) or a T-leading file.

    timesteps: (T,) dataset timestep of each row (default: the file's ``timesteps`` or ``arange(T)``).
    require_shape: False accepts motion files without ``shape`` (then ``shape`` is (0,)).
    Raises InputError(path, ...) naming the key and the expected vs actual shape, or NaN/Inf.
    """
    path = Path(path)
    return params_from_arrays(path, read_npz(path, "FLAME parameter file"), None if timesteps is None else np.asarray(timesteps),
                              require_shape=require_shape)


def _atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    with atomic_writer(path) as fh:
        np.savez(fh, **arrays)
    return path


def save_param_npz(path: str | Path, params: FlameParams, index: int) -> Path:
    """Write row ``index`` as a VHAP per-timestep file (exact VHAP shapes, float32, atomic).

    Writes ``translation, rotation, neck_pose, jaw_pose (1,3)``, ``eyes_pose (1,6)``, ``expr (1,E)``,
    ``shape (S,)`` and, when present, ``static_offset (1,V,3)`` and ``dynamic_offset (1,V,3)``.
    """
    i = int(index)
    arrays: dict[str, np.ndarray] = {
        k: np.asarray(getattr(params, k)[i : i + 1], dtype=np.float32) for k in DYNAMIC_KEYS
    }
    arrays["shape"] = np.asarray(params.shape, dtype=np.float32)
    if params.static_offset is not None:
        arrays["static_offset"] = np.asarray(params.static_offset, dtype=np.float32)[None]
    if params.dynamic_offset is not None:
        arrays["dynamic_offset"] = np.asarray(params.dynamic_offset[i : i + 1], dtype=np.float32)
    return _atomic_savez(Path(path), arrays)


def stack_params(items: Sequence[FlameParams], sources: Sequence[str | Path] | None = None) -> FlameParams:
    """Concatenate per-timestep parameters along T.

    ``shape`` and ``static_offset`` come from the first item; every other item must carry the same
    values (within 1e-5), else InputError naming that item's source file. A missing
    ``dynamic_offset`` in some items is filled with zeros.
    """
    if not items:
        raise ValueError("stack_params needs at least one FlameParams")
    srcs = [Path(s) for s in sources] if sources is not None else [Path(f"<params {i}>") for i in range(len(items))]
    if len(srcs) != len(items):
        raise ValueError("stack_params: sources and items differ in length")
    first = items[0]
    for item, src in zip(items[1:], srcs[1:]):
        if item.shape.shape != first.shape.shape or not np.allclose(item.shape, first.shape, rtol=0, atol=1e-5):
            raise InputError(src, f"'shape' differs from the one in {srcs[0]}; a capture must hold one identity")
        if (item.static_offset is None) != (first.static_offset is None):
            raise InputError(src, f"'static_offset' is {'missing' if item.static_offset is None else 'present'} "
                                  f"but {'present' if first.static_offset is not None else 'missing'} in {srcs[0]}")
        if item.static_offset is not None and (
            item.static_offset.shape != first.static_offset.shape  # type: ignore[union-attr]
            or not np.allclose(item.static_offset, first.static_offset, rtol=0, atol=1e-5)
        ):
            raise InputError(src, f"'static_offset' differs from the one in {srcs[0]}")
        if item.n_expr != first.n_expr:
            raise InputError(src, f"'expr' has {item.n_expr} coefficients but {srcs[0]} has {first.n_expr}")
    n_dyn = {it.dynamic_offset.shape[1] for it in items if it.dynamic_offset is not None}
    if len(n_dyn) > 1:
        bad = next(s for it, s in zip(items, srcs) if it.dynamic_offset is not None
                   and it.dynamic_offset.shape[1] != min(n_dyn))
        raise InputError(bad, f"'dynamic_offset' vertex counts differ across files: {sorted(n_dyn)}")
    dynamic = None
    if n_dyn:
        V = n_dyn.pop()
        dynamic = np.concatenate([
            it.dynamic_offset if it.dynamic_offset is not None else np.zeros((it.n_timesteps, V, 3), np.float32)
            for it in items
        ])
    ts = np.concatenate([it.timesteps for it in items]).astype(np.int64)
    if np.unique(ts).shape[0] != ts.shape[0]:
        raise ValueError("stack_params: duplicate timesteps")
    cat = {k: np.concatenate([getattr(it, k) for it in items]).astype(np.float32) for k in DYNAMIC_KEYS}
    return FlameParams(shape=first.shape.copy(), static_offset=None if first.static_offset is None
                       else first.static_offset.copy(), dynamic_offset=dynamic, timesteps=ts, **cat)


def save_stacked_npz(path: str | Path, params: FlameParams) -> Path:
    """Write all T rows (GaussianAvatars key layout plus ``timesteps``), atomically.

    ``static_offset`` is stored as (1,V,3) and ``dynamic_offset`` as (T,V,3), like GA's
    ``flame_param.npz``.
    """
    arrays: dict[str, Any] = {k: np.asarray(getattr(params, k), dtype=np.float32) for k in DYNAMIC_KEYS}
    arrays["shape"] = np.asarray(params.shape, dtype=np.float32)
    arrays["timesteps"] = np.asarray(params.timesteps, dtype=np.int64)
    arrays["format"] = np.array(STACKED_FORMAT)
    if params.static_offset is not None:
        arrays["static_offset"] = np.asarray(params.static_offset, dtype=np.float32)[None]
    if params.dynamic_offset is not None:
        arrays["dynamic_offset"] = np.asarray(params.dynamic_offset, dtype=np.float32)
    return _atomic_savez(Path(path), arrays)


def load_stacked_npz(path: str | Path) -> FlameParams:
    """Read a file written by :func:`save_stacked_npz` (requires ``timesteps`` and ``shape``)."""
    path = Path(path)
    arrays = read_npz(path, "FLAME parameter file")
    if "timesteps" not in arrays:
        raise InputError(path, "stacked FLAME parameter file lacks key 'timesteps'")
    return params_from_arrays(path, arrays)
