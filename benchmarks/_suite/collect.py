"""Reading a row's numbers back from its workspace: stage manifests, ``sage eval`` results,
``sage reenact`` records, and the SDF geometry against the capture's ground truth."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from sage_core.workspace import Workspace

METRIC_KEYS = ("psnr", "ssim", "lpips")


def _num(v: Any) -> float | int | None:
    """A finite number (ints kept), or None ("inf" strings, NaN, None and non-numbers)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    if isinstance(v, int):
        return v
    f = float(v)
    return f if math.isfinite(f) else None


def _means(m: dict[str, Any] | None) -> dict[str, Any] | None:
    if not m:
        return None
    return {**{k: _num(m.get(k)) for k in METRIC_KEYS}, "count": m.get("count")}


def eval_metrics(ws: Path, stage: str, split: str) -> dict[str, Any]:
    """Means of ``WS/eval/<stage>/<split>/metrics.json``: {"overall", "frontal", "lpips_available",
    "images"} (and "visible_region" and "view_groups" where the split reports them). FileNotFoundError when the
    workspace's eval index has no current result for that avatar stage and split (missing, or
    evaluated on an avatar that was re-trained since)."""
    from sage_core.stages.results import fresh_results

    if f"{stage}/{split}" not in fresh_results(Workspace(ws), "eval"):
        raise FileNotFoundError(f"{ws}: no current eval result {stage}/{split}")
    return metrics_file(ws / "eval" / stage / split / "metrics.json")


def ceiling_metrics(ws: Path, split: str) -> dict[str, Any]:
    """Means of the tracking ceiling's ``WS/eval/ceiling/<split>/metrics.json`` (the suite's own
    step writes it on every run, so it is never stale), as :func:`eval_metrics` gives them."""
    from sage_core.evaluate.ceiling import CEILING_STAGE

    return metrics_file(ws / "eval" / CEILING_STAGE / split / "metrics.json")


def metrics_file(path: Path) -> dict[str, Any]:
    """The means of one evaluation protocol ``metrics.json`` (see :func:`eval_metrics`)."""
    doc = json.loads(path.read_text(encoding="utf-8"))
    out = {
        "overall": _means(doc.get("overall")),
        "frontal": _means(doc.get("frontal")),
        "frontal_camera": doc.get("frontal_camera"),
        "lpips_available": bool(doc.get("lpips_available")),
        "images": (doc.get("counts") or {}).get("images"),
    }
    vis = doc.get("visible_region")
    if isinstance(vis, dict):
        out["visible_region"] = {"overall": _means(vis.get("overall")), "frontal": _means(vis.get("frontal"))}
    groups = doc.get("view_groups")
    if isinstance(groups, dict):
        out["view_groups"] = {g: {"cameras": v.get("cameras"), "overall": _means(v.get("overall")),
                                  "visible_region": _means(v.get("visible_region"))} for g, v in groups.items()}  # fmt: skip
    return out


def stage_record(ws: Path, stage: str) -> dict[str, Any] | None:
    """What the benchmark keeps of a finished stage's manifest (None when it is not complete)."""
    w = Workspace(ws)
    st = w.status(stage)
    if st.status != "complete" or st.manifest is None:
        return None
    m = st.manifest
    metrics = m.get("metrics") or {}
    rec: dict[str, Any] = {"wall_time_s": _num(m.get("wall_time_s")), "finished_at": m.get("finished_at"),
                           "fingerprint": m.get("fingerprint"), "device": m.get("device")}  # fmt: skip
    for k in ("iterations", "iterations_per_s", "train_time_s", "n_surfels", "attributes", "val_psnr", "chamfer_m",
              "chamfer_rel", "normal_error_deg", "correction", "distortion_first100_mean"):  # fmt: skip
        if k in metrics:
            rec[k] = metrics[k] if isinstance(metrics[k], (str, bool)) else _num(metrics[k])
    return rec


def reenact_record(ws: Path, name: str = "bench") -> dict[str, Any]:
    """FPS and frame count of ``WS/reenact/<name>/reenact.json``."""
    doc = json.loads((ws / "reenact" / name / "reenact.json").read_text(encoding="utf-8"))
    r = doc.get("report") or {}
    return {"render_fps": _num(r.get("render_fps")), "total_fps": _num(r.get("total_fps")), "frames": r.get("n_frames"),
            "size": f"{r.get('width')}x{r.get('height')}", "cameras": doc.get("cameras")}  # fmt: skip


