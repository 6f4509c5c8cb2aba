"""Procedural appearance of the synthetic head and its shaded rendering.

The albedo is a function of the *template* position (and, on the eyeballs, of the direction from
the eyeball centre), interpolated per pixel, so it sticks to the skin whatever the identity,
expression or pose. Shading is Lambert plus ambient under one light fixed in the world,
optionally with Blinn-Phong highlights on skin and eyes (the ground truth of tracked captures).
Expression creases darken the skin where the surface is compressed relative to the neutral face
(per-vertex area ratio), in fine line patterns on the forehead and around the mouth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..cameras import Camera
from ._fields import fbm, gauss, smoothstep, value_noise
from .detail import DetailStyle
from .head import PART_LEFT_EYE, PART_MOUTH, PART_RIGHT_EYE, HeadModel, hair_weight
from .mesh_render import downsample, rasterize, vertex_normals
from .shading import AMBIENT, DIFFUSE, LIGHT_DIR, Render, Specular, _eye_albedo, _mix, _pixel_dirs

if TYPE_CHECKING:
    from .hair import PosedHair
    from .mouth import PosedMouth
    from .photo_skin import PhotoSkin

_SKIN_TONES = np.array(
    [[0.93, 0.76, 0.66], [0.85, 0.64, 0.52], [0.72, 0.52, 0.40], [0.55, 0.38, 0.28], [0.95, 0.80, 0.72], [0.80, 0.60, 0.47]]
)
_HAIR = np.array([[0.10, 0.07, 0.05], [0.28, 0.17, 0.09], [0.55, 0.40, 0.22], [0.05, 0.05, 0.06], [0.45, 0.20, 0.10]])
_IRIS = np.array([[0.25, 0.40, 0.60], [0.35, 0.22, 0.10], [0.30, 0.45, 0.25], [0.20, 0.13, 0.08]])


@dataclass(frozen=True)
class Appearance:
    """Colours (linear RGB in [0, 1]) and noise seed of one synthetic subject; ``detail`` is the
    pixel-scale detail of a detailed subject (:mod:`.detail`), None for the smooth head."""

    skin: tuple[float, float, float]
    hair: tuple[float, float, float]
    iris: tuple[float, float, float]
    lips: tuple[float, float, float]
    noise_seed: int
    detail: DetailStyle | None = None
    photo: PhotoSkin | None = None

    def to_dict(self) -> dict:
        d = {"skin": list(self.skin), "hair": list(self.hair), "iris": list(self.iris), "lips": list(self.lips), "noise_seed": self.noise_seed}
        if self.detail is not None:
            d["detail"] = self.detail.to_dict()
        if self.photo is not None:
            d["skin_photo"] = self.photo.source
        return d


def sample_appearance(rng: np.random.Generator) -> Appearance:
    """Draw a subject's colours from ``rng``."""
    skin = _SKIN_TONES[rng.integers(len(_SKIN_TONES))] * rng.uniform(0.95, 1.05, 3)
    hair = _HAIR[rng.integers(len(_HAIR))] * rng.uniform(0.85, 1.15, 3)
    iris = _IRIS[rng.integers(len(_IRIS))] * rng.uniform(0.85, 1.15, 3)
    lips = skin * np.array([0.88, 0.55, 0.55]) * rng.uniform(0.9, 1.05)
    t = lambda a: tuple(float(x) for x in np.clip(a, 0.0, 1.0))  # noqa: E731
    return Appearance(t(skin), t(hair), t(iris), t(lips), int(rng.integers(0, 2**31 - 1)))


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """One third of the incident triangle areas per vertex. vertices: (V, 3) -> (V,)."""
    tri = vertices[faces]
    a = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    out = np.zeros(vertices.shape[0])
    for k in range(3):
        np.add.at(out, faces[:, k], a / 3.0)
    return out


