"""Prior-free pseudo-views for one-shot captures (SAGE §5, one image with its FLAME fit and camera).

Two providers build :class:`PseudoView` s that phase 1 adds to the real input view:

* :class:`MirrorViewProvider`: the mirror view. The world is reflected by S = diag(−1, 1, 1): the
  camera becomes S·c2w·S with cx' = W − cx (:func:`mirror_camera`), the image and mask are flipped
  horizontally, and the avatar is posed with the input frame's FLAME parameters and then mirrored
  through the template's vertex mirror correspondence (:func:`mirror_vertices`, from
  :mod:`sage_core.flame.mirror`). A surfel on the subject's left cheek is then rendered where the
  flipped image shows the right cheek: the symmetry prior. The per-pixel weight is the input
  confidence of the source pixel times how little the input already sees that surface (seen
  surface keeps ``pseudo.mirror_seen_weight``); the view weight grows with the head's yaw.
* :class:`TexturedRingProvider`: the input image back-projected onto the posed FLAME mesh and
  re-rendered from a ring of cameras around the head.

Texture representation (no UV atlas needed): a per-face barycentric sample grid of resolution r —
samples at barycentrics (i, j, r − i − j)/r, i + j ≤ r, (r + 1)(r + 2)/2 per face, each face keeping
its own copies of its edge samples. A point (face f, barycentrics β) reads the texture by linear
interpolation inside the grid cell holding β (:func:`texture_lookup`).

Building the texture (:func:`backproject_texture`, :meth:`TexturedRingProvider.complete_texture`):

1. back-projection: each sample of the posed mesh is projected into the input camera; it is seen
   when its depth matches the rasterized depth of the pixel it falls in (the rasterizer's z-buffer,
   both ways within a tolerance relative to the mesh size, so that a pixel showing another surface
   does not colour it); colour = bilinear image sample; confidence = smoothstep of the cosine between
   the face normal and the direction to the camera × distance from the silhouette (ramp over a
   fraction of the image diagonal) × mask;
2. mirror fill: a sample whose confidence is below its mirror partner's (scaled by
   ``pseudo.texture_mirror_confidence``) takes the partner's colour; the partner of a sample is the
   closest surface point of the template to the reflection of the sample through the vertex mirror
   map (works also when the triangulation itself is not mirror-symmetric);
3. inpainting by mesh-graph diffusion (there is no 2D layout to run ``cv2.inpaint`` on): known
   samples are splatted to the vertices, the unknown vertices solve the graph Laplace equation
   (harmonic fill) over edges whose two vertices lie in the same region (mouth interior, teeth,
   eyeballs, hair, lips, the rest), and unknown samples interpolate their face's vertex colours
   with confidence ``pseudo.texture_inpaint_confidence`` (default 0: no photometric constraint).

The ring views render the completed texture with the mesh rasterizer (supersampled, box-filtered)
on the dataset background, with the interpolated confidence as the per-pixel weight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np
import torch
import torch.nn.functional as F

from ..config import PseudoViewConfig
from ..data.cameras import Camera
from ..render.mesh_raster import rasterize_mesh

if TYPE_CHECKING:
    from ..avatar.model import Avatar
    from ..data.dataset import IngestedData

_S = (-1.0, 1.0, 1.0)

_DEFAULTS = PseudoViewConfig()
"""Read for the pseudo-view settings when the providers are given no config (or one without them)."""

_COS_LO, _COS_HI = 0.1, 0.5
_SILHOUETTE_RAMP = 0.02
_DEPTH_TOL = 0.005
_MIN_CONF = 1e-3
_SPLAT_MIN_CONF = 0.1
_REGION_ORDER = ("mouth_interior", "teeth", "eyeballs", "hair", "lips")


def _cfg(cfg: Any, name: str) -> Any:
    """Setting ``name`` of :class:`PseudoViewConfig` from ``cfg``: a phase-1 config (its ``pseudo``
    section), the section itself or any object with some of its fields; the default otherwise."""
    section = getattr(cfg, "pseudo", cfg) if cfg is not None else None
    return getattr(section, name, getattr(_DEFAULTS, name)) if section is not None else getattr(_DEFAULTS, name)


@dataclass
class PseudoView:
    """One pseudo-view for phase 1.

    Attributes:
        name: label ("mirror", "ring00", ...).
        camera: OpenCV camera (w2c, K, width, height).
        image: (H, W, 3) float32 in [0, 1] on the dataset background.
        mask: (H, W) float32 foreground matte.
        weight: (H, W) float32 in [0, 1], per-pixel photometric weight (0 = no constraint).
        frame_index: index into the ingested train frames whose FLAME parameters pose the avatar.
        mirror: pose the mesh with those parameters, then mirror it
            (``verts' = mirror_vertices(verts, mirror_index)``).
        view_weight: weight of this view's loss relative to the real input view (1.0).
    """

    name: str
    camera: Camera
    image: torch.Tensor
    mask: torch.Tensor
    weight: torch.Tensor
    frame_index: int
    mirror: bool
    view_weight: float


class PseudoViewProvider(Protocol):
    """Something that makes pseudo-views for a capture and an avatar."""

    def views(self, data: IngestedData, avatar: Avatar, mirror_index: torch.Tensor | None) -> list[PseudoView]: ...


# ------------------------------------------------------------------------------------------------
# mirror geometry
# ------------------------------------------------------------------------------------------------


def mirror_camera(camera: Camera) -> Camera:
    """The camera of the world reflected by S = diag(−1, 1, 1): c2w' = S·c2w·S, cx' = W − cx (and the
    skew negated). A world point X seen at pixel (u, v) has its reflection S·X seen at (W − u, v):
    with pixel centres at +0.5 this maps pixel column j onto column W − 1 − j (a horizontal flip)."""
    S4 = np.diag([-1.0, 1.0, 1.0, 1.0])
    w2c = S4 @ camera.w2c @ S4
    K = camera.K.copy()
    K[0, 2] = camera.width - camera.K[0, 2]
    K[0, 1] = -camera.K[0, 1]
    extra = dict(camera.extra)
    extra["mirror_of"] = camera.name
    return Camera(K, w2c, camera.width, camera.height, camera.index, f"{camera.name}-mirror" if camera.name else "mirror", extra)


def mirror_vertices(verts: torch.Tensor, mirror_index: torch.Tensor) -> torch.Tensor:
    """verts: (..., V, 3) -> (..., V, 3): v'_i = S v_{m(i)}, S = diag(-1, 1, 1)."""
    s = torch.tensor(_S, dtype=verts.dtype, device=verts.device)
    return verts.index_select(-2, mirror_index.to(device=verts.device, dtype=torch.long)) * s


def mirror_index_of(avatar: Avatar, rel_tol: float = 1e-3) -> tuple[torch.Tensor | None, str]:
    """(V,) int64 vertex mirror index of the avatar's model template (teeth and mouth interior
    included), or (None, reason) when it is not symmetric."""
    from ..flame.mirror import model_mirror

    m, reason = model_mirror(avatar.model_data, rel_tol)
    if m is None:
        return None, reason
    return torch.as_tensor(m.vertex, dtype=torch.long, device=avatar.device), ""


# ------------------------------------------------------------------------------------------------
# per-face barycentric textures
# ------------------------------------------------------------------------------------------------


def sample_barycentrics(resolution: int) -> torch.Tensor:
    """(S, 3) float64 barycentrics (i, j, r − i − j)/r of the per-face sample grid, i outer, j inner."""
    r = int(resolution)
    if r < 1:
        raise ValueError(f"texture resolution must be >= 1, got {resolution}")
    ij = [(i, j) for i in range(r + 1) for j in range(r + 1 - i)]
    a = torch.tensor(ij, dtype=torch.float64)
    return torch.stack([a[:, 0], a[:, 1], r - a[:, 0] - a[:, 1]], -1) / r


def _sample_table(r: int, device: torch.device) -> torch.Tensor:
    """(r + 2, r + 2) int64 sample index of grid point (i, j), −1 outside the triangle."""
    t = torch.full((r + 2, r + 2), -1, dtype=torch.long)
    s = 0
    for i in range(r + 1):
        for j in range(r + 1 - i):
            t[i, j] = s
            s += 1
    return t.to(device)


def texture_lookup(values: torch.Tensor, face_id: torch.Tensor, bary: torch.Tensor, resolution: int) -> torch.Tensor:
    """Read a per-face sample texture at surface points.

    values: (F, S, C) with S = (r + 1)(r + 2)/2 in :func:`sample_barycentrics` order; face_id: (P,)
    int ≥ 0; bary: (P, 3) barycentrics w.r.t. the face's corners. Returns (P, C), linear inside the
    grid cell holding the point (exact at the samples).
    """
    r = int(resolution)
    table = _sample_table(r, values.device)
    b = bary.to(values.dtype).clamp_min(0.0)
    b = b / b.sum(-1, keepdim=True).clamp_min(1e-12)
    u, v = b[:, 0] * r, b[:, 1] * r
    i0 = torch.floor(u).clamp(0, r - 1)
    j0 = torch.minimum(torch.floor(v).clamp_min(0), (r - 1) - i0).clamp_min(0)
    fu, fv = u - i0, v - j0
    i0l, j0l = i0.long(), j0.long()
    upper = (fu + fv) > 1.0
    # lower cell triangle (i0,j0),(i0+1,j0),(i0,j0+1); upper (i0+1,j0+1),(i0,j0+1),(i0+1,j0)
    ia = torch.where(upper, i0l + 1, i0l)
    ja = torch.where(upper, j0l + 1, j0l)
    wa = torch.where(upper, fu + fv - 1.0, 1.0 - fu - fv)
    wb = torch.where(upper, 1.0 - fv, fu)  # corner (i0+1, j0)
    wc = torch.where(upper, 1.0 - fu, fv)  # corner (i0, j0+1)
    w = torch.stack([wa, wb, wc], -1).clamp_min(0.0)
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-12)
    sa = table[ia, ja]
    sb = table[i0l + 1, j0l]
    sc = table[i0l, j0l + 1]
    idx = torch.stack([sa, sb, sc], -1)
    w = torch.where(idx >= 0, w, torch.zeros_like(w))
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-12)
    vals = values[face_id.long()[:, None], idx.clamp_min(0)]  # (P, 3, C)
    return (w.unsqueeze(-1) * vals).sum(1)


