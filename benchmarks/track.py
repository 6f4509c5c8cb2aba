"""Accuracy and speed of ``sage track`` on synthetic subjects, whose true meshes are known.

Usage: python benchmarks/track.py [--regimes multiview,monocular,oneshot] [--synth-preset default]
       [--track-preset default] [--video] [--video-seconds 20] [--out WORK] [--docs docs/benchmarks]
       [--threads 2]

For every regime a ``sage synth`` capture (tracked: its own parameters are a tracker-like fit, about
1.7-1.9 mm off the truth) is turned into what a user would give ``sage track`` (one photo, the clip
as a folder of frames, the camera folders with the rig's transforms.json), tracked with
``sage track`` in a fresh process (wall time measured), and compared with the truth
(:func:`sage_core.track.truth.compare_to_truth`: vertex error in the world, in each camera's frame,
and after one similarity alignment of the whole sequence; focal length error).

``--avatars`` also trains an avatar (``sage run``, ``--avatar-preset``) on the tracked capture and one
on the capture's own parameters, and compares them on the same held-out images: the tracking is
rerun with ``crop=false`` and ``neck_line=false`` so the tracked capture's images are the capture's
own pixels, and the scores are taken over the test images both captures hold (matched by the
capture's timestep and camera). The one-shot photo holds no test image: both avatars are scored on
the synthetic capture's held-out set (``gt/novel``: the photo's expression from 14 cameras around
the head, three novel expressions from the six in front), which
:func:`sage_core.track.truth.held_out_for_tracked` moves into the tracked capture's world.

``--video`` also renders a head-turn video of a synthetic head (yaw ±60°, some pitch, ``--video-fps``
frames per second for ``--video-seconds``, ``--video-size``) as an MP4 and tracks it: the time of the
issue's "20-second 30-fps head-turn video" target, and its vertex error against the rendered truth.
The head is rendered as ``sage synth`` renders its subjects, hair volume past the scalp and mouth
interior included (``--video-appearance detailed``); ``smooth`` renders the bare head of earlier
versions, whose outline is the skull's and so favours a silhouette that pulls the whole outline.

``--only-avatars --avatar-label L --avatar-track-set KEY=VALUE`` trains the tracked avatar on a capture
tracked with other settings (its own folders) and records it under ``avatar_variants``.

``--only-clip-seeds 0,1,2`` tracks the monocular clip once per tracking seed with the settings of
``--clip-set`` (and the true focal length with ``--known-focal``) and records the runs under
``--clip-label``: a setting's effect on one clip beside the spread of the seeds.

``--only-backgrounds coffee,rocket,chelsea`` puts the one-shot photo's head (its own mask) over
photographs that ship with scikit-image, tracks each with the masks' colour cut on and off
(``mask_colour_cut``), and scores the written mask against the capture's (intersection over union,
the share of the true mask added and missed) and the vertex error: the person segmentation and the
colour cut meet a real background only there (the other inputs are matted on white and keyed).

Results: ``DOCS/track.json`` (everything measured, the commands and the machine) and ``DOCS/track.md``
(the tables). Captures, inputs and outputs stay in ``WORK`` (default ``bench-track/``) and are reused
when they exist (delete the folder to start over).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's sage_core, whatever is installed
REGIME_OF = {"multiview": "mv-mf", "monocular": "sv-hr", "oneshot": "one-shot"}


def _sage(args: list[str], threads: int) -> tuple[float, str]:
    """Run ``sage <args>`` in a fresh process; returns (wall seconds, output). Raises on failure."""
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), "COLUMNS": "200"}
    t0 = time.time()
    proc = subprocess.run([sys.executable, "-m", "sage_cli.app", *args, "--threads", str(threads)] if args[0] != "synth"
                          else [sys.executable, "-m", "sage_cli.app", *args], capture_output=True, text=True, env=env, cwd=REPO)
    dt = time.time() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"sage {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return dt, proc.stdout


def _capture(work: Path, regime: str, preset: str) -> Path:
    cap = work / f"cap_{regime}_{preset}"
    if not (cap / "gt" / "info.json").is_file():
        _sage(["synth", str(cap), "--regime", regime, "--preset", preset, "--quiet", "--force"], 1)
    return cap


def _train_ratio(info: dict) -> str:
    """``train_ratio=...`` that gives the tracked capture the synthetic capture's train timesteps: the
    ratio written in full precision (six digits, 8/11 -> 0.727273, put a ninth frame in train)."""
    return f"train_ratio={info['config']['train_timesteps'] / info['counts']['timesteps']!r}"


def _input(work: Path, regime: str, synth_preset: str, cap: Path) -> tuple[Path, Path | None]:
    """The ``sage track`` input made from a synthetic capture (written once, reused)."""
    from sage_core.track.truth import input_from_capture

    inp_dir = work / f"in_{regime}_{synth_preset}"
    if not inp_dir.exists():
        return input_from_capture(cap, inp_dir)
    inp = next(p for p in (inp_dir / "rig", inp_dir / "frames", *sorted(inp_dir.glob("*.png"))) if p.exists())
    return inp, (inp_dir / "transforms.json" if (inp_dir / "transforms.json").is_file() else None)


def _means(m: dict) -> dict:
    """PSNR / SSIM / LPIPS of an evaluation's mean block, rounded (LPIPS when measured)."""
    return {k: round(float(m[k]), 4) for k in ("psnr", "ssim", "lpips") if m.get(k) is not None}


def _test_scores(ws: Path, capture_timestep: dict[int, int] | None = None, split: str = "test") -> dict[tuple[int, int], dict]:
    """Per-image metrics of a workspace's phase-2 evaluation of ``split`` (test; novel: the held-out
    set), keyed by (capture timestep, camera); ``capture_timestep`` maps a tracked capture's timestep
    index to the synthetic capture's."""
    doc = json.loads((ws / "eval" / "phase2" / split / "metrics.json").read_text())
    out = {}
    for m in doc["images"]:
        t = m["timestep"] if capture_timestep is None else capture_timestep[m["timestep"]]
        out[(t, m["camera"])] = m
    return out


def _phase2_finished(ws: Path) -> str | None:
    """When the workspace's phase 2 finished (its manifest's ``finished_at``; None: not yet)."""
    manifest = ws / "phase2" / "manifest.json"
    return json.loads(manifest.read_text()).get("finished_at") if manifest.is_file() else None


