"""The ingest engine: select a regime's frames from a capture and write the workspace data folder.

Output (``out_dir``, a fresh folder the caller provides and later promotes atomically):

- ``cameras.json``: camera_index -> camera (OpenCV K/w2c at the ingested resolution);
- ``frames.json``: one entry per ingested frame (split, role, timestep, camera, image/mask paths);
- ``images/{ti:05d}_{ci:02d}.png`` (RGB) and ``masks/{ti:05d}_{ci:02d}.png`` (L) when masks exist;
- ``flame_params.npz``: stacked FLAME parameters of every timestep used by any role;
- ``flame_model.npz``: the model in the project's npz format;
- ``flame_masks.json``: FLAME region masks (name -> vertex ids) when a mask file is available;
- ``summary.json`` (written last): regime, timesteps, cameras, counts, resolution, head box.

Regimes (paper §5): ``mv-sf`` one timestep seen by all training cameras, ``mv-mf`` every training
timestep, ``sv-hr`` every frame of one camera (head turns), ``one-shot`` a single image.
``val`` (novel view) and ``test`` (self-reenactment) frames are kept as evaluation roles.
"""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from ..atomic import atomic_write_text
from ..errors import ConfigError, InputError
from .cameras import Camera
from .capture import Capture, CaptureFrame, fit_params_to_model, validate_against_model

if TYPE_CHECKING:
    from ..flame.params import FlameParams

REGIMES: tuple[str, ...] = ("mv-sf", "mv-mf", "sv-hr", "one-shot")
BACKGROUNDS: tuple[str, ...] = ("white", "black")
INGEST_FORMAT = "sage-ingest-v1"
OUTPUT_NAMES: tuple[str, ...] = (
    "summary.json", "frames.json", "cameras.json", "flame_params.npz", "flame_model.npz", "flame_masks.json",
    "images", "masks",
)
"""Entries ingest writes in its output folder (``summary.json`` is written last)."""

NEUTRAL_JAW = np.array([0.3, 0.0, 0.0], dtype=np.float64)
"""Target jaw pose (axis-angle, rad) of the automatic canonical timestep: mouth slightly open."""
NEUTRAL_JAW_WEIGHT = 10.0
"""Weight per radian of jaw deviation against the expression norm in :func:`neutral_score`."""
NEUTRAL_RULE = (
    f"argmin over candidate timesteps of ||expr||_2 + {NEUTRAL_JAW_WEIGHT:g}*||jaw_pose - (0.3,0,0)||_2 "
    "(ties: earliest timestep)"
)

CROSS_VIEW_TIMESTEPS = 8
"""sv-hr from a multiview capture: the other cameras' train frames at up to this many evenly spaced
training timesteps become val frames (cross-view ground truth)."""

Progress = Callable[[int, int, str], None]


@dataclass
class Selection:
    """Frames chosen for each role, and the canonical timestep."""

    train: list[CaptureFrame]
    val: list[CaptureFrame]
    test: list[CaptureFrame]
    canonical_timestep: int
    warnings: list[str] = field(default_factory=list)

    @property
    def roles(self) -> dict[str, list[CaptureFrame]]:
        return {"train": self.train, "val": self.val, "test": self.test}


