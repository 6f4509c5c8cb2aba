"""The training step loop every stage shares: resume, step, report progress, checkpoint.

:func:`run_steps` drives any trainer that has a step counter, a ``step()`` and a state dict
(:class:`SteppingTrainer`: the phase-1 and phase-2 trainers, the SDF pretrainer of init-mesh) up
to ``total`` steps:

1. resume: the trainer's state is loaded from the newest usable checkpoint in ``checkpoint_dir``
   (``load_checkpoint(ck)["state"][state_key]``), or from a given checkpoint file;
2. each step: ``out = trainer.step()``; the duration estimate (:class:`sage_core.runtime.StepClock`)
   goes to ``progress(step, total, label, **estimate)`` once it is known; ``on_step(step, out)``
   (a stage's periodic evaluation) runs; ``progress(step, total, stats_label, **stats(out))``;
3. every ``checkpoint_every`` steps, except at the last step (the stage writes its outputs then),
   ``save_checkpoint(checkpoint_dir, step, {state_key: trainer.state_dict()})``.

All randomness lives in the trainer (its generator and the global RNG states it saves in its
state dict), so a run interrupted after a checkpoint and resumed repeats the uninterrupted run
step for step. The checkpoint helpers are looked up in :mod:`sage_core.workspace` when the loop
runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Protocol

from ..runtime import StepClock

Progress = Callable[..., None]
"""``progress(step, total, message, **stats)``: the engine's progress callback."""


class SteppingTrainer(Protocol):
    """What :func:`run_steps` needs of a trainer."""

    step_count: int
    """Steps made so far (restored by :meth:`load_state_dict`)."""

    def step(self) -> Mapping[str, Any]:
        """Make one optimisation step, advance ``step_count``; returns that step's losses."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly (parameters, optimiser, generator, RNG states)."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        ...


@dataclass(frozen=True)
class LoopResult:
    """What a :func:`run_steps` call did.

    resumed_from: the checkpoint the trainer was restored from (None: a fresh start);
    start_step: the trainer's step count when the loop began; steps_run: the steps this call made;
    train_time_s: wall time of those steps; last: the last step's output (empty when no step ran).
    """

    resumed_from: Path | None
    start_step: int
    steps_run: int
    train_time_s: float
    last: Mapping[str, Any] = field(default_factory=dict)

    @property
    def resumed(self) -> bool:
        """Whether the trainer continued from a checkpoint."""
        return self.resumed_from is not None

    @property
    def steps_per_s(self) -> float:
        """Steps per second of this call (NaN when none ran or no time passed)."""
        return self.steps_run / self.train_time_s if self.train_time_s > 0 and self.steps_run > 0 else float("nan")


def resume(trainer: SteppingTrainer, checkpoint: str | Path | None, state_key: str, *, map_location: Any = "cpu") -> Path | None:
    """Load ``trainer`` from ``checkpoint``'s ``state[state_key]``; returns the file (None: nothing loaded).

    A checkpoint without that key is a StageError naming the file and the keys it has.
    """
    from ..errors import StageError
    from ..workspace import load_checkpoint

    if checkpoint is None:
        return None
    path = Path(checkpoint)
    state = load_checkpoint(path, map_location=map_location)["state"]
    if state_key not in state:
        raise StageError(f"{path}: checkpoint holds no {state_key!r} state (it has: {', '.join(sorted(state)) or 'nothing'})")
    trainer.load_state_dict(state[state_key])
    return path


def run_steps(
    trainer: SteppingTrainer,
    total: int,
    *,
    label: str,
    progress: Progress | None = None,
    checkpoint_dir: str | Path | None = None,
    checkpoint_every: int = 0,
    state_key: str = "trainer",
    resume_from: str | Path | None | Literal["latest"] = "latest",
    map_location: Any = "cpu",
    stats: Callable[[Mapping[str, Any]], Mapping[str, Any]] | None = None,
    stats_label: str | None = None,
    on_step: Callable[[int, Mapping[str, Any]], None] | None = None,
) -> LoopResult:
    """Step ``trainer`` until its step count reaches ``total``, resuming and checkpointing on the way.

    label: progress message of the duration estimate (and of the per-step progress unless
    ``stats_label`` is given). checkpoint_dir: where checkpoints are read and written (None: no
    checkpoints); checkpoint_every: interval in steps (<= 0: none written); state_key: the
    trainer's entry in the checkpoint state. resume_from: ``"latest"`` (the newest usable
    checkpoint in ``checkpoint_dir``), a checkpoint file, or None (start from the trainer as it is).
    stats: the per-step progress values from a step's output (default: none). on_step: called
    after each step, before its progress report (periodic evaluation).
    """
    from ..workspace import latest_checkpoint, save_checkpoint

    if resume_from == "latest":
        resume_from = latest_checkpoint(checkpoint_dir) if checkpoint_dir is not None else None
    resumed_from = resume(trainer, resume_from, state_key, map_location=map_location)
    start = trainer.step_count
    t0 = time.perf_counter()
    last: Mapping[str, Any] = {}
    clock = StepClock(total, start)
    while trainer.step_count < total:
        last = trainer.step()
        step = trainer.step_count
        estimate = clock.tick(step)
        if estimate is not None and progress is not None:
            progress(step, total, label, **estimate.as_stats())
        if on_step is not None:
            on_step(step, last)
        if progress is not None:
            progress(step, total, stats_label or label, **(stats(last) if stats is not None else {}))
        if checkpoint_dir is not None and checkpoint_every > 0 and step % checkpoint_every == 0 and step < total:
            save_checkpoint(checkpoint_dir, step, {state_key: trainer.state_dict()})
    return LoopResult(resumed_from, start, trainer.step_count - start, time.perf_counter() - t0, last)
