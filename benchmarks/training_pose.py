"""How much of a one-timestep avatar's error on held-out expressions its training timestep's tracking
error causes, on a ``sage synth`` capture (whose true meshes are known).

Usage:
    python benchmarks/training_pose.py bound CAPTURE WS [--rigid-fixed | --registered STAGE] [--lpips WEIGHTS] [--out FILE.json]
    python benchmarks/training_pose.py oracle CAPTURE WS
    python benchmarks/training_pose.py registration CAPTURE WS [--stage phase1]

``bound``: the best a one-timestep avatar bound to the tracked FLAME mesh can do. The truth's mesh of
the canonical (training) timestep is bound vertex by vertex to the written model posed with that
timestep's tracked parameters (its offset from the tracked mesh kept in the frame of the vertex's
one-ring), then moved with the written model posed with each test frame's tracked parameters (the
one-ring's rotation, fitted by Kabsch) and drawn with the truth's appearance by the capture's own
renderer, like the tracking ceiling (:mod:`sage_core.evaluate.ceiling`) draws the truth on the
tracked mesh. Scored on WS's test split under the evaluation protocol. The ceiling adds only each
test frame's tracking error; the bound adds the training timestep's too. ``--rigid-fixed`` first
moves the tracked training mesh by the rigid transform that best aligns it with the truth's (what
a perfect registration of that timestep would do) and reports that transform; ``--registered
STAGE`` binds to the training mesh posed with the parameters of WS's avatar of that stage instead
(phase 1's registration of the timestep, :mod:`sage_core.train.registration`).

``oracle``: rewrites the canonical timestep's global rotation and translation in
``WS/data/flame_params.npz`` (a copy's: the workspace's data are changed) by fitting the written
model to that timestep's true mesh, the other parameters kept: a perfect rigid registration of the
training timestep, to train any row on.

``registration``: the vertex error of the training timestep's mesh against the truth's (mm, all
vertices and the face region) as tracked and as the avatar of WS's stage registered it (its FLAME
parameters of the timestep, :mod:`sage_core.train.registration`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np


def _params(params: Any, t: int) -> dict[str, np.ndarray]:
    """The per-frame FLAME parameters of timestep ``t`` as the tracking ceiling poses them."""
    from sage_core.data.synthetic.ceiling import FLAME_KEYS as FRAME_KEYS

    row = params.row_of(t)
    return {k: np.asarray(getattr(params, k)[row], np.float64) for k in FRAME_KEYS}


def _truth_mesh(capture: Path, t: int) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.load(capture / "gt" / "meshes" / f"{t:05d}.ply", process=False).vertices, np.float64)


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t with R·src + t ≈ dst (least squares). src, dst: (N, 3)."""
    ms, md = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - ms).T @ (dst - md))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ d @ u.T
    return r, md - r @ ms


def _one_rings(faces: np.ndarray, n: int) -> list[np.ndarray]:
    ring: list[set[int]] = [set() for _ in range(n)]
    for a, b, c in faces:
        ring[a] |= {b, c}
        ring[b] |= {a, c}
        ring[c] |= {a, b}
    return [np.fromiter(sorted(r), np.int64) for r in ring]


def _ring_rotations(src: np.ndarray, dst: np.ndarray, rings: list[np.ndarray]) -> np.ndarray:
    """(V, 3, 3): per vertex, the rotation that best maps its one-ring's edges in ``src`` onto ``dst``."""
    out = np.empty((len(src), 3, 3))
    for i, r in enumerate(rings):
        if len(r) < 2:
            out[i] = np.eye(3)
            continue
        out[i] = _kabsch(src[r] - src[i], dst[r] - dst[i])[0]
    return out


def _rotation_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def bound(capture: Path, ws: Path, rigid_fixed: bool, lpips_weights: str | None, registered: str | None = None) -> dict[str, Any]:
    import torch

    from sage_core.data.dataset import IngestedData
    from sage_core.data.synthetic.capture import neck_line_mask
    from sage_core.data.synthetic.ceiling import TrackedTruth
    from sage_core.evaluate.lpips import load_lpips_or_none
    from sage_core.evaluate.protocol import evaluate_frames

    data = IngestedData.open(ws / "data")
    truth = TrackedTruth.open(capture)
    t0 = data.canonical_timestep
    tracked0, _ = truth.pose(_params(data.params, t0))
    true0 = _truth_mesh(capture, t0)
    report: dict[str, Any] = {"capture": str(capture.name), "timestep": t0,
                              "training_error_mm": float(np.linalg.norm(true0 - tracked0, axis=1).mean() * 1000.0)}  # fmt: skip
    if registered is not None:
        from sage_core.avatar.model import Avatar

        with torch.no_grad():
            params = Avatar.load(ws / registered / "avatar.pt").params
        tracked0, _ = truth.pose(_params(params, t0))
        report["registered_error_mm"] = float(np.linalg.norm(true0 - tracked0, axis=1).mean() * 1000.0)
    if rigid_fixed:
        r, t = _kabsch(tracked0, true0)
        tracked0 = tracked0 @ r.T + t
        report["rigid_fix"] = {"rotation_deg": _rotation_deg(r), "translation_mm": float(np.linalg.norm(t) * 1000.0),
                               "remaining_error_mm": float(np.linalg.norm(true0 - tracked0, axis=1).mean() * 1000.0)}  # fmt: skip
    offset = true0 - tracked0
    rings = _one_rings(truth.subject.head.faces, len(true0))
    posed: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def render(frame: Any) -> torch.Tensor:
        t = int(frame.timestep)
        if t not in posed:
            verts, crease = truth.pose(_params(data.params, t))
            rot = _ring_rotations(tracked0, verts, rings)
            posed[t] = (verts + np.einsum("vij,vj->vi", rot, offset), crease)
        verts, crease = posed[t]
        subject = truth.subject
        rgb = subject.render(verts, frame.camera, crease, truth.config.supersample).rgb
        neck = neck_line_mask(subject.head, verts, frame.camera)[..., None]
        return torch.from_numpy((rgb * neck + (1.0 - neck)).astype(np.float32))

    rep = evaluate_frames(render, data, data.role("test"), lpips=load_lpips_or_none(lpips_weights), out_dir=None)
    report["test"] = rep.to_dict()["overall"]
    return report


