"""Measuring ``sage track`` on synthetic captures (``sage synth``), whose true meshes are known.

:func:`input_from_capture` turns a synthetic capture into what a user would give ``sage track``: the
one-shot image, the monocular clip as a folder of frames, or the multiview rig as camera folders with
the capture's ``transforms.json``. :func:`compare_to_truth` poses the model with the tracked
parameters and measures the distance of every vertex to the true mesh (``gt/meshes``), and the
camera error.

Vertex errors, in mm, per timestep (mean and max over vertices), summarised over timesteps:

- ``world``: in the capture's world. A multiview rig is given with its calibration, so this is the
  error that counts there.
- ``camera``: in each image's camera frame (the tracked mesh in the tracked camera against the true
  mesh in the true camera): what one camera sees, including the depth of the head.
- ``aligned``: after one similarity transform (rotation, translation, scale) for the whole sequence,
  fitted to all vertices of all timesteps in the camera frames: the shape and motion error without
  the depth/size ambiguity of a single uncalibrated camera (whose size and distance trade off); the
  scale is reported with it.
- ``rigid_per_timestep``: after a rotation and translation of each timestep's mesh on its own (no
  scale): the error of the head's shape and expression alone, as face-reconstruction benchmarks
  measure it, with the pose and the camera left out.
- ``regions``: the world and aligned errors averaged over the FLAME masks' face, neck and scalp
  vertices (when the capture's model has ``FLAME_masks.pkl``): the scalp, half the vertices, lies
  under the hair, which only its outline shows.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError


def input_from_capture(capture: str | Path, out: str | Path, camera: int | None = None) -> tuple[Path, Path | None]:
    """Write a synthetic capture's images as ``sage track`` input. Returns (INPUT, cameras file or None).

    - one camera (monocular, one-shot): ``out/frames/{timestep:05d}.png`` (a single image file
      ``out/{timestep:05d}.png`` when there is one frame);
    - several cameras: ``out/rig/{camera:02d}/{timestep:05d}.png`` plus the capture's
      ``transforms.json`` (``camera`` picks one camera of a rig instead).
    """
    cap = Path(capture)
    out = Path(out)
    doc = json.loads((cap / "transforms.json").read_text())
    frames = doc["frames"]
    cams = sorted({f["camera_index"] for f in frames})
    if camera is not None:
        frames = [f for f in frames if f["camera_index"] == camera]
        cams = [camera]
    if not frames:
        raise InputError(cap / "transforms.json", f"no frames of camera {camera}")
    if len(cams) == 1:
        if len(frames) == 1:
            f = frames[0]
            dst = out / f"{f['timestep_index']:05d}.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(cap / f["file_path"], dst)
            return dst, None
        for f in frames:
            dst = out / "frames" / f"{f['timestep_index']:05d}.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(cap / f["file_path"], dst)
        return out / "frames", None
    for f in frames:
        dst = out / "rig" / f"{f['camera_index']:02d}" / f"{f['timestep_index']:05d}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(cap / f["file_path"], dst)
    shutil.copyfile(cap / "transforms.json", out / "transforms.json")
    return out / "rig", out / "transforms.json"


def _read_ply_vertices(path: Path) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.load(path, process=False).vertices, dtype=np.float64)


def similarity_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The similarity transform that best maps points ``a`` onto ``b`` (Umeyama's least squares).

    a, b: (N, 3) corresponding points (N >= 3, not all on a line). Returns (R (3, 3) rotation,
    t (3,) translation, s scale) minimising the mean of |s·R·a_i + t − b_i|², so that
    ``s * a @ R.T + t ≈ b``.
    """
    ma, mb = a.mean(0), b.mean(0)
    A, B = a - ma, b - mb
    U, S, Vt = np.linalg.svd(B.T @ A / len(a))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (A ** 2).sum(1).mean())
    return R, mb - s * R @ ma, s


def rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation (R, t) with R·a + t ≈ b, no scale (least squares over rows of (N, 3) arrays)."""
    ma, mb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((b - mb).T @ (a - ma))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    return R, mb - R @ ma


def error_summary(per_t: list[tuple[float, float]]) -> dict[str, float]:
    """Vertex errors of T timesteps summarised, in mm rounded to 0.001.

    per_t: T pairs (mean, max) of one timestep's vertex errors in mm, i.e. a (T, 2) table.
    Returns ``mean_mm`` (mean of the means), ``max_mm`` (largest max) and ``worst_timestep_mean_mm``
    (largest mean).
    """
    arr = np.array(per_t)
    return {"mean_mm": round(float(arr[:, 0].mean()), 3), "max_mm": round(float(arr[:, 1].max()), 3),
            "worst_timestep_mean_mm": round(float(arr[:, 0].max()), 3)}


REGIONS: tuple[str, ...] = ("face", "neck", "scalp")
"""FLAME mask regions of the per-region errors: the face and neck an image shows, and the scalp that
hair covers (about half of FLAME's vertices, seen only through the hair's outline)."""


def region_errors(masks_file: Path, **per_vertex: np.ndarray) -> dict[str, dict[str, float]] | None:
    """Mean vertex error (mm) over each of :data:`REGIONS`, for each named measure.

    per_vertex: measure name -> (V,) per-vertex errors in mm averaged over the timesteps (e.g. ``world``,
    ``aligned``). Returns region -> ``{NAME_mm: mean}``; None without a masks file.
    """
    from ..flame.regions import load_masks

    if not masks_file.is_file():
        return None
    masks = load_masks(masks_file)
    return {k: {f"{name}_mm": round(float(v[masks[k]].mean()), 3) for name, v in per_vertex.items()}
            for k in REGIONS if k in masks and len(masks[k])}


def compare_to_truth(tracked: str | Path, truth: str | Path) -> dict[str, Any]:
    """Vertex and camera errors of a ``sage track`` capture of a synthetic capture (module docstring).

    tracked: the capture ``sage track`` wrote; truth: the synthetic capture its input came from (its
    timestep ids are the truth's timestep indices, as :func:`input_from_capture` names the files).
    """
    import torch

    from ..data.capture import read_capture
    from ..flame import FlameModel, load_flame_model

    tr = read_capture(tracked, check_images=False)
    gt = read_capture(truth, check_images=False)
    model = FlameModel(load_flame_model(Path(truth) / "model" / "synth_flame.npz"), dtype=torch.float64)
    ids = {}
    for split in ("train", "val", "test"):
        p = Path(tracked) / f"transforms_{split}.json"
        if p.is_file():
            for f in json.loads(p.read_text())["frames"]:
                ids[f["timestep_index"]] = int(f["timestep_id"])
    p = tr.params
    with torch.no_grad():
        kw = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in p.to_torch(dtype=torch.float64).items()}
        verts = model(**kw).vertices.numpy()
    world, camera, cam_pairs, per, world_v = [], [], [], [], []
    cam_frames = {}
    for f in tr.frames:
        cam_frames.setdefault(f.timestep, f)
    gt_cam = {}
    for f in gt.frames:
        gt_cam.setdefault(f.timestep, {})[f.camera_index] = f.camera
    for row, t in enumerate(p.timesteps):
        true_t = ids[int(t)]
        true_v = _read_ply_vertices(Path(truth) / "gt" / "meshes" / f"{true_t:05d}.ply")
        mine = verts[row]
        e = np.linalg.norm(mine - true_v, axis=1) * 1000
        world.append((e.mean(), e.max()))
        world_v.append(e)
        f = cam_frames[int(t)]
        tc = gt_cam[true_t].get(f.camera_index) or next(iter(gt_cam[true_t].values()))
        a = mine @ f.camera.w2c[:3, :3].T + f.camera.w2c[:3, 3]
        b = true_v @ tc.w2c[:3, :3].T + tc.w2c[:3, 3]
        ec = np.linalg.norm(a - b, axis=1) * 1000
        camera.append((ec.mean(), ec.max()))
        cam_pairs.append((a, b))
        per.append({"timestep": int(t), "truth_timestep": true_t, "world_mean_mm": round(float(e.mean()), 3),
                    "camera_mean_mm": round(float(ec.mean()), 3)})
    R, tvec, s = similarity_fit(np.concatenate([a for a, _ in cam_pairs]), np.concatenate([b for _, b in cam_pairs]))
    aligned, rigid, aligned_v = [], [], []
    for a, b in cam_pairs:
        ea = np.linalg.norm((s * a @ R.T + tvec) - b, axis=1) * 1000
        aligned.append((ea.mean(), ea.max()))
        aligned_v.append(ea)
        Rr, tr_ = rigid_fit(a, b)
        er = np.linalg.norm(a @ Rr.T + tr_ - b, axis=1) * 1000
        rigid.append((er.mean(), er.max()))
    # camera: focal length of the first camera in input pixels (the report undoes the crop) against the truth's
    report = json.loads((Path(tracked) / "track" / "report.json").read_text())
    cam0 = report["camera"]["cameras"][0]
    f0 = tr.frames[0]
    tc = gt_cam[ids[f0.timestep]].get(f0.camera_index) or next(iter(gt_cam[ids[f0.timestep]].values()))
    focal_rel = float(cam0["focal_input_px"] / tc.K[0, 0] - 1.0)
    return {
        "timesteps": len(per),
        "world": error_summary(world),
        "camera": error_summary(camera),
        "aligned": {**error_summary(aligned), "scale": round(s, 4)},
        "rigid_per_timestep": error_summary(rigid),
        "focal_rel_error": round(focal_rel, 4),
        "regions": region_errors(Path(truth) / "model" / "FLAME_masks.pkl", world=np.mean(world_v, 0), aligned=np.mean(aligned_v, 0)),
        "per_timestep": per,
        "truth_tracking_error": json.loads((Path(truth) / "gt" / "info.json").read_text()).get("tracking", {}).get("error"),
    }


def held_out_for_tracked(tracked: str | Path, truth: str | Path, anchor: str = "photo") -> dict[str, Any]:
    """Give a one-image ``sage track`` capture of a synthetic photo the truth's held-out set.

    The synthetic one-shot capture holds its novel views and expressions in ``gt/novel`` (its own
    world); an avatar trained on the tracked capture lives in the tracker's world, with the tracked
    shape, pose and camera. This writes ``tracked/gt/novel`` (and the ``novel`` block of
    ``tracked/gt/info.json``) so that ``sage eval --split novel`` scores that avatar on the same
    images. A similarity ``x_true = s·R·x + t`` from the tracked world to the truth's moves every
    held-out camera ``(R_c, t_c)`` to ``(R_c·R, (R_c·t + t_c)/s)``, which projects every point as
    before. ``anchor`` chooses it:

    - ``photo`` (default): the held-out cameras keep their place relative to the photo's camera, as a
      user orbits the head from their photo: the similarity maps the tracked camera's frame onto the
      true camera's, scaled by the ratio of the two heads' depths in them (the mean vertex's; one
      uncalibrated photo fixes neither the head's size nor its distance), and every held-out focal
      length is scaled by the ratio of the tracked focal length to the true one. The held-out camera
      at the photo's place then renders exactly what the tracked camera saw; the error of the tracked
      head's shape and pose shows in the views away from it;
    - ``mesh``: the similarity that best maps the tracked mesh onto the true mesh (all vertices,
      :func:`similarity_fit`, the ``aligned`` error's alignment), focal lengths unchanged: the
      held-out views see the tracked head where the true head is, so the photo's own view is off by
      the tracked camera's error.

    FLAME parameters: the tracked parameters of the photo with the capture's own change from its
    training parameters to the held-out timestep's: expression coefficients, jaw, eyes and neck added,
    the head rotation composed in the head's frame and the translation moved into the tracked world
    (``R^T·Δt / s``), so that both avatars are driven by the same change (the views of the training
    expression change only by the own parameters' per-timestep tracking noise). Images and masks are
    copied.

    Returns the alignment (rotation, translation, scale, focal ratio, anchor) and the number of frames
    written. Raises InputError when the tracked capture has more than one timestep or the truth no
    ``gt/novel``, ValueError for an unknown anchor.
    """
    import torch
    from scipy.spatial.transform import Rotation

    from ..atomic import atomic_write_text
    from ..data.cameras import camera_from_nerf_frame, camera_to_nerf_frame
    from ..data.capture import read_capture
    from ..flame import FlameModel, load_flame_model
    from ..flame.params import load_param_npz, save_param_npz

    tracked, truth = Path(tracked), Path(truth)
    src = truth / "gt" / "novel"
    if not (src / "transforms_val.json").is_file() and not (src / "transforms_test.json").is_file():
        raise InputError(src, "holds no held-out set (transforms_val.json / transforms_test.json)")
    tr = read_capture(tracked, check_images=False)
    gt = read_capture(truth, check_images=False)
    if tr.params.n_timesteps != 1 or gt.params.n_timesteps != 1:
        raise InputError(tracked, "the held-out set is moved only for a one-image capture of a one-image truth")
    model = FlameModel(load_flame_model(truth / "model" / "synth_flame.npz"), dtype=torch.float64)
    with torch.no_grad():
        kw = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in tr.params.to_torch(dtype=torch.float64).items()}
        mine = model(**kw).vertices.numpy()[0]
    true_v = _read_ply_vertices(truth / "gt" / "meshes" / f"{int(gt.params.timesteps[0]):05d}.ply")
    cam_t, cam_r = gt.frames[0].camera, tr.frames[0].camera
    if anchor == "mesh":
        R, t, s = similarity_fit(mine, true_v)
        focal_ratio = 1.0
    elif anchor == "photo":
        depth_t = float((cam_t.w2c[:3, :3] @ true_v.mean(0) + cam_t.w2c[:3, 3])[2])
        depth_r = float((cam_r.w2c[:3, :3] @ mine.mean(0) + cam_r.w2c[:3, 3])[2])
        s = depth_t / depth_r
        sim = np.linalg.inv(cam_t.w2c) @ np.diag([s, s, s, 1.0]) @ cam_r.w2c  # tracked world -> true world
        R, t = sim[:3, :3] / s, sim[:3, 3]
        focal_ratio = float(cam_r.K[0, 0] / cam_t.K[0, 0])
    else:
        raise ValueError(f"anchor must be 'photo' or 'mesh', not {anchor!r}")
    own0, trk = gt.params, tr.params

    dst = tracked / "gt" / "novel"
    if dst.exists():
        shutil.rmtree(dst)
    (dst / "flame_param").mkdir(parents=True)
    written: dict[int, str] = {}
    count = 0
    for split in ("val", "test"):
        jpath = src / f"transforms_{split}.json"
        if not jpath.is_file():
            continue
        doc = json.loads(jpath.read_text(encoding="utf-8"))
        frames = []
        for fr in doc["frames"]:
            cam = camera_from_nerf_frame(fr)
            Rc, tc = cam.w2c[:3, :3], cam.w2c[:3, 3]
            cam.w2c = np.eye(4)
            cam.w2c[:3, :3] = Rc @ R
            cam.w2c[:3, 3] = (Rc @ t + tc) / s
            cam.K = cam.K.copy()
            cam.K[0, 0] *= focal_ratio
            cam.K[1, 1] *= focal_ratio
            out = {k: v for k, v in fr.items() if k not in ("transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h",
                                                               "camera_angle_x", "camera_angle_y")}
            out.update(camera_to_nerf_frame(cam))
            for key in ("file_path", "fg_mask_path"):
                if fr.get(key):
                    rel = Path(fr[key])
                    (dst / rel).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(jpath.parent / rel, dst / rel)
            ti = int(fr["timestep_index"])
            if ti not in written:
                nov = load_param_npz(jpath.parent / fr["flame_param_path"])
                p = trk.select([0])
                e = min(p.expr.shape[1], nov.expr.shape[1], own0.expr.shape[1])
                p.expr[:, :e] += nov.expr[:, :e] - own0.expr[:, :e]
                for key in ("jaw_pose", "eyes_pose", "neck_pose"):
                    getattr(p, key)[:] += getattr(nov, key) - getattr(own0, key)
                d = Rotation.from_rotvec(own0.rotation[0]).inv() * Rotation.from_rotvec(nov.rotation[0])
                p.rotation[0] = (Rotation.from_rotvec(p.rotation[0]) * d).as_rotvec()
                p.translation[0] += R.T @ (nov.translation[0] - own0.translation[0]) / s
                name = f"flame_param/{ti:05d}.npz"
                save_param_npz(dst / name, p, 0)
                written[ti] = name
            out["flame_param_path"] = written[ti]
            frames.append(out)
            count += 1
        atomic_write_text(dst / jpath.name, json.dumps({**{k: v for k, v in doc.items() if k != "frames"}, "frames": frames},
                                                       indent=2))
    info_path = truth / "gt" / "info.json"
    block = json.loads(info_path.read_text(encoding="utf-8")).get("novel", {}) if info_path.is_file() else {}
    alignment = {"anchor": anchor, "rotation": R.tolist(), "translation": t.tolist(), "scale": s, "focal_ratio": focal_ratio}
    block = {**block, "moved_from": "the synthetic capture's gt/novel", "alignment": alignment}
    atomic_write_text(tracked / "gt" / "info.json", json.dumps({"novel": block}, indent=2))
    return {"frames": count, **alignment}