def capture_tracking(capture: Path) -> dict[str, Any] | None:
    """How the capture's FLAME parameters relate to its ground truth (``gt/info.json``): exact, or
    fitted with its tracking error summary (mean / max / face-region mean vertex distance, mm)."""
    try:
        info = json.loads((capture / "gt" / "info.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    tr = info.get("tracking")
    if not tr:
        return {"mode": "exact"}
    return {"mode": tr.get("mode", "fitted"), "error": tr.get("error")}


def capture_appearance(capture: Path) -> dict[str, Any]:
    """The capture's synthetic head (``gt/info.json``): appearance "detailed" (with its hair style)
    or "smooth"; empty when unreadable."""
    try:
        info = json.loads((capture / "gt" / "info.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    detail = ((info.get("identity") or {}).get("appearance") or {}).get("detail")
    if not detail:
        return {"appearance": "smooth"}
    return {"appearance": "detailed", "hair": detail.get("hair_style")}


def gt_canonical_mesh(capture: Path, avatar: Any) -> tuple[Any, Any, int]:
    """The capture's ground-truth mesh at the avatar's canonical timestep, moved into the
    avatar's canonical space.

    ``gt/meshes/<T>.ply`` is the posed world-space mesh of timestep T; canonical space differs
    from it by the timestep's global rotation R0 (about the root joint J0) and translation t:
    x_c = R0ᵀ(x_w − t − J0) + J0. Returns (vertices (V, 3), faces (F, 3), T).
    """
    import numpy as np
    import torch
    import trimesh

    from sage_core.errors import InputError
    from sage_core.geometry.rigid import world_to_canonical

    t_can = int(avatar.canonical_timestep)
    path = capture / "gt" / "meshes" / f"{t_can:05d}.ply"
    if not path.is_file():
        raise InputError(path, "no ground-truth mesh for the canonical timestep")
    mesh = trimesh.load(path, process=False)
    inputs = avatar.frame_inputs(t_can)
    rig = avatar.rigid_transform(inputs, tol=1e-4)
    if rig is None:
        raise InputError(path, f"timestep {t_can} is not a rigid motion of the canonical mesh")
    R0, t = (x.detach().double().cpu() for x in rig)
    J0 = avatar.root_joint.detach().double().cpu()
    v = world_to_canonical(torch.from_numpy(np.asarray(mesh.vertices, np.float64)), R0, t, J0).numpy()
    return v, np.asarray(mesh.faces, np.int64), t_can


def geometry_vs_gt(ws: Path, capture: Path, n_samples: int = 20000, seed: int = 0) -> dict[str, Any]:
    """Chamfer distance and normal error of the phase-1 SDF mesh (``WS/phase1/sdf_mesh.ply``; the
    SDF is frozen in phase 2) against the ground-truth mesh of the canonical timestep."""
    import numpy as np
    import torch
    import trimesh

    from sage_core.avatar import Avatar
    from sage_core.geometry.mesh_metrics import mesh_chamfer, normal_error

    with torch.no_grad():
        avatar = Avatar.load(ws / "phase1" / "avatar.pt", "cpu")
        gv, gf, t_can = gt_canonical_mesh(capture, avatar)
    sdf = trimesh.load(ws / "phase1" / "sdf_mesh.ply", process=False)
    sv, sf = np.asarray(sdf.vertices, np.float64), np.asarray(sdf.faces, np.int64)
    used = gv[np.unique(gf)]
    diag = float(np.linalg.norm(used.max(0) - used.min(0)))
    ch = mesh_chamfer(sv, sf, gv, gf, n_samples=n_samples, seed=seed)
    ne = normal_error(sv, sf, gv, gf, n_samples=n_samples // 2, seed=seed)
    return {
        "chamfer_mm": ch * 1000.0 if math.isfinite(ch) else None,
        "chamfer_rel_pct": 100.0 * ch / diag if diag > 0 and math.isfinite(ch) else None,
        "normal_error_deg": _num(ne),
        "gt_mesh": f"gt/meshes/{t_can:05d}.ply (canonical timestep {t_can}, moved to canonical space)",
        "samples": n_samples,
    }
