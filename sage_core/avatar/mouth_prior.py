"""The pretrained mouth-interior prior: albedo grids over subject-independent mouth coordinates.

SAGE composites a pretrained mouth-interior prior into the avatar, because no training view shows
the inside of the mouth. sage's prior is a small file shipped with the package
(``mouth_prior.safetensors`` beside this module, kind ``sage-mouth-prior``): four albedo grids, one
per part of the mouth interior,

* ``cavity_upper`` / ``cavity_lower``: mouth-interior faces (cavity, tongue, and a capture's own
  mouth pocket) rigged mostly to the neck / to the jaw,
* ``teeth_upper`` / ``teeth_lower``: teeth faces rigged to the neck / the jaw,

over the mouth coordinates u = ((x − x_c)/w, (y − y_s)/w, (z_f − z)/w) of a canonical point: lateral,
up and backward from the mouth frame's origin (the slit's centre on the front plane, from the lips;
:func:`sage_core.flame.mouth.mouth_frame`), in lip widths ``w``. The grids cover the box
:data:`BOX_LO` .. :data:`BOX_HI`; a point outside is clamped to it. A surfel's prior is the
trilinear interpolation of its part's grid at its canonical centre, so the prior maps onto any
subject's mouth mesh (sage's own, FLAME with teeth, a capture's own mouth pocket) by position alone.

The grids hold albedo (what the avatar's colour is before the light's shading) in sage's convention,
where the light's irradiance has mean 1 over the sphere (:mod:`sage_core.avatar.shading`). They are fitted
once, on synthetic subjects that no benchmark uses, by ``python benchmarks/train_mouth_prior.py``
(docs/method.md, "The mouth interior"); the file's ``provenance`` records the script, the seeds, the
sampling and the sage version.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError
from ..serialization import MOUTH_PRIOR_FORMAT, MOUTH_PRIOR_KIND, load_file, save_file

if TYPE_CHECKING:
    import torch

    from ..flame.model_data import FlameModelData
    from ..flame.regions import Regions

PARTS: tuple[str, ...] = ("cavity_upper", "cavity_lower", "teeth_upper", "teeth_lower")
BOX_LO = (-0.6, -0.6, -0.1)
"""Lower corner of the grids in mouth coordinates (lateral, up, backward), lip widths."""
BOX_HI = (0.6, 0.4, 1.0)
"""Upper corner of the grids."""
GRID_SHAPE = (16, 12, 16)
"""Grid cells along (lateral, up, backward)."""
PRIOR_FILE = Path(__file__).with_name("mouth_prior.safetensors")
"""The prior shipped with the package."""


@dataclass
class MouthPrior:
    """Albedo grids of the mouth interior.

    Attributes:
        color: (P, X, Y, Z, 3) float32 albedo per part (:data:`PARTS`) and grid node.
        weight: (P, X, Y, Z) float32 observed weight of each node (0: filled from neighbours).
        lo, hi: (3,) the box the grids span (mouth coordinates).
        provenance: how the grids were made (plain data).
    """

    color: np.ndarray
    weight: np.ndarray
    lo: np.ndarray = field(default_factory=lambda: np.array(BOX_LO, np.float32))
    hi: np.ndarray = field(default_factory=lambda: np.array(BOX_HI, np.float32))
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        c, w = np.asarray(self.color), np.asarray(self.weight)
        if c.ndim != 5 or c.shape[0] != len(PARTS) or c.shape[-1] != 3:
            raise ValueError(f"color must be ({len(PARTS)}, X, Y, Z, 3), got {c.shape}")
        if w.shape != c.shape[:-1]:
            raise ValueError(f"weight must be {c.shape[:-1]}, got {w.shape}")
        if min(c.shape[1:4]) < 2:
            raise ValueError("each grid needs at least 2 nodes per axis")

    def to_tree(self) -> dict[str, Any]:
        return {"color": np.asarray(self.color, np.float32), "weight": np.asarray(self.weight, np.float32),
                "lo": np.asarray(self.lo, np.float32), "hi": np.asarray(self.hi, np.float32),
                "parts": list(PARTS), "provenance": self.provenance}  # fmt: skip

    def lookup(self, coords: np.ndarray, part: np.ndarray) -> np.ndarray:
        """(N, 3) albedo at mouth coordinates ``coords`` (N, 3) of parts ``part`` (N,) int (index into
        :data:`PARTS`), trilinear over the part's grid, clamped to the box."""
        c = np.asarray(self.color, np.float64)
        n = np.array(c.shape[1:4])
        t = (np.asarray(coords, np.float64) - self.lo) / (np.asarray(self.hi, np.float64) - self.lo) * (n - 1)
        t = np.clip(t, 0.0, n - 1 - 1e-9)
        i0 = np.floor(t).astype(np.int64)
        f = t - i0
        out = np.zeros((t.shape[0], 3))
        p = np.asarray(part, np.int64)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    wgt = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (f[:, 2] if dz else 1 - f[:, 2])
                    out += wgt[:, None] * c[p, i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz]
        return np.clip(out, 0.0, 1.0)


