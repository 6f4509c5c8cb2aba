"""Evaluation on held-out ground truth: ``CAPTURE/gt/novel/`` (``sage synth --regime oneshot|monocular``).

The held-out set is a capture in the VHAP layout and the capture's world frame:
``transforms_val.json`` holds the training expression (the neutral face) seen from novel cameras
("views"), ``transforms_test.json`` novel expressions from the same cameras ("expressions"); each
timestep has its FLAME npz under ``flame_param/``. The capture folder is the ``source`` recorded in
the ingest summary. Images are resized like the ingested ones (the ratio of an ingested training
image to its source image) and put on the dataset background.

Every held-out frame is rendered with the avatar posed by the frame's FLAME parameters (the avatar
keeps its own shape and static offset; a view of its training timestep with that timestep's
parameters takes the avatar's own parameters of it, which phase 1's registration of the training
pose may have moved: :func:`held_out_inputs`) and compared with the ground truth twice:

* over the full image, exactly as the other splits (:mod:`.protocol`: PSNR, GA PSNR, SSIM, LPIPS);
* over the visible region: the pixels whose FLAME surface the training view(s) saw. Training
  visibility is per face: a face is visible when it wins the z-buffer at some pixel of a training
  frame's posed mesh rasterized at twice the training resolution. In a held-out frame, the posed
  mesh is rasterized from the held-out camera and a pixel belongs to the region when its face was
  visible in training. Region PSNR averages the squared error over the region's pixels × 3
  channels, region SSIM averages the full-image SSIM map over the region, and region LPIPS compares
  the two images with everything outside the region replaced by the background.

"frontal" is the held-out camera marked ``frontal_camera`` in ``gt/info.json`` (block ``novel``)
when present, else the held-out camera whose direction from the head centre is closest to a
training camera's.

View groups: when ``gt/info.json`` (block ``novel``) lists ``view_groups`` (group name -> camera
indices: "front", "side", "back" for captures with views all around the head), the report adds the
means of each group (full image and visible region) under ``view_groups``; captures without them
report no groups.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..data.cameras import Camera
from ..errors import InputError
from ..image_metrics import psnr, psnr_per_channel_mean, ssim, ssim_map
from .protocol import EvalReport, ImageMetrics, MetricMeans, _fmt, _lpips_device, error_strip, sample_indices, sample_refs

if TYPE_CHECKING:
    from ..avatar.model import Avatar
    from ..data.dataset import IngestedData
    from ..flame.params import FlameParams
    from .lpips import LPIPS

NOVEL_FOLDER = Path("gt") / "novel"
SUBSETS: dict[str, str] = {"val": "views", "test": "expressions"}
"""Held-out transforms split -> subset name (views: training expression, novel cameras;
expressions: novel expressions, novel cameras)."""
VISIBLE_DEFINITION = (
    "pixels of the held-out render whose posed FLAME face was visible (won the z-buffer at 2x resolution) "
    "in a training frame; PSNR over those pixels x 3 channels, SSIM map averaged over them, LPIPS with "
    "everything outside them set to the background"
)

NovelRenderFn = Callable[[Camera, dict[str, torch.Tensor]], torch.Tensor]
"""``render_fn(camera, flame_inputs) -> (H, W, 3)`` float tensor in [0, 1]."""
Progress = Callable[[int, int, str], None]


@dataclass
class NovelFrame:
    """One held-out image.

    subset: "views" or "expressions"; timestep: held-out timestep index (row ``row`` of the set's
    parameters); camera_index; image, mask: ground-truth files; camera: at the evaluation size.
    """

    subset: str
    timestep: int
    camera_index: int
    image: Path
    mask: Path | None
    camera: Camera
    row: int


@dataclass
class NovelSet:
    """The held-out ground truth of a capture.

    root: ``CAPTURE/gt/novel``; frames: held-out images (views first, then expressions); params:
    their FLAME parameters; frontal_camera, frontal_rule: the frontal camera and how it was chosen;
    background: 1.0 (white) or 0.0 (black); view_groups: group name -> camera indices (empty when
    the capture does not group its views).
    """

    root: Path
    frames: list[NovelFrame]
    params: FlameParams
    frontal_camera: int
    frontal_rule: str
    background: float = 1.0
    view_groups: dict[str, list[int]] = field(default_factory=dict)

    def fingerprint_files(self) -> list[Path]:
        """Files whose content defines the set (transforms of both subsets)."""
        return [p for p in (self.root / "transforms_val.json", self.root / "transforms_test.json") if p.is_file()]


def capture_folder(data: IngestedData) -> Path:
    """The capture folder recorded by ingest (``summary.json`` ``source``)."""
    src = data.summary.get("source")
    if not src:
        raise InputError(data.root / "summary.json", "does not record the capture folder ('source')")
    return Path(src)


def _size_ratio(data: IngestedData) -> tuple[float, float]:
    """(sx, sy) of the ingested images relative to their source images (1, 1 when unknown)."""
    from ..data.imageio import image_size

    try:
        doc = json.loads((data.root / "frames.json").read_text(encoding="utf-8"))
        entry = next(e for e in doc["frames"] if e.get("role") == "train" and e.get("source_image"))
        w, h = image_size(entry["source_image"])[:2]
        cam = entry["camera"]
        return float(cam["width"]) / float(w), float(cam["height"]) / float(h)
    except (OSError, StopIteration, KeyError, TypeError, ValueError, json.JSONDecodeError, InputError):
        return 1.0, 1.0


def _view_groups(info_path: Path, cameras: dict[int, Camera]) -> dict[str, list[int]]:
    """``novel.view_groups`` of ``gt/info.json`` restricted to the held-out cameras (empty when the
    file or the block is missing or unreadable)."""
    try:
        groups = json.loads(info_path.read_text(encoding="utf-8")).get("novel", {}).get("view_groups") or {}
        out = {str(g): sorted(int(c) for c in cams if int(c) in cameras) for g, cams in groups.items()}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}
    return {g: c for g, c in out.items() if c}


def _frontal(data: IngestedData, cameras: dict[int, Camera], info_path: Path) -> tuple[int, str]:
    if info_path.is_file():
        try:
            info = json.loads(info_path.read_text(encoding="utf-8"))
            marked = info.get("novel", {}).get("frontal_camera")
            if marked is not None and int(marked) in cameras:
                return int(marked), f"marked frontal in {info_path.name}"
        except (OSError, ValueError, AttributeError, TypeError):
            pass
    box = data.summary.get("head_bbox")
    centre = 0.5 * (np.asarray(box[0], float) + np.asarray(box[1], float)) if box else np.zeros(3)

    def unit(c: Camera) -> np.ndarray:
        d = c.center - centre
        return d / max(float(np.linalg.norm(d)), 1e-12)

    train = [unit(f.camera) for f in data.train]
    best, best_cos = None, -2.0
    for ci in sorted(cameras):
        u = unit(cameras[ci])
        cos = max(float(u @ t) for t in train)
        if cos > best_cos + 1e-12:
            best, best_cos = ci, cos
    assert best is not None
    angle = math.degrees(math.acos(max(-1.0, min(1.0, best_cos))))
    return best, f"closest to a training camera ({angle:.1f} deg from it, seen from the head centre)"


_FRAME_KEYS = ("timestep_index", "camera_index", "w", "h", "fl_x", "fl_y", "cx", "cy", "transform_matrix",
               "file_path", "flame_param_path")


def _read_novel_frames(root: Path) -> tuple[list[tuple[str, int, int, Path, Path | None, Camera]], FlameParams]:
    """Frames (subset, timestep, camera index, image, mask, camera) of ``transforms_{val,test}.json``
    and their stacked FLAME parameters; InputError naming the file for anything malformed."""
    from ..data.cameras import camera_from_nerf_frame
    from ..flame.params import load_param_npz, stack_params

    out: list[tuple[str, int, int, Path, Path | None, Camera]] = []
    param_files: dict[int, Path] = {}
    for split, subset in SUBSETS.items():
        jpath = root / f"transforms_{split}.json"
        if not jpath.is_file():
            continue
        try:
            doc = json.loads(jpath.read_text(encoding="utf-8"))
            items = doc["frames"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise InputError(jpath, f"not a readable transforms file ({type(e).__name__}: {e})") from None
        for i, fr in enumerate(items):
            try:
                missing = [k for k in _FRAME_KEYS if k not in fr]
                if missing:
                    raise KeyError(", ".join(missing))
                cam = camera_from_nerf_frame(fr)
                ti, ci = int(fr["timestep_index"]), int(fr["camera_index"])
                image = (jpath.parent / fr["file_path"]).resolve()
                mask = (jpath.parent / fr["fg_mask_path"]).resolve() if fr.get("fg_mask_path") else None
                par = (jpath.parent / fr["flame_param_path"]).resolve()
            except (KeyError, TypeError, ValueError, AttributeError, np.linalg.LinAlgError) as e:
                raise InputError(jpath, f"frame {i} is malformed ({type(e).__name__}: {e})") from None
            if not image.is_file():
                raise InputError(image, "held-out image not found")
            if mask is not None and not mask.is_file():
                mask = None
            if param_files.setdefault(ti, par) != par:
                raise InputError(jpath, f"timestep {ti} names two FLAME files: {param_files[ti]} and {par}")
            out.append((subset, ti, ci, image, mask, cam))
    if not out:
        raise InputError(root, "lists no held-out frames")
    loaded, sources = [], []
    for ti in sorted(param_files):
        prm = load_param_npz(param_files[ti])
        if prm.n_timesteps != 1:
            raise InputError(param_files[ti], f"per-timestep FLAME file holds {prm.n_timesteps} rows, expected 1")
        prm.timesteps = np.array([ti], dtype=np.int64)
        loaded.append(prm)
        sources.append(param_files[ti])
    return out, stack_params(loaded, sources)


def has_novel_ground_truth(data: IngestedData) -> bool:
    """Whether the capture the data was ingested from has held-out ground truth (``gt/novel`` with
    a transforms file), without reading it."""
    src = data.summary.get("source")
    if not src:
        return False
    root = Path(src) / NOVEL_FOLDER
    return root.is_dir() and any((root / f"transforms_{s}.json").is_file() for s in SUBSETS)


def open_novel_set(data: IngestedData, n_vertices: int | None = None, n_base_vertices: int | None = None) -> NovelSet:
    """Read ``CAPTURE/gt/novel`` for the ingested data.

    n_vertices, n_base_vertices: the avatar model's vertex counts, to fit any per-vertex offsets of
    the held-out parameters. Raises InputError naming the folder when the capture has no held-out
    ground truth, or naming the offending file when it is malformed.
    """
    from ..data.capture import fit_params_to_model

    cap_root = capture_folder(data)
    root = cap_root / NOVEL_FOLDER
    if not root.is_dir():
        raise InputError(root, "the capture has no held-out ground truth (gt/novel/, written by "
                               "`sage synth --regime oneshot|monocular`); --split novel needs it")
    if not any((root / f"transforms_{s}.json").is_file() for s in SUBSETS):
        raise InputError(root, "holds neither transforms_val.json nor transforms_test.json")
    entries, params = _read_novel_frames(root)
    if n_vertices is not None and n_base_vertices is not None and params.n_offset_vertices is not None:
        try:
            params = fit_params_to_model(params, n_vertices, n_base_vertices)
        except ValueError as e:
            raise InputError(root / "flame_param", str(e)) from None
    sx, sy = _size_ratio(data)
    frames: list[NovelFrame] = []
    cams: dict[int, Camera] = {}
    for subset, ti, ci, image, mask, camera in entries:
        w = max(1, int(math.floor(camera.width * sx + 0.5)))
        h = max(1, int(math.floor(camera.height * sy + 0.5)))
        cam = camera.resized(w, h) if (w, h) != (camera.width, camera.height) else camera
        frames.append(NovelFrame(subset, ti, ci, image, mask, cam, params.row_of(ti)))
        cams.setdefault(ci, cam)
    if not frames:
        raise InputError(root, "lists no held-out frames")
    frontal, rule = _frontal(data, cams, cap_root / "gt" / "info.json")
    bg = 0.0 if str(data.summary.get("background", "white")) == "black" else 1.0
    return NovelSet(root, frames, params, frontal, rule, bg, _view_groups(cap_root / "gt" / "info.json", cams))


def load_novel_image(novel: NovelSet, frame: NovelFrame) -> np.ndarray:
    """(H, W, 3) float32 ground truth at the evaluation size, on the set's background."""
    import cv2

    from ..data.imageio import read_image

    img = read_image(frame.image)
    if img.shape[2] == 4:
        a = img[:, :, 3:4]
        img = img[:, :, :3] * a + (1.0 - a)
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    img = np.ascontiguousarray(img[:, :, :3], dtype=np.float32)
    if novel.background == 0.0:
        if frame.mask is None:
            raise InputError(frame.image, "a black background needs the held-out foreground mask, but it has none")
        m = read_image(frame.mask)
        m = m[:, :, 3 if m.shape[2] == 4 else 0]
        img = np.clip(img - (1.0 - m)[:, :, None], 0.0, 1.0)
    size = (frame.camera.width, frame.camera.height)
    if (img.shape[1], img.shape[0]) != size:
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    return img


