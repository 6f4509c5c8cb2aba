"""Ground-truth triangle rasterizer (numpy, vectorised z-buffer), independent of ``sage_core.render``.

Cameras are :class:`sage_core.data.cameras.Camera` (OpenCV axes, K in pixels with pixel centres at
+0.5). Barycentrics are perspective-correct; ``depth`` is the camera-space z (not the ray length).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cameras import Camera

_NEAR = 1e-4
_MAX_CANDIDATES = 1_000_000


@dataclass
class Fragments:
    """Visible surface per pixel.

    Attributes:
        face: (H, W) int64 triangle id, -1 where nothing is hit.
        bary: (H, W, 3) float64 perspective-correct barycentrics of the hit (zeros on background).
        depth: (H, W) float64 camera-space z of the hit, +inf on background.
    """

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool foreground."""
        return self.face >= 0

    def interpolate(self, attr: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Per-pixel interpolation of per-vertex attributes at the foreground pixels.

        attr: (V, C); faces: (F, 3) -> (M, C) for the M foreground pixels in row-major order.
        """
        m = self.mask
        tri = faces[self.face[m]]  # (M, 3)
        b = self.bary[m]  # (M, 3)
        return np.einsum("mk,mkc->mc", b, attr[tri])


def rasterize(vertices: np.ndarray, faces: np.ndarray, camera: Camera, scale: int = 1) -> Fragments:
    """Z-buffer rasterization of a triangle mesh.

    vertices: (V, 3) world positions; faces: (F, 3) int; camera: the view; scale: render at
    ``scale``× the camera's resolution (supersampling; K is scaled accordingly).
    Returns :class:`Fragments` of size (scale·H, scale·W). Triangles with a vertex behind the
    near plane (z < 1e-4) are dropped; both sides of every triangle are drawn.
    """
    W, H = camera.width * scale, camera.height * scale
    K = camera.K.astype(np.float64).copy()
    K[:2] *= scale
    v = np.asarray(vertices, dtype=np.float64)
    pc = v @ camera.w2c[:3, :3].T + camera.w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[:, 0] / z + K[0, 1] * pc[:, 1] / z + K[0, 2]
        vv = K[1, 1] * pc[:, 1] / z + K[1, 2]
    f = np.asarray(faces, dtype=np.int64)
    fz = z[f]
    keep = np.all(fz > _NEAR, axis=1)
    fu, fv = u[f], vv[f]
    x0 = np.ceil(fu.min(1) - 0.5)
    x1 = np.floor(fu.max(1) - 0.5)
    y0 = np.ceil(fv.min(1) - 0.5)
    y1 = np.floor(fv.max(1) - 0.5)
    x0, y0 = np.maximum(x0, 0), np.maximum(y0, 0)
    x1, y1 = np.minimum(x1, W - 1), np.minimum(y1, H - 1)
    area = (fu[:, 1] - fu[:, 0]) * (fv[:, 2] - fv[:, 0]) - (fu[:, 2] - fu[:, 0]) * (fv[:, 1] - fv[:, 0])
    keep &= (x1 >= x0) & (y1 >= y0) & (np.abs(area) > 1e-12) & np.isfinite(area)
    fid = np.flatnonzero(keep)
    nx = (x1[fid] - x0[fid] + 1).astype(np.int64)
    ny = (y1[fid] - y0[fid] + 1).astype(np.int64)
    counts = nx * ny

    best_depth = np.full(H * W, np.inf)
    best_face = np.full(H * W, -1, dtype=np.int64)
    best_bary = np.zeros((H * W, 3))
    start = 0
    while start < len(fid):
        csum = np.cumsum(counts[start:])
        stop = start + max(1, int(np.searchsorted(csum, _MAX_CANDIDATES, side="right")))
        sel = fid[start:stop]
        cnt = counts[start:stop]
        rep = np.repeat(np.arange(len(sel)), cnt)
        offs = np.arange(rep.shape[0]) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        nxr = nx[start:stop][rep]
        px = x0[sel][rep] + offs % nxr + 0.5
        py = y0[sel][rep] + offs // nxr + 0.5
        fsel = sel[rep]
        u0, u1, u2 = fu[fsel, 0], fu[fsel, 1], fu[fsel, 2]
        v0, v1, v2 = fv[fsel, 0], fv[fsel, 1], fv[fsel, 2]
        a = area[fsel]
        b1 = ((px - u0) * (v2 - v0) - (u2 - u0) * (py - v0)) / a
        b2 = ((u1 - u0) * (py - v0) - (px - u0) * (v1 - v0)) / a
        b0 = 1.0 - b1 - b2
        inside = (b0 >= 0) & (b1 >= 0) & (b2 >= 0)
        b = np.stack([b0, b1, b2], -1)[inside]
        fsel = fsel[inside]
        pid = (py[inside] - 0.5).astype(np.int64) * W + (px[inside] - 0.5).astype(np.int64)
        wz = b / fz[fsel]
        inv = wz.sum(1)
        depth = 1.0 / inv
        bpc = wz * depth[:, None]
        order = np.lexsort((depth, pid))
        pid_s = pid[order]
        first = np.ones(len(order), bool)
        first[1:] = pid_s[1:] != pid_s[:-1]
        win = order[first]
        pw = pid[win]
        better = depth[win] < best_depth[pw]
        pw, win = pw[better], win[better]
        best_depth[pw] = depth[win]
        best_face[pw] = fsel[win]
        best_bary[pw] = bpc[win]
        start = stop
    return Fragments(best_face.reshape(H, W), best_bary.reshape(H, W, 3), best_depth.reshape(H, W))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals. vertices: (V, 3), faces: (F, 3) -> (V, 3)."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)


def downsample(img: np.ndarray, scale: int) -> np.ndarray:
    """Box-filter an (sH, sW, ...) image down by ``scale`` per axis -> (H, W, ...)."""
    if scale == 1:
        return img
    H, W = img.shape[0] // scale, img.shape[1] // scale
    return img.reshape(H, scale, W, scale, *img.shape[2:]).mean(axis=(1, 3))


def pixel_rays(camera: Camera, scale: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World ray origin (3,) and unit directions (sH, sW, 3) through the pixel centres."""
    W, H = camera.width * scale, camera.height * scale
    K = camera.K.astype(np.float64).copy()
    K[:2] *= scale
    xs = (np.arange(W) + 0.5 - K[0, 2]) / K[0, 0]
    ys = (np.arange(H) + 0.5 - K[1, 2]) / K[1, 1]
    xs = xs[None, :] - K[0, 1] * ys[:, None] / K[0, 0]
    d_cam = np.stack(np.broadcast_arrays(xs, ys[:, None], np.ones((H, W))), -1)
    R = camera.w2c[:3, :3]
    d = d_cam @ R  # rows: R^T d
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return camera.center, d