@dataclass
class IngestSummary:
    """What ingest wrote, for the CLI's panel and later stages.

    Attributes:
        out_dir: the folder written.
        source: the capture folder.
        regime: one of :data:`REGIMES`.
        train_timesteps: sorted training timesteps.
        canonical_timestep: the timestep whose FLAME mesh defines canonical space.
        train_cameras: sorted camera indices of the training frames.
        cameras: sorted camera indices over all roles.
        counts: role -> number of frames.
        resolution: (width, height) of the training images (the most common one).
        head_bbox: ((x,y,z) min, (x,y,z) max) of the posed FLAME mesh at the canonical timestep, metres.
        n_timesteps: rows of ``flame_params.npz``.
        background: "white" or "black".
        has_masks: whether ``masks/`` holds a mask for every frame.
        warnings: non-fatal findings.
        coverage: sv-hr / one-shot: the yaw/pitch of the training camera relative to the head
            (:meth:`sage_core.data.coverage.Coverage.to_dict`), else None.
    """

    out_dir: Path
    source: Path
    regime: str
    train_timesteps: list[int]
    canonical_timestep: int
    train_cameras: list[int]
    cameras: list[int]
    counts: dict[str, int]
    resolution: tuple[int, int]
    head_bbox: tuple[tuple[float, float, float], tuple[float, float, float]]
    n_timesteps: int
    background: str
    has_masks: bool
    warnings: list[str] = field(default_factory=list)
    coverage: dict[str, Any] | None = None

    def metrics(self) -> dict[str, Any]:
        """Flat JSON-safe numbers for a stage manifest."""
        cov = {k: v for k, v in (self.coverage or {}).items() if k.startswith("coverage_")}
        return {
            **cov,
            "regime": self.regime,
            "canonical_timestep": self.canonical_timestep,
            "train_images": self.counts.get("train", 0),
            "val_images": self.counts.get("val", 0),
            "test_images": self.counts.get("test", 0),
            "timesteps": self.n_timesteps,
            "train_timesteps": len(self.train_timesteps),
            "train_cameras": len(self.train_cameras),
            "width": self.resolution[0],
            "height": self.resolution[1],
        }

    def rows(self) -> list[tuple[str, str]]:
        """(label, value) lines for a summary panel."""
        lo, hi = np.asarray(self.head_bbox[0]), np.asarray(self.head_bbox[1])
        size = " x ".join(f"{v:.3f}" for v in hi - lo)
        ts = self.train_timesteps
        ts_text = ", ".join(map(str, ts)) if len(ts) <= 8 else f"{len(ts)} ({ts[0]}..{ts[-1]})"
        rows = [
            ("regime", self.regime),
            ("train timesteps", ts_text),
            ("canonical timestep", str(self.canonical_timestep)),
            ("train cameras", ", ".join(map(str, self.train_cameras))),
            ("images train / val / test", " / ".join(str(self.counts.get(k, 0)) for k in ("train", "val", "test"))),
            ("resolution", f"{self.resolution[0]} x {self.resolution[1]}"),
            ("head box (m)", size),
            ("background", self.background + ("" if self.has_masks else " (no masks)")),
        ]
        if self.coverage is not None:
            from .coverage import Coverage

            rows.append(("head coverage", Coverage.from_dict(self.coverage).text()))
        rows += [("warning", w) for w in self.warnings]
        return rows

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON-safe)."""
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        d["source"] = str(self.source)
        d["resolution"] = list(self.resolution)
        d["head_bbox"] = [list(self.head_bbox[0]), list(self.head_bbox[1])]
        return d


def neutral_score(params: FlameParams, rows: np.ndarray | list[int]) -> np.ndarray:
    """Distance to "neutral face, mouth slightly open" of the given rows: (len(rows),).

    score = ||expr||_2 + NEUTRAL_JAW_WEIGHT · ||jaw_pose − (0.3, 0, 0)||_2.
    """
    idx = np.asarray(rows, dtype=np.int64)
    expr = params.expr[idx].astype(np.float64)
    jaw = params.jaw_pose[idx].astype(np.float64)
    return np.linalg.norm(expr, axis=1) + NEUTRAL_JAW_WEIGHT * np.linalg.norm(jaw - NEUTRAL_JAW, axis=1)


def choose_neutral_timestep(params: FlameParams, timesteps: list[int]) -> int:
    """The timestep among ``timesteps`` with the smallest :func:`neutral_score` (earliest on ties)."""
    ts = sorted(int(t) for t in timesteps)
    if not ts:
        raise ValueError("no candidate timesteps")
    scores = neutral_score(params, [params.row_of(t) for t in ts])
    return ts[int(np.argmin(scores))]


def _train_source(capture: Capture) -> Path:
    """The file that lists the capture's train frames (for messages)."""
    train = capture.split("train")
    return train[0].source if train else capture.root


def _listing(values: list[int], limit: int = 12) -> str:
    head = ", ".join(str(v) for v in values[:limit])
    return head + (f", ... ({len(values)} in all)" if len(values) > limit else "")