def _rasterize_faces(avatar: Avatar, flame_inputs: dict[str, torch.Tensor], camera: Camera, scale: int = 1) -> torch.Tensor:
    """(H·scale, W·scale) face ids of the posed mesh."""
    from ..render.mesh_raster import rasterize_mesh

    cam = camera.resized(camera.width * scale, camera.height * scale) if scale > 1 else camera
    with torch.no_grad():
        verts = avatar.pose_mesh(flame_inputs)
        K = torch.as_tensor(cam.K, dtype=verts.dtype, device=verts.device)
        w2c = torch.as_tensor(cam.w2c, dtype=verts.dtype, device=verts.device)
        return rasterize_mesh(verts, avatar.faces, K, w2c, cam.width, cam.height).face_id[0]


def training_face_visibility(avatar: Avatar, data: IngestedData, scale: int = 2) -> torch.Tensor:
    """(F,) bool: faces of the avatar's mesh that win the z-buffer at some pixel of a training frame
    (posed with the frame's FLAME parameters, rasterized at ``scale``× the training resolution)."""
    vis = torch.zeros(avatar.faces.shape[0], dtype=torch.bool, device=avatar.device)
    inputs: dict[int, dict[str, torch.Tensor]] = {}
    for fr in data.train:
        if fr.timestep not in inputs:
            inputs[fr.timestep] = avatar.frame_inputs(fr.timestep)
        fid = _rasterize_faces(avatar, inputs[fr.timestep], fr.camera, scale)
        vis[fid[fid >= 0].unique()] = True
    return vis


