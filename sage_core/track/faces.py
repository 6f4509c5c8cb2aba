"""One face per image: detection, the checks that refuse an unusable image, and dense landmarks.

:class:`FaceObserver` runs the detector and the landmark model on one image and returns a
:class:`FaceObservation`, or raises :class:`FaceProblem` saying why the image cannot be tracked:

- ``no-face``: nothing detected, in the whole image nor in the tiled search for faces down to
  ``min_face_px`` wide (also when the landmark model finds no face in the detected box);
- ``rotated``: no upright face, but one appears when the image is turned by 90°, 180° or 270°; or
  the face's eye line is tilted beyond ``max_roll_deg``; or an unsure upright face (an upside-down
  face can pass for one) is found much more surely in a turned view;
- ``two-faces``: a second face at least ``second_face_ratio`` of the main face's width;
- ``tiny-face``: the face is narrower than ``min_face_px``;
- ``cut-off``: more than ``max_outside`` of the face's landmarks lie beyond the image's edge (the
  face leaves the picture, and the landmark model guesses where the rest of it is).

A video frame may also be given the landmarks of the frame before it (``previous``): the landmark
model then looks at the crop those landmarks give, as MediaPipe's face mesh follows a face through a
video. With ``follow="fallback"`` that happens only when the detector's crop yields no usable face
(near profile the detector's box is loose and the landmark model's presence falls, where the crop
from the previous frame's landmarks still fits the face); with ``follow="first"`` the followed crop is
tried before the detector, which then runs only when the face is lost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import FOLLOW_MODES
from .detector import Detection, FaceDetector
from .face_mesh import FaceLandmarks, FaceMesh
from .weights import ModelPaths

PROBLEM_KINDS = ("no-face", "rotated", "two-faces", "tiny-face", "cut-off")
UNSURE_SCORE = 0.75
"""An upright detection scoring below this is compared with the image turned by 90°, 180° and 270°."""
TURNED_MARGIN = 0.2
"""... and the image is refused as turned when a turned view scores higher by this much."""


# face-mesh points standing in for the detector's keypoints when a face is followed from landmarks
_EYE_R, _EYE_L, _NOSE_TIP, _MOUTH, _EAR_R, _EAR_L = (33, 133), (263, 362), (1,), (13, 14), (234,), (454,)


def detection_from_landmarks(xy: np.ndarray, score: float) -> Detection:
    """A :class:`Detection` for a face found from landmarks (468, 2): their box, and the detector's six
    keypoints (eye centres, nose tip, mouth centre, ear points) taken from the face mesh."""
    kp = np.stack([xy[list(ids)].mean(0) for ids in (_EYE_R, _EYE_L, _NOSE_TIP, _MOUTH, _EAR_R, _EAR_L)])
    return Detection(float(score), np.concatenate([xy.min(0), xy.max(0)]), kp)


class FaceProblem(Exception):
    """An image without one usable face. ``kind`` is one of :data:`PROBLEM_KINDS`; the message says what
    was found and what to do."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message


@dataclass
class FaceObservation:
    """The face of one image.

    Attributes:
        landmarks: (468, 2) face-mesh points in image pixels.
        presence: landmark face-presence probability.
        detection: the detector's box and keypoints.
        face_height: forehead-to-chin extent of the landmarks (pixels): the unit of the fitting's
            landmark residuals.
    """

    landmarks: np.ndarray
    presence: float
    detection: Detection

    @property
    def face_height(self) -> float:
        lo, hi = self.landmarks.min(0), self.landmarks.max(0)
        return float(max(hi - lo))

    def box(self) -> np.ndarray:
        """(4,) x0, y0, x1, y1 of the landmarks."""
        lo, hi = self.landmarks.min(0), self.landmarks.max(0)
        return np.concatenate([lo, hi])