def select_frames(capture: Capture, regime: str, timestep: int | None = None, camera: int | None = None) -> Selection:
    """Choose the training frames of ``regime`` and the evaluation frames (raises ConfigError).

    - ``mv-sf``: the train frames of one timestep (``timestep`` or the most neutral train timestep,
      :func:`choose_neutral_timestep`); val = val frames of that timestep; test unchanged.
    - ``mv-mf``: every train frame; ``timestep`` picks the canonical timestep (default: most neutral).
    - ``sv-hr``: every train frame of one camera (``camera``, or the only train camera).
    - ``one-shot``: exactly one train frame; ``camera``/``timestep`` are required when the capture
      has several.
    For the last three, val keeps the val frames at the training timesteps (sv-hr adds the other train
    cameras' frames at up to :data:`CROSS_VIEW_TIMESTEPS` of those timesteps: cross-view ground
    truth); test is unchanged. A capture that
    does not fit the regime is refused with a message naming its train transforms file.
    """
    if regime not in REGIMES:
        raise ConfigError(f"unknown regime '{regime}' (choose from {', '.join(REGIMES)})")
    train_all = capture.split("train")
    train_ts = sorted({f.timestep for f in train_all})
    train_cams = sorted({f.camera_index for f in train_all})
    warnings: list[str] = []
    if camera is not None and regime in ("mv-sf", "mv-mf"):
        raise ConfigError(f"a camera choice applies to the sv-hr and one-shot regimes, not {regime}")
    if timestep is not None and timestep not in train_ts:
        raise ConfigError(f"timestep {timestep} is not a train timestep of the capture (train timesteps: "
                          f"{_listing(train_ts)})")
    if camera is not None and camera not in train_cams:
        raise ConfigError(f"camera {camera} has no train frames in the capture (train cameras: "
                          f"{_listing(train_cams)})")

    if regime == "mv-sf":
        t = timestep if timestep is not None else choose_neutral_timestep(capture.params, train_ts)
        train = [f for f in train_all if f.timestep == t]
        if len(train) < 2:
            warnings.append(f"mv-sf: timestep {t} has only {len(train)} train view(s)")
    elif regime == "mv-mf":
        train = list(train_all)
        t = timestep if timestep is not None else choose_neutral_timestep(capture.params, train_ts)
    elif regime == "sv-hr":
        if camera is None:
            if len(train_cams) > 1:
                raise ConfigError(f"{_train_source(capture)}: sv-hr needs one camera but the capture has "
                                  f"{len(train_cams)} train cameras ({_listing(train_cams)}); choose one with the "
                                  "camera option (the other cameras then serve as cross-view ground truth)")
            camera = train_cams[0]
        train = [f for f in train_all if f.camera_index == camera]
        cam_ts = sorted({f.timestep for f in train})
        if timestep is not None and timestep not in cam_ts:
            raise ConfigError(f"timestep {timestep} has no train frame from camera {camera}")
        t = timestep if timestep is not None else choose_neutral_timestep(capture.params, cam_ts)
        if len(cam_ts) < 2:
            warnings.append(f"sv-hr: camera {camera} has only {len(cam_ts)} train frame(s); a head-turn clip "
                            "needs several")
    else:  # one-shot
        if camera is None:
            if len(train_cams) > 1:
                raise ConfigError(f"{_train_source(capture)}: one-shot uses a single image but the capture has "
                                  f"{len(train_cams)} train cameras ({_listing(train_cams)}); choose one with the "
                                  "camera option")
            camera = train_cams[0]
        cam_frames = [f for f in train_all if f.camera_index == camera]
        cam_ts = sorted({f.timestep for f in cam_frames})
        if timestep is None:
            if len(cam_ts) > 1:
                raise ConfigError(f"{_train_source(capture)}: one-shot uses a single image but camera {camera} "
                                  f"has {len(cam_ts)} train timesteps ({_listing(cam_ts)}); choose one with the "
                                  "timestep option")
            timestep = cam_ts[0]
        train = [f for f in cam_frames if f.timestep == timestep]
        if not train:
            raise ConfigError(f"no train frame for timestep {timestep}, camera {camera}")
        t = timestep

    seen_ts = {f.timestep for f in train}
    val = [f for f in capture.split("val") if f.timestep in seen_ts]
    if regime == "sv-hr":
        # the capture's other train cameras at (up to CROSS_VIEW_TIMESTEPS evenly spaced of) the clip's
        # timesteps: cross-view ground truth
        ts = sorted(seen_ts)
        if len(ts) > CROSS_VIEW_TIMESTEPS:
            ts = [ts[i] for i in np.unique(np.linspace(0, len(ts) - 1, CROSS_VIEW_TIMESTEPS).round().astype(int))]
        keep = set(ts)
        val += [f for f in train_all if f.camera_index != camera and f.timestep in keep]
    test = list(capture.split("test"))
    return Selection(train=train, val=val, test=test, canonical_timestep=int(t), warnings=warnings)


