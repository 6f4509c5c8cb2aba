"""Foreground masks of the head: segmentation, background keying, the mesh's silhouette, the neck line.

- :func:`person_probability`: MediaPipe's person segmentation; when the image has a uniform
  background (its border is one colour, as in studio captures and matted exports) the matte keyed
  on that colour replaces it inside a dilation of the segmentation (which alone tends to invent
  shoulders below a blanked neck).
- :func:`refine_mask`: the final mask of a tracked image: every pixel the fitted mesh covers, plus the
  person pixels near the mesh (hair around the head); on images without a uniform background the
  pixels whose colour goes with the background around them go back to it (:func:`colour_cut`; the
  fit's person map was cut the same way around the detected face, :func:`person_colour_cut`), the
  mesh's pixels near its outline that the person map left out included (a fitted jaw wider than the
  head), times the neck-line mask from the fitted mesh (VHAP's rule: keep what lies above the line
  through the neck's sides, blurred).
"""

from __future__ import annotations

import numpy as np

from ..data.cameras import Camera

BORDER = 3
"""Pixels of the image border that define its background colour."""
UNIFORM_FRACTION = 0.92
"""Share of the border pixels within :data:`KEY_TOLERANCE` of the border's median colour that makes a
background uniform."""
KEY_TOLERANCE = 0.06


def background_key(image: np.ndarray) -> np.ndarray | None:
    """(H, W) float32 matte keyed on a uniform background colour, or None when the border is not uniform."""
    b = BORDER
    border = np.concatenate([image[:b].reshape(-1, 3), image[-b:].reshape(-1, 3), image[:, :b].reshape(-1, 3),
                             image[:, -b:].reshape(-1, 3)])
    ref = np.median(border, axis=0)
    if np.mean(np.linalg.norm(border - ref, axis=1) < KEY_TOLERANCE) < UNIFORM_FRACTION:
        return None
    import cv2

    dist = np.linalg.norm(image[..., :3] - ref, axis=-1).astype(np.float32)
    # coverage of an edge pixel: its distance from the background over that of the foreground nearby
    full = cv2.dilate(dist, np.ones((5, 5), np.uint8))
    alpha = np.where(full > 2 * KEY_TOLERANCE, dist / np.maximum(full, 1e-6), 0.0)
    return np.clip(alpha * (dist > KEY_TOLERANCE * 0.5), 0.0, 1.0).astype(np.float32)


def person_probability(image: np.ndarray, segmentation: np.ndarray) -> tuple[np.ndarray, str]:
    """(H, W) float32 person probability and how it was made ("keyed" or "segmented").

    image: (H, W, 3) in [0, 1]; segmentation: (H, W) from :class:`.segmenter.Segmenter`.
    """
    import cv2

    key = background_key(image)
    if key is None:
        return segmentation.astype(np.float32), "segmented"
    H, W = segmentation.shape
    r = max(3, int(0.04 * max(H, W))) | 1
    near = cv2.dilate((segmentation > 0.5).astype(np.uint8), np.ones((r, r), np.uint8)) > 0
    return (key * near).astype(np.float32), "keyed"


def neck_line_mask(vertices: np.ndarray, ids: tuple[int, int, int], camera: Camera) -> np.ndarray:
    """(H, W) float32 in [0, 1]: VHAP's neck-line cut on the fitted mesh (:func:`sage_core.data.neck_line.neck_line_cut`)."""
    from ..data.neck_line import neck_line_cut

    return neck_line_cut(vertices, ids, camera)


COLOUR_CUT_SIZE = 320
"""Longer side (pixels) the colour cut works at; larger images are cut at this size and the decision
scaled back (the mask keeps its own edges)."""


RING = 0.1
"""Width of the background ring the colour cut models, in face heights (at least 3 pixels)."""


def ring_band(face_height: float) -> int:
    """The colour cut's background ring in pixels for a face ``face_height`` pixels high (:data:`RING`)."""
    return max(3, round(RING * face_height))


