"""Speed of the SDF network: the autograd reference against the fused native CPU kernel, one process.

Usage: python benchmarks/sdf_network.py [--threads 1] [--repeats 11] [--warmup 2] [--out docs/benchmarks]
       [--quick]

Networks (config.py presets; SDFNetConfig: hidden 64, one hidden layer, F_z 13, F = 2):
  * ``tiny``: grid of 8 levels, 2^14 entries per level, resolution 16..256;
  * ``small``: grid of 12 levels, 2^16 entries per level, resolution 16..512.
Cases:
  * ``grad+backward``: ``sdf, grad, feature = net.gradient(x, create_graph=True)`` at points that require
    a gradient, then the backward of eikonal + |sdf| + (1 - |n . t|) + a feature term into x, the table and
    the MLP (the pattern of the surfel-centre and NeuS terms of phase 1);
  * ``sdf no_grad``: ``net.sdf(x)`` under ``torch.no_grad`` (the NeuS coarse and importance sampling).
Points: ``surfels``, N points near an ellipsoid shell in random order (N = 6,000 for tiny, 20,000 for
small, the presets' surfel counts, and 256, the tiny preset's normal-smoothness points); ``rays``, N
samples in order along rays through the box (12,800 = 320 rays x 40 samples, the NeuS pattern).

Both backends (``SDFNetwork.backend`` torch / cpp; the reference's encoding uses the native hash grid,
as in training) run in the same process on the same inputs; each repeat times both, the order
alternating every repeat. Reported: the median wall time of each, the ratio of the medians (torch /
cpp), and the median CPU time of the process (less sensitive to other jobs on the machine).

Written: ``OUT/sdf_network.json`` and ``OUT/sdf_network.md`` (also printed).
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import _kernel_bench  # noqa: E402 - after the path set-up

GRIDS = {
    "tiny": dict(n_levels=8, n_features=2, log2_table=14, base_res=16, max_res=256),
    "small": dict(n_levels=12, n_features=2, log2_table=16, base_res=16, max_res=512),
}
MLP = dict(hidden=64, n_hidden_layers=1, feature_dim=13)
BOX = ((-0.15, -0.2, -0.15), (0.15, 0.15, 0.15))


def surfel_points(n: int, seed: int):  # noqa: ANN201 - torch tensor
    """(n, 3) points within 3 % of an ellipsoid shell filling the box, in random order."""
    import torch

    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(BOX[0]), torch.tensor(BOX[1])
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    r = 0.8 + 0.03 * torch.randn(n, 1, generator=g)
    return centre + half * r * d


def ray_points(n_rays: int, n_samples: int, seed: int):  # noqa: ANN201 - torch tensor
    """(n_rays * n_samples, 3) samples along rays from outside the box through its centre region, in ray order."""
    import torch

    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(BOX[0]), torch.tensor(BOX[1])
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    origin = centre + torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=-1) * 0.6
    aim = centre + half * 0.5 * (2 * torch.rand(n_rays, 3, generator=g) - 1)
    d = torch.nn.functional.normalize(aim - origin, dim=-1)
    t = 0.6 - 0.25 + 0.5 * (torch.arange(n_samples) + 0.5) / n_samples
    return (origin[:, None] + d[:, None] * t[None, :, None]).reshape(-1, 3)


def make_net(preset: str):  # noqa: ANN201 - SDFNetwork
    """A network of the preset's shape with a random table and encoding weights (both zero at init)."""
    import torch

    from sage_core.fields.sdf import SDFNetwork

    torch.manual_seed(0)
    net = SDFNetwork(*BOX, **GRIDS[preset], **MLP, sphere_radius=0.8)
    with torch.no_grad():
        net.encoding.table.uniform_(-0.05, 0.05)
        net.layers[0].weight[:, 3:].normal_(0.0, 0.5)
    return net


