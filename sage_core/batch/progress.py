"""A subject's live status from its stages' events (:mod:`sage_core.stages.events`).

:class:`StatusWriter` is the ``on_event`` callback of a batch subject's chain: it keeps
``WS/.batch_status.json`` up to date with the stage that started last (so a failure names the
stage that failed, even one that stops before its work begins), its step and total, the progress
message and the training PSNR (the ``psnr`` metric of a progress event), at most every
``min_interval`` seconds except for a stage's start, end and last step.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

from ..stages.events import StageEvent, format_stat
from .summary import write_status


class StatusWriter:
    """Writes the events of one subject's stages into its status file (never raises)."""

    def __init__(self, ws: str | Path, min_interval: float = 2.0) -> None:
        self.ws = Path(ws)
        self.min_interval = min_interval
        self._last = 0.0

    def __call__(self, ev: StageEvent) -> None:
        try:
            self._write(ev)
        except Exception:  # noqa: BLE001 - a status update must never break the stage
            pass

    def _write(self, ev: StageEvent) -> None:
        if ev.kind == "started":  # the stage a failure before its work belongs to
            write_status(self.ws, stage=ev.stage, done=0, total=None, message="starting")
            self._last = time.time()
        elif ev.kind == "running":
            write_status(self.ws, stage=ev.stage, done=0, total=None, message="started")
            self._last = time.time()
        elif ev.kind == "finished" and ev.result is not None:
            write_status(self.ws, stage=ev.stage, message="skipped" if getattr(ev.result, "skipped", False) else "complete")
        elif ev.kind == "progress":
            final = ev.total is not None and ev.step is not None and ev.step >= ev.total
            if not final and time.time() - self._last < self.min_interval:
                return
            info = ev.message
            if ev.metrics:
                info = (info + "  " if info else "") + "  ".join(format_stat(k, v) for k, v in ev.metrics.items())
            fields: dict[str, Any] = {"done": ev.step, "total": ev.total, "message": info[:120]}
            psnr = ev.metrics.get("psnr")
            if isinstance(psnr, (int, float)) and not isinstance(psnr, bool) and math.isfinite(float(psnr)):
                fields["psnr"] = float(psnr)
            write_status(self.ws, **fields)
            self._last = time.time()
