"""``sage track``: from images, a video or a calibrated rig to a VHAP-layout capture.

:func:`track_capture` checks everything it can before heavy work (the face models, the FLAME model,
the input, the options), then:

1. finds one face per image (:mod:`.observe`) and each camera's crop window;
2. writes the cropped images and computes the person masks (second pass over the input);
3. loads or calibrates the landmark embedding (:mod:`.embedding`);
4. fits FLAME and the cameras (:mod:`.fitting`);
5. refines the masks with the fitted meshes, mattes the images onto white below VHAP's neck line, and
   writes the FLAME parameters, the transforms files with splits, and ``track/`` (the report, a contact
   sheet, the embedding, the landmarks, the resolved config).

Everything is written into a hidden sibling folder that replaces OUT only at the end, so a failure
leaves nothing half-written (and an earlier OUT untouched). ``track/report.json`` is written last.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import ConfigError, InputError
from .config import TrackConfig, to_dict

Progress = Callable[..., None]
REPORT_FORMAT = "sage-track-report-v1"
SMALL_IMAGE_HEIGHT = 186
"""Written images less tall than this (the tiny preset's synthetic captures) get a warning: the face
spans few pixels of the input."""


@dataclass
class TrackResult:
    """What ``sage track`` wrote and measured.

    Attributes:
        out_dir: the capture folder. regime: the regime it was written for; kind: the input's kind.
        timesteps: timesteps written; images: images written; splits: frames per split.
        dropped: images without a usable face (dicts: timestep_id, view, kind, message).
        reprojection_px / reprojection_max_px: mean and largest landmark error (output pixels).
        focal_px: fitted or given focal length of an uncalibrated camera (output pixels), else None.
        focal_source: "given", "exif", "fitted", "assumed" or "calibrated".
        masks: how the person masks were made -> count ("keyed" on a uniform background, "segmented").
        calibration: the landmark calibration's numbers, or None when an embedding file was given.
        timings: phase -> seconds; wall_time_s: total.
        warnings: non-fatal findings.
        per_image: one dict per written image (timestep, timestep_id, camera_index, landmarks,
            reprojection_px, reprojection_max_px).
        cameras: one dict per camera: index, name, crop window in input pixels (x0, y0, w, h), output
            size, focal length in input pixels.
        rig_scale: the fitted scale of a calibrated rig (1 when fixed); losses: the fit's final losses.
        steady_pivot: whether the head's pivot was held steady (``TrackConfig.steady_pivot``): mode
            ("on", "off", "auto"; "off" where it does not apply: one image, a rig), held (bool), and for
            auto the pivot's spread over the frames fitted without it and the scale it was held within.
        focal_refit: when a fitted focal length was held for a second fit (``TrackConfig.focal_refit``):
            the first fit's focal lengths (output pixels) and its seconds, both fits' mean landmark errors
            (``landmark_px``: first, second), whether they were compared (``landmarks_compared``: both
            fits with a pose table or both without) and the fit kept (``kept``: "first" or "second",
            :func:`refit_kept`); else None.
    """

    out_dir: Path
    regime: str
    kind: str
    timesteps: int
    images: int
    splits: dict[str, int]
    dropped: list[dict[str, str]]
    reprojection_px: float
    reprojection_max_px: float
    focal_px: float | None
    focal_source: str
    masks: dict[str, int]
    calibration: dict[str, Any] | None
    timings: dict[str, float]
    wall_time_s: float
    warnings: list[str] = field(default_factory=list)
    per_image: list[dict[str, Any]] = field(default_factory=list)
    rig_scale: float = 1.0
    losses: dict[str, float] = field(default_factory=dict)
    cameras: list[dict[str, Any]] = field(default_factory=list)
    steady_pivot: dict[str, Any] = field(default_factory=dict)
    focal_refit: dict[str, Any] | None = None

    def rows(self) -> list[tuple[str, str]]:
        """(label, value) lines for the closing panel."""
        rows = [
            ("regime", self.regime),
            ("input", self.kind),
            ("timesteps / images", f"{self.timesteps} / {self.images}"),
            ("train / val / test", " / ".join(str(self.splits.get(k, 0)) for k in ("train", "val", "test"))),
            ("dropped", str(len(self.dropped)) + (f" ({', '.join(f'{k} {n}' for k, n in Counter(d['kind'] for d in self.dropped).items())})"
                                                  if self.dropped else "")),
            ("landmark error", f"mean {self.reprojection_px:.2f} px, max {self.reprojection_max_px:.1f} px"),
            ("focal length", (f"{self.focal_px:.1f} px ({self.focal_source}"
                              + ((", then held for a second fit" if self.focal_refit.get("kept") == "second"
                                  else ", the first fit kept over a second with it held") if self.focal_refit else "") + ")")
             if self.focal_px is not None else self.focal_source),
            ("masks", ", ".join(f"{k} {n}" for k, n in self.masks.items())),
            ("wall time", f"{self.wall_time_s:.1f} s"),
        ]
        sp = self.steady_pivot
        if sp.get("mode", "off") != "off":
            spread = f" (spread {100 * sp['spread']:.2f} % of its distance, held within {100 * sp['scale']:g} %)" if "spread" in sp else ""
            rows.insert(len(rows) - 2, ("head's pivot", ("held" if sp["held"] else "free") + f", {sp['mode']}{spread}"))
        if self.calibration is not None:
            c = self.calibration
            rows.insert(6, ("landmark embedding", f"calibrated: {c['kept']} landmarks from {c['views_with_face']}/{c['views']} views"))
        rows += [("warning", w) for w in self.warnings]
        return rows


def face_only_silhouette(mode: str, focal_fitted: bool) -> bool:
    """Whether the silhouette pulls only the face and neck outline both ways (the rest only inwards).

    mode: ``TrackConfig.silhouette_two_sided`` (face, all, auto); focal_fitted: a camera's focal length
    is being fitted. ``auto`` is face-only unless a focal length is fitted: with the scalp pulled only
    inwards a fitted focal length drifted (monocular clip −22 % → −26 %), while with it known face-only
    lowered every error (docs/track.md).
    """
    return mode == "face" or (mode == "auto" and not focal_fitted)


def focal_refit_rule(mode: str, focal_fitted: bool, sequence: bool, pivot_held: bool) -> bool:
    """Whether a fit that fitted a focal length is followed by a second fit with that focal length held
    (and so, with ``silhouette_two_sided=auto``, the face-only silhouette of a known focal length, and
    for a sequence no pose table, :func:`landmark_pose_rule`).

    mode: ``TrackConfig.focal_refit`` (auto, on, off); focal_fitted: a camera's focal length was
    fitted; sequence: one camera's video or folder of several frames; pivot_held: the first fit held
    the head's pivot (``TrackConfig.steady_pivot``). ``on`` refits; ``auto`` refits one photo, and a
    sequence whose pivot was held, and keeps the second fit when its landmark error is lower, or the
    two errors do not compare (:func:`refit_kept`). While the focal length is free the whole outline
    is pulled both ways, and that pulls the head onto its hair (the synthetic photo's face 8 % too
    large, the landmarks 3.1 px off); holding the focal length found and fitting again as with a known
    one puts the face where the images have it: the synthetic one-shot avatar 3.88 dB behind the
    capture's own parameters before, 0.41 dB after; the 11-frame clip 7.54 → 5.64 mm after one
    similarity (mean of three seeds), its avatar +0.75 → +1.42 dB over the own parameters'; the 20-s
    head-turn video with hair 7.16 → 4.29 mm. With the pivot free the face-only outline leaves each
    frame's depth to itself: the same video with the head drifting ±30 mm went 10.56 → 19.47 mm. On
    the bare synthetic head, whose outline is its skull, the whole outline's first fit was the better
    one (the video 3.42 mm against 5.65; docs/track.md, "Limits").
    """
    return focal_fitted and (mode == "on" or (mode == "auto" and (not sequence or pivot_held)))


def landmark_error(fit: Any) -> float:
    """Mean landmark reprojection error of a fit over its images with landmarks (output pixels; inf
    without any)."""
    px = np.asarray(fit.reprojection_px, np.float64)
    px = px[np.isfinite(px)]
    return float(px.mean()) if px.size else float("inf")


def refit_kept(mode: str, first_px: float, second_px: float, comparable: bool = True) -> bool:
    """Whether the second fit of ``focal_refit`` is kept: always when asked for (on); with ``auto`` when
    its landmark error is lower than the first fit's, where the two are ``comparable`` (both fits
    measured their landmarks against the same points: with a pose table in both or in neither), and
    otherwise always. A sequence's first fit follows the detector's lean with the pose table and its
    second does not (:func:`landmark_pose_rule`); the table lets the landmarks lie closer on a worse
    mesh (the synthetic head-turn video with hair 4.43 px and 7.16 mm after one similarity against
    4.98 px and 4.29 mm), so there the errors are not compared. For one photo, which mask's outline
    lies better decides: the face-only silhouette lowers the landmark and the vertex error on the
    synthetic photo matted on white (3.11 → 1.78 px, 3.25 → 1.98 mm after one similarity) and the
    landmark error on the real astronaut photo (4.63 → 3.16 px); over photographs whose colour cut
    trims the hair from the mask it raises both (coffee 1.74 → 2.31 px, 1.92 → 3.13 mm; rocket 1.80 →
    2.05 px, 2.05 → 2.90 mm), and there the whole outline's first fit is kept (docs/track.md)."""
    return mode == "on" or not comparable or second_px < first_px