class FaceObserver:
    """Detector + landmark model with the checks of the module docstring.

    models: verified model files; min_score: detector threshold; min_presence: landmark presence
    threshold; min_face_px, second_face_ratio, max_roll_deg, max_outside: the refusal thresholds;
    threads: interpreter threads.
    """

    def __init__(self, models: ModelPaths, min_score: float = 0.5, min_presence: float = 0.5, min_face_px: float = 40.0,
                 second_face_ratio: float = 0.5, max_roll_deg: float = 45.0, threads: int = 1,
                 max_outside: float = 0.5) -> None:
        self.detector = FaceDetector(str(models.detector), threads, min_score)
        self.mesh = FaceMesh(str(models.landmarks), threads)
        self.min_presence = float(min_presence)
        self.min_face_px = float(min_face_px)
        self.second_face_ratio = float(second_face_ratio)
        self.max_roll = np.deg2rad(max_roll_deg)
        self.max_outside = float(max_outside)

    def _inside(self, found: FaceObservation, size: tuple[int, int]) -> FaceObservation:
        """``found`` when at most ``max_outside`` of its landmarks lie beyond the (W, H) image's edge;
        otherwise raises the ``cut-off`` problem."""
        W, H = size
        xy = found.landmarks
        out = float(((xy[:, 0] < 0) | (xy[:, 0] > W) | (xy[:, 1] < 0) | (xy[:, 1] > H)).mean())
        if out > self.max_outside:
            raise FaceProblem("cut-off", f"the face runs out of the {W}x{H} image ({out:.0%} of its landmarks lie beyond the "
                                         f"edge, more than {self.max_outside:.0%}): keep the whole face in the picture")
        return found

    def _turned(self, image: np.ndarray, above: float = 0.0) -> int | None:
        """The clockwise turn (90, 180, 270) that shows a face with a detector score above ``above``, or
        None. A turned detection counts only when the landmark model confirms it (presence at least
        ``min_presence``): the detector alone finds faces in patterns such as a cup seen sideways."""
        for k, deg in ((1, 270), (2, 180), (3, 90)):
            turned = np.ascontiguousarray(np.rot90(image, k))
            dets = [d for d in self.detector(turned) if d.score > above]
            if dets and abs(dets[0].roll) < self.max_roll and self.mesh(turned, dets[0]).presence >= self.min_presence:
                return deg
        return None

    def _detect_near(self, image: np.ndarray, near: np.ndarray | None) -> list[Detection]:
        """Faces in ``image`` (H, W, 3), best first: the whole image; when it shows none, the region
        around ``near`` (4,) (a neighbouring video frame's face box). The caller runs the tiled search
        (:meth:`FaceDetector.search`) when both find none."""
        dets = self.detector(image)
        if not dets and near is not None:
            dets = self.detector.in_region(image, near)
        return dets

    def _followed(self, image: np.ndarray, previous: np.ndarray | None) -> FaceObservation | None:
        """The face found on the crop from the previous frame's landmarks ``previous`` (468, 2), or None
        when there are none, the landmark model's presence is below ``min_presence`` or the face's eye
        line is tilted beyond ``max_roll_deg``."""
        if previous is None:
            return None
        lm = self.mesh.follow(image, previous)
        if lm.presence < self.min_presence:
            return None
        det = detection_from_landmarks(lm.xy, lm.presence)
        if abs(det.roll) > self.max_roll:
            return None
        return FaceObservation(lm.xy.copy(), lm.presence, det)

    def __call__(self, image: np.ndarray, near: np.ndarray | None = None, previous: np.ndarray | None = None,
                 follow: str = "fallback") -> FaceObservation:
        """image: (H, W, 3) float RGB in [0, 1]; near: (4,) x0, y0, x1, y1 where a neighbouring frame's
        face was (or None); previous: (468, 2) that frame's landmarks (or None); follow: "off",
        "fallback" or "first" (module docstring). Raises FaceProblem."""
        if follow not in FOLLOW_MODES:
            raise ValueError(f"follow must be one of {FOLLOW_MODES}, not {follow!r}")
        H, W = image.shape[:2]
        if follow == "first":
            found = self._followed(image, previous)
            if found is not None:
                return self._inside(found, (W, H))
        dets = self._detect_near(image, near)
        if not dets and follow == "fallback":
            found = self._followed(image, previous)
            if found is not None:
                return self._inside(found, (W, H))
        if not dets:
            dets = self.detector.search(image, self.min_face_px)
        if not dets:
            turn = self._turned(image)
            if turn is not None:
                raise FaceProblem("rotated", f"no upright face, but a face appears when the image is turned {turn}° clockwise: "
                                             "the image is sideways or upside down; rotate it upright")
            raise FaceProblem("no-face", f"no face found in the {W}x{H} image (searched for faces at least "
                                         f"{self.min_face_px:.0f} px wide, seen from the front or the side)")
        dets.sort(key=lambda d: -d.width)
        main = dets[0]
        others = [d for d in dets[1:] if d.width >= self.second_face_ratio * main.width]
        if others:
            where = ", ".join(f"({d.center[0]:.0f}, {d.center[1]:.0f})" for d in [main, *others])
            raise FaceProblem("two-faces", f"{1 + len(others)} faces found (centres at {where} px); crop the image to one person")
        if abs(main.roll) > self.max_roll:
            deg = float(np.rad2deg(main.roll))
            raise FaceProblem("rotated", f"the face is tilted by {deg:+.0f}° in the image plane (more than "
                                         f"{np.rad2deg(self.max_roll):.0f}°): the image is sideways or upside down; rotate it upright")
        if main.score < UNSURE_SCORE:  # an upside-down face can pass for an upright one at a low score
            turn = self._turned(image, main.score + TURNED_MARGIN)
            if turn is not None:
                raise FaceProblem("rotated", f"the face is clearer when the image is turned {turn}° clockwise: the image is "
                                             "sideways or upside down; rotate it upright")
        if main.width < self.min_face_px:
            raise FaceProblem("tiny-face", f"the face is {main.width:.0f} px wide, less than the {self.min_face_px:.0f} px needed; "
                                           "use a larger image or crop closer to the face")
        lm: FaceLandmarks = self.mesh(image, main)
        if lm.presence < self.min_presence:
            found = self._followed(image, previous) if follow == "fallback" else None
            if found is not None:
                return self._inside(found, (W, H))
            raise FaceProblem("no-face", f"the landmark model finds no face in the detected box (presence {lm.presence:.2f})")
        return self._inside(FaceObservation(lm.xy.copy(), lm.presence, main), (W, H))
