"""Write a synthetic capture in the VHAP / GaussianAvatars layout (docs/formats.md §1–2) plus ground truth.

Layout of ``OUT``::

    images/{ti:05d}_{ci:02d}.png      RGB on white, below the neck line blanked
    fg_masks/{ti:05d}_{ci:02d}.png    L uint8 = coverage × neck-line mask
    flame_param/{ti:05d}.npz          per-timestep FLAME parameters (docs/formats.md §1.3)
    canonical_flame_param.npz
    transforms.json, transforms_{train,val,test}.json
    model/   synth_flame.pkl (official pickle layout), synth_flame.npz, FLAME_masks.pkl
    gt/      canonical.ply, meshes/{ti:05d}.ply, info.json, [novel/ held-out views and expressions],
             [hair/ canonical.ply, {ti:05d}.ply: the hair volume of a detailed subject]
    [preview.png]

``appearance="detailed"``: the albedo carries pixel-scale detail (:mod:`.detail`) and the truth
has a hair volume off the scalp (:mod:`.hair`, rigid with the skull; in the images, masks and
``gt/hair/``, not in ``model/``) and a mouth interior in the lip pocket (:mod:`.mouth`: teeth,
gums and tongue; in the images and masks, described in ``gt/info.json``). Monocular and one-shot captures may add held-out views all
around the head (``novel_around``; neutral face only), grouped in ``gt/info.json``.

``tracking="exact"``: the written model and parameters are the ground truth. ``"fitted"``: the
ground truth (images and ``gt/`` meshes) is the full head with non-linear correctives, geometric
creases and specular highlights; the written model keeps the leading expression components and
the written parameters are a least-squares fit plus pose noise (:mod:`.tracking`);
``gt/info.json`` reports the tracking error per timestep.

Everything is deterministic in the config (same seed ⇒ same bytes). The capture is assembled in
a temporary sibling folder and moved into place at the end, so a failure leaves nothing half-written.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ...errors import ConfigError
from ..cameras import Camera, camera_to_nerf_frame
from ...atomic import replace_dir
from ..imageio import write_image
from ..neck_line import neck_line_cut
from ._files import write_json, write_npz, write_ply
from .appearance import Appearance, Render, Specular, crease_weights, render_head, sample_appearance
from .config import SynthConfig
from .detail import sample_detail
from .hair import HairVolume, PosedHair, build_hair, pose_hair
from .head import EXPRESSION_NAMES, IDENTITY_NAMES, PART_SKIN, HeadModel, build_head, hair_weight
from .model_files import MASKS_NAME, NPZ_NAME, PICKLE_NAME, flame_model, write_model_files
from .motion import (
    Frame,
    arc_cameras,
    around_cameras,
    off_arc_cameras,
    monocular_camera,
    monocular_frames,
    multiview_frames,
    novel_frames,
    sample_identity,
    shift_camera,
)
from .mouth import MouthVolume, PosedMouth, build_mouth, pose_mouth, sample_mouth_style
from .photo_skin import PHOTO_SKIN_FILE, PhotoSkin, load_photo_skin, save_photo_skin
from .tracking import TrackedHead, add_pose_noise, fit_frames, make_tracked_head, pose_truth, vertex_errors, written_vertices

Progress = Callable[[int, int, str], None]
TRAIN_RATIO = 0.7


@dataclass
class _Subject:
    head: HeadModel
    shape: np.ndarray
    static_offset: np.ndarray
    app: Appearance
    tracked: TrackedHead | None = None
    specular: Specular | None = None
    hair: HairVolume | None = None
    canonical: np.ndarray | None = None  # (V, 3) canonical head (detailed subjects)
    hair_canonical: np.ndarray | None = None  # (H, 3) hair volume on it
    mouth: MouthVolume | None = None  # teeth, gums and tongue (detailed subjects)

    @property
    def written_head(self) -> HeadModel:
        """The FLAME-format model written with the capture (truncated when tracked)."""
        return self.head if self.tracked is None else self.tracked.written_head

    def posed_hair(self, vertices: np.ndarray) -> PosedHair | None:
        """The hair volume on the posed head ``vertices`` (V, 3) (rigid with the skull), or None."""
        if self.hair is None:
            return None
        assert self.canonical is not None and self.hair_canonical is not None
        return pose_hair(self.hair, self.canonical, self.hair_canonical, vertices)

    def posed_mouth(self, vertices: np.ndarray) -> PosedMouth | None:
        """The mouth interior in the posed head ``vertices`` (V, 3) (upper part with the skull, lower
        part with the jaw), or None."""
        if self.mouth is None:
            return None
        assert self.canonical is not None
        return pose_mouth(self.mouth, self.canonical, vertices)

    def render(self, vertices: np.ndarray, camera: Camera, crease: np.ndarray | None, supersample: int) -> Render:
        """The subject (head, hair volume and mouth interior) posed at ``vertices`` (V, 3), seen by ``camera``."""
        return render_head(self.head, vertices, camera, self.app, crease, supersample=supersample, specular=self.specular,
                           hair=self.posed_hair(vertices), mouth=self.posed_mouth(vertices))


@dataclass
class _Posed:
    vertices: np.ndarray  # (T, V, 3)
    crease: np.ndarray  # (T, V)


def _pose(subject: _Subject, frames: list[Frame]) -> _Posed:
    """Ground-truth posed vertices (T, V, 3) through ``sage_core.flame.FlameModel`` (float64) and
    crease weights (T, V); tracked subjects add the truth's correctives and creases."""
    if subject.tracked is not None:
        tp = pose_truth(subject.tracked, subject.shape, subject.static_offset, frames)
        crease = np.stack([crease_weights(tp.v_shaped[t], tp.neutral, subject.head.faces) for t in range(len(frames))])
        return _Posed(tp.vertices, crease)
    import torch

    model = flame_model(subject.head)
    st = lambda a: torch.as_tensor(np.stack(a), dtype=torch.float64)  # noqa: E731
    shape = torch.as_tensor(subject.shape, dtype=torch.float64)
    off = torch.as_tensor(subject.static_offset, dtype=torch.float64)
    with torch.no_grad():
        out = model(
            shape=shape,
            expr=st([f.expr for f in frames]),
            rotation=st([f.rotation for f in frames]),
            neck_pose=st([f.neck_pose for f in frames]),
            jaw_pose=st([f.jaw_pose for f in frames]),
            eyes_pose=st([f.eyes_pose for f in frames]),
            translation=st([f.translation for f in frames]),
            static_offset=off,
        )
        neutral = model(shape=shape, static_offset=off).v_shaped[0].numpy()
    verts = out.vertices.numpy()
    vs = out.v_shaped.numpy()
    crease = np.stack([crease_weights(vs[t], neutral, subject.head.faces) for t in range(len(frames))])
    return _Posed(verts, crease)