def _one_camera_sequence(kind: str, n_timesteps: int) -> bool:
    """A video or a folder of several frames: one uncalibrated camera that sees the head move."""
    return kind in ("video", "images") and n_timesteps >= 2


def steady_depth_rule(enabled: bool, kind: str, n_timesteps: int) -> bool:
    """Whether the head's distance from the camera (or with ``TrackConfig.steady_pivot`` its pivot's
    whole position; for its auto mode, whether the fit decides) is held steady over the frames: when
    asked for (``TrackConfig.steady_depth``, ``steady_pivot``), for a video or a folder of several
    frames from one camera (a rig places the head itself; one image has nothing to agree with)."""
    return enabled and _one_camera_sequence(kind, n_timesteps)


def landmark_pose_rule(mode: str, kind: str, n_timesteps: int, whole_outline: bool) -> bool:
    """Whether the landmarks follow the detector's lean with the pose (``TrackConfig.landmark_pose``):
    on / off as asked; auto: for a video or a folder of several frames from one camera whose fit pulls
    the whole outline both ways (``whole_outline``: a fitted focal length with
    ``silhouette_two_sided=auto``, or ``all``). There the lean turns every fitted frame back towards
    the camera by the same share (pitch by about 15 %), which nothing else in one camera's view
    corrects. With the face-only silhouette (a known focal length: EXIF, ``focal``, or the second fit
    of ``focal_refit``) the table traded against the head's depth instead: the synthetic clip 4.66 mm
    off without it against 5.24 with it (mean of three seeds), the camera 5.3 mm against 10.7, the
    head-turn video with hair 4.39 mm without it; the bare head's video with the whole outline and its
    focal length given 3.56 mm with it against 4.22. A calibrated rig's views hold the pose, and on
    one photo the table did not lower the error (docs/track.md)."""
    return mode == "on" or (mode == "auto" and whole_outline and _one_camera_sequence(kind, n_timesteps))


