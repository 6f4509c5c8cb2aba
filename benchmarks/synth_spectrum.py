"""Detail that survives: power spectra of skin and hair, a real photograph against the synthetic heads.

Usage: python benchmarks/synth_spectrum.py [--seeds 0 1 2 3] [--preset small] [--out docs/benchmarks]
                                           [--image docs/images/synth_vs_photo.png]

The photograph is scikit-image's ``astronaut`` (a portrait shipped in its wheel). Its scale is
estimated from the interpupillary distance (the two pupil centres below, picked by hand on the
image, against a typical 63 mm). Each synthetic subject (``sage synth`` subject of each seed, smooth
and detailed appearance, tracked-capture shading with highlights) is rendered frontally with its
neutral canonical mesh by the ground-truth renderer at the *same* pixels per millimetre, and its
pupils are projected into the render. Patches are boxes placed relative to the pupils' midpoint
in millimetres, identical for the photo and the renders: three skin boxes (both cheeks below the
eyes, the chin below the mouth) and three hair boxes (the top of the head, its upper left side, the
right side next to the temple).

Each patch's luminance (Rec. 709 weights on the stored 8-bit values) has a least-squares plane
removed (shading gradients), is multiplied by a 2D Hann window and Fourier transformed; the power
is normalised so that it sums to the window-weighted variance. The radially averaged spectrum is
reported in cycles/mm, and the *band energy* is the luminance variance between ``BAND`` cycles/mm
(periods 3.3–10 mm: the pixel-scale detail of a 0.5–0.7 px/mm capture; the photo's Nyquist
frequency is 0.34 cycles/mm). Writes ``OUT/synth_spectrum.json`` and ``OUT/synth_spectrum.md`` and
a side-by-side picture (photo crop | the first three detailed subjects | the first smooth subject,
same scale, enlarged 3×).
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

PHOTO = "skimage.data.astronaut()"
PHOTO_PUPILS = ((203.1, 101.3), (245.6, 103.1))
"""Pupil centres (x, y) in pixels of the astronaut photo (image left = the subject's right eye)."""
IPD_MM = 63.0
BAND = (0.1, 0.3)
"""High-frequency band in cycles/mm."""
BIN = 0.025
"""Width of the radial spectrum bins, cycles/mm."""

# Boxes: (name, (x0, y0, w, h) in photo pixels, centre offset from the pupils' midpoint in mm for the
# renders (x right, y down in the image) or None for the photo box's own offset). The skin boxes sit at
# the same place on both faces (the synthetic chin box 4 mm lower, clear of the lips of a long face);
# the photo's hair is much fuller than a synthetic head's, so the synthetic hair boxes are placed
# inside the synthetic hair (top of the head, both upper sides).
BOXES: dict[str, list[tuple[str, tuple[int, int, int, int], tuple[float, float] | None]]] = {
    "skin": [("cheek (subject's right)", (190, 110, 20, 20), None), ("cheek (subject's left)", (240, 112, 20, 20), None),
             ("chin", (205, 157, 26, 12), (-9.4, 94.0))],
    "hair": [("top", (213, 34, 16, 12), (0.0, -74.0)), ("upper left side", (246, 44, 16, 12), (33.0, -62.0)),
             ("upper right side", (178, 56, 16, 12), (-33.0, -62.0))],
}
FACE_CROP = (150, 10, 160, 170)
"""The photo crop of the side-by-side picture (x0, y0, w, h)."""


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W) Rec. 709 luminance of an (H, W, 3) image in [0, 1]."""
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def patch_spectrum(patch: np.ndarray, px_per_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Power of a luminance patch (h, w) after plane removal and a Hann window, normalised to sum to
    the window-weighted variance. Returns (frequency in cycles/mm (h, w), power (h, w))."""
    h, w = patch.shape
    yy, xx = np.mgrid[0:h, 0:w]
    A = np.stack([np.ones(h * w), xx.ravel(), yy.ravel()], 1)
    coef, *_ = np.linalg.lstsq(A, patch.ravel(), rcond=None)
    resid = patch - (A @ coef).reshape(h, w)
    win = np.outer(np.hanning(h + 2)[1:-1], np.hanning(w + 2)[1:-1])
    F = np.fft.fft2(resid * win)
    power = np.abs(F) ** 2 / (h * w) / np.sum(win**2)
    f = np.hypot(np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None]) * px_per_mm
    return f, power


