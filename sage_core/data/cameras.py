"""Pinhole cameras in OpenCV convention and the conversion from/to VHAP "NeRF-style" frames.

OpenCV axes: x right, y down, z forward. ``K`` is 3×3 in pixels with continuous pixel
coordinates (the image spans [0, w]×[0, h], pixel centres at +0.5). ``w2c`` is 4×4.

VHAP ``transforms*.json`` frames store ``transform_matrix`` as camera-to-world in OpenGL axes and
``cy`` flipped (``cy_json = h − cy_opencv``); see docs/formats.md §2.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    """One calibrated view.

    Attributes:
        K: (3, 3) float64 intrinsics, pixels.
        w2c: (4, 4) float64 world-to-camera, OpenCV axes.
        width, height: image size in pixels.
        index: the capture's camera index (8 = frontal in NeRSemble exports), -1 if none.
        name: camera serial or free-form label.
    """

    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    index: int = -1
    name: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def c2w(self) -> np.ndarray:
        """(4, 4) camera-to-world, OpenCV axes."""
        return np.linalg.inv(self.w2c)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        R = self.w2c[:3, :3]
        return -R.T @ self.w2c[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points.

        points: (N, 3) -> (uv (N, 2) pixel coordinates, z (N,) view depth). Visible iff z > 0.
        """
        pc = points @ self.w2c[:3, :3].T + self.w2c[:3, 3]
        z = pc[:, 2]
        uvw = pc @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[:, :2] / uvw[:, 2:3]
        return uv, z

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for an image resized to (width, height); K scales per axis (docs/formats.md §2.2)."""
        sx = width / self.width
        sy = height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 2] *= sx
        K[1, 1] *= sy
        K[1, 2] *= sy
        return Camera(K, self.w2c.copy(), int(width), int(height), self.index, self.name, dict(self.extra))

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON-safe)."""
        return {
            "K": self.K.tolist(),
            "w2c": self.w2c.tolist(),
            "width": self.width,
            "height": self.height,
            "index": self.index,
            "name": self.name,
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "Camera":
        """Inverse of :meth:`to_dict`."""
        return Camera(
            np.asarray(d["K"], dtype=np.float64),
            np.asarray(d["w2c"], dtype=np.float64),
            int(d["width"]),
            int(d["height"]),
            int(d.get("index", -1)),
            str(d.get("name", "")),
        )


def camera_from_nerf_frame(frame: dict[str, Any]) -> Camera:
    """Build an OpenCV camera from one VHAP transforms frame (per-frame intrinsics, never the top level).

    Required keys: ``transform_matrix`` (4×4 OpenGL c2w), ``fl_x``, ``fl_y``, ``cx``, ``cy``
    (OpenGL-flipped), ``w``, ``h``. Optional: ``camera_index``, ``camera_id``.
    """
    M = np.asarray(frame["transform_matrix"], dtype=np.float64)
    w, h = int(frame["w"]), int(frame["h"])
    C = M @ _GL_TO_CV
    R = C[:3, :3]
    t = C[:3, 3]
    w2c = np.eye(4)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ t
    K = np.array(
        [
            [float(frame["fl_x"]), 0.0, float(frame["cx"])],
            [0.0, float(frame["fl_y"]), h - float(frame["cy"])],
            [0.0, 0.0, 1.0],
        ]
    )
    return Camera(K, w2c, w, h, int(frame.get("camera_index", -1)), str(frame.get("camera_id", "")))


def camera_to_nerf_frame(cam: Camera) -> dict[str, Any]:
    """The inverse of :func:`camera_from_nerf_frame`: VHAP per-frame camera fields.

    Returns ``transform_matrix`` (OpenGL c2w), ``fl_x``, ``fl_y``, ``cx``, ``cy`` (flipped), ``w``,
    ``h``, ``camera_angle_x`` and ``camera_angle_y``.
    """
    c2w_cv = np.linalg.inv(cam.w2c)
    M = c2w_cv @ _GL_TO_CV  # diag is its own inverse
    fx, fy = float(cam.K[0, 0]), float(cam.K[1, 1])
    return {
        "transform_matrix": M.tolist(),
        "fl_x": fx,
        "fl_y": fy,
        "cx": float(cam.K[0, 2]),
        "cy": float(cam.height - cam.K[1, 2]),
        "w": int(cam.width),
        "h": int(cam.height),
        "camera_angle_x": float(2 * np.arctan(cam.width / (2 * fx))),
        "camera_angle_y": float(2 * np.arctan(cam.height / (2 * fy))),
    }


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """World-to-camera (4, 4), OpenCV axes, for a camera at ``eye`` looking at ``target``.

    ``up`` is the world up direction; the camera's y axis (down in the image) is opposite to it.
    """
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], 0)  # rows: camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ np.asarray(eye, float)
    return w2c
