"""``sage eval WS``: PSNR / SSIM / LPIPS of the avatar on the evaluation splits (docs/formats.md §8);
``sage lpips-weights``: build the LPIPS weights file it uses.

Every frame of a split is rendered with that frame's FLAME parameters and camera on the dataset
background and compared with its ground truth. ``WS/eval/`` is a workspace stage that accumulates
results: each (avatar stage, split) pair has its own folder ``WS/eval/<stage>/<split>/`` with
``metrics.json``, ``config.json`` and sample strips in ``images/``; ``WS/eval/results.json`` indexes
them (key of the inputs, avatar stage and fingerprint, overall means). ``--split novel`` scores the
avatar on the capture's held-out ground truth (``CAPTURE/gt/novel``: novel views and expressions)
over the full image and over the region the training view(s) saw (``sage_core.evaluate.novel``).
A new run copies the earlier
results whose avatar stage is unchanged into the new stage folder and drops those whose avatar was
re-trained since; the manifest lists every result's means. Re-running a (stage, split) whose avatar,
data, settings and LPIPS weights are unchanged skips it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

from .._common import (
    require_workspace,
    ConfigOpt,
    DeviceOpt,
    ForceOpt,
    PresetOpt,
    SeedOpt,
    SetOpt,
    RenderBackendOpt,
    ThreadsOpt,
    VerboseOpt,
    cli_errors,
    console,
    fmt_metric,
    parse_sets,
    resolve_stage_config,
    summary_panel,
)
from .._stage import StageDisplay

if TYPE_CHECKING:
    from sage_core.stages import EvalResult

_LPIPS_HINT = "unavailable: no weights (give --lpips-weights, set $SAGE_LPIPS_WEIGHTS or place ~/.cache/sage/lpips_alex_v0.1.pth; `sage lpips-weights` builds it)"


def _fmt(v: Any, digits: int) -> str:
    """A metric with ``digits`` decimals; a string as it is; the dash where there is no value."""
    if isinstance(v, str):
        return v
    return fmt_metric(v, f".{digits}f")


def metrics_rows(doc: dict[str, Any]) -> list[tuple[str, ...]]:
    """Table rows (group, images, PSNR, PSNR (GA), SSIM, LPIPS) from a ``metrics.json`` document:
    one per camera, then the frontal camera and all images."""

    def row(name: str, m: dict[str, Any]) -> tuple[str, ...]:
        return (name, str(m["count"]), _fmt(m["psnr"], 2), _fmt(m["psnr_ga"], 2), _fmt(m["ssim"], 4), _fmt(m["lpips"], 4))

    out = [row(f"camera {c}", m) for c, m in sorted(doc["per_camera"].items(), key=lambda kv: int(kv[0]))]
    if doc.get("frontal") is not None:
        out.append(row(f"frontal (cam {doc.get('frontal_camera', 8)})", doc["frontal"]))
    out.append(row("all", doc["overall"]))
    return out


def print_metrics_table(title: str, doc: dict[str, Any]) -> None:
    """A rich table of one split's metrics (per camera, frontal, all)."""
    from rich.table import Table

    t = Table(title=title, show_lines=False)
    for c in ("group", "images", "PSNR", "PSNR (GA)", "SSIM", "LPIPS"):
        t.add_column(c, justify="left" if c == "group" else "right")
    for r in metrics_rows(doc):
        t.add_row(*r, style="bold" if r[0] == "all" else None)
    console.print(t)


def eval_(
    ws: Annotated[Path, typer.Argument(help="Workspace folder (after `sage phase1` or `sage phase2`).")],
    split: Annotated[Optional[str], typer.Option("--split", help="test (self-reenactment), val (novel view), all (both) or novel (the capture's held-out gt/novel views and expressions).")] = None,
    stage: Annotated[Optional[str], typer.Option("--stage", help="Avatar to evaluate: auto (latest finished of phase2, phase1), phase1 or phase2.")] = None,
    lpips_weights: Annotated[Optional[Path], typer.Option("--lpips-weights", help="LPIPS AlexNet v0.1 weights (default: $SAGE_LPIPS_WEIGHTS, then ~/.cache/sage/lpips_alex_v0.1.pth, which `sage lpips-weights` builds; without them LPIPS is reported unavailable).")] = None,
    samples: Annotated[Optional[int], typer.Option("--samples", help="Sample strips (GT | render | error) written per split.")] = None,
    preset: PresetOpt = "default",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "auto",
    force: ForceOpt = False,
    verbose: VerboseOpt = True,
    threads: ThreadsOpt = None,
    render_backend: RenderBackendOpt = None,
) -> None:
    """Evaluate the avatar: PSNR, SSIM and LPIPS per image, per camera, frontal and overall; results accumulate in WS/eval/<stage>/<split>/."""
    with cli_errors():

        flags = {"split": split, "stage": stage, "samples": samples, "render_backend": render_backend, **parse_sets(set_)}
        cfg = resolve_stage_config("eval", preset, config, flags)
        require_workspace(ws)
        from sage_core.stages import StageSettings, eval_stage

        with StageDisplay(verbose, preset) as display:
            r = eval_stage(ws, cfg, lpips_weights, StageSettings(seed, device, force, threads), display)
        show(r, ws)


