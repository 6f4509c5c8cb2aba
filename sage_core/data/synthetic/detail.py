"""Pixel-scale detail of the synthetic head (``appearance="detailed"``): skin, brows, lashes, hair.

Everything here is a solid texture of the *template* position (metres, FLAME's axes: face +z, up
+y, subject's left +x), so it is glued to the skin and deforms with identity and expression like
the procedural albedo of :mod:`.appearance`. Features and their physical scale:

- skin: mottling (3–15 mm), pores (0.3–0.6 mm, denser and deeper on the nose and cheeks),
  freckles (0.5–2 mm spots on a jittered grid), moles (1–3 mm), fine lines (forehead lines,
  crow's feet, lower and upper lid lines, nasolabial folds, neck rings: 0.3–0.6 mm wide), lip
  lines, optional stubble (follicle dots with a beard-shaped density);
- brows: hair strands oriented like real brows (the inner head points up, the body and tail run
  outward), with ragged edges; lashes: a dark lash line along the lid margin with radial strands;
- scalp hair: strands flowing from a crown whorl (optionally a spiral, a wave and a side parting
  that shows a line of scalp), clumps of 2–6 mm, strands of ≈ 1 mm, fine strands of ≈ 0.3 mm,
  lighter streaks and grey strands, a ragged hairline.

**Prefiltering.** Every feature is band-limited analytically to the footprint of the sample it is
evaluated for (``fp``: standard deviation of a Gaussian pixel filter on the surface, metres): a
pattern of spatial frequency f is scaled by ``exp(-2π² f² fp²)`` towards its mean, and Gaussian
spots and lines widen to ``sqrt(w² + fp²)`` with their integral kept. Detail far below the pixel
(pores at 0.5 px/mm) therefore turns into its mean colour instead of aliased noise, and detail
at the pixel scale keeps its contrast.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import cache

import numpy as np

from ._fields import _hash01, gauss, smoothstep

HAIR_STYLES = ("short", "fringe", "bob", "bun")
"""Scalp hair styles: short (hair on the scalp only), fringe (a fringe over the forehead), bob
(hair hanging to the jaw at the sides and back) and bun (a bun at the back of the crown)."""

_STYLE_WEIGHTS = (0.2, 0.3, 0.25, 0.25)
"""Chances of the :data:`HAIR_STYLES` (most subjects have hair off the scalp beyond its shell)."""
_SKULL_CENTRE = np.array([0.0, 0.01, -0.005])
_TWO_PI2 = 2.0 * math.pi * math.pi


@dataclass(frozen=True)
class DetailStyle:
    """The per-subject parameters of the detail (drawn from the seed by :func:`sample_detail`).

    Attributes:
        seed: noise seed of every pattern.
        freckles: freckle density in [0, 1] (0 = none).
        moles: (n, 6) rows (x, y, z, radius m, darkness, warmth) of moles at template positions.
        age: strength in [0, 1] of the fine lines.
        pores: contrast scale of the pores.
        stubble: stubble density in [0, 1] (0 = clean-shaven).
        hair_style: one of :data:`HAIR_STYLES`.
        hair_volume_mm: thickness of the hair above the scalp at the crown (hair volume geometry).
        whorl: (polar, azimuth) in radians of the crown whorl, seen from the skull centre (polar 0 =
            straight up, azimuth 0 = towards the back).
        swirl: spiral of the strands around the whorl (radians of turn per radian of polar angle).
        parting: azimuth of a side parting in the whorl frame (radians, 0 = towards the face), or
            None for no parting.
        wave: amplitude of the strands' wave (radians of azimuth).
        streaks: strength of lighter streaks in the hair.
        grey: fraction-like strength of grey strands.
        brow_density, brow_thickness: brow strand density and width scale.
        lashes: lash strength.
        fringe_gap_mm: the fringe ends this far above the brows.
        bob_end_y: height (template y, metres) where a bob ends at the sides.
    """

    seed: int
    freckles: float
    moles: tuple[tuple[float, ...], ...]
    age: float
    pores: float
    stubble: float
    hair_style: str
    hair_volume_mm: float
    whorl: tuple[float, float]
    swirl: float
    parting: float | None
    wave: float
    streaks: float
    grey: float
    brow_density: float
    brow_thickness: float
    lashes: float
    fringe_gap_mm: float
    bob_end_y: float

    def to_dict(self) -> dict:
        """Plain data (rounded), as recorded in ``gt/info.json``."""
        d = asdict(self)
        r = lambda v: round(float(v), 6)  # noqa: E731
        for k, v in d.items():
            if isinstance(v, float):
                d[k] = r(v)
        d["moles"] = [[r(x) for x in m] for m in self.moles]
        d["whorl"] = [r(x) for x in self.whorl]
        return d

    @property
    def mole_array(self) -> np.ndarray:
        """(n, 6) the moles as an array."""
        return np.asarray(self.moles, dtype=np.float64).reshape(-1, 6)

    def whorl_frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(origin, pole w, e1, e2) of the scalp hair's strand coordinates (template space): strands
        run along the meridians of a sphere whose pole ``w`` is the whorl; ``e1`` points towards
        the face."""
        th, az = self.whorl
        w = np.array([math.sin(th) * math.sin(az), math.cos(th), -math.sin(th) * math.cos(az)])
        return _frame(_SKULL_CENTRE, w, np.array([0.0, 0.0, 1.0]))


