"""``sage demo``: a synthetic subject from capture to reenactment video, on a CPU.

1. a tiny synthetic capture is written into ``WS/capture`` (kept when it already holds the same
   synthetic subject);
2. :func:`sage_core.stages.run.run_pipeline` with the tiny preset trains, evaluates and exports the
   avatar in ``WS``;
3. a clip of novel expressions, interpolated between the capture's held-out test timesteps, is
   written as a motion file (``WS/motion/demo_motion.npz``) and reenacted from the frontal (val)
   camera into ``WS/reenact/demo/`` (frames + MP4).

``fast`` cuts the iteration counts and the capture (9 cameras, 2 test timesteps, 64x94) to a smoke
test (CI); its numbers are not representative of the method.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ._runner import StageSettings
from .events import Emitter, EventFn

FAST_SETS: dict[str, list[str]] = {
    "ingest": [],
    "init-mesh": ["pretrain.steps=20", "pretrain.bank_size=4000", "pretrain.batch_size=1024", "pretrain.eval_samples=2000", "mc_resolution=32"],
    "phase1": ["iterations=2", "surfels.count=800", "schedule.eval_every=0", "mc_resolution=32", "neus.rays_per_step=64", "neus.samples=8",
               "neus.importance=8"],
    "phase2": ["iterations=1", "pixels.per_step=64", "neus.samples=8", "neus.importance=8", "eval_phase1=false"],
    "eval": ["samples=2"],
    "export": [],
}
"""``fast`` overrides per stage (``key=value``, as ``--set`` takes them): a smoke test, not a quality run."""

FAST_CAPTURE = {"n_cameras": 9, "test_timesteps": 2, "width": 64, "height": 94}
"""``fast`` synthesizes a smaller tiny capture: 9 cameras (camera 8 stays the frontal val view),
2 held-out test timesteps, 64x94 images."""

STEPS_BETWEEN_KEYS = 6
"""Frames from one test timestep to the next in the demo clip (the last key is held)."""


def fast_flags() -> dict[str, dict[str, Any]]:
    """:data:`FAST_SETS` as per-stage config flags (``{"phase1": {"iterations": "2", ...}}``)."""
    return {stage: dict(kv.split("=", 1) for kv in kvs) for stage, kvs in FAST_SETS.items()}


def synth_demo_capture(capture: Path, seed: int = 0, fast: bool = False, on_event: EventFn | None = None) -> str:
    """Write the demo's tiny synthetic capture into ``capture`` unless it already holds the same one;
    returns the outcome line (``kept (same synthetic subject)`` or ``done in 4.2 s``). Events of
    stage ``synth``."""
    from ..data.synthetic import preset, write_capture

    emitter = Emitter("synth", on_event)
    emitter.emit("started")
    cfg = preset("tiny", seed=seed, **(FAST_CAPTURE if fast else {}))
    info = capture / "gt" / "info.json"
    if info.is_file():
        try:
            if json.loads(info.read_text())["config"] == cfg.to_dict():
                emitter.emit("finished", message="kept (same synthetic subject)")
                return "kept (same synthetic subject)"
        except (OSError, json.JSONDecodeError, KeyError):
            pass
    t = time.time()
    emitter.emit("running", title="synth")
    write_capture(capture, cfg, progress=emitter, force=True)
    outcome = f"done in {time.time() - t:.1f} s"
    emitter.emit("finished", message=outcome)
    return outcome


@dataclass
class DemoResult:
    """What :func:`run_demo` did: the pipeline's result (with ``synth`` and ``reenact`` outcome lines
    added), the capture folder, the motion file and its key timesteps, and the reenactment."""

    pipeline: Any
    capture: Path
    motion_path: Path
    keys: list[int]
    reenact: Any
    fast: bool


def run_demo(
    ws: str | Path,
    *,
    fast: bool = False,
    lpips_weights: str | Path | None = None,
    render_backend: str | None = None,
    settings: StageSettings = StageSettings(),
    on_event: EventFn | None = None,
) -> DemoResult:
    """Synthesize a tiny subject in ``WS/capture``, train, evaluate and export it in ``WS`` with the
    tiny preset, and reenact novel expressions into ``WS/reenact/demo``. InputError when ``ws``
    exists and is not a folder."""
    from ..data.synthetic import capture_model_path
    from ..errors import InputError
    from ..export.motion import write_key_motion
    from .reenact import reenact_stage
    from .run import run_pipeline

    t0 = time.time()
    ws = Path(ws)
    if ws.exists() and not ws.is_dir():
        raise InputError(ws, "exists and is not a folder")
    ws.mkdir(parents=True, exist_ok=True)
    capture = ws / "capture"
    synth_outcome = synth_demo_capture(capture, settings.seed, fast, on_event)
    res = run_pipeline(capture, ws, capture_model_path(capture, "npz"), preset="tiny", flags=fast_flags() if fast else None,
                       lpips_weights=lpips_weights, render_backend=render_backend, settings=settings, on_event=on_event)  # fmt: skip
    t = time.time()
    motion_path, keys = write_key_motion(capture, ws / "motion" / "demo_motion.npz", 2 if fast else STEPS_BETWEEN_KEYS)
    rec = reenact_stage(ws=ws, flame_seq=motion_path, name="demo", stage=res.avatar_stage or "auto", device=settings.device,
                        on_event=on_event)  # fmt: skip
    reenact_s = time.time() - t
    res.stages.insert(0, ("synth", synth_outcome))
    report = rec.record["report"]
    res.stages.append(("reenact", f"{report['n_frames']} frames in {reenact_s:.1f} s ({report['render_fps']:.2f} rendered frames/s)"))
    res.wall_time_s = time.time() - t0
    return DemoResult(res, capture, motion_path, keys, rec, fast)
