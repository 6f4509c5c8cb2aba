"""What an avatar shows from behind: the face's and the mouth's surfels seen through the back of the head.

Usage:
    python benchmarks/back_views.py WS[:STAGE[:LABEL]] [WS[:STAGE[:LABEL]] ...] [--from 140] [--to 220]
        [--step 10] [--threshold 0.25] [--panels FILE.png] [--angles 30,90,180] [--scale 2] [--out FILE.json]

A single camera never sees the back of the head, and a capture without views there (one photo, a
head-turn clip) has nothing to score it against. What can be measured without a truth is what a
closed head never shows from behind: the inside of the face. Each avatar (STAGE defaults to
``phase2``) is posed at its capture's canonical timestep and rendered from an orbit about the head
at the reference camera's distance and focal length, as ``sage reenact --orbit`` frames it, at the
angles ``--from`` to ``--to``; 0° is the orbit view nearest the direction the face looks in (from the
centroid of all surfels to that of the face's), 180° the back of the head. A render of the
surfels with their colours replaced by markers of their region gives per pixel the share of the
colour that the face's surfels (regions ``face`` and ``eyes``) and the mouth's (``mouth``: lips, mouth
interior, teeth) make. Per angle it counts the foreground pixels (accumulated opacity above one half)
and those where the face's or the mouth's share exceeds ``--threshold``; the table gives both as a
percentage of the foreground over all angles. Within 40° of the back the mouth's share should be
zero, the face's near zero (the cheek in front of the ear shows at the outline from 140°).

``--panels`` writes one image: per avatar a row of its renders at ``--angles`` and a row with its
surfels coloured by region (face peach, eyes blue, mouth red, hair brown, neck green, the rest of
the scalp grey). ``--out`` writes the per-angle counts as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

REGION_COLORS = ((0.6, 0.6, 0.6), (1.0, 0.7, 0.5), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.5, 0.3, 0.1), (0.0, 0.8, 0.0))
"""Panel colours by region label (other, face, eyes, mouth, hair, neck; ``sage_core.avatar.init.REGION_NAMES``)."""


def parse_item(item: str) -> tuple[Path, str, str]:
    """``WS[:STAGE[:LABEL]]`` -> (workspace, stage, label); the label defaults to the folder's name."""
    parts = item.split(":")
    ws = Path(parts[0])
    stage = parts[1] if len(parts) > 1 and parts[1] else "phase2"
    label = parts[2] if len(parts) > 2 and parts[2] else ws.name
    return ws, stage, label


def orbit_renders(ws: Path, stage: str, angles: list[float], panel_angles: list[float]) -> dict[float, dict[str, Any]]:
    """Angle -> renders, for every angle of ``angles`` and ``panel_angles``: ``share`` (H, W, 3) the
    face's and the mouth's share of the colour and the accumulated opacity, and at the panel angles
    ``color`` (H, W, 3) the render on white and ``regions`` (H, W, 3) the surfels in their region
    colours."""
    import torch

    from sage_core.avatar.init import REGION_EYES, REGION_FACE, REGION_MOUTH
    from sage_core.data.dataset import IngestedData
    from sage_core.render import RenderCamera, rasterize_surfels
    from sage_core.stages.avatars import head_center, load_stage_avatar, reference_camera
    from sage_core.stages.reenact import orbit_around
    from sage_core.workspace import Workspace

    w = Workspace(ws)
    data = IngestedData.open(w.stage_dir("ingest"))
    av = load_stage_avatar(w, stage, data, torch.device("cpu")).avatar
    centre = head_center(data)
    cams, _ = orbit_around(reference_camera(data, None), centre, 360, 360.0, 0.0)
    with torch.no_grad():
        p = av.posed(av.frame_inputs(data.canonical_timestep), None)
    reg = av.surfels.region_id.long()
    face = (reg == REGION_FACE) | (reg == REGION_EYES)
    # 0° faces the face: the orbit camera nearest the direction from the surfels' centroid to the face's
    means = p.means.detach().double().cpu().numpy()
    forward = means[face.cpu().numpy()].mean(0) - means.mean(0)
    dirs = np.stack([c.center - centre for c in cams])
    first = int(np.argmax(dirs @ forward / np.maximum(np.linalg.norm(dirs, axis=1), 1e-12)))
    marker = torch.stack([face.float(), (reg == REGION_MOUTH).float(), torch.ones_like(face, dtype=torch.float32)], -1)
    palette = torch.tensor(REGION_COLORS, dtype=torch.float32)[reg.clamp(0, len(REGION_COLORS) - 1)]
    out: dict[float, dict[str, Any]] = {}
    for a in sorted({float(v) for v in angles} | {float(v) for v in panel_angles}):
        cam = RenderCamera.from_camera(cams[(first + int(round(a))) % 360], torch.device("cpu"))

        def draw(colors: torch.Tensor, background: float) -> np.ndarray:
            with torch.no_grad():
                r = rasterize_surfels(p.means, p.quats, p.scales, p.opacities, colors, cam, background,
                                      near=0.01, far=100.0, return_statistics=False)  # fmt: skip
            return r.color.clamp(0, 1).numpy()

        rec: dict[str, Any] = {"share": draw(marker, 0.0)}
        if a in panel_angles:
            rec["color"] = draw(p.colors.float(), 1.0)
            rec["regions"] = draw(palette, 1.0)
        out[a] = rec
    return out


