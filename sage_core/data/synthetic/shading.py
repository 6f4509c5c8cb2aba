"""Shading shared by the synthetic head's renderers: the world light, highlights' parameters, the
eyes' albedo, the render result and pixel rays."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..cameras import Camera
from ._fields import smoothstep, value_noise

if TYPE_CHECKING:
    from .appearance import Appearance

LIGHT_DIR = np.array([0.35, 0.55, 0.75]) / np.linalg.norm([0.35, 0.55, 0.75])
AMBIENT, DIFFUSE = 0.42, 0.62


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a * (1.0 - t[:, None]) + b * t[:, None]


def _eye_albedo(eye_dir: np.ndarray, app: Appearance) -> np.ndarray:
    """Sclera, iris and pupil from directions out of the eyeball centre: (M, 3) -> (M, 3)."""
    ed = eye_dir / np.maximum(np.linalg.norm(eye_dir, axis=1, keepdims=True), 1e-12)
    ang = np.arccos(np.clip(ed[:, 2], -1.0, 1.0))
    rad = np.arctan2(ed[:, 1], ed[:, 0])
    sclera = np.array([0.93, 0.9, 0.86])[None] * (1.0 - 0.08 * smoothstep(ang, 0.9, 1.4))[:, None]
    iris_c = np.asarray(app.iris)[None] * (0.75 + 0.25 * np.sin(rad * 23.0 + 4.0 * value_noise(ed, 8.0, app.noise_seed + 5)))[:, None]
    iris_c *= (1.0 - 0.5 * smoothstep(ang, 0.40, 0.5))[:, None]
    eye = _mix(sclera, iris_c, smoothstep(ang, 0.52, 0.47))
    return _mix(eye, np.full_like(eye, 0.03), smoothstep(ang, 0.21, 0.18))


@dataclass(frozen=True)
class Specular:
    """Blinn-Phong highlights under the world light (added on top of the shaded albedo).

    Attributes:
        skin, skin_shininess: strength and exponent on skin (none on scalp hair or in the mouth).
        eye, eye_shininess: strength and exponent on the eyeballs.
        hair, hair_shininess: strength and exponent of the anisotropic sheen of hair strands
            (detailed subjects only: it needs the strand direction).
    """

    skin: float = 0.08
    skin_shininess: float = 18.0
    eye: float = 0.45
    eye_shininess: float = 90.0
    hair: float = 0.25
    hair_shininess: float = 12.0

    def scaled(self, k: float) -> Specular:
        """The same highlights with every strength multiplied by ``k``."""
        return Specular(self.skin * k, self.skin_shininess, self.eye * k, self.eye_shininess, self.hair * k, self.hair_shininess)


@dataclass
class Render:
    """A shaded view.

    Attributes:
        rgb: (H, W, 3) float32 composited on the background.
        alpha: (H, W) float32 coverage in [0, 1] (fractional at edges when supersampled).
        depth: (H, W) float32 camera-space z at pixel centres (+inf background), or None.
        normal: (H, W, 3) float32 world-space unit normals facing the camera (0 background), or None.
    """

    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray | None = None
    normal: np.ndarray | None = None


def _pixel_dirs(camera: Camera, scale: int, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World ray origin and unit directions (M, 3) through the given pixel centres."""
    K = camera.K.astype(np.float64).copy()
    K[:2] *= scale
    yc = (ys + 0.5 - K[1, 2]) / K[1, 1]
    xc = (xs + 0.5 - K[0, 2] - K[0, 1] * yc) / K[0, 0]
    d = np.stack([xc, yc, np.ones_like(xc)], -1) @ camera.w2c[:3, :3]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return camera.center, d
