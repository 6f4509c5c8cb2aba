"""The first pass over the input: one face per image, the crop window of every camera, and the
output cameras.

Images are streamed and only their landmarks are kept. A single image without a usable face is an
input error; in a sequence such frames are dropped and reported (too many dropped frames is an
error); in a multiview rig a view without a face still joins the capture (its silhouette and colours
count), and a timestep is dropped only when none of its views shows a face.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..data.cameras import Camera
from ..errors import InputError
from .config import TrackConfig
from .faces import FaceObservation, FaceObserver, FaceProblem
from .inputs import TrackSource

Progress = Callable[..., None]


@dataclass
class Dropped:
    """An image without a usable face: timestep id, view name, problem kind and message."""

    timestep_id: str
    view: str
    kind: str
    message: str

    def to_dict(self) -> dict[str, str]:
        return dict(self.__dict__)


@dataclass
class Observations:
    """The faces found: (view, timestep id) -> observation in input pixels, the dropped images, the
    timesteps kept (input order) and per view the input image size."""

    faces: dict[tuple[int, str], FaceObservation]
    dropped: list[Dropped]
    kept: list[str]
    sizes: dict[int, tuple[int, int]] = field(default_factory=dict)


def observe(source: TrackSource, observer: FaceObserver, cfg: TrackConfig, progress: Progress | None = None) -> Observations:
    """Run the face checks and landmarks on every image (see the module docstring)."""
    faces: dict[tuple[int, str], FaceObservation] = {}
    dropped: list[Dropped] = []
    sizes: dict[int, tuple[int, int]] = {}
    total = len(source.timesteps) * len(source.views)
    done = 0
    for vi, view in enumerate(source.views):
        near = None  # the last face box of this view: where to look first when the whole frame shows none
        previous = None  # the last landmarks of this view (a sequence's frames): the crop the face is followed in
        follow = cfg.follow_landmarks if source.kind in ("video", "images") else "off"
        for t, img in source.frames(vi):
            sizes[vi] = (img.shape[1], img.shape[0])
            done += 1
            try:
                faces[(vi, t)] = observer(img, near, previous, follow)
                near = faces[(vi, t)].detection.box
                previous = faces[(vi, t)].landmarks
            except FaceProblem as p:
                if source.kind == "image":
                    raise InputError(source.views[vi].files.get(t, source.path), p.message) from None
                dropped.append(Dropped(t, view.name, p.kind, p.message))
            if progress is not None:
                progress(done, total, "finding faces")
    seen_ts = {t for (_, t) in faces}
    kept = [t for t in source.timesteps if t in seen_ts]
    n_frames = len(source.timesteps)
    if not kept:
        kinds = Counter(d.kind for d in dropped)
        first = dropped[0] if dropped else None
        why = f"{first.message} (e.g. {first.timestep_id})" if first else "no frames"
        raise InputError(source.path, f"no usable face in any of the {n_frames} frame(s) ({dict(kinds)}): {why}")
    if source.kind != "multiview":
        lost = n_frames - len(kept)
        if lost > cfg.max_dropped * n_frames:
            kinds = Counter(d.kind for d in dropped).most_common(1)[0][0]
            example = next(d for d in dropped if d.kind == kinds)
            raise InputError(source.path, f"{lost} of {n_frames} frames have no usable face (more than {cfg.max_dropped:.0%}); "
                                          f"most often {kinds}: {example.message} (frame {example.timestep_id})")
    else:
        # a multiview timestep is lost only when no view shows a face; other views without one are noted
        for t in source.timesteps:
            if t not in seen_ts:
                dropped.append(Dropped(t, "all", "no-face", "no view of this timestep shows a usable face"))
    return Observations(faces, dropped, kept, sizes)


@dataclass
class Window:
    """A crop of one camera's input images: corner (x0, y0) and size (w, h) in input pixels (integers),
    and the output size (out_w, out_h)."""

    x0: int
    y0: int
    w: int
    h: int
    out_w: int
    out_h: int

    def camera(self, K: np.ndarray, w2c: np.ndarray, index: int, name: str) -> Camera:
        """The output camera of an input camera (K in input pixels): shifted by the corner, scaled
        per axis to the output size (formats.md §2.3)."""
        sx, sy = self.out_w / self.w, self.out_h / self.h
        Kc = K.astype(np.float64).copy()
        Kc[0, 2] -= self.x0
        Kc[1, 2] -= self.y0
        Kc[0] *= sx
        Kc[1] *= sy
        return Camera(Kc, w2c.astype(np.float64).copy(), self.out_w, self.out_h, index, name)

    def points(self, xy: np.ndarray) -> np.ndarray:
        """Input pixel positions (..., 2) -> output pixel positions."""
        return (xy - np.array([self.x0, self.y0])) * np.array([self.out_w / self.w, self.out_h / self.h])

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Crop and resize an input image (H, W, C) to (out_h, out_w, C)."""
        import cv2

        crop = np.ascontiguousarray(image[self.y0:self.y0 + self.h, self.x0:self.x0 + self.w])
        if (self.w, self.h) == (self.out_w, self.out_h):
            return crop
        interp = cv2.INTER_AREA if self.out_h < self.h else cv2.INTER_LINEAR
        out = cv2.resize(crop, (self.out_w, self.out_h), interpolation=interp)
        return out.reshape(self.out_h, self.out_w, *image.shape[2:])


