"""Face detection with MediaPipe's short-range BlazeFace model (``face_detection_short_range.tflite``).

The model sees the image letterboxed into a 128×128 square (zero borders, values in [-1, 1]) and
scores 896 SSD anchors: 16×16 cells × 2 anchors at stride 8, then 8×8 cells × 6 anchors at stride 16,
every anchor centred in its cell with a fixed unit size. Each anchor regresses a box (centre offset,
width, height) and six keypoints in 128-pixel units relative to the anchor centre. Overlapping
boxes are merged by score-weighted averaging (the "weighted" suppression MediaPipe uses).

Keypoints, in the order the model gives them: the subject's right eye, left eye, nose tip, mouth
centre, right ear tragion, left ear tragion (the right eye is on the image's left in a photo).

The short-range model finds a face whose box is at least about an eighth of its square input, so a
whole image letterboxed into 128 pixels misses a face that fills less than that of the image's
longer side (a person a few metres from the camera). :meth:`FaceDetector.search` looks for such
faces: squares of the image at halving sizes, each cut into tiles at half a tile's stride.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .litert import TFLiteModel

INPUT_SIZE = 128
SCORE_CLIP = 100.0
SUPPRESSION_IOU = 0.3
TILE_FACE_RANGE = (0.15, 0.5)
"""Face widths, as fractions of a tile's side, that a tile of the search counts: from the smallest the
model finds reliably (the search goes down to tiles where a face ``min_width`` wide is that small) to
half the tile (a wider face is a coarser tile's, which holds it with a margin)."""
SEARCH_MIN_SCORE = 0.75
"""Confidence a tile's detection needs: the search scores hundreds of windows, and patterns that are not
faces (a picture's edge, a collar) reach 0.5–0.6 in some of them, where a face at a size the model
sees well scores above 0.9."""


@dataclass
class Detection:
    """One detected face, in image pixels (continuous coordinates, pixel centres at +0.5).

    Attributes:
        score: detector confidence in [0, 1].
        box: (4,) x0, y0, x1, y1.
        keypoints: (6, 2) right eye, left eye, nose tip, mouth centre, right ear, left ear.
    """

    score: float
    box: np.ndarray
    keypoints: np.ndarray

    @property
    def width(self) -> float:
        return float(self.box[2] - self.box[0])

    @property
    def height(self) -> float:
        return float(self.box[3] - self.box[1])

    @property
    def center(self) -> np.ndarray:
        """(2,) box centre."""
        return np.array([(self.box[0] + self.box[2]) / 2, (self.box[1] + self.box[3]) / 2])

    @property
    def roll(self) -> float:
        """In-plane rotation of the eye line (radians; 0 = upright, positive = clockwise in the image)."""
        d = self.keypoints[1] - self.keypoints[0]
        return float(np.arctan2(d[1], d[0]))


def anchor_centres() -> np.ndarray:
    """(896, 2) anchor centres in [0, 1] (x, y), in the order the model scores them."""
    out = []
    for stride, per_cell in ((8, 2), (16, 6)):
        n = INPUT_SIZE // stride
        ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        cells = np.stack([xs.ravel(), ys.ravel()], -1)
        out.append(np.repeat(cells, per_cell, axis=0))
    return np.concatenate(out).astype(np.float64)


_ANCHORS = anchor_centres()


def letterbox(image: np.ndarray, size: int) -> tuple[np.ndarray, float, np.ndarray]:
    """Fit an (H, W, 3) image into a size×size square with zero borders.

    Returns (square (size, size, 3) float32, scale (square pixels per image pixel), offset (2,) of the
    image's corner in square pixels): square = image · scale + offset.
    """
    import cv2

    H, W = image.shape[:2]
    s = size / max(H, W)
    w, h = max(1, int(round(W * s))), max(1, int(round(H * s)))
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
    resized = cv2.resize(np.ascontiguousarray(image, dtype=np.float32), (w, h), interpolation=interp)
    out = np.zeros((size, size, 3), np.float32)
    ox, oy = (size - w) // 2, (size - h) // 2
    out[oy:oy + h, ox:ox + w] = resized.reshape(h, w, -1)[..., :3]
    # exact mapping of continuous coordinates: the resized image spans [0, w] for [0, W]
    return out, w / W, np.array([ox, oy], np.float64)


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = lambda b: np.clip(b[..., 2] - b[..., 0], 0, None) * np.clip(b[..., 3] - b[..., 1], 0, None)  # noqa: E731
    return inter / np.maximum(area(box) + area(boxes) - inter, 1e-12)


def decode(regressors: np.ndarray, logits: np.ndarray, min_score: float) -> list[Detection]:
    """Raw model outputs -> merged detections in the 128-pixel square's [0, 1] units.

    regressors: (896, 16); logits: (896,). Boxes scoring below ``min_score`` are dropped; the rest are
    merged (weighted suppression at IoU 0.3), best first.
    """
    scores = 1.0 / (1.0 + np.exp(-np.clip(logits.astype(np.float64), -SCORE_CLIP, SCORE_CLIP)))
    keep = np.flatnonzero(scores >= min_score)
    if keep.size == 0:
        return []
    r = regressors[keep].astype(np.float64) / INPUT_SIZE
    a = _ANCHORS[keep]
    cx, cy = r[:, 0] + a[:, 0], r[:, 1] + a[:, 1]
    w, h = r[:, 2], r[:, 3]
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], -1)
    kps = r[:, 4:16].reshape(-1, 6, 2) + a[:, None, :]
    return merge(boxes, kps, scores[keep])