def oracle(capture: Path, ws: Path) -> dict[str, Any]:
    import torch

    from sage_core.data.dataset import IngestedData
    from sage_core.data.synthetic.ceiling import TrackedTruth

    data = IngestedData.open(ws / "data")
    truth = TrackedTruth.open(capture)
    t0 = data.canonical_timestep
    target = torch.as_tensor(_truth_mesh(capture, t0))
    p = {k: torch.tensor(v.reshape(1, -1), dtype=torch.float64) for k, v in _params(data.params, t0).items()}
    free = [p["rotation"].requires_grad_(True), p["translation"].requires_grad_(True)]
    shape = torch.as_tensor(truth.subject.shape, dtype=torch.float64)
    off = torch.as_tensor(truth.subject.static_offset, dtype=torch.float64)
    opt = torch.optim.LBFGS(free, max_iter=200, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = ((truth.written(shape=shape, static_offset=off, **p).vertices[0] - target) ** 2).sum(1).mean()
        loss.backward()
        return loss

    for _ in range(3):
        opt.step(closure)
    with torch.no_grad():
        err = float((truth.written(shape=shape, static_offset=off, **p).vertices[0] - target).norm(dim=1).mean()) * 1000.0
    path = ws / "data" / "flame_params.npz"
    arrays = dict(np.load(path))
    row = data.params.row_of(t0)
    before = {k: arrays[k][row].tolist() for k in ("rotation", "translation")}
    for k in ("rotation", "translation"):
        arrays[k][row] = p[k].detach().numpy().reshape(arrays[k][row].shape).astype(arrays[k].dtype)
    np.savez(path, **arrays)
    return {"timestep": t0, "before": before, "after": {k: arrays[k][row].tolist() for k in ("rotation", "translation")},
            "remaining_error_mm": err}  # fmt: skip


def registration(capture: Path, ws: Path, stage: str) -> dict[str, Any]:
    import torch

    from sage_core.avatar.model import Avatar
    from sage_core.data.dataset import IngestedData
    from sage_core.data.synthetic.ceiling import TrackedTruth
    from sage_core.flame.regions import Regions

    data = IngestedData.open(ws / "data")
    truth = TrackedTruth.open(capture)
    with torch.no_grad():
        avatar = Avatar.load(ws / stage / "avatar.pt")
    t0 = avatar.canonical_timestep
    true0 = _truth_mesh(capture, t0)
    face = Regions.from_dict(json.loads((ws / "init" / "regions.json").read_text(encoding="utf-8"))).vertex_ids("face")
    out: dict[str, Any] = {"timestep": t0}
    for name, params in (("tracked", data.params), ("registered", avatar.params)):
        verts, _ = truth.pose(_params(params, t0))
        d = np.linalg.norm(true0 - verts, axis=1) * 1000.0
        out[name] = {"all_mm": float(d.mean()), "face_mm": float(d[face].mean())}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/training_pose.py", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("bound", help="the one-timestep bound on the test split")
    b.add_argument("capture", type=Path)
    b.add_argument("ws", type=Path)
    g = b.add_mutually_exclusive_group()
    g.add_argument("--rigid-fixed", action="store_true", help="remove the training timestep's rigid error first")
    g.add_argument("--registered", choices=("phase1", "phase2"), default=None, help="bind to the training mesh as the avatar of this stage registered it")
    b.add_argument("--lpips", default=None, help="LPIPS AlexNet v0.1 weights (default: where sage finds them)")
    b.add_argument("--out", type=Path, default=None)
    o = sub.add_parser("oracle", help="rewrite the training timestep's global pose from the truth (changes WS/data)")
    o.add_argument("capture", type=Path)
    o.add_argument("ws", type=Path)
    r = sub.add_parser("registration", help="the training mesh's error as tracked and as registered")
    r.add_argument("capture", type=Path)
    r.add_argument("ws", type=Path)
    r.add_argument("--stage", default="phase1", choices=("phase1", "phase2"))
    args = ap.parse_args(argv)
    if args.cmd == "bound":
        result = bound(args.capture, args.ws, args.rigid_fixed, args.lpips, args.registered)
    elif args.cmd == "oracle":
        result = oracle(args.capture, args.ws)
    else:
        result = registration(args.capture, args.ws, args.stage)
    text = json.dumps(result, indent=2)
    print(text)
    if getattr(args, "out", None) is not None:
        args.out.write_text(text + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
