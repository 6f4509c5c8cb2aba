"""``sage demo [WS]``: a synthetic subject from capture to reenactment video, on a CPU
(:func:`sage_core.stages.run_demo`).

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

from pathlib import Path
from typing import Annotated, Optional

import typer

from .._common import DeviceOpt, RenderBackendOpt, SeedOpt, ThreadsOpt, VerboseOpt, cli_errors, summary_panel


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
        from sage_core.stages import StageSettings, run_demo

        from .run_cmd import ChainDisplay, pipeline_rows

        with ChainDisplay(ws, verbose) as display:
            d = run_demo(ws, fast=fast, lpips_weights=lpips_weights, render_backend=render_backend,
                         settings=StageSettings(seed=seed, device=device, threads=threads), on_event=display)  # fmt: skip
        res = d.pipeline
        rows, paths = pipeline_rows(res)
        if fast:
            rows.insert(0, ("mode", "--fast SMOKE TEST: reduced iterations and a 9-camera 64x94 capture; metrics are not representative of the method"))
        else:
            rows.insert(0, ("mode", "tiny preset (CPU demo)"))
        rows.insert(-1, ("clip", f"novel expressions interpolated between test timesteps {d.keys}, frontal camera"))
        r = d.reenact.record["report"]
        paths = [("capture", d.capture)] + paths + [("motion", d.motion_path)]
        if r.get("frames_dir"):
            paths.append(("reenact frames", Path(r["frames_dir"])))
        if r.get("video_path"):
            paths.append(("reenact video", Path(r["video_path"])))
        paths += [("log folder", ws / "logs")]
        summary_panel("sage demo", rows, paths)
