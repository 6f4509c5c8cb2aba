"""What ``sage track`` reads: one image, a folder of images, a video, or a folder of camera folders
with a calibration file.

Nothing is decoded up front beyond headers: :class:`TrackSource` lists the views (cameras) and the
timesteps, and :meth:`TrackSource.frames` streams each view's images as float32 RGB in [0, 1],
upright (EXIF orientation applied) and undistorted (calibrated cameras with distortion).

- one image (``.png``, ``.jpg``, ...): one view, one timestep; the focal length comes from EXIF
  (``FocalLengthIn35mmFilm``) when present.
- a folder of images: one view (one camera, e.g. a phone), timesteps in file-name order.
- a video (``.mp4``, ``.mov``, ...; decoded with ffmpeg through ``imageio-ffmpeg``): one view,
  optionally subsampled to ``fps`` frames per second.
- a folder of folders plus a cameras file (:mod:`.camera_files`): one view per folder, timesteps
  are the image names the folders share.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..data.cameras import Camera
from ..data.imageio import read_header, read_on_white
from ..errors import ConfigError, InputError
from .camera_files import CameraSet, read_cameras

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr")
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
HEIF_SUFFIXES = (".heic", ".heif", ".avif")
"""Photo formats the image reader has no codec for (named in the refusal, with what to do)."""
KINDS = ("image", "images", "video", "multiview")


@dataclass
class SourceView:
    """One camera of the input.

    Attributes:
        name: folder name, file stem or "video".
        index: camera index written to the capture.
        width, height: image size after orientation.
        calibrated: the calibrated camera at (width, height), or None (uncalibrated: focal from EXIF,
            ``focal`` or fitted; principal point at the image centre).
        distortion: OpenCV coefficients of a calibrated camera, or None.
        exif_focal: focal length in pixels from EXIF, or None.
        files: timestep id -> image file (image inputs).
    """

    name: str
    index: int
    width: int
    height: int
    calibrated: Camera | None = None
    distortion: np.ndarray | None = None
    exif_focal: float | None = None
    files: dict[str, Path] = field(default_factory=dict)


@dataclass
class TrackSource:
    """A parsed input.

    Attributes:
        kind: "image", "images", "video" or "multiview".
        path: the input file or folder.
        views: the cameras.
        timesteps: timestep ids in time order (file stems, or ``frame_00012`` for video frame 12).
        fps: frames per second of a video after subsampling, else None.
        video_frames: video frame number of each timestep (videos), else None.
        metric: calibrated cameras are in metres (VHAP exports); None for uncalibrated inputs.
        warnings: non-fatal findings, one sentence each.
    """

    kind: str
    path: Path
    views: list[SourceView]
    timesteps: list[str]
    fps: float | None = None
    video_frames: list[int] | None = None
    metric: bool | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def calibrated(self) -> bool:
        return all(v.calibrated is not None for v in self.views)

    def frames(self, view: int) -> Iterator[tuple[str, np.ndarray]]:
        """Stream (timestep id, image (H, W, 3) float32 in [0, 1]) of one view in time order;
        a timestep the view lacks is skipped. Decoding failures raise InputError naming the file."""
        v = self.views[view]
        if self.kind == "video":
            assert self.video_frames is not None
            wanted = dict(zip(self.video_frames, self.timesteps))
            for n, img in _video_frames(self.path, max(wanted) if wanted else -1):
                if n in wanted:
                    yield wanted[n], img
            return
        for t in self.timesteps:
            if t in v.files:
                img = read_rgb(v.files[t])
                if v.distortion is not None and v.calibrated is not None:
                    img = undistort(img, v.calibrated, v.distortion)
                yield t, img


# -- images ----------------------------------------------------------------------------------------

def read_rgb(path: Path) -> np.ndarray:
    """An image file as (H, W, 3) float32 in [0, 1], upright (EXIF orientation applied).

    Read with :func:`sage_core.data.imageio.read_on_white` (alpha applied once, grey repeated to RGB),
    clipped to [0, 1]. InputError names the file when it is missing or cannot be decoded.
    """
    return np.clip(read_on_white(path, upright=True), 0.0, 1.0)


def _header(path: Path) -> tuple[int, int, float | None]:
    """(width, height, EXIF focal in pixels) after orientation, from the header."""
    head = read_header(path)
    w, h = head.upright_size
    return w, h, head.focal_px


def undistort(img: np.ndarray, cam: Camera, dist: np.ndarray) -> np.ndarray:
    """Remove lens distortion; the result is the pinhole image of the same K."""
    import cv2

    K = cam.K.copy()
    K[:2, 2] -= 0.5  # OpenCV puts pixel centres at integers
    return cv2.undistort(img, K, dist.astype(np.float64), None, K)


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))


# -- video -----------------------------------------------------------------------------------------

def _open_video(path: Path) -> tuple[Iterator, dict]:
    """The frame generator and header of a video. ffmpeg applies a phone video's display rotation,
    so ``meta["size"]`` is the upright (width, height) the frames come in (the reader's warning that
    it differs from the coded size is silenced: upright is what is wanted)."""
    import logging

    import imageio_ffmpeg

    log = logging.getLogger("imageio_ffmpeg")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
        meta = next(gen)
    except (OSError, RuntimeError, StopIteration, ValueError) as exc:
        raise InputError(path, f"cannot read the video ({_first_line(exc)})") from None
    finally:
        log.setLevel(level)
    size = meta.get("size") or (0, 0)
    if not size or min(size) <= 0:
        gen.close()
        raise InputError(path, "the video has no readable video stream")
    return gen, meta


def _first_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    bad = [ln for ln in lines if "invalid" in ln.lower() or "error" in ln.lower() or "moov" in ln.lower()]
    return (bad or lines or [type(exc).__name__])[-1][:200]


def _video_frames(path: Path, last: int) -> Iterator[tuple[int, np.ndarray]]:
    """(frame number, image) up to frame ``last`` (inclusive)."""
    gen, meta = _open_video(path)
    w, h = meta["size"]
    try:
        n = 0
        for buf in gen:
            if n > last:
                break
            arr = np.frombuffer(buf, dtype=np.uint8)
            if arr.size != w * h * 3:
                raise InputError(path, f"frame {n} has {arr.size} bytes, expected {w * h * 3}")
            yield n, arr.reshape(h, w, 3).astype(np.float32) / 255.0
            n += 1
    except (OSError, RuntimeError) as exc:
        raise InputError(path, f"the video breaks off at frame {n} ({_first_line(exc)})") from None
    finally:
        gen.close()


def _probe_video(path: Path) -> tuple[int, int, float, int]:
    """(width, height, fps, frame count) of a video, decoding it once."""
    gen, meta = _open_video(path)
    w, h = meta["size"]
    n = 0
    try:
        for buf in gen:
            if len(buf) != w * h * 3:
                break
            n += 1
    except (OSError, RuntimeError) as exc:
        if n == 0:
            raise InputError(path, f"cannot decode the video ({_first_line(exc)})") from None
    finally:
        gen.close()
    if n == 0:
        raise InputError(path, "the video holds no decodable frames (corrupt or empty file)")
    return int(w), int(h), float(meta.get("fps") or 0.0), n


def _subsample(n: int, src_fps: float, fps: float | None, max_frames: int | None) -> list[int]:
    idx = np.arange(n)
    if fps is not None and src_fps > 0 and fps < src_fps:
        t = idx / src_fps
        keep = np.unique(np.floor(t * fps + 1e-9).astype(int), return_index=True)[1]
        idx = idx[keep]
    return _evenly(list(int(i) for i in idx), max_frames)


def _evenly(items: list, k: int | None) -> list:
    if k is None or len(items) <= k:
        return items
    pick = np.unique(np.linspace(0, len(items) - 1, k).round().astype(int))
    return [items[i] for i in pick]


# -- the input ---------------------------------------------------------------------------------------

def read_source(path: str | Path, cameras: str | Path | None = None, fps: float | None = None,
                max_frames: int | None = None) -> TrackSource:
    """Parse INPUT (see the module docstring). cameras: a calibration file for multiview folders.

    Raises InputError naming the file or folder when it is missing, empty, unreadable or does not fit
    the cameras file; ConfigError for a cameras file with a single image or video.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, "input not found (give an image, a folder of images, a video, or a folder of camera folders)")
    if p.is_file():
        if cameras is not None:
            raise ConfigError("a cameras file goes with a folder of camera folders, not with a single image or video")
        suffix = p.suffix.lower()
        if suffix in VIDEO_SUFFIXES:
            w, h, src_fps, n = _probe_video(p)
            keep = _subsample(n, src_fps, fps, max_frames)
            out_fps = (src_fps * len(keep) / n) if src_fps > 0 else None
            ts = [f"frame_{i:05d}" for i in keep]
            return TrackSource("video", p, [SourceView("video", 0, w, h)], ts, fps=out_fps, video_frames=keep)
        if suffix in IMAGE_SUFFIXES:
            w, h, focal = _header(p)
            return TrackSource("image", p, [SourceView(p.stem, 0, w, h, exif_focal=focal, files={p.stem: p})], [p.stem])
        hint = "; a phone's HEIF photo: export it as JPEG (the camera's focal length stays in its EXIF)" if suffix in HEIF_SUFFIXES else ""
        raise InputError(p, f"unknown input type '{suffix}' (images: {', '.join(IMAGE_SUFFIXES)}; videos: {', '.join(VIDEO_SUFFIXES)}{hint})")

    files = _image_files(p)
    subdirs = sorted(d for d in p.iterdir() if d.is_dir() and not d.name.startswith(".") and _image_files(d))
    if cameras is not None:
        if not subdirs:
            raise InputError(p, "a cameras file needs one folder of images per camera inside the input folder")
        return _multiview(p, subdirs, read_cameras(cameras), max_frames)
    if subdirs and not files:
        raise InputError(p, f"the folder holds {len(subdirs)} camera folder(s) but no cameras file was given "
                            "(pass a COLMAP model or a transforms.json with --cameras)")
    if not files:
        raise InputError(p, "the folder holds no images")
    files = _evenly(files, max_frames)
    sizes = {_header(f)[:2] for f in files}
    if len(sizes) > 1:
        raise InputError(p, f"the images differ in size ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))}); one camera "
                            "needs one image size")
    w, h, focal = _header(files[0])
    stems = [f.stem for f in files]
    view = SourceView(p.name, 0, w, h, exif_focal=focal, files=dict(zip(stems, files)))
    kind = "image" if len(files) == 1 else "images"
    return TrackSource(kind, p, [view], stems)