def grad_backward_case(preset: str, x0) -> Callable[[str], Callable[[], None]]:  # noqa: ANN001 - tensor
    """gradient(create_graph=True) and the backward of a training-style loss; backend -> step."""
    import torch

    net = make_net(preset)
    gen = torch.Generator().manual_seed(4)
    target = torch.nn.functional.normalize(torch.randn(x0.shape[0], 3, generator=gen), dim=-1)

    def make(backend: str) -> Callable[[], None]:
        def step() -> None:
            net.backend = backend
            net.zero_grad(set_to_none=True)
            x = x0.clone().requires_grad_(True)
            sdf, grad, feat = net.gradient(x, create_graph=True)
            norm = grad.norm(dim=-1)
            normal = grad / norm[:, None].clamp_min(1e-12)
            loss = ((norm - 1) ** 2).mean() + sdf.abs().mean() + (1 - (normal * target).sum(-1).abs()).mean()
            (loss + 0.1 * feat.square().mean()).backward()

        return step

    return make


def sdf_no_grad_case(preset: str, x0) -> Callable[[str], Callable[[], None]]:  # noqa: ANN001 - tensor
    """net.sdf(x) under no_grad; backend -> step."""
    import torch

    net = make_net(preset)

    def make(backend: str) -> Callable[[], None]:
        def step() -> None:
            net.backend = backend
            with torch.no_grad():
                net.sdf(x0)

        return step

    return make