def band_energy(f: np.ndarray, power: np.ndarray, band: tuple[float, float] = BAND) -> float:
    """Variance of the patch between band[0] and band[1] cycles/mm."""
    return float(power[(f >= band[0]) & (f < band[1])].sum())


def radial(f: np.ndarray, power: np.ndarray, fmax: float) -> list[float]:
    """Power summed per radial bin of :data:`BIN` cycles/mm from 0 to ``fmax``."""
    edges = np.arange(0.0, fmax + 1e-9, BIN)
    return [float(power[(f >= a) & (f < b)].sum()) for a, b in zip(edges[:-1], edges[1:])]


def measure(image: np.ndarray, pupils: np.ndarray, px_per_mm: float, photo_pupils: np.ndarray, photo_px_per_mm: float,
            image_is_photo: bool = False) -> dict:
    """Band energies and radial spectra of every box of :data:`BOXES` in ``image`` (H, W, 3) whose
    pupils are at ``pupils`` (2, 2): the photo's boxes, or for a render the boxes at their offsets
    from the pupils' midpoint in mm."""
    Y = luminance(image)
    mid, pmid = pupils.mean(0), photo_pupils.mean(0)
    out: dict = {}
    for region, boxes in BOXES.items():
        rows = []
        for name, (x0, y0, w, h), synth_mm in boxes:
            if synth_mm is None or image_is_photo:
                cx = mid[0] + (x0 + w / 2 - pmid[0]) / photo_px_per_mm * px_per_mm
                cy = mid[1] + (y0 + h / 2 - pmid[1]) / photo_px_per_mm * px_per_mm
            else:
                cx, cy = mid[0] + synth_mm[0] * px_per_mm, mid[1] + synth_mm[1] * px_per_mm
            xa, ya = int(round(cx - w / 2)), int(round(cy - h / 2))
            if xa < 0 or ya < 0 or xa + w > Y.shape[1] or ya + h > Y.shape[0]:
                raise ValueError(f"box {name} falls outside the image")
            patch = Y[ya : ya + h, xa : xa + w]
            f, p = patch_spectrum(patch, px_per_mm)
            e = band_energy(f, p)
            rows.append({"box": name, "pixels": [xa, ya, w, h], "mean_luminance": float(patch.mean()), "band_energy": e,
                         "relative_band_energy": e / max(float(patch.mean()) ** 2, 1e-12), "radial": radial(f, p, 0.5 * px_per_mm)})  # fmt: skip
        out[region] = {"boxes": rows, "band_energy": float(np.mean([r["band_energy"] for r in rows])),
                       "relative_band_energy": float(np.mean([r["relative_band_energy"] for r in rows])),
                       "mean_luminance": float(np.mean([r["mean_luminance"] for r in rows]))}
    return out


def photo() -> tuple[np.ndarray, np.ndarray, float]:
    """The astronaut photo (H, W, 3) in [0, 1], its pupils (2, 2) and pixels per mm."""
    from skimage import data

    img = data.astronaut().astype(np.float64) / 255.0
    pupils = np.asarray(PHOTO_PUPILS)
    return img, pupils, float(np.linalg.norm(pupils[1] - pupils[0]) / IPD_MM)


def render_subject(seed: int, appearance: str, preset: str, px_per_mm: float, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, dict]:
    """A frontal render (H, W, 3) of the neutral subject of ``seed`` at ``px_per_mm`` on the face,
    its pupils (2, 2), and what the subject is (detail style)."""
    from sage_core.data.cameras import Camera, look_at
    from sage_core.data.synthetic import preset as synth_preset
    from sage_core.data.synthetic.capture import canonical_vertices, make_subject
    from sage_core.data.synthetic.head import _EYE_R

    cfg = synth_preset(preset, seed=seed, tracking="fitted", appearance=appearance)
    subj = make_subject(cfg)
    verts = canonical_vertices(subj)
    joints = subj.head.j_regressor @ verts
    pupils3 = joints[3:5] + np.array([0.0, 0.0, _EYE_R])
    W, H = size
    distance = 1.0
    face_z = float(pupils3[:, 2].mean())
    fl = px_per_mm * 1000.0 * (distance - face_z)
    centre = np.array([0.0, float(pupils3[:, 1].mean()) - 0.02, 0.0])
    eye = centre + np.array([0.0, 0.0, distance])
    K = np.array([[fl, 0.0, W / 2], [0.0, fl, H / 2], [0.0, 0.0, 1.0]])
    cam = Camera(K, look_at(eye, centre), W, H)
    r = subj.render(verts, cam, None, cfg.supersample)
    img = np.round(np.clip(r.rgb.astype(np.float64), 0, 1) * 255.0) / 255.0  # as stored in a capture's PNG
    uv, _ = cam.project(pupils3)
    info = {"seed": seed, "appearance": appearance, "preset": preset}
    if subj.app.detail is not None:
        d = subj.app.detail
        info.update(hair_style=d.hair_style, freckles=round(d.freckles, 3), stubble=round(d.stubble, 3), age=round(d.age, 3))
    return img, uv[::-1], info  # photo order: image left (the subject's right eye) first