@dataclass
class FaceTexture:
    """Per-face barycentric sample texture.

    colors: (F, S, 3) in [0, 1]; confidence: (F, S) in [0, 1]; source: (F, S) int8 with 0 = unknown,
    1 = seen in the input, 2 = filled from the mirror partner, 3 = inpainted; resolution: r.
    """

    colors: torch.Tensor
    confidence: torch.Tensor
    source: torch.Tensor
    resolution: int

    SEEN: ClassVar[int] = 1
    MIRROR: ClassVar[int] = 2
    INPAINTED: ClassVar[int] = 3

    def lookup(self, face_id: torch.Tensor, bary: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(P, 3) colours and (P,) confidences at surface points (face_id (P,), bary (P, 3))."""
        both = torch.cat([self.colors, self.confidence.unsqueeze(-1)], -1)
        out = texture_lookup(both, face_id, bary, self.resolution)
        return out[:, :3], out[:, 3]


def _face_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    tri = verts[faces]
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)


def _smoothstep(lo: float, hi: float, x: torch.Tensor) -> torch.Tensor:
    t = ((x - lo) / (hi - lo)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _bilinear(img: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """img: (H, W, C); uv: (P, 2) continuous pixel coordinates (centres at +0.5) -> (P, C)."""
    H, W = img.shape[:2]
    g = torch.stack([2.0 * uv[:, 0] / W - 1.0, 2.0 * uv[:, 1] / H - 1.0], -1).to(img.dtype)
    out = F.grid_sample(img.permute(2, 0, 1)[None], g[None, None], mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T


def _silhouette_distance(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 distance in pixels from each foreground pixel to the background."""
    import cv2

    fg = (mask > 0.5).astype(np.uint8)
    return cv2.distanceTransform(fg, cv2.DIST_L2, 5).astype(np.float32)


@dataclass
class InputProjection:
    """The input view projected onto the posed mesh.

    vertices: (V, 3) posed mesh of the input frame; texture: the back-projected texture (seen
    samples only); pixel_confidence: (H, W) confidence of each input pixel (0 off the mesh);
    image: (H, W, 3); mask: (H, W); camera: the input camera; frame_index: index into ``data.train``.
    """

    vertices: torch.Tensor
    texture: FaceTexture
    pixel_confidence: torch.Tensor
    image: torch.Tensor
    mask: torch.Tensor
    camera: Camera
    frame_index: int


def _cam_tensors(camera: Camera, device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.as_tensor(camera.K, dtype=dtype, device=device), torch.as_tensor(camera.w2c, dtype=dtype, device=device))


def _mesh_size(verts: torch.Tensor) -> float:
    return float((verts.max(0).values - verts.min(0).values).norm())


def backproject_texture(
    verts: torch.Tensor, faces: torch.Tensor, camera: Camera, image: torch.Tensor, mask: torch.Tensor | None,
    resolution: int = 4, depth_tol: float = _DEPTH_TOL,
) -> tuple[FaceTexture, torch.Tensor]:
    """Back-project an image onto a mesh.

    verts: (V, 3) world; faces: (F, 3); camera: the image's camera; image: (H, W, 3); mask: (H, W)
    foreground matte or None (the mesh coverage is used). depth_tol: visibility tolerance relative to
    the mesh size. Returns the texture (seen samples: source 1, the rest 0 with confidence 0) and the
    (H, W) per-pixel confidence of the image (cosine × silhouette distance × mask on the mesh).
    """
    dev, dt = verts.device, verts.dtype
    faces = faces.to(device=dev, dtype=torch.long)
    H, W = camera.height, camera.width
    K, w2c = _cam_tensors(camera, dev, dt)
    image = image.to(device=dev, dtype=dt)
    with torch.no_grad():
        ras = rasterize_mesh(verts, faces, K, w2c, W, H)
        fid = ras.face_id[0]
        depth = ras.depth[0]
        cover = (fid >= 0).to(dt)
        m = cover if mask is None else mask.to(device=dev, dtype=dt)
        dist = torch.as_tensor(_silhouette_distance(m.cpu().numpy()), device=dev, dtype=dt)
        ramp = max(1.0, _SILHOUETTE_RAMP * math.hypot(W, H))
        sil = (dist / ramp).clamp(0.0, 1.0)
        normals = _face_normals(verts, faces)
        centre = -(w2c[:3, :3].T @ w2c[:3, 3])

        # per-pixel confidence of the input
        pix_conf = torch.zeros(H, W, dtype=dt, device=dev)
        hit = fid >= 0
        if bool(hit.any()):
            from ..render.mesh_raster import points_on_mesh

            f_hit = fid[hit]
            p = points_on_mesh(verts, faces, f_hit, ras.bary[0][hit])
            to_cam = centre - p
            to_cam = to_cam / to_cam.norm(dim=-1, keepdim=True).clamp_min(1e-20)
            cos = (normals[f_hit] * to_cam).sum(-1)
            pix_conf[hit] = _smoothstep(_COS_LO, _COS_HI, cos) * sil[hit] * m[hit].clamp(0.0, 1.0)

        # per-sample back-projection
        B = sample_barycentrics(resolution).to(device=dev, dtype=dt)  # (S, 3)
        Fn, Sn = faces.shape[0], B.shape[0]
        tri = verts[faces]  # (F, 3, 3)
        pts = torch.einsum("sk,fkc->fsc", B, tri).reshape(-1, 3)
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        uvw = pc @ K.T
        uv = uvw[:, :2] / uvw[:, 2:3].clamp_min(1e-12)
        col = torch.floor(uv[:, 0]).long()
        row = torch.floor(uv[:, 1]).long()
        inside = (z > 1e-6) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        ci, ri = col.clamp(0, W - 1), row.clamp(0, H - 1)
        zr = depth[ri, ci]
        tol = depth_tol * _mesh_size(verts)
        visible = inside & torch.isfinite(zr) & ((z - zr).abs() <= tol)
        to_cam = centre - pts
        to_cam = to_cam / to_cam.norm(dim=-1, keepdim=True).clamp_min(1e-20)
        fidx = torch.arange(Fn, device=dev).repeat_interleave(Sn)
        cos = (normals[fidx] * to_cam).sum(-1)
        conf = _smoothstep(_COS_LO, _COS_HI, cos) * sil[ri, ci] * m[ri, ci].clamp(0.0, 1.0)
        conf = torch.where(visible, conf, torch.zeros_like(conf))
        colors = _bilinear(image, uv.clamp(min=torch.zeros(2, device=dev, dtype=dt), max=torch.tensor([W, H], device=dev, dtype=dt)))
        colors = torch.where(visible[:, None], colors, torch.zeros_like(colors))
        source = torch.where(conf > 0, torch.ones_like(conf, dtype=torch.int8), torch.zeros_like(conf, dtype=torch.int8))
    tex = FaceTexture(colors.reshape(Fn, Sn, 3).clamp(0.0, 1.0), conf.reshape(Fn, Sn), source.reshape(Fn, Sn), int(resolution))
    return tex, pix_conf


def mirror_sample_partners(template: np.ndarray, faces: np.ndarray, mirror_index: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """The mirror partner of every texture sample on the (symmetric) template.

    template: (V, 3); faces: (F, 3); mirror_index: (V,). The sample (f, β) maps to
    Σ_k β_k·S·v[m(faces[f, k])], then to the closest point of the template surface. Returns
    face ids (F·S,) int64 and barycentrics (F·S, 3) float64.
    """
    import igl

    V = np.asarray(template, np.float64)
    Fc = np.asarray(faces, np.int64)
    B = sample_barycentrics(resolution).numpy()
    mv = V[np.asarray(mirror_index)] * np.asarray(_S)
    pts = np.einsum("sk,fkc->fsc", B, mv[Fc]).reshape(-1, 3)
    _, fid, closest = igl.point_mesh_squared_distance(pts, V, Fc)
    fid = np.asarray(fid, np.int64).reshape(-1)
    closest = np.asarray(closest, np.float64).reshape(-1, 3)
    tri = V[Fc[fid]]
    return fid, _barycentric(closest, tri[:, 0], tri[:, 1], tri[:, 2])


def _barycentric(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(P, 3) barycentrics of points p in triangles (a, b, c), clamped to the triangle."""
    v0, v1, v2 = b - a, c - a, p - a
    d00 = (v0 * v0).sum(1)
    d01 = (v0 * v1).sum(1)
    d11 = (v1 * v1).sum(1)
    d20 = (v2 * v0).sum(1)
    d21 = (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    out = np.stack([1.0 - w1 - w2, w1, w2], 1).clip(0.0, None)
    return out / np.maximum(out.sum(1, keepdims=True), 1e-12)


def fill_from_mirror(tex: FaceTexture, partner_face: torch.Tensor, partner_bary: torch.Tensor, factor: float = 0.5) -> FaceTexture:
    """Replace samples whose confidence is below ``factor`` × their mirror partner's seen confidence
    by the partner's colour (source 2, confidence factor × partner's)."""
    Fn, Sn = tex.confidence.shape
    seen_conf = torch.where(tex.source == FaceTexture.SEEN, tex.confidence, torch.zeros_like(tex.confidence))
    # confidence-weighted interpolation: unseen samples (colour 0) do not darken their neighbours
    both = torch.cat([tex.colors * seen_conf[..., None], seen_conf[..., None]], -1)
    out = texture_lookup(both, partner_face.to(tex.colors.device), partner_bary.to(tex.colors), tex.resolution)
    wsum = out[:, 3:]
    pc = (out[:, :3] / wsum.clamp_min(1e-12)).clamp(0.0, 1.0).reshape(Fn, Sn, 3)
    pconf = (factor * wsum[:, 0]).reshape(Fn, Sn)
    take = (pconf > tex.confidence) & (wsum[:, 0].reshape(Fn, Sn) > _MIN_CONF)
    colors = torch.where(take[..., None], pc, tex.colors)
    conf = torch.where(take, pconf, tex.confidence)
    source = torch.where(take, torch.full_like(tex.source, FaceTexture.MIRROR), tex.source)
    return FaceTexture(colors, conf, source, tex.resolution)


def vertex_region_labels(avatar: Avatar, data: IngestedData | None) -> np.ndarray:
    """(V,) int64 region label per vertex for the inpainting (0 = none of :data:`_REGION_ORDER`)."""
    from ..flame.regions import Regions

    md = avatar.model_data
    V = int(np.asarray(md.v_template).shape[0])
    labels = np.zeros(V, dtype=np.int64)
    masks = data.load_masks_json() if data is not None else {}
    groups = dict(md.vertex_groups)
    if not masks and not groups:
        return labels
    reg = Regions(masks, np.asarray(md.faces), V, groups)
    assigned = np.zeros(V, dtype=bool)
    for k, name in enumerate(_REGION_ORDER):
        if reg.has(name):
            m = reg.vertex_mask(name) & ~assigned
            labels[m] = k + 1
            assigned |= m
    return labels


def inpaint_texture(tex: FaceTexture, faces: torch.Tensor, n_vertices: int, labels: np.ndarray | None = None,
                    confidence: float = 0.0) -> FaceTexture:
    """Fill the unknown samples (confidence below 0.1) by harmonic diffusion over the mesh graph, per region.

    faces: (F, 3); labels: (V,) region per vertex (edges between regions are cut; None = one region).
    Known samples are splatted to their face's vertices (weights β_k × confidence; grazing,
    silhouette-blended samples under 0.1 count as unknown); unknown vertices
    solve the graph Laplace equation with the known ones fixed (a vertex in a component without any
    known vertex gets the mean known colour); unknown samples interpolate their face's vertex
    colours and get ``confidence`` (source 3).
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    dev = tex.colors.device
    Fc = faces.detach().cpu().long().numpy()
    B = sample_barycentrics(tex.resolution).numpy()
    conf = tex.confidence.detach().cpu().double().numpy()  # (F, S)
    cols = tex.colors.detach().cpu().double().numpy()  # (F, S, 3)
    unknown = conf < _SPLAT_MIN_CONF
    if not unknown.any():
        return tex
    V = int(n_vertices)
    w = np.where(conf >= _SPLAT_MIN_CONF, conf, 0.0)[:, :, None] * B[None]  # (F, S, 3 corners)
    wsum = np.zeros(V)
    csum = np.zeros((V, 3))
    np.add.at(wsum, Fc.reshape(-1), w.sum(1).reshape(-1))
    np.add.at(csum, Fc.reshape(-1), np.einsum("fsk,fsc->fkc", w, cols).reshape(-1, 3))
    known_v = wsum > 1e-8
    vcol = np.zeros((V, 3))
    vcol[known_v] = csum[known_v] / wsum[known_v, None]
    mean = vcol[known_v].mean(0) if known_v.any() else np.full(3, 0.5)
    e = np.concatenate([Fc[:, [0, 1]], Fc[:, [1, 2]], Fc[:, [2, 0]]], 0)
    e = np.unique(np.sort(e, 1), axis=0)
    if labels is not None:
        lab = np.asarray(labels)
        e = e[lab[e[:, 0]] == lab[e[:, 1]]]
    used = np.zeros(V, dtype=bool)
    used[Fc.reshape(-1)] = True
    U = np.nonzero(~known_v & used)[0]
    if U.size:
        A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(V, V)).tocsr()
        deg = np.asarray(A.sum(1)).ravel()
        pos = -np.ones(V, dtype=np.int64)
        pos[U] = np.arange(U.size)
        eps = 1e-6
        A_uu = A[U][:, U]
        A_uk = A[U][:, np.nonzero(known_v)[0]]
        L = sp.diags(deg[U] + eps) - A_uu
        rhs = A_uk @ vcol[known_v] + eps * mean[None]
        sol = spsolve(L.tocsc(), rhs)
        vcol[U] = np.asarray(sol).reshape(-1, 3)
    vcol = vcol.clip(0.0, 1.0)
    interp = np.einsum("sk,fkc->fsc", B, vcol[Fc])
    new_cols = np.where(unknown[..., None], interp, cols)
    new_conf = np.where(unknown, float(confidence), conf)
    src = tex.source.detach().cpu().numpy().copy()
    src[unknown] = FaceTexture.INPAINTED
    return FaceTexture(
        torch.as_tensor(new_cols, dtype=tex.colors.dtype, device=dev),
        torch.as_tensor(new_conf, dtype=tex.confidence.dtype, device=dev),
        torch.as_tensor(src, dtype=torch.int8, device=dev),
        tex.resolution,
    )


