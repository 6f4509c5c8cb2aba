"""Dense face landmarks with MediaPipe's 468-point face mesh model (``face_landmark.tflite``).

The model takes an upright 192×192 crop of the face (RGB in [0, 1]) and returns 468 points (x, y in
crop pixels, z a relative depth in the same units) and a face-presence logit. As in MediaPipe's face
mesh pipeline, the crop is a square rotated so that the eyes are level: from a detection, centred on
its box with side 1.5 × the box's longer side and turned by the eye line of its keypoints; from
landmarks (the refinement pass), centred on their bounding box with side 1.5 × its longer side and
turned by the line through the outer eye corners (points 33 and 263).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .detector import Detection
from .litert import TFLiteModel

CROP = 192
ROI_SCALE = 1.5
N_LANDMARKS = 468
RIGHT_EYE_OUTER = 33
"""The subject's right outer eye corner (on the image's left in a photo)."""
LEFT_EYE_OUTER = 263


@dataclass
class Roi:
    """A rotated square region of the image: centre (2,), side in pixels, angle in radians."""

    center: np.ndarray
    size: float
    angle: float

    def crop_to_image(self) -> np.ndarray:
        """(2, 3) affine map of continuous crop coordinates (0..192) to continuous image coordinates."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        k = self.size / CROP
        A = np.array([[c * k, -s * k], [s * k, c * k]])
        return np.concatenate([A, (self.center - A @ np.array([CROP / 2, CROP / 2]))[:, None]], 1)


def roi_from_detection(det: Detection) -> Roi:
    """The crop MediaPipe's face mesh takes from a detection."""
    return Roi(det.center, max(det.width, det.height) * ROI_SCALE, det.roll)


def roi_from_landmarks(points: np.ndarray) -> Roi:
    """The crop for a refinement pass from earlier landmarks (468, 2+)."""
    xy = points[:, :2]
    d = xy[LEFT_EYE_OUTER] - xy[RIGHT_EYE_OUTER]
    angle = float(np.arctan2(d[1], d[0]))
    lo, hi = xy.min(0), xy.max(0)
    return Roi((lo + hi) / 2, float(max(hi - lo)) * ROI_SCALE, angle)


def crop(image: np.ndarray, roi: Roi) -> np.ndarray:
    """(192, 192, 3) float32 crop of an (H, W, 3) image (edges replicated beyond the image)."""
    import cv2

    A = roi.crop_to_image()
    # OpenCV samples at integer pixel centres: img_cv = A·(crop_cv + 0.5) − 0.5
    M = A.copy()
    M[:, 2] = A[:, 2] + A[:, :2] @ np.array([0.5, 0.5]) - 0.5
    return cv2.warpAffine(np.ascontiguousarray(image, dtype=np.float32), M, (CROP, CROP),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)


@dataclass
class FaceLandmarks:
    """468 face-mesh points in image pixels.

    Attributes:
        points: (468, 3) x, y in image pixels (continuous, pixel centres at +0.5); z relative depth in
            the same scale (smaller = nearer the camera).
        presence: face-presence probability of the last pass in [0, 1].
        roi: the crop of the last pass.
    """

    points: np.ndarray
    presence: float
    roi: Roi

    @property
    def xy(self) -> np.ndarray:
        """(468, 2) image positions."""
        return self.points[:, :2]


class FaceMesh:
    """The landmark model. model_path: verified ``face_landmark.tflite``; threads: interpreter threads."""

    def __init__(self, model_path: str, threads: int = 1) -> None:
        self.model = TFLiteModel(model_path, threads)

    def run(self, image: np.ndarray, roi: Roi) -> FaceLandmarks:
        """One pass on one crop. image: (H, W, 3) float RGB in [0, 1]."""
        outs = self.model(crop(image, roi))
        pts = self.model.output_by_size(outs, N_LANDMARKS * 3).reshape(N_LANDMARKS, 3).astype(np.float64)
        logit = float(self.model.output_by_size(outs, 1).reshape(()))
        A = roi.crop_to_image()
        xy = pts[:, :2] @ A[:, :2].T + A[:, 2]
        z = pts[:, 2:3] * roi.size / CROP
        presence = float(1.0 / (1.0 + np.exp(-np.clip(logit, -60.0, 60.0))))
        return FaceLandmarks(np.concatenate([xy, z], 1), presence, roi)

    def _passes(self, image: np.ndarray, roi: Roi, passes: int) -> FaceLandmarks:
        """One pass on ``roi``, then ``passes − 1`` refinement passes on crops from the previous landmarks."""
        lm = self.run(image, roi)
        for _ in range(max(0, passes - 1)):
            lm = self.run(image, roi_from_landmarks(lm.points))
        return lm

    def follow(self, image: np.ndarray, points: np.ndarray, passes: int = 2) -> FaceLandmarks:
        """Landmarks from a neighbouring video frame's (468, 2+) points, without a detection (the first
        pass on the crop those points give), as MediaPipe's face mesh follows a face from frame to frame."""
        return self._passes(image, roi_from_landmarks(points), passes)

    def __call__(self, image: np.ndarray, det: Detection, passes: int = 2) -> FaceLandmarks:
        """Landmarks from a detection: one pass on the detection's crop, then ``passes − 1``
        refinement passes on crops from the previous landmarks."""
        return self._passes(image, roi_from_detection(det), passes)