def side_by_side(photo_img: np.ndarray, photo_pupils: np.ndarray, renders: list[tuple[np.ndarray, np.ndarray]], path: Path, zoom: int = 3) -> None:
    """Photo crop and renders (each aligned on the pupils' midpoint), same size, enlarged ``zoom``×."""
    import cv2

    from sage_core.data.imageio import write_image

    x0, y0, w, h = FACE_CROP
    pmid = photo_pupils.mean(0)
    tiles = [photo_img[y0 : y0 + h, x0 : x0 + w]]
    for img, pupils in renders:
        mid = pupils.mean(0)
        xa, ya = int(round(mid[0] - (pmid[0] - x0))), int(round(mid[1] - (pmid[1] - y0)))
        canvas = np.ones((h, w, 3))
        sx0, sy0 = max(xa, 0), max(ya, 0)
        sx1, sy1 = min(xa + w, img.shape[1]), min(ya + h, img.shape[0])
        canvas[sy0 - ya : sy1 - ya, sx0 - xa : sx1 - xa] = img[sy0:sy1, sx0:sx1]
        tiles.append(canvas)
    sep = np.ones((h, 2, 3))
    row = np.concatenate([t if i == 0 else np.concatenate([sep, t], 1) for i, t in enumerate(tiles)], 1)
    big = cv2.resize(row.astype(np.float32), None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    write_image(path, big)


def summarise(results: list[dict], photo_doc: dict) -> dict:
    """Mean band energy (absolute and relative to the mean luminance²) per appearance and region,
    and its ratio to the photo's."""
    out: dict = {}
    for app in ("smooth", "detailed"):
        rows = [r for r in results if r["subject"]["appearance"] == app]
        out[app] = {}
        for region in BOXES:
            out[app][region] = {}
            for key in ("band_energy", "relative_band_energy"):
                vals = [r["spectrum"][region][key] for r in rows]
                out[app][region][key] = {"mean": float(np.mean(vals)), "min": float(np.min(vals)), "max": float(np.max(vals)),
                                         "ratio_to_photo": float(np.mean(vals) / photo_doc[region][key])}  # fmt: skip
    return out


def markdown(doc: dict) -> str:
    s = doc["summary"]
    ph = doc["photo"]["spectrum"]
    lines = ["# Skin and hair detail against a photograph", "",
             f"Command: `{doc['command']}` ({doc['wall_s']:.0f} s on {doc['machine']}).", "",
             f"Photo: `{PHOTO}`, {doc['photo']['px_per_mm']:.3f} px/mm from its interpupillary distance "
             f"({doc['photo']['ipd_px']:.1f} px for {IPD_MM:.0f} mm). Synthetic subjects: `sage synth` seeds "
             f"{', '.join(str(x) for x in doc['seeds'])} (preset `{doc['preset']}`, tracked-capture shading), "
             "rendered frontally at the same px/mm. Band energy = luminance variance between "
             f"{BAND[0]} and {BAND[1]} cycles/mm of each box (plane removed, Hann window), mean over the boxes of a region; "
             "RMS = its square root in percent of full scale.", "",
             "| region | photo | smooth synthetic (mean) | detailed synthetic (mean, min–max over seeds) | detailed / photo | smooth / photo |",
             "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    rms = lambda e: f"{e:.2e} ({100 * math.sqrt(e):.2f} %)"  # noqa: E731
    for key, label in (("band_energy", "absolute"), ("relative_band_energy", "relative to the mean luminance²")):
        for region in BOXES:
            p = ph[region][key]
            sm, de = s["smooth"][region][key], s["detailed"][region][key]
            lines.append(f"| {region}, {label} | {rms(p)} | {rms(sm['mean'])} | {rms(de['mean'])}, {de['min']:.1e}–{de['max']:.1e} | "
                         f"{de['ratio_to_photo']:.2f} | {sm['ratio_to_photo']:.3f} |")
    lines += ["", "Per subject (band energy, skin / hair; relative in brackets):", "",
              "| seed | appearance | hair style | freckles | stubble | skin | hair |", "|---:|---|---|---:|---:|---:|---:|"]
    for r in doc["subjects"]:
        sub, sp = r["subject"], r["spectrum"]
        lines.append(f"| {sub['seed']} | {sub['appearance']} | {sub.get('hair_style', '—')} | {sub.get('freckles', '—')} | "
                     f"{sub.get('stubble', '—')} | {sp['skin']['band_energy']:.2e} ({sp['skin']['relative_band_energy']:.1e}) | "
                     f"{sp['hair']['band_energy']:.2e} ({sp['hair']['relative_band_energy']:.1e}) |")
    lines += ["", "Boxes (photo pixels; the renders use the same offsets from the pupils in mm): " +
              "; ".join(f"{region} {name} {box}" + (f", renders {mm} mm from the pupils" if mm else "")
                        for region, boxes in BOXES.items() for name, box, mm in boxes) + ".", "",
              f"![photo | detailed subjects | smooth subject]({doc['image_rel']})", ""]  # fmt: skip
    return "\n".join(lines)


def _repo_relative(path: Path) -> str:
    """``path`` relative to the repository when inside it (no machine paths in the results)."""
    try:
        return str(path.resolve().relative_to(REPO))
    except ValueError:
        return str(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/synth_spectrum.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="Synthetic subjects (seeds).")
    ap.add_argument("--preset", default="small", help="Synth preset whose head grid and supersampling are used.")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks", help="Folder for synth_spectrum.json and .md.")
    ap.add_argument("--image", type=Path, default=REPO / "docs" / "images" / "synth_vs_photo.png", help="Side-by-side picture.")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from sage_core.workspace import atomic_write_json, atomic_write_text

    t0 = time.time()
    img, pupils, pxmm = photo()
    photo_doc = measure(img, pupils, pxmm, pupils, pxmm, image_is_photo=True)
    size = (FACE_CROP[2] + 40, FACE_CROP[3] + 60)
    results, tiles = [], []
    for app in ("detailed", "smooth"):
        for seed in args.seeds:
            r, pp, info = render_subject(seed, app, args.preset, pxmm, size)
            results.append({"subject": info, "pupils_px": pp.tolist(), "spectrum": measure(r, pp, pxmm, pupils, pxmm)})
            if (app == "detailed" and seed in args.seeds[:3]) or (app == "smooth" and seed == args.seeds[0]):
                tiles.append((r, pp))
    side_by_side(img, pupils, tiles, args.image)
    try:
        image_rel = str(args.image.resolve().relative_to(args.out.resolve().parent))
        image_rel = "../" + image_rel
    except ValueError:
        image_rel = str(args.image)
    doc = {
        "command": "python benchmarks/synth_spectrum.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": f"{platform.processor() or platform.machine()}, Python {platform.python_version()}",
        "wall_s": time.time() - t0,
        "band_cycles_per_mm": list(BAND),
        "bin_cycles_per_mm": BIN,
        "seeds": args.seeds,
        "preset": args.preset,
        "photo": {"source": PHOTO, "pupils_px": [list(p) for p in PHOTO_PUPILS], "ipd_px": float(np.linalg.norm(pupils[1] - pupils[0])),
                  "ipd_mm": IPD_MM, "px_per_mm": pxmm, "spectrum": photo_doc},
        "subjects": results,
        "image": _repo_relative(args.image),
        "image_rel": image_rel,
    }
    doc["summary"] = summarise(results, photo_doc)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out / "synth_spectrum.json", doc)
    atomic_write_text(args.out / "synth_spectrum.md", markdown(doc))
    print(markdown(doc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