def infer_regime(kind: str, n_timesteps: int) -> str:
    """The regime an input suggests: one image -> one-shot, a sequence -> sv-hr, a rig -> mv-sf / mv-mf."""
    if kind == "multiview":
        return "mv-sf" if n_timesteps == 1 else "mv-mf"
    return "one-shot" if kind == "image" or n_timesteps == 1 else "sv-hr"


def resolve_regime(regime: str | None, kind: str, n_timesteps: int) -> str:
    """The regime to write: the one asked for (an alias of :data:`REGIME_ALIASES` resolved; ``mv`` by
    the input's timesteps), or the input's own (:func:`infer_regime`)."""
    from .config import REGIME_ALIASES

    regime = REGIME_ALIASES.get(regime, regime) if regime else None
    if regime is None:
        return infer_regime(kind, n_timesteps)
    if regime == "mv":
        return "mv-sf" if n_timesteps == 1 else "mv-mf"
    return regime


def check_regime(regime: str, kind: str, n_timesteps: int, source: Path) -> None:
    """ConfigError when the regime does not fit the input."""
    if regime in ("mv-sf", "mv-mf") and kind != "multiview":
        raise ConfigError(f"regime {regime} needs calibrated cameras: a folder of camera folders and --cameras "
                          f"(the input {source} is {'one image' if kind == 'image' else 'one camera'})")
    if regime in ("one-shot", "sv-hr") and kind == "multiview":
        raise ConfigError(f"regime {regime} takes one camera; the input {source} has calibrated cameras (use mv-sf or mv-mf)")
    if regime == "one-shot" and n_timesteps != 1:
        raise ConfigError(f"regime one-shot takes one image; the input {source} holds {n_timesteps} frames "
                          "(use sv-hr, or --set max_frames=1)")
    if regime == "sv-hr" and n_timesteps < 2:
        raise ConfigError(f"regime sv-hr needs several frames of one camera; the input {source} holds one image (use one-shot)")


def _output_folder(out_dir: str | Path, input_path: str | Path) -> Path:
    """OUT as an absolute path (``.`` and ``..`` resolved). The finished capture takes OUT's place as
    a whole (the old folder is moved aside and deleted), so ConfigError when OUT is the current
    folder or holds it (the shell would be left in a deleted folder) or holds the input."""
    out = Path(os.path.abspath(Path(out_dir).expanduser()))
    real = Path(os.path.realpath(out))
    try:
        here: Path | None = Path(os.path.realpath(os.getcwd()))
    except OSError:  # the current folder was deleted
        here = None
    if here is not None and (real == here or real in here.parents):
        raise ConfigError(f"the output folder {out_dir} is the current folder or holds it; sage track puts a new folder "
                          f"in its place: give a folder to create, e.g. {Path(out_dir) / 'capture'}")
    source = Path(os.path.realpath(Path(input_path).expanduser()))
    if real in source.parents:
        raise ConfigError(f"the output folder {out_dir} holds the input {input_path}; sage track replaces the output "
                          "folder as a whole: give a folder elsewhere")
    return out


