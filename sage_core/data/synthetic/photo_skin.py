"""A photograph as the skin of a detailed synthetic subject (``sage synth --set skin_photo=CAP``).

The procedural skin of :mod:`.detail` matches a real face's contrast band by band, but not its
structure: real pores, freckles, brows, lashes and lips are arranged as no noise field arranges
them. For a check on real skin, a photograph tracked by ``sage track`` with a FLAME-format model of
the same head grid (a one-photo capture, CAP) gives the face its colours: the tracked mesh is
posed with the capture's parameters and projected into the photo; every face vertex the photo sees
(in front of the z-buffer of the tracked mesh, turned towards the camera) takes the photo's
coordinates there, and the renderer samples the photo at the interpolated coordinates, blended
with the procedural skin by a weight that fades over a few rings of vertices at the edge of what
the photo shows. The photo carries its own light, which the subject's world light then shades
again; the procedural skin tone is set to the photo's median face colour so the two meet without a
step. Only the skin of the face takes the photo: eyes, mouth interior, scalp hair and the hair
volume stay procedural.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import ConfigError
from ...geometry.topology import edges
from ..cameras import Camera
from .mesh_render import rasterize, vertex_normals

MIN_FACING = 0.3
"""A vertex whose normal turns further than acos(0.3) ≈ 73° from the photo's camera is not taken from it."""
DEPTH_TOLERANCE_M = 0.003
"""A vertex further behind the photo's z-buffer than this is occluded."""
MASK_MARGIN_PX = 2
"""A vertex counts only this many pixels inside the photo's foreground mask (its outline is uncertain)."""
FEATHER_RINGS = 2
"""Vertex rings inside the edge of what the photo shows over which its weight rises from 0 to 1."""


@dataclass
class PhotoSkin:
    """Per-vertex photo coordinates of a head mesh and the photo.

    Attributes:
        image: (H, W, 3) float64 photo in [0, 1].
        uv: (V, 2) pixel coordinates (x, y; pixel centres at +0.5) of every head vertex in the photo.
        weight: (V,) in [0, 1]: 1 where the photo shows the vertex's face skin, 0 where it does not.
        median_rgb: (3,) median photo colour over the vertices of weight 1.
        source: the capture folder's name (for the capture's info.json).
    """

    image: np.ndarray
    uv: np.ndarray
    weight: np.ndarray
    median_rgb: np.ndarray
    source: str

    def sample(self, uv: np.ndarray) -> np.ndarray:
        """(M, 2) pixel coordinates -> (M, 3) bilinear photo colours (clamped at the border)."""
        H, W = self.image.shape[:2]
        x = np.clip(uv[:, 0] - 0.5, 0.0, W - 1.0)
        y = np.clip(uv[:, 1] - 0.5, 0.0, H - 1.0)
        x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        im = self.image
        top = im[y0, x0] * (1 - fx) + im[y0, x1] * fx
        bottom = im[y1, x0] * (1 - fx) + im[y1, x1] * fx
        return top * (1 - fy) + bottom * fy


def ring_distance(inside: np.ndarray, faces: np.ndarray, most: int) -> np.ndarray:
    """(V,) bool, (F, 3) -> (V,) int: for every vertex of ``inside`` the number of mesh edges to the
    nearest vertex outside it (1 on its border), capped at ``most``; 0 outside."""
    e = edges(faces)
    e = np.concatenate([e, e[:, ::-1]])
    d = np.where(inside, most, 0).astype(np.int64)
    for k in range(1, most):
        near = np.full(inside.shape[0], most, np.int64)
        np.minimum.at(near, e[:, 0], d[e[:, 1]])
        d = np.where(inside & (near == k - 1) & (d == most), k, d)
    return d


