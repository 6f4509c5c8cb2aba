"""``sage info WS``: a table of the workspace's stages."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Annotated

import typer

from .._common import cli_errors, console


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


def _metrics(m: dict | None) -> str:
    if not m:
        return ""
    parts = []
    for k, v in (m.get("metrics") or {}).items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            parts.append(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}")
        if len(parts) >= 4:
            break
    return "  ".join(parts)


def info(ws: Annotated[Path, typer.Argument(help="Workspace folder.")]) -> None:
    """Show every stage of a workspace: status, age, wall time and key metrics."""
    from rich.table import Table

    from sage_core.errors import InputError
    from sage_core.workspace import Workspace

    with cli_errors():
        if not ws.is_dir():
            raise InputError(ws, "workspace folder not found")
        w = Workspace(ws)
        t = Table(title=f"sage workspace {w.root}")
        for col in ("stage", "folder", "status", "finished", "wall time", "seed", "device", "key metrics"):
            t.add_column(col)
        colours = {"complete": "green", "stale": "yellow", "missing": "dim", "interrupted": "yellow", "failed": "red"}
        for st in w.stages():
            m = st.manifest or {}
            status = st.status + (f" ({st.reason})" if st.reason else "")
            wall = m.get("wall_time_s")
            t.add_row(
                st.stage,
                st.folder.name + "/",
                f"[{colours.get(st.status, 'white')}]{status}[/]",
                _age(m.get("finished_at")),
                f"{wall:.1f} s" if isinstance(wall, (int, float)) else "",
                str(m.get("seed", "")),
                str(m.get("device", "")),
                _metrics(m),
            )
        console.print(t)
