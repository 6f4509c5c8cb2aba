"""How close the landmark model's points lie to the truth on a synthetic head-turn video, found from each
frame's detection or followed from the previous frame's landmarks.

    python benchmarks/landmark_follow.py --video bench-track/headturn_20s_30fps_360x640.mp4 \\
        --embedding bench-track/tracked_video_default/track/landmark_embedding.npz [--docs docs/benchmarks]

The video and its truth (``VIDEO`` with ``.truth.npz`` beside it: per-frame vertices, rotations, the
camera) are what ``benchmarks/track.py --video`` renders; the embedding is the one ``sage track`` calibrated
on the video's model (``OUT/track/landmark_embedding.npz``). Each frame is observed twice, as ``sage track``
observes a sequence with ``follow_landmarks=off`` (every frame from its detection) and ``first`` (every
frame from the previous frame's landmarks, the detector only when the face is lost). The error of a
landmark is its distance in pixels to its embedding point on the true mesh, projected; only points on
triangles facing the camera and inside the image count. Writes ``DOCS/landmark_follow.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's sage_core, whatever is installed

from sage_core.data.cameras import Camera  # noqa: E402

MODES = {"detected": "off", "followed": "first"}
TURNS = (("within 15°", 0.0, 15.0), ("15–45°", 15.0, 45.0), ("beyond 45°", 45.0, 91.0))


def truth_points(vertices: np.ndarray, tri: np.ndarray, bary: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Projected embedding points of one frame's true mesh and which of them count.

    vertices: (V, 3) world; tri: (L, 3) vertex ids of each landmark's triangle; bary: (L, 3).
    Returns (L, 2) pixel positions and (L,) bool: the triangle faces the camera and the point lies
    inside the image.
    """
    p = (vertices[tri] * bary[..., None]).sum(1)
    uv, _ = camera.project(p)
    t = vertices[tri]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    ok = (((camera.center - p) * n).sum(1) > 0) & (uv >= 0).all(1) & (uv[:, 0] <= camera.width) & (uv[:, 1] <= camera.height)
    return uv, ok


def measure(video: Path, embedding: Path, threads: int = 1) -> dict:
    """Per mode: frames with a face, mean landmark error (px) over all of them, over the frames both
    modes found, and by the true head turn."""
    from sage_core.track.embedding import load_embedding
    from sage_core.track.faces import FaceObserver, FaceProblem
    from sage_core.track.inputs import read_source
    from sage_core.track.weights import find_models

    truth = np.load(video.with_suffix(".truth.npz"))
    faces = truth["faces"]
    emb = load_embedding(embedding, len(faces))
    ids = np.asarray(emb.landmark_ids)
    tri = faces[np.asarray(emb.faces)]
    bary = np.asarray(emb.bary, dtype=np.float64)
    observer = FaceObserver(find_models(), threads=threads)
    errors = {m: {} for m in MODES}
    state = {m: (None, None) for m in MODES}  # (near box, previous landmarks)
    n_frames = 0
    for i, (_, img) in enumerate(read_source(video).frames(0)):
        n_frames += 1
        camera = Camera(truth["K"].astype(np.float64), truth["w2c"].astype(np.float64), img.shape[1], img.shape[0])
        uv, ok = truth_points(truth["vertices"][i].astype(np.float64), tri, bary, camera)
        for m, follow in MODES.items():
            near, prev = state[m]
            try:
                o = observer(img, near, prev, follow)
            except FaceProblem:
                continue
            state[m] = (o.detection.box, o.landmarks)
            errors[m][i] = float(np.linalg.norm(o.landmarks[ids][ok] - uv[ok], axis=1).mean())
    yaw = np.abs(np.rad2deg(truth["rotation"][:, 1]))
    both = sorted(set(errors["detected"]) & set(errors["followed"]))
    out = {}
    for m, e in errors.items():
        frames = np.array(sorted(e))
        vals = np.array([e[f] for f in frames])
        out[m] = {"frames_found": len(frames), "mean_px": round(float(vals.mean()), 3),
                  "mean_px_frames_both_found": round(float(np.mean([e[f] for f in both])), 3),
                  "by_turn": {name: round(float(np.mean([e[f] for f in both if lo <= yaw[f] < hi])), 3)
                              for name, lo, hi in TURNS if any(lo <= yaw[f] < hi for f in both)}}
    return {"video": video.name, "frames": n_frames, "frames_both_found": len(both), "modes": out}


def markdown(doc: dict) -> str:
    m = doc["machine"]
    lines = ["# Landmarks detected or followed", "",
             f"`{doc['command']}` ({m['date_utc']} UTC, {m['cpus']} CPUs, torch {m['torch']}, Python {m['python']}).", "",
             f"Video `{doc['video']}` ({doc['frames']} frames). Mean distance in pixels of the landmark model's points "
             "to their calibrated points on the true mesh, projected (points facing the camera and inside the image); "
             "*detected*: every frame from its detection (`follow_landmarks=off`); *followed*: from the previous "
             "frame's landmarks (`first`). The turn columns and \"frames both found\" average over the "
             f"{doc['frames_both_found']} frames both found.", "",
             "| landmarks | frames found | mean (px) | frames both found (px) | " + " | ".join(f"turned {n}" for n, _, _ in TURNS) + " |",
             "|---|---:|---:|---:|" + "---:|" * len(TURNS)]
    for name, r in doc["modes"].items():
        lines.append(f"| {name} | {r['frames_found']} | {r['mean_px']:.2f} | {r['mean_px_frames_both_found']:.2f} | "
                     + " | ".join(f"{r['by_turn'][n]:.2f}" if n in r["by_turn"] else "—" for n, _, _ in TURNS) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--video", type=Path, required=True)
    ap.add_argument("--embedding", type=Path, required=True)
    ap.add_argument("--docs", type=Path, default=REPO / "docs" / "benchmarks")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    import torch

    torch.set_num_threads(a.threads)
    doc = measure(a.video, a.embedding, a.threads)
    doc["command"] = "python benchmarks/landmark_follow.py " + " ".join(
        x if not x.startswith(str(REPO)) else os.path.relpath(x, REPO) for x in sys.argv[1:])
    doc["machine"] = {"cpus": os.cpu_count(), "torch": torch.__version__, "python": platform.python_version(),
                      "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    a.docs.mkdir(parents=True, exist_ok=True)
    from sage_core.atomic import atomic_write_text

    atomic_write_text(a.docs / "landmark_follow.json", json.dumps(doc, indent=1) + "\n")
    atomic_write_text(a.docs / "landmark_follow.md", markdown(doc))
    print(markdown(doc))


if __name__ == "__main__":
    main()