def target_size(width: int, height: int, downsample: float | None, out_height: int | None) -> tuple[int, int]:
    """Output (width, height): ``out_height`` keeps the aspect ratio (width rounded half up), or both
    sides divided by ``downsample`` and rounded; neither = unchanged."""
    if out_height is not None:
        return max(1, int(np.floor(width * out_height / height + 0.5))), int(out_height)
    if downsample is not None:
        return max(1, int(np.floor(width / downsample + 0.5))), max(1, int(np.floor(height / downsample + 0.5)))
    return int(width), int(height)


def _write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1) + "\n")


def _check_options(regime: str, background: str, downsample: float | None, height: int | None,
                   workers: int | None) -> None:
    if regime not in REGIMES:
        raise ConfigError(f"unknown regime '{regime}' (choose from {', '.join(REGIMES)})")
    if background not in BACKGROUNDS:
        raise ConfigError(f"unknown background '{background}' (choose from {', '.join(BACKGROUNDS)})")
    if downsample is not None and height is not None:
        raise ConfigError("give either a downsample factor or an output height, not both")
    if downsample is not None and not (np.isfinite(downsample) and downsample > 0):
        raise ConfigError(f"downsample must be a positive number, got {downsample}")
    if height is not None and (int(height) != height or height < 8):
        raise ConfigError(f"output height must be an integer of at least 8 pixels, got {height}")
    if workers is not None and workers < 1:
        raise ConfigError(f"workers must be at least 1, got {workers}")


