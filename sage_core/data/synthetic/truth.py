"""Ground-truth deformation beyond the written FLAME-format model (``tracking="fitted"``).

The written model keeps only the leading expression components of the procedural head. The
ground truth poses the full head and adds, in canonical space before skinning,

- non-linear correctives driven by the expression and the jaw: lip roll (lip press, pucker), lip
  thinning and corner pull-in as the jaw opens, cheek bulge (smile, mouth stretch, smile × cheek
  puff), brow bunching (furrow, furrow × brow raise);
- geometric expression creases: an inward displacement along the normal in crease bands
  (forehead lines, glabella, nasolabial folds, and weakly everywhere), growing with the local
  compression of the surface relative to the neutral face.

All of them vanish at the neutral expression with a closed jaw, so the canonical mesh is shared.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ._fields import gauss, smoothstep
from .appearance import crease_weights
from .head import EXPRESSION_NAMES, N_SHAPE_COLUMNS, PART_SKIN, HeadModel, _regions, hair_weight
from .mesh_render import vertex_normals

_E = {name: i for i, name in enumerate(EXPRESSION_NAMES)}


def kept_expressions(expr_keep: float) -> int:
    """Number of leading expression components the written model keeps (at least 1)."""
    return max(1, min(len(EXPRESSION_NAMES), int(round(expr_keep * len(EXPRESSION_NAMES)))))


def truncated_head(head: HeadModel, n_keep: int) -> HeadModel:
    """The written model: ``head`` with the expression columns from ``n_keep`` on zeroed."""
    sd = head.shapedirs.copy()
    sd[:, :, N_SHAPE_COLUMNS + n_keep :] = 0.0
    return replace(head, shapedirs=sd)


@dataclass
class TruthFields:
    """Per-vertex fields of the truth's extra deformation (template space, float64).

    Attributes:
        normal: (V, 3) template vertex normals.
        skin: (V,) 1 on skin that may deform beyond the model, 0 elsewhere (eyes, mouth pocket, hair).
        regions: name -> (V,) soft region weights (lips, corner, cheek, cheek_low, brow, brow_inner).
        side: (V,) +1 upper lip side, -1 jaw side, 0 on the mouth corners.
        x_sign: (V,) sign of the template x (subject's left +1, right -1).
        band: (V,) crease band weight in [0, 1].
        corrective_scale: scale of the correctives; crease_depth: metres at full compression.
    """

    normal: np.ndarray
    skin: np.ndarray
    regions: dict[str, np.ndarray]
    side: np.ndarray
    x_sign: np.ndarray
    band: np.ndarray
    corrective_scale: float
    crease_depth: float


def truth_fields(head: HeadModel, corrective_scale: float, crease_depth_mm: float) -> TruthFields:
    """The fields of :class:`TruthFields` for ``head``."""
    v = head.v_template
    n = vertex_normals(v, head.faces)
    r = _regions(v, head.mouth_y)
    skin = ((head.part == PART_SKIN) * (1.0 - hair_weight(v))).astype(np.float64)
    return TruthFields(
        normal=n,
        skin=skin,
        regions={k: r[k] for k in ("lips", "corner", "cheek", "cheek_low", "brow", "brow_inner")},
        side=head.side.astype(np.float64),
        x_sign=np.sign(v[:, 0]),
        band=crease_band(v, head.mouth_y) * skin,
        corrective_scale=float(corrective_scale),
        crease_depth=1e-3 * float(crease_depth_mm),
    )


def crease_band(p: np.ndarray, mouth_y: float) -> np.ndarray:
    """Crease band weight (N,) in [0, 1] at template points p (N, 3): horizontal forehead lines,
    vertical glabella lines, nasolabial folds, and 0.25 everywhere else on the face."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    front = smoothstep(z, 0.0, 0.04)
    lines = np.square(0.5 + 0.5 * np.cos(2.0 * np.pi * (y - 0.052) / 0.008))
    forehead = smoothstep(y, 0.05, 0.058) * smoothstep(y, 0.098, 0.088) * gauss(x, 0.045) * lines
    glabella = gauss(ax - 0.006, 0.0025) * gauss(y - 0.04, 0.009)
    a = np.array([0.017, 0.002])
    b = np.array([0.031, mouth_y - 0.012])
    q = np.stack([ax, y], -1)
    t = np.clip(((q - a) @ (b - a)) / float((b - a) @ (b - a)), 0.0, 1.0)
    dist = np.linalg.norm(q - (a + t[:, None] * (b - a)), axis=1)
    nasolabial = gauss(dist, 0.003)
    return (0.25 + 0.75 * np.clip(forehead + glabella + nasolabial, 0.0, 1.0)) * front


def correctives(f: TruthFields, expr: np.ndarray, jaw: np.ndarray) -> np.ndarray:
    """Non-linear corrective offsets (T, V, 3) in metres.

    expr: (T, 100) expression coefficients; jaw: (T,) jaw opening angle in radians.
    """
    pos = lambda a: np.maximum(a, 0.0)  # noqa: E731
    e = lambda name: expr[:, _E[name]][:, None, None]  # noqa: E731
    r = {k: w[None, :, None] for k, w in f.regions.items()}
    n = f.normal[None]
    ex, ey, ez = (np.eye(3)[i][None, None] for i in range(3))
    side = f.side[None, :, None]
    jaw_ = pos(jaw)[:, None, None]
    xsign = f.x_sign[None, :, None]

    roll = 0.004 * np.tanh(1.3 * pos(e("lip_press")) + 0.5 * np.square(pos(e("pucker"))))
    out = roll * r["lips"] * (-0.7 * ez - 0.5 * side * ey)
    open_ = 1.0 - np.exp(-np.square(jaw_ / 0.12))
    out = out - 0.0025 * open_ * r["lips"] * n - 0.003 * open_ * r["corner"] * xsign * ex
    s = pos(e("smile")) + 0.5 * pos(e("mouth_stretch"))
    bulge = 0.002 * np.square(s) / (1.0 + 0.25 * np.square(s))
    out = out + bulge * r["cheek"] * (n + 0.6 * ey) + 0.002 * pos(e("smile")) * pos(e("cheek_puff")) * r["cheek_low"] * n
    furrow = np.tanh(pos(e("brow_furrow")))
    out = out + 0.0025 * np.square(furrow) * r["brow_inner"] * n - 0.0015 * furrow * r["brow"] * ey
    out = out + 0.0025 * pos(e("brow_furrow")) * pos(e("brow_raise")) * r["brow_inner"] * ey
    return f.corrective_scale * out * f.skin[None, :, None]


def crease_offsets(f: TruthFields, deformed: np.ndarray, neutral: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Inward crease displacement (T, V, 3) in metres: depth · compression · band along −normal.

    deformed: (T, V, 3) canonical meshes with the expression; neutral: (V, 3) without it.
    """
    comp = np.stack([crease_weights(d, neutral, faces) for d in deformed])  # (T, V)
    return -(f.crease_depth * comp * f.band[None])[..., None] * f.normal[None]
