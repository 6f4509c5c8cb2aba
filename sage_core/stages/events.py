"""Structured progress of the stages: one small event type, sent through an ``on_event`` callback.

A stage function emits, in order:

* ``started`` when it is entered (before its inputs are checked);
* ``note`` for things worth telling before or beside the work (``level`` ``info`` or ``warning``);
* ``skipped`` when the stage (or every item asked of it) is already complete with the same config
  and inputs; ``message`` says so;
* ``running`` when the work begins (``title``, ``resumed``, ``device``, ``threads``,
  ``threads_basis`` (why that many), ``render_backend`` in ``metrics``);
* ``estimate`` once a training loop knows its duration, then as it re-estimates (``metrics``:
  ``estimate_s``, ``remaining_s``, ``s_per_step``, ``estimate_basis``, ``estimate_first``);
* ``progress`` as it goes (``step`` of ``total``, ``message``, ``metrics``: losses, PSNR ...);
* ``finished`` with the stage's result object (also after a skip).

The engine never prints: a display (the CLI's progress bars, ``sage batch``'s status files) consumes
these events.
"""

from __future__ import annotations

import logging
import math
import numbers
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Literal

EventKind = Literal["started", "note", "skipped", "running", "estimate", "progress", "finished"]
EVENT_KINDS: tuple[str, ...] = ("started", "note", "skipped", "running", "estimate", "progress", "finished")


@dataclass(frozen=True)
class StageEvent:
    """One thing a stage reports.

    kind: see the module doc. stage: the stage name (``phase1``, ``eval`` ...). step / total: the
    progress counter (total None when unknown). message: a short human text. metrics: numbers of
    this event (losses, PSNR, an estimate, the run's device). level: ``info`` or ``warning``
    (notes). title: what a display names the running stage (``phase 1``, ``eval phase1``).
    result: the stage's result object (``finished`` only).
    """

    kind: EventKind
    stage: str
    step: int | None = None
    total: int | None = None
    message: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)
    level: str = "info"
    title: str = ""
    result: Any = None


EventFn = Callable[[StageEvent], None]
"""The callback a stage function takes (``on_event``)."""


class Emitter:
    """Sends one stage's events to ``on_event`` (None: nowhere) and logs the progress.

    Calling it as ``emitter(done, total, message="", **stats)`` is the engine's progress callback
    (the training loops' signature): stats with ``estimate_s`` become an ``estimate`` event, the
    rest ``progress`` events. Progress also goes to the ``sage`` logger (the stage's log file)
    every ``log_every_s`` seconds and at the end.
    """

    def __init__(self, stage: str, on_event: EventFn | None, title: str = "", log_every_s: float = 5.0) -> None:
        self.stage = stage
        self.on_event = on_event
        self.title = title or stage
        self.log_every_s = log_every_s
        self._last_log = 0.0
        self._log = logging.getLogger("sage")

    def emit(self, kind: EventKind, **fields: Any) -> None:
        """Send one event of ``kind`` for this stage."""
        if self.on_event is not None:
            self.on_event(StageEvent(kind=kind, stage=self.stage, **fields))

    def note(self, message: str, level: str = "info") -> None:
        self.emit("note", message=message, level=level)

    def __call__(self, done: int, total: int | None = None, message: str = "", **stats: Any) -> None:
        if "estimate_s" in stats:
            self.emit("estimate", step=done, total=total, message=message, metrics=dict(stats))
            return
        self.emit("progress", step=done, total=total, message=message, metrics=dict(stats))
        now = time.time()
        if now - self._last_log > self.log_every_s or (total is not None and done >= total):
            info = message
            if stats:
                info = (message + "  " if message else "") + "  ".join(format_stat(k, v) for k, v in stats.items())
            self._log.info("%s %s/%s %s", self.title, done, total, info)
            self._last_log = now


def format_stat(key: str, value: Any) -> str:
    """``"psnr 21.46"``: a float with 4 significant digits (a dash when NaN), anything else as is."""
    if isinstance(value, float):
        ok = isinstance(value, numbers.Real) and not math.isnan(value)
        return f"{key} {format(value, '.4g') if ok else '—'}"
    return f"{key} {value}"
