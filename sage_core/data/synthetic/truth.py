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
from .head import EXPRESSION_NAMES, N_SHAPE_COLUMNS, PART_SKIN, HeadModel, hair_weight
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

    The corrective patterns are chosen outside the span of the written expression components
    (a per-frame fit would absorb any pattern the kept components can reproduce, however
    non-linear its coefficient).

    Attributes:
        normal: (V, 3) template vertex normals.
        skin: (V,) 1 on skin that may deform beyond the model, 0 elsewhere (eyes, mouth pocket, hair).
        roll: (V, 3) lip roll per unit: the red of the lips turns inward about the lip root (near the
            slit inward and towards it, at the lip border slightly outward).
        thin: (V, 3) lip thinning per unit: the lips' sides flatten, the corners pull in.
        apple: (V,) the apple of the cheek (bulges along the normal and lifts).
        procerus: (V,) the skin between the brows (bunches outward along the normal).
        inner_lift: (V,) the inner brow heads (lift when furrow and brow raise combine).
        band: (V,) crease band weight in [0, 1].
        corrective_scale: scale of the correctives; crease_depth: metres at full compression.
    """

    normal: np.ndarray
    skin: np.ndarray
    roll: np.ndarray
    thin: np.ndarray
    apple: np.ndarray
    procerus: np.ndarray
    inner_lift: np.ndarray
    band: np.ndarray
    corrective_scale: float
    crease_depth: float


def truth_fields(head: HeadModel, corrective_scale: float, crease_depth_mm: float) -> TruthFields:
    """The fields of :class:`TruthFields` for ``head``."""
    v = head.v_template
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    ax = np.abs(x)
    n = vertex_normals(v, head.faces)
    skin = ((head.part == PART_SKIN) * (1.0 - hair_weight(v))).astype(np.float64)
    front = smoothstep(z, 0.0, 0.045)
    lipx = np.exp(-((x / 0.026) ** 4)) * front
    a = (y - head.mouth_y) / 0.008  # signed distance from the slit in lip heights
    towards = -np.sign(a) * np.abs(a) * np.exp(-a * a)  # towards the slit, largest mid-lip
    inward = (1.5 * a * a - 1.0) * np.exp(-a * a)  # -1 at the slit, slightly outward at the border
    roll = lipx[:, None] * (np.stack([np.zeros_like(x), towards, inward], -1) * np.array([0.0, 0.5, 1.0]))
    corner = gauss(ax - 0.025, 0.007) * gauss(y - head.mouth_y, 0.007) * front
    thin = -(lipx * np.square(x / 0.024) * np.exp(-a * a))[:, None] * n
    thin[:, 0] -= corner * np.sign(x)
    return TruthFields(
        normal=n,
        skin=skin,
        roll=roll,
        thin=thin,
        apple=gauss(ax - 0.034, 0.012) * gauss(y - (head.mouth_y + 0.03), 0.012) * front,
        procerus=gauss(x, 0.009) * gauss(y - 0.036, 0.009) * front,
        inner_lift=gauss(ax - 0.012, 0.006) * gauss(y - 0.047, 0.006) * front,
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
    n = f.normal[None]
    ey = np.array([0.0, 1.0, 0.0])[None, None]
    roll = 0.004 * np.tanh(1.3 * pos(e("lip_press")) + 0.5 * np.square(pos(e("pucker"))))
    out = roll * f.roll[None]
    open_ = 1.0 - np.exp(-np.square(pos(jaw)[:, None, None] / 0.12))
    out = out + 0.004 * open_ * f.thin[None]
    s = pos(e("smile")) + 0.5 * pos(e("mouth_stretch"))
    bulge = 0.002 * np.square(s) / (1.0 + 0.25 * np.square(s)) + 0.0015 * pos(e("smile")) * pos(e("cheek_puff"))
    out = out + bulge * f.apple[None, :, None] * (n + 0.4 * ey)
    furrow = np.tanh(pos(e("brow_furrow")))
    out = out + 0.003 * np.square(furrow) * f.procerus[None, :, None] * n
    out = out + 0.003 * pos(e("brow_furrow")) * pos(e("brow_raise")) * f.inner_lift[None, :, None] * ey
    return f.corrective_scale * out * f.skin[None, :, None]


def crease_offsets(f: TruthFields, deformed: np.ndarray, neutral: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Inward crease displacement (T, V, 3) in metres: depth · compression · band along −normal.

    deformed: (T, V, 3) canonical meshes with the expression; neutral: (V, 3) without it.
    """
    comp = np.stack([crease_weights(d, neutral, faces) for d in deformed])  # (T, V)
    return -(f.crease_depth * comp * f.band[None])[..., None] * f.normal[None]
