"""The tracking report's picture: a contact sheet of the fitted mesh over the images, with the
detected landmarks (green) and where the fit puts them (red)."""

from __future__ import annotations

import numpy as np
import torch

from ..data.cameras import Camera
from .shading import shade

TILE_HEIGHT = 240


def _dot(img: np.ndarray, xy: np.ndarray, color: tuple[float, float, float]) -> None:
    H, W = img.shape[:2]
    for x, y in xy:
        xi, yi = int(x), int(y)
        if 0 <= xi < W and 0 <= yi < H:
            img[max(yi - 0, 0):yi + 1, max(xi - 0, 0):xi + 1] = color


def overlay_tile(image: np.ndarray, vertices: torch.Tensor, faces: torch.Tensor, camera: Camera,
                 detected: np.ndarray | None, fitted: np.ndarray | None) -> np.ndarray:
    """One contact-sheet tile (TILE_HEIGHT high): the image on the left, the shaded mesh blended over it
    on the right, landmarks (output pixels) drawn on both. image: (H, W, 3) in [0, 1]."""
    import cv2

    H, W = image.shape[:2]
    s = TILE_HEIGHT / H
    w = max(1, int(round(W * s)))
    small = cv2.resize(np.ascontiguousarray(image, dtype=np.float32), (w, TILE_HEIGHT), interpolation=cv2.INTER_AREA)
    cam = camera.resized(w, TILE_HEIGHT)
    mesh, cov, _ = shade(vertices.detach().float().cpu(), faces.cpu(), cam, supersample=2)
    blend = small * (1 - 0.6 * cov[..., None]) + mesh * 0.6 * cov[..., None]
    left, right = small.copy(), blend
    for img in (left, right):
        if detected is not None:
            _dot(img, detected * s, (0.1, 0.85, 0.1))
        if fitted is not None:
            _dot(img, fitted * s, (0.95, 0.1, 0.1))
    return np.clip(np.concatenate([left, right], 1), 0, 1)


def contact_sheet(tiles: list[np.ndarray], columns: int = 3) -> np.ndarray:
    """Tiles (TILE_HEIGHT, w_i, 3) in a grid, white padding between them -> (H, W, 3)."""
    if not tiles:
        return np.ones((TILE_HEIGHT, TILE_HEIGHT, 3), np.float32)
    pad = 4
    width = max(t.shape[1] for t in tiles)
    rows = []
    for i in range(0, len(tiles), columns):
        row = [np.pad(t, ((0, 0), (0, width - t.shape[1] + pad), (0, 0)), constant_values=1.0) for t in tiles[i:i + columns]]
        while len(row) < columns:
            row.append(np.ones((TILE_HEIGHT, width + pad, 3), np.float32))
        rows.append(np.pad(np.concatenate(row, 1), ((0, pad), (0, 0), (0, 0)), constant_values=1.0))
    return np.concatenate(rows, 0)