def _multiview(root: Path, subdirs: list[Path], cams: CameraSet, max_frames: int | None) -> TrackSource:
    views: list[SourceView] = []
    warnings = list(cams.warnings)
    used: set[int] = set()
    unmatched = []
    for d in subdirs:
        cc = cams.match(d.name)
        if cc is None:
            unmatched.append(d.name)
            continue
        if id(cc) in used:
            raise InputError(d, f"two folders select the same camera '{cc.names[0]}' of {cams.source}")
        used.add(id(cc))
        files = {f.stem: f for f in _image_files(d)}
        w, h, _ = _header(next(iter(files.values())))
        cam = cc.camera
        if (w, h) != (cam.width, cam.height):
            if abs(w / h - cam.width / cam.height) > 0.01:
                raise InputError(d, f"images are {w}x{h} but the camera in {cams.source.name} is {cam.width}x{cam.height}")
            cam = cam.resized(w, h)
        views.append(SourceView(d.name, cc.index, w, h, calibrated=cam, distortion=cc.distortion, files=files))
    if unmatched:
        raise InputError(root / unmatched[0], f"no camera of {cams.source} matches the folder name(s) {', '.join(unmatched)}")
    if not views:
        raise InputError(root, f"no camera folder matches {cams.source}")
    if any(v.index < 0 for v in views):  # cameras without an index of their own: folder order
        for i, v in enumerate(views):
            v.index = i
    if len({v.index for v in views}) != len(views):
        raise InputError(cams.source, "two cameras share one camera index")
    common = set.intersection(*(set(v.files) for v in views))
    union = set.union(*(set(v.files) for v in views))
    if not common:
        raise InputError(root, "the camera folders share no image name (a timestep is the same file name in every folder)")
    if len(common) < len(union):
        warnings.append(f"{len(union) - len(common)} image name(s) are missing from some camera folders; those views are skipped")
    ts = _evenly(sorted(union), max_frames)
    views.sort(key=lambda v: v.index)
    return TrackSource("multiview", root, views, ts, metric=cams.metric, warnings=warnings)