def visible_region(avatar: Avatar, flame_inputs: dict[str, torch.Tensor], camera: Camera, face_visible: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: pixels whose posed face (from ``camera``) is marked in ``face_visible`` (F,)."""
    fid = _rasterize_faces(avatar, flame_inputs, camera)
    out = torch.zeros(fid.shape, dtype=torch.bool, device=fid.device)
    hit = fid >= 0
    out[hit] = face_visible.to(fid.device)[fid[hit]]
    return out


def region_metrics(pred: torch.Tensor, gt: torch.Tensor, region: torch.Tensor, background: float,
                   lpips: LPIPS | None, psnr_cap: float | None) -> tuple[float, float, float, float | None]:
    """Metrics over a pixel region.

    pred, gt: (H, W, 3) in [0, 1]; region: (H, W) bool. Returns (psnr, psnr_ga, ssim, lpips): PSNR
    from the MSE over the region's pixels × channels (GA variant: per channel, then the mean), the
    SSIM map's mean over the region, LPIPS of the images with the outside set to ``background``
    (None without a model). An empty region gives NaN (LPIPS None).
    """
    r = region.to(pred.device)
    n = int(r.sum())
    if n == 0:
        return math.nan, math.nan, math.nan, None
    diff2 = (pred - gt)[r] ** 2  # (n, 3)
    p = 10.0 * torch.log10(1.0 / diff2.mean())
    per_c = 10.0 * torch.log10(1.0 / diff2.mean(0))
    if psnr_cap is not None:
        p = p.clamp_max(psnr_cap)
        per_c = per_c.clamp_max(psnr_cap)
    pc = per_c.mean()
    smap = ssim_map(pred.permute(2, 0, 1), gt.permute(2, 0, 1))  # (3, H, W)
    s = smap.mean(0)[r].mean()
    lp: float | None = None
    if lpips is not None:
        dev = _lpips_device(lpips)
        bg = torch.full_like(pred, float(background))
        a = torch.where(r[..., None], pred, bg).permute(2, 0, 1)
        b = torch.where(r[..., None], gt, bg).permute(2, 0, 1)
        lp = float(lpips(a.to(dev), b.to(dev)))
    return float(p), float(pc), float(s), lp


@dataclass
class NovelReport:
    """Result of :func:`evaluate_novel`: full-image and visible-region reports over all held-out
    images, the frontal camera, per-subset means, the visible fraction of each image, and the
    camera indices of each view group (``NovelSet.view_groups``)."""

    full: EvalReport
    visible: EvalReport
    frontal_camera: int
    frontal_rule: str
    subsets: dict[str, list[int]]
    coverage: list[float]
    source: Path
    samples: list[Path] = field(default_factory=list)
    metrics_path: Path | None = None
    view_groups: dict[str, list[int]] = field(default_factory=dict)

    def _means(self, report: EvalReport, idx: list[int]) -> dict[str, Any]:
        rows = [report.images[i] for i in idx]
        fr = [m for m in rows if m.camera == self.frontal_camera]
        return {"overall": MetricMeans.of(rows).to_dict(), "frontal": MetricMeans.of(fr).to_dict() if fr else None}

    def to_dict(self) -> dict[str, Any]:
        """The other splits' metrics.json shape (all held-out images, frontal = the chosen camera),
        plus ``subsets`` (views / expressions) and the ``visible_region`` block."""
        doc = self.full.to_dict()
        doc["frontal_camera"] = self.frontal_camera
        doc["frontal_rule"] = self.frontal_rule
        doc["source"] = str(self.source)
        doc["subsets"] = {k: self._means(self.full, v) for k, v in self.subsets.items()}
        vis = self.visible.to_dict()
        for key in ("protocol", "counts", "lpips_available", "samples"):
            vis.pop(key, None)
        vis["definition"] = VISIBLE_DEFINITION
        vis["frontal_camera"] = self.frontal_camera
        vis["subsets"] = {k: self._means(self.visible, v) for k, v in self.subsets.items()}
        vis["mean_coverage"] = float(np.mean(self.coverage)) if self.coverage else None
        for row, cov in zip(vis["images"], self.coverage):
            row["coverage"] = cov
        doc["visible_region"] = vis
        if self.view_groups:
            doc["view_groups"] = {}
            for g, cams in self.view_groups.items():
                idx = [i for i, m in enumerate(self.full.images) if m.camera in set(cams)]
                doc["view_groups"][g] = {
                    "cameras": cams,
                    "overall": MetricMeans.of([self.full.images[i] for i in idx]).to_dict(),
                    "visible_region": MetricMeans.of([self.visible.images[i] for i in idx]).to_dict(),
                    "mean_coverage": float(np.mean([self.coverage[i] for i in idx])) if idx else None,
                }
        doc["samples"] = sample_refs(self.samples, self.metrics_path)
        return doc


def _with_frontal(report: EvalReport, camera: int) -> EvalReport:
    report.frontal = report.per_camera.get(camera)
    return report


def held_out_inputs(avatar: Avatar, data: IngestedData, novel: NovelSet, frame: NovelFrame, trained: set[int]) -> dict[str, torch.Tensor]:
    """FLAME kwargs of a held-out frame: row ``frame.row`` of the set's parameters with the avatar's
    identity, except for a view of a training timestep (in ``trained``) whose parameters are that
    timestep's as ingested: it takes the avatar's own parameters of the timestep, which differ when
    phase 1 registered or refined the training pose (:mod:`sage_core.train.registration`), so the
    view shows the training timestep as the avatar was fitted to it."""
    t = int(frame.timestep)
    if frame.subset == "views" and t in trained and _same_frame(novel.params, frame.row, data.params, data.params.row_of(t)):
        return avatar.frame_inputs(t)
    return avatar.params_inputs(novel.params, frame.row)


def _same_frame(a: FlameParams, row_a: int, b: FlameParams, row_b: int, tol: float = 1e-6) -> bool:
    """True when two parameter rows hold the same per-frame values (expression, poses, translation)."""
    from ..avatar.posing import FLAME_KEYS

    for k in FLAME_KEYS:
        x, y = np.asarray(getattr(a, k)[row_a], np.float64), np.asarray(getattr(b, k)[row_b], np.float64)
        if x.shape != y.shape or not np.allclose(x, y, rtol=0.0, atol=tol):
            return False
    return True


@torch.no_grad()
def evaluate_novel(
    render_fn: NovelRenderFn,
    avatar: Avatar,
    data: IngestedData,
    novel: NovelSet,
    *,
    lpips: LPIPS | None,
    out_dir: Path | None,
    n_samples: int = 8,
    psnr_cap: float | None = None,
    progress: Progress | None = None,
) -> NovelReport:
    """Render and score every held-out frame (see the module doc).

    render_fn: ``(camera, flame_inputs) -> (H, W, 3)``; the inputs come from
    :func:`held_out_inputs` (the set's parameters with the avatar's identity; the avatar's own
    parameters for views of its training timestep). With ``out_dir``:
    writes ``metrics.json`` (atomically, last) and ``n_samples`` sample strips
    ``images/{subset}_{ti:05d}_{ci:02d}.png`` (GT | render | error).
    """
    frames = novel.frames
    face_vis = training_face_visibility(avatar, data)
    samples = set(sample_indices(len(frames), n_samples if out_dir is not None else 0))
    lp_dev = _lpips_device(lpips) if lpips is not None else None
    full_rows: list[ImageMetrics] = []
    vis_rows: list[ImageMetrics] = []
    coverage: list[float] = []
    written: list[Path] = []
    inputs: dict[int, dict[str, torch.Tensor]] = {}
    trained = {int(f.timestep) for f in data.train}
    for i, fr in enumerate(frames):
        if fr.row not in inputs:
            inputs[fr.row] = held_out_inputs(avatar, data, novel, fr, trained)
        gt_np = load_novel_image(novel, fr)
        render = render_fn(fr.camera, inputs[fr.row])
        if not isinstance(render, torch.Tensor) or tuple(render.shape) != gt_np.shape:
            raise ValueError(f"render_fn returned {getattr(render, 'shape', type(render))} for held-out timestep "
                             f"{fr.timestep}, camera {fr.camera_index}; the ground truth is {gt_np.shape}")
        render = render.detach().to(torch.float32).clamp(0.0, 1.0)
        gt = torch.from_numpy(gt_np).to(render.device).clamp(0.0, 1.0)
        pc, gc = render.permute(2, 0, 1), gt.permute(2, 0, 1)
        lp = float(lpips(pc.to(lp_dev), gc.to(lp_dev))) if lpips is not None else None
        full_rows.append(ImageMetrics(fr.timestep, fr.camera_index, float(psnr(pc, gc, cap=psnr_cap)),
                                      float(psnr_per_channel_mean(pc, gc, cap=psnr_cap)), float(ssim(pc, gc)), lp))
        region = visible_region(avatar, inputs[fr.row], fr.camera, face_vis).to(render.device)
        coverage.append(float(region.float().mean()))
        vp, vpg, vs, vl = region_metrics(render, gt, region, novel.background, lpips, psnr_cap)
        vis_rows.append(ImageMetrics(fr.timestep, fr.camera_index, vp, vpg, vs, vl))
        if i in samples:
            from ..data.imageio import write_image

            assert out_dir is not None
            path = Path(out_dir) / "images" / f"{fr.subset}_{fr.timestep:05d}_{fr.camera_index:02d}.png"
            write_image(path, error_strip(gt, render))
            written.append(path)
        if progress is not None:
            progress(i + 1, len(frames), f"{fr.subset} t{fr.timestep} cam {fr.camera_index}: PSNR {_fmt(full_rows[-1].psnr, 2)}, "
                                         f"visible {_fmt(vp, 2)}")
    kw = {"lpips_available": lpips is not None,
          "lpips_inputs": None if lpips is None else ("[-1,1]" if lpips.rescale_inputs else "[0,1]"), "psnr_cap": psnr_cap}
    full = _with_frontal(EvalReport.build(full_rows, **kw), novel.frontal_camera)
    visible = _with_frontal(EvalReport.build(vis_rows, **kw), novel.frontal_camera)
    subsets = {name: [i for i, f in enumerate(frames) if f.subset == name] for name in SUBSETS.values()}
    report = NovelReport(full, visible, novel.frontal_camera, novel.frontal_rule,
                         {k: v for k, v in subsets.items() if v}, coverage, novel.root, written, view_groups=novel.view_groups)
    full.samples = written
    if out_dir is not None:
        from ..workspace import atomic_write_json

        report.metrics_path = Path(out_dir) / "metrics.json"
        atomic_write_json(report.metrics_path, report.to_dict())
    return report
