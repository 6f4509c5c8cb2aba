"""``sage demo [WS]``: a synthetic subject from capture to reenactment video, on a CPU.

1. ``sage synth`` (tiny preset) writes a capture into ``WS/capture`` (kept when it already holds the
   same synthetic subject);
2. ``sage run`` with the tiny preset trains and evaluates the avatar in ``WS`` and exports it;
3. a clip of novel expressions, interpolated between the capture's held-out test timesteps, is
   written as a motion file (``WS/motion/demo_motion.npz``) and reenacted from the frontal (val)
   camera into ``WS/reenact/demo/`` (frames + MP4);
4. a panel lists val and test PSNR / SSIM / LPIPS and every path written.

``--fast`` cuts the iteration counts and the capture (9 cameras, 2 test timesteps, 64x94) to a smoke test
(CI); the panel says so and its numbers are not representative of the method. LPIPS is computed only when weights are found the standard way
(``--lpips-weights``, ``$SAGE_LPIPS_WEIGHTS``, ``~/.cache/sage/lpips_alex_v0.1.pth``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from .._common import DeviceOpt, ProgressDisplay, RenderBackendOpt, SeedOpt, ThreadsOpt, VerboseOpt, cli_errors, console, summary_panel

FAST_SETS: dict[str, list[str]] = {
    "ingest": [],
    "init-mesh": ["pretrain.steps=20", "pretrain.bank_size=4000", "pretrain.batch_size=1024", "pretrain.eval_samples=2000", "mc_resolution=32"],
    "phase1": ["iterations=2", "n_surfels=800", "eval_every=0", "mc_resolution=32", "rays_per_step=64", "neus_samples=8", "neus_importance=8"],
    "phase2": ["iterations=1", "rays_per_step=64", "neus_samples=8", "neus_importance=8", "eval_phase1=false"],
    "eval": ["samples=2"],
    "export": [],
}
"""``--fast`` overrides per stage: a smoke test, not a quality run."""

FAST_CAPTURE = {"n_cameras": 9, "test_timesteps": 2, "width": 64, "height": 94}
"""``--fast`` synthesizes a smaller tiny capture: 9 cameras (camera 8 stays the frontal val view),
2 held-out test timesteps, 64x94 images."""

STEPS_BETWEEN_KEYS = 6
"""Frames from one test timestep to the next in the demo clip (the last key is held)."""


def _synth_capture(capture: Path, seed: int, fast: bool, verbose: bool) -> str:
    """Write the tiny synthetic capture unless ``capture`` already holds the same one."""
    from sage_core.data.synthetic import preset, write_capture

    cfg = preset("tiny", seed=seed, **(FAST_CAPTURE if fast else {}))
    info = capture / "gt" / "info.json"
    if info.is_file():
        try:
            if json.loads(info.read_text())["config"] == cfg.to_dict():
                return "kept (same synthetic subject)"
        except (OSError, json.JSONDecodeError, KeyError):
            pass
    t = time.time()
    with ProgressDisplay("synth", enabled=verbose) as progress:
        write_capture(capture, cfg, progress=progress, force=True)
    return f"done in {time.time() - t:.1f} s"


def demo(
    ws: Annotated[Path, typer.Argument(help="Demo folder: the capture goes to WS/capture, every stage into WS.")] = Path("sage-demo"),
    fast: Annotated[bool, typer.Option("--fast", help="Smoke test: far fewer iterations (numbers not representative).")] = False,
    lpips_weights: Annotated[Optional[Path], typer.Option("--lpips-weights", help="LPIPS AlexNet v0.1 weights (default: $SAGE_LPIPS_WEIGHTS, then ~/.cache/sage/lpips_alex_v0.1.pth).")] = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
    render_backend: RenderBackendOpt = None,
) -> None:
    """Synthesize a tiny subject, train it with the tiny preset, evaluate, export and reenact novel expressions to MP4."""
    with cli_errors():
        from sage_core.errors import InputError

        from .reenact_cmd import run_reenact
        from .run_cmd import PipelineResult, pipeline_rows, run_pipeline

        t0 = time.time()
        if ws.exists() and not ws.is_dir():
            raise InputError(ws, "exists and is not a folder")
        ws.mkdir(parents=True, exist_ok=True)
        capture = ws / "capture"
        console.rule("[bold]synth")
        synth_outcome = _synth_capture(capture, seed, fast, verbose)
        from sage_core.data.synthetic import capture_model_path

        sets = {k: list(v) for k, v in FAST_SETS.items()} if fast else None
        res: PipelineResult = run_pipeline(
            capture, ws, capture_model_path(capture, "npz"), preset="tiny", sets=sets, seed=seed, device=device,
            lpips_weights=lpips_weights, verbose=verbose, threads=threads, render_backend=render_backend,
        )  # fmt: skip
        console.rule("[bold]reenact")
        t = time.time()
        from sage_core.export.motion import write_key_motion

        motion_path, keys = write_key_motion(capture, ws / "motion" / "demo_motion.npz", 2 if fast else STEPS_BETWEEN_KEYS)
        rec = run_reenact(ws=ws, flame_seq=motion_path, name="demo", stage=res.avatar_stage or "auto", device=device, verbose=verbose)
        reenact_s = time.time() - t
        res.stages.insert(0, ("synth", synth_outcome))
        res.stages.append(("reenact", f"{rec['report']['n_frames']} frames in {reenact_s:.1f} s "
                                      f"({rec['report']['render_fps']:.2f} rendered frames/s)"))  # fmt: skip
        res.wall_time_s = time.time() - t0
        rows, paths = pipeline_rows(res)
        if fast:
            rows.insert(0, ("mode", "--fast SMOKE TEST: reduced iterations and a 9-camera 64x94 capture; metrics are not representative of the method"))
        else:
            rows.insert(0, ("mode", "tiny preset (CPU demo)"))
        rows.insert(-1, ("clip", f"novel expressions interpolated between test timesteps {keys}, frontal camera"))
        r = rec["report"]
        paths = [("capture", capture)] + paths + [("motion", motion_path)]
        if r.get("frames_dir"):
            paths.append(("reenact frames", Path(r["frames_dir"])))
        if r.get("video_path"):
            paths.append(("reenact video", Path(r["video_path"])))
        paths += [("log folder", ws / "logs")]
        summary_panel("sage demo", rows, paths)