def avatar_case(work: Path, regime: str, synth_preset: str, track_preset: str, avatar_preset: str, avatar_sets: list[str],
                threads: int, known_focal: bool = False, track_sets: list[str] | None = None) -> dict:
    """Train an avatar on the tracked capture and one on the capture's own parameters; compare them on
    the same test images (module docstring). ``known_focal``: the tracking is given one camera's true
    focal length (as EXIF gives it); ``track_sets``: more ``--set KEY=VALUE`` of the tracking (its
    capture and avatar in folders of their own). The own avatar is the same for all."""
    track_sets = list(track_sets or [])
    tag = _settings_tag(track_sets)
    cap = _capture(work, regime, synth_preset)
    inp, cams = _input(work, regime, synth_preset, cap)
    info = json.loads((cap / "gt" / "info.json").read_text())
    tracked = _tracked_dir(work, regime, synth_preset, track_preset, known_focal, sets=track_sets, uncropped=True)
    model = str(cap / "model" / "synth_flame.pkl")
    if not (tracked / "transforms.json").is_file():
        args = ["track", str(inp), str(tracked), "--flame-model", model, "--preset", track_preset, "--quiet", "--force",
                "--set", _train_ratio(info), "--set", "crop=false", "--set", "neck_line=false"]
        if cams is not None:
            args += ["--cameras", str(cams)]
        if known_focal:
            args += ["--set", f"focal={json.loads((cap / 'transforms.json').read_text())['frames'][0]['fl_x']}"]
        for kv in track_sets:
            args += ["--set", kv]
        _sage(args, threads)
    ids = {f["timestep_index"]: int(f["timestep_id"]) for f in json.loads((tracked / "transforms.json").read_text())["frames"]}
    held_out = None
    if regime == "oneshot":  # the photo holds nothing out: the truth's held-out set, moved into the tracked world
        from sage_core.track.truth import held_out_for_tracked

        held_out = held_out_for_tracked(tracked, cap)
    runs = {}
    for name, capture in (("own", cap), ("tracked", tracked)):
        ws = work / (f"avatar_{regime}_{synth_preset}_{name}{'_focal' if known_focal and name == 'tracked' else ''}"
                     f"{tag if name == 'tracked' else ''}_{avatar_preset}")
        args = ["run", str(capture), str(ws), "--flame-model", model, "--regime", REGIME_OF[regime], "--preset", avatar_preset,
                "--seed", "0", "--quiet"]
        for kv in avatar_sets:
            args += ["--set", kv]
        before = _phase2_finished(ws)
        wall, _ = _sage(args, threads)
        runs[name] = {"workspace": ws.name, "wall_s": round(wall, 1), "command": "sage " + " ".join(args)}
        if before is not None and _phase2_finished(ws) == before:  # nothing retrained: its stages' own times
            runs[name]["reused"] = True
            runs[name]["wall_s"] = round(sum(json.loads(m.read_text()).get("wall_time_s") or 0.0
                                             for m in ws.glob("*/manifest.json")), 1)
    if held_out is None:
        own = _test_scores(work / runs["own"]["workspace"])
        trk = _test_scores(work / runs["tracked"]["workspace"], ids)
    else:
        own, trk = (_test_scores(work / runs[k]["workspace"], split="novel") for k in ("own", "tracked"))
    common = sorted(set(own) & set(trk))
    if not common:
        raise RuntimeError(f"{regime}: the two captures share no test image")
    for name, scores in (("own", own), ("tracked", trk)):
        runs[name]["test_images"] = len(scores)
        runs[name]["common"] = {k: round(sum(float(scores[c][k]) for c in common) / len(common), 4)
                                for k in ("psnr", "ssim", "lpips") if all(scores[c].get(k) is not None for c in common)}
    if held_out is not None:
        for name in ("own", "tracked"):
            doc = json.loads((work / runs[name]["workspace"] / "eval" / "phase2" / "novel" / "metrics.json").read_text())
            runs[name]["novel_groups"] = {
                **{f"subset_{k}": _means(v["overall"]) for k, v in doc.get("subsets", {}).items()},
                **{f"views_{k}": _means(v["overall"]) for k, v in doc.get("view_groups", {}).items()}}
    return {"regime": regime, "track_regime": REGIME_OF[regime], "known_focal": known_focal, "synth_preset": synth_preset,
            "avatar_preset": avatar_preset, "avatar_sets": avatar_sets, "track_sets": track_sets, "common_images": len(common),
            "held_out_alignment": held_out,
            "common_timesteps": sorted({t for t, _ in common}), "runs": runs,
            "psnr_difference_db": round(runs["tracked"]["common"]["psnr"] - runs["own"]["common"]["psnr"], 3)}


def _settings_tag(sets: list[str]) -> str:
    """A short folder suffix for a list of ``--set`` items ("" for none)."""
    return "_" + hashlib.sha1("\n".join(sorted(sets)).encode()).hexdigest()[:8] if sets else ""


def _tracked_dir(work: Path, regime: str, synth_preset: str, track_preset: str, known_focal: bool = False,
                 seed: int | None = None, sets: list[str] | None = None, uncropped: bool = False) -> Path:
    """The folder a tracking is written to (one per regime, presets, focal mode, seed and settings;
    ``uncropped``: an avatar comparison's, tracked without the crop and the neck line)."""
    return work / (f"tracked_{regime}_{synth_preset}_{track_preset}{'_focal' if known_focal else ''}"
                   f"{'_uncropped' if uncropped else ''}{'' if seed is None else f'_seed{seed}'}{_settings_tag(sets or [])}")


def track_case(work: Path, regime: str, synth_preset: str, track_preset: str, threads: int, known_focal: bool = False,
               seed: int | None = None, sets: list[str] | None = None) -> dict:
    """Synthesise (or reuse), track and compare one regime; ``known_focal`` gives one camera's true focal
    length (``--set focal=...``), as a photo's EXIF would; ``seed`` is the tracking's ``--seed`` (None:
    the command's default) and ``sets`` more ``--set`` items for it."""
    from sage_core.track.truth import compare_to_truth

    sets = list(sets or [])
    cap = _capture(work, regime, synth_preset)
    inp, cams = _input(work, regime, synth_preset, cap)
    out = _tracked_dir(work, regime, synth_preset, track_preset, known_focal, seed, sets)
    info = json.loads((cap / "gt" / "info.json").read_text())
    args = ["track", str(inp), str(out), "--flame-model", str(cap / "model" / "synth_flame.pkl"), "--preset", track_preset,
            "--quiet", "--force", "--set", _train_ratio(info)]
    if known_focal:
        frame = json.loads((cap / "transforms.json").read_text())["frames"][0]
        args += ["--set", f"focal={frame['fl_x']}"]
    for kv in sets:
        args += ["--set", kv]
    if seed is not None:
        args += ["--seed", str(seed)]
    if cams is not None:
        args += ["--cameras", str(cams)]
    wall, _ = _sage(args, threads)
    err = compare_to_truth(out, cap)
    report = json.loads((out / "track" / "report.json").read_text())
    return {
        "regime": regime, "track_regime": report["regime"], "synth_preset": synth_preset, "track_preset": track_preset,
        "known_focal": known_focal, "seed": seed, "sets": sets, "image_size": [info["config"]["width"], info["config"]["height"]], "timesteps": report["timesteps"],
        "images": report["images"], "dropped": len(report["dropped"]), "wall_s": round(wall, 1),
        "timings_s": report["timings_s"], "reprojection_px": report["reprojection_px"]["mean"],
        "focal_source": report["camera"]["focal_source"], "steady_pivot": report.get("steady_pivot"), "errors": err,
        "command": "sage " + " ".join(a if a != str(REPO) else "." for a in args),
        "capture_tracking_error": (info.get("tracking") or {}).get("error", {}).get("all"),
    }


