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
from typing import Annotated, Any, Optional

import numpy as np
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


def interpolate_keys(keys: dict[str, np.ndarray], steps: int) -> dict[str, np.ndarray]:
    """Linear interpolation between consecutive rows of T-leading arrays.

    keys: name -> (K, ...) key frames. Returns name -> ((K − 1)·steps + 1, ...) float32: ``steps``
    frames from each key to the next, then the last key.
    """
    out: dict[str, np.ndarray] = {}
    for name, a in keys.items():
        a = np.asarray(a, np.float64)
        if a.shape[0] == 1:
            out[name] = a.astype(np.float32)
            continue
        frames = []
        for i in range(a.shape[0] - 1):
            for s in range(steps):
                w = s / steps
                frames.append((1.0 - w) * a[i] + w * a[i + 1])
        frames.append(a[-1])
        out[name] = np.stack(frames).astype(np.float32)
    return out


def write_demo_motion(capture: Path, out_path: Path, steps: int, fps: float = 25.0) -> tuple[Path, list[int]]:
    """A GaussianAvatars-style motion npz interpolated between the capture's test timesteps (or its
    training timesteps when it has no test split). Returns (path, key timesteps)."""
    from sage_core.data.capture import read_capture
    from sage_core.flame.params import DYNAMIC_KEYS
    from sage_core.workspace import atomic_write_bytes

    cap = read_capture(capture, check_images=False)
    test_ts = sorted({f.timestep for f in cap.split("test")}) or sorted({f.timestep for f in cap.frames})
    p = cap.params.select_timesteps(test_ts)
    keys = {k: np.asarray(getattr(p, k)) for k in DYNAMIC_KEYS}
    if p.dynamic_offset is not None:
        keys["dynamic_offset"] = np.asarray(p.dynamic_offset)
    arrays: dict[str, Any] = interpolate_keys(keys, steps)
    arrays["fps"] = np.array(fps, np.float32)
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(out_path, buf.getvalue())
    return out_path, test_ts


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
        motion_path, keys = write_demo_motion(capture, ws / "motion" / "demo_motion.npz", 2 if fast else STEPS_BETWEEN_KEYS)
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