def cases(quick: bool) -> list[tuple[str, str, str, int, Callable[[], object], Callable]]:
    """(case, preset, points, N, point factory, case factory) rows."""
    k = 10 if quick else 1
    rays = (320 // k, 40)
    return [
        ("grad+backward", "tiny", "surfels", 256, lambda: surfel_points(256, 1), grad_backward_case),
        ("grad+backward", "tiny", "surfels", 6000 // k, lambda: surfel_points(6000 // k, 1), grad_backward_case),
        ("grad+backward", "tiny", "rays", rays[0] * rays[1], lambda: ray_points(*rays, 2), grad_backward_case),
        ("grad+backward", "small", "surfels", 20000 // k, lambda: surfel_points(20000 // k, 1), grad_backward_case),
        ("grad+backward", "small", "rays", rays[0] * rays[1], lambda: ray_points(*rays, 2), grad_backward_case),
        ("sdf no_grad", "tiny", "rays", rays[0] * rays[1], lambda: ray_points(*rays, 2), sdf_no_grad_case),
        ("sdf no_grad", "small", "rays", rays[0] * rays[1], lambda: ray_points(*rays, 2), sdf_no_grad_case),
    ]


def run(repeats: int, warmup: int, quick: bool) -> list[dict]:
    """Time every case with both backends, interleaved; returns one row per case."""
    rows = []
    for name, preset, points, n, points_fn, factory in cases(quick):
        make = factory(preset, points_fn())
        steps = {b: make(b) for b in ("torch", "cpp")}
        for _ in range(warmup):
            for step in steps.values():
                step()
        wall: dict[str, list[float]] = {"torch": [], "cpp": []}
        cpu: dict[str, list[float]] = {"torch": [], "cpp": []}
        for r in range(repeats):
            order = ("torch", "cpp") if r % 2 == 0 else ("cpp", "torch")
            for b in order:
                t, c = time.perf_counter(), time.process_time()
                steps[b]()
                cpu[b].append(time.process_time() - c)
                wall[b].append(time.perf_counter() - t)
        med = {b: statistics.median(v) for b, v in wall.items()}
        cmed = {b: statistics.median(v) for b, v in cpu.items()}
        row = {
            "case": name,
            "preset": preset,
            "points": points,
            "n": n,
            "torch_ms": round(1e3 * med["torch"], 2),
            "cpp_ms": round(1e3 * med["cpp"], 2),
            "speedup": round(med["torch"] / med["cpp"], 2),
            "torch_cpu_ms": round(1e3 * cmed["torch"], 2),
            "cpp_cpu_ms": round(1e3 * cmed["cpp"], 2),
            "cpu_speedup": round(cmed["torch"] / cmed["cpp"], 2),
            "wall_s": wall,
            "cpu_s": cpu,
        }
        rows.append(row)
        print(
            f"{name:14s} {preset:5s} {points:7s} N={n:>6}: torch {row['torch_ms']:8.1f} ms  "
            f"cpp {row['cpp_ms']:7.1f} ms  {row['speedup']:.2f}x  (CPU time {row['cpu_speedup']:.2f}x)",
            flush=True,
        )
    return rows


def markdown(meta: dict, rows: list[dict]) -> str:
    """The report as a Markdown page."""
    lines = [
        "# SDF network: autograd reference vs fused native CPU kernel",
        "",
        f"Command: `{meta['command']}`",
        "",
        f"Machine: {meta['cpu_count']} CPUs ({meta['cpu']}), torch {meta['torch']}, {meta['threads']} thread(s), "
        f"AVX2 build: {meta['avx2']}; load average before/after {meta['load_before']} / {meta['load_after']}"
        f"{' (other jobs were running)' if meta['load_before'][0] > 1.0 else ''}; {meta['date_utc']} UTC.",
        f"Median of {meta['repeats']} interleaved repeats after {meta['warmup']} warm-up steps per backend; "
        "wall time, and CPU time of the process (less sensitive to the other jobs).",
        "",
        "- Networks: the `tiny` and `small` presets' SDF (hash grid of 8 levels, 2^14 entries, resolution 16 to 256, "
        "and of 12 levels, 2^16, 16 to 512; F = 2; one hidden layer of 64; Softplus(100); feature 13).",
        "- `grad+backward`: `net.gradient(x, create_graph=True)` at points that require a gradient, then the backward "
        "of eikonal + |sdf| + (1 - |n . t|) + a feature term into x, the table and the MLP.",
        "- `sdf no_grad`: `net.sdf(x)` under `no_grad` (NeuS sampling).",
        "- Points: `surfels` near an ellipsoid shell, random order (6,000 / 20,000: the presets' surfel counts; "
        "256: the tiny preset's smoothness points); `rays`: 320 rays x 40 samples in ray order (12,800).",
        "- torch: `SDFNetwork(backend='torch')` with the native hash-grid encoding (as in training before this "
        "kernel); cpp: the fused kernel (`backend='cpp'`).",
        "",
        "| case | preset | points | N | torch wall (ms) | cpp wall (ms) | speed-up | torch CPU (ms) | cpp CPU (ms) "
        "| speed-up (CPU) |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['preset']} | {r['points']} | {r['n']:,} | {r['torch_ms']:.1f} | {r['cpp_ms']:.1f} | "
            f"**{r['speedup']:.2f}x** | {r['torch_cpu_ms']:.1f} | {r['cpp_cpu_ms']:.1f} | {r['cpu_speedup']:.2f}x |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    args = _kernel_bench.parse_args(__doc__.splitlines()[0], "sdf_network", repeats=11)

    import torch

    from sage_core.fields import _cpp_sdf

    torch.set_num_threads(args.threads)
    ok, reason = _cpp_sdf.available()
    if not ok:
        raise SystemExit(f"the native SDF extension is unavailable: {reason}")
    load_before = _kernel_bench.loadavg()
    rows = run(args.repeats, args.warmup, args.quick)
    meta = _kernel_bench.run_meta(
        "sdf_network.py", args, load_before,
        avx2=bool(torch.ops.sage_sdf_cpu.avx2()),
        geomean_speedup_wall=round(math.exp(statistics.mean(math.log(r["speedup"]) for r in rows)), 2),
    )  # fmt: skip
    _kernel_bench.write(args, "sdf_network", meta, rows, markdown(meta, rows))


if __name__ == "__main__":
    main()
