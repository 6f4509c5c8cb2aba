"""Configuration of ``sage track``: one flat dataclass, two presets, and its resolution from a
preset, an optional YAML/JSON file and ``--set key=value`` flags (preset < file < flags)."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any

from ..config import parse_bool
from ..errors import ConfigError

REGIMES: tuple[str, ...] = ("mv-sf", "mv-mf", "sv-hr", "one-shot")
"""The regimes ``sage ingest`` and ``sage run`` accept; ``sage track`` writes a capture for one of them."""
REGIME_ALIASES: dict[str, str] = {"mv": "mv", "multiview": "mv", "monocular": "sv-hr", "oneshot": "one-shot"}
"""Other spellings ``--regime`` takes: ``mv`` (or ``multiview``) is mv-sf for one timestep of a rig and
mv-mf for several; ``monocular`` and ``oneshot`` are the ``sage synth`` names."""
TRACK_PRESETS: tuple[str, ...] = ("tiny", "default")
FOLLOW_MODES: tuple[str, ...] = ("off", "fallback", "first")
"""``follow_landmarks``: how a sequence's frame may use the previous frame's landmarks (:mod:`.faces`)."""


def _opt(default: Any, help: str, **meta: Any) -> Any:
    """A field with its help text and allowed values (``choices``, ``ge``, ``gt``, ``le``, ``lt``), in the
    metadata layout :func:`sage_core.config.validate_config` and ``describe`` read."""
    return field(default=default, metadata={"help": help, **{k: (tuple(v) if k == "choices" else v) for k, v in meta.items()}})


@dataclass
class TrackConfig:
    """``sage track``: FLAME parameters, cameras and masks from images or a video."""

    regime: str | None = _opt(None, "Regime of the capture written: one-shot (one image), sv-hr (one camera, several frames), "
                                    "mv-sf / mv-mf (calibrated cameras; needs a cameras file), mv (mv-sf or mv-mf by the "
                                    "number of timesteps). None: from the input.",
                              choices=REGIMES + tuple(REGIME_ALIASES))
    # -- input ---------------------------------------------------------------------------------
    fps: float | None = _opt(None, "Video: track this many frames per second (None: every frame).", gt=0)
    max_frames: int | None = _opt(None, "Track at most this many frames, evenly spaced (None: all).", ge=1)
    focal: float | None = _opt(None, "Focal length of an uncalibrated camera in pixels of the input images (None: from EXIF, else fitted).", gt=0)
    focal_init: float = _opt(1.2, "Initial focal length of an uncalibrated camera without EXIF, as a multiple of the image's longer side.", gt=0)
    fit_focal: bool = _opt(True, "Fit the focal length of an uncalibrated camera without a known one (EXIF or focal).")
    rig_scale: str = _opt("auto", "Scale of calibrated cameras: fixed (already in metres), fit (one scale factor fitted to the head), "
                                  "auto (fixed for VHAP transforms, fit for COLMAP and NeRF files).", choices=("auto", "fixed", "fit"))
    # -- faces -----------------------------------------------------------------------------------
    min_detection_score: float = _opt(0.5, "Face detector confidence below which a face is ignored.", gt=0, lt=1)
    min_presence: float = _opt(0.5, "Landmark face-presence probability below which a frame counts as a missed detection.", gt=0, lt=1)
    min_face_px: float = _opt(40.0, "A face narrower than this (pixels of the input image) is refused as too small; the tiled search "
                                      "for faces the whole image misses looks down to this width.", gt=0)
    second_face_ratio: float = _opt(0.5, "Another face at least this fraction of the main face's width makes the image ambiguous.", gt=0, le=1)
    max_roll_deg: float = _opt(45.0, "Refuse faces turned further than this in the image plane (a sideways photo).", gt=0, le=180)
    max_outside: float = _opt(0.5, "Refuse a face with more than this fraction of its landmarks beyond the image's edge (a "
                                    "sequence's frame is dropped): where the face leaves the picture the landmark model guesses.",
                              gt=0, le=1)
    follow_landmarks: str = _opt("fallback", "Video and folder of frames: look for the face on the crop the previous frame's "
                                             "landmarks give (as MediaPipe's face mesh follows a face). fallback: only when the "
                                             "detector's crop yields no usable face (near profile); first: before the detector, "
                                             "which then runs only when the face is lost; off: every frame from its detection.",
                                 choices=FOLLOW_MODES)
    max_dropped: float = _opt(0.5, "Fail when more than this fraction of the frames has no usable face.", ge=0, le=1)
    # -- crop and output -----------------------------------------------------------------------
    crop: bool = _opt(True, "Crop every camera's images to a window around the head (cx, cy follow).")
    crop_scale: float = _opt(3.0, "Height of the crop window in face heights (forehead-to-chin landmark extent).", gt=1)
    crop_aspect: float = _opt(550 / 802, "Width / height of the crop window (NeRSemble exports: 550/802).", gt=0.2, le=5)
    max_height: int = _opt(802, "Largest height of the written images in pixels (larger crops are shrunk, never enlarged).", ge=32)
    train_ratio: float = _opt(0.7, "Fraction of the timesteps (the first ones) in train/val; the rest is the test split (VHAP's rule).", gt=0, le=1)
    val_camera: int | None = _opt(None, "Camera index held out as val in multiview captures (None: 8 when present, else none).", ge=0)
    neck_line: bool = _opt(True, "Blank the image below the fitted mesh's neck line, as VHAP exports do.")
    # -- landmark correspondence ---------------------------------------------------------------
    calib_yaw_deg: float = _opt(30.0, "Calibration: largest yaw of the rendered views (degrees).", ge=0, le=60)
    calib_pitch_deg: float = _opt(12.0, "Calibration: largest pitch of the rendered views (degrees).", ge=0, le=45)
    calib_views: int = _opt(5, "Calibration: yaw steps (the views are yaw steps x 3 pitches).", ge=1, le=15)
    calib_size: int = _opt(320, "Calibration: rendered image size in pixels.", ge=128, le=1024)
    calib_jaw: float = _opt(0.0, "Calibration: jaw opening of the rendered head (radians), so the inner lips separate.", ge=0, le=0.5)
    landmark_pose: str = _opt("auto", "Let the landmarks slide over the face with the head's pose relative to the camera, as the "
                                      "detector's do (it leans towards a frontal face: uncorrected, a turned or pitched head is "
                                      "fitted turned too little), from the calibrated embedding's pose table: on, off, or auto "
                                      "(on for one camera that sees the head turn, a video or a folder of frames, while the whole "
                                      "outline is pulled both ways: a fitted focal length, or silhouette_two_sided=all; with the "
                                      "face-only silhouette of a known focal length the table traded against the head's depth, a "
                                      "calibrated rig holds the pose by itself and one photo showed no gain, docs/track.md).",
                              choices=("auto", "on", "off"))
    calib_pose_yaw_deg: float = _opt(45.0, "Calibration: the pose table's views continue the yaw steps out to this yaw (degrees).", ge=0, le=75)
    pivot_pose_yaw_deg: float = _opt(60.0, "Calibration: with the head's pivot held (steady_pivot on, or auto when the frames agree "
                                           "on it) the pose table continues out to this yaw instead (degrees; a value no wider than "
                                           "calib_pose_yaw_deg adds nothing). With the pivot free a wider table traded against "
                                           "the head's depth and focal length (docs/track.md).", ge=0, le=75)
    calib_pose_pitch_deg: float = _opt(24.0, "Calibration: ... and the pitch steps out to this pitch (degrees).", ge=0, le=45)
    calib_spread: float = _opt(0.035, "Calibration: keep a landmark whose back-projections agree within this fraction of the head height.", gt=0)
    calib_min_views: float = _opt(0.6, "Calibration: keep a landmark seen on the surface in at least this fraction of the views.", gt=0, le=1)
    # -- fitting -------------------------------------------------------------------------------
    shape_components: int = _opt(100, "Identity components fitted (the model's leading ones).", ge=0)
    expr_components: int = _opt(50, "Expression components fitted (the model's leading ones).", ge=0)
    rigid_steps: int = _opt(150, "Adam steps of the rigid pose (and focal) fit on the landmarks.", ge=0)
    steps: int = _opt(400, "Adam steps of the full fit (shape, expression, jaw, eyes, neck, pose, scalp offsets) on landmarks and silhouettes.", ge=0)
    refine_steps: int = _opt(60, "Adam steps with the photometric term added.", ge=0)
    hair_fit: str = _opt("on", "With the face-only silhouette (a known focal length, or the second fit of focal_refit), end the "
                               "fit by fitting the hair volume (the scalp offsets) alone to the whole outline, both ways, the "
                               "head's shape and pose held: on or off. Measured in docs/track.md: sharper avatars from the "
                               "synthetic photo, clip and rig, the scalp further from the synthetic truth's thin hair shell.",
                         choices=("on", "off"))
    hair_steps: int = _opt(100, "Adam steps of that hair-volume fit.", ge=0)
    refine_batch: int = _opt(8, "Images rasterized per refinement step for the photometric term (all when fewer).", ge=1)
    outline_refresh: int = _opt(4, "Images re-rasterized per step to update their outline vertices (the silhouette term).", ge=1)
    outline_period: int = _opt(20, "Steps between two rasterizations of an image's outline in the shape and refine stages "
                                   "(fewer when outline_refresh per step cannot keep up).", ge=1)
    keyframes: int = _opt(30, "Ordered sequences (a video, or images with smooth_sequences) with more timesteps than this are fitted on this many evenly spaced keyframes with "
                              "the full schedule (identity, focal length, landmark and scalp offsets, the keyframes' own "
                              "parameters), then every timestep is tracked with those shared parameters frozen "
                              "(track_chunk, track_steps). 0: every timestep in the full schedule at once (slow for videos).", ge=0)
    track_chunk: int = _opt(30, "Tracking after the keyframes: timesteps fitted together, in time order, each chunk's "
                                "smoothing tied to its neighbours.", ge=1)
    track_steps: int = _opt(30, "Tracking after the keyframes: Adam steps per chunk (landmarks, silhouettes, priors, smoothing; "
                                "warm-started from the keyframes interpolated).", ge=0)
    track_lr: float = _opt(0.01, "Tracking after the keyframes: Adam learning rate (as lr; smaller, the start is close).", gt=0)
    track_outline_period: int = _opt(30, "Tracking after the keyframes: steps between two rasterizations of an image's outline "
                                         "(each chunk starts with all of them).", ge=1)
    fit_height: int = _opt(256, "Image height of the rasterized terms (pixels).", ge=32)
    lr: float = _opt(0.02, "Adam learning rate (poses in radians, translation in decimetres, coefficients as they are).", gt=0)
    w_landmark: float = _opt(1.0, "Weight of the landmark reprojection term (robust, in units of the face size).", ge=0)
    landmark_scale: float = _opt(0.03, "Robust scale of the landmark residuals (fraction of the face size).", gt=0)
    landmark_full_deg: float = _opt(20.0, "Landmarks count fully on faces turned up to this angle from the camera (degrees).", ge=0, le=90)
    landmark_zero_deg: float = _opt(80.0, "... and not at all from this angle on (the detector's points slide on turned faces).", gt=0, le=90)
    landmark_offsets: str = _opt("auto", "Fit a shared in-plane offset per landmark (absorbs where the detector's idea of a point "
                                         "differs from the embedding's): on, off, or auto (on when the input sees the head from "
                                         "several directions: calibrated cameras, or a video or folder of images).",
                                 choices=("auto", "on", "off"))
    w_landmark_offset: float = _opt(0.1, "Weight of the size prior of the landmark offsets (squared, in centimetres).", ge=0)
    w_silhouette: float = _opt(1.0, "Weight of the silhouette term (mesh outline against the segmentation's outline).", ge=0)
    silhouette_two_sided: str = _opt("auto", "Outline vertices the silhouette pulls both ways: face (the FLAME masks' face and neck "
                                             "regions; elsewhere — scalp, ears, back of the head, which hair may cover — only inwards, "
                                             "when outside the person mask), all (every outline vertex; also without region masks), "
                                             "or auto (face when the focal length is known: calibrated cameras, EXIF or focal; all while it is fitted).",
                                     choices=("auto", "face", "all"))
    focal_refit: str = _opt("auto", "After fitting an uncalibrated camera's focal length, fit everything again with that focal length "
                                    "held, and so as with a known one (the face-only silhouette and the hair stage; for a "
                                    "sequence no pose table, landmark_pose): auto (one photo, and a sequence whose head's pivot "
                                    "was held, steady_pivot; the second fit kept when its landmark error is lower), on (the "
                                    "second fit kept), or off (one fit). Measured in docs/track.md: better on the synthetic "
                                    "photo, clip and head-turn video with hair and on the real photo; worse on a head that "
                                    "drifts (hence the pivot) and on a bare head, whose outline is the skull's (use off there).",
                            choices=("auto", "on", "off"))
    silhouette_outward_max: float = _opt(0.05, "With the face-only silhouette (silhouette_two_sided face, or auto with a known focal "
                                               "length): outline points this far inside the person mask (fraction of the face size) "
                                               "or further are not pulled outwards (hair, a collar or a hand lies between them and "
                                               "the mask's edge); 0.2 or more: every point the term uses.", gt=0)
    silhouette_scale: float = _opt(0.01, "Robust scale of the silhouette distances (fraction of the face size).", gt=0)
    w_photo: float = _opt(1.0, "Weight of the photometric term (rasterized vertex colours against the images).", ge=0)
    w_shape: float = _opt(0.01, "Weight of the identity prior (squared coefficients).", ge=0)
    w_expr: float = _opt(0.01, "Weight of the expression prior (squared coefficients).", ge=0)
    w_pose: float = _opt(1.0, "Weight of the prior on jaw, neck and eye rotations (squared radians).", ge=0)
    w_smooth: float = _opt(5.0, "Weight of the temporal smoothing of videos (squared frame-to-frame differences).", ge=0)
    smooth_sequences: bool = _opt(False, "Also smooth folders of images over time (they may be unordered photos).")
    steady_depth: bool = _opt(False, "Hold the head's distance from one uncalibrated camera steady over the frames of a video or a "
                                     "folder: for a head turning in front of a camera that stays put (a tripod). A head's depth "
                                     "from one image rests on its apparent size, which the outline and landmarks give to about "
                                     "1 %; the frames agreeing on it removes that jitter, but a head that really moves towards "
                                     "or away from the camera is then tracked worse (docs/track.md).")
    steady_pivot: str = _opt("auto", "Hold the point the head turns about (FLAME's root joint, the pivot of its global rotation) in one "
                                     "place in front of one uncalibrated camera over the frames of a video or a folder: its "
                                     "distance, as steady_depth does, and its position across the image. For a person who "
                                     "sits still and turns their head in front of a camera that stays put (a tripod): a "
                                     "frame's pitch and depth then cannot trade against a shift of the whole head. A person "
                                     "who leans or moves is tracked worse (docs/track.md). on, off (true / false are read as "
                                     "on / off), or auto: the frames (a video's keyframes) are fitted without it first, and the "
                                     "pivot is held when they already agree on it, its spread over the frames (standard "
                                     "deviation of its log depth and of its position across the image as a share of its "
                                     "distance) within steady_depth_scale; the fit is then run again with it held.",
                                choices=("auto", "on", "off"))
    w_steady_depth: float = _opt(1.0, "Weight of the steady-depth and steady-pivot priors (robust, per frame).", ge=0)
    steady_depth_scale: float = _opt(0.01, "Robust scale of the steady-depth and steady-pivot priors: deviations from the "
                                           "frames' common value (log depth; the pivot's sideways and vertical position as a "
                                           "share of its distance) up to this (1 %) cost quadratically, larger ones (the "
                                           "camera or the person really moved) only linearly.", gt=0)
    w_focal: float = _opt(0.001, "Weight of the prior pulling the log focal length to its initial value.", ge=0)
    mask_colour_cut: str = _opt("auto", "Check the person pixels by colour (a graph cut on colour models: background the "
                                        "segmentation took for the person goes back), before the fit (the landmarks' hull kept) and "
                                        "on the written mask (the fitted mesh kept): on, off, or auto (on when the image's "
                                        "background is not one uniform colour).", choices=("auto", "on", "off"))
    scalp_offsets: bool = _opt(True, "Fit static offsets along the normals on the model's scalp region (hair volume; needs "
                                     "FLAME_masks with a 'scalp' region).")
    w_offset_smooth: float = _opt(20.0, "Weight of the smoothness of the scalp offsets (squared differences along mesh edges, centimetres).", ge=0)
    w_offset: float = _opt(0.01, "Weight of the size prior of the scalp offsets (squared, in centimetres).", ge=0)
    threads: int = _opt(1, "Threads of each face model (detector, landmarks, segmentation).", ge=1)


PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    "default": {},
    "tiny": {"calib_views": 3, "calib_size": 256, "rigid_steps": 60, "steps": 200, "refine_steps": 20, "hair_steps": 50, "refine_batch": 4,
             "fit_height": 160, "max_height": 400, "keyframes": 12, "track_steps": 20,
             "calib_pose_yaw_deg": 30.0, "calib_pose_pitch_deg": 12.0, "pivot_pose_yaw_deg": 30.0},
}
"""What each preset changes against the dataclass defaults (tiny: tests, seconds per capture)."""


def _coerce(value: Any, tp: Any, key: str) -> Any:
    if typing.get_origin(tp) in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null", "")):
            return None
        tp = next(a for a in typing.get_args(tp) if a is not type(None))
    try:
        if tp is bool:
            return parse_bool(value)
        if tp is int:
            f = float(value)
            if isinstance(value, bool) or not f.is_integer():
                raise ValueError
            return int(f)
        if tp is float:
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        return str(value)
    except (TypeError, ValueError):
        raise ConfigError(f"track config: {key} = {value!r} is not a valid {getattr(tp, '__name__', tp)}") from None


def _on_off(value: Any, key: str) -> Any:
    """A boolean spelling (true / false, yes / no, 1 / 0) of a field whose choices are on / off (/ auto)
    read as on / off; every other value unchanged."""
    choices = TrackConfig.__dataclass_fields__[key].metadata.get("choices", ())
    if "on" in choices and "off" in choices and (isinstance(value, bool) or isinstance(value, str)) and value not in choices:
        try:
            return "on" if parse_bool(value) else "off"
        except (TypeError, ValueError):
            return value
    return value


def resolve_track_config(preset: str = "default", file_data: dict[str, Any] | None = None,
                         flags: dict[str, Any] | None = None) -> TrackConfig:
    """Dataclass defaults < preset < file (a flat mapping, or its ``track:`` section) < flags.

    Unknown keys and values outside a field's choices or range raise ConfigError naming the field.
    ``None`` flag values are ignored (unset options).
    """
    from ..config import validate_config

    if preset not in PRESET_OVERRIDES:
        raise ConfigError(f"unknown track preset '{preset}' (choose from {', '.join(TRACK_PRESETS)})")
    hints = typing.get_type_hints(TrackConfig)
    values: dict[str, Any] = {}
    section = (file_data or {}).get("track", file_data or {})
    if not isinstance(section, dict):
        raise ConfigError("track config: the 'track' section must be a mapping")
    for source, items in (("preset " + preset, PRESET_OVERRIDES[preset]), ("config file", section), ("command line", flags or {})):
        for key, value in items.items():
            if value is None and source == "command line":
                continue
            if key not in hints:
                raise ConfigError(f"{source}: unknown track option '{key}' (known: {', '.join(sorted(hints))})")
            values[key] = _on_off(_coerce(value, hints[key], key), key)
    cfg = TrackConfig(**values)
    validate_config(cfg, "track config")
    return cfg


def to_dict(cfg: TrackConfig) -> dict[str, Any]:
    """Plain-data form (JSON-safe)."""
    return dataclasses.asdict(cfg)
