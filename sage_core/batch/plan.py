"""How a local batch shares this machine out: which GPUs, how many subjects at once, how many CPU
threads each (the arithmetic of ``sage batch``'s ``--device``, ``--gpus-per-subject``,
``--cpus-per-subject`` and ``--max-parallel``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from ..errors import ConfigError

DEFAULT_CPUS_PER_SUBJECT = 4
"""CPU threads per subject on a CPU-only machine when neither --cpus-per-subject nor --max-parallel
is given (several subjects with few threads each use the cores better than one with all)."""


def local_gpus(device: str, visible: Sequence[int] | None = None) -> list[int]:
    """GPU indices the local engine shares out for ``--device`` (auto, cpu, cuda, cuda:N).

    visible: the CUDA devices of this machine (None: as torch sees them). ``cpu`` and ``auto``
    without GPUs give none; ``cuda`` gives all, ``cuda:N`` that one. The names are checked as
    :func:`sage_core.workspace.resolve_device` checks them (ConfigError naming the option)."""
    if device == "cpu":
        return []
    if visible is None:
        from .engines import visible_gpus

        visible = visible_gpus()
    if device == "auto":
        return list(visible)
    head, _, idx = device.partition(":")
    if head != "cuda" or (idx and not idx.isdigit()):
        raise ConfigError(f"--device {device}: expected auto, cpu, cuda or cuda:N")
    if not visible:
        raise ConfigError(f"--device {device}: CUDA is not available on this machine (use --device cpu or auto)")
    if not idx:
        return list(visible)
    if int(idx) not in visible:
        raise ConfigError(f"--device {device}: no such CUDA device ({len(visible)} visible)")
    return [int(idx)]


@dataclass(frozen=True)
class LocalPlan:
    """The local engine's sharing: ``max_parallel`` subjects at once, ``cpus_per_subject`` threads
    each, ``gpus`` shared out ``gpus_per_subject`` to a subject (none: CPU only)."""

    max_parallel: int
    cpus_per_subject: int
    gpus: tuple[int, ...] = ()
    gpus_per_subject: int = 1


def plan_local(
    cores: int,
    gpus: Sequence[int] = (),
    *,
    gpus_per_subject: float | None = None,
    cpus_per_subject: int | None = None,
    max_parallel: int | None = None,
) -> LocalPlan:
    """The local sharing of ``cores`` CPU cores and ``gpus`` among the subjects.

    With GPUs: one subject per ``gpus_per_subject`` GPUs (a whole number, default 1), at most
    ``max_parallel``, the cores divided among them. CPU only: ``cpus_per_subject`` threads each
    (default :data:`DEFAULT_CPUS_PER_SUBJECT`, at most the cores) and as many subjects as fit, or
    ``max_parallel`` subjects sharing the cores. A subject never gets more threads than ``cores``.
    ConfigError for counts below 1.
    """
    from ..runtime import threads_per_worker

    if (cpus_per_subject is not None and cpus_per_subject < 1) or (max_parallel is not None and max_parallel < 1):
        raise ConfigError("--max-parallel and --cpus-per-subject must be at least 1")
    if gpus:
        g = int(gpus_per_subject or 1)
        if g < 1 or g != (gpus_per_subject or 1):
            raise ConfigError("--gpus-per-subject must be a whole number of at least 1 for the local engine on GPUs")
        slots = len(gpus) // g
        if slots < 1:
            raise ConfigError(f"--gpus-per-subject {g}: only {len(gpus)} GPU(s) visible")
        n = min(max_parallel or slots, slots)
        return LocalPlan(n, min(cores, cpus_per_subject or threads_per_worker(n, cores)), tuple(gpus), g)
    if cpus_per_subject is None and max_parallel is None:
        c = min(DEFAULT_CPUS_PER_SUBJECT, cores)
        return LocalPlan(max(1, cores // c), c)
    c = min(cores, cpus_per_subject or threads_per_worker(max_parallel or 1, cores))
    return LocalPlan(max_parallel or max(1, cores // c), c)
