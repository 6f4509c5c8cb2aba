"""Profile whole training iterations of phase 1 or phase 2 on an existing workspace.

Usage: python benchmarks/profile_train.py WS [--stage phase1|phase2] [--device cuda|cpu|auto]
       [--warmup N] [--steps M] [--out DIR] [--preset tiny|small|default] [--config FILE] [--set key=value ...]

The trainer is built as ``sage phase1`` / ``sage phase2`` build it: phase 1 from ``WS/data/`` and
``WS/init/`` (the avatar of ``build_avatar``, one-shot pseudo-views where the regime has them),
phase 2 from ``WS/phase1/avatar.pt``; the settings are those of the stage command with the same
``--preset``, ``--config`` and ``--set`` (phase 1 adds the capture regime's defaults). Nothing in
the workspace is written.

After ``--warmup`` steps, ``--steps`` steps run under ``torch.profiler`` (CPU activity, plus CUDA
on a GPU; no shapes), each timed with ``perf_counter`` between device synchronisations. Written:

- ``DIR/profile_<stage>.json``: device, steps, per-step and median milliseconds (measured under the
  profiler), the 25 ops with the most self time (count, self and total ms; on CUDA ordered by device
  time), peak memory (CUDA ``max_memory_allocated`` over the measured steps, else the process's
  peak resident set) and, on CUDA, the host-device synchronisations the measured steps made
  (``torch.cuda.set_sync_debug_mode("warn")``: count and the most frequent call sites);
- ``DIR/trace_<stage>.json``: the Chrome trace (chrome://tracing or https://ui.perfetto.dev).

The hotspot table is printed as Markdown.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import warnings
from collections import Counter
from pathlib import Path
from typing import Any, Callable

STAGES = ("phase1", "phase2")
TOP_OPS = 25
TOP_SYNC_SITES = 10
SYNC_WARNING = "synchronizing CUDA operation"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python benchmarks/profile_train.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("ws", type=Path, help="workspace folder (data/ and init/ for phase1; phase1/avatar.pt too for phase2)")
    ap.add_argument("--stage", choices=STAGES, default="phase1", help="trainer to profile")
    ap.add_argument("--device", default="auto", help="cpu, cuda[:N] or auto")
    ap.add_argument("--warmup", type=int, default=3, help="steps run before profiling (not measured)")
    ap.add_argument("--steps", type=int, default=10, help="steps measured under the profiler")
    ap.add_argument("--out", type=Path, default=Path("profile"), help="folder for profile_<stage>.json and trace_<stage>.json")
    ap.add_argument("--preset", default="default", help="settings preset of the stage (tiny, small or default)")
    ap.add_argument("--config", type=Path, default=None, help="YAML/JSON config file, as for the stage command")
    ap.add_argument("--set", dest="sets", action="append", default=None, metavar="KEY=VALUE", help="override a config field (repeatable)")
    ap.add_argument("--seed", type=int, default=0, help="random seed")
    return ap


def parse_sets(values: list[str] | None) -> dict[str, str]:
    """``key=value`` overrides as a dict (values are parsed by the config resolver)."""
    out: dict[str, str] = {}
    for v in values or []:
        if "=" not in v:
            raise SystemExit(f"--set expects key=value, got {v!r}")
        k, val = v.split("=", 1)
        out[k.strip()] = val.strip()
    return out


def build_trainer(ws_path: Path, stage: str, device: str, preset: str, config: Path | None, sets: dict[str, str], seed: int) -> Any:
    """The stage's trainer on ``device``, built as the stage command builds it (nothing is written)."""
    import torch

    from sage_core.config import load_config_file, resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.errors import InputError
    from sage_core.workspace import Workspace

    ws = Workspace(ws_path)
    data = IngestedData.open(ws.stage_dir("ingest"))
    init_dir = ws.stage_dir("init-mesh")
    file_data = load_config_file(config) if config is not None else None
    label = str(config) if config is not None else "config file"
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    if stage == "phase1":
        from sage_core.train.phase1 import Phase1Trainer, build_avatar, one_shot_pseudo_views

        if not (init_dir / "head_mesh.ply").is_file():
            raise InputError(init_dir, "no init-mesh outputs (run `sage init-mesh` first)")
        cfg = resolve_config("phase1", preset, file_data, sets, file_label=label, regime=data.regime)
        avatar = build_avatar(data, init_dir, cfg, device, gen)
        views, mirror_index = one_shot_pseudo_views(data, avatar, cfg)
        return Phase1Trainer(avatar, data, cfg, device, gen, pseudo_views=views, mirror_index=mirror_index)
    from sage_core.avatar.model import Avatar
    from sage_core.train.phase2 import Phase2Trainer

    avatar_path = ws.stage_dir("phase1") / "avatar.pt"
    if not avatar_path.is_file():
        raise InputError(avatar_path, "missing (run `sage phase1` first)")
    cfg = resolve_config("phase2", preset, file_data, sets, file_label=label)
    avatar = Avatar.load(avatar_path, device)
    return Phase2Trainer(avatar, data, cfg, device, gen, init_dir if init_dir.is_dir() else None)


