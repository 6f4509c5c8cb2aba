"""Speed and memory of the surfel rasterizer (forward + backward), packed torch backend by default.

Usage: python benchmarks/render_surfels.py [--quick] [--out docs/benchmarks] [--device cpu]
       [--backend torch [cpp triton ...]] [--threads N] [--profile]

``--backend`` lists the rasterizer backends to time; each case renders the same scene with each of
them, back to back (on a CPU: ``--backend torch cpp``; on a GPU: ``--device cuda --backend torch
triton``). The triton backend needs CUDA tensors; cpp builds its extension in the warm-up render.
With torch and another backend, the markdown has a speed-up table (torch median total / backend
median total, per case). ``--threads`` sets torch's thread count in every case process (which the
cpp backend follows); ``--profile`` runs one extra, untimed step under torch.profiler per case and
lists the top operators by self CPU time.

Scene (docs/rendering.md §3.2): N random surfels filling the view at depth 3 ± 0.3, scales 0.005–0.025,
opacity 0.1–0.9, RGB features, focal length 1.2·S for an S×S image. The loss touches every output
(colour, depth, median, normals, depth-normal, distortion) so the backward is the full one.
Each case runs in a fresh subprocess; its peak memory is the VmHWM (peak resident set) that
process reached minus its resident set just before the first render.
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
from pathlib import Path

GRID_N = (5_000, 20_000, 80_000)
GRID_S = (128, 256, 512)


def _vm(key: str) -> int:
    """A /proc/self/status entry in bytes (0 where unavailable)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def run_case(
    n: int,
    size: int,
    repeats: int,
    device: str,
    seed: int = 0,
    backend: str = "torch",
    threads: int | None = None,
    profile: bool = False,
) -> dict:
    """Render one scene ``repeats`` times (after one warm-up) with ``backend`` and time forward and backward."""
    import torch

    if threads:
        torch.set_num_threads(threads)

    from sage_core.render import RenderCamera, rasterize_surfels

    g = torch.Generator().manual_seed(seed)
    f = 1.2 * size
    z = 3.0 + 0.6 * (torch.rand(n, generator=g) - 0.5)
    half = (size / 2) / f * z
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * half[:, None]
    params = [
        torch.cat([xy, z[:, None]], 1),
        torch.randn(n, 4, generator=g),
        0.005 + 0.02 * torch.rand(n, 2, generator=g),
        0.1 + 0.8 * torch.rand(n, generator=g),
        torch.rand(n, 3, generator=g),
    ]
    params = [p.to(device).requires_grad_(True) for p in params]
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    cam = RenderCamera(K, torch.eye(4), size, size).to(device)
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    rss0 = _vm("VmRSS")
    load0 = os.getloadavg()[0]

    def step() -> tuple[float, float, int]:
        for p in params:
            p.grad = None
        sync()
        t0 = time.perf_counter()
        out = rasterize_surfels(*params, cam, background=1.0, backend=backend)
        sync()
        t1 = time.perf_counter()
        loss = (
            out.color.sum()
            + out.depth.sum()
            + out.median_depth.sum()
            + out.normal_cam.sum()
            + out.surf_normal_cam.sum()
            + out.distortion.sum()
        )
        loss.backward()
        sync()
        t2 = time.perf_counter()
        return t1 - t0, t2 - t1, int(out.num_pairs)

    fwd, bwd, pairs = [], [], 0
    for it in range(repeats + 1):
        tf, tb, pairs = step()
        if it > 0:
            fwd.append(tf)
            bwd.append(tb)
    total = [a + b for a, b in zip(fwd, bwd)]
    res = {
        "n": n,
        "size": size,
        "load_1min_at_start": round(load0, 2),
        "device": device,
        "backend": backend,
        "repeats": repeats,
        "pairs": pairs,
        "forward_s": statistics.median(fwd),
        "backward_s": statistics.median(bwd),
        "total_s": statistics.median(total),
        "total_min_s": min(total),
        "peak_rss_bytes": _vm("VmHWM"),
        "peak_delta_bytes": max(0, _vm("VmHWM") - rss0),
    }
    res["threads"] = torch.get_num_threads()
    if device.startswith("cuda"):
        res["cuda_peak_bytes"] = int(torch.cuda.max_memory_allocated())
    if profile:
        from torch.profiler import ProfilerActivity
        from torch.profiler import profile as torch_profile

        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            step()
        top = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)[:8]
        total = sum(e.self_cpu_time_total for e in prof.key_averages())
        res["profile_top"] = [[e.key, round(e.self_cpu_time_total / 1e3, 2), e.count] for e in top]
        res["profile_total_ms"] = round(total / 1e3, 2)
    return res


