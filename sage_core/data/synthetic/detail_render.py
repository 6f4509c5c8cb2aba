"""Shaded rendering of a detailed synthetic subject (head plus hair volume and mouth interior) by
the ground-truth mesh rasterizer.

The head, the hair volume and the mouth interior (:mod:`.mouth`: teeth, gums, tongue with their
own per-vertex albedo; the pocket lining in the subject's cavity colour) are rasterized together
(one z-buffer, supersampled). The albedo is evaluated at the template (texture) position with the
footprint on the surface, so the detail of :mod:`.detail` is band-limited to what the pixel can
hold: the footprint is half the world size of a sub-pixel at the sample's depth, widened by the
obliquity of the surface (the geometric mean of the two axes of the sub-pixel's ellipse on it).
Pixels whose sub-pixels all hit the same part get one albedo, at their mean attributes with the
footprint of the whole pixel (the Gaussian equivalent of its box, σ = pixel / √12); silhouette and
part-boundary pixels one per sub-pixel, averaged. Shading, per sub-pixel, is that of the smooth
head (Lambert + ambient under the world light, optional Blinn-Phong highlights) plus, with
highlights, an anisotropic sheen on hair strands (Kajiya-Kay: the strength follows
``sqrt(1 - (t·h)²)`` for the strand tangent t and the half vector h).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..cameras import Camera
from ._fields import smoothstep
from .detail import FaceAnchors, hair_strands, skin_detail
from .hair import PosedHair
from .mouth import MouthStyle, PosedMouth
from .head import (
    _EYE_R,
    PART_LEFT_EYE,
    PART_MOUTH,
    PART_RIGHT_EYE,
    PART_SKIN,
    HeadModel,
)
from .mesh_render import downsample, rasterize, vertex_normals
from .shading import (
    AMBIENT,
    DIFFUSE,
    LIGHT_DIR,
    Render,
    Specular,
    _eye_albedo,
    _pixel_dirs,
)

if TYPE_CHECKING:
    from .appearance import Appearance

# part columns of the rasterized attributes
_EYE, _MOUTH, _SKIN, _HAIR = 0, 1, 2, 3


def face_anchors(head: HeadModel) -> FaceAnchors:
    """The template landmarks of ``head`` the detail is placed by."""
    return FaceAnchors(head.mouth_y, head.joints[3:5].copy(), _EYE_R)


def render_detailed(head: HeadModel, vertices: np.ndarray, camera: Camera, app: Appearance, crease: np.ndarray | None,
                    background: tuple[float, float, float], supersample: int, geometry: bool, specular: Specular | None,
                    hair: PosedHair | None, mouth: PosedMouth | None = None) -> Render:
    """See :func:`.appearance.render_head` (same arguments; ``app.detail`` is set)."""
    st = app.detail
    assert st is not None
    V = head.n_vertices
    crease = np.zeros(V) if crease is None else crease
    part = np.zeros((V, 4))
    eyes = (head.part == PART_LEFT_EYE) | (head.part == PART_RIGHT_EYE)
    part[eyes, _EYE] = 1.0
    part[head.part == PART_MOUTH, _MOUTH] = 1.0
    part[head.part == PART_SKIN, _SKIN] = 1.0
    nrm = vertex_normals(vertices, head.faces)
    # columns 21:24: the photo skin's coordinates and weight (zeros without one)
    photo = app.photo
    ph = np.zeros((V, 3)) if photo is None else np.concatenate([photo.uv, photo.weight[:, None]], 1)
    cols = [head.v_template, head.eye_dir, part, head.mouth_depth[:, None], crease[:, None], nrm, np.zeros((V, 6)), ph]
    attrs = np.concatenate(cols, 1)
    verts, faces = np.asarray(vertices, np.float64), head.faces
    rot = np.eye(3)
    if hair is not None:
        hv = hair.volume
        H = hv.n_vertices
        hpart = np.zeros((H, 4))
        hpart[:, _HAIR] = 1.0
        hn = vertex_normals(hair.vertices, hv.faces)
        hattrs = np.concatenate([hv.tex, np.zeros((H, 3)), hpart, np.zeros((H, 2)), hn, hv.force[:, None], hv.frame[:, None].astype(np.float64),
                                 hv.tangent, np.zeros((H, 1)), np.zeros((H, 3))], 1)
        attrs = np.concatenate([attrs, hattrs], 0)
        verts = np.concatenate([verts, hair.vertices], 0)
        faces = np.concatenate([faces, hv.faces + V], 0)
        rot = hair.rotation
    if mouth is not None:
        # column 20 flags an albedo given per vertex (in columns 0:3)
        mv = mouth.volume
        M = mv.n_vertices
        mpart = np.zeros((M, 4))
        mpart[:, _MOUTH] = 1.0
        mn = vertex_normals(mouth.vertices, mv.faces)
        mattrs = np.concatenate([mv.albedo, np.zeros((M, 3)), mpart, np.zeros((M, 2)), mn, np.zeros((M, 5)), np.ones((M, 1)),
                                 np.zeros((M, 3))], 1)
        n_before = verts.shape[0]
        attrs = np.concatenate([attrs, mattrs], 0)
        verts = np.concatenate([verts, mouth.vertices], 0)
        faces = np.concatenate([faces, mv.faces + n_before], 0)
    frag = rasterize(verts, faces, camera, supersample)
    H_, W_ = frag.face.shape
    m = frag.mask
    img = np.broadcast_to(np.asarray(background, dtype=np.float64), (H_, W_, 3)).copy()
    if m.any():
        a = frag.interpolate(attrs, faces)
        which = np.argmax(a[:, 6:10], axis=1)
        n = a[:, 12:15]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        ys, xs = np.nonzero(m)
        _, dirs = _pixel_dirs(camera, supersample, ys, xs)
        cosv = np.einsum("ij,ij->i", n, dirs)
        n[cosv > 0] *= -1.0
        fl = 0.5 * (camera.K[0, 0] + camera.K[1, 1]) * supersample
        fp = 0.5 * frag.depth[m] / fl / np.sqrt(np.maximum(np.abs(cosv), 0.1))
        alb, cov, tan = _pixel_albedo(a, which, fp, ys, xs, camera, supersample, app, head,
                                      hair.volume.bun_frame if hair is not None else None,
                                      mouth.volume.style if mouth is not None else None)
        shade = AMBIENT + DIFFUSE * np.clip(n @ LIGHT_DIR, 0.0, None)
        out = alb * shade[:, None]
        if specular is not None:
            out = out + _highlights(specular, which, cov, tan @ rot.T, n, dirs)[:, None]
        img[m] = np.clip(out, 0.0, 1.0)
    rgb = downsample(img, supersample).astype(np.float32)
    alpha = downsample(m.astype(np.float64), supersample).astype(np.float32)
    res = Render(rgb=rgb, alpha=alpha)
    if geometry:
        g = frag if supersample == 1 else rasterize(verts, faces, camera, 1)
        res.depth = g.depth.astype(np.float32)
        normal = np.zeros(g.face.shape + (3,))
        if g.mask.any():
            all_n = vertex_normals(verts, faces)
            nn = g.interpolate(all_n, faces)
            nn /= np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12)
            ys, xs = np.nonzero(g.mask)
            _, dirs = _pixel_dirs(camera, 1, ys, xs)
            nn[np.einsum("ij,ij->i", nn, dirs) > 0] *= -1.0
            normal[g.mask] = nn
        res.normal = normal.astype(np.float32)
    return res


def _pixel_albedo(a: np.ndarray, which: np.ndarray, fp: np.ndarray, ys: np.ndarray, xs: np.ndarray, camera: Camera, supersample: int,
                  app: Appearance, head: HeadModel, bun_frame: tuple | None, mouth_style: MouthStyle | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_albedo` of the M foreground sub-pixel samples (at ys, xs of the supersampled grid),
    evaluated once per pixel where all of a pixel's sub-pixels hit the same part: at the mean of
    their attributes, with the footprint of the whole pixel (the prefilter then does what the
    pixel's box would: a Gaussian of σ = pixel / √12); per sub-pixel elsewhere (silhouettes, part
    boundaries, and where the mouth interior's own-albedo surfaces meet the pocket lining)."""
    s = supersample
    if s == 1:
        return _albedo(a, which, fp, app, head, bun_frame, mouth_style)
    n_px = camera.width * camera.height
    pix = (ys // s) * camera.width + (xs // s)
    # part, the bun's strand frame apart from the scalp's, and the mouth interior's own albedo
    # (teeth, gums, tongue) apart from the pocket lining
    key = which * 4 + (a[:, 16] > 0.5) * 2 + (a[:, 20] > 0.5)
    count = np.bincount(pix, minlength=n_px)
    kmin = np.full(n_px, 1 << 20)
    kmax = np.full(n_px, -1)
    np.minimum.at(kmin, pix, key)
    np.maximum.at(kmax, pix, key)
    uniform = (count == s * s) & (kmin == kmax)
    shared = uniform[pix]
    upix = np.flatnonzero(uniform)
    slot = np.full(n_px, -1)
    slot[upix] = np.arange(len(upix))
    M = a.shape[0]
    alb, cov, tan = np.zeros((M, 3)), np.zeros(M), np.zeros((M, 3))
    if len(upix):
        ps = pix[shared]
        a_px = np.stack([np.bincount(ps, weights=a[shared, c], minlength=n_px)[upix] for c in range(a.shape[1])], 1) / (s * s)
        # the pixel integrates the light of its area: a box, whose Gaussian equivalent has σ = pixel / √12
        # (a sub-pixel footprint is half a sub-pixel, so σ = 2·s·fp / √12)
        fp_px = (2.0 / math.sqrt(12.0)) * s * np.bincount(ps, weights=fp[shared], minlength=n_px)[upix] / (s * s)
        pa, pc, pt = _albedo(a_px, kmin[upix] // 4, fp_px, app, head, bun_frame, mouth_style)
        k = slot[ps]
        alb[shared], cov[shared], tan[shared] = pa[k], pc[k], pt[k]
    own = ~shared
    if own.any():
        alb[own], cov[own], tan[own] = _albedo(a[own], which[own], fp[own], app, head, bun_frame, mouth_style)
    return alb, cov, tan


def _albedo(a: np.ndarray, which: np.ndarray, fp: np.ndarray, app: Appearance, head: HeadModel, bun_frame: tuple | None,
            mouth_style: MouthStyle | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Albedo (M, 3), hair coverage (M,) and template strand tangents (M, 3) of the M samples with
    interpolated attributes ``a`` and parts ``which``; bun_frame: the hair volume's bun frame;
    mouth_style: the mouth interior's style (its cavity colours the pocket lining), or None."""
    st = app.detail
    assert st is not None
    M = a.shape[0]
    alb = np.zeros((M, 3))
    cov = np.zeros(M)
    tan = np.zeros((M, 3))
    tex, crease, force, frame = a[:, 0:3], a[:, 11], a[:, 15], a[:, 16]
    skin_rgb, lips_rgb, hair_rgb = np.asarray(app.skin), np.asarray(app.lips), np.asarray(app.hair)
    fa = face_anchors(head)
    e = which == _EYE
    if e.any():
        alb[e] = _eye_albedo(a[e, 3:6], app)
    mo = which == _MOUTH
    if mo.any():
        if mouth_style is None:
            alb[mo] = np.array([0.45, 0.12, 0.12])[None] * (1.0 - 0.75 * np.clip(a[mo, 10], 0, 1))[:, None]
        else:
            alb[mo] = mouth_style.cavity_albedo(a[mo, 10])
            own = mo & (a[:, 20] > 0.5)
            alb[own] = a[own, 0:3]
    hair_px = which == _HAIR
    bun = hair_px & (frame > 0.5)
    # skin, and the hair sheet where it may still show skin (near the hairline)
    sk = (which == _SKIN) | (hair_px & ~bun & (force < 0.999))
    if sk.any():
        over = None
        if app.photo is not None:  # the face's skin from a photograph (photo_skin.py), faded at its edge
            w = np.where(which[sk] == _SKIN, np.clip(a[sk, 23], 0.0, 1.0), 0.0)
            rgb = np.zeros((w.size, 3))
            on = w > 1e-3
            rgb[on] = app.photo.sample(a[sk][on, 21:23])
            over = (rgb, w)
        alb[sk], cov[sk], tan[sk] = skin_detail(tex[sk], fp[sk], np.where(which[sk] == _SKIN, crease[sk], 0.0), skin_rgb, lips_rgb,
                                                hair_rgb, st, fa, over)  # fmt: skip
    forced = hair_px & ~bun & (force > 1e-3)
    if forced.any():
        hcol, htan = hair_strands(tex[forced], fp[forced], hair_rgb, st, st.whorl_frame())
        f = force[forced]
        alb[forced] = alb[forced] * (1.0 - f[:, None]) + hcol * f[:, None]
        cov[forced] = np.maximum(cov[forced], f)
        # hanging hair (fringe, bob) shines along the sheet; the scalp part along the whorl's strands
        tan[forced] = tan[forced] * (1.0 - f[:, None]) + _along(a[forced, 17:20], htan) * f[:, None]
    if bun.any() and bun_frame is not None:
        hcol, htan = hair_strands(tex[bun], fp[bun], hair_rgb, st, bun_frame)
        alb[bun], cov[bun], tan[bun] = hcol, 1.0, _along(a[bun, 17:20], htan)
    return np.clip(alb, 0.0, 1.0), cov, tan


def _along(direction: np.ndarray, gloss_tangent: np.ndarray) -> np.ndarray:
    """The hair volume's strand ``direction`` (M, 3) (interpolated, not unit) scaled to the gloss of
    ``gloss_tangent`` (M, 3) (a texture tangent whose length is the gloss)."""
    d = direction / np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
    return d * np.linalg.norm(gloss_tangent, axis=1, keepdims=True)


def _highlights(spec: Specular, which: np.ndarray, cov: np.ndarray, tangent: np.ndarray, normal: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
    """Specular intensity (M,): Blinn-Phong on skin (less where hair covers it) and eyes, and the
    anisotropic sheen of hair strands. tangent: (M, 3) world strand tangents, their length the
    gloss (zero without hair)."""
    h = LIGHT_DIR[None] - view_dirs
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    nh = np.clip(np.einsum("ij,ij->i", normal, h), 0.0, 1.0)
    lit = (normal @ LIGHT_DIR > 0).astype(np.float64)
    skin = spec.skin * (which == _SKIN) * (1.0 - cov) * nh**spec.skin_shininess
    eye = spec.eye * (which == _EYE) * nh**spec.eye_shininess
    gloss = np.linalg.norm(tangent, axis=1)
    t = tangent / np.maximum(gloss, 1e-12)[:, None]
    th = np.einsum("ij,ij->i", t, h)
    sheen = spec.hair * cov * gloss * np.sqrt(np.clip(1.0 - th * th, 0.0, 1.0)) ** spec.hair_shininess
    sheen *= smoothstep(normal @ LIGHT_DIR, 0.0, 0.3)  # fades out towards the shadow side
    return (skin + eye) * lit + sheen
