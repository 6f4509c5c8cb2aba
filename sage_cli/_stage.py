"""Showing a stage run from the CLI: the engine's stage events drawn as rich output.

:class:`StageDisplay` consumes :class:`sage_core.stages.StageEvent` objects: notes and the skip line
are printed, ``running`` prints what the stage runs on (device, threads and why, rasterizer) and
opens a progress bar (it/s, loss, PSNR, ETA; closed when the stage finishes or fails), ``estimate``
prints the duration estimate and the updates that move it. ``rules=True`` (``sage run``, ``sage demo``)
puts a rule with the stage's name above each stage.
"""

from __future__ import annotations

from typing import Any

from ._common import ProgressDisplay, console


class StageDisplay:
    """The ``on_event`` callback of the stage functions, drawing with rich; use it as a context
    manager so a failing stage closes its progress bar."""

    def __init__(self, verbose: bool = True, preset: str | None = None, rules: bool = False) -> None:
        self.verbose = verbose
        self.preset = preset
        self.rules = rules
        self._bar: ProgressDisplay | None = None

    def __enter__(self) -> "StageDisplay":
        return self

    def __exit__(self, *exc: Any) -> None:
        self._close(*exc)

    def _close(self, *exc: Any) -> None:
        if self._bar is not None:
            bar, self._bar = self._bar, None
            bar.__exit__(*(exc or (None, None, None)))

    def __call__(self, ev: Any) -> None:
        kind = ev.kind
        if kind == "started":
            if self.rules:
                console.rule(f"[bold]{ev.stage}")
        elif kind == "note":
            if ev.level == "warning":
                console.print(f"[yellow]warning:[/] {ev.message}")
            elif ev.level == "notice":
                console.print(f"[yellow]{ev.stage}[/]: {ev.message}")
            elif self.verbose:
                console.print(f"[bold]{ev.title}[/]: {ev.message}" if ev.title else ev.message)
        elif kind == "skipped":
            console.print(f"[green]{ev.stage}[/]: {ev.message}")
        elif kind == "running":
            self._close()
            if self.verbose:
                console.print(f"[bold]{ev.title or ev.stage}[/]: {running_line(ev.metrics)}", soft_wrap=True)
            if ev.metrics.get("resumed"):
                console.print(f"[yellow]{ev.stage}[/]: resuming an interrupted run")
            self._bar = ProgressDisplay(ev.title or ev.stage, enabled=self.verbose, device=ev.metrics.get("device"), preset=self.preset)
            self._bar.__enter__()
        elif kind in ("progress", "estimate"):
            if self._bar is not None:
                self._bar(ev.step or 0, ev.total, ev.message, **ev.metrics)
        elif kind == "finished":
            self._close()


def running_line(metrics: dict[str, Any]) -> str:
    """What a stage runs on, from its ``running`` event: ``cpu · 2 threads (2 of 2 cores idle) · cpp
    rasterizer``."""
    parts = [str(metrics.get("device") or "?")]
    basis = metrics.get("threads_basis")
    if basis:
        parts.append(str(basis))
    elif metrics.get("threads"):
        n = int(metrics["threads"])
        parts.append(f"{n} thread{'s' if n != 1 else ''}")
    if metrics.get("render_backend"):
        parts.append(f"{metrics['render_backend']} rasterizer")
    return " · ".join(parts)