def _frame(origin: np.ndarray, pole: np.ndarray, front: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    w = pole / np.linalg.norm(pole)
    e1 = front - (front @ w) * w
    e1 /= np.linalg.norm(e1)
    return origin, w, e1, np.cross(w, e1)


def sample_detail(rng: np.random.Generator, skin_points: np.ndarray) -> DetailStyle:
    """Draw a subject's detail from ``rng``. skin_points: (N, 3) template points of the face and
    neck front where moles may sit."""
    freckles = 0.0 if rng.random() < 0.4 else float(rng.uniform(0.3, 1.0))
    n_moles = int(rng.integers(2, 9))
    pick = skin_points[rng.choice(len(skin_points), size=n_moles, replace=False)]
    moles = tuple(
        (*(float(c) for c in pick[i]), float(rng.uniform(0.0007, 0.0016)), float(rng.uniform(0.3, 0.6)), float(rng.uniform(0.0, 1.0)))
        for i in range(n_moles)
    )
    stubble = float(rng.uniform(0.5, 1.0)) if rng.random() < 0.4 else 0.0
    style = HAIR_STYLES[int(np.searchsorted(np.cumsum(_STYLE_WEIGHTS), rng.random() * sum(_STYLE_WEIGHTS), side="right"))]
    parting = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.6)) if rng.random() < 0.6 else None
    return DetailStyle(
        seed=int(rng.integers(0, 2**31 - 1)),
        freckles=freckles,
        moles=moles,
        age=float(rng.uniform(0.2, 1.0)),
        pores=float(rng.uniform(0.8, 1.25)),
        stubble=stubble,
        hair_style=style,
        hair_volume_mm=float(rng.uniform(5.0, 12.0)),
        whorl=(float(rng.uniform(0.35, 0.7)), float(rng.uniform(-0.35, 0.35))),
        swirl=float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.8)),
        parting=parting,
        wave=float(rng.uniform(0.0, 0.12)),
        streaks=float(rng.uniform(0.0, 0.35)),
        grey=float(rng.uniform(0.1, 0.4)) if rng.random() < 0.25 else 0.0,
        brow_density=float(rng.uniform(0.75, 1.15)),
        brow_thickness=float(rng.uniform(0.85, 1.3)),
        lashes=float(rng.uniform(0.8, 1.2)),
        fringe_gap_mm=float(rng.uniform(3.0, 12.0)),
        bob_end_y=float(rng.uniform(-0.085, -0.045)),
    )


# ----------------------------------------------------------------------------- band limiting