def clip_seed_run(work: Path, synth_preset: str, track_preset: str, threads: int, known_focal: bool, seeds: list[int],
                  sets: list[str]) -> dict:
    """The monocular clip tracked once per seed with the same settings: the spread a setting's effect has to
    clear. Returns the per-seed cases (as :func:`track_case`) and the means of the main errors."""
    cases = [track_case(work, "monocular", synth_preset, track_preset, threads, known_focal, seed=s, sets=sets)
             for s in seeds]

    return {"known_focal": known_focal, "sets": list(sets), "seeds": seeds, "synth_preset": synth_preset,
            "track_preset": track_preset, "cases": cases, "mean": _clip_means(cases)}


def _clip_means(cases: list[dict]) -> dict:
    """The means over a clip run's seeds of its cases' main errors."""
    def mean(get, digits: int = 3) -> float:
        return round(float(np.mean([get(c["errors"]) for c in cases])), digits)

    return {"aligned_mm": mean(lambda e: e["aligned"]["mean_mm"]),
            "rigid_per_timestep_mm": mean(lambda e: e["rigid_per_timestep"]["mean_mm"]),
            "camera_mm": mean(lambda e: e["camera"]["mean_mm"]),
            "focal_rel_error": mean(lambda e: e["focal_rel_error"], 4)}


BACKGROUNDS = ("coffee", "rocket", "chelsea")
"""scikit-image photographs the background cases use (``skimage.data.<name>()``)."""


def _mask_scores(tracked: Path, truth_mask: np.ndarray) -> dict:
    """The written mask of a one-image capture against the truth's (in the input image's pixels):
    intersection over union, and the truth's area added / missed, as shares of the truth's area."""
    from sage_core.data.imageio import read_image
    from sage_core.track.observe import Window

    cam = json.loads((tracked / "track" / "report.json").read_text())["camera"]["cameras"][0]
    truth = Window(*cam["crop"], *cam["output_size"]).apply(truth_mask) > 0.5  # the crop sage track wrote
    mine = read_image(tracked / "fg_masks" / "00000_00.png")[..., 0] > 0.5
    area = max(int(truth.sum()), 1)
    return {"iou": round(float((mine & truth).sum() / max((mine | truth).sum(), 1)), 4),
            "added": round(float((mine & ~truth).sum() / area), 4), "missed": round(float((~mine & truth).sum() / area), 4)}


def background_cases(work: Path, synth_preset: str, track_preset: str, threads: int, names: list[str]) -> list[dict]:
    """The one-shot head over each named scikit-image photograph, tracked with the colour cut off and on."""
    import cv2
    from skimage import data

    from sage_core.data.imageio import read_image, write_image
    from sage_core.track.truth import compare_to_truth

    cap = _capture(work, "oneshot", synth_preset)
    inp, _ = _input(work, "oneshot", synth_preset, cap)
    head = read_image(inp)[..., :3]
    alpha = read_image(cap / "fg_masks" / "00000_00.png")[..., :1]
    out = []
    for name in names:
        photo = getattr(data, name)()[..., :3].astype(np.float32) / 255.0
        bg = cv2.resize(photo, (head.shape[1], head.shape[0]), interpolation=cv2.INTER_AREA)
        src = work / f"in_oneshot_{synth_preset}_on_{name}" / "00000.png"
        if not src.is_file():
            write_image(src, head * alpha + bg * (1.0 - alpha))
        row = {"background": name, "synth_preset": synth_preset, "track_preset": track_preset}
        for mode in ("off", "on"):
            tracked = work / f"tracked_oneshot_{synth_preset}_on_{name}_cut_{mode}"
            args = ["track", str(src), str(tracked), "--flame-model", str(cap / "model" / "synth_flame.pkl"), "--preset", track_preset,
                    "--quiet", "--force", "--set", "train_ratio=1.0", "--set", f"mask_colour_cut={mode}"]
            wall, _ = _sage(args, threads)
            err = compare_to_truth(tracked, cap)
            report = json.loads((tracked / "track" / "report.json").read_text())
            row[f"cut_{mode}"] = {"mask": _mask_scores(tracked, alpha[..., 0]), "aligned_mm": err["aligned"]["mean_mm"],
                                  "world_mm": err["world"]["mean_mm"], "reprojection_px": report["reprojection_px"]["mean"],
                                  "masks": report["masks"], "wall_s": round(wall, 1), "timings_s": report["timings_s"],
                                  "command": "sage " + " ".join(a if a != str(REPO) else "." for a in args)}
        out.append(row)
    return out