def _prepare_out(out: Path, force: bool) -> Path:
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise ConfigError(f"{out} is not empty; pass --force to replace it")
    tmp = out.with_name(f".{out.name}.track-tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    return tmp


def _promote(tmp: Path, out: Path) -> None:
    from ..atomic import replace_dir

    replace_dir(tmp, out, "track")


def track_capture(
    input_path: str | Path,
    out_dir: str | Path,
    flame_model: str | Path,
    cfg: TrackConfig,
    *,
    cameras: str | Path | None = None,
    flame_masks: str | Path | None = None,
    landmark_embedding: str | Path | None = None,
    models_dir: str | Path | None = None,
    device: str = "cpu",
    seed: int = 0,
    force: bool = False,
    progress: Progress | None = None,
) -> TrackResult:
    """Track ``input_path`` into a capture at ``out_dir`` (see the module docstring).

    flame_model: FLAME-format model (pickle or the project's npz). cameras: calibration file of a
    multiview input. flame_masks: region masks (default: ``FLAME_masks.pkl`` beside the model; its
    ``scalp`` region enables the hair offsets). landmark_embedding: a MediaPipe landmark embedding for
    this model (default: calibrated). models_dir: folder of the MediaPipe models (default:
    ``$SAGE_MEDIAPIPE_DIR``, then the cache). device: torch device of the fit. progress:
    ``progress(done, total, message, **stats)``.
    Raises ConfigError (options, regime, an occupied OUT, an OUT that is the current folder or
    holds the input) or InputError (a file or image) before writing anything.
    """
    from ..flame import FlameModel, load_flame_model, load_masks
    from .faces import FaceObserver
    from .inputs import read_source
    from .litert import litert_available
    from .observe import observe
    from .weights import find_models

    t_start = time.time()
    timings: dict[str, float] = {}
    out = _output_folder(out_dir, input_path)
    reason = litert_available()
    if reason is not None:
        raise ConfigError(reason)
    models = find_models(models_dir)
    model_path = Path(flame_model)
    model = load_flame_model(model_path)
    masks_file = Path(flame_masks) if flame_masks is not None else (model_path.parent / "FLAME_masks.pkl")
    groups: dict[str, np.ndarray] = {}
    if flame_masks is not None or masks_file.is_file():
        groups = {k: np.asarray(v) for k, v in load_masks(masks_file).items()}
        bad = [k for k, v in groups.items() if v.size and int(v.max()) >= model.n_vertices]
        if bad:
            raise InputError(masks_file, f"region '{bad[0]}' names vertices beyond the model's {model.n_vertices}")
    emb_given = None
    if landmark_embedding is not None:
        from .embedding import load_embedding

        emb_given = load_embedding(landmark_embedding, model.n_faces)
    source = read_source(input_path, cameras, cfg.fps, cfg.max_frames)
    regime = resolve_regime(cfg.regime, source.kind, len(source.timesteps))
    check_regime(regime, source.kind, len(source.timesteps), source.path)
    if out.resolve() == source.path.resolve() or source.path.resolve() in out.resolve().parents:
        raise ConfigError(f"the output folder {out} lies inside the input {source.path}")
    observer = FaceObserver(models, cfg.min_detection_score, cfg.min_presence, cfg.min_face_px, cfg.second_face_ratio,
                            cfg.max_roll_deg, cfg.threads, cfg.max_outside)

    t0 = time.time()
    obs = observe(source, observer, cfg, progress)
    timings["faces"] = time.time() - t0
    if regime == "sv-hr" and len(obs.kept) < 2:
        raise InputError(source.path, f"only {len(obs.kept)} frame shows a usable face; sv-hr needs several (use one-shot)")

    tmp = _prepare_out(out, force)
    try:
        flame = FlameModel(model).to(device)
        result = _track(source, obs, flame, model, groups, emb_given, observer, models, cfg, regime, tmp, device, seed,
                        progress, timings)
        result.out_dir = out
        result.warnings = list(source.warnings) + result.warnings
        _write_report(tmp, result, source, cfg, model_path, masks_file if groups else None, cameras, landmark_embedding,
                      device, seed, t_start)
        _promote(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    result.wall_time_s = time.time() - t_start
    return result


def _second_fit(flame: Any, fitter: Any, fit: Any, problem: Any, face_neck: np.ndarray | None, pivot_held: bool,
                cfg: TrackConfig, progress: Progress | None, seed: int, first_s: float,
                pose_table: bool) -> tuple[Any, Any, dict[str, Any]]:
    """``focal_refit``: the fit of ``fitter`` (whose result is ``fit``, ``first_s`` seconds) fitted again
    from the start with its focal lengths held, as with known ones: the face-only silhouette
    (``face_neck``: (V,) bool, the vertices pulled both ways; None, the whole outline), the pose table
    only with ``pose_table``, and the head's pivot held as the first fit decided (``pivot_held``; its
    check is not run twice). Returns the fitter and fit kept (:func:`refit_kept`) and the report's
    ``focal_refit`` entry."""
    from .fitting import Fitter, FitCamera

    held = [FitCamera(fc.K.copy(), c.w2c, c.width, c.height, fit_focal=False) for fc, c in zip(fit.cameras, problem.cameras)]
    problem = replace(problem, cameras=held, silhouette_inward=None if face_neck is None else ~face_neck,
                      silhouette_outward_max=None if face_neck is None else cfg.silhouette_outward_max,
                      steady_pivot=pivot_held, steady_pivot_auto=False)
    emb = fitter.emb if pose_table or fitter.emb.pose is None else replace(fitter.emb, pose=None)
    # the two fits' landmark errors compare only when both measure them against the same points
    compared = (fitter.emb.pose is None) == (emb.pose is None)
    second_fitter = Fitter(flame, emb, problem, cfg, progress, seed=seed)
    second = second_fitter.run()
    # the pivot's check and its cost belong to the first fit; its stages' times kept beside the second's
    second = replace(second, pivot_check=dict(fit.pivot_check),
                     timings={**{f"first_{k}": v for k, v in fit.timings.items()}, **second.timings})
    px = [landmark_error(fit), landmark_error(second)]
    kept = "second" if refit_kept(cfg.focal_refit, *px, comparable=compared) else "first"
    report = {"focal_px": [float(c.K[0, 0]) for c in fit.cameras], "fit_s": round(first_s, 1),
              "landmark_px": [round(x, 3) for x in px], "landmarks_compared": compared, "kept": kept}
    return (second_fitter, second, report) if kept == "second" else (fitter, fit, report)


def _track(source: Any, obs: Any, flame: Any, model: Any, groups: dict[str, np.ndarray], emb_given: Any, observer: Any,
           models: Any, cfg: TrackConfig, regime: str, root: Path, device: str, seed: int, progress: Progress | None,
           timings: dict[str, float]) -> TrackResult:
    import cv2
    import torch

    from ..data.cameras import Camera
    from ..data.imageio import write_image
    from .capture_writer import OutFrame, write_flame_params, write_transforms
    from .embedding import calibrate_embedding, same_landmarks, save_embedding
    from .fitting import FitCamera, FitImage, FitProblem, Fitter
    from .masks import neck_line_mask, person_colour_cut, person_probability, refine_mask, wants_colour_cut
    from .mesh_utils import boundary_loops, hair_region, neck_line_vertices, ring
    from .observe import MONOCULAR_W2C, crop_window, focal_for
    from .report import contact_sheet, overlay_tile
    from .segmenter import Segmenter

    warnings: list[str] = []
    t_row = {t: i for i, t in enumerate(obs.kept)}
    original = {t: i for i, t in enumerate(source.timesteps)}
    # -- cameras and crop windows
    windows, out_cams, fit_cams = [], [], []
    focal_source = "calibrated"
    for vi, view in enumerate(source.views):
        size = obs.sizes.get(vi, (view.width, view.height))
        boxes = [f.box() for (v, t), f in obs.faces.items() if v == vi]
        win = crop_window(boxes, size, cfg)
        if win.out_h < SMALL_IMAGE_HEIGHT:
            faces_h = [f.face_height for (v, t), f in obs.faces.items() if v == vi]
            warnings.append(f"{'view ' + view.name + ': ' if len(source.views) > 1 else ''}the face is about "
                            f"{np.median(faces_h):.0f} px tall (forehead to chin) in the input, so the written images are "
                            f"{win.out_w}x{win.out_h} (crops are never enlarged): the avatar will show little detail; "
                            "a closer or larger picture gives more")
        if view.calibrated is not None:
            K, w2c = view.calibrated.K, view.calibrated.w2c
        else:
            f, focal_source = focal_for(source, vi, size, cfg)
            K = np.array([[f, 0, size[0] / 2], [0, f, size[1] / 2], [0, 0, 1.0]])
            w2c = MONOCULAR_W2C
        cam = win.camera(K, w2c, view.index, view.name if source.kind == "multiview" else "monocular")
        windows.append(win)
        out_cams.append(cam)
        fit_cams.append(FitCamera(cam.K, cam.w2c, cam.width, cam.height, fit_focal=view.calibrated is None and focal_source == "fitted"))

    # -- second pass: crop, write raw images, person masks at the fit resolution
    seg = Segmenter(str(models.segmenter), cfg.threads)
    images: list[FitImage] = []
    frames: list[OutFrame] = []
    raw = root / ".raw"  # cropped images until the fitted meshes refine their masks
    raw.mkdir()
    mask_kinds: Counter[str] = Counter()
    colour_cut_frames: set[str] = set()  # images whose person pixels are checked by colour, before and after the fit
    total = sum(1 for vi in range(len(source.views)) for t in obs.kept if t in source.views[vi].files or source.kind == "video")
    done = 0
    t0 = time.time()
    for vi, view in enumerate(source.views):
        win = windows[vi]
        for t, img in source.frames(vi):
            if t not in t_row:
                continue
            ti = t_row[t]
            out_img = win.apply(img)
            of = OutFrame(ti, out_cams[vi].index, out_cams[vi].name, out_cams[vi], t, original[t])
            np.save(raw / f"{of.name}.npy", (np.clip(out_img, 0, 1) * 65535).astype(np.uint16))
            person, how = person_probability(out_img, seg(out_img))
            face = obs.faces.get((vi, t))
            lm = None if face is None else win.points(face.landmarks)
            fh = float(face.face_height * win.out_h / win.h) if face is not None else 1.0
            cut = wants_colour_cut(cfg.mask_colour_cut, how)
            if cut and lm is not None:
                person = person_colour_cut(out_img, person, lm, fh)
            np.save(raw / f"{of.name}.person.npy", np.round(np.clip(person, 0, 1) * 255).astype(np.uint8))  # reused by the masks
            if cut:
                colour_cut_frames.add(of.name)
            mask_kinds[how] += 1
            h = min(cfg.fit_height, out_img.shape[0])
            w = max(1, int(round(out_img.shape[1] * h / out_img.shape[0])))
            small = cv2.resize(out_img, (w, h), interpolation=cv2.INTER_AREA)
            small_p = cv2.resize(person, (w, h), interpolation=cv2.INTER_AREA)
            images.append(FitImage(ti, vi, lm, fh, small.astype(np.float32), small_p.astype(np.float32)))
            frames.append(of)
            done += 1
            if progress is not None:
                progress(done, total, "cropping and segmenting")
    timings["images"] = time.time() - t0

    # -- landmark embedding (whether it has a pose table follows the silhouette's outline rule)
    t0 = time.time()
    calibration = None
    focal_fitted = any(c.fit_focal for c in fit_cams)
    V = model.n_vertices
    # the outline vertices a face-only silhouette pulls both ways: the FLAME masks' face and neck (None
    # without a face region); every other outline vertex it pulls only inwards
    face_neck = None
    if len(groups.get("face", [])):
        face_neck = np.zeros(V, bool)
        for k in ("face", "neck"):
            face_neck[np.asarray(groups.get(k, []), np.int64)] = True
    face_only = face_only_silhouette(cfg.silhouette_two_sided, focal_fitted=focal_fitted)
    inward = ~face_neck if face_only and face_neck is not None else None
    pose_on = landmark_pose_rule(cfg.landmark_pose, source.kind, len(obs.kept), whole_outline=inward is None)
    pivot = steady_depth_rule(cfg.steady_pivot == "on", source.kind, len(obs.kept))
    pivot_auto = steady_depth_rule(cfg.steady_pivot == "auto", source.kind, len(obs.kept))
    pivot_emb = None
    if emb_given is not None:
        emb = emb_given
    else:
        with torch.no_grad():
            neutral = flame(jaw_pose=torch.tensor([[cfg.calib_jaw, 0.0, 0.0]], device=flame.v_template.device)).vertices[0]

        def calibrate(pose_yaw_deg: float) -> tuple[Any, Any]:
            return calibrate_embedding(neutral.cpu(), flame.faces.cpu(), observer, size=cfg.calib_size,
                                       yaw_deg=cfg.calib_yaw_deg, pitch_deg=cfg.calib_pitch_deg, n_yaw=cfg.calib_views,
                                       spread_frac=cfg.calib_spread, min_views_frac=cfg.calib_min_views,
                                       pose_yaw_deg=pose_yaw_deg, pose_pitch_deg=cfg.calib_pose_pitch_deg,
                                       pose_table=pose_on, progress=progress)

        emb, rep = calibrate(cfg.calib_pose_yaw_deg)
        calibration = rep.to_dict()
        if pose_on and (pivot or pivot_auto) and cfg.pivot_pose_yaw_deg > cfg.calib_pose_yaw_deg:
            # the wider table of a held pivot: the same landmarks (the embedding comes from the narrower views)
            wide, wide_rep = calibrate(cfg.pivot_pose_yaw_deg)
            if same_landmarks(wide, emb):
                calibration["pivot_pose_views"] = wide_rep.pose_views
                emb, pivot_emb = (wide, None) if pivot else (emb, wide)
            else:  # never seen: the wider grid's calibration kept other landmarks
                warnings.append("the wider pose table of a held pivot kept other landmarks than the embedding; not used")
    if emb.pose is not None and not pose_on:
        emb = replace(emb, pose=None)
    (root / "track").mkdir(exist_ok=True)
    timings["embedding"] = time.time() - t0

    # -- fit
    t0 = time.time()
    hair = hair_region(groups, V) if cfg.scalp_offsets else None
    if cfg.scalp_offsets and hair is None:
        warnings.append("no 'scalp' region in the FLAME masks: hair volume (static offsets) not fitted")
    loops = boundary_loops(model.faces)
    exclude = ring(model.faces, loops[0], V, 2) if loops else np.zeros(V, bool)
    several_views = source.kind == "multiview" or len(obs.kept) >= 3
    lmk_offsets = cfg.landmark_offsets == "on" or (cfg.landmark_offsets == "auto" and several_views)
    smooth = source.kind == "video" or (source.kind == "images" and cfg.smooth_sequences)
    steady = steady_depth_rule(cfg.steady_depth, source.kind, len(obs.kept))
    rig_scale = source.kind == "multiview" and (cfg.rig_scale == "fit" or (cfg.rig_scale == "auto" and not source.metric))
    problem = FitProblem(fit_cams, images, len(obs.kept), fit_rig_scale=rig_scale, smooth=smooth, hair=hair,
                         silhouette_exclude=exclude, silhouette_inward=inward,
                         silhouette_outward_max=cfg.silhouette_outward_max if inward is not None else None,
                         hair_stage=cfg.hair_fit == "on",
                         landmark_offsets=lmk_offsets,
                         camera_relative=source.kind != "multiview", steady_depth=steady,
                         steady_pivot=pivot, steady_pivot_auto=pivot_auto)
    fitter = Fitter(flame, emb, problem, cfg, progress, seed=seed, pivot_embedding=pivot_emb)
    fit = fitter.run()
    focal_refit = None
    pivot_held = pivot or bool(fit.pivot_check.get("held"))
    if focal_refit_rule(cfg.focal_refit, focal_fitted, _one_camera_sequence(source.kind, len(obs.kept)), pivot_held):
        fitter, fit, focal_refit = _second_fit(
            flame, fitter, fit, problem, face_neck, pivot_held, cfg, progress, seed, time.time() - t0,
            pose_table=landmark_pose_rule(cfg.landmark_pose, source.kind, len(obs.kept), whole_outline=face_neck is None))
    save_embedding(root / "track" / "landmark_embedding.npz", fitter.emb)  # the one the fit ended with
    timings["fit"] = time.time() - t0
    timings.update({f"fit_{k}": v for k, v in fit.timings.items()})

    # -- world re-centring of a monocular capture (VHAP): mean translation 0, the camera moves along
    cams = [Camera(c.K, c.w2c, c.width, c.height, oc.index, oc.name) for c, oc in zip(fit.cameras, out_cams)]
    if source.kind != "multiview":
        t_mean = fit.params.translation.mean(0).astype(np.float64)
        fit.params.translation = (fit.params.translation - t_mean).astype(np.float32)
        for c in cams:
            c.w2c = c.w2c.copy()
            c.w2c[:3, 3] = c.w2c[:3, 3] + c.w2c[:3, :3] @ t_mean
    for f in frames:
        f.camera = cams[[oc.index for oc in out_cams].index(f.camera_index)]

    # -- masks and matted images
    t0 = time.time()
    with torch.no_grad():
        verts_all = []
        for chunk in np.array_split(np.arange(len(obs.kept)), max(1, math.ceil(len(obs.kept) / 64))):
            verts_all.append(flame(**fit.params.select(chunk).to_torch(flame.v_template.device)).vertices.cpu())
        verts = torch.cat(verts_all)
    neck_ids = neck_line_vertices(model.v_template, model.faces, model.face_table == "flame" and model.n_base_vertices == 5023)
    from ..render.mesh_raster import rasterize_mesh

    faces_t = flame.faces.cpu()
    for n, (f, im) in enumerate(zip(frames, images)):
        img = np.load(raw / f"{f.name}.npy").astype(np.float32) / 65535.0
        H, W = img.shape[:2]
        v = verts[f.timestep]
        h, w = im.person.shape
        cs = f.camera.resized(w, h)
        with torch.no_grad():
            r = rasterize_mesh(v, faces_t, torch.as_tensor(cs.K, dtype=v.dtype), torch.as_tensor(cs.w2c, dtype=v.dtype), w, h)
        coverage = cv2.resize(r.mask[0].float().numpy(), (W, H), interpolation=cv2.INTER_LINEAR)
        person = np.load(raw / f"{f.name}.person.npy").astype(np.float32) / 255.0
        neck = neck_line_mask(v.double().numpy(), neck_ids, f.camera) if cfg.neck_line else None
        fh = im.face_height if im.landmarks is not None else float(np.sqrt(max(coverage.sum(), 1.0)))
        cut = f.name in colour_cut_frames
        mask_kinds["colour_cut"] += int(cut)
        mask = refine_mask(person, coverage, neck, fh, image=img if cut else None)
        matted = img * mask[..., None] + (1.0 - mask[..., None])
        write_image(root / "images" / f"{f.name}.png", matted)
        write_image(root / "fg_masks" / f"{f.name}.png", mask)
        if progress is not None:
            progress(n + 1, len(frames), "masks and images")
    timings["masks"] = time.time() - t0

    # -- parameters, transforms, report files
    write_flame_params(root, fit.params)
    val_camera = cfg.val_camera
    if val_camera is None and source.kind == "multiview" and len(source.views) > 1:
        idx = [c.index for c in out_cams]
        val_camera = 8 if 8 in idx else None
    splits = write_transforms(root, frames, len(obs.kept), cfg.train_ratio if regime != "one-shot" else 1.0, val_camera)
    if regime == "sv-hr" and splits.get("test", 0) == 0:
        warnings.append("the test split is empty (too few frames for the train ratio)")
    # contact sheet: up to 12 images, evenly over time (and cameras)
    order = np.unique(np.linspace(0, len(frames) - 1, min(12, len(frames))).round().astype(int))
    tiles = []
    lmk_ids = emb.landmark_ids
    with torch.no_grad():
        tri_all = verts[:, faces_t[torch.as_tensor(emb.faces)]].to(flame.v_template.device)
    for i in order:
        f, im = frames[int(i)], images[int(i)]
        img = np.asarray(_read_png(root / "images" / f"{f.name}.png"))
        with torch.no_grad():
            tri = tri_all[f.timestep: f.timestep + 1]
            centre = torch.as_tensor(f.camera.center, dtype=tri.dtype, device=tri.device)[None]
            pts = fitter.landmark_points(tri, fitter.pose_offsets(torch.tensor([f.timestep], device=tri.device), tri, centre))[0]
        uv, _ = f.camera.project(pts.cpu().double().numpy())
        det = im.landmarks[lmk_ids] if im.landmarks is not None else None
        tiles.append(overlay_tile(img, verts[f.timestep], faces_t, f.camera, det, uv))
    write_image(root / "track" / "contact_sheet.png", contact_sheet(tiles, columns=min(3, len(tiles))))
    lm_arr = np.full((len(images), 468, 2), np.nan, np.float32)
    for n, im in enumerate(images):
        if im.landmarks is not None:
            lm_arr[n] = im.landmarks
    with open(root / "track" / ".landmarks.tmp.npz", "wb") as fh_:
        np.savez(fh_, landmarks=lm_arr, timestep=np.array([f.timestep for f in frames]),
                 camera_index=np.array([f.camera_index for f in frames]), reprojection_px=fit.reprojection_px.astype(np.float32))
    os.replace(root / "track" / ".landmarks.tmp.npz", root / "track" / "landmarks.npz")
    shutil.rmtree(raw, ignore_errors=True)

    rep = fit.reprojection_px[np.isfinite(fit.reprojection_px)]
    rep_max = fit.reprojection_max_px[np.isfinite(fit.reprojection_max_px)]
    focal = float(cams[0].K[0, 0]) if source.kind != "multiview" else None
    result = TrackResult(
        out_dir=root, regime=regime, kind=source.kind, timesteps=len(obs.kept), images=len(frames), splits=splits,
        dropped=[d.to_dict() for d in obs.dropped], reprojection_px=float(rep.mean()) if rep.size else float("nan"),
        reprojection_max_px=float(rep_max.max()) if rep_max.size else float("nan"), focal_px=focal,
        focal_source=focal_source, masks=dict(mask_kinds), calibration=calibration, timings=timings, wall_time_s=0.0,
        warnings=warnings, rig_scale=fit.rig_scale, losses=fit.losses,
        steady_pivot={"mode": cfg.steady_pivot if pivot or pivot_auto else "off", "held": pivot_held,
                      **({"spread": fit.pivot_check["spread"], "scale": cfg.steady_depth_scale} if fit.pivot_check else {})},
        focal_refit=focal_refit,
        cameras=[{"index": c.index, "name": c.name, "crop": [win.x0, win.y0, win.w, win.h], "output_size": [win.out_w, win.out_h],
                  "focal_input_px": round(float(c.K[0, 0] * win.w / win.out_w), 3)} for c, win in zip(cams, windows)],
        per_image=[
        {"timestep": f.timestep, "timestep_id": f.timestep_id, "camera_index": f.camera_index, "landmarks": im.landmarks is not None,
         "reprojection_px": None if not np.isfinite(fit.reprojection_px[n]) else round(float(fit.reprojection_px[n]), 3),
         "reprojection_max_px": None if not np.isfinite(fit.reprojection_max_px[n]) else round(float(fit.reprojection_max_px[n]), 3)}
        for n, (f, im) in enumerate(zip(frames, images))],
    )
    return result


def _read_png(path: Path) -> np.ndarray:
    from ..data.imageio import read_image

    return read_image(path)[..., :3]


def _write_report(root: Path, r: TrackResult, source: Any, cfg: TrackConfig, model_path: Path, masks_file: Path | None,
                  cameras: Any, embedding: Any, device: str, seed: int, t_start: float) -> None:
    from .._version import __version__
    from .capture_writer import write_json

    write_json(root / "track" / "config.json", to_dict(cfg))
    doc = {
        "format": REPORT_FORMAT,
        "version": __version__,
        "regime": r.regime,
        "input": {"path": str(source.path), "kind": source.kind, "frames": len(source.timesteps), "fps": source.fps,
                  "cameras_file": None if cameras is None else str(cameras)},
        "flame_model": str(model_path),
        "flame_masks": None if masks_file is None else str(masks_file),
        "landmark_embedding": "track/landmark_embedding.npz (" + ("calibrated" if embedding is None else f"from {embedding}") + ")",
        "calibration": r.calibration,
        "seed": seed,
        "device": device,
        "timesteps": r.timesteps,
        "images": r.images,
        "splits": r.splits,
        "dropped": r.dropped,
        "reprojection_px": {"mean": r.reprojection_px, "max": r.reprojection_max_px,
                            "definition": "per image: mean (max) distance in output pixels between the detected landmarks "
                                          "and the fitted mesh's, over landmarks on triangles facing the camera"},
        "camera": {"focal_px": r.focal_px, "focal_source": r.focal_source, "rig_scale": r.rig_scale, "cameras": r.cameras,
                   "focal_refit": r.focal_refit},
        "steady_pivot": r.steady_pivot,
        "masks": r.masks,
        "losses": r.losses,
        "timings_s": {k: round(v, 2) for k, v in r.timings.items()},
        "wall_time_s": round(time.time() - t_start, 2),
        "warnings": r.warnings,
        "per_image": r.per_image,
    }
    write_json(root / "track" / "report.json", doc)
