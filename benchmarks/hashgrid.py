"""Speed of the hash-grid encoding: the pure-torch reference against the native CPU kernel, one run.

Usage: python benchmarks/hashgrid.py [--threads 1] [--repeats 9] [--warmup 2] [--out docs/benchmarks]
       [--quick]

Cases (tiny-preset sizes, config.py):
  * ``app``: the appearance network's grid (8 levels, 2^15 entries, resolution 16..512, F = 2).
    Forward plus the backward of a random linear loss on the features into the table and x, at
    N = 6,000 (the tiny preset's surfels) and 20,000.
  * ``sdf-eikonal``: a full ``SDFNetwork`` with the tiny SDF grid (8 levels, 2^14, 16..256, F = 2,
    hidden 64): sdf and feature at x, ``autograd.grad(sdf.sum(), x, create_graph=True)``, then the
    backward of eikonal + |sdf| + a normal-alignment term into the table, the MLP and x, at N = 6,000
    (surfel centres) and 10,240 (256 rays x 40 NeuS samples).
Both backends run in the same process on the same inputs; each repeat times torch then cpp (the
order alternates every repeat), so a drift in machine load touches both alike. The report gives
the median of each and the ratio of the medians (torch / cpp).

Written: ``OUT/hashgrid.json`` and ``OUT/hashgrid.md`` (also printed).
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import _kernel_bench  # noqa: E402 - after the path set-up

APP = dict(n_levels=8, n_features=2, log2_table=15, base_res=16, max_res=512)
SDF_GRID = dict(n_levels=8, n_features=2, log2_table=14, base_res=16, max_res=256)
BOX = ((-0.15, -0.2, -0.15), (0.15, 0.15, 0.15))


def _points(n: int, seed: int):  # noqa: ANN202 - torch tensor
    import torch

    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(BOX[0]), torch.tensor(BOX[1])
    return lo + (hi - lo) * (0.1 + 0.8 * torch.rand(n, 3, generator=g))


def app_step(n: int) -> Callable[[str], Callable[[], None]]:
    """Forward + backward of the appearance-grid encoding; returns backend -> step function."""
    import torch

    from sage_core.fields.hashgrid import HashGrid

    torch.manual_seed(0)
    grid = HashGrid(*BOX, **APP)
    with torch.no_grad():
        grid.table.uniform_(-0.1, 0.1)
    x0 = _points(n, 1)
    w = torch.randn(n, grid.output_dim, generator=torch.Generator().manual_seed(2))

    def make(backend: str) -> Callable[[], None]:
        def step() -> None:
            grid.backend = backend
            grid.table.grad = None
            x = x0.clone().requires_grad_(True)
            (grid(x) * w).sum().backward()

        return step

    return make


def sdf_eikonal_step(n: int) -> Callable[[str], Callable[[], None]]:
    """The SDF terms' pattern: gradient with create_graph, then the backward of a loss on it."""
    import torch

    from sage_core.fields.sdf import SDFNetwork

    torch.manual_seed(0)
    net = SDFNetwork(*BOX, **SDF_GRID, hidden=64, n_hidden_layers=1, feature_dim=13)
    with torch.no_grad():
        net.encoding.table.uniform_(-0.05, 0.05)
        net.layers[0].weight[:, 3:].normal_(0.0, 0.5)
    x0 = _points(n, 3)
    target = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(4)), dim=-1)

    def make(backend: str) -> Callable[[], None]:
        def step() -> None:
            net.encoding.backend = backend
            net.zero_grad(set_to_none=True)
            x = x0.clone().requires_grad_(True)
            sdf, _feat = net(x)
            (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=True)
            eik = ((grad.norm(dim=-1) - 1) ** 2).mean()
            align = (1 - torch.nn.functional.cosine_similarity(grad, target, dim=-1)).mean()
            (eik + align + sdf.abs().mean()).backward()

        return step

    return make


CASES: list[tuple[str, int, Callable[[int], Callable[[str], Callable[[], None]]]]] = [
    ("app", 6000, app_step),
    ("app", 20000, app_step),
    ("sdf-eikonal", 6000, sdf_eikonal_step),
    ("sdf-eikonal", 10240, sdf_eikonal_step),
]


def run(repeats: int, warmup: int, quick: bool) -> list[dict]:
    """Time every case with both backends, interleaved; returns one row per case."""
    rows = []
    for name, n, factory in CASES:
        if quick:
            n = n // 10
        make = factory(n)
        steps = {b: make(b) for b in ("torch", "cpp")}
        for _ in range(warmup):
            for step in steps.values():
                step()
        times: dict[str, list[float]] = {"torch": [], "cpp": []}
        for r in range(repeats):
            order = ("torch", "cpp") if r % 2 == 0 else ("cpp", "torch")
            for b in order:
                t = time.perf_counter()
                steps[b]()
                times[b].append(time.perf_counter() - t)
        med = {b: statistics.median(v) for b, v in times.items()}
        row = {
            "case": name,
            "n": n,
            "torch_ms": round(1e3 * med["torch"], 2),
            "cpp_ms": round(1e3 * med["cpp"], 2),
            "speedup": round(med["torch"] / med["cpp"], 2),
            "times_s": times,
        }
        rows.append(row)
        print(f"{name:12s} N={n:>6}: torch {row['torch_ms']:8.1f} ms  cpp {row['cpp_ms']:7.1f} ms  "
              f"{row['speedup']:.1f}x", flush=True)
    return rows


def markdown(meta: dict, rows: list[dict]) -> str:
    """The report as a Markdown page."""
    lines = [
        "# Hash-grid encoding: torch reference vs native CPU kernel",
        "",
        f"Command: `{meta['command']}`",
        "",
        f"Machine: {meta['cpu_count']} CPUs, torch {meta['torch']}, {meta['threads']} thread(s); load average "
        f"before/after {meta['load_before']} / {meta['load_after']}; {meta['date_utc']} UTC.",
        f"Median of {meta['repeats']} interleaved repeats after {meta['warmup']} warm-up steps per backend.",
        "",
        "- `app`: the appearance grid of the tiny preset (8 levels, 2^15 entries per level, resolution 16 to 512, "
        "F = 2), forward and backward into the table and x.",
        "- `sdf-eikonal`: a whole SDF network with the tiny preset's grid (8 levels, 2^14, 16 to 256, F = 2, hidden 64): "
        "sdf at x, its gradient with `create_graph`, and the backward of eikonal + normal alignment + |sdf| into the "
        "table, the MLP and x (the double backward). N = 10,240 is 256 rays × 40 NeuS samples.",
        "",
        "| case | N | torch (ms) | cpp (ms) | speed-up |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['case']} | {r['n']:,} | {r['torch_ms']:.1f} | {r['cpp_ms']:.1f} | **{r['speedup']:.1f}×** |")
    return "\n".join(lines) + "\n"


def main() -> None:
    args = _kernel_bench.parse_args(__doc__.splitlines()[0], "hashgrid", repeats=9)

    import torch

    from sage_core.fields import _cpp_hashgrid

    torch.set_num_threads(args.threads)
    ok, reason = _cpp_hashgrid.available()
    if not ok:
        raise SystemExit(f"the native hash-grid extension is unavailable: {reason}")
    load_before = _kernel_bench.loadavg()
    rows = run(args.repeats, args.warmup, args.quick)
    meta = _kernel_bench.run_meta("hashgrid.py", args, load_before)
    _kernel_bench.write(args, "hashgrid", meta, rows, markdown(meta, rows))


if __name__ == "__main__":
    main()
