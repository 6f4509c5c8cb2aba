"""Fit the mouth-interior prior that ships with sage (``sage_core/avatar/mouth_prior.safetensors``).

Usage:
    python benchmarks/train_mouth_prior.py [--out FILE] [--seeds 1000-1015] [--size 64x48]
        [--jaw 0.12,0.22,0.32] [--yaw -40,-20,0,20,40] [--pitch -10,5]

For every seed, a detailed synthetic subject (``sage synth --appearance detailed`` with that seed and
exact tracking: the written model is the truth's geometry) is posed with each jaw opening and seen
by small cameras aimed at its mouth from each yaw and pitch. sage's mouth interior is appended to
its written model as ``sage init-mesh`` appends it (cavity, teeth and tongue) and rasterized with
the same camera. Every pixel where that mesh shows a mouth-interior or teeth face and the truth
covers the pixel gives one sample: the truth's albedo there in sage's convention (its colour divided
by the truth's Lambert + ambient shading at its normal relative to that shading's mean over the
sphere, as sage's light has mean irradiance 1) at the mouth coordinates of the point sage's mesh shows,
in the grid of that face's part (:mod:`sage_core.avatar.mouth_prior`). Each grid node holds the
trilinearly weighted mean of its samples; nodes without samples take the mean of their nearest
sampled neighbours. The result is deterministic in the arguments.

The benchmark subjects use seeds 0 and 1 (``benchmarks/suite.py``); the default seeds here,
1000-1015, keep well away. The file records its provenance (this script, its arguments, the seeds,
the number of samples and the sage version).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

DEFAULT_SEEDS = "1000-1015"


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        if "-" in part.strip()[1:]:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part.strip():
            out.append(int(part))
    return out


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python benchmarks/train_mouth_prior.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="output file (default: the package's mouth_prior.safetensors)")
    ap.add_argument("--seeds", default=DEFAULT_SEEDS, help="synthetic subjects: a list and/or ranges, e.g. 1000-1015")
    ap.add_argument("--size", default="64x48", help="image size of the mouth cameras, WxH")
    ap.add_argument("--jaw", default="0.12,0.22,0.32", help="jaw openings (rad)")
    ap.add_argument("--yaw", default="-40,-20,0,20,40", help="camera yaws about the head's vertical axis (deg)")
    ap.add_argument("--pitch", default="-10,5", help="camera pitches (deg, positive from above)")
    ap.add_argument("--grid", default=None, help="grid nodes X,Y,Z (default: sage_core.avatar.mouth_prior.GRID_SHAPE)")
    return ap


def _mouth_camera(centre: np.ndarray, yaw: float, pitch: float, width: int, height: int, distance: float = 0.35,
                  field_m: float = 0.06):
    from sage_core.data.cameras import Camera, look_at

    y, p = np.deg2rad(yaw), np.deg2rad(pitch)
    eye = centre + distance * np.array([np.sin(y) * np.cos(p), np.sin(p), np.cos(y) * np.cos(p)])
    f = width * distance / field_m
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(eye, centre), width, height)


def subject_samples(seed: int, jaws: list[float], yaws: list[float], pitches: list[float], width: int, height: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of one synthetic subject: ((S, 3) mouth coordinates, (S,) parts, (S, 3) albedo)."""
    import torch

    from sage_core.avatar.mouth_prior import face_parts, mouth_coordinates
    from sage_core.data.synthetic.appearance import render_head
    from sage_core.data.synthetic.capture import make_subject
    from sage_core.data.synthetic.config import preset
    from sage_core.data.synthetic.model_files import flame_model_data
    from sage_core.data.synthetic.shading import AMBIENT, DIFFUSE, LIGHT_DIR
    from sage_core.flame import FlameModel, Regions, add_mouth_interior
    from sage_core.flame.mouth import lip_ids, mouth_frame
    from sage_core.render.mesh_raster import rasterize_mesh

    cfg = replace(preset("tiny", "multiview", seed=seed), appearance="detailed", tracking="exact")
    subj = make_subject(cfg)
    head = subj.head
    base = flame_model_data(head)
    masks = {k: np.asarray(v) for k, v in head.masks.items()}
    model = add_mouth_interior(base, masks, cavity=True, tongue=True)
    regions = Regions(masks, model.faces, model.n_vertices, model.vertex_groups)
    parts = face_parts(model, regions)
    fl = FlameModel(model).double()
    V = head.n_vertices
    offset = np.zeros((model.n_vertices, 3))
    offset[:V] = subj.static_offset
    shape = torch.as_tensor(subj.shape, dtype=torch.float64)
    off = torch.as_tensor(offset, dtype=torch.float64)
    with torch.no_grad():
        canon = fl(shape=shape, static_offset=off).vertices[0].numpy()
    origin, w = mouth_frame(canon, lip_ids(regions, model.n_base_vertices), model.lbs_weights)
    faces_t = torch.as_tensor(model.faces)
    coords, part_out, albedo = [], [], []
    for jaw in jaws:
        with torch.no_grad():
            posed = fl(shape=shape, static_offset=off, jaw_pose=torch.tensor([[jaw, 0.0, 0.0]], dtype=torch.float64)).vertices[0].numpy()
        hv = posed[:V]
        centre = posed[model.vertex_groups["mouth_lower"]].mean(0) * 0.5 + posed[model.vertex_groups["mouth_upper"]].mean(0) * 0.5
        for yaw in yaws:
            for pitch in pitches:
                cam = _mouth_camera(centre, yaw, pitch, width, height)
                r = render_head(head, hv, cam, subj.app, None, supersample=1, geometry=True, specular=None,
                                hair=subj.posed_hair(hv), mouth=subj.posed_mouth(hv))  # fmt: skip
                ras = rasterize_mesh(torch.as_tensor(posed, dtype=torch.float32), faces_t, torch.as_tensor(cam.K, dtype=torch.float32),
                                     torch.as_tensor(cam.w2c, dtype=torch.float32), width, height)  # fmt: skip
                fid = ras.face_id[0].numpy()
                bary = ras.bary[0].numpy().astype(np.float64)
                ok = (fid >= 0) & (r.alpha > 0.999)
                ok[ok] = parts[fid[ok]] >= 0
                if not ok.any():
                    continue
                f = fid[ok]
                p = (bary[ok][:, :, None] * canon[model.faces[f]]).sum(1)
                # sage's albedo convention: the light's irradiance has mean 1 over the sphere, so the
                # truth's shading is taken relative to its own mean (ambient + diffuse / 4)
                shade = (AMBIENT + DIFFUSE * np.clip(r.normal[ok].astype(np.float64) @ LIGHT_DIR, 0.0, None)) / (AMBIENT + 0.25 * DIFFUSE)
                coords.append(mouth_coordinates(p, origin, w))
                part_out.append(parts[f])
                albedo.append(np.clip(r.rgb[ok].astype(np.float64) / shade[:, None], 0.0, 1.0))
    if not coords:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(coords), np.concatenate(part_out), np.concatenate(albedo)