def _load_mask(path: Path) -> np.ndarray:
    """(H, W) float32 in [0, 1]: the single channel, or the alpha of an RGBA mask."""
    from .imageio import read_image

    m = read_image(path)
    ch = 3 if m.shape[2] == 4 else 0
    return np.ascontiguousarray(np.clip(m[:, :, ch], 0.0, 1.0), dtype=np.float32)


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    if (img.shape[1], img.shape[0]) == size:
        return img
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def _head_bbox(
    model: Any, params: FlameParams, timestep: int, source: Path
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Axis-aligned box (min, max) of the posed FLAME mesh at ``timestep``; ``source`` names its npz."""
    import torch

    from ..flame import FlameModel

    flame = FlameModel(model)
    with torch.no_grad():
        out = flame(**params.select([params.row_of(timestep)]).to_torch("cpu"))
    v = out.vertices[0].double().numpy()
    if not np.all(np.isfinite(v)):
        raise InputError(source, f"the posed FLAME mesh of timestep {timestep} has non-finite vertices")
    lo, hi = v.min(axis=0), v.max(axis=0)
    return tuple(float(x) for x in lo), tuple(float(x) for x in hi)


def _frame_name(f: CaptureFrame) -> str:
    return f"{f.timestep:05d}_{f.camera_index:02d}.png"


def _clear_outputs(out_dir: Path) -> None:
    """Remove this engine's outputs left in ``out_dir`` by an earlier run (summary first, so a folder
    being rewritten never looks complete); other files (the caller's) are kept."""
    for name in OUTPUT_NAMES:
        p = out_dir / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()


def _write_frame(
    f: CaptureFrame, role: str, out_dir: Path, size: tuple[int, int], background: str
) -> dict[str, Any]:
    """Read, convert, resize and write one frame's image (and mask); returns its frames.json entry."""
    from .imageio import read_on_white, write_image

    name = _frame_name(f)
    img = read_on_white(f.image_path)
    mask = _load_mask(f.mask_path) if f.mask_path is not None else None
    if (img.shape[1], img.shape[0]) != (f.camera.width, f.camera.height):
        raise InputError(f.image_path, f"image is {img.shape[1]}x{img.shape[0]}, expected "
                                       f"{f.camera.width}x{f.camera.height}")
    if background == "black" and mask is not None:
        img = np.clip(img - (1.0 - mask)[:, :, None], 0.0, 1.0)
    write_image(out_dir / "images" / name, _resize(img, size))
    if mask is not None:
        write_image(out_dir / "masks" / name, _resize(mask, size))
    return {
        "split": f.split,
        "role": role,
        "timestep": f.timestep,
        "camera_index": f.camera_index,
        "camera_id": f.camera_id,
        "image": f"images/{name}",
        "mask": f"masks/{name}" if mask is not None else None,
        "camera": f.camera.resized(*size).to_dict(),
        "source_image": str(f.image_path),
    }


def capture_files(capture: Capture) -> list[Path]:
    """Every file of a capture that ingest reads besides the transforms JSONs: each frame's image
    and mask, each timestep's FLAME parameter file and ``canonical_flame_param.npz`` (sorted)."""
    paths: set[Path] = set()
    for f in capture.frames:
        paths.add(Path(f.image_path))
        if f.mask_path is not None:
            paths.add(Path(f.mask_path))
    paths.update(Path(p) for p in capture.param_paths.values())
    canon = capture.root / "canonical_flame_param.npz"
    if canon.is_file():
        paths.add(canon)
    return sorted(paths)


def capture_fingerprint(capture: Capture, cache_file: str | Path | None = None) -> str:
    """Content fingerprint (16 hex) of :func:`capture_files`: replacing an image or mask or
    re-tracking the FLAME parameters changes it. ``cache_file``: the workspace's hash cache
    (:data:`sage_core.workspace.HASH_CACHE`), so unchanged files (same size and mtime) are not
    read again."""
    from ..workspace import combined_hash, content_hashes

    root = capture.root.resolve()
    hashes = content_hashes(capture_files(capture), cache_file)
    keyed: dict[str, str] = {}
    for path, digest in hashes.items():
        try:
            keyed[Path(path).relative_to(root).as_posix()] = digest
        except ValueError:  # union captures point into sibling folders
            keyed[path] = digest
    return combined_hash(keyed)


def ingest(
    capture: Capture,
    model_path: str | Path,
    out_dir: str | Path,
    *,
    masks_path: str | Path | None = None,
    regime: str = "mv-sf",
    timestep: int | None = None,
    camera: int | None = None,
    downsample: float | None = None,
    height: int | None = None,
    background: str = "white",
    workers: int | None = None,
    progress: Progress | None = None,
) -> IngestSummary:
    """Select a regime's frames from ``capture`` and write them, resized, into ``out_dir``.

    capture: from :func:`read_capture` (already validated).
    model_path: FLAME model (official pickle or the project's npz).
    out_dir: the output folder (created only after every check passed); entries named in
        :data:`OUTPUT_NAMES` left there by an earlier run are replaced, anything else is kept.
    masks_path: ``FLAME_masks.pkl``; default: that file beside the model when present.
    regime, timestep, camera: see :func:`select_frames`.
    downsample / height: shrink each image by a factor, or to a height keeping the aspect ratio
        (``cv2.INTER_AREA``); K is rescaled with :meth:`Camera.resized`.
    background: "white" keeps the images (already matted onto white); "black" removes the white
        using the foreground mask (img − (1 − mask)), which needs a mask for every frame.
    workers: threads reading/resizing/writing images (default: min(8, CPU count)).
    progress: ``progress(done, total, message)``, called from the calling thread.
    Raises ConfigError for bad options and InputError naming the file for bad inputs, in both
    cases before anything is written.
    """
    from ..flame import load_flame_model, load_masks, save_flame_npz
    from ..flame.params import save_stacked_npz

    _check_options(regime, background, downsample, height, workers)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, "output path exists and is not a folder")
    model_path = Path(model_path)
    model = load_flame_model(model_path)
    warnings = list(capture.warnings)
    warnings += validate_against_model(capture, model.n_vertices, model.n_base_vertices, model.n_expr)

    masks_file: Path | None = Path(masks_path) if masks_path is not None else None
    if masks_file is None and (model_path.parent / "FLAME_masks.pkl").is_file():
        masks_file = model_path.parent / "FLAME_masks.pkl"
    region_masks: dict[str, list[int]] | None = None
    if masks_file is not None:
        loaded = load_masks(masks_file)
        for name, ids in loaded.items():
            if ids.size and int(ids.max()) >= model.n_vertices:
                raise InputError(masks_file, f"mask '{name}' names vertex {int(ids.max())} but the model has "
                                             f"{model.n_vertices} vertices")
        region_masks = {name: [int(i) for i in ids] for name, ids in loaded.items()}

    sel = select_frames(capture, regime, timestep, camera)
    warnings += sel.warnings
    roles = sel.roles
    all_frames = [(role, f) for role, frames in roles.items() for f in frames]
    has_masks = all(f.mask_path is not None for _, f in all_frames)
    if background == "black" and not has_masks:
        first = next(f for _, f in all_frames if f.mask_path is None)
        raise InputError(first.source, f"a black background needs foreground masks, but the frame of timestep "
                                       f"{first.timestep}, camera {first.camera_index} has none")

    used_ts = sorted({f.timestep for _, f in all_frames})
    params = fit_params_to_model(capture.params.select_timesteps(used_ts), model.n_vertices, model.n_base_vertices)
    if params.dynamic_offset is not None and np.any(params.dynamic_offset != 0):
        warnings.append("the capture has non-zero dynamic_offset; it is kept in flame_params.npz")
    canon_src = capture.param_paths.get(sel.canonical_timestep, capture.root)
    bbox = _head_bbox(model, params, sel.canonical_timestep, canon_src)
    coverage: dict[str, Any] | None = None
    if regime in ("sv-hr", "one-shot"):
        from .coverage import coverage_of_frames

        cov = coverage_of_frames(model, params, [(f.timestep, f.camera) for f in sel.train])
        coverage = cov.to_dict()
        note = cov.warning()
        if regime == "sv-hr" and note is not None:
            warnings.append(note)

    # -- everything is checked; write
    total = len(all_frames) + 3
    done = 0
    frame_entries: list[dict[str, Any]] = []
    cameras_out: dict[int, Camera] = {}
    out_dir.mkdir(parents=True, exist_ok=True)
    _clear_outputs(out_dir)

    def work(item: tuple[str, CaptureFrame]) -> tuple[dict[str, Any], Camera]:
        role, f = item
        size = target_size(f.camera.width, f.camera.height, downsample, height)
        return _write_frame(f, role, out_dir, size, background), f.camera.resized(*size)

    n_workers = max(1, min(8, os.cpu_count() or 1) if workers is None else int(workers))
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        for (role, f), (entry, cam) in zip(all_frames, pool.map(work, all_frames)):
            cameras_out.setdefault(f.camera_index, cam)
            frame_entries.append(entry)
            done += 1
            if progress is not None:
                progress(done, total, f"{role} {_frame_name(f)}")

    _write_json(out_dir / "cameras.json", {
        "cameras": {str(ci): cam.to_dict() for ci, cam in sorted(cameras_out.items())},
        "varying": [ci for ci in capture.varying_cameras if ci in cameras_out],
    })
    _write_json(out_dir / "frames.json", {"frames": frame_entries})
    save_stacked_npz(out_dir / "flame_params.npz", params)
    done += 1
    if progress is not None:
        progress(done, total, "flame_params.npz")
    save_flame_npz(model, out_dir / "flame_model.npz")
    if region_masks is not None:
        _write_json(out_dir / "flame_masks.json", {"source": str(masks_file), "masks": region_masks})
    done += 1
    if progress is not None:
        progress(done, total, "flame_model.npz")

    sizes = Counter((e["camera"]["width"], e["camera"]["height"]) for e in frame_entries if e["role"] == "train")
    summary = IngestSummary(
        out_dir=out_dir,
        source=capture.root,
        regime=regime,
        train_timesteps=sorted({f.timestep for f in sel.train}),
        canonical_timestep=sel.canonical_timestep,
        train_cameras=sorted({f.camera_index for f in sel.train}),
        cameras=sorted(cameras_out),
        counts={role: len(frames) for role, frames in roles.items()},
        resolution=sizes.most_common(1)[0][0],
        head_bbox=bbox,  # type: ignore[arg-type]
        n_timesteps=params.n_timesteps,
        background=background,
        has_masks=has_masks,
        warnings=warnings,
        coverage=coverage,
    )
    doc = summary.to_dict()
    doc.pop("out_dir")
    doc.update({
        "format": INGEST_FORMAT,
        "model_source": str(model_path),
        "n_vertices": model.n_vertices,
        "n_faces": model.n_faces,
        "face_table": model.face_table,
        "flame_masks": region_masks is not None,
        "neutral_rule": NEUTRAL_RULE,
    })
    _write_json(out_dir / "summary.json", doc)
    done += 1
    if progress is not None:
        progress(done, total, "summary.json")
    return summary