def render_video(path: Path, seconds: float, fps: float, size: tuple[int, int], seed: int = 0,
                 sway_mm: float = 0.0, appearance: str = "detailed") -> tuple[Path, dict]:
    """A head-turn MP4 of a synthetic head (exact model) and its truth: model file, per-frame FLAME
    parameters and the camera (VHAP monocular convention). ``sway_mm``: the head also drifts, up to
    this far towards and away from the camera and half as far sideways (slower than the turns).
    ``appearance``: detailed renders the subject as ``sage synth`` does (its hair volume past the
    scalp, mouth interior, skin detail); smooth the bare head of earlier versions of this benchmark
    (skin only, its outline the skull's)."""
    import torch

    from sage_core.data.synthetic import (
        make_subject,
        neck_line_mask,
        preset,
        render_head,
    )
    from sage_core.data.synthetic.model_files import flame_model, write_model_files
    from sage_core.data.synthetic.motion import monocular_camera
    from sage_core.export.video import VideoWriter

    W, H = size
    cfg = preset("small", regime="monocular", seed=seed, width=W, height=H, tracking="exact", appearance=appearance)
    subject = make_subject(cfg)
    model_files = write_model_files(subject.head, path.parent / "video_model")
    cam = monocular_camera(W, H, cfg.mono_focal)
    n = int(round(seconds * fps))
    s = np.arange(n) / max(n - 1, 1)
    yaw = np.deg2rad(60.0 * np.sin(2 * np.pi * s))  # right, back through frontal, left and back
    pitch = np.deg2rad(8.0 * np.sin(4 * np.pi * s + 0.5))
    rot = np.stack([pitch, yaw, np.zeros(n)], 1)
    sway = sway_mm / 1000.0
    trans = np.stack([0.5 * sway * np.sin(2 * np.pi * 0.7 * s + 1.0), np.zeros(n), sway * np.sin(2 * np.pi * 1.5 * s)], 1)
    model = flame_model(subject.head)
    with torch.no_grad():
        verts = model(shape=torch.as_tensor(subject.shape, dtype=torch.float64), rotation=torch.as_tensor(rot, dtype=torch.float64),
                      translation=torch.as_tensor(trans, dtype=torch.float64),
                      static_offset=torch.as_tensor(subject.static_offset, dtype=torch.float64)).vertices.numpy()
        neutral = model(shape=torch.as_tensor(subject.shape, dtype=torch.float64),
                        static_offset=torch.as_tensor(subject.static_offset, dtype=torch.float64))
    crease = np.zeros(verts.shape[1])
    with VideoWriter(path, fps=fps, width=W, height=H, quality=9) as vw:
        for t in range(n):
            if appearance == "detailed":
                r = subject.render(verts[t], cam, crease, supersample=1)
            else:
                r = render_head(subject.head, verts[t], cam, subject.app, crease, supersample=1)
            neck = neck_line_mask(subject.head, verts[t], cam)
            vw.write(r.rgb * neck[..., None] + (1 - neck[..., None]))
    np.savez(path.with_suffix(".truth.npz"), vertices=verts.astype(np.float32), rotation=rot, translation=trans, K=cam.K, w2c=cam.w2c,
             faces=subject.head.faces)
    del neutral
    return path, {"model": str(model_files["npz"]), "frames": n, "appearance": appearance}


TURN_BINS: tuple[tuple[str, float, float], ...] = (("within 15°", 0.0, 15.0), ("15–45°", 15.0, 45.0), ("beyond 45°", 45.0, 91.0))
"""The video's frames grouped by the truth's head turn (absolute yaw, degrees) for ``errors.by_turn``."""


def video_case(work: Path, seconds: float, fps: float, size: tuple[int, int], track_preset: str, threads: int,
               sway_mm: float = 0.0, sets: list[str] | None = None, appearance: str = "detailed") -> dict:
    """Render (or reuse) the head-turn video (``appearance`` as :func:`render_video`), track it (``sets``:
    extra ``--set KEY=VALUE`` of the tracking), and compare the meshes with the rendered truth."""
    import torch

    from sage_core.data.capture import read_capture
    from sage_core.flame import FlameModel, load_flame_model
    from sage_core.data.synthetic.model_files import MASKS_NAME
    from sage_core.track.truth import error_summary, region_errors, rigid_fit, similarity_fit

    sway = f"_sway{sway_mm:g}mm" if sway_mm else ""
    look = "" if appearance == "detailed" else f"_{appearance}"
    video = work / f"headturn_{int(seconds)}s_{int(fps)}fps_{size[0]}x{size[1]}{sway}{look}.mp4"
    meta_path = video.with_suffix(".json")
    if not meta_path.is_file():
        t0 = time.time()
        _, meta = render_video(video, seconds, fps, size, sway_mm=sway_mm, appearance=appearance)
        meta["render_s"] = round(time.time() - t0, 1)
        meta_path.write_text(json.dumps(meta))
    meta = json.loads(meta_path.read_text())
    # one folder per video and settings, so runs of the same video with other settings may overlap
    out = work / f"tracked_video{sway}{look}_{track_preset}{_settings_tag(sets or [])}"
    args = ["track", str(video), str(out), "--flame-model", meta["model"], "--preset", track_preset, "--quiet", "--force"]
    for kv in sets or []:
        args += ["--set", kv]
    wall, _ = _sage(args, threads)
    truth = np.load(video.with_suffix(".truth.npz"))
    tr = read_capture(out, check_images=False)
    fm = FlameModel(load_flame_model(meta["model"]), dtype=torch.float64)
    with torch.no_grad():
        v = fm(**tr.params.to_torch(dtype=torch.float64)).vertices.numpy()
    frames = {f["timestep_index"]: int(f["timestep_id"].split("_")[1]) for f in json.loads((out / "transforms.json").read_text())["frames"]}
    w2c = truth["w2c"]
    pairs = []  # (tracked, true) vertices (V, 3) of every frame in the video camera's frame
    for row, t in enumerate(tr.params.timesteps):
        f = next(fr for fr in tr.frames if fr.timestep == int(t))
        a = v[row] @ f.camera.w2c[:3, :3].T + f.camera.w2c[:3, 3]
        b = truth["vertices"][frames[int(t)]].astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
        pairs.append((a, b))
    R, tv, s = similarity_fit(np.concatenate([a for a, _ in pairs]), np.concatenate([b for _, b in pairs]))
    # per frame (V,) vertex errors in mm: in the camera's frame, after the one similarity, and with each
    # frame's mesh moved alone (the shape and expression error without the frame's pose and depth)
    camera = [np.linalg.norm(a - b, axis=1) * 1000 for a, b in pairs]
    aligned = [np.linalg.norm(s * a @ R.T + tv - b, axis=1) * 1000 for a, b in pairs]
    rigid = []
    for a, b in pairs:
        Rr, tr_ = rigid_fit(a, b)
        rigid.append(np.linalg.norm(a @ Rr.T + tr_ - b, axis=1) * 1000)
    regions = region_errors(Path(meta["model"]).parent / MASKS_NAME, camera=np.mean(camera, 0),
                            aligned=np.mean(aligned, 0), rigid=np.mean(rigid, 0))
    yaw = np.abs(np.rad2deg(truth["rotation"][[frames[int(t)] for t in tr.params.timesteps], 1]))
    by_turn = {}
    for name, lo, hi in TURN_BINS:
        sel = (yaw >= lo) & (yaw < hi)
        if sel.any():
            by_turn[name] = {"frames": int(sel.sum()), "aligned_mm": round(float(np.mean([aligned[i].mean() for i in np.flatnonzero(sel)])), 3)}
    report = json.loads((out / "track" / "report.json").read_text())
    focal = report["camera"]["cameras"][0]["focal_input_px"]
    return {
        "video": video.name, "appearance": appearance, "seconds": seconds, "fps": fps, "size": list(size), "frames": meta["frames"], "sway_mm": sway_mm,
        "timesteps": report["timesteps"], "dropped": len(report["dropped"]), "wall_s": round(wall, 1),
        "timings_s": report["timings_s"], "reprojection_px": report["reprojection_px"]["mean"],
        "steady_pivot": report.get("steady_pivot"),
        "errors": {"camera": error_summary([(e.mean(), e.max()) for e in camera]),
                   "aligned": {**error_summary([(e.mean(), e.max()) for e in aligned]), "scale": round(s, 4)},
                   "rigid_per_timestep": error_summary([(e.mean(), e.max()) for e in rigid]),
                   "regions": regions, "by_turn": by_turn,
                   "focal_rel_error": round(focal / float(truth["K"][0, 0]) - 1, 4)},
        "command": "sage " + " ".join(args), "render_s": meta.get("render_s"),
    }


