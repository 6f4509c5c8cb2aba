"""Calibrated cameras for multiview tracking: COLMAP text models and ``transforms.json`` files.

Each reader returns named cameras (:class:`CalibratedCamera`): OpenCV intrinsics and world-to-camera
pose (:class:`sage_core.data.cameras.Camera`), optional OpenCV distortion coefficients, and the
names a camera folder of the input may carry.

- COLMAP text (``cameras.txt`` + ``images.txt``, a folder such as ``sparse/0`` or either file): models
  SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV; ``images.txt`` poses are world-to-camera
  (quaternion w, x, y, z and translation) in OpenCV axes. An image named ``cam_03/00000.png`` belongs
  to camera folder ``cam_03``; ``cam_03.png`` too. COLMAP's scale is arbitrary (not metres).
- ``transforms.json``: a VHAP / GaussianAvatars export (frames carry ``timestep_index`` and
  ``camera_index``; ``cy`` is stored flipped; metres) or a NeRF-style file (instant-ngp, nerfstudio:
  intrinsics per frame or at the top level, ``cy`` not flipped, OpenGL camera-to-world, any scale).
  A VHAP camera is matched by its ``camera_id`` or by its index (a folder name ending in that number);
  a NeRF frame by the folder of its ``file_path`` (or the file's stem).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data.cameras import Camera, camera_from_nerf_frame
from ..errors import InputError

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class CalibratedCamera:
    """One calibrated camera.

    Attributes:
        camera: intrinsics (pixels, pixel centres at +0.5) and pose, OpenCV axes, at the calibration's
            image size.
        distortion: OpenCV coefficients (k1, k2, p1, p2, k3), or None for a pinhole camera.
        names: folder names that select this camera (first = its display name).
        index: camera index to write (the file's own index when it has one).
    """

    camera: Camera
    distortion: np.ndarray | None
    names: list[str]
    index: int


@dataclass
class CameraSet:
    """The cameras of a calibration file: ``cameras`` in file order, ``metric`` when the file is known
    to be in metres (VHAP exports), ``source`` the file read, ``warnings`` one sentence each."""

    cameras: list[CalibratedCamera]
    metric: bool
    source: Path
    warnings: list[str] = field(default_factory=list)

    def match(self, folder: str) -> CalibratedCamera | None:
        """The camera a folder name selects: an exact name, else a trailing number equal to the index."""
        for c in self.cameras:
            if folder in c.names:
                return c
        m = re.search(r"(\d+)$", folder)
        if m is not None:
            hits = [c for c in self.cameras if c.index == int(m.group(1)) and c.index >= 0]
            if len(hits) == 1:
                return hits[0]
        return None


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


_COLMAP_MODELS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}


def _colmap_intrinsics(path: Path, line_no: int, model: str, p: list[float]) -> tuple[np.ndarray, np.ndarray | None]:
    if model not in _COLMAP_MODELS:
        raise InputError(path, f"line {line_no}: camera model {model} is not supported (use one of {', '.join(_COLMAP_MODELS)})")
    if len(p) != _COLMAP_MODELS[model]:
        raise InputError(path, f"line {line_no}: {model} takes {_COLMAP_MODELS[model]} parameters, found {len(p)}")
    dist = None
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        if model == "SIMPLE_RADIAL":
            dist = np.array([p[3], 0.0, 0.0, 0.0, 0.0])
        elif model == "RADIAL":
            dist = np.array([p[3], p[4], 0.0, 0.0, 0.0])
    else:
        fx, fy, cx, cy = p[:4]
        if model == "OPENCV":
            dist = np.array([p[4], p[5], p[6], p[7], 0.0])
    if not (fx > 0 and fy > 0):
        raise InputError(path, f"line {line_no}: focal length must be positive")
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), dist


def _data_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the file ({exc})") from None
    return [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]


def read_colmap(path: str | Path) -> CameraSet:
    """Read a COLMAP text model (a folder with ``cameras.txt`` and ``images.txt``, or one of them)."""
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    cam_file, img_file = folder / "cameras.txt", folder / "images.txt"
    for f in (cam_file, img_file):
        if not f.is_file():
            raise InputError(f, "COLMAP text model file not found (expected cameras.txt and images.txt side by side)")
    intr: dict[int, tuple[np.ndarray, np.ndarray | None, int, int]] = {}
    for no, ln in _data_lines(cam_file):
        parts = ln.split()
        try:
            cid, model, w, h = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = [float(x) for x in parts[4:]]
        except (ValueError, IndexError):
            raise InputError(cam_file, f"line {no}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'") from None
        K, dist = _colmap_intrinsics(cam_file, no, model, params)
        intr[cid] = (K, dist, w, h)
    lines = _data_lines(img_file)
    cams: list[CalibratedCamera] = []
    i = 0
    # images.txt alternates an image line and a (possibly empty, then skipped) points line; an image
    # line has exactly 10 fields with an integer camera id in field 9
    while i < len(lines):
        no, ln = lines[i]
        parts = ln.split()
        i += 1
        if len(parts) < 10:
            continue
        try:
            vals = [float(x) for x in parts[1:8]]
            cid = int(parts[8])
        except ValueError:
            continue
        name = " ".join(parts[9:])
        if cid not in intr:
            raise InputError(img_file, f"line {no}: image {name} names camera {cid}, which cameras.txt lacks")
        K, dist, w, h = intr[cid]
        w2c = np.eye(4)
        w2c[:3, :3] = _quat_to_matrix(np.array(vals[:4]))
        w2c[:3, 3] = vals[4:7]
        rel = Path(name)
        folder_name = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        cams.append(CalibratedCamera(Camera(K, w2c, w, h, -1, folder_name), dist, [folder_name], -1))
        if i < len(lines) and len(lines[i][1].split()) != 10:
            i += 1  # its 2D points line
    if not cams:
        raise InputError(img_file, "no images listed")
    return CameraSet(_unique(cams, img_file), metric=False, source=img_file)


def _unique(cams: list[CalibratedCamera], source: Path) -> list[CalibratedCamera]:
    """One entry per camera folder (a folder listed twice must carry the same camera)."""
    out: dict[str, CalibratedCamera] = {}
    for c in cams:
        key = c.names[0]
        if key in out:
            a, b = out[key].camera, c.camera
            if not (np.allclose(a.K, b.K, atol=1e-6) and np.allclose(a.w2c, b.w2c, atol=1e-6)):
                raise InputError(source, f"camera folder '{key}' is listed with two different calibrations")
            continue
        out[key] = c
    return list(out.values())


def _num(d: dict[str, Any], key: str, where: str, source: Path) -> float:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise InputError(source, f"{where}: '{key}' is missing or not a number")
    return float(v)


def read_transforms(path: str | Path) -> CameraSet:
    """Read a VHAP export's or a NeRF-style ``transforms.json``."""
    source = Path(path)
    try:
        doc = json.loads(source.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(source, f"cannot read the file ({exc})") from None
    except json.JSONDecodeError as exc:
        raise InputError(source, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise InputError(source, "expected a JSON object with a non-empty 'frames' list")
    frames = doc["frames"]
    vhap = all(isinstance(f, dict) and "timestep_index" in f and "camera_index" in f for f in frames)
    cams: list[CalibratedCamera] = []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "transform_matrix" not in fr:
            raise InputError(source, f"frame {i} lacks 'transform_matrix'")
        M = np.asarray(fr["transform_matrix"], dtype=np.float64)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise InputError(source, f"frame {i}: 'transform_matrix' is not a 4x4 matrix of numbers")
        R = M[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-3):
            raise InputError(source, f"frame {i}: the rotation of 'transform_matrix' is not orthonormal")
        merged = {**{k: doc[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2", "k3") if k in doc}, **fr}
        where = f"frame {i}"
        if "fl_x" not in merged and "camera_angle_x" in merged:
            merged["fl_x"] = _num(merged, "w", where, source) / (2 * np.tan(_num(merged, "camera_angle_x", where, source) / 2))
        merged.setdefault("fl_y", merged.get("fl_x"))
        w, h = int(_num(merged, "w", where, source)), int(_num(merged, "h", where, source))
        merged.setdefault("cx", w / 2)
        merged.setdefault("cy", h / 2)
        for k in ("fl_x", "fl_y", "cx", "cy"):
            _num(merged, k, where, source)
        if vhap:
            cam = camera_from_nerf_frame(merged)
            cid = str(fr.get("camera_id", "")) or f"{int(fr['camera_index']):02d}"
            names = [cid, f"{int(fr['camera_index']):02d}", str(int(fr["camera_index"]))]
            index = int(fr["camera_index"])
        else:
            C = M @ _GL_TO_CV
            w2c = np.linalg.inv(C)
            K = np.array([[merged["fl_x"], 0, merged["cx"]], [0, merged["fl_y"], merged["cy"]], [0, 0, 1.0]], dtype=np.float64)
            rel = Path(str(fr.get("file_path", f"camera_{i}")))
            name = rel.parent.name if rel.parent.name else rel.stem
            cam = Camera(K, w2c, w, h, -1, name)
            names, index = [name], -1
        dist = None
        if any(k in merged for k in ("k1", "k2", "p1", "p2", "k3")):
            dist = np.array([float(merged.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")])
            if not np.any(dist):
                dist = None
        cam.name = names[0]
        cam.index = index
        cams.append(CalibratedCamera(cam, dist, names, index))
    return CameraSet(_unique(cams, source), metric=vhap, source=source)


def read_cameras(path: str | Path) -> CameraSet:
    """A calibration file by its kind: ``*.json`` -> :func:`read_transforms`, a folder or ``*.txt`` ->
    :func:`read_colmap`. InputError names the file when it is missing or malformed."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "cameras file not found")
    if p.is_file() and p.suffix.lower() == ".json":
        return read_transforms(p)
    if p.is_dir() or p.suffix.lower() == ".txt":
        return read_colmap(p)
    raise InputError(p, "unknown cameras file: give a transforms.json or a COLMAP text model (folder, cameras.txt or images.txt)")
