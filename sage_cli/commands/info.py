"""``sage info WS``: a table of the workspace's stages."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Annotated

import typer

from .._common import cli_errors, console, fmt_metric, require_workspace


def _age(iso: str | None) -> str:
    if not iso:
        return ""
    try:
        t = dt.datetime.fromisoformat(iso)
    except ValueError:
        return ""
    s = (dt.datetime.now(dt.timezone.utc) - t).total_seconds()
    for unit, n in (("d", 86400), ("h", 3600), ("min", 60)):
        if s >= n:
            return f"{s / n:.0f} {unit} ago"
    return f"{s:.0f} s ago"


# the metrics ``sage info`` shows first for each stage (others follow until four are shown)
KEY_METRICS: dict[str, tuple[str, ...]] = {
    "ingest": ("regime", "train_images", "val_images", "test_images"),
    "init-mesh": ("chamfer_rel", "mean_abs_sdf_rel", "normal_cos"),
    "phase1": ("val_psnr", "train_psnr", "chamfer_rel", "iterations_per_s"),
    "phase2": ("test_psnr",),
    "eval": ("psnr", "ssim", "lpips"),
}


RUNTIME_KEYS = ("threads", "render_backend", "hashgrid_backend", "sdf_backend")
"""Manifest ``metrics`` entries that describe how the stage ran (the "ran on" column), not results."""


def _ran_on(m: dict | None) -> str:
    """``cpu · 2 threads · cpp``: device, thread count and resolved render backend of a manifest."""
    if not m:
        return ""
    metrics = m.get("metrics") or {}
    parts = [str(m["device"])] if m.get("device") else []
    if isinstance(metrics.get("threads"), int):
        parts.append(f"{metrics['threads']} thread{'s' if metrics['threads'] != 1 else ''}")
    if metrics.get("render_backend"):
        parts.append(f"{metrics['render_backend']} rasterizer")
    if metrics.get("hashgrid_backend"):
        parts.append(f"{metrics['hashgrid_backend']} hash grid")
    if metrics.get("sdf_backend"):
        parts.append(f"{metrics['sdf_backend']} SDF")
    return " · ".join(parts)


def _metrics(stage: str, m: dict | None, limit: int = 3) -> str:
    if not m:
        return ""
    metrics = {k: v for k, v in (m.get("metrics") or {}).items() if k not in RUNTIME_KEYS}
    order = [k for k in KEY_METRICS.get(stage, ()) if k in metrics] + sorted(k for k in metrics if k not in KEY_METRICS.get(stage, ()))
    parts = []
    for k in order:
        v = metrics[k]
        if isinstance(v, bool) or not isinstance(v, (int, float, str)):
            continue
        parts.append(f"{k} {fmt_metric(v)}" if isinstance(v, float) else f"{k} {v}")
        if len(parts) >= limit:
            break
    return "\n".join(parts)


def _reenact_table(root: Path) -> object | None:
    """A table of the reenactments in ``root/reenact/*/reenact.json`` (None when there are none)."""
    import json

    from rich.table import Table

    records = sorted((root / "reenact").glob("*/reenact.json")) if (root / "reenact").is_dir() else []
    if not records:
        return None
    t = Table(title="reenactments (WS/reenact/)")
    for col in ("name", "finished", "frames", "cameras", "render FPS", "outputs"):
        t.add_column(col, overflow="fold")
    for path in records:
        try:
            doc = json.loads(path.read_text())
            rep = doc.get("report") or {}
            # paths in the record are relative to its folder (absolute in records of older versions)
            outputs = [str(path.parent / p) for p in (rep.get("video_path"), rep.get("frames_dir")) if p]
            fps = rep.get("render_fps")
            t.add_row(path.parent.name, _age(doc.get("finished_at")), str(rep.get("n_frames", "")), str(doc.get("cameras", "")),
                      f"{fps:.2f}" if isinstance(fps, (int, float)) else "", "\n".join(outputs))  # fmt: skip
        except (OSError, ValueError, AttributeError) as e:
            t.add_row(path.parent.name, "", "", "", "", f"[red]unreadable reenact.json ({type(e).__name__})[/]")
    return t


def info(
    ws: Annotated[Path, typer.Argument(help="Workspace folder.")],
    verify: Annotated[bool, typer.Option("--verify", help="Also check every output of every complete stage against the SHA-256 its manifest recorded (reads every file); exit 4 when one changed.")] = False,
) -> None:
    """Show every stage of a workspace: status, age, wall time, device / threads / render backend, and key metrics."""
    from rich.table import Table

    from sage_core.workspace import Workspace

    with cli_errors():
        require_workspace(ws)
        w = Workspace(ws)
        t = Table(title=f"sage workspace {w.root}")
        t.add_column("stage", no_wrap=True)
        t.add_column("status", min_width=8)
        t.add_column("finished", min_width=9)
        t.add_column("wall time", no_wrap=True)
        t.add_column("ran on", overflow="fold")
        t.add_column("key metrics", overflow="fold")
        colours = {"complete": "green", "stale": "yellow", "missing": "dim", "interrupted": "yellow", "failed": "red",
                   "incomplete": "red", "corrupt": "red", "running": "cyan", "changed": "red"}
        changed: list[str] = []
        for st in w.stages():
            m = st.manifest or {}
            status = st.status + (f" ({st.reason})" if st.reason else "")
            if verify and st.status == "complete":
                problems = w.verify(st.stage)
                if problems:
                    more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
                    status = f"[{colours['changed']}]changed ({problems[0]}{more})[/]"
                    changed += [f"{st.folder.name}/{p}" for p in problems]
            wall = m.get("wall_time_s")
            t.add_row(
                f"{st.stage} ({st.folder.name}/)",
                status if status.startswith("[") else f"[{colours.get(st.status, 'white')}]{status}[/]",
                _age(m.get("finished_at")),
                f"{wall:.1f} s" if isinstance(wall, (int, float)) else "",
                _ran_on(st.manifest),
                _metrics(st.stage, m),
            )
        console.print(t)
        runs = _reenact_table(w.root)
        if runs is not None:
            console.print(runs)
        if verify:
            if changed:
                from sage_core.errors import StageError

                raise StageError(f"{w.root}: {len(changed)} output(s) changed since their stage finished: " + "; ".join(changed[:5])
                                 + (" ..." if len(changed) > 5 else "") + "; re-run those stages with --force")
            console.print("verified: every output of every complete stage matches its manifest"
                          if any(st.status == "complete" for st in w.stages()) else "nothing to verify")