def _machine() -> dict:
    import torch

    return {"cpus": os.cpu_count(), "torch": torch.__version__, "python": platform.python_version(),
            "load_average": [round(x, 2) for x in os.getloadavg()], "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}


def _sec(timings: dict, key: str) -> str:
    return f"{timings[key]:.0f}" if key in timings else "—"


def _fmt(e: dict) -> str:
    return f"{e['mean_mm']:.2f} / {e['max_mm']:.1f}"


def _region(e: dict, name: str) -> str:
    r = (e.get("regions") or {}).get(name)
    return f"{r['world_mm']:.2f} / {r['aligned_mm']:.2f}" if r else "—"


def _video_label(v: dict) -> str:
    sway = f", drifting ±{v['sway_mm']:g} mm" if v.get("sway_mm") else ""
    look = "with hair" if v.get("appearance") == "detailed" else "bare head"
    return f"{v['seconds']:.0f} s ({v['frames']} frames{sway}, {look})"


def _video_shape_table(runs: list[dict]) -> list[str]:
    """Where a video's error lies (runs that measured it): each frame moved alone, FLAME's regions, the head's turn."""
    rows = [r for r in runs if "rigid_per_timestep" in r["video"]["errors"]]
    if not rows:
        return []
    lines = ["", "Where the error lies (mm). *Rigid per frame*: each frame's mesh moved alone onto the truth's (the shape "
                 "and expression error, without the frame's pose and depth); regions: FLAME's face, neck and scalp masks, "
                 "after the one similarity of the whole video / each frame moved alone; turns: the one similarity's error over "
                 "the frames whose true head turn (|yaw|) lies in the range.", "",
             "| video | fit | aligned | rigid per frame | face | neck | scalp | " + " | ".join(f"turned {n}" for n, _, _ in TURN_BINS) + " |",
             "|---|---|---:|---:|---:|---:|---:|" + "---:|" * len(TURN_BINS)]
    for r in rows:
        e = r["video"]["errors"]
        reg = e.get("regions") or {}
        cells = [f"{reg[k]['aligned_mm']:.2f} / {reg[k]['rigid_mm']:.2f}" if k in reg else "—" for k in ("face", "neck", "scalp")]
        turns = [f"{e['by_turn'][n]['aligned_mm']:.2f} ({e['by_turn'][n]['frames']})" if n in e.get("by_turn", {}) else "—"
                 for n, _, _ in TURN_BINS]
        lines.append(f"| {_video_label(r['video'])} | {r['label']} | {e['aligned']['mean_mm']:.2f} | "
                     f"{e['rigid_per_timestep']['mean_mm']:.2f} | " + " | ".join(cells + turns) + " |")
    return lines


def markdown(doc: dict) -> str:
    """The tables of ``track.md``."""
    lines = ["# `sage track` on synthetic subjects", "",
             f"Command: `{doc['command']}`", "",
             f"Machine: {doc['machine']['cpus']} CPUs, torch {doc['machine']['torch']}, {doc['threads']} thread(s); load average "
             f"before/after {doc['machine']['load_average']} / {doc['load_after']}; {doc['machine']['date_utc']} UTC.", "",
             "Vertex error in mm, mean over timesteps of the mean over vertices / the largest over all vertices, against the "
             "true meshes (`gt/meshes`): **world** in the capture's world (the rig's calibration is given), **camera** in each "
             "image's camera frame, **aligned** after one similarity transform for the whole sequence (size and distance of a "
             "head seen by one uncalibrated camera trade off). The capture's own parameters (`--tracking fitted`) are off by "
             "the last column.", "",
             "**rigid per timestep**: after a rotation and translation of each timestep's mesh alone (shape and expression "
             "error without pose and camera).", "",
             "**face**, **scalp**: the mean world / aligned error over the FLAME masks' face and scalp vertices (the scalp, "
             "half of the vertices, lies under the hair, which only its outline shows).", "",
             "| regime | images | size | wall time (s) | landmark error (px) | world (mm) | camera (mm) | aligned (mm) | scale | rigid per timestep (mm) | face (mm) | scalp (mm) | focal error | capture's own (mm) |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in doc["cases"]:
        e = r["errors"]
        own = r["capture_tracking_error"]
        own_text = f"{own['mean_mm']:.2f} / {own['max_mm']:.1f}" if own else "—"
        label = f"{r['regime']} ({r['track_regime']}{', focal length given' if r.get('known_focal') else ''})"
        lines.append(f"| {label} | {r['images']} | {r['image_size'][0]}x{r['image_size'][1]} | "
                     f"{r['wall_s']:.0f} | {r['reprojection_px']:.2f} | {_fmt(e['world'])} | {_fmt(e['camera'])} | "
                     f"{_fmt(e['aligned'])} | {e['aligned']['scale']:.3f} | "
                     f"{_fmt(e['rigid_per_timestep']) if 'rigid_per_timestep' in e else '—'} | {_region(e, 'face')} | "
                     f"{_region(e, 'scalp')} | {e['focal_rel_error']:+.1%} | {own_text} |")
    notes = doc.get("notes") or {}
    if notes.get("cases"):
        lines += ["", notes["cases"]]
    runs = doc.get("video_runs") or ([{"label": "", "run": {"command": doc["command"], "machine": doc["machine"],
                                                             "load_after": doc["load_after"]}, "video": doc["video"]}]
                                     if doc.get("video") else [])
    if runs:
        lines += ["", "Head-turn videos of a synthetic head (yaw ±60°, 360x640, 30 fps; some also drifting towards and away from "
                      "the camera by the amount given and half as far sideways): with hair, the subject as `sage synth` renders "
                      "it (hair volume past the scalp, mouth interior, skin detail; `--video-appearance detailed`, the default), "
                      "or the bare head of earlier versions whose outline is the skull's (`smooth`). Times in seconds: the wall time of "
                      "the whole command and its phases; the fit is split into the keyframes' full schedule and the tracking "
                      "of every frame (a joint fit of all frames has neither). Commands, machine and load per row in "
                      "`track.json` (`video_runs`).", "",
                  "| video | fit | frames tracked | dropped | wall time | faces | images | embedding | fit | fit: keyframes "
                  "| fit: tracking | masks | landmark error (px) | camera (mm) | aligned (mm) | focal error |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in runs:
            v = r["video"]
            e = v["errors"]
            lines.append(f"| {_video_label(v)} | {r['label']} | {v['timesteps']} | {v['dropped']} | "
                         f"{v['wall_s']:.0f} | "
                         + " | ".join(_sec(v["timings_s"], k) for k in ("faces", "images", "embedding", "fit", "fit_keyframes",
                                                                         "fit_track", "masks"))
                         + f" | {v['reprojection_px']:.2f} | {_fmt(e['camera'])} | {_fmt(e['aligned'])} | {e['focal_rel_error']:+.1%} |")
        lines += _video_shape_table(runs)
        if notes.get("video"):
            lines += ["", notes["video"]]
    if doc.get("clip_runs"):
        frames = sorted({c.get("timesteps") for r in doc["clip_runs"] for c in r["cases"]} - {None})
        lines += ["", f"The monocular clip (a folder of {' or '.join(map(str, frames)) or 'its'} frames) tracked at several seeds "
                      "with the settings given "
                      "(`--only-clip-seeds`): aligned error per seed, and the means. Commands per seed in `track.json` "
                      "(`clip_runs[].cases[].command`).", "",
                  "| settings (`--set`) | focal length | aligned (mm) per seed | aligned mean (mm) | rigid per timestep mean (mm) "
                  "| camera mean (mm) | focal error mean | run (UTC) |",
                  "|---|---|---|---:|---:|---:|---:|---|"]
        for r in doc["clip_runs"]:
            per = ", ".join(f"{c['errors']['aligned']['mean_mm']:.2f} ({c['seed']})" for c in r["cases"])
            m = r["mean"]
            sets = " ".join(f"`{kv}`" for kv in r["sets"]) or "—"
            lines.append(f"| {r['label']}: {sets} | {'given' if r['known_focal'] else 'fitted'} | {per} | {m['aligned_mm']:.2f} | "
                         f"{m['rigid_per_timestep_mm']:.2f} | {m['camera_mm']:.2f} | {m['focal_rel_error']:+.1%} | "
                         f"{r.get('machine', {}).get('date_utc', '—')} |")
    lines += ["", "Commands per case are in `track.json` (`cases[].command`)."]
    if doc.get("avatars"):
        a0 = doc["avatars"][0]
        lines += ["", "Avatars trained on the tracked capture against avatars trained on the capture's own parameters (the "
                      "tracker-like fit `sage synth` writes), scored on the same test images: the tracking rerun with "
                      "`crop=false neck_line=false`, so both captures hold the same pixels; images matched by the capture's "
                      f"timestep and camera. Training: `sage run ... --preset {a0['avatar_preset']}"
                      + "".join(f" --set {kv}" for kv in a0["avatar_sets"]) + "`, seed 0; commands in `track.json` "
                      "(`avatars[].runs`).", "",
                  "| regime | test images | own parameters: PSNR / SSIM / LPIPS | `sage track`'s: PSNR / SSIM / LPIPS | difference (dB) "
                  "| run (UTC) | training wall time, own / tracked (s) |",
                  "|---|---:|---|---|---:|---|---|"]
        for a in doc["avatars"]:
            o, t = a["runs"]["own"]["common"], a["runs"]["tracked"]["common"]
            walls = " / ".join(f"{a['runs'][k]['wall_s']:.0f}" + (" (reused)" if a["runs"][k].get("reused") else "")
                               for k in ("own", "tracked"))
            lines.append(f"| {a['regime']} ({a['track_regime']}{', focal length given' if a.get('known_focal') else ''}) | {a['common_images']} | {o['psnr']:.2f} / {o['ssim']:.4f} / "
                         f"{o.get('lpips', float('nan')):.4f} | {t['psnr']:.2f} / {t['ssim']:.4f} / {t.get('lpips', float('nan')):.4f} | "
                         f"{a['psnr_difference_db']:+.2f} | {a.get('machine', {}).get('date_utc', '—')} | {walls} |")
        for a in doc["avatars"]:
            o, t = (a["runs"][k].get("novel_groups") for k in ("own", "tracked"))
            if o and t:
                lines += ["", f"{a['regime']}{' (focal length given)' if a.get('known_focal') else ''}: the held-out set by "
                          "group, own / `sage track`'s, PSNR / SSIM / LPIPS: "
                          + "; ".join(f"{k.replace('subset_', '').replace('views_', 'views ')} {o[k]['psnr']:.2f} / "
                                      f"{o[k]['ssim']:.4f} / {o[k].get('lpips', float('nan')):.4f} against {t[k]['psnr']:.2f} / "
                                      f"{t[k]['ssim']:.4f} / {t[k].get('lpips', float('nan')):.4f}"
                                      for k in o if k in t)
                          + f" (held-out cameras anchored at the {a['held_out_alignment'].get('anchor', 'mesh')}: scale "
                          f"{a['held_out_alignment']['scale']:.3f}, focal lengths × "
                          f"{a['held_out_alignment'].get('focal_ratio', 1.0):.3f}; `held_out_for_tracked`)."]
        lines += ["", "A regime's row is replaced only when `--only-avatars` trains it again."]
        if any(r.get("reused") for a in doc["avatars"] for r in a["runs"].values()):
            lines[-1] += (" (reused): the avatar of an earlier run of the same command, whose workspace the benchmark "
                          "found complete; its time is the sum of its stages' recorded times.")
    if doc.get("avatar_variants"):
        lines += ["", "Avatars on captures tracked with other settings (`--only-avatars --avatar-label`, "
                      "`--avatar-track-set`; `avatar_variants` in `track.json`), against the same own-parameter avatar:", "",
                  "| variant | regime | tracking `--set` | `sage track`'s: PSNR / SSIM / LPIPS | difference (dB) | run (UTC) |",
                  "|---|---|---|---|---:|---|"]
        for a in doc["avatar_variants"]:
            t = a["runs"]["tracked"]["common"]
            sets = " ".join(f"`{kv}`" for kv in a.get("track_sets") or []) or "—"
            lines.append(f"| {a['label']} | {a['regime']}{', focal length given' if a.get('known_focal') else ''} | {sets} | "
                         f"{t['psnr']:.2f} / {t['ssim']:.4f} / {t.get('lpips', float('nan')):.4f} | "
                         f"{a['psnr_difference_db']:+.2f} | {a.get('machine', {}).get('date_utc', '—')} |")
    if doc.get("backgrounds"):
        lines += ["", "The one-shot photo's head over photographs from scikit-image (`--only-backgrounds`), tracked with the "
                      "masks' colour cut off and on (`--set mask_colour_cut=off|on`; `auto` turns it on for such "
                      "backgrounds): the written mask against the truth's (intersection over union; the truth's area "
                      "added and missed) and the vertex error after alignment.", "",
                  "| background | mask IoU, cut off / on | added, off / on | missed, off / on | aligned mm, off / on "
                  "| world mm, off / on | landmark px, off / on |",
                  "|---|---|---|---|---|---|---|"]
        for r in doc["backgrounds"]:
            f, n = r["cut_off"], r["cut_on"]
            lines.append(f"| `skimage.data.{r['background']}()` | {f['mask']['iou']:.3f} / {n['mask']['iou']:.3f} | "
                         f"{f['mask']['added']:.1%} / {n['mask']['added']:.1%} | {f['mask']['missed']:.1%} / {n['mask']['missed']:.1%} | "
                         f"{f['aligned_mm']:.2f} / {n['aligned_mm']:.2f} | {f['world_mm']:.1f} / {n['world_mm']:.1f} | "
                         f"{f['reprojection_px']:.2f} / {n['reprojection_px']:.2f} |")
    return "\n".join(lines) + "\n"


def _write(docs: Path, doc: dict) -> None:
    """``docs/track.json`` and ``docs/track.md`` from ``doc``; the tables printed."""
    docs.mkdir(parents=True, exist_ok=True)
    (docs / "track.json").write_text(json.dumps(doc, indent=1) + "\n")
    (docs / "track.md").write_text(markdown(doc))
    print(markdown(doc))


def rescore(work: Path, docs: Path) -> None:
    """Recompute the vertex errors of the cases and the clip's seed runs in ``docs/track.json`` from their
    tracked captures in ``work`` (after a change of the error measures), keeping the measured times;
    rewrites both files."""
    from sage_core.track.truth import compare_to_truth

    def score(r: dict) -> None:
        out = _tracked_dir(work, r["regime"], r["synth_preset"], r["track_preset"], bool(r.get("known_focal")),
                           r.get("seed"), r.get("sets"))
        r["errors"] = compare_to_truth(out, work / f"cap_{r['regime']}_{r['synth_preset']}")

    doc = json.loads((docs / "track.json").read_text())
    for r in doc["cases"]:
        score(r)
    for run in doc.get("clip_runs") or []:
        for r in run["cases"]:
            score(r)
        run["mean"] = _clip_means(run["cases"])
    doc["rescored"] = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    _write(docs, doc)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--regimes", default="multiview,monocular,oneshot")
    ap.add_argument("--synth-preset", default="default", choices=("tiny", "small", "default"))
    ap.add_argument("--multiview-preset", default=None, choices=("tiny", "small", "default"),
                    help="synth preset of the multiview capture (default: --synth-preset; 'small' renders 96 images instead of 224)")
    ap.add_argument("--track-preset", default="default", choices=("tiny", "default"))
    ap.add_argument("--video", action="store_true", help="also render and track the head-turn video")
    ap.add_argument("--video-seconds", type=float, default=20.0)
    ap.add_argument("--video-fps", type=float, default=30.0)
    ap.add_argument("--video-size", default="360x640")
    ap.add_argument("--video-sway", type=float, default=0.0, metavar="MM",
                    help="the video's head also drifts this far towards and away from the camera (half as far sideways)")
    ap.add_argument("--video-label", default=None,
                    help="add the video run to DOCS/track.json's video_runs under this label (replacing a run of the same "
                         "video and label) instead of making it the only video row")
    ap.add_argument("--video-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a --set for the video's tracking (repeatable)")
    ap.add_argument("--video-appearance", default="detailed", choices=("detailed", "smooth"),
                    help="detailed: the synthetic subject with its hair volume, mouth and skin detail; smooth: the bare "
                         "head of earlier versions (its outline the skull's)")
    ap.add_argument("--out", type=Path, default=Path("bench-track"))
    ap.add_argument("--docs", type=Path, default=REPO / "docs" / "benchmarks")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--known-focal", action="store_true",
                    help="also track the one-camera regimes with the true focal length given (as EXIF would give it)")
    ap.add_argument("--only-known-focal", action="store_true",
                    help="run only those and add them to DOCS/track.json's cases (replacing earlier known-focal cases)")
    ap.add_argument("--avatars", action="store_true",
                    help="also train avatars on the tracked and the own-parameter captures (monocular, multiview) and compare them")
    ap.add_argument("--only-avatars", action="store_true",
                    help="run only the avatar comparison and put it into DOCS/track.json beside the cases already there")
    ap.add_argument("--avatar-preset", default="tiny", choices=("tiny", "small", "default"))
    ap.add_argument("--avatar-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a --set for both avatars' sage run (repeatable)")
    ap.add_argument("--avatar-track-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a --set for the tracking of the avatars' captures (repeatable; needs --avatar-label)")
    ap.add_argument("--avatar-label", default=None,
                    help="with --only-avatars: put the comparison into DOCS/track.json's avatar_variants under this "
                         "label (replacing one of the same label, regime and focal mode) instead of the main avatar rows")
    ap.add_argument("--only-backgrounds", default=None, metavar="NAMES",
                    help=f"run only the one-shot head over these scikit-image photographs (comma-separated, e.g. {','.join(BACKGROUNDS)}) "
                         "and put them into DOCS/track.json beside the cases already there")
    ap.add_argument("--only-clip-seeds", default=None, metavar="SEEDS",
                    help="track only the monocular clip, once per tracking seed (comma-separated, e.g. 0,1,2), with the "
                         "--clip-set settings (and the true focal length with --known-focal), and put the runs into "
                         "DOCS/track.json's clip_runs under --clip-label (replacing a run of the same label and focal)")
    ap.add_argument("--clip-label", default="default", help="the label of an --only-clip-seeds run")
    ap.add_argument("--clip-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a --set for the clip's tracking in --only-clip-seeds (repeatable)")
    ap.add_argument("--rescore", action="store_true",
                    help="recompute the errors of DOCS/track.json's tracked captures in WORK, the clip's seed runs "
                         "included (no tracking; times kept)")
    a = ap.parse_args(argv)
    if a.avatar_track_set and a.avatar_label is None:
        ap.error("--avatar-track-set needs --avatar-label (a variant is not recorded as the main avatar rows)")
    if a.avatar_label is not None and not a.only_avatars:
        ap.error("--avatar-label needs --only-avatars")
    if a.rescore:
        rescore(a.out, a.docs)
        return
    a.out.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/track.py " + shlex.join(argv if argv is not None else sys.argv[1:])
    machine = _machine()
    avatars = None
    if a.avatars or a.only_avatars:
        avatars = [avatar_case(a.out, r, (a.multiview_preset or a.synth_preset) if r == "multiview" else a.synth_preset,
                               a.track_preset, a.avatar_preset, a.avatar_set, a.threads, track_sets=a.avatar_track_set)
                   for r in a.regimes.split(",") if r in ("monocular", "multiview", "oneshot")]
        if a.known_focal:  # the one-camera regimes tracked again with the true focal length given
            avatars += [avatar_case(a.out, r, a.synth_preset, a.track_preset, a.avatar_preset, a.avatar_set, a.threads,
                                    known_focal=True, track_sets=a.avatar_track_set)
                        for r in a.regimes.split(",") if r in ("monocular", "oneshot")]
        for x in avatars:
            x["machine"] = machine
            x["benchmark_command"] = command
            if a.avatar_label is not None:
                x["label"] = a.avatar_label
    one_camera = [r for r in a.regimes.split(",") if r in ("monocular", "oneshot")]
    # each branch reads the results file only after its measurements, just before it writes it back, so
    # that runs of the benchmark side by side do not drop each other's entries
    if a.only_known_focal:
        extra = [track_case(a.out, r, a.synth_preset, a.track_preset, a.threads, known_focal=True) for r in one_camera]
        for x in extra:
            x["machine"] = machine
            x["benchmark_command"] = command
        doc = json.loads((a.docs / "track.json").read_text())
        doc["cases"] = [c for c in doc["cases"] if not c.get("known_focal")] + extra
        _write(a.docs, doc)
        return
    if a.only_clip_seeds is not None:
        run = clip_seed_run(a.out, a.synth_preset, a.track_preset, a.threads, a.known_focal,
                            [int(x) for x in a.only_clip_seeds.split(",")], a.clip_set)
        run.update(label=a.clip_label, machine=machine, benchmark_command=command)
        doc = json.loads((a.docs / "track.json").read_text())
        doc["clip_runs"] = [r for r in doc.get("clip_runs") or []
                            if (r["label"], r["known_focal"]) != (a.clip_label, a.known_focal)] + [run]
        _write(a.docs, doc)
        return
    if a.only_backgrounds:
        rows = background_cases(a.out, a.synth_preset, a.track_preset, a.threads, a.only_backgrounds.split(","))
        for x in rows:
            x["machine"] = machine
            x["benchmark_command"] = command
        doc = json.loads((a.docs / "track.json").read_text())
        ran = {x["background"] for x in rows}
        doc["backgrounds"] = [x for x in doc.get("backgrounds") or [] if x["background"] not in ran] + rows
        _write(a.docs, doc)
        return
    if a.only_avatars and a.avatar_label is not None:
        doc = json.loads((a.docs / "track.json").read_text())
        ran = {(x["regime"], bool(x.get("known_focal"))) for x in avatars}
        doc["avatar_variants"] = [x for x in doc.get("avatar_variants") or []
                                  if (x["label"], x["regime"], bool(x.get("known_focal"))) not in
                                  {(a.avatar_label, *k) for k in ran}] + avatars
        _write(a.docs, doc)
        return
    if a.only_avatars:
        doc = json.loads((a.docs / "track.json").read_text())
        # regimes this run did not train keep their earlier comparison (with its own command and machine)
        ran = {(x["regime"], bool(x.get("known_focal"))) for x in avatars}
        doc["avatars"] = [x for x in doc.get("avatars") or [] if (x["regime"], bool(x.get("known_focal"))) not in ran] + avatars
        doc.pop("avatar", None)  # the earlier, not like-for-like comparison
        _write(a.docs, doc)
        return
    cases = [track_case(a.out, r, (a.multiview_preset or a.synth_preset) if r == "multiview" else a.synth_preset, a.track_preset,
                        a.threads) for r in a.regimes.split(",") if r]
    if a.known_focal:
        cases += [track_case(a.out, r, a.synth_preset, a.track_preset, a.threads, known_focal=True) for r in one_camera]
    video = None
    if a.video:
        w, h = (int(x) for x in a.video_size.split("x"))
        video = video_case(a.out, a.video_seconds, a.video_fps, (w, h), a.track_preset, a.threads, a.video_sway, a.video_set,
                           a.video_appearance)
    old = json.loads((a.docs / "track.json").read_text()) if (a.docs / "track.json").is_file() else {}
    if video is not None and a.video_label is not None:
        run = {"label": a.video_label, "run": {"command": command, "machine": machine,
                                               "load_after": [round(x, 2) for x in os.getloadavg()]}, "video": video}
        old["video_runs"] = [r for r in old.get("video_runs", []) if (r["video"]["video"], r["label"]) != (video["video"], a.video_label)] + [run]
        old.pop("video", None)
        _write(a.docs, old)
        return
    doc = {"command": command, "machine": machine, "threads": a.threads, "cases": cases or old.get("cases", []),
           "load_after": [round(x, 2) for x in os.getloadavg()]}
    # what this run did not measure is kept from the previous results (with its own commands and machine)
    doc["video"] = video
    for key in ("video_runs", "notes", "cases_previous_version", "clip_runs", "clip_runs_superseded", "backgrounds",
                "avatar_variants"):
        if key in old and not (key == "video_runs" and video is not None):
            doc[key] = old[key]
    if video is None and old.get("video") and "video_runs" not in old:
        doc["video"] = old["video"]
    doc["avatars"] = avatars if avatars is not None else old.get("avatars")
    _write(a.docs, doc)


if __name__ == "__main__":
    main()
