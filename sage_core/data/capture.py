"""Read and validate a VHAP "NeRF-style" capture export (single sequence or union).

Layout (docs/formats.md §1): ``transforms_{train,val,test}.json`` whose per-frame entries name an image,
an optional foreground mask and a per-timestep FLAME npz, plus an optional
``canonical_flame_param.npz``. Frame paths are resolved relative to the JSON file's folder and then
normalised, so union exports (``../<sequence>/images/...``) work when they sit beside their
sequences.

Everything is checked before anything is written: :func:`read_capture` collects every problem it
finds and raises one :class:`InputError` naming the first offending file and listing the others.
"""

from __future__ import annotations

import json
import math
import os
import reprlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from ..errors import InputError
from .cameras import Camera, camera_from_nerf_frame
from .imageio import image_size

if TYPE_CHECKING:
    from ..flame.params import FlameParams

SPLITS: tuple[str, ...] = ("train", "val", "test")
REQUIRED_FRAME_KEYS: tuple[str, ...] = (
    "timestep_index", "camera_index", "w", "h", "fl_x", "fl_y", "cx", "cy", "transform_matrix", "file_path",
    "flame_param_path",
)
FLAME_N_VERTICES = 5023
TEETH_N_VERTICES = 120
MAX_LISTED_PROBLEMS = 10

Progress = Callable[[int, int, str], None]


@dataclass
class CaptureFrame:
    """One image of the capture.

    Attributes:
        split: "train", "val" or "test" (the JSON it came from).
        timestep: dataset ``timestep_index`` (indexes :attr:`Capture.params` via ``params.row_of``).
        camera_index: the capture's camera index.
        camera_id: camera serial ("" when absent).
        image_path: absolute, normalised path of the RGB image.
        mask_path: absolute path of the foreground mask, or None.
        param_path: absolute path of the timestep's FLAME npz.
        camera: this frame's camera (OpenCV, per-frame intrinsics).
        source: the transforms JSON that listed this frame.
    """

    split: str
    timestep: int
    camera_index: int
    camera_id: str
    image_path: Path
    mask_path: Path | None
    param_path: Path
    camera: Camera
    source: Path


@dataclass
class Capture:
    """A validated capture.

    Attributes:
        root: the capture folder (absolute).
        frames: all frames of all splits, in file order (train, val, test).
        cameras: camera_index -> the camera of its first frame.
        varying_cameras: camera indices whose camera differs between frames (use ``frame.camera``).
        params: FLAME parameters stacked over every referenced timestep, sorted by timestep.
        param_paths: timestep -> npz it was read from.
        canonical: ``canonical_flame_param.npz`` when present, else None.
        image_size: the most common (width, height) over the frames.
        warnings: non-fatal findings (fallbacks, mixed sizes), one sentence each.
    """

    root: Path
    frames: list[CaptureFrame]
    cameras: dict[int, Camera]
    varying_cameras: list[int]
    params: FlameParams
    param_paths: dict[int, Path]
    canonical: FlameParams | None
    image_size: tuple[int, int]
    warnings: list[str] = field(default_factory=list)

    def split(self, name: str) -> list[CaptureFrame]:
        """Frames of one split ("train", "val", "test")."""
        return [f for f in self.frames if f.split == name]

    @property
    def splits(self) -> dict[str, list[CaptureFrame]]:
        """split name -> frames."""
        return {s: self.split(s) for s in SPLITS}

    def timesteps(self, split: str | None = None) -> list[int]:
        """Sorted timesteps of one split (or all frames)."""
        frames = self.frames if split is None else self.split(split)
        return sorted({f.timestep for f in frames})

    def camera_indices(self, split: str | None = None) -> list[int]:
        """Sorted camera indices of one split (or all frames)."""
        frames = self.frames if split is None else self.split(split)
        return sorted({f.camera_index for f in frames})


