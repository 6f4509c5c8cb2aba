"""Face detection with MediaPipe's short-range BlazeFace model (``face_detection_short_range.tflite``).

The model sees the image letterboxed into a 128×128 square (zero borders, values in [-1, 1]) and
scores 896 SSD anchors: 16×16 cells × 2 anchors at stride 8, then 8×8 cells × 6 anchors at stride 16,
every anchor centred in its cell with a fixed unit size. Each anchor regresses a box (centre offset,
width, height) and six keypoints in 128-pixel units relative to the anchor centre. Overlapping
boxes are merged by score-weighted averaging (the "weighted" suppression MediaPipe uses).

Keypoints, in the order the model gives them: the subject's right eye, left eye, nose tip, mouth
centre, right ear tragion, left ear tragion (the right eye is on the image's left in a photo).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .litert import TFLiteModel

INPUT_SIZE = 128
SCORE_CLIP = 100.0
SUPPRESSION_IOU = 0.3


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
    s = scores[keep]
    order = np.argsort(-s)
    boxes, kps, s = boxes[order], kps[order], s[order]
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


class FaceDetector:
    """BlazeFace short range on images of any size.

    model_path: the verified ``face_detection_short_range.tflite``; threads: interpreter threads;
    min_score: detections below this confidence are dropped.
    """

    def __init__(self, model_path: str, threads: int = 1, min_score: float = 0.5) -> None:
        self.model = TFLiteModel(model_path, threads)
        self.min_score = float(min_score)

    def __call__(self, image: np.ndarray) -> list[Detection]:
        """image: (H, W, 3) float RGB in [0, 1] -> detections in image pixels, best first."""
        square, scale, offset = letterbox(image, INPUT_SIZE)
        outs = self.model(square * 2.0 - 1.0)
        reg = self.model.output_by_size(outs, 896 * 16).reshape(896, 16)
        logit = self.model.output_by_size(outs, 896).reshape(896)
        dets = decode(reg, logit, self.min_score)
        for d in dets:  # square [0, 1] units -> image pixels
            d.box = (d.box.reshape(2, 2) * INPUT_SIZE - offset).reshape(4) / scale
            d.keypoints = (d.keypoints * INPUT_SIZE - offset) / scale
        return dets
