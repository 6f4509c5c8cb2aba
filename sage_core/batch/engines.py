"""Where the subjects of a batch run: a local pool of subprocesses, or Ray tasks on a cluster.

Both engines run every :class:`Job` as its own subprocess (``job.argv``) with stdout and stderr
appended to ``job.log_path``. The ``argv`` items ``{python}``, ``{device}`` and ``{cpus}`` are
replaced by the interpreter of the machine that runs the job, the subject's device (``cpu``,
``cuda:i`` locally, ``cuda`` inside a Ray task whose GPUs Ray exposes through
``CUDA_VISIBLE_DEVICES``) and its CPU count (also exported as ``OMP_NUM_THREADS`` /
``MKL_NUM_THREADS`` and as ``SAGE_THREADS``, the thread count every stage of the job applies). Results come back through ``on_result`` as they finish; ``on_poll`` is
called about every ``poll_interval`` seconds while subjects run. A failed job's error is its exit
code (the logs are never parsed); what went wrong is in the subject's status file.

Ray is imported only inside :func:`run_ray`.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from ..errors import ConfigError
from ..runtime import THREADS_ENV

ResultFn = Callable[["JobResult"], None]
PollFn = Callable[[], None]


@dataclass
class Job:
    """One subject's command: ``argv`` items may be the placeholders ``{python}``, ``{device}``, ``{cpus}``."""

    id: str
    ws: Path
    argv: list[str]
    log_path: Path
    env: dict[str, str] = field(default_factory=dict)


@dataclass
class JobResult:
    """How a job's process ended: exit code (None if it never ran), wall time, device, error line."""

    id: str
    returncode: int | None
    wall_time_s: float
    device: str
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.returncode == 0


class _Processes:
    """The live child processes of a local batch, so an interrupt can stop them."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._procs: set[subprocess.Popen] = set()
        self.stopping = False

    def add(self, p: subprocess.Popen) -> None:
        with self._lock:
            self._procs.add(p)

    def discard(self, p: subprocess.Popen) -> None:
        with self._lock:
            self._procs.discard(p)

    def stop(self, grace_s: float = 20.0) -> None:
        """SIGINT every child (stages checkpoint and exit), then kill what is left after ``grace_s``."""
        self.stopping = True
        with self._lock:
            procs = list(self._procs)
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.time() + grace_s
        for p in procs:
            try:
                p.wait(timeout=max(0.0, deadline - time.time()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def run_job(job: Job, device: str, cpus: int, procs: _Processes | None = None) -> JobResult:
    """Run one job's subprocess to completion (in the calling thread / Ray worker)."""
    subst = {"{device}": device, "{cpus}": str(cpus), "{python}": sys.executable}
    argv = [subst.get(a, a) for a in job.argv]
    env = {**os.environ, **job.env, "OMP_NUM_THREADS": str(cpus), "MKL_NUM_THREADS": str(cpus), THREADS_ENV: str(cpus), "COLUMNS": "160"}
    env.setdefault("PYTHONUNBUFFERED", "1")
    job.log_path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with open(job.log_path, "ab") as log:
        log.write(f"# sage batch: {job.id} on {device} with {cpus} CPU(s)\n# {' '.join(argv)}\n".encode())
        log.flush()
        if procs is not None and procs.stopping:
            return JobResult(job.id, None, 0.0, device, "not started: the batch was interrupted")
        p = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        if procs is not None:
            procs.add(p)
        try:
            rc = p.wait()
        finally:
            if procs is not None:
                procs.discard(p)
    wall = time.time() - t0
    err = None if rc == 0 else f"exit code {rc}"
    return JobResult(job.id, rc, wall, device, err)


def visible_gpus() -> list[int]:
    """Indices of the CUDA devices torch sees here (empty without CUDA)."""
    import torch

    return list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []


def run_local(
    jobs: Sequence[Job],
    *,
    max_parallel: int,
    cpus_per_subject: int,
    gpus: Sequence[int] = (),
    gpus_per_subject: int = 1,
    on_result: ResultFn | None = None,
    on_poll: PollFn | None = None,
    poll_interval: float = 0.5,
) -> list[JobResult]:
    """Run jobs in a pool of at most ``max_parallel`` subprocesses on this machine.

    gpus: CUDA device indices to share out, ``gpus_per_subject`` to a subject (it runs on the
    first, ``cuda:i``); empty -> every subject runs on ``cpu``. With GPUs, at most
    ``len(gpus) // gpus_per_subject`` subjects run at once. A KeyboardInterrupt stops the children
    (SIGINT, then kill) and is re-raised.
    """
    if max_parallel < 1 or cpus_per_subject < 1:
        raise ConfigError("--max-parallel and --cpus-per-subject must be at least 1")
    slots: queue.Queue[str] = queue.Queue()
    if gpus:
        if gpus_per_subject < 1:
            raise ConfigError("--gpus-per-subject must be at least 1 when running on GPUs")
        n_slots = len(gpus) // gpus_per_subject
        if n_slots < 1:
            raise ConfigError(f"--gpus-per-subject {gpus_per_subject}: only {len(gpus)} GPU(s) visible")
        for i in range(n_slots):
            slots.put(f"cuda:{gpus[i * gpus_per_subject]}")
        max_parallel = min(max_parallel, n_slots)
    else:
        for _ in range(max_parallel):
            slots.put("cpu")
    procs = _Processes()

    def work(job: Job) -> JobResult:
        device = slots.get()
        try:
            return run_job(job, device, cpus_per_subject, procs)
        finally:
            slots.put(device)

    results: list[JobResult] = []
    pool = cf.ThreadPoolExecutor(max_workers=max_parallel, thread_name_prefix="sage-batch")
    try:
        futures = {pool.submit(work, j): j for j in jobs}
        pending = set(futures)
        while pending:
            done, pending = cf.wait(pending, timeout=poll_interval, return_when=cf.FIRST_COMPLETED)
            for f in done:
                res = f.result()
                results.append(res)
                if on_result is not None:
                    on_result(res)
            if on_poll is not None:
                on_poll()
    except BaseException:
        procs.stopping = True
        for f in futures:
            f.cancel()
        procs.stop()
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
    return results


def _ray_task(job: Job, cpus: int, gpus: float) -> JobResult:
    """Body of a Ray task: Ray has set CUDA_VISIBLE_DEVICES to the task's GPUs."""
    return run_job(job, "cuda" if gpus > 0 else "cpu", max(1, int(cpus)))


def run_ray(
    jobs: Sequence[Job],
    *,
    address: str | None = None,
    cpus_per_subject: int = 1,
    gpus_per_subject: float = 0,
    max_parallel: int | None = None,
    max_retries: int = 2,
    init_kwargs: dict[str, Any] | None = None,
    on_result: ResultFn | None = None,
    on_poll: PollFn | None = None,
    poll_interval: float = 0.5,
) -> list[JobResult]:
    """Run one Ray task per job with ``cpus_per_subject`` CPUs and ``gpus_per_subject`` GPUs.

    Joins the cluster at ``address`` (``ray.init(address=...)``), or starts a local one when
    ``address`` is None (``init_kwargs`` such as ``num_cpus`` go to ``ray.init``); an already
    initialized Ray is reused. A task whose worker dies is retried up to ``max_retries`` times;
    results are gathered as they finish; at most ``max_parallel`` tasks are in flight (None: as
    many as the cluster schedules). Paths in the jobs must be valid on every node (shared file
    system) and every node needs the same sage installation.
    """
    try:
        import ray
    except ImportError:
        raise ConfigError("the ray engine needs Ray: pip install 'ray>=2.9' (from a checkout: pip install -e '.[batch]')") from None
    if cpus_per_subject < 1 or gpus_per_subject < 0 or (max_parallel is not None and max_parallel < 1):
        raise ConfigError("--cpus-per-subject and --max-parallel must be at least 1, --gpus-per-subject at least 0")
    started = False
    if not ray.is_initialized():
        kw = {"log_to_driver": False, "include_dashboard": False, **(init_kwargs or {})}
        if address:
            kw.pop("num_cpus", None)
            kw.pop("num_gpus", None)
        ray.init(address=address, **kw)
        started = True
    remote = ray.remote(_ray_task).options(
        num_cpus=cpus_per_subject, num_gpus=gpus_per_subject, max_retries=max_retries, retry_exceptions=False
    )
    waiting = list(jobs)
    inflight: dict[Any, Job] = {}
    results: list[JobResult] = []
    try:
        while waiting or inflight:
            while waiting and (max_parallel is None or len(inflight) < max_parallel):
                job = waiting.pop(0)
                inflight[remote.remote(job, cpus_per_subject, gpus_per_subject)] = job
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=poll_interval)
            for ref in ready:
                job = inflight.pop(ref)
                try:
                    res = ray.get(ref)
                except Exception as e:  # noqa: BLE001 - a lost worker after its retries, or a task error
                    msg = str(e).strip().splitlines()
                    res = JobResult(job.id, None, 0.0, "ray", f"ray: {type(e).__name__}: {msg[0] if msg else ''}")
                results.append(res)
                if on_result is not None:
                    on_result(res)
            if on_poll is not None:
                on_poll()
    except BaseException:
        for ref in inflight:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001 - best effort while stopping
                pass
        raise
    finally:
        if started:
            ray.shutdown()
    return results