def attenuation(freq: float | np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Gain (M,) of a Gaussian filter of standard deviation ``fp`` (M,) metres at ``freq`` cycles/m."""
    return np.exp(-_TWO_PI2 * np.square(freq * fp))


_MIN_GAIN = 0.02
"""Below this gain a band is not evaluated (it contributes its mean; the step is under 2 % of the
band's contrast)."""

_LATTICE_BITS = 6
_LATTICE = 1 << _LATTICE_BITS


@cache
def _lattice_table() -> np.ndarray:
    """Random values in [0, 1) on a periodic 64³ lattice (float32, flat; fixed generator seed)."""
    return np.random.default_rng(20240617).random(_LATTICE**3, dtype=np.float32)


@cache
def _seed_offset(seed: int) -> np.ndarray:
    """Lattice offset (3,) int64 of a noise seed (each seed reads another part of the table)."""
    h = _hash01(np.array([seed, seed, seed], np.int64), np.array([1, 2, 3], np.int64), np.zeros(3, np.int64), 77)
    return (h * _LATTICE).astype(np.int64)


def _cell_values(ic: np.ndarray, seed: int) -> np.ndarray:
    """Random value (M,) in [0, 1) of the integer lattice cells ic (M, 3) for a seed."""
    i = (ic + _seed_offset(seed)) & (_LATTICE - 1)
    return _lattice_table()[(i[:, 0] << (2 * _LATTICE_BITS)) | (i[:, 1] << _LATTICE_BITS) | i[:, 2]].astype(np.float64)


def lattice_noise(q: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise (M,) in [0, 1] at lattice coordinates q (M, 3) (one cell per unit, period
    64 cells; smoothstep-weighted trilinear interpolation of a fixed random table)."""
    i0 = np.floor(q)
    f = q - i0
    f = f * f * (3.0 - 2.0 * f)
    m = _LATTICE - 1
    i = i0.astype(np.int64) + _seed_offset(seed)
    x0, y0, z0 = i[:, 0] & m, i[:, 1] & m, i[:, 2] & m
    x1, y1, z1 = (x0 + 1) & m, (y0 + 1) & m, (z0 + 1) & m
    t = _lattice_table()
    b = _LATTICE_BITS
    a0, a1, b0, b1 = x0 << (2 * b), x1 << (2 * b), y0 << b, y1 << b
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    gz = 1.0 - fz
    c00 = t[a0 | b0 | z0] * gz + t[a0 | b0 | z1] * fz
    c01 = t[a0 | b1 | z0] * gz + t[a0 | b1 | z1] * fz
    c10 = t[a1 | b0 | z0] * gz + t[a1 | b0 | z1] * fz
    c11 = t[a1 | b1 | z0] * gz + t[a1 | b1 | z1] * fz
    return (c00 * (1.0 - fy) + c01 * fy) * (1.0 - fx) + (c10 * (1.0 - fy) + c11 * fy) * fx


def _fbm(p: np.ndarray, frequency: float, seed: int, octaves: int) -> np.ndarray:
    """Fractal sum (M,) of :func:`lattice_noise` at positions p (M, 3) metres, roughly in [0, 1]."""
    total = np.zeros(p.shape[0])
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += amp * lattice_noise(p * (frequency * 2.0**o), seed + 101 * o)
        norm += amp
        amp *= 0.5
    return total / norm


def _band(q: np.ndarray, seed: int, gain: np.ndarray) -> np.ndarray:
    """Value noise at lattice coordinates q (M, 3) (one cell per unit), centred and scaled by gain
    (M,); 0 where the gain is negligible (not evaluated there)."""
    out = np.zeros(q.shape[0])
    k = gain > _MIN_GAIN
    if k.any():
        out[k] = (lattice_noise(q[k], seed) - 0.5) * gain[k]
    return out


@cache
def _noise_stats(lo: float, hi: float) -> float:
    """Mean of smoothstep(value noise, lo, hi) (a fixed sample of the lattice; deterministic)."""
    pts = np.random.default_rng(1234).uniform(0.0, 64.0, (20000, 3))
    return float(np.mean(smoothstep(lattice_noise(pts, 99), lo, hi)))


def _dots(p: np.ndarray, freq: float, seed: int, fp: np.ndarray, lo: float = 0.6, hi: float = 0.85) -> np.ndarray:
    """Dots (M,) in [0, 1] of value noise at ``freq`` cells/m thresholded to [lo, hi], faded to
    their mean with the footprint (evaluated only where they survive)."""
    mean = _noise_stats(lo, hi)
    gain = attenuation(freq, fp)
    out = np.full(p.shape[0], mean)
    k = gain > _MIN_GAIN
    if k.any():
        out[k] = mean + (smoothstep(lattice_noise(p[k] * freq, seed), lo, hi) - mean) * gain[k]
    return out


def _spots(q: np.ndarray, seed: int, fp: np.ndarray, cell: float, prob: np.ndarray, r_lo: float, r_hi: float) -> np.ndarray:
    """Darkness (M,) of Gaussian spots on a jittered 3D grid of ``cell`` metres, at most one per cell
    and never crossing its cell. q: (M, 3) positions (metres); prob: (M,) chance of a spot in the
    sample's cell; radii uniform in [r_lo, r_hi]. Each spot keeps its integral when widened by the
    footprint (2D Gaussian: peak × σ²/σ'²); as the widened spots outgrow their cells the result
    fades to the spots' mean darkness (prob × the mean of a grid full of spots)."""
    val = _spot_field(q, seed, fp, cell, prob, r_lo, r_hi)
    g = np.exp(-np.square(fp / (0.25 * cell)))
    return g * val + (1.0 - g) * prob * _spot_mean(cell, r_lo, r_hi)


@cache
def _spot_mean(cell: float, r_lo: float, r_hi: float) -> float:
    """Mean darkness of sharp spots with one spot in every cell, over a fixed sample of points."""
    pts = np.random.default_rng(4321).uniform(-0.2, 0.2, (40000, 3))
    return float(_spot_field(pts, 1, np.zeros(len(pts)), cell, np.ones(len(pts)), r_lo, r_hi).mean())


def _spot_field(q: np.ndarray, seed: int, fp: np.ndarray, cell: float, prob: np.ndarray, r_lo: float, r_hi: float) -> np.ndarray:
    """The spots of :func:`_spots` widened by the footprint, without the fade."""
    g = q / cell
    ic = np.floor(g).astype(np.int64)
    h = lambda k: _cell_values(ic, seed + k)  # noqa: E731
    r = r_lo + (r_hi - r_lo) * h(0)
    margin = np.minimum(2.0 * r / cell, 0.45)
    centre = ic + margin[:, None] + (1.0 - 2.0 * margin[:, None]) * np.stack([h(1), h(2), h(3)], -1)
    d2 = np.sum(np.square((g - centre) * cell), axis=1)
    present = h(4) < prob
    s2 = np.square(r) + np.square(fp)
    return present * (np.square(r) / s2) * np.exp(-0.5 * d2 / s2) * h(5)


def _line(d: np.ndarray, width: float, fp: np.ndarray) -> np.ndarray:
    """Profile (M,) of a line of Gaussian half-width ``width`` at signed distance d, widened by the
    footprint with its integral kept (1D: peak × w/w')."""
    w2 = width * width + np.square(fp)
    return (width / np.sqrt(w2)) * np.exp(-0.5 * np.square(d) / w2)


def _segment_distance(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (M,) of 2D points q (M, 2) to the segment a–b, and the parameter t in [0, 1]."""
    ab = b - a
    t = np.clip(((q - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(q - (a + t[:, None] * ab), axis=1), t


# ----------------------------------------------------------------------------- skin


@dataclass(frozen=True)
class FaceAnchors:
    """Template landmarks the detail is placed by: mouth height, eyeball centres (2, 3) and radius."""

    mouth_y: float
    eye_centres: np.ndarray
    eye_radius: float


def hairline(p: np.ndarray) -> np.ndarray:
    """Hairline height (M,) at the azimuth of template points p (M, 3) (the smooth head's)."""
    phi = np.arctan2(p[:, 0], p[:, 2] + 0.005)
    return 0.02125 + 0.0675 * np.cos(phi) - 0.01375 * np.cos(2 * phi)


def hair_coverage(p: np.ndarray, fp: np.ndarray, st: DetailStyle) -> np.ndarray:
    """Scalp hair coverage (M,) in [0, 1]: a ragged hairline with fine hairs, and the parting line."""
    rag = _band(p * 260.0, st.seed + 40, attenuation(130.0, fp)) + 0.6 * _band(p * 900.0, st.seed + 41, attenuation(450.0, fp))
    y = p[:, 1] - hairline(p) + 0.004 * rag
    cov = smoothstep(y, -0.002, 0.008) * (p[:, 1] > -0.1)
    if st.parting is not None:
        o, w, e1, e2 = st.whorl_frame()
        q = p - o
        x1, x2, z = q @ e1, q @ e2, q @ w
        theta = np.arctan2(np.hypot(x1, x2), z)
        phi = np.arctan2(x2, x1)
        dphi = np.angle(np.exp(1j * (phi - st.parting)))
        dist = dphi * np.linalg.norm(q, axis=1) * np.sin(theta)
        along = smoothstep(theta, 0.05, 0.25) * (p[:, 1] > hairline(p) + 0.004)
        cov = cov * (1.0 - 0.6 * along * _line(dist, 0.0005, fp) / _line(np.zeros(1), 0.0005, np.zeros(1)))
    return cov


def skin_detail(p: np.ndarray, fp: np.ndarray, crease: np.ndarray, skin_rgb: np.ndarray, lips_rgb: np.ndarray,
                hair_rgb: np.ndarray, st: DetailStyle, fa: FaceAnchors,
                over: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Detailed albedo of M skin points (skin, lips, brows, lashes, scalp hair).

    p: (M, 3) template positions; fp: (M,) footprint (metres); crease: (M,) compression weights;
    skin_rgb, lips_rgb, hair_rgb: (3,) base colours; over: an albedo (M, 3) and its weight (M,) in
    [0, 1] laid over the procedural one before the expression creases shade it (a photograph's
    skin, :mod:`.photo_skin`), or None -> (albedo (M, 3), hair coverage (M,) of scalp, brows and
    lashes, template hair tangent (M, 3) whose length is the gloss, zero where there is no hair).
    """
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    s = st.seed
    M = p.shape[0]
    front = smoothstep(z, 0.0, 0.04)
    # low and mid frequencies: tone, mottling, blush
    n_low = _fbm(p, 45.0, s, 2) - 0.5
    mottle = _band(p * 160.0, s + 1, attenuation(80.0, fp)) + 0.7 * _band(p * 420.0, s + 2, attenuation(210.0, fp))
    red = np.maximum(_band(p * 120.0, s + 3, attenuation(60.0, fp)), 0.0)
    lum = 1.0 + 0.16 * n_low + 0.1 * mottle
    col = skin_rgb[None] * lum[:, None]
    col *= (1.0 + red[:, None] * np.array([0.06, -0.18, -0.14])[None])
    # fine texture: pigment and micro-relief irregularity at 1–2 mm, the skin's texture at the pixel scale
    fine = _band(p * 700.0, s + 11, attenuation(350.0, fp)) + 0.4 * _band(p * 1300.0, s + 12, attenuation(650.0, fp))
    col *= (1.0 + fine[:, None] * np.array([0.32, 0.34, 0.38])[None])
    blush = 0.5 * gauss(ax - 0.043, 0.014) * gauss(y + 0.005, 0.012) * front
    col = _mix(col, col * np.array([1.08, 0.82, 0.8]), blush)
    # pores: dark pits, deeper on the nose and cheeks (their mean darkening survives any footprint)
    pore_w = st.pores * (0.7 + 0.8 * gauss(ax - 0.03, 0.022) * gauss(y - 0.0, 0.025) * front + 0.8 * gauss(x, 0.012) * gauss(y - 0.0, 0.02) * front)
    pits = 0.3 * _dots(p, 1900.0, s + 4, fp) + 0.2 * _dots(p, 3300.0, s + 5, fp)
    col *= (1.0 - pore_w * pits)[:, None]
    # freckles and moles
    if st.freckles > 0:
        fr_region = st.freckles * front * (0.35 + 1.3 * gauss(ax - 0.03, 0.02) * gauss(y - 0.005, 0.022) + 0.9 * gauss(x, 0.01) * gauss(y - 0.01, 0.015)
                                           + 0.3 * smoothstep(y, 0.05, 0.07))
        fr = _spots(p, s + 6, fp, 0.0034, 0.75 * fr_region, 0.00035, 0.0008) + 0.8 * _spots(p + 0.0011, s + 7, fp, 0.0026, 0.6 * fr_region, 0.0003, 0.0006)
        col *= (1.0 - np.clip(0.5 * fr, 0.0, 0.8)[:, None] * np.array([0.5, 0.62, 0.72])[None])
    moles = st.mole_array
    if len(moles):
        dk = np.zeros(M)
        for mx, my, mz, mr, md, _warm in moles:
            d2 = np.square(x - mx) + np.square(y - my) + np.square(z - mz)
            s2 = mr * mr + np.square(fp)
            dk = np.maximum(dk, md * (mr * mr / s2) * np.exp(-0.5 * d2 / s2 * 1.6))
        col *= (1.0 - dk[:, None] * np.array([0.55, 0.68, 0.75])[None])
    # fine lines
    col *= (1.0 - _fine_lines(p, fp, st, fa))[:, None]
    # lips
    mouth_y = fa.mouth_y
    up = 0.0085 - 0.002 * gauss(x, 0.004)
    lip_band = np.where(y >= mouth_y, smoothstep(y - mouth_y, up, up - 0.002), smoothstep(mouth_y - y, 0.0105, 0.0085))
    lip = lip_band * smoothstep(ax, 0.026, 0.021) * front
    if (lip > 0).any():
        lines = np.cos(2.0 * np.pi * (x * 800.0 + 2.0 * _fbm(p, 120.0, s + 8, 1)))
        lip_lum = 1.0 + 0.1 * n_low - 0.07 * lines * attenuation(800.0, fp) * smoothstep(np.abs(y - mouth_y), 0.001, 0.003)
        col = _mix(col, lips_rgb[None] * lip_lum[:, None], lip)
    nostril = gauss(ax - 0.0075, 0.0028) * gauss(y + 0.0125, 0.002) * front
    col *= (1.0 - 0.55 * nostril)[:, None]
    # stubble
    if st.stubble > 0:
        bw = _beard(p, fa) * st.stubble * (1.0 - lip)
        b = bw > 1e-3
        if b.any():
            dots = _dots(p[b], 2300.0, s + 9, fp[b], 0.5, 0.7)
            patch = 0.75 + 0.5 * (_fbm(p[b], 90.0, s + 10, 2) - 0.5)
            amount = np.clip(bw[b] * patch * (0.25 + 0.75 * dots), 0.0, 1.0)
            col[b] = _mix(col[b], hair_rgb[None] * 0.7 + 0.03, amount)
    # hair: scalp, brows, lashes (coverage and strand tangents)
    cov = np.zeros(M)
    tan = np.zeros((M, 3))
    hw = np.zeros(M)
    near = y > hairline(p) - 0.012
    if near.any():
        hw[near] = hair_coverage(p[near], fp[near], st)
    h = hw > 1e-3
    if h.any():
        hcol, htan = scalp_hair(p[h], fp[h], hair_rgb, st)
        col[h] = _mix(col[h], hcol, hw[h])
        cov[h], tan[h] = hw[h], htan
    bw, bcol, btan = _brows(p, fp, hair_rgb, st, front)
    b = bw > 1e-3
    if b.any():
        col[b] = _mix(col[b], bcol[b], bw[b])
        cov = np.maximum(cov, bw)
        tan[b] = np.where((bw[b] > cov[b] - 1e-9)[:, None], btan[b], tan[b])
    lw = _lashes(p, fp, st, fa)
    lb = lw > 1e-3
    if lb.any():
        col[lb] = _mix(col[lb], np.broadcast_to(hair_rgb * 0.35 + 0.01, (int(lb.sum()), 3)), lw[lb])
    if over is not None:
        rgb, w = over
        col = col * (1.0 - w[:, None]) + rgb * w[:, None]
    # expression creases (as the smooth head)
    lines = 0.55 + 0.45 * np.cos(2 * np.pi * y / 0.0045 + 3.0 * n_low)
    forehead = smoothstep(y, 0.045, 0.055)
    crease_shade = crease * (forehead * lines + (1.0 - forehead) * 0.8) * (1.0 - hw)
    col = col * (1.0 - 0.5 * np.clip(crease_shade, 0.0, 1.0))[:, None]
    return np.clip(col, 0.0, 1.0), cov, tan


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a * (1.0 - t[:, None]) + b * t[:, None]


def _fine_lines(p: np.ndarray, fp: np.ndarray, st: DetailStyle, fa: FaceAnchors) -> np.ndarray:
    """Darkening (M,) of static fine lines: forehead lines, crow's feet, lid lines, nasolabial
    folds, neck rings; strength grows with ``st.age``. Each family is evaluated in its region only."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    out = np.zeros(p.shape[0])
    a = st.age
    eye_y = float(fa.eye_centres[0, 1])
    eye_x = float(abs(fa.eye_centres[0, 0]))
    front_pts = z > 0.0

    def wobble(q: np.ndarray) -> np.ndarray:
        return 0.0018 * (_fbm(q * np.array([1.0, 0.0, 1.0]), 70.0, st.seed + 20, 2) - 0.5)

    k = front_pts & (y > 0.05) & (ax < 0.07)
    if k.any():
        q, f = p[k], fp[k]
        hl = hairline(q)
        fh = smoothstep(q[:, 2], 0.0, 0.04) * gauss(q[:, 0], 0.04) * smoothstep(q[:, 1], hl - 0.002, hl - 0.012)
        wob = wobble(q)
        vary = 0.6 + 0.4 * lattice_noise(q * 120.0, st.seed + 21)
        acc = np.zeros(len(q))
        for j, yk in enumerate((0.058, 0.067, 0.077)):
            acc += _line(q[:, 1] - yk - wob * (1 + j), 0.00035, f)
        out[k] += 0.16 * a * fh * acc * vary
    k = front_pts & (np.abs(ax - eye_x - 0.022) < 0.014) & (np.abs(y - eye_y) < 0.014)
    if k.any():
        q2 = np.stack([ax[k], y[k]], -1)
        corner = np.array([eye_x + 0.016, eye_y])
        acc = np.zeros(int(k.sum()))
        for ang in (-0.45, -0.1, 0.3):
            dirn = np.array([math.cos(ang), math.sin(ang)])
            d, t = _segment_distance(q2, corner + 0.003 * dirn, corner + 0.013 * dirn)
            acc += _line(d, 0.0003, fp[k]) * np.sin(np.pi * t)
        out[k] += 0.14 * a * smoothstep(z[k], 0.0, 0.04) * acc
    k = front_pts & (np.abs(ax - eye_x) < 0.03) & (np.abs(y - eye_y) < 0.03)
    if k.any():
        r_eye = np.hypot(ax[k] - eye_x, y[k] - eye_y)
        fr = smoothstep(z[k], 0.0, 0.04)
        below = smoothstep(y[k], eye_y - 0.006, eye_y - 0.010) * gauss(ax[k] - eye_x, 0.012)
        above = smoothstep(y[k], eye_y + 0.004, eye_y + 0.008) * gauss(ax[k] - eye_x, 0.011)
        out[k] += fr * (0.10 * (0.3 + a) * below * _line(r_eye - 0.0165, 0.0005, fp[k]) + 0.14 * above * _line(r_eye - 0.0145, 0.0004, fp[k]))
    k = front_pts & (ax > 0.01) & (ax < 0.04) & (y < 0.01) & (y > fa.mouth_y - 0.02)
    if k.any():
        q2 = np.stack([ax[k], y[k]], -1)
        d, t = _segment_distance(q2, np.array([0.017, 0.002]), np.array([0.031, fa.mouth_y - 0.012]))
        out[k] += 0.12 * (0.3 + a) * smoothstep(z[k], 0.0, 0.04) * _line(d, 0.0006, fp[k]) * smoothstep(t, 0.0, 0.15) * smoothstep(t, 1.0, 0.8)
    k = (z > -0.02) & (y < -0.095) & (y > -0.14)
    if k.any():
        neck = smoothstep(z[k], -0.02, 0.01) * smoothstep(y[k], -0.095, -0.105)
        wob = wobble(p[k])
        acc = _line(y[k] - (-0.112) - 2 * wob, 0.0006, fp[k]) + _line(y[k] - (-0.127) - 2 * wob, 0.0006, fp[k])
        out[k] += 0.10 * a * neck * acc
    return np.clip(out, 0.0, 0.6)


def _beard(p: np.ndarray, fa: FaceAnchors) -> np.ndarray:
    """Beard-shaped stubble density (M,) in [0, 1]: cheeks below the cheekbone line, jaw, chin,
    upper lip, under the chin, joined to the sideburns."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ax = np.abs(x)
    m = fa.mouth_y
    top = np.where(ax < 0.032, m + 0.014, m + 0.014 + (ax - 0.032) * 1.2)
    cheek = smoothstep(y, top + 0.004, top - 0.004) * smoothstep(y, -0.125, -0.105)
    lip = gauss(x, 0.022) * smoothstep(y - m, 0.002, 0.006) * smoothstep(y - m, 0.022, 0.015)
    side = smoothstep(z, -0.045, -0.02)
    return np.clip(np.maximum(cheek, lip) * side, 0.0, 1.0)


def _brows(p: np.ndarray, fp: np.ndarray, hair_rgb: np.ndarray, st: DetailStyle, front: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Brow coverage (M,), colour (M, 3) and strand tangents (M, 3; length = gloss) of strands: the
    inner head points up, the body and tail run outward."""
    x, y = p[:, 0], p[:, 1]
    ax = np.abs(x)
    M = p.shape[0]
    yc = 0.047 + 0.005 * (1.0 - np.square((ax - 0.033) / 0.022)) - 0.002 * smoothstep(ax, 0.045, 0.058)
    half = st.brow_thickness * (0.0028 + 0.0016 * smoothstep(ax, 0.03, 0.014) - 0.0013 * smoothstep(ax, 0.04, 0.057))
    region = smoothstep(np.abs(y - yc), 1.6 * half + 0.002, 0.6 * half) * smoothstep(ax, 0.06, 0.052) * smoothstep(ax, 0.009, 0.013) * front
    cov = np.zeros(M)
    colr = np.zeros((M, 3))
    tan = np.zeros((M, 3))
    r = region > 1e-3
    if not r.any():
        return cov, colr, tan
    pr, fr, axr, yr = p[r], fp[r], ax[r], y[r]
    ang = 1.25 * smoothstep(axr, 0.026, 0.012) + 0.22 - 0.4 * smoothstep(axr, 0.035, 0.058)
    c, sn = np.cos(ang), np.sin(ang)
    u = -sn * axr + c * yr  # across the strands
    v = c * axr + sn * yr  # along the strands
    side = np.sign(pr[:, 0]) * 7.3
    q = lambda fu, fv: np.stack([u * fu, v * fv, side + 0.0 * u], -1)  # noqa: E731
    strands = (0.9 * _band(q(1400.0, 180.0), st.seed + 30, attenuation(1400.0, fr))
               + 0.7 * _band(q(3000.0, 300.0), st.seed + 31, attenuation(3000.0, fr))
               + 0.5 * _band(q(500.0, 120.0), st.seed + 32, attenuation(500.0, fr)))
    edge = np.abs(yr - yc[r]) / np.maximum(half[r], 1e-6)
    ragged = np.clip(1.5 - edge + 2.2 * strands, 0.0, 1.0)
    dens = np.clip(st.brow_density * (0.78 + 1.1 * strands), 0.0, 1.0)
    cov[r] = region[r] * np.clip(ragged * dens, 0.0, 1.0)
    colr[r] = hair_rgb[None] * (0.85 + 0.8 * strands)[:, None]
    tan[r] = 0.35 * np.stack([np.sign(pr[:, 0]) * c, sn, np.zeros_like(c)], -1)  # short, sparse hairs: little sheen
    return cov, colr, tan


def _lashes(p: np.ndarray, fp: np.ndarray, st: DetailStyle, fa: FaceAnchors) -> np.ndarray:
    """Lash coverage (M,): a dark line on the lid margin (where the skin meets the eyeball) and
    radial lash strands beyond it, strong on the upper lid, weak on the lower one."""
    out = np.zeros(p.shape[0])
    for ctr in fa.eye_centres:
        q = p - ctr
        dist = np.linalg.norm(q, axis=1) - fa.eye_radius
        near = (dist < 0.006) & (q[:, 2] > 0.0)
        if not near.any():
            continue
        qn, dn, fn = q[near], dist[near], fp[near]
        ang = np.arctan2(qn[:, 1], qn[:, 0] * np.sign(ctr[0]))  # 0 = outer corner, pi/2 = top
        upper = smoothstep(ang, -0.35, 0.15) * smoothstep(ang, np.pi + 0.35, np.pi - 0.15)
        lower = 1.0 - upper
        taper = smoothstep(np.abs(np.abs(ang - np.pi / 2) - np.pi / 2), 0.0, 0.45)  # thinner at the corners
        margin = _line(dn - 0.0004, 0.0006, fn) / _line(np.zeros(1), 0.0006, np.zeros(1))
        strands = 0.5 + 0.5 * np.cos(ang * 70.0 + 3.0 * lattice_noise(qn * 300.0, st.seed + 35)) * attenuation(70.0 / (2 * np.pi * 0.014), fn)
        reach = smoothstep(dn, 0.0035, 0.0005)
        lash = upper * (0.95 * margin + 0.7 * reach * strands) + lower * (0.45 * margin + 0.25 * reach * strands)
        out[near] = np.maximum(out[near], np.clip(st.lashes * lash * (0.4 + 0.6 * taper), 0.0, 1.0))
    return out


# ----------------------------------------------------------------------------- hair


def strand_coordinates(p: np.ndarray, frame: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], st: DetailStyle | None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Coordinates of points p (M, 3) in a hair frame (origin, pole, e1, e2): (azimuth φ of the
    strand (M,), polar angle θ (M,), radius r (M,), unit strand tangent (M, 3) along increasing θ).
    With a style: its spiral, wave and parting bend φ."""
    o, w, e1, e2 = frame
    q = p - o
    x1, x2, zz = q @ e1, q @ e2, q @ w
    rho = np.hypot(x1, x2)
    theta = np.arctan2(rho, zz)
    phi = np.arctan2(x2, x1)
    r = np.linalg.norm(q, axis=1)
    if st is not None:
        phi = phi + st.swirl * theta + st.wave * np.sin(theta * 9.0 + 2.0)
        if st.parting is not None:
            dphi = np.angle(np.exp(1j * (phi - st.parting)))
            phi = phi + np.sign(dphi) * 0.25 * np.exp(-np.abs(dphi) / 0.25) * smoothstep(theta, 0.05, 0.3)
    cphi, sphi = np.cos(phi), np.sin(phi)
    ct, stt = np.cos(theta), np.sin(theta)
    tan = ct[:, None] * (cphi[:, None] * e1[None] + sphi[:, None] * e2[None]) - stt[:, None] * w[None]
    return phi, theta, r, tan


def hair_strands(p: np.ndarray, fp: np.ndarray, hair_rgb: np.ndarray, st: DetailStyle,
                 frame: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Hair colour (M, 3) and strand tangents (M, 3) at points p (M, 3) of a hair frame: clumps,
    strands and fine strands along the frame's meridians, with streaks and grey strands. The
    tangents' length is the strands' gloss (their luminance factor: shadowed gaps shine less)."""
    phi, theta, r, tan = strand_coordinates(p, frame, st)
    along = theta * 0.1  # metres along the strand (at a 0.1 m radius)
    circ = 2.0 * np.pi * np.maximum(r * np.sin(theta), 0.004)  # metres around at this point
    total = np.zeros(p.shape[0])
    cp, sp = np.cos(phi), np.sin(phi)
    for k, (n_around, f_along, amp) in enumerate(((420.0, 60.0, 0.9), (1500.0, 110.0, 0.7), (4000.0, 200.0, 0.5))):
        rho = n_around / (2.0 * np.pi)
        qq = np.stack([rho * cp, rho * sp, along * f_along], -1)
        total += amp * _band(qq, st.seed + 51 + k, attenuation(n_around / circ, fp))
    # clumps (≈ 2–6 mm): lit tops and shadowed gaps
    clump = np.zeros(p.shape[0])
    for k, (n_around, f_along, amp) in enumerate(((110.0, 18.0, 1.0), (230.0, 35.0, 0.7))):
        rho = n_around / (2.0 * np.pi)
        clump += amp * _band(np.stack([rho * cp, rho * sp, along * f_along], -1), st.seed + 48 + k, attenuation(n_around / circ, fp))
    streak_q = np.stack([8.0 * cp, 8.0 * sp, along * 12.0], -1)
    streak = st.streaks * smoothstep(lattice_noise(streak_q, st.seed + 60), 0.55, 0.8)
    lum = np.clip((0.8 + 2.0 * clump) * (1.0 + 1.8 * total), 0.1, 1.8)
    # the cuticles' grey sheen on the lit tops of clumps (what makes dark hair's clumps visible)
    col = hair_rgb[None] * lum[:, None] + 0.06 * smoothstep(lum, 0.8, 1.6)[:, None]
    col = _mix(col, np.clip(hair_rgb * 1.9 + 0.12, 0.0, 1.0)[None] * lum[:, None], streak)
    if st.grey > 0:
        grey_q = np.stack([80.0 * cp, 80.0 * sp, along * 30.0], -1)
        g = st.grey * smoothstep(lattice_noise(grey_q, st.seed + 61), 0.5, 0.75)
        col = _mix(col, np.full_like(col, 0.62) * lum[:, None], g)
    return np.clip(col, 0.0, 1.0), tan * np.clip(lum, 0.2, 1.5)[:, None]


def scalp_hair(p: np.ndarray, fp: np.ndarray, hair_rgb: np.ndarray, st: DetailStyle) -> tuple[np.ndarray, np.ndarray]:
    """Scalp hair colour (M, 3) and template strand tangents (M, 3) (strands from the crown whorl;
    length = gloss)."""
    return hair_strands(p, fp, hair_rgb, st, st.whorl_frame())
