"""Running one ``sage`` command in a subprocess: wall time, peak memory, exit code, log.

Peak resident memory is the child's ``VmHWM`` (the kernel's high-water mark of its resident set)
read from ``/proc/<pid>/status`` every ``poll_s`` seconds once the child runs its own program
(:class:`MemorySampler`); the mark only grows, so the last reading misses at most what was allocated
in the last interval, and a child that ends before the first reading has none.
(``ru_maxrss`` from ``wait4`` cannot be used: it starts from the forking parent's resident set.)
On CUDA machines with ``nvidia-smi`` the process's GPU memory is sampled every ``gpu_poll_s``
seconds and the largest sample is kept (a lower bound of the true peak between samples).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

SAGE_MODULE = "sage_cli.app"
"""The CLI module run as ``python -m sage_cli.app`` (the ``sage`` entry point calls its ``main``)."""

_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


@dataclass
class ProcResult:
    """Outcome of one subprocess: exit code, wall time (s), peak RSS (MiB), largest sampled GPU
    memory (MiB, None when not sampled) and the last non-empty lines of its output."""

    rc: int
    wall_s: float
    peak_rss_mib: float | None
    gpu_peak_mib: float | None
    tail: str


def sage_argv(args: list[str]) -> list[str]:
    """The full argument list that runs ``sage ARGS`` with this interpreter."""
    return [sys.executable, "-m", SAGE_MODULE, *args]


def command_line(args: list[str]) -> str:
    """The shell line a user types for ``sage ARGS``."""
    return " ".join(["sage", *(shlex.quote(a) for a in args)])


def log_tail(path: Path, lines: int = 3) -> str:
    """The last non-empty lines of a log file without terminal colour codes and box borders."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ""
    out = []
    for ln in text.splitlines():
        ln = _ANSI.sub("", ln).strip().strip("│╭╮╰╯─ ").strip()
        if ln:
            out.append(ln)
    return " | ".join(out[-lines:])


def _gpu_used_mib(pid: int) -> float | None:
    """GPU memory (MiB) nvidia-smi lists for ``pid`` (None when it lists nothing or fails)."""
    try:
        res = subprocess.run(
            ["nvidia-smi", "--query-compute-apps=pid,used_memory", "--format=csv,noheader,nounits"],
            capture_output=True, text=True, timeout=10, check=False,
        )  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    total = None
    for line in res.stdout.splitlines():
        parts = [p.strip() for p in line.split(",")]
        if len(parts) == 2 and parts[0] == str(pid):
            try:
                total = (total or 0.0) + float(parts[1])
            except ValueError:
                pass
    return total


def _vm_hwm_mib(pid: int, argv0: bytes) -> float | None:
    """VmHWM (MiB) of ``pid`` once it runs ``argv0`` (None before its exec, after its exit, or
    without /proc)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            if f.read().split(b"\0", 1)[0] != argv0:
                return None
        with open(f"/proc/{pid}/status", encoding="utf-8") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        return None
    return None


class MemorySampler:
    """The peak resident memory (``VmHWM``, MiB) of the process ``pid`` once it runs ``argv0``, as
    far as :meth:`sample` saw it (the mark only grows, so the last sample is the peak so far)."""

    def __init__(self, pid: int, argv0: bytes) -> None:
        self.pid = pid
        self.argv0 = argv0
        self.peak: float | None = None

    def sample(self) -> float | None:
        """Read the mark now; returns it (None before the exec, after the exit, or without /proc)."""
        v = _vm_hwm_mib(self.pid, self.argv0)
        if v is not None:
            self.peak = v if self.peak is None else max(self.peak, v)
        return v


def run_process(
    argv: list[str],
    log_path: Path,
    *,
    poll_gpu: bool = False,
    poll_s: float = 0.2,
    gpu_poll_s: float = 0.5,
    env: dict[str, str] | None = None,
) -> ProcResult:
    """Run ``argv`` with stdout and stderr to ``log_path``; sample its peak memory while it runs.

    poll_gpu: also sample the process's GPU memory with nvidia-smi (when available).
    """
    log_path.parent.mkdir(parents=True, exist_ok=True)
    gpu: list[float] = []
    stop = threading.Event()
    use_gpu = poll_gpu and shutil.which("nvidia-smi") is not None
    argv0 = os.fsencode(argv[0])
    with open(log_path, "wb") as log:
        log.write(("$ " + " ".join(shlex.quote(a) for a in argv) + "\n").encode())
        log.flush()
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env)
        memory = MemorySampler(proc.pid, argv0)

        def poll() -> None:
            last_gpu = 0.0
            while not stop.is_set():
                memory.sample()
                now = time.perf_counter()
                if use_gpu and now - last_gpu >= gpu_poll_s:
                    last_gpu = now
                    g = _gpu_used_mib(proc.pid)
                    if g is not None:
                        gpu.append(g)
                stop.wait(poll_s)

        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        try:
            _, status = os.waitpid(proc.pid, 0)
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        finally:
            stop.set()
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        poller.join(timeout=15)
    return ProcResult(proc.returncode, wall, memory.peak, max(gpu) if gpu else None, log_tail(log_path))
