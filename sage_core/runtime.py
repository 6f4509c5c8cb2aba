"""How a stage uses this machine: CPU threads, the surfel rasterizer backend, duration estimates.

* Threads (:func:`apply_threads`): ``--threads N``, else ``$SAGE_THREADS``, else the cores this
  process may run on that other work is not already using (:func:`idle_cores`). On a busy
  machine torch's spinning worker threads compete with the other processes for the same cores:
  measured on 2 cores at a load average of about 8, a tiny phase-1 step took 24 s with 2 threads
  and 2.2 s with 1. ``sage batch`` sets ``$SAGE_THREADS`` to cores ÷ concurrent subjects for its
  workers (:func:`threads_per_worker`) so several processes never multiply threads past the cores.
  torch's intra-op and inter-op pools are sized once, at stage start; the count is recorded in the
  stage manifest (``metrics.threads``).
* Render backend (:func:`resolve_render_backend`): a stage's ``render_backend`` config value
  resolved for its device (``auto`` -> triton on CUDA, the native CPU backend when it builds, else
  torch); an explicit backend that cannot run here is a ConfigError.
* Duration (:class:`StepClock`): the first steps of a training loop are timed (after one warm-up
  step) and the loop's duration on this device is extrapolated from them; nothing extra runs.

torch is imported inside the functions that need it.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from .errors import ConfigError

THREADS_ENV = "SAGE_THREADS"
"""Environment variable holding the default thread count of a sage process."""


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def busy_cores() -> int:
    """Cores other processes keep busy: the larger of the 1-minute load average (rounded down) and
    the runnable processes other than this one right now (``/proc/loadavg``); 0 where the OS does
    not say."""
    try:
        fields = open("/proc/loadavg").read().split()
        load1, running = float(fields[0]), int(fields[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        try:
            load1, running = os.getloadavg()[0], 1
        except (AttributeError, OSError):
            return 0
    return max(int(load1), running - 1, 0)


def idle_cores() -> int:
    """:func:`available_cores` minus :func:`busy_cores`, at least 1."""
    return max(1, available_cores() - busy_cores())


def default_threads() -> int:
    """``$SAGE_THREADS`` when set (a whole number >= 1, else ConfigError), else :func:`idle_cores`."""
    raw = os.environ.get(THREADS_ENV, "").strip()
    if not raw:
        return idle_cores()
    try:
        n = int(raw)
    except ValueError:
        raise ConfigError(f"${THREADS_ENV} = {raw!r} is not a whole number (allowed: >= 1)") from None
    if n < 1:
        raise ConfigError(f"${THREADS_ENV} = {n} is out of range (allowed: >= 1)")
    return n


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    """Threads for each of ``workers`` concurrent processes sharing ``cores`` (default: this
    machine's): ``cores // workers``, at least 1."""
    if workers < 1:
        raise ConfigError(f"concurrent workers = {workers} is out of range (allowed: >= 1)")
    return max(1, (cores if cores is not None else available_cores()) // workers)


def apply_threads(threads: int | None = None) -> int:
    """Size torch's thread pools for this process and return the thread count used.

    threads: ``--threads`` (None: :func:`default_threads`); must be >= 1 (ConfigError). The
    intra-op pool gets ``threads``; the inter-op pool is sized too where torch still allows it
    (only before its first parallel work; later calls keep the pool it has).
    """
    import torch

    n = default_threads() if threads is None else int(threads)
    if n < 1:
        raise ConfigError(f"--threads = {n} is out of range (allowed: >= 1)")
    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(n)
    except RuntimeError:
        pass  # the inter-op pool is fixed once torch has used it; the intra-op count still applies
    return n


def resolve_render_backend(name: str, device: str) -> str:
    """The surfel rasterizer backend a stage with ``render_backend = name`` uses on ``device``:
    "torch", "cpp" or "triton". An explicit backend that cannot run here is a ConfigError naming
    the field and the reason."""
    from .render import BACKENDS, resolve_backend

    if name not in BACKENDS:
        raise ConfigError(f"render_backend = {name!r} is not allowed (allowed: one of {', '.join(BACKENDS)})")
    try:
        return resolve_backend(name, device)
    except ValueError as e:
        raise ConfigError(f"render_backend = {name!r} cannot run on {device}: {e}") from None


@dataclass
class StepClock:
    """Extrapolates a training loop's duration from its first real steps.

    Call :meth:`tick` after every step with the loop's step counter; it returns a
    :class:`Estimate` once (after ``warmup`` steps are skipped and ``steps`` more are timed, or
    earlier when the timed steps already took ``max_wait_s``), else None.

    total: the loop's last step; start: the step the loop (re)started from.
    """

    total: int
    start: int = 0
    warmup: int = 1
    steps: int = 4
    max_wait_s: float = 60.0
    _mark: float | None = None
    _mark_step: int = 0
    _t0: float = 0.0
    _reported: bool = False

    def __post_init__(self) -> None:
        self._t0 = time.perf_counter()

    def tick(self, step: int) -> "Estimate | None":
        if self._reported:
            return None
        now = time.perf_counter()
        done = step - self.start
        if self._mark is None:
            if done >= self.warmup:
                self._mark, self._mark_step = now, step
            return None
        timed = step - self._mark_step
        if timed < 1 or (timed < self.steps and now - self._mark < self.max_wait_s and step < self.total):
            return None
        self._reported = True
        per_step = (now - self._mark) / timed
        remaining = per_step * max(0, self.total - step)
        return Estimate(per_step, remaining, now - self._t0 + remaining, self.total - self.start)


@dataclass(frozen=True)
class Estimate:
    """A training loop's expected duration on this device.

    s_per_step: measured seconds per step; remaining_s: the steps still to run; total_s: the
    whole loop (elapsed + remaining); steps: the steps this run makes.
    """

    s_per_step: float
    remaining_s: float
    total_s: float
    steps: int

    def as_stats(self) -> dict[str, float]:
        """Keyword arguments for a progress callback (``progress(step, total, msg, **stats)``)."""
        return {"estimate_s": self.total_s, "remaining_s": self.remaining_s, "s_per_step": self.s_per_step}


def format_duration(seconds: float) -> str:
    """``42 s``, ``7 min``, ``3 h 20 min``, ``2.5 days``."""
    s = max(0.0, float(seconds))
    if s < 90:
        return f"{s:.0f} s"
    if s < 3600:
        return f"{s / 60:.0f} min"
    if s < 48 * 3600:
        h, m = divmod(round(s / 60), 60)
        return f"{h} h {m} min" if m else f"{h} h"
    return f"{s / 86400:.1f} days"
