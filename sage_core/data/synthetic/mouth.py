"""Mouth interior of a detailed synthetic subject: teeth, gums and tongue inside the mouth pocket.

The procedural head's mouth is a closed pocket behind the lip slit (:mod:`.head`). A detailed
subject (``appearance="detailed"``) also has, inside that pocket, geometry that the FLAME-format
model does not carry, like its hair volume (:mod:`.hair`):

* upper teeth and gums, rigid with the skull (the least-squares rigid motion of the scalp vertices,
  as the hair);
* lower teeth, gums and the tongue, rigid with the jaw (the least-squares rigid motion of the chin:
  skin vertices skinned to the jaw joint alone, away from the lips);
* the pocket's own lining coloured per subject (its colour and how much darker it gets towards the
  throat).

Geometry, in the canonical head (identity shape and static offset applied; FLAME axes: x lateral,
y up, z forward), placed from the lip slit: its centre height ``y_s``, its front ``z_f`` and half
width ``w`` (so the mouth follows the subject's lips). Each jaw has ``tooth_count`` teeth on a
parabolic arc (front ``tooth_setback`` behind the lips, sides bending back), each tooth a small box
from its biting edge (the upper edge slightly below the slit, the lower teeth behind the upper ones)
to a root hidden in the pocket wall; a gum band runs along each arc's roots; the tongue is the
upper half of an ellipsoid on the pocket floor behind the lower teeth. What varies with the seed
(:class:`MouthStyle`): tooth size, count, shade and gaps, the gum and tongue colours, the tongue's
height and how far forward it lies, the cavity's colour and darkness.

It is part of the ground truth only: rendered into the images and masks (in the pocket, so it shows
only where the lips part), never written into ``model/``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .hair import rigid_fit, skull_vertices
from .head import PART_MOUTH, PART_SKIN, HeadModel

UPPER, LOWER = 0, 1
"""Rigid group of a mouth vertex: with the skull or with the jaw."""
KIND_TOOTH, KIND_GUM, KIND_TONGUE = 0, 1, 2


@dataclass(frozen=True)
class MouthStyle:
    """What a subject's mouth interior looks like (linear RGB in [0, 1], lengths in metres).

    Attributes:
        tooth_count: teeth per jaw along the visible arc.
        tooth_height: visible height of an upper tooth (lower teeth: 0.85 of it).
        tooth_width: fraction of the arc the teeth span (scales their width).
        gap: fraction of each tooth's slot left open between neighbours.
        tooth_shade: base tooth colour; tooth_var: per-tooth brightness spread (relative).
        gum: gum colour; tongue: tongue colour.
        tongue_height: height of the tongue's top relative to the slit (negative: below it).
        tongue_forward: how far forward (towards the lower teeth) the tongue lies.
        cavity: colour of the pocket lining at the lips; cavity_darkness: fraction of it lost at
            the back of the pocket (the throat).
        tooth_factors: (2·tooth_count,) per-tooth brightness factors (upper jaw first).
    """

    tooth_count: int
    tooth_height: float
    tooth_width: float
    gap: float
    tooth_shade: tuple[float, float, float]
    tooth_var: float
    gum: tuple[float, float, float]
    tongue: tuple[float, float, float]
    tongue_height: float
    tongue_forward: float
    cavity: tuple[float, float, float]
    cavity_darkness: float
    tooth_factors: tuple[float, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict:
        r = lambda v: round(float(v), 5)  # noqa: E731
        return {"tooth_count": int(self.tooth_count), "tooth_height_mm": r(1000 * self.tooth_height),
                "tooth_width": r(self.tooth_width), "gap": r(self.gap), "tooth_shade": [r(c) for c in self.tooth_shade],
                "gum": [r(c) for c in self.gum], "tongue": [r(c) for c in self.tongue],
                "tongue_height_mm": r(1000 * self.tongue_height), "tongue_forward_mm": r(1000 * self.tongue_forward),
                "cavity": [r(c) for c in self.cavity], "cavity_darkness": r(self.cavity_darkness)}  # fmt: skip

    def cavity_albedo(self, depth: np.ndarray) -> np.ndarray:
        """(M, 3) albedo of the pocket lining at mouth depth ``depth`` (M,) (0 lips .. 1 throat)."""
        d = np.clip(depth, 0.0, 1.0)
        return np.asarray(self.cavity)[None] * (1.0 - self.cavity_darkness * d)[:, None]


def sample_mouth_style(rng: np.random.Generator) -> MouthStyle:
    """Draw a mouth interior from ``rng``."""
    n = int(rng.integers(8, 13))
    shade = np.array([0.90, 0.86, 0.76]) * rng.uniform(0.78, 1.0) * np.array([1.0, rng.uniform(0.95, 1.0), rng.uniform(0.82, 1.0)])
    var = float(rng.uniform(0.02, 0.10))
    gum = np.array([0.78, 0.36, 0.38]) * rng.uniform(0.8, 1.1, 3)
    tongue = np.array([0.76, 0.36, 0.38]) * rng.uniform(0.8, 1.15, 3)
    cavity = np.array([0.45, 0.13, 0.13]) * rng.uniform(0.75, 1.2, 3)
    t = lambda a: tuple(float(x) for x in np.clip(a, 0.0, 1.0))  # noqa: E731
    return MouthStyle(
        tooth_count=n, tooth_height=float(rng.uniform(0.0035, 0.005)), tooth_width=float(rng.uniform(0.85, 1.0)),
        gap=float(rng.uniform(0.0, 0.22)), tooth_shade=t(shade), tooth_var=var, gum=t(gum), tongue=t(tongue),
        tongue_height=float(rng.uniform(-0.0005, 0.0025)), tongue_forward=float(rng.uniform(0.0, 0.003)),
        cavity=t(cavity), cavity_darkness=float(rng.uniform(0.6, 0.88)),
        tooth_factors=tuple(float(x) for x in 1.0 + var * rng.uniform(-1.0, 1.0, 2 * n)),
    )  # fmt: skip


@dataclass
class MouthVolume:
    """Mouth-interior geometry on one canonical head.

    Attributes:
        vertices: (M, 3) canonical positions; faces: (K, 3) int64.
        albedo: (M, 3) per-vertex albedo; group: (M,) int8 :data:`UPPER` / :data:`LOWER`;
        kind: (M,) int8 tooth, gum or tongue.
        skull: head vertex ids of the skull fit; jaw: head vertex ids of the jaw fit.
        style: the :class:`MouthStyle` it was built from.
    """

    vertices: np.ndarray
    faces: np.ndarray
    albedo: np.ndarray
    group: np.ndarray
    kind: np.ndarray
    skull: np.ndarray
    jaw: np.ndarray
    style: MouthStyle

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])


@dataclass
class PosedMouth:
    """The mouth interior in one frame: vertices (M, 3) and the volume (faces, albedo, style)."""

    vertices: np.ndarray
    volume: MouthVolume


def jaw_vertices(head: HeadModel) -> np.ndarray:
    """Head vertex ids that move rigidly with the jaw: chin skin skinned to the jaw joint alone, at
    least 2.2 cm below the slit (away from the lips' expressions) and on the front of the face."""
    v = head.v_template
    expr = np.abs(head.shapedirs[:, :, 300:]).reshape(v.shape[0], -1).max(1)
    ok = (head.part == PART_SKIN) & (head.weights[:, 2] > 1.0 - 1e-9) & (v[:, 1] < head.mouth_y - 0.022) & (v[:, 2] > 0.03)
    ids = np.flatnonzero(ok)
    # the chin's least expression-driven half (correctives and expressions move the lips' surroundings)
    keep = ids[expr[ids] <= np.quantile(expr[ids], 0.5)] if ids.size > 8 else ids
    return keep.astype(np.int64)


def _slit_frame(head: HeadModel, canonical: np.ndarray) -> tuple[float, float, float, float, float]:
    """(x_c, y_s, z_f, w, z_back): slit centre, height, front, half width and the pocket's back (centre)."""
    slit = canonical[head.slit_pairs.reshape(-1)]
    x_c = float(slit[:, 0].mean())
    w = float(np.abs(slit[:, 0] - x_c).max())
    centre = np.abs(slit[:, 0] - x_c) < 0.3 * w
    y_s = float(slit[centre, 1].mean())
    z_f = float(slit[centre, 2].max())
    pocket = (head.part == PART_MOUTH) & (head.mouth_depth > 0.99)
    back = canonical[pocket]
    z_b = float(back[np.abs(back[:, 0] - x_c) < 0.3 * w, 2].mean())
    return x_c, y_s, z_f, w, z_b


def _box(c0: np.ndarray, c1: np.ndarray, c2: np.ndarray, c3: np.ndarray, thick: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A box from the front quad (c0 c1 c2 c3, counter-clockwise) pushed back by ``thick`` (3,):
    vertices (8, 3), faces (12, 3) local ids."""
    front = np.stack([c0, c1, c2, c3])
    pts = np.concatenate([front, front + thick[None]], 0)
    q = [(0, 1, 2, 3), (5, 4, 7, 6), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)]
    faces = []
    for a, b, c, d in q:
        faces += [[a, b, c], [a, c, d]]
    return pts, np.array(faces, dtype=np.int64)


def _band(xs: np.ndarray, zs: np.ndarray, y0: float, y1: float, rows: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A vertical band through the points (xs, zs) from height y0 to y1: vertices, faces."""
    n = xs.shape[0]
    ys = np.linspace(y0, y1, rows + 1)
    pts = np.stack([np.broadcast_to(xs, (rows + 1, n)), np.broadcast_to(ys[:, None], (rows + 1, n)),
                    np.broadcast_to(zs, (rows + 1, n))], -1).reshape(-1, 3)  # fmt: skip
    idx = np.arange((rows + 1) * n).reshape(rows + 1, n)
    faces = []
    for r in range(rows):
        for i in range(n - 1):
            a, b, c, d = idx[r, i], idx[r, i + 1], idx[r + 1, i + 1], idx[r + 1, i]
            faces += [[a, b, c], [a, c, d]]
    return pts, np.array(faces, dtype=np.int64)


def build_mouth(head: HeadModel, canonical: np.ndarray, style: MouthStyle) -> MouthVolume:
    """The mouth interior of ``style`` inside the pocket of the canonical head ``canonical`` (V, 3)."""
    x_c, y_s, z_f, w, z_b = _slit_frame(head, canonical)
    depth = max(z_f - z_b, 1e-3)
    k = w / 0.0198  # the template's slit half width
    half = 0.86 * w * style.tooth_width
    bend = 0.42 * depth

    def arc_z(x: np.ndarray, front: float) -> np.ndarray:
        return front - bend * ((x - x_c) / (0.86 * w)) ** 2

    verts: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    albedo: list[np.ndarray] = []
    group: list[np.ndarray] = []
    kind: list[np.ndarray] = []

    def add(p: np.ndarray, f: np.ndarray, rgb: np.ndarray, g: int, kd: int) -> None:
        start = sum(len(x) for x in verts)
        verts.append(p)
        faces.append(f + start)
        albedo.append(np.broadcast_to(rgb, p.shape).copy() if rgb.ndim == 1 else rgb)
        group.append(np.full(len(p), g, np.int8))
        kind.append(np.full(len(p), kd, np.int8))

    n = style.tooth_count
    edges = x_c + np.linspace(-half, half, n + 1)
    shade = np.asarray(style.tooth_shade)
    thick_len = 0.0022 * k
    front_u = z_f - 0.35 * depth
    for jaw, (g, sign, h, front, y_edge) in enumerate(((UPPER, 1.0, style.tooth_height, front_u, y_s - 0.0004 * k),
                                                        (LOWER, -1.0, 0.85 * style.tooth_height, front_u - 0.0012 * k, y_s + 0.0002 * k))):
        root = y_edge + sign * (h + 0.004 * k)  # the root goes on into the pocket wall
        for i in range(n):
            a, b = edges[i], edges[i + 1]
            m = 0.5 * style.gap * (b - a)
            xa, xb = a + m, b - m
            za, zb = float(arc_z(np.array([xa]), front)[0]), float(arc_z(np.array([xb]), front)[0])
            c0 = np.array([xa, y_edge, za])
            c1 = np.array([xb, y_edge, zb])
            c2 = np.array([xb, root, zb])
            c3 = np.array([xa, root, za])
            # push back towards the arc's centre of curvature (mostly -z)
            xm = 0.5 * (xa + xb) - x_c
            tdir = np.array([-2.0 * bend * xm / (0.86 * w) ** 2, 0.0, -1.0])
            tdir /= np.linalg.norm(tdir)
            p, f = _box(c0, c1, c2, c3, thick_len * tdir)
            fac = style.tooth_factors[jaw * n + i] if len(style.tooth_factors) == 2 * n else 1.0
            rgb = np.empty((8, 3))
            rgb[:] = shade * fac
            rgb[[0, 1, 4, 5]] *= 1.04  # the biting edge is lighter
            rgb[[2, 3, 6, 7]] *= 0.9
            rgb[4:] *= 0.8  # the back faces see less light
            add(p, f, np.clip(rgb, 0.0, 1.0), g, KIND_TOOTH)
        # gums: a band just in front of the roots, from the visible crown's top into the wall
        xs = x_c + np.linspace(-1.04 * half, 1.04 * half, 2 * n + 1)
        zs = arc_z(xs, front) + 0.0006 * k
        y0 = y_edge + sign * h
        p, f = _band(xs, zs, y0, y0 + sign * 0.004 * k)
        add(p, f, np.asarray(style.gum), g, KIND_GUM)

    # tongue: the upper half of an ellipsoid on the pocket floor behind the lower teeth
    rows, cols = 5, 13
    rx, rz, ry = 0.72 * w, 0.34 * depth, 0.004 * k
    zc = front_u - 0.0012 * k - thick_len - 0.0008 * k - rz + style.tongue_forward * k
    yc = y_s + style.tongue_height * k - ry
    th = np.linspace(0.0, np.pi / 2, rows)[:, None]  # from the rim (0) to the top (π/2)
    ph = np.linspace(0.0, 2 * np.pi, cols, endpoint=False)[None, :]
    pts = np.stack([x_c + rx * np.cos(th) * np.cos(ph), np.broadcast_to(yc + ry * np.sin(th), (rows, cols)),
                    zc + rz * np.cos(th) * np.sin(ph)], -1).reshape(-1, 3)  # fmt: skip
    pts[(rows - 1) * cols:] = [x_c, yc + ry, zc]  # collapse the top ring onto the pole
    idx = np.arange(rows * cols).reshape(rows, cols)
    tf = []
    for r in range(rows - 1):
        for i in range(cols):
            a, b = idx[r, i], idx[r, (i + 1) % cols]
            c, d = idx[r + 1, (i + 1) % cols], idx[r + 1, i]
            tf += [[a, b, c], [a, c, d]]
    back = np.clip((zc + rz - pts[:, 2]) / (2 * rz), 0.0, 1.0)  # 0 at the tip .. 1 at the back
    groove = np.exp(-(((pts[:, 0] - x_c) / (0.18 * rx)) ** 2))
    rgb = np.asarray(style.tongue)[None] * ((1.0 - 0.35 * back) * (1.0 - 0.12 * groove))[:, None]
    add(pts, np.array(tf, dtype=np.int64), rgb, LOWER, KIND_TONGUE)

    return MouthVolume(
        vertices=np.concatenate(verts, 0), faces=np.concatenate(faces, 0).astype(np.int64),
        albedo=np.concatenate(albedo, 0), group=np.concatenate(group), kind=np.concatenate(kind),
        skull=skull_vertices(head), jaw=jaw_vertices(head), style=style,
    )  # fmt: skip


def pose_mouth(volume: MouthVolume, canonical_head: np.ndarray, posed_head: np.ndarray) -> PosedMouth:
    """The mouth interior of a frame: the upper group moved by the skull's rigid motion from
    ``canonical_head`` (V, 3) to ``posed_head`` (V, 3), the lower group by the jaw's."""
    out = np.empty_like(volume.vertices)
    for g, ids in ((UPPER, volume.skull), (LOWER, volume.jaw)):
        R, t = rigid_fit(canonical_head[ids], posed_head[ids])
        sel = volume.group == g
        out[sel] = volume.vertices[sel] @ R.T + t
    return PosedMouth(out, volume)
