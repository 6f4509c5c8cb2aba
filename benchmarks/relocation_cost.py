"""Cost of phase-1 surfel relocation against a phase-1 step, measured in one process.

Usage:
    python benchmarks/relocation_cost.py WS [--surfels 25000] [--preset tiny] [--rounds 3] [--steps 5]
        [--threads 1] [--out DIR]

WS is a workspace with ``data/`` and ``init/`` (ingest and init-mesh done). The trainer is built as
``sage phase1`` builds it; after three warm-up steps, rounds of ``--steps`` timed steps alternate
with one timed relocation, so load drift affects both alike. Reported: the median step, the median
relocation, the relocation interval of the config, and the amortised ratio
1 + relocation / (interval × step): how much slower phase 1 is per step because of relocation.
Written: ``DIR/relocation_cost.json`` and ``DIR/relocation_cost.md`` (also printed).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ws", type=Path)
    ap.add_argument("--surfels", type=int, default=25000)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("."))
    a = ap.parse_args(argv)

    import torch

    from sage_core.config import resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.train import relocate
    from sage_core.train.phase1 import Phase1Trainer, build_avatar

    torch.set_num_threads(a.threads)
    data = IngestedData.open(a.ws / "data")
    cfg = resolve_config("phase1", a.preset, None, {"n_surfels": a.surfels}, regime=data.regime)
    g = torch.Generator().manual_seed(0)
    tr = Phase1Trainer(build_avatar(data, a.ws / "init", cfg, "cpu", g), data, cfg, "cpu", g)
    for _ in range(3):
        tr.step()
    steps: list[float] = []
    calls: list[float] = []
    moved: list[int] = []
    for _ in range(a.rounds):
        for _ in range(a.steps):
            t = time.perf_counter()
            tr.step()
            steps.append(time.perf_counter() - t)
        t = time.perf_counter()
        moved.append(relocate.relocate(tr).moved)
        calls.append(time.perf_counter() - t)
    step, call = statistics.median(steps), statistics.median(calls)
    doc = {"command": "python benchmarks/relocation_cost.py WS " + " ".join(f"--{k} {v}" for k, v in
                                                                           (("surfels", a.surfels), ("preset", a.preset), ("threads", a.threads))),
           "surfels": a.surfels, "preset": a.preset, "threads": a.threads, "step_median_s": step, "relocation_median_s": call,
           "every": cfg.relocate.every, "amortized_ratio": 1.0 + call / (cfg.relocate.every * step), "moved_per_call": moved}  # fmt: skip
    md = ("| surfels | median step (ms) | median relocation (ms) | every (steps) | amortised step ratio | moved per call |\n"
          "|---:|---:|---:|---:|---:|---|\n"
          f"| {a.surfels} | {1000 * step:.0f} | {1000 * call:.0f} | {cfg.relocate.every} | {doc['amortized_ratio']:.3f}× | "
          f"{', '.join(map(str, moved))} |\n")  # fmt: skip
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "relocation_cost.json").write_text(json.dumps(doc, indent=1) + "\n")
    (a.out / "relocation_cost.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