def fit_grids(coords: np.ndarray, parts: np.ndarray, albedo: np.ndarray, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear splatting of the samples into grids, then the empty nodes filled from their
    neighbours. Returns ((P, X, Y, Z, 3) colour, (P, X, Y, Z) weight)."""
    from sage_core.avatar.mouth_prior import BOX_HI, BOX_LO, PARTS

    n = np.array(shape)
    lo, hi = np.array(BOX_LO), np.array(BOX_HI)
    P = len(PARTS)
    acc = np.zeros((P, *shape, 3))
    wsum = np.zeros((P, *shape))
    t = np.clip((coords - lo) / (hi - lo) * (n - 1), 0.0, n - 1 - 1e-9)
    i0 = np.floor(t).astype(np.int64)
    f = t - i0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                wgt = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (f[:, 2] if dz else 1 - f[:, 2])
                idx = (parts, i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz)
                np.add.at(wsum, idx, wgt)
                np.add.at(acc, idx, wgt[:, None] * albedo)
    color = np.zeros_like(acc)
    seen = wsum > 1e-6
    color[seen] = acc[seen] / wsum[seen][:, None]
    overall = albedo.mean(0) if albedo.size else np.full(3, 0.3)
    for p in range(P):
        if not seen[p].any():
            color[p] = overall
            continue
        known = seen[p].copy()
        c = color[p]
        while not known.all():  # grow the sampled region one node at a time (6-neighbourhood mean)
            s = np.zeros(c.shape)
            k = np.zeros(known.shape)
            for ax in range(3):
                for d in (1, -1):
                    kk = np.roll(known, d, ax)
                    cc = np.roll(c * known[..., None], d, ax)
                    edge = [slice(None)] * 3
                    edge[ax] = 0 if d == 1 else -1
                    kk[tuple(edge)] = False
                    cc[tuple(edge)] = 0.0
                    s += cc
                    k += kk
            grow = ~known & (k > 0)
            c[grow] = s[grow] / k[grow][:, None]
            known |= grow
    return color.astype(np.float32), wsum.astype(np.float32)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from sage_core._version import __version__
    from sage_core.avatar.mouth_prior import GRID_SHAPE, PRIOR_FILE, MouthPrior, save_mouth_prior

    seeds = _seeds(args.seeds)
    bad = [s for s in seeds if s in (0, 1)]
    if bad:
        print(f"error: seeds {bad} are the benchmark's subjects; the prior must not see them", file=sys.stderr)
        return 2
    width, height = (int(v) for v in args.size.lower().split("x"))
    jaws, yaws, pitches = _floats(args.jaw), _floats(args.yaw), _floats(args.pitch)
    grid = tuple(int(v) for v in args.grid.split(",")) if args.grid else GRID_SHAPE
    t0 = time.time()
    C, Pt, A = [], [], []
    for s in seeds:
        c, p, a = subject_samples(s, jaws, yaws, pitches, width, height)
        C.append(c)
        Pt.append(p)
        A.append(a)
        print(f"seed {s}: {len(p)} samples ({time.time() - t0:.0f} s)", flush=True)
    coords, parts, albedo = np.concatenate(C), np.concatenate(Pt), np.concatenate(A)
    color, weight = fit_grids(coords, parts, albedo, grid)
    out = args.out or PRIOR_FILE
    cmd = "python benchmarks/train_mouth_prior.py" + "".join(f" {a}" for a in (argv if argv is not None else sys.argv[1:]) if a)
    provenance = {"script": "benchmarks/train_mouth_prior.py", "command": cmd, "seeds": seeds, "jaw": jaws, "yaw_deg": yaws,
                  "pitch_deg": pitches, "image_size": [width, height], "grid": list(grid), "samples": int(len(parts)),
                  "samples_per_part": [int((parts == i).sum()) for i in range(color.shape[0])], "sage_version": __version__,
                  "albedo": "colour / (shading / its mean over the sphere): sage's convention, mean irradiance 1",
                  "subjects": "sage synth --appearance detailed --tracking exact --preset tiny --seed S (benchmark subjects: seeds 0 and 1)"}  # fmt: skip
    save_mouth_prior(out, MouthPrior(color, weight, provenance=provenance))
    print(f"wrote {out} ({Path(out).stat().st_size} bytes, {len(parts)} samples, {time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
