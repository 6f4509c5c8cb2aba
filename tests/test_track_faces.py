"""Face detection, dense landmarks and segmentation on a real photograph (scikit-image's astronaut),
and the checks that refuse images without exactly one usable face."""

from __future__ import annotations

import numpy as np
import pytest

from track_helpers import astronaut, models_or_skip

from sage_core.track.detector import INPUT_SIZE, anchor_centres, decode, letterbox
from sage_core.track.faces import FaceObserver, FaceProblem
from sage_core.track.weights import find_models

# the astronaut's face in skimage.data.astronaut() (512x512): eyes near (205, 108) and (245, 105),
# mouth near (225, 160); measured by hand on the image
FACE_BOX = (175, 70, 280, 185)


@pytest.fixture(scope="module")
def observer():
    return FaceObserver(find_models(models_or_skip()))


def test_anchors_and_decoding():
    a = anchor_centres()
    assert a.shape == (896, 2)
    assert np.allclose(a[0], [0.5 / 16, 0.5 / 16]) and np.allclose(a[1], a[0]) and np.allclose(a[512], [1 / 16, 1 / 16])
    reg = np.zeros((896, 16), np.float32)
    logits = np.full(896, -20.0, np.float32)
    # two overlapping anchors vote for one face, a third far away for another
    for k, dx in ((300, 0.0), (301, 2.0), (700, 0.0)):
        logits[k] = 3.0
        reg[k, :4] = [dx, 0.0, 40.0, 40.0]
        reg[k, 4:] = np.tile([-10.0, -8.0], 6)
    dets = decode(reg, logits, 0.5)
    assert len(dets) == 2
    assert dets[0].box[2] - dets[0].box[0] == pytest.approx(40 / INPUT_SIZE, abs=1e-6)
    assert dets[0].keypoints.shape == (6, 2)
    sq, scale, off = letterbox(np.ones((50, 100, 3), np.float32), 128)
    assert sq.shape == (128, 128, 3) and scale == pytest.approx(1.28) and off[1] == 32 and sq[0, 0, 0] == 0


def test_astronaut_face_and_landmarks(observer):
    img = astronaut()
    obs = observer(img)
    x0, y0, x1, y1 = FACE_BOX
    cx, cy = obs.detection.center
    assert x0 < cx < x1 and y0 < cy < y1
    assert obs.presence > 0.9 and abs(np.degrees(obs.detection.roll)) < 15
    lm = obs.landmarks
    assert lm.shape == (468, 2)
    assert lm[33, 0] < lm[263, 0]  # the subject's right eye on the image's left
    assert lm[10, 1] < lm[1, 1] < lm[13, 1] < lm[152, 1]  # forehead, nose tip, lips, chin from top to bottom
    assert x0 - 20 < lm[:, 0].min() and lm[:, 0].max() < x1 + 20 and y0 - 20 < lm[:, 1].min() and lm[:, 1].max() < y1 + 20


def test_segmentation_of_the_astronaut():
    from sage_core.track.segmenter import Segmenter

    seg = Segmenter(str(find_models(models_or_skip()).segmenter))
    p = seg(astronaut())
    assert p.shape == (512, 512)
    assert p[130, 225] > 0.8  # the face
    assert p[240, 230] > 0.5  # the suit
    assert p[20, 480] < 0.3 and p[200, 40] < 0.5  # the wall, the flag


def _problem(observer, img, *args) -> FaceProblem:
    with pytest.raises(FaceProblem) as e:
        observer(img, *args)
    return e.value


def test_refusals(observer):
    img = astronaut()
    assert _problem(observer, np.ones((300, 300, 3), np.float32)).kind == "no-face"
    turned = _problem(observer, np.ascontiguousarray(np.rot90(img)))
    assert turned.kind == "rotated" and "rotate" in turned.message
    face = img[40:220, 130:320]
    two = np.concatenate([face, face], 1)
    p = _problem(observer, two)
    assert p.kind == "two-faces" and "2 faces" in p.message
    import cv2

    small = cv2.resize(face, (48, 45), interpolation=cv2.INTER_AREA)  # the detector still finds a 24 px face
    canvas = np.ones((96, 96, 3), np.float32)
    canvas[25:70, 24:72] = small
    p = _problem(observer, canvas)
    assert p.kind == "tiny-face" and "px wide, less than the 40 px needed" in p.message


