"""What the native-kernel benchmarks (``hashgrid.py``, ``sdf_network.py``) share: their command
line, the machine description of a run, and writing ``NAME.json`` / ``NAME.md``."""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any


def parse_args(description: str, name: str, repeats: int) -> argparse.Namespace:
    """``--threads``, ``--repeats``, ``--warmup``, ``--quick`` and ``--out`` of a kernel benchmark."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (the cpp kernel follows it)")
    ap.add_argument("--repeats", type=int, default=repeats)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="N / 10, for a smoke test (writes nothing)")
    ap.add_argument("--out", default="docs/benchmarks", help=f"folder for {name}.json / {name}.md")
    return ap.parse_args()


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (else the platform's processor string)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def loadavg() -> list[float]:
    """The 1, 5 and 15 minute load averages, rounded."""
    return [round(x, 2) for x in os.getloadavg()]


def run_meta(script: str, args: argparse.Namespace, load_before: list[float], **extra: Any) -> dict[str, Any]:
    """The description of one run: command, torch, threads, machine, repeats, load before/after, date."""
    import sys

    import torch

    return {
        "command": f"python benchmarks/{script} " + " ".join(sys.argv[1:]),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "cpu": cpu_name(),
        "platform": platform.platform(),
        "repeats": args.repeats,
        "warmup": args.warmup,
        "load_before": load_before,
        "load_after": loadavg(),
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        **extra,
    }


def write(args: argparse.Namespace, name: str, meta: dict[str, Any], rows: list[dict], text: str) -> None:
    """Print ``text``; unless ``--quick``, write ``OUT/NAME.json`` (meta + rows) and ``OUT/NAME.md`` atomically."""
    from sage_core.atomic import atomic_write_text

    print(text)
    if args.quick:
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / f"{name}.json", json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    atomic_write_text(out / f"{name}.md", text)
