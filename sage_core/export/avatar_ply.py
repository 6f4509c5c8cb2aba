"""World-space 3DGS PLY of a posed avatar, and the inverse: PLY rows back to rasterizer inputs.

The avatar's colours come from its appearance network (or per-surfel SH) evaluated for one view
direction (the caller poses the surfels, e.g. ``AvatarRenderer.posed``), so a viewer PLY stores them
as SH degree 0: ``f_dc = (rgb − 0.5) / C0`` with
C0 = 0.28209479 (docs/formats.md §7.1), which a viewer turns back into ``rgb = 0.5 + C0·f_dc``. Which view
the colours are baked for is the caller's choice when posing: a camera centre, or None for each
surfel seen along its own normal.

Shading: for an avatar with ``shading="sh2"`` the posed colours are albedo × the world irradiance at
each surfel's outward normal in the pose being written (``Avatar.posed`` with its default
``shade=True``), so the PLY's colours have that pose's shading baked in: a rest/canonical-pose PLY
carries the light as it falls on the head in the canonical pose (no global rotation), and a viewer
that moves the splats does not relight them. With ``shading="none"`` the colours are the avatar's
head-space colours, unchanged.

Viewer files (:func:`encode_viewer`): the same Gaussians as an INRIA PLY, a ``.splat`` or a
PlayCanvas compressed PLY, in sage's y-up world (``orientation="flame"``) or turned by 180° about x
into the y-down convention splat viewers expect (``orientation="viewer"``, see
:mod:`sage_core.export.orientation`), optionally with the SH zero-padded to degree 3.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from .compressed_ply import encode_compressed_ply
from .orientation import orient, oriented_up_axis
from .ply import SH_C0, encode_ply, encode_splat, pad_sh_rest
from ..workspace import atomic_write_bytes

VIEWER_FORMATS: tuple[str, ...] = ("ply", "splat", "compressed-ply")
"""Viewer file formats: INRIA PLY, 32-byte ``.splat`` and PlayCanvas' ``.compressed.ply``."""
VIEWER_SUFFIX = {"ply": ".ply", "splat": ".splat", "compressed-ply": ".compressed.ply"}

if TYPE_CHECKING:
    from ..avatar.model import PosedSurfels


@dataclass
class PlyExport:
    """One written PLY: its path, rows written and rows dropped (non-finite or opacity < 1/255)."""

    path: Path
    n_rows: int
    n_dropped: int


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """(N, 3) colours in [0, 1] -> (N, 3) SH DC coefficients ``(rgb − 0.5) / C0``."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    """(N, 3) SH DC -> (N, 3) colours ``0.5 + C0·f_dc`` clamped at 0 (as 3DGS viewers evaluate them)."""
    return (0.5 + SH_C0 * sh_dc).clamp_min(0.0)


def viewer_gaussians(posed: PosedSurfels, orientation: str = "flame", sh_degree: int = 0) -> dict[str, np.ndarray]:
    """World-space viewer attributes of posed surfels in the given orientation.

    Returns float64 arrays: means (N, 3), quats (N, 4) wxyz, scales (N, 2) linear, opacities (N,),
    sh_dc (N, 3) from the colours clamped to [0, 1], sh_rest (N, (deg+1)² − 1, 3) zeros.
    """
    def a(t: torch.Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float64).numpy()

    n = int(posed.means.shape[0])
    means, quats, rest = orient(a(posed.means), a(posed.quats), pad_sh_rest(None, n, sh_degree), orientation)
    return {
        "means": means, "quats": quats, "scales": a(posed.scales), "opacities": a(posed.opacities),
        "sh_dc": a(rgb_to_sh_dc(posed.colors.clamp(0.0, 1.0))), "sh_rest": rest if rest is not None else np.zeros((n, 0, 3)),
    }  # fmt: skip


def encode_viewer(
    posed: PosedSurfels,
    fmt: str = "ply",
    comments: Sequence[str] | None = None,
    up_axis: str | None = "y",
    orientation: str = "flame",
    sh_degree: int = 0,
) -> tuple[bytes, int]:
    """Viewer file bytes of posed surfels in ``fmt`` (one of :data:`VIEWER_FORMATS`); returns
    (bytes, rows dropped). ``up_axis`` names sage's vertical axis; the comment written is the one of
    the chosen orientation. ``.splat`` has no SH beyond the DC term and no comments."""
    g = viewer_gaussians(posed, orientation, sh_degree)
    up = oriented_up_axis(up_axis, orientation)
    if fmt == "ply":
        return encode_ply(g["means"], g["quats"], g["scales"], g["opacities"], g["sh_dc"], g["sh_rest"], comments, up)
    if fmt == "splat":
        return encode_splat(g["means"], g["quats"], g["scales"], g["opacities"], g["sh_dc"])
    if fmt == "compressed-ply":
        return encode_compressed_ply(g["means"], g["quats"], g["scales"], g["opacities"], g["sh_dc"], g["sh_rest"], comments, up)
    raise ValueError(f"viewer format must be one of {', '.join(VIEWER_FORMATS)}, got {fmt!r}")


def encode_posed_ply(
    posed: PosedSurfels,
    comments: Sequence[str] | None = None,
    up_axis: str | None = "y",
    orientation: str = "flame",
    sh_degree: int = 0,
) -> tuple[bytes, int]:
    """PLY bytes of posed surfels (means (N, 3), quats (N, 4), scales (N, 2), opacities (N,),
    colours (N, 3)); returns (bytes, rows dropped). See :func:`encode_viewer`.

    The colours are written as given: for a shaded avatar (``shading="sh2"``) posed with
    ``shade=True`` they are albedo × irradiance at the written pose, i.e. the pose's shading is baked
    into the PLY (see the module doc)."""
    return encode_viewer(posed, "ply", comments, up_axis, orientation, sh_degree)


def write_posed_ply(
    path: str | Path,
    posed: PosedSurfels,
    comments: Sequence[str] | None = None,
    up_axis: str | None = "y",
    orientation: str = "flame",
    sh_degree: int = 0,
    fmt: str = "ply",
) -> PlyExport:
    """Encode posed surfels as a viewer file (``fmt``: ply, splat or compressed-ply) and write it
    atomically (colours as in :func:`encode_posed_ply`: a shaded avatar's irradiance at this pose is
    baked in)."""
    data, dropped = encode_viewer(posed, fmt, comments, up_axis, orientation, sh_degree)
    atomic_write_bytes(path, data)
    n = int(posed.means.shape[0])
    return PlyExport(Path(path), n - dropped, dropped)


def ply_render_inputs(
    ply: dict[str, np.ndarray], device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rasterizer inputs from :func:`sage_core.export.ply.read_ply` output.

    Returns means (N, 3), quats (N, 4), scales (N, 2) (the two in-plane axes; the thin third one is
    dropped), opacities (N,) and colours (N, 3) from the SH DC (higher SH terms, if any, ignored).
    """
    def t(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), device=device).to(dtype)

    scales = ply["scales"]
    if scales.shape[1] == 3:
        scales = scales[:, :2]
    return t(ply["means"]), t(ply["quats"]), t(scales), t(ply["opacities"]), sh_dc_to_rgb(t(ply["sh_dc"]))