def colour_cut(image: np.ndarray, mask: np.ndarray, sure: np.ndarray, band: int, iterations: int = 3) -> np.ndarray:
    """(H, W) bool: the pixels of ``mask > 0.5`` whose colour goes with the foreground.

    A graph cut on colour models (OpenCV's GrabCut) decides the pixels the mask holds but ``sure`` (the
    fitted mesh's coverage) does not: it models the foreground from the mask and the background from a
    ``band``-pixel ring outside it, so a patch of background that the segmentation took for the person
    (a gap between hair and collar, a wall beside the neck) goes back to the background. It only
    removes: ``sure`` stays, and nothing outside the mask is added.
    """
    import cv2

    fg = mask > 0.5
    if not fg.any() or fg.all():
        return fg
    H, W = mask.shape
    scale = COLOUR_CUT_SIZE / max(H, W)
    if scale < 1.0:
        size = (max(1, round(W * scale)), max(1, round(H * scale)))
        small = colour_cut(cv2.resize(image[..., :3], size, interpolation=cv2.INTER_AREA),
                           cv2.resize(mask, size, interpolation=cv2.INTER_AREA),
                           cv2.resize(sure.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0,
                           max(1, round(band * scale)), iterations)
        return fg & ((cv2.resize(small.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0) | sure)
    ring = cv2.dilate(fg.astype(np.uint8), np.ones((2 * band + 1, 2 * band + 1), np.uint8)) > 0
    gc = np.full(mask.shape, cv2.GC_BGD, np.uint8)
    gc[ring] = cv2.GC_PR_BGD
    gc[fg] = cv2.GC_PR_FGD
    gc[sure] = cv2.GC_FGD
    if not (gc == cv2.GC_PR_BGD).any():
        return fg
    img8 = (np.clip(image[..., :3], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(img8, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return fg
    return fg & ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD))


def person_colour_cut(image: np.ndarray, person: np.ndarray, landmarks: np.ndarray, face_height: float) -> np.ndarray:
    """The person probability (H, W) with the pixels :func:`colour_cut` hands back to the background set
    to 0, the detected face (the landmarks' hull) fixed as the person: the silhouette the fit pulls the
    mesh to then follows the head rather than a patch of background the segmentation kept.

    image: (H, W, 3) in [0, 1]; landmarks: (K, 2) pixel positions in the same image; face_height: pixels.
    """
    import cv2

    hull = cv2.convexHull(np.round(landmarks).astype(np.int32))
    face = np.zeros(person.shape, np.uint8)
    cv2.fillConvexPoly(face, hull, 1)
    sure = (face > 0) & (person > 0.5)
    if not sure.any():
        return person
    keep = colour_cut(image, person, sure, band=ring_band(face_height))
    return np.where(keep | sure, person, 0.0).astype(np.float32)


def wants_colour_cut(mode: str, how: str) -> bool:
    """Whether an image's person pixels are checked by colour (:func:`person_colour_cut`,
    :func:`refine_mask`): ``mode`` on / off, or auto: when :func:`person_probability` found no uniform
    background to key on (``how`` "segmented"; a keyed matte has no such patches)."""
    return mode == "on" or (mode == "auto" and how == "segmented")


MESH_EDGE_CHECK = 0.15
"""Depth (face heights) from the fitted mesh's outline within which its pixels that the person map
leaves out are checked by colour (:func:`refine_mask`); deeper ones are a hole in the segmentation."""


def refine_mask(person: np.ndarray, mesh_coverage: np.ndarray, neck: np.ndarray | None, face_height: float,
                hair_reach: float = 0.35, image: np.ndarray | None = None) -> np.ndarray:
    """The written foreground mask (H, W) float32 in [0, 1].

    person: person probability; mesh_coverage: (H, W) in [0, 1], the fitted mesh's coverage; neck: the
    neck-line mask or None; face_height: pixels; hair_reach: person pixels further than this many
    face heights from the mesh are dropped (other people, furniture, long hair far off the head);
    image: (H, W, 3) in [0, 1], when given the pixels are checked by colour (:func:`colour_cut`): the
    person pixels off the mesh, and the mesh's pixels near its outline (:data:`MESH_EDGE_CHECK`) that
    the person map leaves out (more than one pixel from it); the mesh's other pixels stay.
    """
    import cv2
    from scipy.ndimage import distance_transform_edt

    covered = mesh_coverage > 0.5
    if covered.any():
        dist = distance_transform_edt(~covered)
        near = dist <= hair_reach * face_height
    else:
        near = np.ones_like(covered)
    m = np.maximum(person * near, mesh_coverage)
    if image is not None and covered.any():
        # the mesh's pixels are taken on trust where the person map also has the person, or deep inside
        # the mesh (a hole in the segmentation); near the mesh's outline where it does not (a fitted jaw
        # or ear wider than the head beside a short haircut) the colour decides
        seen = cv2.dilate((person > 0.5).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        trusted = seen | (distance_transform_edt(covered) > MESH_EDGE_CHECK * face_height)
        sure = cv2.erode((covered & trusted).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        keep = colour_cut(image, m, sure, band=ring_band(face_height))
        m = np.where(keep | sure, m, np.minimum(m, mesh_coverage * trusted))
    # close pinholes the segmentation leaves inside the head
    m = np.maximum(m, cv2.morphologyEx((m > 0.5).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)).astype(np.float32) * (m > 0.2))
    if neck is not None:
        m = m * neck
    return np.clip(m, 0.0, 1.0).astype(np.float32)
