"""Where the error of an evaluated avatar falls: silhouette band, inside, face regions.

Usage:
    python benchmarks/error_regions.py WS:STAGE[:LABEL] [WS:STAGE[:LABEL] | ceiling:CAPTURE ...]
        [--split train|test|val] [--cams 2,8,12] [--panels DIR] [--scale 3] [--out FILE.json]
        [--lpips WEIGHTS] [--timesteps 2,4] [--min-jaw 0.1]

Every avatar renders every frame of the split as ``sage eval`` renders it (the stage's render
settings, surfel correction included) and is compared with the ground-truth image;
``ceiling:CAPTURE`` adds the tracking ceiling of the synthetic capture the workspaces were ingested
from (its ground-truth appearance on the tracked FLAME fit, :mod:`sage_core.evaluate.ceiling`).
The first item must be an avatar. Per image, the
sum of squared errors over the pixels and the three channels (SSE) is split by where it falls:

* ``band``: pixels within 2 px of the ground-truth silhouette (the mask dilated minus the mask eroded,
  3×3 steps); ``inside``: the eroded mask;
* inside, by the region of the triangle the FIRST avatar's posed FLAME mesh shows at the pixel
  (``init/regions.json`` of its workspace): ``mouth`` (lips, mouth interior, teeth), ``eyes``
  (eyeballs, eye regions), ``hair``, ``neck`` and ``skin`` (everything else);
* ``silhouette``: pixels where that posed mesh covers the image and the ground-truth mask does not,
  or the reverse. With tracked FLAME parameters this is error no avatar drawn on the tracked mesh
  can avoid; it overlaps ``band``.

With ``--lpips`` (the AlexNet v0.1 weights), LPIPS is split the same way, by composites: for each of
the disjoint areas ``band``, ``mouth`` (inside pixels where the posed mesh shows the mouth group,
dilated by 2 px, kept inside), ``rest`` (the other inside pixels) and ``outside`` (the rest of the
image), the image that is the render in that area and the ground truth everywhere else is scored
against the ground truth (``lpips_band``, ``lpips_mouth``, ``lpips_rest``, ``lpips_outside``, beside
``lpips`` of the whole render). LPIPS is not additive, so these do not sum to ``lpips``; each says how
far the render's errors in one area alone are perceptually from the truth.

``--timesteps`` keeps the frames of the listed timesteps; ``--min-jaw`` those whose tracked jaw
opening (the first, opening component of the jaw pose, radians) is at least the value: the open-jaw
frames, where the mouth interior shows.

The workspaces must share the data (the same capture and split). Prints a Markdown table of the mean
SSE per image (and of the LPIPS split); ``--out`` writes the per-image values as JSON; ``--panels`` writes, for the frames of
``--cams``, the ground truth, each avatar's render and its error (upscaled by ``--scale``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

GROUPS: dict[str, tuple[str, ...]] = {
    "mouth": ("lips", "mouth_interior", "teeth", "mouth_lower", "mouth_upper"),
    "eyes": ("eyeballs", "eye_region"),
    "hair": ("hair",),
    "neck": ("neck",),
}
"""Region groups of the inside error (``skin`` is every other face)."""

COLUMNS = ("total", "band", "inside", *GROUPS, "skin", "silhouette")

LPIPS_AREAS = ("band", "mouth", "rest", "outside")
"""Disjoint areas of the ``--lpips`` composites (see the module doc)."""


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python benchmarks/error_regions.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("items", nargs="+", help="WS:STAGE[:LABEL] (stage phase1 or phase2), or ceiling:CAPTURE")
    ap.add_argument("--split", default="test", choices=("train", "test", "val"), help="role of the ingested frames (train: the views the avatar was fitted to)")
    ap.add_argument("--cams", default="2,8,12", help="camera indices of the panels")
    ap.add_argument("--panels", type=Path, default=None, help="folder for GT | renders | errors panels")
    ap.add_argument("--scale", type=int, default=3, help="panel upscaling")
    ap.add_argument("--out", type=Path, default=None, help="JSON file of the per-image values")
    ap.add_argument("--lpips", type=Path, default=None, help="LPIPS AlexNet v0.1 weights: also split LPIPS by area")
    ap.add_argument("--timesteps", default=None, help="comma-separated timesteps: only their frames")
    ap.add_argument("--min-jaw", type=float, default=None, help="only frames whose tracked jaw opening is at least this (rad)")
    return ap


def _dilate(area: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool area grown by ``radius`` px (square structuring element)."""
    import torch

    m = torch.as_tensor(area, dtype=torch.float32)[None, None]
    return (torch.nn.functional.max_pool2d(m, 2 * radius + 1, 1, radius)[0, 0] > 0).numpy()