def peak_rss_mib() -> float | None:
    """The process's peak resident set (VmHWM) in MiB; None where /proc is unavailable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def op_rows(events: Any, on_cuda: bool, limit: int = TOP_OPS) -> list[dict[str, Any]]:
    """The ``limit`` ops with the most self time (device time on CUDA, else CPU time), from
    ``profile.key_averages()``; times in ms."""

    def dev(e: Any, name: str) -> float:
        v = getattr(e, name, None)
        if v is None:
            v = getattr(e, name.replace("device", "cuda"), 0.0)
        return float(v) / 1000.0

    rows = []
    for e in events:
        row = {"name": e.key, "count": int(e.count), "self_cpu_ms": float(e.self_cpu_time_total) / 1000.0,
               "cpu_total_ms": float(e.cpu_time_total) / 1000.0}  # fmt: skip
        if on_cuda:
            row["self_device_ms"] = dev(e, "self_device_time_total")
            row["device_total_ms"] = dev(e, "device_time_total")
        rows.append(row)
    key = "self_device_ms" if on_cuda else "self_cpu_ms"
    rows.sort(key=lambda r: r[key], reverse=True)
    return rows[:limit]


def sync_sites(records: list[warnings.WarningMessage], skip_file: str, limit: int = TOP_SYNC_SITES) -> tuple[int, list[dict[str, Any]]]:
    """Count of the host-device synchronisation warnings in ``records`` and their most frequent
    call sites (``file:line``), leaving out those raised from ``skip_file``."""
    sites: Counter[str] = Counter()
    for w in records:
        if SYNC_WARNING not in str(w.message) or os.path.abspath(w.filename) == os.path.abspath(skip_file):
            continue
        sites[f"{w.filename}:{w.lineno}"] += 1
    return sum(sites.values()), [{"site": s, "count": n} for s, n in sites.most_common(limit)]


def markdown_table(doc: dict[str, Any]) -> str:
    """The hotspot table of a profile document, with a heading line of the step time and memory."""
    on_cuda = doc["device"].startswith("cuda")
    key, total = ("self_device_ms", "device_total_ms") if on_cuda else ("self_cpu_ms", "cpu_total_ms")
    mem = doc["peak_memory_mib"]
    lines = [f"{doc['stage']} on {doc['device']}: median step {doc['median_step_ms']:.2f} ms over {doc['steps']} steps "
             f"(under the profiler); peak memory {'unknown' if mem is None else f'{mem:.1f} MiB'} ({doc['peak_memory_kind']})", ""]  # fmt: skip
    if on_cuda:
        lines.insert(1, f"host-device synchronisations in the measured steps: {doc['syncs']['count']}")
    header = ["op", "count", "self ms", "total ms", "self ms / step"] + (["self CPU ms"] if on_cuda else [])
    lines += ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    steps = max(doc["steps"], 1)
    for r in doc["top_ops"]:
        cells = [r["name"].replace("|", "\\|"), str(r["count"]), f"{r[key]:.3f}", f"{r[total]:.3f}", f"{r[key] / steps:.3f}"]
        if on_cuda:
            cells.append(f"{r['self_cpu_ms']:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    if on_cuda and doc["syncs"]["sites"]:
        lines += ["", "| sync call site | count |", "|---|---:|"]
        lines += [f"| {s['site']} | {s['count']} |" for s in doc["syncs"]["sites"]]
    return "\n".join(lines) + "\n"


def measure(step: Callable[[], Any], n: int, sync: Callable[[], None]) -> list[float]:
    """Run ``step`` ``n`` times; the wall time of each in ms, between device synchronisations."""
    times = []
    for _ in range(n):
        sync()
        t0 = time.perf_counter()
        step()
        sync()
        times.append((time.perf_counter() - t0) * 1000.0)
    return times


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.warmup < 0 or args.steps < 1:
        raise SystemExit("--warmup must be >= 0 and --steps >= 1")
    import torch
    from torch.profiler import ProfilerActivity, profile

    from sage_core.errors import SageError
    from sage_core.workspace import atomic_write_json, resolve_device

    try:
        device = resolve_device(args.device)
        trainer = build_trainer(args.ws, args.stage, device, args.preset, args.config, parse_sets(args.sets), args.seed)
    except SageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    on_cuda = device.startswith("cuda")

    def sync() -> None:
        if on_cuda:
            torch.cuda.synchronize(device)

    for _ in range(args.warmup):
        trainer.step()
    sync()
    if on_cuda:
        torch.cuda.reset_peak_memory_stats(device)

    def watched_step() -> None:
        torch.cuda.set_sync_debug_mode("warn")
        try:
            trainer.step()
        finally:
            torch.cuda.set_sync_debug_mode("default")

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if on_cuda else [])
    with warnings.catch_warnings(record=True) as records:
        warnings.simplefilter("always")
        with profile(activities=activities, record_shapes=False) as prof:
            step_ms = measure(watched_step if on_cuda else trainer.step, args.steps, sync)
    n_sync, sites = sync_sites(records, __file__) if on_cuda else (0, [])
    for w in records:  # the other warnings of the measured steps are shown as usual
        if SYNC_WARNING not in str(w.message):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)

    rss = peak_rss_mib()
    if on_cuda:
        mem, mem_kind = torch.cuda.max_memory_allocated(device) / 2**20, "cuda max_memory_allocated"
    else:
        mem, mem_kind = rss, "peak resident set (VmHWM)"
    doc: dict[str, Any] = {
        "workspace": str(args.ws),
        "stage": args.stage,
        "device": device,
        "gpu": torch.cuda.get_device_name(device) if on_cuda else None,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "preset": args.preset,
        "overrides": parse_sets(args.sets),
        "n_surfels": len(trainer.avatar.surfels),
        "warmup": args.warmup,
        "steps": args.steps,
        "step_ms": step_ms,
        "median_step_ms": statistics.median(step_ms),
        "timing": "perf_counter between device synchronisations, under the profiler",
        "sort_by": "self_device_ms" if on_cuda else "self_cpu_ms",
        "top_ops": op_rows(prof.key_averages(), on_cuda),
        "peak_memory_mib": mem,
        "peak_memory_kind": mem_kind,
        "peak_rss_mib": rss,
        "syncs": {"count": n_sync, "sites": sites} if on_cuda else None,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    trace_tmp = args.out / f".trace_{args.stage}.{os.getpid()}.tmp.json"
    try:
        prof.export_chrome_trace(str(trace_tmp))
        os.replace(trace_tmp, args.out / f"trace_{args.stage}.json")
    finally:
        trace_tmp.unlink(missing_ok=True)
    atomic_write_json(args.out / f"profile_{args.stage}.json", doc)
    print(markdown_table(doc))
    print(f"written: {args.out / f'profile_{args.stage}.json'}\n         {args.out / f'trace_{args.stage}.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