def _markdown(meta: dict, rows: list[dict]) -> str:
    backends = sorted({r.get("backend", "torch") for r in rows})
    multi = backends != ["torch"]
    title = "packed torch backend" if not multi else "backends: " + ", ".join(backends)
    lines = [
        f"# Surfel rasterizer benchmark ({title})",
        "",
        f"Machine: {meta['cpu_count']} CPUs, torch {meta['torch']} ({meta['threads']} threads), device {meta['device']}, "
        f"load average before/after {meta['load_before']} / {meta['load_after']} (the machine was shared).",
        "Scene: docs/rendering.md §3.2 (depth 3 ± 0.3, scales 0.005–0.025, opacity 0.1–0.9, f = 1.2·S); forward + full "
        f"backward over every output; median of {meta['repeats']} runs after one warm-up.",
        "Peak memory: peak resident set of a fresh process per case minus its resident set before rendering.",
        "Forward, backward and total are medians taken separately; best total is the fastest run.",
    ]
    if multi:
        lines.append(
            "Pairs: the torch backend counts every significant (surfel, pixel) pair, the cpp and triton backends only "
            "the composited ones (they stop at terminated pixels). CUDA peak memory is in the JSON (cuda_peak_bytes)."
        )
    head = "| N | image | pairs | forward (s) | backward (s) | total (s) | best total (s) | peak Δ RSS (GB) | load (1 min) |"
    lines += ["", ("| backend " if multi else "") + head, "|---" * (head.count("|") - 1 + multi) + "|"]
    for r in rows:
        lines.append(
            (f"| {r.get('backend', 'torch')} " if multi else "")
            + f"| {r['n']:,} | {r['size']}² | {r['pairs']:,} | {r['forward_s']:.2f} | {r['backward_s']:.2f} | "
            f"{r['total_s']:.2f} | {r['total_min_s']:.2f} | {r['peak_delta_bytes'] / 1e9:.2f} | {r['load_1min_at_start']:.1f} |"
        )
    lines += _speedups(rows) + _profiles(rows)
    return "\n".join(lines) + "\n"


def _speedups(rows: list[dict]) -> list[str]:
    """Markdown table of torch median total / other backend's median total, per case."""
    torch_rows = {(r["n"], r["size"]): r for r in rows if r.get("backend", "torch") == "torch"}
    others = [r for r in rows if r.get("backend", "torch") != "torch" and (r["n"], r["size"]) in torch_rows]
    if not others:
        return []
    out = [
        "",
        "Speed-up over the packed torch backend (forward + backward, ratio of the medians above; ratio of the best "
        "runs in brackets):",
        "",
        "| backend | N | image | torch total (s) | backend total (s) | speed-up |",
        "|---|---|---|---|---|---|",
    ]
    for r in others:
        t = torch_rows[(r["n"], r["size"])]
        out.append(
            f"| {r['backend']} | {r['n']:,} | {r['size']}² | {t['total_s']:.3f} | {r['total_s']:.3f} | "
            f"{t['total_s'] / r['total_s']:.1f}× ({t['total_min_s'] / r['total_min_s']:.1f}×) |"
        )
    return out


def _profiles(rows: list[dict]) -> list[str]:
    """Markdown lists of the top operators (self CPU time of one profiled step) per backend and case."""
    out: list[str] = []
    for r in rows:
        if "profile_top" not in r:
            continue
        if not out:
            out += ["", "Where the time goes (one extra profiled step; operators by self CPU time, summed over threads):"]
        ops = ", ".join(f"`{name}` {ms:.1f} ms" for name, ms, _ in r["profile_top"][:6])
        out.append(
            f"- {r.get('backend', 'torch')}, N = {r['n']:,}, {r['size']}² (profiled total {r['profile_total_ms']:.0f} ms): {ops}"
        )
    return out


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="N = 5k, 20k at 128² and 256², 2 repeats")
    ap.add_argument("--out", default="docs/benchmarks", help="folder for render_surfels.json / .md")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument(
        "--backend", nargs="+", default=["torch"], choices=["torch", "cpp", "triton", "auto"],
        help="rasterizer backends to time on the same scenes (triton needs --device cuda)",
    )
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads in every case process")
    ap.add_argument("--profile", action="store_true", help="profile one extra step per case (top operators)")
    ap.add_argument("--only", nargs=2, type=int, metavar=("N", "S"), help="run this one case of the grid")
    ap.add_argument("--case", nargs=2, type=int, metavar=("N", "S"), help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.case:
        row = run_case(args.case[0], args.case[1], args.repeats or 3, args.device, backend=args.backend[0],
                       threads=args.threads, profile=args.profile)
        print(json.dumps(row))
        return

    import torch

    grid = [(n, s) for n in GRID_N[:2] for s in GRID_S[:2]] if args.quick else [(n, s) for n in GRID_N for s in GRID_S]
    if args.only:
        grid = [tuple(args.only)]
    if args.threads:
        torch.set_num_threads(args.threads)
    repeats = args.repeats or (2 if args.quick else 3)
    load_before = [round(x, 2) for x in os.getloadavg()]
    rows = []
    for n, s in grid:
        for backend in args.backend:
            cmd = [sys.executable, __file__, "--case", str(n), str(s), "--repeats", str(repeats), "--device", args.device,
                   "--backend", backend]
            cmd += (["--threads", str(args.threads)] if args.threads else []) + (["--profile"] if args.profile else [])
            proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            rows.append(row)
            tag = f"[{backend}] " if len(args.backend) > 1 or backend != "torch" else ""
            print(f"{tag}N={n:>6} {s}²: total {row['total_s']:.2f} s (fwd {row['forward_s']:.2f}, bwd {row['backward_s']:.2f}), "
                  f"peak Δ {row['peak_delta_bytes'] / 1e9:.2f} GB, pairs {row['pairs']:,}", flush=True)
    meta = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "device": args.device,
        "backends": args.backend,
        "repeats": repeats,
        "load_before": load_before,
        "load_after": [round(x, 2) for x in os.getloadavg()],
        "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _write_atomic(out / "render_surfels.json", json.dumps({"meta": meta, "results": rows}, indent=2) + "\n")
    _write_atomic(out / "render_surfels.md", _markdown(meta, rows))


if __name__ == "__main__":
    main()