def canonical_vertices(subject: _Subject) -> np.ndarray:
    """(V, 3) identity mesh at zero pose and expression (the ground-truth canonical surface)."""
    return subject.head.v_template + subject.head.shapedirs[:, :, :300] @ subject.shape + subject.static_offset


def neck_line_mask(head: HeadModel, vertices: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) float mask in [0, 1] keeping what is above the head's neck line (docs/formats.md §1.1), blurred."""
    return neck_line_cut(vertices, tuple(head.neck_line), camera)


def _frame_npz(subject: _Subject, f: Frame) -> dict[str, np.ndarray]:
    f32 = np.float32
    return {
        "translation": f.translation.reshape(1, 3).astype(f32),
        "rotation": f.rotation.reshape(1, 3).astype(f32),
        "neck_pose": f.neck_pose.reshape(1, 3).astype(f32),
        "jaw_pose": f.jaw_pose.reshape(1, 3).astype(f32),
        "eyes_pose": f.eyes_pose.reshape(1, 6).astype(f32),
        "shape": subject.shape.reshape(300).astype(f32),
        "expr": f.expr.reshape(1, 100).astype(f32),
        "static_offset": subject.static_offset[None].astype(f32),
    }


def _canonical_npz(subject: _Subject) -> dict[str, np.ndarray]:
    f = Frame()
    f.jaw_pose = np.array([0.3, 0.0, 0.0])
    return _frame_npz(subject, f)