def _band_and_inside(mask: np.ndarray, radius: int = 2) -> tuple[np.ndarray, np.ndarray]:
    fg = mask > 0.5
    dil, ero = _dilate(fg, radius), ~_dilate(~fg, radius)
    return dil & ~ero, ero


def _lpips_areas(band: np.ndarray, inside: np.ndarray, group: np.ndarray, radius: int = 2) -> dict[str, np.ndarray]:
    """The disjoint (H, W) bool areas of :data:`LPIPS_AREAS`: group (H, W) is the posed mesh's region
    group per pixel (0 = mouth, -1 = background)."""
    mouth = _dilate(group == 0, radius) & inside
    return {"band": band, "mouth": mouth, "rest": inside & ~mouth, "outside": ~band & ~inside}


def _face_labels(regions_path: Path) -> np.ndarray:
    """(F + 1,) group index of every face (len(GROUPS) = skin); the last entry serves the background."""
    reg = json.loads(regions_path.read_text())
    labels = np.full(int(reg["n_faces"]) + 1, len(GROUPS))
    for gi, names in enumerate(GROUPS.values()):
        for name in names:
            labels[np.asarray(reg["face_sets"].get(name, []), dtype=np.int64)] = gi
    return labels


def select_frames(data: Any, frames: list[Any], timesteps: str | None, min_jaw: float | None) -> list[Any]:
    """The frames of ``timesteps`` (comma-separated, None: all) whose tracked jaw opening is at least
    ``min_jaw`` (None: any)."""
    keep = None if timesteps is None else {int(t) for t in timesteps.split(",") if t.strip()}
    out = []
    for fr in frames:
        if keep is not None and fr.timestep not in keep:
            continue
        if min_jaw is not None and float(np.asarray(data.params.jaw_pose)[data.params.row_of(fr.timestep)][0]) < min_jaw:
            continue
        out.append(fr)
    return out


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import torch

    from sage_core.data.dataset import IngestedData
    from sage_core.data.imageio import write_image
    from sage_core.render import RenderCamera
    from sage_core.render.mesh_raster import rasterize_mesh
    from sage_core.stages.avatars import AvatarRenderer, load_stage_avatar
    from sage_core.workspace import Workspace

    torch.set_num_threads(1)
    lpips = None
    if args.lpips is not None:
        from sage_core.evaluate.lpips import LPIPS
        from sage_core.image_metrics import to_nchw

        lpips = LPIPS.from_path(args.lpips)

    def lp(xs: list[np.ndarray], gt: np.ndarray) -> list[float]:
        """LPIPS of each (H, W, 3) image in xs against gt, in one batch."""
        assert lpips is not None
        pred = to_nchw(np.stack(xs).astype(np.float32))
        return [float(v) for v in lpips(pred, to_nchw(gt.astype(np.float32)).expand_as(pred))]

    avatars: list[tuple[str, Callable[[Any], np.ndarray]]] = []
    data = None
    first: AvatarRenderer | None = None
    first_ws = None
    for item in args.items:
        parts = item.split(":")
        if len(parts) < 2:
            print(f"error: {item!r} is not WS:STAGE[:LABEL] or ceiling:CAPTURE", file=sys.stderr)
            return 2
        if parts[0] == "ceiling":
            if data is None:
                print("error: the first item must be an avatar (WS:STAGE)", file=sys.stderr)
                return 2
            from sage_core.data.synthetic.ceiling import TrackedTruth
            from sage_core.evaluate.ceiling import ceiling_render_fn

            fn = ceiling_render_fn(TrackedTruth.open(parts[1]), data)
            avatars.append(("ceiling", lambda fr, fn=fn: fn(fr).numpy()))
            continue
        ws = Workspace(parts[0])
        d = IngestedData.open(ws.stage_dir("ingest"))
        data = data or d
        first_ws = first_ws or ws
        sa = load_stage_avatar(ws, parts[1], d)
        rd = AvatarRenderer(sa.avatar, sa.render)
        first = first or rd
        avatars.append((parts[2] if len(parts) > 2 else f"{Path(parts[0]).name}/{parts[1]}",
                        lambda fr, rd=rd: rd.render(fr.camera, rd.avatar.frame_inputs(fr.timestep)).clamp(0, 1).cpu().numpy()))
    assert data is not None and first_ws is not None and first is not None
    labels = _face_labels(first_ws.stage_dir("init-mesh") / "regions.json")
    cams = {int(c) for c in args.cams.split(",") if c.strip()}
    per_image: dict[str, list[dict[str, Any]]] = {lab: [] for lab, _ in avatars}
    ref = first.avatar
    frames = select_frames(data, data.role(args.split), args.timesteps, args.min_jaw)
    if not frames:
        print("error: no frame of the split passes --timesteps / --min-jaw", file=sys.stderr)
        return 2
    with torch.no_grad():
        for fr in frames:
            gt = data.load_image(fr)
            mask = data.load_mask(fr) if fr.mask is not None else np.ones(gt.shape[:2], np.float32)
            band, inside = _band_and_inside(mask)
            cam = RenderCamera.from_camera(fr.camera, ref.device)
            verts = ref.pose_mesh(ref.frame_inputs(fr.timestep))
            fid = rasterize_mesh(verts, ref.faces, cam.K, cam.w2c, cam.width, cam.height).face_id[0].cpu().numpy()
            group = np.where(fid >= 0, labels[np.clip(fid, 0, labels.size - 1)], -1)
            sil = (fid >= 0) != (mask > 0.5)
            row, errs = [gt], []
            for lab, render in avatars:
                img = render(fr)
                e = ((img - gt) ** 2).sum(-1)
                rec = {"timestep": fr.timestep, "camera": fr.camera_index, "total": float(e.sum()), "band": float(e[band].sum()),
                       "inside": float(e[inside].sum()), "silhouette": float(e[sil].sum())}  # fmt: skip
                for gi, name in enumerate((*GROUPS, "skin")):
                    rec[name] = float(e[inside & (group == gi)].sum())
                if lpips is not None:
                    areas = _lpips_areas(band, inside, group)
                    vals = lp([img, *(np.where(areas[a][..., None], img, gt) for a in LPIPS_AREAS)], gt)
                    rec["lpips"] = vals[0]
                    rec.update({f"lpips_{a}": v for a, v in zip(LPIPS_AREAS, vals[1:])})
                per_image[lab].append(rec)
                row.append(img)
                errs.append(np.repeat(np.clip(np.sqrt(e / 3.0) * 3.0, 0, 1)[..., None], 3, -1))
            if args.panels is not None and fr.camera_index in cams:
                panel = np.concatenate([np.concatenate(row, 1), np.concatenate([np.zeros_like(gt), *errs], 1)], 0)
                write_image(args.panels / f"{args.split}_t{fr.timestep:05d}_c{fr.camera_index:02d}.png",
                            panel.repeat(args.scale, 0).repeat(args.scale, 1))
    means = {lab: {c: float(np.mean([r[c] for r in recs])) for c in COLUMNS} for lab, recs in per_image.items()}
    n = len(next(iter(per_image.values())))
    print(f"Mean SSE per image ({args.split} split, {n} images; band/inside split by the GT mask, inside by region):\n")
    print("| avatar | " + " | ".join(COLUMNS) + " |")
    print("|---|" + "---:|" * len(COLUMNS))
    for lab, m in means.items():
        print(f"| {lab} | " + " | ".join(f"{m[c]:.1f}" for c in COLUMNS) + " |")
    if lpips is not None:
        cols = ("lpips", *(f"lpips_{a}" for a in LPIPS_AREAS))
        for lab, recs in per_image.items():
            means[lab].update({c: float(np.mean([r[c] for r in recs])) for c in cols})
        print("\nMean LPIPS per image: of the render, and of the render in one area only (the ground truth elsewhere):\n")
        print("| avatar | all | " + " | ".join(f"{a} only" for a in LPIPS_AREAS) + " |")
        print("|---|" + "---:|" * len(cols))
        for lab, m in means.items():
            print(f"| {lab} | " + " | ".join(f"{m[c]:.4f}" for c in cols) + " |")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"split": args.split, "items": args.items, "mean": means, "images": per_image}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
