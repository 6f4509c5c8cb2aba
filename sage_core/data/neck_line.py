"""The neck-line cut of a head image (VHAP's export rule, docs/formats.md §1.1).

Below the neck the body is cut away: an image keeps what lies above the line through the neck's two
side vertices, anchored at its front-bottom vertex, blurred over about 3 % of the image width. Used
by the synthetic captures (their truth) and by ``sage track`` (on the fitted mesh).
"""

from __future__ import annotations

import numpy as np

from .cameras import Camera


def neck_line_cut(vertices: np.ndarray, ids: tuple[int, int, int], camera: Camera) -> np.ndarray:
    """(H, W) float32 in [0, 1]: 1 above the line through the projected vertices ``ids[0]`` (left) and
    ``ids[1]`` (right) of ``vertices`` (V, 3), moved to pass through ``ids[2]`` (front-bottom), 0 below,
    blurred with a Gaussian about 3 % of the image width wide."""
    import cv2

    uv, _ = camera.project(vertices[list(ids)])
    (xl, yl), (xr, yr), (xa, ya) = uv
    k = (yr - yl) / (xr - xl) if abs(xr - xl) > 1e-6 else 0.0
    b = ya - k * xa
    W, H = camera.width, camera.height
    xs = np.arange(W) + 0.5
    ys = np.arange(H) + 0.5
    mask = ((k * xs[None, :] + b - ys[:, None]) > 0).astype(np.float32)
    ks = int(0.03 * W) // 2 * 2 + 1
    return cv2.GaussianBlur(mask, (ks, ks), ks)