def save_mouth_prior(path: str | Path, prior: MouthPrior) -> Path:
    """Write ``prior`` as a safetensors file of kind ``sage-mouth-prior`` (atomic)."""
    return save_file(path, prior.to_tree(), MOUTH_PRIOR_KIND, MOUTH_PRIOR_FORMAT)


def load_mouth_prior(path: str | Path | None = None) -> MouthPrior:
    """Read a mouth prior (default: the one shipped with the package). InputError for a missing,
    damaged or foreign file, or one whose parts differ from :data:`PARTS`."""
    p = Path(path) if path is not None else PRIOR_FILE
    tree, _ = load_file(p, MOUTH_PRIOR_KIND, MOUTH_PRIOR_FORMAT, "mouth prior")
    if not isinstance(tree, dict) or tuple(tree.get("parts", ())) != PARTS:
        raise InputError(p, f"mouth prior parts must be {list(PARTS)}")
    try:
        return MouthPrior(np.asarray(tree["color"], np.float32), np.asarray(tree["weight"], np.float32),
                          np.asarray(tree["lo"], np.float32), np.asarray(tree["hi"], np.float32), dict(tree.get("provenance") or {}))  # fmt: skip
    except (KeyError, ValueError) as e:
        raise InputError(p, f"malformed mouth prior: {e}") from None


def mouth_coordinates(points: np.ndarray, origin: np.ndarray, width: float) -> np.ndarray:
    """(N, 3) mouth coordinates of canonical points (N, 3) in the frame (origin (3,), lip width)."""
    d = (np.asarray(points, np.float64) - np.asarray(origin, np.float64)[None]) / float(width)
    return np.stack([d[:, 0], d[:, 1], -d[:, 2]], -1)


def face_parts(model: FlameModelData, regions: Regions) -> np.ndarray:
    """(F,) int64 part of every face (index into :data:`PARTS`), −1 outside the mouth interior.

    Mouth-interior faces are those of the ``mouth_interior`` and ``teeth`` regions; teeth faces are
    the ``teeth`` region's; a face is lower when the mean jaw skinning weight of its vertices is at
    least 0.5."""
    faces = np.asarray(model.faces)
    part = np.full(faces.shape[0], -1, np.int64)
    jaw = np.asarray(model.lbs_weights)[:, 2][faces].mean(1) >= 0.5
    for name, base in (("mouth_interior", 0), ("teeth", 2)):
        if regions.has(name):
            m = np.asarray(regions.face_mask(name), bool)
            part[m] = base + jaw[m]
    return part


def surfel_prior_colors(canonical_vertices: np.ndarray, canonical_means: np.ndarray, binding: np.ndarray, model: FlameModelData,
                        regions: Regions, prior: MouthPrior) -> tuple[np.ndarray, np.ndarray]:
    """The prior's albedo of every surfel: ((N, 3) colours, (N,) bool surfels of the mouth interior).

    canonical_vertices: (V, 3) the avatar's canonical mesh (identity applied); canonical_means:
    (N, 3) surfel centres in canonical space; binding: (N,) face ids. Surfels outside the mouth
    interior get zeros. Raises ValueError when the mouth frame cannot be found (no lips)."""
    from ..flame.mouth import lip_ids, mouth_frame

    origin, width = mouth_frame(np.asarray(canonical_vertices, np.float64), lip_ids(regions, model.n_base_vertices), np.asarray(model.lbs_weights))
    part = face_parts(model, regions)[np.asarray(binding, np.int64)]
    on = part >= 0
    out = np.zeros((part.shape[0], 3))
    if on.any():
        out[on] = prior.lookup(mouth_coordinates(np.asarray(canonical_means)[on], origin, width), part[on])
    return out, on


def avatar_prior_colors(avatar: Any, regions: Regions, prior: MouthPrior | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`surfel_prior_colors` of an :class:`~sage_core.avatar.model.Avatar` (its canonical mesh and
    surfel centres), as tensors on its device: ((N, 3) float32, (N,) bool)."""
    import torch

    prior = load_mouth_prior() if prior is None else prior
    with torch.no_grad():
        canon = avatar.canonical_state(with_sdf=False)
        cols, on = surfel_prior_colors(avatar.canonical_vertices.detach().double().cpu().numpy(), canon.means.detach().double().cpu().numpy(),
                                       avatar.surfels.binding.cpu().numpy(), avatar.model_data, regions, prior)  # fmt: skip
    return torch.as_tensor(cols, dtype=torch.float32, device=avatar.device), torch.as_tensor(on, device=avatar.device)
