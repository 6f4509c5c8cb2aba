"""World orientation of viewer exports: FLAME's y-up world or the splat ecosystem's y-down one.

sage's world is the capture's (VHAP/FLAME: y up, the face looking towards +z). 3DGS viewers
(PlayCanvas, SuperSplat, splat-transform's HTML viewer and most others) take PLY and ``.splat`` data
in the y-down OpenCV/COLMAP convention (a frontal camera looks along +z, so a face it sees looks
towards −z) and turn it upright with a 180° rotation about z when they display it. The "viewer"
orientation is the OpenGL → OpenCV flip, a rotation by 180° about x:

    x' = (x, −y, −z)   (det +1)

so those viewers show the head upright, its face towards −z of their displayed world, where
splat-transform's HTML viewer puts its default camera ((2, 2, −2) looking at the origin).

It applies to every world-space attribute: positions, rotations (q' = q_z ⊗ q, so R(q') = S·R(q))
and the higher SH coefficients, which a diagonal sign matrix only negates (each real SH basis
function is even or odd in every axis). Scales, opacities and the SH DC term are unchanged.
"""

from __future__ import annotations

import functools

import numpy as np

ORIENTATIONS: tuple[str, ...] = ("viewer", "flame")
"""``viewer``: y-down (rotated 180° about x) as splat viewers expect; ``flame``: sage's y-up world."""

_FLIP = {"viewer": np.array([1.0, -1.0, -1.0]), "flame": np.array([1.0, 1.0, 1.0])}
_QUAT = {"viewer": np.array([0.0, 1.0, 0.0, 0.0]), "flame": np.array([1.0, 0.0, 0.0, 0.0])}  # wxyz


def check_orientation(name: str) -> str:
    """``name`` if it is one of :data:`ORIENTATIONS`, else ValueError."""
    if name not in ORIENTATIONS:
        raise ValueError(f"orientation must be one of {', '.join(ORIENTATIONS)}, got {name!r}")
    return name


def orientation_matrix(name: str) -> np.ndarray:
    """(3, 3) rotation taking sage's world to the ``name`` orientation."""
    return np.diag(_FLIP[check_orientation(name)])


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of wxyz quaternions; a (4,), b (N, 4) -> (N, 4)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=1,
    )


@functools.lru_cache(maxsize=8)
def _sh_signs(flip: tuple[float, float, float], degree: int) -> np.ndarray:
    """(K,) sign of every non-DC SH coefficient under the diagonal map ``flip`` (K = (deg+1)² − 1),
    measured on sage's own basis so it follows its sign conventions."""
    import torch

    from ..geometry.sh import sh_basis

    d = torch.nn.functional.normalize(torch.tensor([[0.3, 0.5, 0.8], [-0.6, 0.2, 0.7]], dtype=torch.float64), dim=-1)
    b0 = sh_basis(d, degree)[:, 1:]
    b1 = sh_basis(d * torch.tensor(flip, dtype=torch.float64), degree)[:, 1:]
    ratio = (b1 / b0).mean(0).numpy()
    signs = np.sign(ratio)
    if not np.allclose(np.abs(ratio), 1.0, atol=1e-9):
        raise AssertionError("SH basis is not even or odd in every axis")
    return signs


def orient(
    means: np.ndarray, quats: np.ndarray, sh_rest: np.ndarray | None, name: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Apply the ``name`` orientation to world-space Gaussians.

    means: (N, 3); quats: (N, 4) wxyz (any norm); sh_rest: (N, K, 3) or None.
    Returns the rotated (means, quats, sh_rest) as float64 arrays (sh_rest None stays None).
    """
    check_orientation(name)
    means = np.asarray(means, dtype=np.float64)
    quats = np.asarray(quats, dtype=np.float64)
    if name == "flame":
        return means, quats, None if sh_rest is None else np.asarray(sh_rest, dtype=np.float64)
    flip = _FLIP[name]
    out_means = means * flip
    out_quats = _quat_mul(_QUAT[name], quats)
    if sh_rest is None or sh_rest.shape[1] == 0:
        return out_means, out_quats, None if sh_rest is None else np.asarray(sh_rest, dtype=np.float64)
    k = sh_rest.shape[1]
    degree = int(round(np.sqrt(k + 1))) - 1
    signs = _sh_signs(tuple(float(f) for f in flip), degree)
    return out_means, out_quats, np.asarray(sh_rest, dtype=np.float64) * signs[None, :, None]


def oriented_up_axis(up_axis: str | None, name: str) -> str | None:
    """The PLY ``Vertical Axis`` comment after the ``name`` orientation: ``y`` becomes ``-y`` in the
    viewer orientation (y and z are negated there, x is kept)."""
    if up_axis is None or check_orientation(name) == "flame":
        return up_axis
    neg = up_axis.startswith("-")
    axis = up_axis.lstrip("-+")
    if axis in ("y", "z"):
        neg = not neg
    return ("-" if neg else "") + axis
