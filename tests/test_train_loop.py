"""The shared training step loop (sage_core.train.loop.run_steps) with a tiny deterministic trainer:
resume from the newest checkpoint, checkpoint cadence, progress reports, interruption and resume."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

import sage_core.workspace as workspace
from sage_core.errors import StageError
from sage_core.train.loop import LoopResult, run_steps


class Interrupted(RuntimeError):
    """Raised by the fake trainer to stand for a crash at a given step."""


class NoisyTrainer:
    """A random walk w <- 0.9 w + noise, the noise drawn from its own generator: each step's output
    depends on every earlier draw, so only an exact resume repeats an uninterrupted run."""

    def __init__(self, seed: int = 0, fail_at: int | None = None) -> None:
        self.generator = torch.Generator().manual_seed(seed)
        self.w = torch.zeros(3)
        self.step_count = 0
        self.fail_at = fail_at
        self.outputs: list[dict[str, float]] = []

    def step(self) -> dict[str, float]:
        if self.fail_at is not None and self.step_count + 1 == self.fail_at:
            raise Interrupted(f"killed at step {self.fail_at}")
        noise = torch.randn(3, generator=self.generator)
        self.w = 0.9 * self.w + noise
        self.step_count += 1
        out = {"loss": float(self.w.square().sum()), "noise": float(noise[0]), "step": float(self.step_count)}
        self.outputs.append(out)
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"w": self.w.clone(), "generator": self.generator.get_state(), "step": self.step_count}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.w = state["w"].clone()
        self.generator.set_state(state["generator"])
        self.step_count = int(state["step"])


class Recorder:
    """A progress callback that keeps every call."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, int, str, dict[str, Any]]] = []

    def __call__(self, step: int, total: int, message: str = "", **stats: Any) -> None:
        self.calls.append((step, total, message, stats))

    def estimates(self) -> list[tuple[int, int, str, dict[str, Any]]]:
        return [c for c in self.calls if "estimate_s" in c[3]]

    def steps(self) -> list[tuple[int, int, str, dict[str, Any]]]:
        return [c for c in self.calls if "estimate_s" not in c[3]]


