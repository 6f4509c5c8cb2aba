"""Training speed of several code trees or settings, measured in one interleaved run.

Usage:
    python benchmarks/compare_speed.py --variant NAME=SRC::WS[::key=value;key=value] [--variant ...]
        [--stages phase1,phase2] [--preset tiny] [--rounds 3] [--warmup 3] [--steps 8] [--threads 1]
        [--out DIR]

Each variant is a source tree ``SRC`` (a checkout of the package: the current one, or a git worktree
of the commit to compare against), a workspace ``WS`` in that tree's file format (with ``data/``,
``init/`` and, for phase 2, ``phase1/avatar.pt``) and optional ``--set`` overrides: ``key=value``
for every measured stage, ``phase1.key=value`` for one stage only.
Every measurement runs in a fresh process with ``PYTHONPATH=SRC``: the trainer is built as the stage
command builds it (``benchmarks/profile_train.py`` of that tree), ``--warmup`` steps run, then
``--steps`` steps are timed one by one. The variants take turns, round after round, so a machine
whose load drifts affects them alike; the report gives each variant's median step time over all
its timed steps, the ratio to the first variant, and the peak resident set of its processes.

Written: ``DIR/compare_speed.json`` and ``DIR/compare_speed.md`` (a Markdown table, also printed).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

CHILD = r"""
import json, resource, sys, time
from pathlib import Path
src, ws, stage, preset, sets, warmup, steps, threads = sys.argv[1:9]
import torch
torch.set_num_threads(int(threads))
sys.path.insert(0, str(Path(src) / "benchmarks"))
import profile_train
sets = json.loads(sets)
trainer = profile_train.build_trainer(Path(ws), stage, "cpu", preset, None, sets, 0)
for _ in range(int(warmup)):
    trainer.step()
times = []
for _ in range(int(steps)):
    t = time.perf_counter()
    trainer.step()
    times.append(time.perf_counter() - t)
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print("RESULT " + json.dumps({"times": times, "peak_rss_mib": rss}))
"""


@dataclass
class Variant:
    """One code tree + workspace + overrides."""

    name: str
    src: Path
    ws: Path
    sets: dict[str, str] = field(default_factory=dict)


def parse_variant(text: str) -> Variant:
    """``NAME=SRC::WS[::k=v;k=v]`` -> Variant (raises SystemExit with the problem)."""
    name, sep, rest = text.partition("=")
    parts = rest.split("::")
    if not sep or not name or len(parts) not in (2, 3):
        raise SystemExit(f"--variant expects NAME=SRC::WS[::key=value;...], got {text!r}")
    sets: dict[str, str] = {}
    if len(parts) == 3 and parts[2]:
        for item in parts[2].split(";"):
            k, eq, v = item.partition("=")
            if not eq:
                raise SystemExit(f"--variant {name}: override {item!r} is not key=value")
            sets[k.strip()] = v.strip()
    src, ws = Path(parts[0]).resolve(), Path(parts[1]).resolve()
    for p, what in ((src / "sage_core", "source tree"), (ws / "data", "workspace")):
        if not p.is_dir():
            raise SystemExit(f"--variant {name}: {p} not found ({what})")
    return Variant(name, src, ws, sets)


def stage_sets(sets: dict[str, str], stage: str) -> dict[str, str]:
    """The overrides of ``sets`` that apply to ``stage`` (``stage.key`` prefixes removed)."""
    out = {}
    for k, val in sets.items():
        head, dot, rest = k.partition(".")
        if dot and head in ("phase1", "phase2"):
            if head == stage:
                out[rest] = val
        else:
            out[k] = val
    return out


def measure(v: Variant, stage: str, preset: str, warmup: int, steps: int, threads: int) -> dict:
    """One fresh process timing ``steps`` steps of ``stage`` for variant ``v``."""
    env = {**os.environ, "PYTHONPATH": str(v.src), "OMP_NUM_THREADS": str(threads), "SAGE_THREADS": str(threads)}
    argv = [sys.executable, "-c", CHILD, str(v.src), str(v.ws), stage, preset, json.dumps(stage_sets(v.sets, stage)), str(warmup), str(steps), str(threads)]
    res = subprocess.run(argv, env=env, capture_output=True, text=True, cwd=str(v.src))
    for line in res.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"{v.name} {stage}: no result (exit {res.returncode}):\n{res.stderr[-2000:]}")


def markdown(doc: dict) -> str:
    """The table of ``doc`` (see :func:`main`)."""
    lines = [
        f"Preset `{doc['preset']}`, {doc['threads']} thread(s) per process, {doc['rounds']} rounds × {doc['steps']} timed steps "
        f"after {doc['warmup']} warm-up steps; load average at start / end {doc['load_start']} / {doc['load_end']}.",
        "",
        "| stage | variant | median step (ms) | steps/s | speed-up vs first | peak RSS (MiB) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for stage, rows in doc["results"].items():
        base = rows[0]["median_ms"]
        for r in rows:
            lines.append(f"| {stage} | {r['variant']} | {r['median_ms']:.1f} | {1000.0 / r['median_ms']:.2f} | "
                         f"{base / r['median_ms']:.2f}× | {r['peak_rss_mib']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/compare_speed.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", action="append", required=True, help="NAME=SRC::WS[::key=value;key=value] (repeatable; the first is the reference).")
    ap.add_argument("--stages", default="phase1,phase2", help="Comma-separated: phase1, phase2.")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    variants = [parse_variant(t) for t in args.variant]
    stages = [s for s in args.stages.split(",") if s]
    for s in stages:
        if s not in ("phase1", "phase2"):
            raise SystemExit(f"--stages: unknown stage {s!r}")
    load_start = [round(x, 2) for x in os.getloadavg()]
    times: dict[str, dict[str, list[float]]] = {s: {v.name: [] for v in variants} for s in stages}
    rss: dict[str, dict[str, float]] = {s: {v.name: 0.0 for v in variants} for s in stages}
    t0 = time.time()
    for r in range(args.rounds):
        for s in stages:
            for v in variants:
                out = measure(v, s, args.preset, args.warmup, args.steps, args.threads)
                times[s][v.name] += out["times"]
                rss[s][v.name] = max(rss[s][v.name], out["peak_rss_mib"])
                print(f"round {r + 1}/{args.rounds} {s} {v.name}: median {1000 * statistics.median(out['times']):.1f} ms", flush=True)
    doc = {
        "command": "python benchmarks/compare_speed.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "preset": args.preset, "threads": args.threads, "rounds": args.rounds, "warmup": args.warmup, "steps": args.steps,
        "load_start": load_start, "load_end": [round(x, 2) for x in os.getloadavg()], "wall_s": round(time.time() - t0, 1),
        "variants": [{"name": v.name, "src": str(v.src), "ws": str(v.ws), "sets": v.sets} for v in variants],
        "results": {
            s: [{"variant": v.name, "median_ms": 1000 * statistics.median(times[s][v.name]), "steps_timed": len(times[s][v.name]),
                 "peak_rss_mib": rss[s][v.name]} for v in variants]
            for s in stages
        },
    }  # fmt: skip
    from _suite.portable import portable_doc

    doc = portable_doc(doc, [args.out.resolve()] if args.out is not None else [])  # no path of this machine: trees and workspaces by name
    md = markdown(doc)
    print(md)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "compare_speed.json").write_text(json.dumps(doc, indent=2) + "\n")
        (args.out / "compare_speed.md").write_text(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