def test_tiles_cover_the_image_and_their_central_halves_leave_no_gap():
    from sage_core.track.detector import tile_starts

    for length, side in ((128, 128), (300, 128), (1000, 128), (129, 128), (64, 128)):
        starts = tile_starts(length, side)
        assert starts[0] == 0 and starts == sorted(set(starts))
        if length <= side:
            assert starts == [0]
            continue
        assert starts[-1] == length - side and all(b - a <= side // 2 for a, b in zip(starts, starts[1:]))
        # the half each tile answers for (to the edge for the outer tiles) reaches the next one's
        ends = [s + 3 * side / 4 for s in starts[:-1]]
        begins = [s + side / 4 for s in starts[1:]]
        assert all(b <= e for b, e in zip(begins, ends))


def _pasted(size: int, canvas_hw: tuple[int, int], corners: list[tuple[int, int]]) -> np.ndarray:
    """The astronaut shrunk to size×size, pasted at the (x, y) corners of a grey canvas."""
    import cv2

    small = cv2.resize(astronaut(), (size, size), interpolation=cv2.INTER_AREA)
    canvas = np.full(canvas_hw + (3,), 0.55, np.float32)
    for x, y in corners:
        canvas[y:y + size, x:x + size] = small
    return canvas


def test_a_small_face_in_a_large_image_is_found_by_the_tiled_search(observer):
    # a person a few metres away: the face about 47 px wide in a 1200x1600 picture, too small for
    # the whole-image pass, which letterboxes the picture into 128 px
    size, x, y = 256, 700, 900
    img = _pasted(size, (1600, 1200), [(x, y)])
    assert observer.detector(img) == []
    obs = observer(img)
    k = size / 512
    x0, y0, x1, y1 = FACE_BOX
    cx, cy = obs.detection.center
    assert x + x0 * k < cx < x + x1 * k and y + y0 * k < cy < y + y1 * k
    assert obs.presence > 0.9 and 35 < obs.detection.width < 70
    lm = obs.landmarks
    assert lm[33, 0] < lm[263, 0] and lm[10, 1] < lm[1, 1] < lm[152, 1]
    assert x + (x0 - 20) * k < lm[:, 0].min() and lm[:, 0].max() < x + (x1 + 20) * k


def test_the_tiled_search_refuses_two_small_faces_and_finds_none_in_an_empty_picture(observer):
    p = _problem(observer, _pasted(256, (1600, 1200), [(100, 900), (760, 300)]))
    assert p.kind == "two-faces" and "2 faces" in p.message
    p = _problem(observer, np.full((1600, 1200, 3), 0.55, np.float32))
    assert p.kind == "no-face" and "at least 40 px wide" in p.message


def test_a_video_frame_is_searched_first_where_the_previous_face_was(observer):
    size, x, y = 256, 700, 900
    img = _pasted(size, (1600, 1200), [(x, y)])
    first = observer(img)
    near = observer.detector.in_region(img, first.detection.box)
    assert near and abs(near[0].center - first.detection.center).max() < 6
    again = observer(img, first.detection.box)
    assert np.abs(again.landmarks - first.landmarks).max() < 3.0
    # a box far from the face finds nothing there, and the search still finds the face
    assert observer.detector.in_region(img, np.array([40.0, 40.0, 90.0, 90.0])) == []
    assert abs(observer(img, np.array([40.0, 40.0, 90.0, 90.0])).detection.center - first.detection.center).max() < 6


def test_a_video_frame_the_detector_misses_is_followed_from_the_previous_landmarks(observer, monkeypatch):
    """follow="fallback": a frame whose detection yields no face is looked at on the crop from the
    previous frame's landmarks; without them (or with follow="off") it is dropped as before. A shifted
    frame is followed to where the face went."""
    img = astronaut()
    first = observer(img)
    shifted = np.roll(img, (6, -9), axis=(0, 1))
    monkeypatch.setattr(type(observer.detector), "__call__", lambda self, *a, **k: [])
    monkeypatch.setattr(type(observer.detector), "search", lambda self, *a, **k: [])
    followed = observer(shifted, None, first.landmarks, "fallback")
    assert followed.presence > 0.9
    assert np.abs(followed.landmarks - (first.landmarks + [-9, 6])).mean() < 2.0
    assert np.allclose(followed.detection.box, [*followed.landmarks.min(0), *followed.landmarks.max(0)])
    assert abs(np.degrees(followed.detection.roll)) < 15
    for previous, follow in ((None, "fallback"), (first.landmarks, "off")):
        with pytest.raises(FaceProblem) as e:
            observer(shifted, None, previous, follow)
        assert e.value.kind == "no-face"


def test_follow_first_uses_the_previous_landmarks_before_the_detector(observer, monkeypatch):
    img = astronaut()
    first = observer(img)
    calls = []
    real = type(observer.detector).__call__
    monkeypatch.setattr(type(observer.detector), "__call__", lambda self, *a, **k: calls.append(1) or real(self, *a, **k))
    followed = observer(img, first.detection.box, first.landmarks, "first")
    assert calls == [] and np.abs(followed.landmarks - first.landmarks).mean() < 2.0
    # a crop with no face in it (the landmarks moved far off the face) falls back to the detector
    away = first.landmarks + [-170.0, 300.0]
    again = observer(img, first.detection.box, away, "first")
    assert calls and np.abs(again.landmarks - first.landmarks).mean() < 1.0


def test_a_face_mostly_beyond_the_images_edge_is_refused_as_cut_off(observer):
    """The astronaut's photo cut through her face: with 30 % of the landmarks beyond the edge the face is
    kept; followed into a cut that leaves more than half of them beyond it, it is refused as cut off (a
    sequence drops that frame) instead of trusting the landmark model's guesses."""
    img = astronaut()
    full = observer(img)
    kept = observer(np.ascontiguousarray(img[:, 210:]))
    assert 0.2 < float((kept.landmarks[:, 0] < 0).mean()) < 0.5
    cut = np.ascontiguousarray(img[:, 230:])
    p = _problem(observer, cut, None, full.landmarks - [230, 0], "fallback")
    assert p.kind == "cut-off" and "beyond the edge, more than 50%" in p.message and "282x512" in p.message
    lenient = FaceObserver(find_models(models_or_skip()), max_outside=0.8)
    assert lenient(cut, None, full.landmarks - [230, 0], "fallback").presence > 0.5