def _nerf_frame(cam: Camera, ti: int, rel: str = "") -> dict:
    d = camera_to_nerf_frame(cam)
    name = f"{ti:05d}_{cam.index:02d}"
    return {
        "timestep_index": ti,
        "timestep_index_original": ti,
        "timestep_id": f"frame_{ti:05d}",
        "camera_index": cam.index,
        "camera_id": cam.name,
        **d,
        "file_path": f"{rel}images/{name}.png",
        "fg_mask_path": f"{rel}fg_masks/{name}.png",
        "flame_param_path": f"{rel}flame_param/{ti:05d}.npz",
    }


def _transforms(frames: list[dict]) -> dict:
    out: dict = {"frames": frames}
    out["timestep_indices"] = sorted({f["timestep_index"] for f in frames})
    out["camera_indices"] = sorted({f["camera_index"] for f in frames})
    if frames:
        last = frames[-1]
        for k in ("cx", "cy", "fl_x", "fl_y", "h", "w", "camera_angle_x", "camera_angle_y"):
            out[k] = last[k]
    return out


@dataclass
class _Sequence:
    vertices: np.ndarray  # (T, V, 3) ground truth
    error_mean_mm: np.ndarray | None = None  # (T,) tracking error (fitted captures)
    error_max_mm: np.ndarray | None = None
    error_face_mm: np.ndarray | None = None  # (T,) mean over the face region
    written: list[Frame] | None = None  # the parameters written (the tracker's fit for fitted captures)

    def rows(self, idx: list[int]) -> "_Sequence":
        """The timesteps ``idx`` of this sequence (truth, errors, written parameters)."""
        def pick(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[idx]
        return _Sequence(self.vertices[idx], pick(self.error_mean_mm), pick(self.error_max_mm), pick(self.error_face_mm),
                         None if self.written is None else [self.written[i] for i in idx])


def _tracked_params(subject: _Subject, frames: list[Frame], truth: np.ndarray, cfg: SynthConfig,
                    rng: np.random.Generator) -> tuple[list[Frame], np.ndarray, np.ndarray, np.ndarray]:
    """What a tracker hands over for ``frames``: the written model fitted to the truth (T, V, 3),
    plus pose noise. Returns (written frames, mean error mm (T,), max error mm (T,), mean error
    over the face region mm (T,))."""
    assert subject.tracked is not None
    th = subject.tracked
    fitted = fit_frames(th, subject.shape, subject.static_offset, frames, truth, cfg.fit_iterations)
    written = add_pose_noise(fitted, rng, cfg.pose_noise_deg, cfg.trans_noise_mm)
    posed = written_vertices(th, subject.shape, subject.static_offset, written)
    mean, mx = vertex_errors(posed, truth)
    face, _ = vertex_errors(posed, truth, subject.head.masks["face"])
    return written, mean, mx, face


def _write_sequence(root: Path, subject: _Subject, frames: list[Frame], cameras: list[Camera],
                    splits: dict[str, list[tuple[int, int]]], cfg: SynthConfig, tick: Callable[[str], None],
                    noise_rng: np.random.Generator | None = None, uncut: frozenset[int] = frozenset(),
                    same_as: _Sequence | None = None) -> _Sequence:
    """Render and write images, masks, FLAME params and transforms; returns the ground truth
    (and, for tracked subjects, the tracking error of the written parameters). Cameras in ``uncut``
    (views around the head) are not cut at the neck line: seen from the side or the back that image
    line would cut through the head, and the mesh itself ends at the neck base. ``same_as``: these
    frames are timesteps of a sequence already written, whose written parameters (and errors) they
    keep (held-out views of training timesteps)."""
    posed = _pose(subject, frames)
    seq = _Sequence(posed.vertices, written=frames)
    if same_as is not None:
        seq = replace(same_as, vertices=posed.vertices)
    elif subject.tracked is not None:
        assert noise_rng is not None
        seq.written, seq.error_mean_mm, seq.error_max_mm, seq.error_face_mm = _tracked_params(subject, frames, posed.vertices, cfg, noise_rng)
    written = seq.written
    assert written is not None
    for ti, f in enumerate(written):
        write_npz(root / "flame_param" / f"{ti:05d}.npz", _frame_npz(subject, f))
    by_index = {c.index: c for c in cameras}
    pairs = sorted({p for ps in splits.values() for p in ps})
    for ti, ci in pairs:
        cam = by_index[ci]
        v = posed.vertices[ti]
        r = subject.render(v, cam, posed.crease[ti], cfg.supersample)
        neck = np.ones((cam.height, cam.width), np.float32) if ci in uncut else neck_line_mask(subject.head, v, cam)
        img = r.rgb * neck[..., None] + (1.0 - neck[..., None])
        write_image(root / "images" / f"{ti:05d}_{ci:02d}.png", img)
        write_image(root / "fg_masks" / f"{ti:05d}_{ci:02d}.png", r.alpha * neck)
        tick(f"t{ti:03d} cam {ci:02d}")
    all_frames = []
    for split, ps in splits.items():
        fr = [_nerf_frame(by_index[ci], ti) for ti, ci in sorted(ps)]
        write_json(root / f"transforms_{split}.json", _transforms(fr))
        all_frames += fr
    all_frames.sort(key=lambda d: (d["timestep_index"], d["camera_index"]))
    write_json(root / "transforms.json", _transforms(all_frames))
    write_npz(root / "canonical_flame_param.npz", _canonical_npz(subject))
    return seq


def _write_meshes(folder: Path, head: HeadModel, verts: np.ndarray) -> list[str]:
    names = []
    for ti in range(verts.shape[0]):
        write_ply(folder / f"{ti:05d}.ply", verts[ti], head.faces)
        names.append(f"{ti:05d}.ply")
    return names


def _write_hair(folder: Path, subject: _Subject, verts: np.ndarray, canonical: bool = True) -> None:
    """The hair volume of every timestep of ``verts`` (T, V, 3) (and its canonical mesh) as PLY."""
    assert subject.hair is not None and subject.hair_canonical is not None
    if canonical:
        write_ply(folder / "canonical.ply", subject.hair_canonical, subject.hair.faces)
    for ti in range(verts.shape[0]):
        ph = subject.posed_hair(verts[ti])
        assert ph is not None
        write_ply(folder / f"{ti:05d}.ply", ph.vertices, subject.hair.faces)


def _preview(path: Path, subject: _Subject, frames: list[Frame], cameras: list[Camera], cfg: SynthConfig) -> None:
    """Contact sheet: rows = up to 4 timesteps (first training, then held-out), cols = up to 3 views."""
    yaws = []
    for c in cameras:
        d = c.c2w[:3, 2]
        yaws.append(math.degrees(math.atan2(-d[0], -d[2])))
    cols = sorted({int(np.argmin([abs(y - t) for y in yaws])) for t in (-45.0, 0.0, 45.0)}, key=lambda i: yaws[i])
    n = len(frames)
    rows = sorted({0, *range(n - 1, max(n - 4, 0), -1)})[:4]
    posed = _pose(subject, [frames[i] for i in rows])
    tiles = []
    for r in range(len(rows)):
        tiles.append(np.concatenate([subject.render(posed.vertices[r], cameras[c], posed.crease[r], cfg.supersample).rgb for c in cols], 1))
    write_image(path, np.concatenate(tiles, 0))


def make_subject(cfg: SynthConfig, photo: PhotoSkin | None = None) -> _Subject:
    """The head model, identity and appearance determined by the config (resolution + seed), and
    for ``tracking="fitted"`` the truth / written-model pair and the truth's highlights. photo: the
    photo skin of a capture with ``skin_photo`` (None: read from the config's capture)."""
    head = build_head(cfg.head_rows, cfg.head_cols, cfg.eye_rows, cfg.eye_cols)
    rng = np.random.default_rng([cfg.seed, 1])
    shape, static_offset = sample_identity(head, rng)
    app = sample_appearance(rng)
    subject = _Subject(head, shape, static_offset, app)
    if cfg.appearance == "detailed":
        _add_detail(subject, np.random.default_rng([cfg.seed, 6]))
        _add_mouth(subject, np.random.default_rng([cfg.seed, 8]))
        if cfg.skin_photo is not None:
            _add_photo_skin(subject, cfg.skin_photo, cfg.skin_photo_model, photo)
    if cfg.tracking == "exact":
        return subject
    subject.tracked = make_tracked_head(head, cfg.expr_keep, cfg.corrective_scale, cfg.crease_depth_mm)
    subject.specular = Specular().scaled(cfg.specular) if cfg.specular > 0 else None
    return subject


def _add_detail(subject: _Subject, rng: np.random.Generator) -> None:
    """Give ``subject`` its pixel-scale detail and hair volume (drawn from ``rng``, a stream of its
    own so the identity, colours and motion stay those of the smooth subject of the same seed)."""
    head = subject.head
    v = head.v_template
    face = (head.part == PART_SKIN) & (v[:, 2] > 0.02) & (v[:, 1] > -0.12) & (v[:, 1] < 0.07) & (hair_weight(v) < 0.2)
    style = sample_detail(rng, v[face])
    subject.app = replace(subject.app, detail=style)
    subject.hair = build_hair(head, style)
    subject.canonical = canonical_vertices(subject)
    subject.hair_canonical = subject.hair.place(subject.canonical, head.faces)


def _add_photo_skin(subject: _Subject, capture: str, model: str | None, skin: PhotoSkin | None) -> None:
    """Give a detailed ``subject`` a photograph as the skin of its face (:mod:`.photo_skin`; ``skin``
    when given, else from the photo's capture); the procedural skin tone becomes the photo's median
    face colour."""
    head = subject.head
    if skin is None:
        # the face and the bare skin around it (cheeks to the ears), not the neck nor what the hair covers
        face = np.zeros(head.n_vertices, bool)
        face[np.asarray(head.masks["face"], dtype=np.int64)] = True
        face |= hair_weight(head.v_template) < 0.2
        face[np.asarray(head.masks["neck"], dtype=np.int64)] = False
        face &= head.part == PART_SKIN
        skin = load_photo_skin(capture, model, head.n_vertices, head.faces, face)
    elif skin.uv.shape[0] != head.n_vertices:
        raise ConfigError(f"the photo skin has {skin.uv.shape[0]} vertices, this head {head.n_vertices}")
    subject.app = replace(subject.app, photo=skin, skin=tuple(float(c) for c in skin.median_rgb))


def _add_mouth(subject: _Subject, rng: np.random.Generator) -> None:
    """Give a detailed ``subject`` its mouth interior (teeth, gums, tongue; drawn from ``rng``, a
    stream of its own so everything else stays as it was)."""
    assert subject.canonical is not None
    subject.mouth = build_mouth(subject.head, subject.canonical, sample_mouth_style(rng))


def write_capture(out_dir: str | Path, cfg: SynthConfig, progress: Progress | None = None,
                  preview: bool = False, force: bool = False) -> Path:
    """Generate and write a synthetic capture into ``out_dir``; returns the folder.

    Raises ConfigError when ``out_dir`` exists and is not empty (unless ``force``) or the config is
    invalid. progress(done, total, what) is called after every written image.
    """
    cfg.validate()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise ConfigError(f"{out} is not empty; pass --force to replace it")
    tmp = out.with_name(f".{out.name}.synth-tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        _generate(tmp, cfg, progress, preview)
        replace_dir(tmp, out, "synth")
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _generate(root: Path, cfg: SynthConfig, progress: Progress | None, preview: bool) -> None:
    subject = make_subject(cfg)
    head = subject.head
    rng = np.random.default_rng([cfg.seed, 2])
    if cfg.regime == "multiview":
        frames = multiview_frames(rng, cfg.train_timesteps, cfg.test_timesteps)
        cameras = arc_cameras(rng, cfg.n_cameras, cfg.width, cfg.height, cfg.camera_distance, cfg.view_height_m)
    elif cfg.regime == "monocular":
        frames = monocular_frames(rng, cfg.train_timesteps, cfg.test_timesteps)
        cameras = [monocular_camera(cfg.width, cfg.height, cfg.mono_focal)]
    else:
        frames = [Frame(label="train: neutral, frontal")]
        cameras = [monocular_camera(cfg.width, cfg.height, cfg.mono_focal)]
    # world re-centring (docs/formats.md §1.5): mean translation 0, cameras moved along
    t_mean = np.mean([f.translation for f in frames], axis=0)
    for f in frames:
        f.translation = f.translation - t_mean
    cameras = [shift_camera(c, -t_mean) for c in cameras]

    n_train = cfg.train_timesteps if cfg.regime != "oneshot" else 1
    train_ts = list(range(n_train))
    test_ts = list(range(n_train, len(frames)))
    cam_ids = [c.index for c in cameras]
    val_cam = (8 if 8 in cam_ids else cam_ids[-1]) if len(cameras) > 1 else None
    splits = {
        "train": [(t, c) for t in train_ts for c in cam_ids if c != val_cam],
        "val": [(t, val_cam) for t in train_ts] if val_cam is not None else [],
        "test": [(t, c) for t in test_ts for c in cam_ids],
    }
    novel_cams: list[Camera] = []
    around: list[Camera] = []
    novel: list[Frame] = []
    if cfg.regime == "multiview" and cfg.novel_multiview:
        novel_cams = off_arc_cameras(np.random.default_rng([cfg.seed, 3]), cfg.novel_views, cfg.n_cameras, cfg.width, cfg.height,
                                     cfg.camera_distance, cfg.view_height_m, first_index=cfg.n_cameras)
        if cfg.novel_around > 0:
            around = around_cameras(np.random.default_rng([cfg.seed, 7]), cfg.novel_around, cfg.width, cfg.height,
                                    cfg.camera_distance, cfg.view_height_m, first_index=cfg.n_cameras + len(novel_cams))
        novel_cams = [shift_camera(c, -t_mean) for c in novel_cams]
        around = [shift_camera(c, -t_mean) for c in around]
        novel = [frames[0]]
    elif cfg.regime != "multiview":
        novel_cams = arc_cameras(np.random.default_rng([cfg.seed, 3]), cfg.novel_views, cfg.width, cfg.height,
                                 cfg.camera_distance, cfg.view_height_m, yaw_span_deg=120.0, frontal=cfg.novel_views // 2)
        if cfg.novel_around > 0:
            around = around_cameras(np.random.default_rng([cfg.seed, 7]), cfg.novel_around, cfg.width, cfg.height,
                                    cfg.camera_distance, cfg.view_height_m, first_index=cfg.novel_views)
        novel = novel_frames(rng, cfg.novel_expressions)
    n_images = sum(len(v) for v in splits.values()) + len(novel) * len(novel_cams) + len(around)
    done = [0]

    def tick(what: str) -> None:
        done[0] += 1
        if progress is not None:
            progress(done[0], n_images, what)

    model_paths = write_model_files(subject.written_head, root / "model")
    seq = _write_sequence(root, subject, frames, cameras, splits, cfg, tick, np.random.default_rng([cfg.seed, 4]))
    verts = seq.vertices
    canon = canonical_vertices(subject)
    write_ply(root / "gt" / "canonical.ply", canon, head.faces)
    mesh_names = _write_meshes(root / "gt" / "meshes", head, verts)
    if subject.hair is not None:
        _write_hair(root / "gt" / "hair", subject, verts)
    if subject.app.photo is not None:
        save_photo_skin(subject.app.photo, root / "gt" / PHOTO_SKIN_FILE)
    info: dict = {
        "generator": "sage synth",
        "regime": cfg.regime,
        "config": cfg.to_dict(),
        "counts": {"vertices": head.n_vertices, "faces": int(head.faces.shape[0]), "timesteps": len(frames),
                   "cameras": len(cameras), **{f"{k}_images": len(v) for k, v in splits.items()}},
        "model": {"pickle": f"model/{PICKLE_NAME}", "npz": f"model/{NPZ_NAME}", "masks": f"model/{MASKS_NAME}",
                  "face_table": "sage-synthetic-v1", "identity_components": list(IDENTITY_NAMES),
                  "expression_components": list(EXPRESSION_NAMES),
                  "neck_line_vertices": {"left": head.neck_line[0], "right": head.neck_line[1], "front_bottom": head.neck_line[2]}},
        "identity": {"shape": [round(float(x), 6) for x in subject.shape[: len(IDENTITY_NAMES)]],
                     "hair_offset": "static_offset thickens the scalp along its normal", "appearance": subject.app.to_dict()},
        "canonical_mesh": "gt/canonical.ply (identity shape + static offset, zero pose and expression)",
        "meshes": {"folder": "gt/meshes", "files": mesh_names, "space": "capture world (re-centred), posed, per timestep_index"},
        "timesteps": [{"timestep_index": i, "split": "train" if i < n_train else "test", "description": f.label} for i, f in enumerate(frames)],
        "world_recentring_offset": [float(x) for x in -t_mean],
    }
    nseq: _Sequence | None = None
    if novel:
        nroot = root / "gt" / "novel"
        nsplits = {
            "val": [(0, c.index) for c in novel_cams + around],
            "test": [(t, c.index) for t in range(1, len(novel)) for c in novel_cams],
        }
        if not nsplits["test"]:
            del nsplits["test"]
        mv = cfg.regime == "multiview"
        nseq = _write_sequence(nroot, subject, novel, novel_cams + around, nsplits, cfg, tick, np.random.default_rng([cfg.seed, 5]),
                               uncut=frozenset(c.index for c in around), same_as=seq.rows([0]) if mv else None)
        _write_meshes(nroot / "meshes", head, nseq.vertices)
        if subject.hair is not None:
            _write_hair(nroot / "hair", subject, nseq.vertices, canonical=False)
        info["novel"] = {
            "folder": "gt/novel",
            "description": "held-out ground truth in the same VHAP layout and world frame: transforms_val.json = "
                           "neutral face from novel views, transforms_test.json = novel expressions from all novel views",
            "cameras": len(novel_cams) + len(around),
            "timesteps": [{"timestep_index": i, "description": f.label} for i, f in enumerate(novel)],
        }
        if mv:
            info["novel"]["description"] = (
                "held-out ground truth in the same VHAP layout and world frame: transforms_val.json = the first training "
                "timestep (timestep_index 0 of the capture, its written FLAME parameters too) seen by cameras off the "
                f"training arc (cameras {novel_cams[0].index}-{novel_cams[-1].index}: midway between two arc cameras, "
                "22 deg above or 16 deg below it)" + (" and around the head" if around else "") + "; no held-out expressions")
            info["novel"]["training_timestep"] = 0
        if mv and around:
            info["novel"]["view_groups"] = view_groups(novel_cams + around)
            info["novel"]["view_group_definition"] = (
                "azimuth of the camera about the head's vertical axis, 0 = facing the face: front up to 75 deg, "
                "side 75-135 deg, back beyond 135 deg; the views around the head (cameras "
                f"{around[0].index}-{around[-1].index}) are not cut at the neck line")
        elif around:
            info["novel"]["description"] = (
                "held-out ground truth in the same VHAP layout and world frame: transforms_val.json = neutral face "
                "from the novel views (the arc in front and the views around the head), transforms_test.json = "
                "novel expressions from the arc in front")
            info["novel"]["view_groups"] = view_groups(novel_cams + around)
            info["novel"]["view_group_definition"] = (
                "azimuth of the camera about the head's vertical axis, 0 = facing the face: front up to 75 deg, "
                "side 75-135 deg, back beyond 135 deg; the views around the head (cameras "
                f"{around[0].index}-{around[-1].index}) are not cut at the neck line")
    if subject.hair is not None:
        assert subject.app.detail is not None
        info["hair"] = {"folder": "gt/hair", "style": subject.app.detail.hair_style,
                        "description": "hair volume off the scalp (not in model/): canonical.ply beside gt/canonical.ply, "
                                       "{ti:05d}.ply posed per timestep like gt/meshes (gt/novel/hair for gt/novel), "
                                       "rigid with the skull"}
    if subject.mouth is not None:
        info["mouth"] = {"style": subject.mouth.style.to_dict(),
                         "description": "mouth interior inside the lip pocket (not in model/): upper teeth and gums rigid "
                                        "with the skull, lower teeth, gums and tongue rigid with the jaw; shows where the lips part"}
    if subject.tracked is not None:
        info["model"]["expression_components"] = list(EXPRESSION_NAMES[: subject.tracked.n_keep])
        info["tracking"] = _tracking_info(subject.tracked, seq, n_train, nseq)
    if preview:
        _preview(root / "preview.png", subject, frames if cfg.regime != "oneshot" else novel or frames,
                 cameras if len(cameras) > 1 else novel_cams, cfg)
    info["files"] = {k: str(Path(v).relative_to(root)) for k, v in model_paths.items()}
    write_json(root / "gt" / "info.json", info)


VIEW_GROUPS = ("front", "side", "back")
"""Held-out view groups by the camera's azimuth about the head (0 = facing the face)."""


def view_group(camera: Camera) -> str:
    """"front" (azimuth up to 75°), "side" (75–135°) or "back" (beyond 135°) of a camera looking at
    the head (template frame: face +z, up +y)."""
    c = camera.center
    yaw = abs(math.degrees(math.atan2(c[0], c[2])))
    return "front" if yaw <= 75.0 else ("side" if yaw <= 135.0 else "back")


def view_groups(cameras: list[Camera]) -> dict[str, list[int]]:
    """Camera indices per non-empty view group (:data:`VIEW_GROUPS` order)."""
    out: dict[str, list[int]] = {g: [] for g in VIEW_GROUPS}
    for c in cameras:
        out[view_group(c)].append(int(c.index))
    return {g: sorted(v) for g, v in out.items() if v}


def _error_rows(seq: _Sequence, split_of: Callable[[int], str]) -> list[dict]:
    assert seq.error_mean_mm is not None and seq.error_max_mm is not None and seq.error_face_mm is not None
    return [{"timestep_index": i, "split": split_of(i), "mean_mm": round(float(m), 4), "max_mm": round(float(x), 4),
             "face_mean_mm": round(float(fm), 4)}
            for i, (m, x, fm) in enumerate(zip(seq.error_mean_mm, seq.error_max_mm, seq.error_face_mm))]


def _summary(rows: list[dict]) -> dict:
    if not rows:
        return {}
    return {"timesteps": len(rows), "mean_mm": round(float(np.mean([r["mean_mm"] for r in rows])), 4),
            "max_mm": round(float(np.max([r["max_mm"] for r in rows])), 4),
            "face_mean_mm": round(float(np.mean([r["face_mean_mm"] for r in rows])), 4)}


def _tracking_info(th: TrackedHead, seq: _Sequence, n_train: int, nseq: _Sequence | None) -> dict:
    """The ``tracking`` section of gt/info.json: what the written model lacks and the tracking error
    (vertex distance between the written model posed with the written parameters and the truth)."""
    rows = _error_rows(seq, lambda i: "train" if i < n_train else "test")
    out: dict = {
        "mode": "fitted",
        "description": "images and gt/ meshes are the truth (full head + non-linear correctives + geometric creases, "
                       "specular highlights); model/ keeps the leading expression components; flame_param/ is a "
                       "least-squares fit of that model to the truth plus pose noise",
        "expression_components_written": list(EXPRESSION_NAMES[: th.n_keep]),
        "expression_components_truth": list(EXPRESSION_NAMES),
        "error_definition": "per timestep: mean / max over all vertices, and mean over the face region (FLAME_masks "
                            "'face'), of the distance in mm between the written model posed with flame_param/ and "
                            "the ground-truth mesh gt/meshes/ (gt/novel/meshes/ for novel_timesteps)",
        "error": {"all": _summary(rows), "train": _summary([r for r in rows if r["split"] == "train"]),
                  "test": _summary([r for r in rows if r["split"] == "test"])},
        "timesteps": rows,
    }
    if nseq is not None:
        nrows = _error_rows(nseq, lambda i: "val" if i == 0 else "test")
        out["error"]["novel"] = _summary(nrows)
        out["novel_timesteps"] = nrows
    return out
