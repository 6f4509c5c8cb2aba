"""The phase-2 stage: self-supervised fine-tuning under sampled expressions, SDF and hash grid frozen."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from ..config import Phase2Config
from ..workspace import Workspace
from ._runner import StageResult, StageSettings, as_workspace, execute_stage, finish_result
from .events import Emitter, EventFn

if TYPE_CHECKING:
    from ..data.dataset import IngestedData, IngestedFrame

Progress = Callable[..., None]

PHASE2_FILES: tuple[str, ...] = ("avatar.pt", "metrics.json", "distortion_curve.json", "eval_test", "eval_val")


def phase2_stage(
    ws: str | Path | Workspace,
    cfg: Phase2Config,
    lpips_weights: str | Path | None = None,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> StageResult:
    """Fine-tune the phase-1 avatar into ``WS/phase2/`` (needs a finished phase1) and evaluate it.

    lpips_weights: LPIPS AlexNet weights for the evaluation (None: ``$SAGE_LPIPS_WEIGHTS`` or the
    cache; InputError when a given file is missing). Resumes an interrupted run.
    """
    from ..errors import require_file

    t0 = time.time()
    emitter = Emitter("phase2", on_event, "phase 2")
    emitter.emit("started")
    w = as_workspace(ws)
    lp = None if lpips_weights is None else Path(lpips_weights)
    if lp is not None:
        require_file(lp, "LPIPS weights file")
    external = None
    if lp is not None:
        from ..workspace import file_fingerprint

        external = {"lpips_weights": file_fingerprint(lp)}

    def body(run, progress) -> None:
        from ..data.dataset import IngestedData

        data = IngestedData.open(run.ws.stage_dir("ingest"))
        metrics = run_phase2(data, run.ws.stage_dir("phase1"), run.ws.stage_dir("init-mesh"), run.work_dir, cfg, device=run.device,
                             seed=run.seed, checkpoint_dir=run.checkpoint_dir, progress=progress, lpips_weights=lp)  # fmt: skip
        run.metrics.update({k: v for k, v in metrics.items() if k != "final_losses"})
        out = run.ws.stage_dir("phase2")
        run.outputs.update({n: str(out / n) for n in PHASE2_FILES})

    outcome = execute_stage("phase2", w, cfg, body, settings, emitter, requires=("phase1",), external_inputs=external)
    return finish_result(StageResult("phase2", w.root), outcome, w, emitter, t0)


def run_phase2(
    data: IngestedData,
    phase1_dir: str | Path,
    init_dir: str | Path | None,
    out_dir: str | Path,
    cfg: Phase2Config,
    *,
    device: str = "cpu",
    seed: int = 0,
    checkpoint_dir: str | Path | None = None,
    progress: Progress | None = None,
    lpips_weights: str | Path | None = None,
) -> dict[str, Any]:
    """Run phase 2 from ``phase1_dir/avatar.pt``; write ``avatar.pt``, ``metrics.json``,
    ``distortion_curve.json`` and evaluation folders (``eval_test/``, ``eval_val/``) into
    ``out_dir``; resume from the newest checkpoint in ``checkpoint_dir``. Returns the metrics.

    Evaluation (docs/formats.md §8 via :func:`evaluate_frames`): self-reenactment on the test split (all
    cameras and the frontal camera) and novel views on the val split, rendered with the correction
    when it is enabled. With ``cfg.eval_phase1`` the phase-1 avatar is evaluated on the test split too.
    LPIPS uses ``lpips_weights`` (or ``$SAGE_LPIPS_WEIGHTS`` / the cache), else it is unavailable.
    """
    import numpy as np
    import torch

    from ..avatar.model import Avatar
    from ..errors import InputError
    from ..evaluate.lpips import load_lpips_or_none
    from ..evaluate.protocol import evaluate_frames
    from ..render import RenderCamera
    from ..runtime import resolve_render_backend
    from ..train.loop import run_steps
    from ..train.phase2 import Phase2Trainer, evenly_spaced_frames
    from ..workspace import atomic_write_json, latest_checkpoint

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    avatar_path = Path(phase1_dir) / "avatar.pt"
    if not avatar_path.is_file():
        raise InputError(avatar_path, "missing (run `sage phase1` first)")
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    avatar = Avatar.load(avatar_path, device)
    lpips = load_lpips_or_none(lpips_weights, device=device)
    test_frames, val_frames = evenly_spaced_frames(list(data.test), cfg.eval_frames), evenly_spaced_frames(list(data.val), cfg.eval_frames)

    backend = resolve_render_backend(cfg.render_backend, str(device))
    metrics: dict[str, Any] = {"correction": cfg.correction.enabled, "attributes": avatar.attributes, "n_surfels": len(avatar.surfels),
                               "iterations": cfg.iterations, "render_backend": backend}  # fmt: skip
    ck = latest_checkpoint(checkpoint_dir) if checkpoint_dir is not None else None
    resumed = ck is not None
    # phase 1 is evaluated before the trainer adds the mouth prior to the avatar
    if cfg.eval_phase1 and test_frames and not resumed:
        if progress is not None:
            progress(0, cfg.iterations, "evaluating phase 1")
        with torch.no_grad():
            def render_p1(fr: IngestedFrame) -> torch.Tensor:
                cam = RenderCamera.from_camera(fr.camera, device)
                img, _ = avatar.render(cam, avatar.frame_inputs(fr.timestep), cfg.background, near=cfg.near, far=cfg.far,
                                       return_statistics=False, backend=backend)  # fmt: skip
                return img.color.clamp(0, 1)

            rep = evaluate_frames(render_p1, data, test_frames, lpips=lpips, out_dir=out_dir / "eval_phase1_test")
        metrics["phase1_test"] = _report_dict(rep)
    elif checkpoint_dir is not None and (Path(out_dir) / "eval_phase1_test" / "metrics.json").is_file():
        d = json.loads((Path(out_dir) / "eval_phase1_test" / "metrics.json").read_text())
        metrics["phase1_test"] = {"overall": d["overall"], "frontal": d["frontal"], "counts": d["counts"],
                                  "lpips_available": d["lpips_available"]}  # fmt: skip

    trainer = Phase2Trainer(avatar, data, cfg, device, gen, init_dir)

    def step_stats(out: Any) -> dict[str, Any]:
        return {k: v for k, v in out.items() if k in ("loss", "normal_consistency", "distortion", "appearance", "rgb")}

    total = cfg.iterations
    loop = run_steps(trainer, total, label="phase 2", progress=progress, checkpoint_dir=checkpoint_dir,
                     checkpoint_every=cfg.schedule.checkpoint_every, state_key="trainer", resume_from=ck, map_location=device,
                     stats=step_stats)  # fmt: skip
    last = dict(loop.last)
    train_time = loop.train_time_s
    steps_run = loop.steps_run
    if trainer.wrinkle_stats is not None:
        metrics["wrinkles"] = trainer.finish_wrinkles()

    if progress is not None:
        progress(total, total, "evaluating")
    if test_frames:
        rep = evaluate_frames(trainer.render_frame, data, test_frames, lpips=lpips, out_dir=out_dir / "eval_test")
        metrics["test"] = _report_dict(rep)
    if val_frames:
        rep = evaluate_frames(trainer.render_frame, data, val_frames, lpips=lpips, out_dir=out_dir / "eval_val")
        metrics["val"] = _report_dict(rep)
    avatar.save(out_dir / "avatar.pt")
    curve = trainer.distortion_curve
    atomic_write_json(out_dir / "distortion_curve.json", {"correction": cfg.correction.enabled, "steps": list(range(1, len(curve) + 1)),
                                                           "distortion": curve})  # fmt: skip
    metrics.update({
        "distortion_first100_mean": float(np.mean(curve)) if curve else float("nan"),
        "iterations_per_s": steps_run / train_time if train_time > 0 and steps_run > 0 else float("nan"),
        "train_time_s": train_time,
        "final_losses": last,
    })  # fmt: skip
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics



def _report_dict(report: Any) -> dict[str, Any]:
    d = report.to_dict()
    return {"overall": d["overall"], "frontal": d["frontal"], "counts": d["counts"], "lpips_available": d["lpips_available"]}