def merge(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray) -> list[Detection]:
    """Weighted suppression: boxes (K, 4), keypoints (K, 6, 2), scores (K,) -> one detection per group
    of boxes overlapping the group's best by IoU above 0.3, its box and keypoints the score-weighted
    means, best first."""
    order = np.argsort(-scores, kind="stable")
    boxes, kps, s = boxes[order], keypoints[order], scores[order]
    out: list[Detection] = []
    remaining = np.ones(len(s), bool)
    for i in range(len(s)):
        if not remaining[i]:
            continue
        group = np.flatnonzero(remaining & (_iou(boxes[i], boxes) > SUPPRESSION_IOU))
        group = np.union1d(group, [i])
        remaining[group] = False
        wts = s[group][:, None]
        box = (boxes[group] * wts).sum(0) / wts.sum()
        kp = (kps[group] * wts[:, :, None]).sum(0) / wts.sum()
        out.append(Detection(float(s[i]), box, kp))
    return out


def tile_starts(length: int, side: int) -> list[int]:
    """Corners along one axis of tiles of ``side`` pixels at a stride of side/2 covering [0, length),
    the last one flush with the end."""
    if length <= side:
        return [0]
    stride = max(1, side // 2)
    starts = list(range(0, length - side, stride))
    return starts + [length - side]


def _merge_all(dets: list[Detection]) -> list[Detection]:
    if not dets:
        return []
    return merge(np.stack([d.box for d in dets]), np.stack([d.keypoints for d in dets]), np.array([d.score for d in dets]))


class FaceDetector:
    """BlazeFace short range on images of any size.

    model_path: the verified ``face_detection_short_range.tflite``; threads: interpreter threads;
    min_score: detections below this confidence are dropped.
    """

    def __init__(self, model_path: str, threads: int = 1, min_score: float = 0.5) -> None:
        self.model = TFLiteModel(model_path, threads)
        self.min_score = float(min_score)

    def _raw(self, square: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A (128, 128, 3) square in [0, 1] -> the model's regressors (896, 16) and logits (896,)."""
        outs = self.model(square * 2.0 - 1.0)
        return self.model.output_by_size(outs, 896 * 16).reshape(896, 16), self.model.output_by_size(outs, 896).reshape(896)

    def __call__(self, image: np.ndarray) -> list[Detection]:
        """image: (H, W, 3) float RGB in [0, 1] -> detections in image pixels, best first."""
        square, scale, offset = letterbox(image, INPUT_SIZE)
        dets = decode(*self._raw(square), self.min_score)
        for d in dets:  # square [0, 1] units -> image pixels
            d.box = (d.box.reshape(2, 2) * INPUT_SIZE - offset).reshape(4) / scale
            d.keypoints = (d.keypoints * INPUT_SIZE - offset) / scale
        return dets

    def in_region(self, image: np.ndarray, box: np.ndarray, context: float = 4.0) -> list[Detection]:
        """Detections in a square of ``context`` × the larger side of ``box`` (4,) x0, y0, x1, y1 around
        its centre, clipped to the image (a face near where a neighbouring video frame had it), in
        image pixels, best first."""
        H, W = image.shape[:2]
        side = max(float(box[2] - box[0]), float(box[3] - box[1])) * context
        cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
        x0, y0 = int(max(0, np.floor(cx - side / 2))), int(max(0, np.floor(cy - side / 2)))
        x1, y1 = int(min(W, np.ceil(cx + side / 2))), int(min(H, np.ceil(cy + side / 2)))
        if x1 - x0 < 8 or y1 - y0 < 8:
            return []
        dets = self(image[y0:y1, x0:x1])
        for d in dets:
            d.box = d.box + np.array([x0, y0, x0, y0], np.float64)
            d.keypoints = d.keypoints + np.array([x0, y0], np.float64)
        return dets

    def search(self, image: np.ndarray, min_width: float) -> list[Detection]:
        """Faces too small for the whole-image pass, in image pixels, best first.

        Squares of side t, from the image's shorter side halving down to the side at which a face
        ``min_width`` pixels wide is the smallest of :data:`TILE_FACE_RANGE` (and not below 128, so no
        tile is enlarged), cover the image at a stride of t/2; each is scored at 128×128 and answers
        for the faces whose centre lies in its central half and whose width is at most
        ``TILE_FACE_RANGE[1]`` of its side, found with at least :data:`SEARCH_MIN_SCORE`. The tiles'
        detections are merged.
        """
        import cv2

        H, W = image.shape[:2]
        t_min = max(float(INPUT_SIZE), min_width / TILE_FACE_RANGE[0])
        t = float(min(H, W))
        min_score = max(self.min_score, SEARCH_MIN_SCORE)
        found: list[Detection] = []
        while t >= t_min:
            s = INPUT_SIZE / t
            w, h = max(INPUT_SIZE, int(round(W * s))), max(INPUT_SIZE, int(round(H * s)))
            small = cv2.resize(np.ascontiguousarray(image[..., :3], dtype=np.float32), (w, h), interpolation=cv2.INTER_AREA)
            sx, sy = w / W, h / H
            xs, ys = tile_starts(w, INPUT_SIZE), tile_starts(h, INPUT_SIZE)
            for y0 in ys:
                for x0 in xs:
                    reg, logit = self._raw(small[y0:y0 + INPUT_SIZE, x0:x0 + INPUT_SIZE])
                    # the central half this tile answers for (to the image's edge for the outer tiles)
                    lo_x = 0.0 if x0 == xs[0] else x0 + INPUT_SIZE / 4
                    hi_x = float(w) if x0 == xs[-1] else x0 + 3 * INPUT_SIZE / 4
                    lo_y = 0.0 if y0 == ys[0] else y0 + INPUT_SIZE / 4
                    hi_y = float(h) if y0 == ys[-1] else y0 + 3 * INPUT_SIZE / 4
                    for d in decode(reg, logit, min_score):
                        box = d.box * INPUT_SIZE + np.array([x0, y0, x0, y0], np.float64)
                        cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
                        if not (lo_x <= cx < hi_x and lo_y <= cy < hi_y) or box[2] - box[0] > TILE_FACE_RANGE[1] * INPUT_SIZE:
                            continue
                        kp = d.keypoints * INPUT_SIZE + np.array([x0, y0], np.float64)
                        found.append(Detection(d.score, box / np.array([sx, sy, sx, sy]), kp / np.array([sx, sy])))
            t /= 2.0
        return _merge_all(found)