def _means(m: dict[str, Any]) -> str:
    return f"{_fmt(m['psnr'], 2)} dB / {_fmt(m['ssim'], 4)} / {_fmt(m['lpips'], 4)}"


def show(r: EvalResult, ws: Path) -> None:
    """The metrics tables of an eval result, then (unless it was skipped) the closing panel: avatar,
    the split means, LPIPS, the other results in the index, wall time (``sage eval``, ``sage run``)."""
    from sage_core.workspace import Workspace

    w = Workspace(ws)
    out_dir = w.stage_dir("eval")
    rows: list[tuple[str, Any]] = []
    paths: list[tuple[str, Path]] = []
    if r.novel_root is not None:
        name = r.names[0]
        doc = r.documents[name]
        print_metrics_table(f"{name} (held-out views and expressions)", doc)
        print_metrics_table(f"{name} visible region", doc["visible_region"])
        rows = [("held-out ground truth", str(r.novel_root)), ("frontal", f"camera {doc['frontal_camera']} ({doc['frontal_rule']})"),
                ("all views PSNR / SSIM / LPIPS", _means(doc["overall"]))]  # fmt: skip
        if doc.get("frontal") is not None:
            rows.append(("frontal PSNR / SSIM / LPIPS", _means(doc["frontal"])))
        rows.append(("visible region PSNR / SSIM / LPIPS", _means(doc["visible_region"]["overall"])))
        for group, g in (doc.get("view_groups") or {}).items():
            rows.append((f"{group} views PSNR / SSIM / LPIPS", f"{_means(g['overall'])} (cameras {', '.join(str(c) for c in g['cameras'])})"))
        paths = [("novel metrics", out_dir / name / "metrics.json"), ("novel samples", out_dir / name / "images")]
        lpips_label, notes = "LPIPS", []
    else:
        for name in r.names:
            split = name.rsplit("/", 1)[1]
            doc = r.documents[name]
            if r.skipped:
                print_metrics_table(name, doc)
                continue
            print_metrics_table(f"{name} ({'novel view' if split == 'val' else 'self-reenactment'})", doc)
            rows.append((f"{split} PSNR / SSIM / LPIPS", _means(doc["overall"])))
            paths.append((f"{split} metrics", out_dir / name / "metrics.json"))
            paths.append((f"{split} samples", out_dir / name / "images"))
        lpips_label, notes = "LPIPS weights", [("PSNR", "standard per image (GA's per-channel mean beside it, labelled)")]
    if r.skipped:
        return
    rows = [("avatar", f"{r.avatar_stage} ({w.stage_dir(r.avatar_stage) / 'avatar.pt'})"), *rows]
    rows.append(("LPIPS", _LPIPS_HINT) if r.lpips_weights is None else (lpips_label, str(r.lpips_weights)))
    others = sorted(k for k in r.index if k not in set(r.names))
    if others:
        rows.append(("also in WS/eval", ", ".join(others)))
    rows += notes
    rows.append(("wall time", f"{r.wall_time_s:.1f} s"))
    summary_panel("sage eval", rows, paths + [("results index", out_dir / "results.json")])


def lpips_weights(
    heads: Annotated[Optional[Path], typer.Option("--heads", help="LPIPS v0.1 linear heads: the lpips package's weights/v0.1/alex.pth, or an lpips 0.1.4 wheel (.whl) holding it (default: fetch the wheel with pip).")] = None,
    alexnet: Annotated[Optional[Path], typer.Option("--alexnet", help="torchvision's ImageNet AlexNet checkpoint alexnet-owt-7be5be79.pth (default: torchvision's copy in ~/.cache/torch/hub/checkpoints/, or $TORCH_HOME/hub/checkpoints/).")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="File to write (default: ~/.cache/sage/lpips_alex_v0.1.pth, where `sage eval` looks).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing file.")] = False,
) -> None:
    """Build the LPIPS weights file `sage eval` uses from the lpips package's linear heads and torchvision's AlexNet, checking keys, shapes and SHA-256."""
    with cli_errors():
        from sage_core.evaluate.lpips_weights import build_lpips_weights

        r = build_lpips_weights(heads, alexnet, out, force)
        summary_panel("sage lpips-weights", r.rows(), [("file", r.path)])