def crease_weights(deformed: np.ndarray, neutral: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-vertex compression in [0, 1]: 0 where the area did not shrink, 1 at ≥ 25 % shrinkage.

    deformed, neutral: (V, 3) the same mesh with and without the expression -> (V,).
    """
    ratio = vertex_areas(deformed, faces) / np.maximum(vertex_areas(neutral, faces), 1e-20)
    return np.clip((1.0 - ratio) / 0.25, 0.0, 1.0)


def albedo(template_pos: np.ndarray, eye_dir: np.ndarray, part_w: np.ndarray, mouth_depth: np.ndarray,
           crease: np.ndarray, app: Appearance, mouth_y: float) -> np.ndarray:
    """Albedo of M surface points.

    template_pos: (M, 3); eye_dir: (M, 3) direction from the eyeball centre (eyeball points);
    part_w: (M, 3) weights of (eyeball, mouth interior, skin); mouth_depth: (M,); crease: (M,)
    -> (M, 3) linear RGB.
    """
    p = template_pos
    skin_px = part_w[:, 2] > 0
    eye_px = part_w[:, 0] > 0
    M = p.shape[0]
    col = np.zeros((M, 3))
    eye = np.zeros((M, 3))
    if skin_px.any():
        col[skin_px] = _skin_albedo(p[skin_px], crease[skin_px], app, mouth_y)
    if eye_px.any():
        eye[eye_px] = _eye_albedo(eye_dir[eye_px], app)
    mouth = np.array([0.45, 0.12, 0.12])[None] * (1.0 - 0.75 * np.clip(mouth_depth, 0, 1))[:, None]
    out = col * part_w[:, 2:3] + eye * part_w[:, 0:1] + mouth * part_w[:, 1:2]
    return np.clip(out, 0.0, 1.0)


def _skin_albedo(p: np.ndarray, crease: np.ndarray, app: Appearance, mouth_y: float) -> np.ndarray:
    """Skin, lips, brows and scalp hair at template points p: (M, 3) -> (M, 3)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    s = app.noise_seed
    skin = np.asarray(app.skin)
    n_low = fbm(p, 45.0, s, 2) - 0.5
    col = skin[None] * (1.0 + 0.16 * n_low)[:, None]
    pores = value_noise(p, 1400.0, s + 7)
    col *= (1.0 - 0.06 * smoothstep(pores, 0.6, 0.9))[:, None]
    front = smoothstep(z, 0.0, 0.04)
    blush = 0.5 * gauss(ax - 0.043, 0.014) * gauss(y + 0.005, 0.012) * front
    col = _mix(col, col * np.array([1.08, 0.82, 0.8]), blush)
    up = 0.0085 - 0.002 * gauss(x, 0.004)
    lip_band = np.where(y >= mouth_y, smoothstep(y - mouth_y, up, up - 0.002), smoothstep(mouth_y - y, 0.0105, 0.0085))
    lip = lip_band * smoothstep(ax, 0.026, 0.021) * front
    col = _mix(col, np.asarray(app.lips)[None] * (1.0 + 0.1 * n_low)[:, None], lip)
    nostril = gauss(ax - 0.0075, 0.0028) * gauss(y + 0.0125, 0.002) * front
    col *= (1.0 - 0.55 * nostril)[:, None]
    yb = 0.048 + 0.0045 * (1.0 - np.square((ax - 0.034) / 0.02))
    brow = gauss(y - yb, 0.0028) * smoothstep(ax, 0.058, 0.05) * smoothstep(ax, 0.008, 0.013) * front
    b = brow > 1e-3
    if b.any():
        brow[b] *= 0.55 + 0.45 * value_noise(p[b] * np.array([1.0, 6.0, 1.0]), 900.0, s + 3)
    col = _mix(col, np.asarray(app.hair)[None] * 1.2, np.clip(brow, 0, 1))
    hw = hair_weight(p)
    h = hw > 1e-3
    if h.any():
        ph = p[h]
        phi = np.arctan2(ph[:, 0], ph[:, 2] + 0.005)
        stripes = 0.72 + 0.28 * np.sin(phi * 260.0 + 9.0 * fbm(ph, 30.0, s + 11, 2)) * (0.6 + 0.4 * value_noise(ph, 300.0, s + 13))
        hair = np.asarray(app.hair)[None] * stripes[:, None] * (1.0 + 0.3 * n_low[h])[:, None]
        col[h] = _mix(col[h], hair, hw[h])
    lines = 0.55 + 0.45 * np.cos(2 * np.pi * y / 0.0045 + 3.0 * n_low)
    forehead = smoothstep(y, 0.045, 0.055)
    crease_shade = crease * (forehead * lines + (1.0 - forehead) * 0.8) * (1.0 - hw)
    return col * (1.0 - 0.5 * np.clip(crease_shade, 0.0, 1.0))[:, None]


def highlights(spec: Specular, template_pos: np.ndarray, part_w: np.ndarray, normal: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
    """Specular intensity (M,) at M surface points.

    template_pos: (M, 3); part_w: (M, 3) one-hot (eyeball, mouth interior, skin); normal: (M, 3)
    unit normals facing the camera; view_dirs: (M, 3) unit ray directions from the camera.
    """
    h = LIGHT_DIR[None] - view_dirs
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    nh = np.clip(np.einsum("ij,ij->i", normal, h), 0.0, 1.0)
    lit = (normal @ LIGHT_DIR > 0).astype(np.float64)
    skin = spec.skin * part_w[:, 2] * (1.0 - hair_weight(template_pos)) * nh**spec.skin_shininess
    eye = spec.eye * part_w[:, 0] * nh**spec.eye_shininess
    return (skin + eye) * lit


def render_head(head: HeadModel, vertices: np.ndarray, camera: Camera, app: Appearance,
                crease: np.ndarray | None = None, background: tuple[float, float, float] = (1.0, 1.0, 1.0),
                supersample: int = 1, geometry: bool = False, specular: Specular | None = None,
                hair: PosedHair | None = None, mouth: PosedMouth | None = None) -> Render:
    """Render the posed head.

    vertices: (V, 3) posed world vertices of ``head``'s topology; crease: (V,) from
    :func:`crease_weights` (None = none); supersample: per-axis factor for anti-aliasing;
    geometry: also return depth and normals (rasterized once more at the native resolution);
    specular: view-dependent highlights (None = Lambert + ambient only). A detailed appearance
    (``app.detail``) renders through :func:`.detail_render.render_detailed`, with the posed hair
    volume ``hair`` and the posed mouth interior ``mouth`` (:mod:`.mouth`) when given.
    """
    if app.detail is not None:
        from .detail_render import render_detailed

        return render_detailed(head, vertices, camera, app, crease, background, supersample, geometry, specular, hair, mouth)
    faces = head.faces
    V = head.n_vertices
    crease = np.zeros(V) if crease is None else crease
    part_w = np.zeros((V, 3))
    eyes = (head.part == PART_LEFT_EYE) | (head.part == PART_RIGHT_EYE)
    part_w[eyes, 0] = 1.0
    part_w[head.part == PART_MOUTH, 1] = 1.0
    part_w[head.part == 0, 2] = 1.0
    nrm = vertex_normals(vertices, faces)
    attrs = np.concatenate([head.v_template, head.eye_dir, part_w, head.mouth_depth[:, None], crease[:, None], nrm], 1)
    frag = rasterize(vertices, faces, camera, supersample)
    H, W = frag.face.shape
    m = frag.mask
    bg = np.asarray(background, dtype=np.float64)
    img = np.broadcast_to(bg, (H, W, 3)).copy()
    if m.any():
        a = frag.interpolate(attrs, faces)
        # one part per pixel: the dominant part of the hit triangle's vertices (no blending across seams)
        pw = np.eye(3)[np.argmax(a[:, 6:9], axis=1)]
        alb = albedo(a[:, 0:3], a[:, 3:6], pw, a[:, 9], a[:, 10], app, head.mouth_y)
        n = a[:, 11:14]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        ys, xs = np.nonzero(m)
        _, dirs = _pixel_dirs(camera, supersample, ys, xs)
        flip = np.einsum("ij,ij->i", n, dirs) > 0
        n[flip] *= -1.0
        shade = AMBIENT + DIFFUSE * np.clip(n @ LIGHT_DIR, 0.0, None)
        if specular is None:
            img[m] = np.clip(alb * shade[:, None], 0.0, 1.0)
        else:
            img[m] = np.clip(alb * shade[:, None] + highlights(specular, a[:, 0:3], pw, n, dirs)[:, None], 0.0, 1.0)
    rgb = downsample(img, supersample).astype(np.float32)
    alpha = downsample(m.astype(np.float64), supersample).astype(np.float32)
    out = Render(rgb=rgb, alpha=alpha)
    if geometry:
        g = frag if supersample == 1 else rasterize(vertices, faces, camera, 1)
        out.depth = g.depth.astype(np.float32)
        normal = np.zeros(g.face.shape + (3,))
        if g.mask.any():
            n = g.interpolate(nrm, faces)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            ys, xs = np.nonzero(g.mask)
            _, dirs = _pixel_dirs(camera, 1, ys, xs)
            n[np.einsum("ij,ij->i", n, dirs) > 0] *= -1.0
            normal[g.mask] = n
        out.normal = normal.astype(np.float32)
    return out