@pytest.fixture()
def saves(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Steps at which the loop saved a checkpoint (the real save still runs)."""
    seen: list[int] = []
    real = workspace.save_checkpoint

    def spy(directory: str | Path, step: int, state: dict[str, Any], keep: int = 2) -> Path:
        seen.append(int(step))
        return real(directory, step, state, keep)

    monkeypatch.setattr(workspace, "save_checkpoint", spy)
    return seen


def test_checkpoints_every_n_steps_but_not_at_the_last(tmp_path: Path, saves: list[int]) -> None:
    res = run_steps(NoisyTrainer(), 9, label="t", checkpoint_dir=tmp_path, checkpoint_every=3)
    assert saves == [3, 6]  # step 9 is the last: the stage writes its outputs then
    res = run_steps(NoisyTrainer(), 10, label="t", checkpoint_dir=tmp_path / "b", checkpoint_every=3)
    assert saves == [3, 6, 3, 6, 9]
    assert res.steps_run == 10 and res.start_step == 0 and not res.resumed
    assert sorted(p.name for p in (tmp_path / "b").glob("ckpt_*.pt")) == ["ckpt_00000006.pt", "ckpt_00000009.pt"]


def test_no_checkpoints_without_a_folder_or_an_interval(tmp_path: Path, saves: list[int]) -> None:
    run_steps(NoisyTrainer(), 6, label="t", checkpoint_dir=None, checkpoint_every=2)
    run_steps(NoisyTrainer(), 6, label="t", checkpoint_dir=tmp_path, checkpoint_every=0)
    assert saves == [] and not list(tmp_path.glob("ckpt_*"))


def test_resumes_from_the_newest_checkpoint_under_its_key(tmp_path: Path) -> None:
    first = NoisyTrainer()
    run_steps(first, 8, label="t", checkpoint_dir=tmp_path, checkpoint_every=2, state_key="pretrainer")
    ck = workspace.load_checkpoint(workspace.latest_checkpoint(tmp_path))
    assert ck["step"] == 6 and set(ck["state"]) == {"pretrainer"}

    again = NoisyTrainer()
    res = run_steps(again, 8, label="t", checkpoint_dir=tmp_path, checkpoint_every=2, state_key="pretrainer")
    assert res.resumed and res.resumed_from is not None and res.resumed_from.name == "ckpt_00000006.pt"
    assert res.start_step == 6 and res.steps_run == 2 and again.step_count == 8
    assert again.outputs == first.outputs[6:]
    assert torch.equal(again.w, first.w)
    assert res.last == first.outputs[-1]


def test_resume_from_none_or_a_given_file(tmp_path: Path) -> None:
    run_steps(NoisyTrainer(), 8, label="t", checkpoint_dir=tmp_path, checkpoint_every=2)
    fresh = run_steps(NoisyTrainer(), 8, label="t", checkpoint_dir=tmp_path, checkpoint_every=2, resume_from=None)
    assert not fresh.resumed and fresh.start_step == 0 and fresh.steps_run == 8
    older = tmp_path / "ckpt_00000004.pt"
    assert older.is_file()
    res = run_steps(NoisyTrainer(), 8, label="t", checkpoint_dir=tmp_path, checkpoint_every=2, resume_from=older)
    assert res.resumed_from == older and res.start_step == 4 and res.steps_run == 4


def test_a_checkpoint_without_the_trainer_key_is_a_stage_error(tmp_path: Path) -> None:
    workspace.save_checkpoint(tmp_path, 3, {"trainer": NoisyTrainer().state_dict()})
    with pytest.raises(StageError, match=r"ckpt_00000003\.pt.*'pretrainer'.*trainer"):
        run_steps(NoisyTrainer(), 5, label="t", checkpoint_dir=tmp_path, checkpoint_every=2, state_key="pretrainer")


def test_progress_reports_each_step_and_one_estimate() -> None:
    rec = Recorder()
    order: list[tuple[str, int]] = []

    def on_step(step: int, out: Any) -> None:
        assert out["step"] == step
        order.append(("on_step", step))

    def stats(out: Any) -> dict[str, float]:
        order.append(("stats", int(out["step"])))
        return {"loss": out["loss"]}

    trainer = NoisyTrainer()
    res = run_steps(trainer, 12, label="phase x", stats_label="fitting", progress=rec, stats=stats, on_step=on_step)
    steps = rec.steps()
    assert [c[0] for c in steps] == list(range(1, 13))
    assert all(c[1] == 12 and c[2] == "fitting" for c in steps)
    assert [c[3] for c in steps] == [{"loss": o["loss"]} for o in trainer.outputs]
    assert order == [(k, s) for s in range(1, 13) for k in ("on_step", "stats")]
    est = rec.estimates()
    assert len(est) == 1
    step, total, message, values = est[0]
    assert message == "phase x" and total == 12 and 1 < step <= 12
    assert set(values) == {"estimate_s", "remaining_s", "s_per_step", "estimate_basis", "estimate_first"}
    assert values["estimate_first"] is True and values["estimate_basis"].startswith("step")
    assert values["remaining_s"] >= 0 and values["s_per_step"] >= 0
    # the estimate comes before that step's own progress report
    i = rec.calls.index(est[0])
    assert rec.calls[i + 1][0] == step and "estimate_s" not in rec.calls[i + 1][3]
    assert isinstance(res, LoopResult) and res.steps_run == 12


def test_progress_without_stats_uses_the_label() -> None:
    rec = Recorder()
    run_steps(NoisyTrainer(), 3, label="only", progress=rec)
    assert [(c[0], c[2], c[3]) for c in rec.steps()] == [(1, "only", {}), (2, "only", {}), (3, "only", {})]


def test_interrupted_then_resumed_repeats_the_uninterrupted_run(tmp_path: Path) -> None:
    total, every = 11, 3
    whole = NoisyTrainer(seed=5)
    rec_whole = Recorder()
    run_steps(whole, total, label="t", progress=rec_whole, checkpoint_dir=tmp_path / "whole", checkpoint_every=every,
              stats=lambda o: {"loss": o["loss"]})  # fmt: skip

    ck = tmp_path / "broken"
    crashed = NoisyTrainer(seed=5, fail_at=8)
    with pytest.raises(Interrupted):
        run_steps(crashed, total, label="t", checkpoint_dir=ck, checkpoint_every=every)
    assert crashed.step_count == 7
    assert workspace.load_checkpoint(workspace.latest_checkpoint(ck))["step"] == 6

    # a fresh process: a new trainer from the same seed, whose generator has not been advanced
    resumed = NoisyTrainer(seed=5)
    rec = Recorder()
    res = run_steps(resumed, total, label="t", progress=rec, checkpoint_dir=ck, checkpoint_every=every,
                    stats=lambda o: {"loss": o["loss"]})  # fmt: skip
    assert res.start_step == 6 and res.steps_run == 5
    assert crashed.outputs + resumed.outputs[1:] == whole.outputs  # step 7 was run twice, identically
    assert resumed.outputs == whole.outputs[6:]
    assert torch.equal(resumed.w, whole.w)
    assert [c for c in rec.steps()] == [c for c in rec_whole.steps() if c[0] > 6]
    # the resumed run checkpoints on the same cadence: 9 (not 11, the last)
    assert workspace.load_checkpoint(workspace.latest_checkpoint(ck))["step"] == 9


def test_a_finished_trainer_runs_no_step(tmp_path: Path) -> None:
    t = NoisyTrainer()
    run_steps(t, 4, label="t")
    rec = Recorder()
    res = run_steps(t, 4, label="t", progress=rec, checkpoint_dir=tmp_path, checkpoint_every=1)
    assert res.steps_run == 0 and res.last == {} and rec.calls == [] and not list(tmp_path.glob("ckpt_*"))
    assert res.steps_per_s != res.steps_per_s  # NaN
