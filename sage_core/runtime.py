"""How a stage uses this machine: CPU threads, the surfel rasterizer backend, duration estimates.

* Threads (:func:`apply_thread_choice`): ``--threads N``, else ``$SAGE_THREADS``, else the cores this
  process may run on that other work is not using right now (:func:`measure_busy_cores`: the busy
  share of each core over a fifth of a second, from ``/proc/stat``, not the load average, which
  lags a minute behind); a count above the cores is capped with a warning. On a busy machine
  torch's spinning worker threads compete with the other processes for the same cores: measured on
  2 cores at a load average of about 8, a tiny phase-1 step took 24 s with 2 threads and 2.2 s
  with 1. ``sage batch`` sets ``$SAGE_THREADS`` to cores ÷ concurrent subjects for its
  workers (:func:`threads_per_worker`) so several processes never multiply threads past the cores.
  torch's intra-op and inter-op pools are sized once, at stage start; the count is recorded in the
  stage manifest (``metrics.threads``).
* Render backend (:func:`resolve_render_backend`): a stage's ``render_backend`` config value
  resolved for its device (``auto`` -> triton on CUDA, the native CPU backend when it builds, else
  torch); an explicit backend that cannot run here is a ConfigError.
* Duration (:class:`StepClock`): the first steps of a training loop are timed (after one warm-up
  step) and the loop's duration on this device is extrapolated from them, then re-estimated from
  the last minute's steps every half minute (the rate follows the machine's load); each estimate
  names the steps it rests on. Nothing extra runs.

torch is imported inside the functions that need it.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any

from .errors import ConfigError

THREADS_ENV = "SAGE_THREADS"
"""Environment variable holding the default thread count of a sage process."""


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


CPU_SAMPLE_S = 0.2
"""Seconds over which :func:`measure_busy_cores` watches the cores."""

CPU_SAMPLE_REUSE_S = 5.0
"""A measurement this recent is reused (the stages of one chain start within seconds of each other)."""

_JIFFY_FIELDS = 8
"""/proc/stat per-CPU fields that make up its time: user nice system idle iowait irq softirq steal
(guest time is already inside user and nice)."""


def _cpu_times(cores: set[int]) -> tuple[float, float] | None:
    """(busy, total) clock ticks since boot, summed over the CPUs ``cores`` (``/proc/stat``); None
    where the file is missing or unreadable."""
    try:
        with open("/proc/stat") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    busy = total = 0.0
    seen = 0
    for line in lines:
        head, _, rest = line.partition(" ")
        if not head.startswith("cpu") or head == "cpu" or not head[3:].isdigit() or int(head[3:]) not in cores:
            continue
        try:
            ticks = [float(x) for x in rest.split()[:_JIFFY_FIELDS]]
        except ValueError:
            return None
        t = sum(ticks)
        idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0.0)
        busy += t - idle
        total += t
        seen += 1
    return (busy, total) if seen else None


def _own_cpu_s() -> float:
    t = os.times()
    return t.user + t.system


@dataclass(frozen=True)
class CpuSample:
    """What :func:`measure_busy_cores` saw: ``busy`` cores' worth of CPU time used by other processes
    (a float: 1.5 is one core fully and another half busy) out of ``cores``, over ``window_s``
    seconds, ending at ``at`` (``time.monotonic``)."""

    busy: float
    cores: int
    window_s: float
    at: float


_LAST_SAMPLE: list[CpuSample] = []


def measure_busy_cores(window_s: float = CPU_SAMPLE_S) -> CpuSample | None:
    """How busy the cores this process may run on are right now: the CPU time they spend on anything
    but idling over ``window_s`` seconds (``/proc/stat``), minus this process's own, in cores. A
    sample newer than :data:`CPU_SAMPLE_REUSE_S` is reused. None where ``/proc/stat`` is unavailable.

    Unlike the load average, this follows the machine as it is now: right after a heavy command the
    1-minute load average still says a core is busy for about a minute."""
    now = time.monotonic()
    if _LAST_SAMPLE and now - _LAST_SAMPLE[-1].at < CPU_SAMPLE_REUSE_S:
        return _LAST_SAMPLE[-1]
    try:
        cores = set(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = set(range(os.cpu_count() or 1))
    a, own_a, t_a = _cpu_times(cores), _own_cpu_s(), time.monotonic()
    if a is None:
        return None
    time.sleep(window_s)
    b, own_b, t_b = _cpu_times(cores), _own_cpu_s(), time.monotonic()
    if b is None or b[1] <= a[1]:
        return None
    share = (b[0] - a[0]) / (b[1] - a[1])  # busy share of the cores' time over the window
    own = (own_b - own_a) / max(t_b - t_a, 1e-6)  # cores' worth this process used meanwhile
    sample = CpuSample(max(0.0, share * len(cores) - own), len(cores), t_b - t_a, t_b)
    _LAST_SAMPLE[:] = [sample]
    return sample


def busy_cores() -> int:
    """Cores other processes keep busy right now (:func:`measure_busy_cores`, rounded to the nearest
    whole core); where ``/proc/stat`` is unavailable, the 1-minute load average rounded down."""
    sample = measure_busy_cores()
    if sample is not None:
        return int(sample.busy + 0.5)
    try:
        return max(0, int(os.getloadavg()[0]))
    except (AttributeError, OSError):
        return 0


def idle_cores() -> int:
    """:func:`available_cores` minus :func:`busy_cores`, at least 1."""
    return max(1, available_cores() - busy_cores())


@dataclass(frozen=True)
class ThreadChoice:
    """How many CPU threads a process uses and why.

    threads: the count; source: ``--threads``, ``$SAGE_THREADS`` or ``idle cores``; cores: the cores
    this process may run on; busy: cores' worth of CPU other processes used when the choice was made
    (None: not measured); capped_from: a requested count above ``cores`` that was lowered to it.
    """

    threads: int
    source: str
    cores: int
    busy: float | None = None
    capped_from: int | None = None

    def describe(self) -> str:
        """``2 threads (2 of 2 cores idle)``, ``1 thread (--threads)``."""
        n = f"{self.threads} thread{'s' if self.threads != 1 else ''}"
        if self.source == "idle cores":
            idle = max(0, self.cores - int((self.busy or 0.0) + 0.5))
            return f"{n} ({idle} of {self.cores} cores idle)"
        return f"{n} ({self.source})"

    def warning(self) -> str | None:
        """The warning of a capped request, else None."""
        if self.capped_from is None:
            return None
        return (f"{self.source} {self.capped_from} is more than the {self.cores} cores this process may run on: using {self.threads} "
                f"(more threads than cores only wait for each other)")


def choose_threads(threads: int | None = None) -> ThreadChoice:
    """The thread count of a process: ``threads`` (``--threads``), else ``$SAGE_THREADS`` (a whole
    number >= 1, else ConfigError), else the cores that are idle now (:func:`measure_busy_cores`).
    A count above the cores this process may run on is capped to them (:meth:`ThreadChoice.warning`
    says so): 999 threads on 2 cores made a training step 100 times slower."""
    cores = available_cores()
    if threads is not None:
        n, source = int(threads), "--threads"
        if n < 1:
            raise ConfigError(f"--threads = {n} is out of range (allowed: >= 1)")
    else:
        raw = os.environ.get(THREADS_ENV, "").strip()
        if not raw:
            sample = measure_busy_cores()
            busy = sample.busy if sample is not None else float(busy_cores())
            return ThreadChoice(max(1, cores - int(busy + 0.5)), "idle cores", cores, busy)
        try:
            n = int(raw)
        except ValueError:
            raise ConfigError(f"${THREADS_ENV} = {raw!r} is not a whole number (allowed: >= 1)") from None
        if n < 1:
            raise ConfigError(f"${THREADS_ENV} = {n} is out of range (allowed: >= 1)")
        source = f"${THREADS_ENV}"
    if n > cores:
        return ThreadChoice(cores, source, cores, capped_from=n)
    return ThreadChoice(n, source, cores)


def default_threads() -> int:
    """The thread count without ``--threads``: ``$SAGE_THREADS`` when set, else the idle cores
    (:func:`choose_threads`)."""
    return choose_threads(None).threads


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    """Threads for each of ``workers`` concurrent processes sharing ``cores`` (default: this
    machine's): ``cores // workers``, at least 1."""
    if workers < 1:
        raise ConfigError(f"concurrent workers = {workers} is out of range (allowed: >= 1)")
    return max(1, (cores if cores is not None else available_cores()) // workers)


def apply_thread_choice(threads: int | None = None) -> ThreadChoice:
    """Size torch's thread pools for this process (:func:`choose_threads`) and return the choice.

    The intra-op pool gets the count; the inter-op pool is sized too where torch still allows it
    (only before its first parallel work; later calls keep the pool it has).
    """
    import torch

    choice = choose_threads(threads)
    torch.set_num_threads(choice.threads)
    try:
        torch.set_num_interop_threads(choice.threads)
    except RuntimeError:
        pass  # the inter-op pool is fixed once torch has used it; the intra-op count still applies
    return choice


def apply_threads(threads: int | None = None) -> int:
    """:func:`apply_thread_choice`, returning the thread count."""
    return apply_thread_choice(threads).threads


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
    """Extrapolates a training loop's duration from its steps, first from its first real steps, then
    again as it runs.

    Call :meth:`tick` after every step with the loop's step counter. It returns an :class:`Estimate`
    once ``warmup`` steps are skipped and ``steps`` more are timed (or earlier when the timed steps
    already took ``max_wait_s``): the mean of those steps. After that, every ``update_s`` seconds it
    returns a new estimate from the steps of the last ``window_s`` seconds, so that a machine whose
    load changes (other processes starting or ending) gets a remaining time that follows it; else
    None. Each estimate names its basis.

    total: the loop's last step; start: the step the loop (re)started from.
    """

    total: int
    start: int = 0
    warmup: int = 1
    steps: int = 4
    max_wait_s: float = 60.0
    update_s: float = 30.0
    window_s: float = 60.0
    _mark: float | None = None
    _mark_step: int = 0
    _t0: float = 0.0
    _reported_at: float | None = None
    _marks: list[tuple[int, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._t0 = time.perf_counter()

    def tick(self, step: int) -> "Estimate | None":
        now = time.perf_counter()
        if self._mark is None:
            if step - self.start >= self.warmup:
                self._mark, self._mark_step = now, step
                self._marks = [(step, now)]
            return None
        self._marks.append((step, now))
        while len(self._marks) > 2 and now - self._marks[1][1] >= self.window_s:
            self._marks.pop(0)  # keep the marks of the last window_s seconds (and the one before them)
        if self._reported_at is None:
            timed = step - self._mark_step
            if timed < 1 or (timed < self.steps and now - self._mark < self.max_wait_s and step < self.total):
                return None
            self._reported_at = now
            first, last = self._mark_step + 1, step
            basis = f"step {first}" if first == last else f"steps {first}-{last}"
            return self._estimate(now, step, (now - self._mark) / timed, basis, first=True)
        if now - self._reported_at < self.update_s or step >= self.total:
            return None
        s0, t0 = self._marks[0]
        if step <= s0:
            return None
        self._reported_at = now
        return self._estimate(now, step, (now - t0) / (step - s0), f"the last {step - s0} steps ({now - t0:.0f} s)", first=False)

    def _estimate(self, now: float, step: int, per_step: float, basis: str, first: bool) -> "Estimate":
        remaining = per_step * max(0, self.total - step)
        return Estimate(per_step, remaining, now - self._t0 + remaining, self.total - self.start, basis, first)


@dataclass(frozen=True)
class Estimate:
    """A training loop's expected duration on this device.

    s_per_step: measured seconds per step; remaining_s: the steps still to run; total_s: the
    whole loop (elapsed + remaining); steps: the steps this run makes; basis: which steps the rate
    was measured on (``steps 2-5``, ``the last 120 steps (60 s)``); first: the loop's first estimate
    (later ones update it).
    """

    s_per_step: float
    remaining_s: float
    total_s: float
    steps: int
    basis: str = "its first steps"
    first: bool = True

    def as_stats(self) -> dict[str, Any]:
        """Keyword arguments for a progress callback (``progress(step, total, msg, **stats)``)."""
        return {"estimate_s": self.total_s, "remaining_s": self.remaining_s, "s_per_step": self.s_per_step,
                "estimate_basis": self.basis, "estimate_first": self.first}  # fmt: skip


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