def render_texture(verts: torch.Tensor, faces: torch.Tensor, tex: FaceTexture, camera: Camera, background: float = 1.0,
                   background_weight: float = 0.0, supersample: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render a textured mesh: (image (H, W, 3) on ``background``, coverage mask (H, W), weight (H, W)).

    The weight is the interpolated texture confidence on the mesh and ``background_weight`` off it;
    with ``supersample`` = s the mesh is rasterized at s× the size and box-filtered down.
    """
    s = max(1, int(supersample))
    cam = camera.resized(camera.width * s, camera.height * s) if s > 1 else camera
    dev, dt = verts.device, verts.dtype
    K, w2c = _cam_tensors(cam, dev, dt)
    with torch.no_grad():
        ras = rasterize_mesh(verts, faces, K, w2c, cam.width, cam.height)
        fid = ras.face_id[0]
        hit = fid >= 0
        img = torch.full((cam.height, cam.width, 3), float(background), dtype=dt, device=dev)
        wgt = torch.full((cam.height, cam.width), float(background_weight), dtype=dt, device=dev)
        if bool(hit.any()):
            c, w = tex.lookup(fid[hit], ras.bary[0][hit])
            img[hit] = c.to(dt)
            wgt[hit] = w.to(dt)
        cover = hit.to(dt)
        if s > 1:
            pool = lambda x: F.avg_pool2d(x[None, None], s)[0, 0]  # noqa: E731
            img = torch.stack([pool(img[..., k]) for k in range(3)], -1)
            cover = pool(cover)
            wgt = pool(wgt)
    return img.float().clamp(0.0, 1.0), cover.float(), wgt.float().clamp(0.0, 1.0)


# ------------------------------------------------------------------------------------------------
# the input view
# ------------------------------------------------------------------------------------------------


def _background(data: IngestedData) -> float:
    return 0.0 if str(data.summary.get("background", "white")) == "black" else 1.0


def project_input(data: IngestedData, avatar: Avatar, frame_index: int = 0, resolution: int = 4) -> InputProjection:
    """Pose the avatar's mesh for training frame ``frame_index`` and back-project its image."""
    fr = data.train[frame_index]
    dev = avatar.device
    with torch.no_grad():
        verts = avatar.pose_mesh(avatar.frame_inputs(fr.timestep)).detach()
    img = torch.as_tensor(data.load_image(fr), device=dev)
    mask = torch.as_tensor(data.load_mask(fr), device=dev) if fr.mask is not None else None
    tex, pix = backproject_texture(verts, avatar.faces, fr.camera, img, mask, resolution)
    if mask is None:
        mask = (pix > 0).float()
    return InputProjection(verts, tex, pix, img, mask, fr.camera, frame_index)


def head_yaw(avatar: Avatar, flame_inputs: dict[str, torch.Tensor], camera: Camera) -> float:
    """Yaw (radians) of the posed head relative to the camera: 0 when the face (template +z) looks
    straight at the camera, positive when it turns towards the image's +u side.

    The head rotation is the best rigid fit (Kabsch) of the rest mesh (zero pose and expression)
    to the posed mesh over the original FLAME vertices.
    """
    with torch.no_grad():
        posed = avatar.pose_mesh(flame_inputs).double()
        rest_in = {k: (torch.zeros_like(v) if k in ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation") else v)
                   for k, v in flame_inputs.items()}
        rest = avatar.pose_mesh(rest_in).double()
    n = int(avatar.model_data.n_base_vertices)
    a = rest[:n] - rest[:n].mean(0)
    b = posed[:n] - posed[:n].mean(0)
    U, _, Vt = torch.linalg.svd(a.T @ b)
    d = torch.sign(torch.det(Vt.T @ U.T))
    D = torch.diag(torch.tensor([1.0, 1.0, float(d)], dtype=torch.float64, device=a.device))
    R = Vt.T @ D @ U.T
    fwd = (R @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=a.device)).cpu().numpy()
    fc = camera.w2c[:3, :3] @ fwd
    return float(math.atan2(fc[0], -fc[2]))


# ------------------------------------------------------------------------------------------------
# providers
# ------------------------------------------------------------------------------------------------


class MirrorViewProvider:
    """The mirror view of the input (see the module doc); no view when the model is not symmetric.

    cfg: a phase-1 config or its ``pseudo`` section (fields ``mirror*``; the defaults without one); projection: a
    precomputed :class:`InputProjection` of the input view (computed when None).
    """

    def __init__(self, cfg: Any = None, projection: InputProjection | None = None) -> None:
        self.cfg = cfg
        self.projection = projection
        self.last_info: dict[str, float] = {}

    def views(self, data: IngestedData, avatar: Avatar, mirror_index: torch.Tensor | None) -> list[PseudoView]:
        c = self.cfg
        if mirror_index is None or not bool(_cfg(c, "mirror")):
            return []
        proj = self.projection or project_input(data, avatar, 0, int(_cfg(c, "texture_resolution")))
        cam = mirror_camera(proj.camera)
        dev = avatar.device
        verts_m = mirror_vertices(proj.vertices, mirror_index)
        K, w2c = _cam_tensors(cam, dev, proj.vertices.dtype)
        with torch.no_grad():
            ras = rasterize_mesh(verts_m, avatar.faces, K, w2c, cam.width, cam.height)
        fid = ras.face_id[0]
        hit = fid >= 0
        image = torch.flip(proj.image, dims=[1]).float()
        mask = torch.flip(proj.mask, dims=[1]).float()
        src_conf = torch.flip(proj.pixel_confidence, dims=[1]).float()
        seen = torch.zeros_like(mask)
        if bool(hit.any()):
            _, sc = proj.texture.lookup(fid[hit], ras.bary[0][hit])
            seen[hit] = sc.float().clamp(0.0, 1.0)
        sw = float(_cfg(c, "mirror_seen_weight"))
        weight = torch.where(hit, src_conf * (sw + (1.0 - sw) * (1.0 - seen)), torch.zeros_like(mask))
        bgw = float(_cfg(c, "mirror_background_weight"))
        weight = torch.where(~hit & (mask < 0.5), torch.full_like(mask, bgw), weight).clamp(0.0, 1.0)
        fr = data.train[proj.frame_index]
        yaw = head_yaw(avatar, avatar.frame_inputs(fr.timestep), proj.camera)
        full = math.radians(float(_cfg(c, "mirror_yaw_full_deg")))
        floor = float(_cfg(c, "mirror_yaw_floor"))
        yaw_factor = floor + (1.0 - floor) * min(1.0, abs(yaw) / max(full, 1e-6))
        unseen = float(((1.0 - seen) * hit).sum() / hit.sum().clamp_min(1)) if bool(hit.any()) else 0.0
        self.last_info = {"yaw_deg": math.degrees(yaw), "yaw_factor": yaw_factor, "unseen_fraction": unseen}
        return [PseudoView("mirror", cam, image, mask, weight, proj.frame_index, True,
                           float(_cfg(c, "mirror_weight")) * yaw_factor)]


def ring_cameras(camera: Camera, center: np.ndarray, n: int, yaw_deg: float, pitch_deg: float) -> list[Camera]:
    """``n`` cameras on an ellipse of (yaw, pitch) = (Y·cos t, P·sin t), t = 2πk/n, obtained by
    rotating ``camera`` about ``center`` (yaw about the camera's up axis, pitch about its right
    axis): same intrinsics and distance to the centre."""
    from ..geometry.rotations import axis_angle_to_matrix

    c2w = camera.c2w
    up = -c2w[:3, 1]
    right = c2w[:3, 0]
    out = []
    center = np.asarray(center, np.float64)
    for k in range(int(n)):
        t = 2.0 * math.pi * k / max(int(n), 1)
        yaw = math.radians(yaw_deg) * math.cos(t)
        pitch = math.radians(pitch_deg) * math.sin(t)
        aa = torch.tensor(np.stack([up * yaw, right * pitch]), dtype=torch.float64)
        Ry, Rp = axis_angle_to_matrix(aa).numpy()
        R = Ry @ Rp
        new = np.eye(4)
        new[:3, :3] = R @ c2w[:3, :3]
        new[:3, 3] = center + R @ (c2w[:3, 3] - center)
        out.append(Camera(camera.K.copy(), np.linalg.inv(new), camera.width, camera.height, -1, f"ring{k:02d}",
                          {"yaw_deg": math.degrees(yaw), "pitch_deg": math.degrees(pitch)}))
    return out


class TexturedRingProvider:
    """Textured-FLAME views on a yaw/pitch ring around the head (see the module doc).

    cfg: a phase-1 config or its ``pseudo`` section (fields ``ring*`` and ``texture*``; the defaults without one);
    projection: a precomputed :class:`InputProjection` (computed when None). After :meth:`views`,
    ``texture`` holds the completed texture.
    """

    def __init__(self, cfg: Any = None, projection: InputProjection | None = None) -> None:
        self.cfg = cfg
        self.projection = projection
        self.texture: FaceTexture | None = None

    def complete_texture(self, data: IngestedData, avatar: Avatar, mirror_index: torch.Tensor | None,
                         proj: InputProjection) -> FaceTexture:
        """Seen samples, mirror fill (when ``mirror_index`` is given), then per-region inpainting."""
        c = self.cfg
        tex = proj.texture
        if mirror_index is not None:
            pf, pb = mirror_sample_partners(np.asarray(avatar.model_data.v_template), avatar.faces.cpu().numpy(),
                                            mirror_index.cpu().numpy(), tex.resolution)
            tex = fill_from_mirror(tex, torch.as_tensor(pf), torch.as_tensor(pb), float(_cfg(c, "texture_mirror_confidence")))
        labels = vertex_region_labels(avatar, data)
        return inpaint_texture(tex, avatar.faces, int(proj.vertices.shape[0]), labels, float(_cfg(c, "texture_inpaint_confidence")))

    def views(self, data: IngestedData, avatar: Avatar, mirror_index: torch.Tensor | None) -> list[PseudoView]:
        c = self.cfg
        n = int(_cfg(c, "ring_views"))
        if n <= 0:
            return []
        proj = self.projection or project_input(data, avatar, 0, int(_cfg(c, "texture_resolution")))
        tex = self.complete_texture(data, avatar, mirror_index, proj)
        self.texture = tex
        nb = int(avatar.model_data.n_base_vertices)
        v = proj.vertices[:nb]
        center = (0.5 * (v.max(0).values + v.min(0).values)).double().cpu().numpy()
        bg = _background(data)
        out = []
        for cam in ring_cameras(proj.camera, center, n, float(_cfg(c, "ring_yaw_deg")), float(_cfg(c, "ring_pitch_deg"))):
            img, cover, w = render_texture(proj.vertices, avatar.faces, tex, cam, bg, float(_cfg(c, "ring_background_weight")),
                                           int(_cfg(c, "ring_supersample")))
            out.append(PseudoView(cam.name, cam, img, cover, w, proj.frame_index, False, float(_cfg(c, "ring_weight"))))
        return out


def build_pseudo_views(data: IngestedData, avatar: Avatar, cfg: Any) -> tuple[list[PseudoView], torch.Tensor | None]:
    """Pseudo-views for a one-shot capture, and the (V,) vertex mirror index (None when the model is not symmetric)."""
    mirror_index, _ = mirror_index_of(avatar, float(_cfg(cfg, "mirror_tolerance")))
    proj = project_input(data, avatar, 0, int(_cfg(cfg, "texture_resolution")))
    views: list[PseudoView] = []
    views += MirrorViewProvider(cfg, proj).views(data, avatar, mirror_index)
    views += TexturedRingProvider(cfg, proj).views(data, avatar, mirror_index)
    return views, mirror_index