class _Problems:
    """Collects (path, problem) pairs and raises them as one InputError."""

    def __init__(self) -> None:
        self.items: list[tuple[Path, str]] = []

    def add(self, path: str | Path, problem: str) -> None:
        self.items.append((Path(path), problem))

    def add_error(self, err: InputError) -> None:
        self.items.append((err.path, err.problem))

    def raise_if_any(self) -> None:
        if not self.items:
            return
        path, first = self.items[0]
        n = len(self.items)
        if n == 1:
            raise InputError(path, first)
        listed = [f"{p}: {m}" for p, m in self.items[1:MAX_LISTED_PROBLEMS]]
        more = n - MAX_LISTED_PROBLEMS
        tail = "\n  - ".join(listed) + (f"\n  ... and {more} more" if more > 0 else "")
        raise InputError(path, f"{first}\n{n} problems in the capture; the others:\n  - {tail}")


def _resolve(json_dir: Path, rel: str) -> Path:
    p = Path(rel)
    return Path(os.path.normpath(p if p.is_absolute() else json_dir / p))


def _outside_capture(json_dir: Path, rel: str, follow_symlinks: bool = False) -> str | None:
    """Why the frame path ``rel`` (relative to the split file's folder) leaves the capture, or None.

    A path stays in the capture when it is relative and resolves inside the capture folder or inside
    a sequence folder beside it (union exports name ``../<sequence>/images/...``). Absolute paths and
    anything that climbs further (``../../etc/hostname``) are refused, so a capture can never make
    sage read files elsewhere on the machine; so are symbolic links (of the file or of a folder on
    its way) whose target lies outside, unless ``follow_symlinks``.
    """
    if Path(rel).is_absolute():
        return "is an absolute path; capture paths are relative to the split file"
    resolved = _resolve(json_dir, rel)
    root = Path(os.path.normpath(json_dir.parent))
    try:
        inner = resolved.relative_to(root)
    except ValueError:
        return "points outside the capture folder and the sequence folders beside it"
    if len(inner.parts) < 2:
        return "points outside the capture folder and the sequence folders beside it"
    if not follow_symlinks:
        sequence = Path(os.path.realpath(root / inner.parts[0]))  # the capture, or the sequence folder beside it
        try:
            Path(os.path.realpath(resolved)).relative_to(sequence)
        except ValueError:
            return ("is a symbolic link (or lies in a linked folder) whose target is outside the capture; "
                    "copy the files into the capture or ingest with --set follow_symlinks=true")
    return None


def _brief(value: Any) -> str:
    """A file's value for a message: its repr, shortened (a 400-digit number, a deeply nested list)."""
    return reprlib.repr(value)


def _as_int(value: Any) -> int | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