def count(share: np.ndarray, threshold: float) -> dict[str, int]:
    """Foreground pixels of one marker render (H, W, 3), and those where the face's / the mouth's
    share exceeds ``threshold``."""
    fg = share[..., 2] > 0.5
    return {"foreground": int(fg.sum()), "face": int((fg & (share[..., 0] > threshold)).sum()),
            "mouth": int((fg & (share[..., 1] > threshold)).sum())}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("items", nargs="+", help="WS[:STAGE[:LABEL]] (stage: phase2 by default)")
    ap.add_argument("--from", dest="start", type=float, default=140.0, help="first orbit angle (degrees, 180 = the back)")
    ap.add_argument("--to", dest="stop", type=float, default=220.0, help="last orbit angle (degrees)")
    ap.add_argument("--step", type=float, default=10.0, help="degrees between orbit views")
    ap.add_argument("--threshold", type=float, default=0.25, help="share of a pixel's colour that counts as showing")
    ap.add_argument("--panels", type=Path, default=None, help="PNG with each avatar's renders and region colours")
    ap.add_argument("--angles", default="30,90,180", help="orbit angles of the panels (comma-separated)")
    ap.add_argument("--scale", type=int, default=2, help="panel upscaling")
    ap.add_argument("--out", type=Path, default=None, help="per-angle counts as JSON")
    args = ap.parse_args(argv)
    if args.step <= 0 or args.stop < args.start or not 0.0 < args.threshold < 1.0:
        print("error: need --step > 0, --to >= --from and 0 < --threshold < 1", file=sys.stderr)
        return 2
    items = [parse_item(i) for i in args.items]
    for ws, _, _ in items:
        if not (ws / "data").is_dir():
            print(f"error: {ws}: not a workspace (no data/ folder)", file=sys.stderr)
            return 2
    angles = [float(a) for a in np.arange(args.start, args.stop + 1e-9, args.step)]
    panel_angles = [float(a) for a in args.angles.split(",")] if args.panels else []
    doc: dict[str, Any] = {"angles": [float(a) for a in angles], "threshold": args.threshold, "avatars": {}}
    rows = []
    print("| avatar | views | foreground px | face shows | mouth shows |\n|---|---|---|---|---|")
    for ws, stage, label in items:
        renders = orbit_renders(ws, stage, angles, panel_angles)
        recs = [{"angle": float(a), **count(renders[float(a)]["share"], args.threshold)} for a in angles]
        tot = {k: sum(r[k] for r in recs) for k in ("foreground", "face", "mouth")}
        fg = max(tot["foreground"], 1)
        doc["avatars"][label] = {"workspace": ws.name, "stage": stage, "per_angle": recs, "total": tot,
                                 "face_percent": 100.0 * tot["face"] / fg, "mouth_percent": 100.0 * tot["mouth"] / fg}  # fmt: skip
        print(f"| {label} | {len(angles)} | {tot['foreground']} | {100.0 * tot['face'] / fg:.2f} % | {100.0 * tot['mouth'] / fg:.2f} % |")
        if panel_angles:
            rows.append(np.concatenate([renders[a]["color"] for a in panel_angles], 1))
            rows.append(np.concatenate([renders[a]["regions"] for a in panel_angles], 1))
    if args.panels:
        import imageio.v3 as iio

        width = max(r.shape[1] for r in rows)  # captures of other sizes: rows padded with white
        rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
        img = (np.concatenate(rows, 0) * 255.0 + 0.5).astype(np.uint8)
        k = max(int(args.scale), 1)
        args.panels.parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(args.panels, img.repeat(k, 0).repeat(k, 1))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