def photo_weights(vertices: np.ndarray, faces: np.ndarray, camera: Camera, face_vertices: np.ndarray,
                  mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Photo coordinates (V, 2) and weights (V,) of a posed mesh seen by ``camera``.

    vertices: (V, 3) the tracked mesh in the photo's world; faces: (F, 3); face_vertices: (V,) bool,
    the face's skin; mask: (H, W) the photo's foreground in [0, 1] (None: all). A vertex counts when
    it is face skin, inside the mask by :data:`MASK_MARGIN_PX` pixels, turned towards the camera by at least
    :data:`MIN_FACING` and not behind the mesh's z-buffer (by :data:`DEPTH_TOLERANCE_M` plus a few
    of the z-buffer's depth steps); its weight rises with its distance in rings from the nearest
    vertex that does not count (1/3 on the border, 1 from :data:`FEATHER_RINGS` + 1 rings in).
    """
    uv, depth = camera.project(vertices)
    # the z-buffer at 512 px or more, compared with a tolerance of a few of its pixels' depth steps
    scale = max(1, math.ceil(512 / camera.height))
    frag = rasterize(vertices, faces, camera, scale)
    H, W = frag.depth.shape
    xi = np.clip(np.floor(uv[:, 0] * scale).astype(np.int64), 0, W - 1)
    yi = np.clip(np.floor(uv[:, 1] * scale).astype(np.int64), 0, H - 1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    tol = DEPTH_TOLERANCE_M + 4.0 * np.abs(depth) / (float(camera.K[0, 0]) * scale)
    visible = inside & (depth <= frag.depth[yi, xi] + tol) & (depth > 0)
    if mask is not None:  # the tracked mesh may be wider than the person: its outline takes the backdrop
        from scipy.ndimage import minimum_filter

        core = minimum_filter(np.asarray(mask, np.float64), size=2 * MASK_MARGIN_PX + 1, mode="nearest") > 0.5
        mi = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, core.shape[1] - 1)
        mj = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, core.shape[0] - 1)
        visible &= core[mj, mi]
    to_cam = np.asarray(camera.center)[None, :] - vertices
    to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-12)
    # |cos|: the winding may put the normals either way; the z-buffer test removes the far side
    facing = np.abs(np.einsum("ij,ij->i", vertex_normals(vertices, faces), to_cam))
    ok = face_vertices & visible & (facing >= MIN_FACING)
    d = ring_distance(ok, faces, FEATHER_RINGS + 1)
    return uv, np.clip(d / (FEATHER_RINGS + 1.0), 0.0, 1.0)


def load_photo_skin(capture: str | Path, model: str | Path | None, n_vertices: int, faces: np.ndarray,
                    face_vertices: np.ndarray) -> PhotoSkin:
    """The photo skin of a one-photo ``sage track`` capture for a head with ``n_vertices`` vertices and
    ``faces`` (F, 3); face_vertices: (V,) bool. model: the FLAME-format model the photo was tracked
    with (None: the one the capture's track/report.json names). Raises ConfigError naming the file
    when the capture or model does not fit."""
    import torch

    from ...flame import FlameModel, load_flame_model
    from ..capture import read_capture
    from ..imageio import read_image

    root = Path(capture)
    if not (root / "transforms.json").is_file():
        raise ConfigError(f"skin_photo: {root} is not a capture folder (no transforms.json)")
    if model is None:
        report = root / "track" / "report.json"
        if not report.is_file():
            raise ConfigError(f"skin_photo: {root} has no track/report.json naming its FLAME model; give skin_photo_model")
        model = json.loads(report.read_text())["flame_model"]
    model_path = Path(model)
    if not model_path.is_file():
        raise ConfigError(f"skin_photo_model: {model_path} not found (the FLAME-format model {root} was tracked with)")
    cap = read_capture(root, check_images=False)
    if len(cap.frames) != 1:
        raise ConfigError(f"skin_photo: {root} holds {len(cap.frames)} images; it needs a one-photo capture (sage track of one image)")
    flame = FlameModel(load_flame_model(model_path), dtype=torch.float64)
    if flame.n_vertices != n_vertices:
        raise ConfigError(f"skin_photo_model: {model_path} has {flame.n_vertices} vertices, this head {n_vertices}: "
                          "track the photo with a model of the same preset (sage synth --preset ...)")
    with torch.no_grad():
        kw = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in cap.params.to_torch(dtype=torch.float64).items()}
        verts = flame(**kw).vertices[0].numpy()
    frame = cap.frames[0]
    image = read_image(frame.image_path)[..., :3].astype(np.float32).astype(np.float64)  # as a capture stores it
    cam = frame.camera
    if (cam.width, cam.height) != (image.shape[1], image.shape[0]):
        cam = cam.resized(image.shape[1], image.shape[0])
    mask = read_image(frame.mask_path)[..., 0] if frame.mask_path is not None and frame.mask_path.is_file() else None
    if mask is not None and mask.shape != image.shape[:2]:
        raise ConfigError(f"skin_photo: {frame.mask_path} is {mask.shape[1]}x{mask.shape[0]}, its image {image.shape[1]}x{image.shape[0]}")
    uv, w = photo_weights(verts, faces, cam, face_vertices, mask)
    full = w > 0.999
    if full.sum() < max(10, 0.1 * face_vertices.sum()):
        raise ConfigError(f"skin_photo: the photo of {root} shows only {int(full.sum())} of the tracked mesh's "
                          f"{int(face_vertices.sum())} face vertices")
    skin = PhotoSkin(image=image, uv=uv, weight=w, median_rgb=np.zeros(3), source=root.name)
    skin.median_rgb = np.median(skin.sample(uv[full]), axis=0)
    return skin


PHOTO_SKIN_FILE = "skin_photo.npz"
"""Where a capture keeps its photo skin (under ``gt/``), so the subject is rebuilt without the photo's
capture (the tracking ceiling)."""


def save_photo_skin(skin: PhotoSkin, path: str | Path) -> Path:
    """Write ``skin`` to an npz file (float32 image, coordinates and weights; float64 median)."""
    import io

    from ...atomic import atomic_write_bytes

    buf = io.BytesIO()
    np.savez_compressed(buf, image=skin.image.astype(np.float32), uv=skin.uv.astype(np.float64),
                        weight=skin.weight.astype(np.float64), median_rgb=skin.median_rgb.astype(np.float64),
                        source=np.array(skin.source))
    return atomic_write_bytes(Path(path), buf.getvalue())


def read_photo_skin(path: str | Path) -> PhotoSkin:
    """Inverse of :func:`save_photo_skin`; raises ConfigError naming the file when it is missing."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: not found (the capture's photo skin)")
    with np.load(p, allow_pickle=False) as z:
        return PhotoSkin(image=z["image"].astype(np.float64), uv=z["uv"], weight=z["weight"], median_rgb=z["median_rgb"],
                         source=str(z["source"]))