def _as_float(value: Any) -> float | None:
    """A finite JSON number as a float; None for anything else (an integer beyond float range too)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        f = float(value)
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _check_frame(jpath: Path, i: int, fr: Any, problems: _Problems) -> dict[str, Any] | None:
    """Validate one JSON frame entry; returns it with parsed values or None after recording problems."""
    if not isinstance(fr, dict):
        problems.add(jpath, f"frame {i} is not a JSON object")
        return None
    label = f"frame {i}" + (f" ({fr['file_path']})" if isinstance(fr.get("file_path"), str) else "")
    missing = [k for k in REQUIRED_FRAME_KEYS if k not in fr]
    if missing:
        problems.add(jpath, f"{label} lacks field(s) {', '.join(missing)}")
        return None
    bad: list[str] = []
    out: dict[str, Any] = dict(fr)
    for k in ("timestep_index", "camera_index"):
        v = _as_int(fr[k])
        if v is None or v < 0:
            bad.append(f"{k}={_brief(fr[k])} (expected an integer >= 0)")
        out[k] = v
    for k in ("w", "h"):
        v = _as_int(fr[k])
        if v is None or v <= 0:
            bad.append(f"{k}={_brief(fr[k])} (expected a positive integer)")
        out[k] = v
    for k in ("fl_x", "fl_y", "cx", "cy"):
        v = _as_float(fr[k])
        if v is None or (k.startswith("fl") and v <= 0):
            bad.append(f"{k}={_brief(fr[k])} (expected a finite {'positive ' if k.startswith('fl') else ''}number)")
        out[k] = v
    try:
        M = np.asarray(fr["transform_matrix"], dtype=np.float64)
        ok = M.shape == (4, 4) and bool(np.all(np.isfinite(M)))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        bad.append("transform_matrix (expected a 4x4 array of finite numbers)")
    else:
        R = M[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or abs(np.linalg.det(R) - 1.0) > 1e-3:
            bad.append("transform_matrix (its 3x3 block is not a rotation)")
        elif not np.allclose(M[3], [0, 0, 0, 1], atol=1e-6):
            bad.append("transform_matrix (last row is not 0 0 0 1)")
    for k in ("file_path", "flame_param_path"):
        if not isinstance(fr[k], str) or not fr[k]:
            bad.append(f"{k}={_brief(fr[k])} (expected a relative path)")
    if "fg_mask_path" in fr and fr["fg_mask_path"] is not None and not isinstance(fr["fg_mask_path"], str):
        bad.append(f"fg_mask_path={_brief(fr['fg_mask_path'])} (expected a relative path)")
    if bad:
        problems.add(jpath, f"{label} has invalid value(s): {'; '.join(bad)}")
        return None
    return out


def _read_json(path: Path, problems: _Problems) -> list[Any] | None:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        problems.add(path, f"cannot read transforms file ({exc})")
        return None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        problems.add(path, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}")
        return None
    except RecursionError:
        problems.add(path, "invalid JSON: nested too deeply to read")
        return None
    except ValueError as exc:  # an integer of more digits than Python converts
        problems.add(path, f"invalid JSON: {exc}")
        return None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        problems.add(path, "expected a JSON object with a 'frames' list")
        return None
    return doc["frames"]


def _same_camera(a: Camera, b: Camera) -> bool:
    return (a.width, a.height) == (b.width, b.height) and np.allclose(a.K, b.K, rtol=1e-6, atol=1e-6) \
        and np.allclose(a.w2c, b.w2c, rtol=1e-6, atol=1e-7)


def _check_image(path: Path, w: int, h: int, what: str, channels: tuple[int, ...], problems: _Problems) -> None:
    try:
        iw, ih, ic = image_size(path)
    except InputError as err:
        problems.add(err.path, f"{what}: {err.problem}")
        return
    except Exception as exc:  # OpenImageIO may raise on truncated headers
        problems.add(path, f"{what}: cannot read the image header ({exc})")
        return
    if (iw, ih) != (w, h):
        problems.add(path, f"{what} is {iw}x{ih} but its frame says w={w}, h={h}")
    if ic not in channels:
        problems.add(path, f"{what} has {ic} channels, expected {' or '.join(map(str, channels))}")


def read_capture(path: str | Path, *, check_images: bool = True, progress: Progress | None = None,
                 follow_symlinks: bool = False) -> Capture:
    """Read a VHAP NeRF-style export (single sequence or union) and validate all of it.

    path: the folder holding ``transforms_{train,val,test}.json`` (``transforms.json`` is used, all
        frames as train, only when no split file exists; a warning says so).
    check_images: read every image/mask header (size and channels) — skip only for speed in tools
        that do not use the images.
    progress: ``progress(done, total, message)`` while checking frames.
    follow_symlinks: accept frame files reached through symbolic links that point outside the
        capture (refused by default, like ``../`` paths that leave it).
    Raises InputError naming the first offending file; its message lists up to 10 problems.
    """
    from ..flame.params import load_param_npz, stack_params

    root = Path(os.path.abspath(path))
    if not root.is_dir():
        raise InputError(root, "capture folder not found" if not root.exists() else "not a folder")
    problems = _Problems()
    warnings: list[str] = []

    split_files = {s: root / f"transforms_{s}.json" for s in SPLITS}
    present = {s: p for s, p in split_files.items() if p.is_file()}
    if not present:
        fallback = root / "transforms.json"
        if not fallback.is_file():
            raise InputError(split_files["train"], "transforms file not found (nor transforms.json)")
        warnings.append(f"no transforms_{{train,val,test}}.json in {root}; using transforms.json with every frame "
                        "as train and no evaluation splits")
        present = {"train": fallback}
    else:
        if "train" not in present:
            problems.add(split_files["train"], "transforms file not found")
        for s in ("val", "test"):
            if s not in present:
                warnings.append(f"{split_files[s].name} not found; the {s} split is empty")

    # 1. parse frames
    raw: list[tuple[str, Path, dict[str, Any]]] = []
    for split, jpath in present.items():
        entries = _read_json(jpath, problems)
        if entries is None:
            continue
        for i, fr in enumerate(entries):
            parsed = _check_frame(jpath, i, fr, problems)
            if parsed is not None:
                raw.append((split, jpath, parsed))
    if "train" in present and not any(s == "train" for s, _, _ in raw) and not any(
        p == present["train"] for p, _ in problems.items
    ):
        problems.add(present["train"], "the train split has no frames")

    # 2. frames, cameras, duplicates, files
    frames: list[CaptureFrame] = []
    seen: dict[tuple[int, int], Path] = {}
    ts_param: dict[int, Path] = {}
    missing_masks: list[Path] = []
    n_masks = 0
    total = len(raw)
    for n, (split, jpath, fr) in enumerate(raw):
        jdir = jpath.parent
        ti, ci = int(fr["timestep_index"]), int(fr["camera_index"])
        key = (ti, ci)
        if key in seen:
            problems.add(jpath, f"duplicate frame for timestep {ti}, camera {ci} (also in {seen[key].name})")
            continue
        seen[key] = jpath
        cam = camera_from_nerf_frame(fr)
        bad = [(k, why) for k in ("file_path", "fg_mask_path", "flame_param_path")
               if isinstance(fr.get(k), str) and fr.get(k) and (why := _outside_capture(jdir, fr[k], follow_symlinks))]
        if bad:
            for k, why in bad:
                problems.add(jpath, f"frame for timestep {ti}, camera {ci}: {k} '{fr[k]}' {why}")
            continue
        img = _resolve(jdir, fr["file_path"])
        mask_rel = fr.get("fg_mask_path")
        mask = _resolve(jdir, mask_rel) if mask_rel else None
        par = _resolve(jdir, fr["flame_param_path"])
        prev = ts_param.setdefault(ti, par)
        if prev != par:
            problems.add(jpath, f"timestep {ti} names two FLAME files: {prev} and {par}")
        if check_images:
            _check_image(img, fr["w"], fr["h"], f"image of timestep {ti}, camera {ci}", (3, 4), problems)
        elif not img.is_file():
            problems.add(img, "image file not found")
        if mask is not None:
            if not mask.is_file():
                missing_masks.append(mask)
            elif check_images:
                _check_image(mask, fr["w"], fr["h"], f"mask of timestep {ti}, camera {ci}", (1, 3, 4), problems)
            n_masks += 1
        frames.append(CaptureFrame(split, ti, ci, cam.name, img, mask, par, cam, jpath))
        if progress is not None:
            progress(n + 1, total, "checking frames")

    if missing_masks and len(missing_masks) == n_masks:
        warnings.append(f"none of the {n_masks} foreground mask files exist (e.g. {missing_masks[0]}); "
                        "the capture is read without masks")
        for f in frames:
            f.mask_path = None
    else:
        for m in missing_masks:
            problems.add(m, "mask file not found")

    # 3. FLAME parameters, each file once
    loaded: list[FlameParams] = []
    sources: list[Path] = []
    for ti in sorted(ts_param):
        p = ts_param[ti]
        try:
            prm = load_param_npz(p, timesteps=None)
        except InputError as err:
            problems.add_error(err)
            continue
        if prm.n_timesteps != 1:
            problems.add(p, f"per-timestep FLAME file holds {prm.n_timesteps} rows, expected 1 "
                            "(key 'expr' should have shape (1,E))")
            continue
        prm.timesteps = np.array([ti], dtype=np.int64)
        loaded.append(prm)
        sources.append(p)
    params: FlameParams | None = None
    if loaded and len(loaded) == len(ts_param):
        try:
            params = stack_params(loaded, sources)
        except InputError as err:
            problems.add_error(err)

    canonical = None
    canon_path = root / "canonical_flame_param.npz"
    if canon_path.is_file():
        try:
            canonical = load_param_npz(canon_path)
        except InputError as err:
            problems.add_error(err)

    if params is None and not problems.items:
        problems.add(present.get("train", root), "the capture lists no frames")
    problems.raise_if_any()
    assert params is not None

    cameras: dict[int, Camera] = {}
    varying: set[int] = set()
    for f in frames:
        ref = cameras.setdefault(f.camera_index, f.camera)
        if ref is not f.camera and not _same_camera(ref, f.camera):
            varying.add(f.camera_index)
    if varying:
        warnings.append(f"camera(s) {sorted(varying)} change between frames; per-frame cameras are used")
    sizes = Counter((f.camera.width, f.camera.height) for f in frames)
    size = sizes.most_common(1)[0][0]
    if len(sizes) > 1:
        warnings.append(f"frames have {len(sizes)} different image sizes: {sorted(sizes)}")
    return Capture(root=root, frames=frames, cameras=cameras, varying_cameras=sorted(varying), params=params,
                   param_paths=dict(sorted(ts_param.items())), canonical=canonical, image_size=size,
                   warnings=warnings)


def offset_rows_compatible(rows: int, n_vertices: int, n_base_vertices: int) -> str | None:
    """How offsets with ``rows`` rows map onto a model: "same", "pad", "trim" or None (incompatible).

    "pad": rows = n_base_vertices < n_vertices (zero rows for appended vertices such as teeth).
    "trim": the model has plain FLAME topology and the offsets carry the 120 appended teeth rows.
    """
    if rows == n_vertices:
        return "same"
    if rows == n_base_vertices and rows < n_vertices:
        return "pad"
    if n_vertices == n_base_vertices == FLAME_N_VERTICES and rows == FLAME_N_VERTICES + TEETH_N_VERTICES:
        return "trim"
    return None


def validate_against_model(capture: Capture, n_vertices: int, n_base_vertices: int,
                           n_expr: int | None = None) -> list[str]:
    """Check that the capture's FLAME offsets fit a model with ``n_vertices`` (``n_base_vertices``
    before extensions), and that no timestep has a non-zero expression coefficient beyond the
    model's ``n_expr`` components (they would be dropped, changing the expression). Returns notes
    on padding/trimming; raises InputError naming the npz.
    """
    from ..flame.params import EXPR_DROP_TOL, expr_overflow

    notes: list[str] = []
    if n_expr is not None:
        for prm, own_file in ((capture.params, None), (capture.canonical, capture.root / "canonical_flame_param.npz")):
            problem = None if prm is None else expr_overflow(prm, n_expr)
            if problem is None:
                continue
            extra = np.abs(np.asarray(prm.expr, np.float64)[:, n_expr:]).max(axis=1)
            ts = int(prm.timesteps[int(np.argmax(extra > EXPR_DROP_TOL))])
            raise InputError(own_file or capture.param_paths.get(ts, capture.root), f"timestep {ts}: {problem}")
    checks: list[tuple[Path, FlameParams]] = []
    if capture.params.n_offset_vertices is not None:
        first_ts = int(capture.params.timesteps[0])
        checks.append((capture.param_paths.get(first_ts, capture.root), capture.params))
    if capture.canonical is not None and capture.canonical.n_offset_vertices is not None:
        checks.append((capture.root / "canonical_flame_param.npz", capture.canonical))
    for path, prm in checks:
        rows = prm.n_offset_vertices
        assert rows is not None
        mode = offset_rows_compatible(rows, n_vertices, n_base_vertices)
        key = "static_offset" if prm.static_offset is not None else "dynamic_offset"
        if mode is None:
            raise InputError(path, f"key '{key}' has {rows} vertex rows but the FLAME model has {n_vertices} "
                                   f"vertices ({n_base_vertices} before extensions)")
        if mode == "pad":
            notes.append(f"{path.name}: {rows}-row offsets zero-padded to {n_vertices} vertices")
        elif mode == "trim":
            notes.append(f"{path.name}: {rows}-row offsets trimmed to the model's {n_vertices} vertices")
    return notes


def fit_params_to_model(params: FlameParams, n_vertices: int, n_base_vertices: int) -> FlameParams:
    """Pad or trim the offsets of ``params`` to ``n_vertices`` rows (see :func:`offset_rows_compatible`)."""
    rows = params.n_offset_vertices
    if rows is None:
        return params
    mode = offset_rows_compatible(rows, n_vertices, n_base_vertices)
    if mode == "pad":
        return params.pad_offsets(n_vertices)
    if mode == "trim":
        return params.trim_offsets(n_vertices)
    if mode == "same":
        return params
    raise ValueError(f"offsets with {rows} rows do not fit a model with {n_vertices} vertices")