def crop_window(boxes: list[np.ndarray], size: tuple[int, int], cfg: TrackConfig) -> Window:
    """The crop of one camera from its faces' landmark boxes (x0, y0, x1, y1) in input pixels.

    The window is ``crop_scale`` median face heights tall with ``crop_aspect``, the median face
    centre at 42 % of its height, grown to hold every face box enlarged by 30 %, then kept inside the
    image (clipped where it cannot fit). Without ``crop`` it is the whole image. The output height is
    the window's, at most ``max_height``.
    """
    W, H = size
    if cfg.crop and boxes:
        b = np.stack(boxes)
        heights = np.maximum(b[:, 3] - b[:, 1], b[:, 2] - b[:, 0])
        ch = cfg.crop_scale * float(np.median(heights))
        cw = ch * cfg.crop_aspect
        cx = float(np.median((b[:, 0] + b[:, 2]) / 2))
        cy = float(np.median((b[:, 1] + b[:, 3]) / 2))
        x0, y0 = cx - cw / 2, cy - 0.42 * ch
        # every face box, enlarged by 30 %, inside the window
        grow = 0.15 * (b[:, 2:] - b[:, :2])
        lo = (b[:, :2] - grow).min(0)
        hi = (b[:, 2:] + grow).max(0)
        x0, y0 = min(x0, lo[0]), min(y0, lo[1])
        x1, y1 = max(x0 + cw, hi[0]), max(y0 + ch, hi[1])
        # keep the aspect when growing: widen or heighten around the centre
        w, h = x1 - x0, y1 - y0
        if w / h < cfg.crop_aspect:
            extra = h * cfg.crop_aspect - w
            x0, x1 = x0 - extra / 2, x1 + extra / 2
        else:
            extra = w / cfg.crop_aspect - h
            y0, y1 = y0 - extra / 2, y1 + extra / 2
        w, h = min(x1 - x0, W), min(y1 - y0, H)
        x0 = min(max(x0, 0.0), W - w)
        y0 = min(max(y0, 0.0), H - h)
        x0i, y0i = int(np.floor(x0)), int(np.floor(y0))
        wi, hi_ = min(int(np.ceil(w)), W - x0i), min(int(np.ceil(h)), H - y0i)
    else:
        x0i, y0i, wi, hi_ = 0, 0, W, H
    out_h = min(hi_, cfg.max_height)
    out_w = max(1, int(round(wi * out_h / hi_)))
    return Window(x0i, y0i, wi, hi_, out_w, out_h)


MONOCULAR_W2C = np.linalg.inv(np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]]) @ np.diag([1.0, -1.0, -1.0, 1.0]))
"""VHAP's monocular camera (formats.md §1.8): OpenGL camera-to-world rotation I at (0, 0, 1), as OpenCV world-to-camera."""


def focal_for(source: TrackSource, view: int, size: tuple[int, int], cfg: TrackConfig) -> tuple[float, str]:
    """(focal length in input pixels, where it came from) of an uncalibrated camera: ``focal``, else
    EXIF, else ``focal_init`` × the longer side (then fitted when ``fit_focal``)."""
    if cfg.focal is not None:
        return float(cfg.focal), "given"
    v = source.views[view]
    if v.exif_focal is not None:
        return float(v.exif_focal), "exif"
    return float(cfg.focal_init * max(size)), "fitted" if cfg.fit_focal else "assumed"
