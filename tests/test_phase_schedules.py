"""The learning rate, ε and β follow the transitions within each phase: in a fresh run, in the
second phase of a run, and in a run interrupted and resumed mid-phase.

A recorder wraps ``DoubleDQN.train`` and notes, at every training call, the model's transition
count, the learning rate the optimizer used and the one logged, ε and the buffer's β. The
expected values are hand-written from the config below (eq. 4.1: linear, then constant).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from harness.config.loading import load_config
from harness.results.rundir import RunDir
from harness.sb3.dqn import DoubleDQN
from harness.sb3.schedules import linear
from harness.training.train import TrainingInterrupted, train

SMOKE = Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml"
PHASE1, PHASE2 = 800, 600
# 2 copies x 2 agents = 4 slots; phase 1 ends at exactly 800 transitions.
OVERRIDES = [
    f"phases.initial.timesteps={PHASE1}",
    f"phases.optimizing.timesteps={PHASE2}",
    "phases.initial.exploration.steps=600",
    "phases.initial.beta.steps=800",
    "phases.optimizing.learning_rate=[1.0e-4, 1.0e-5]",
    "phases.optimizing.exploration.start=0.2",
    "phases.optimizing.exploration.end=0.0",
    "phases.optimizing.exploration.steps=300",
    "phases.optimizing.beta.start=0.5",
    "phases.optimizing.beta.end=1.0",
    "phases.optimizing.beta.steps=400",
    "eval.every=0",
    "checkpoint.every=0",
]


def expected(t: int) -> tuple[float, float, float]:
    """(lr, ε, β) at transition ``t`` of the run (phase 2 starts at ``PHASE1``)."""
    if t <= PHASE1:
        return 5.0e-4, linear(1.0, 0.1, 600, t), linear(0.4, 1.0, 800, t)
    k = t - PHASE1
    return linear(1e-4, 1e-5, PHASE2, k), linear(0.2, 0.0, 300, k), linear(0.5, 1.0, 400, k)


class Recorder:
    """Wraps ``DoubleDQN.train``; optionally sends SIGINT to this process once past a step."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, interrupt_at: int | None = None) -> None:
        self.rows: list[tuple[int, float, float, float, float]] = []
        self.interrupt_at = interrupt_at
        original = DoubleDQN.train

        def recording_train(model: DoubleDQN, gradient_steps: int, batch_size: int = 100) -> None:
            original(model, gradient_steps, batch_size)
            self.rows.append(
                (
                    model.num_timesteps,
                    model.policy.optimizer.param_groups[0]["lr"],
                    model.logger.name_to_value["train/learning_rate"],
                    model.exploration_rate,
                    model.replay_buffer.beta,
                )
            )
            if self.interrupt_at is not None and model.num_timesteps >= self.interrupt_at:
                self.interrupt_at = None
                os.kill(os.getpid(), signal.SIGINT)  # train() turns it into a clean stop

        monkeypatch.setattr(DoubleDQN, "train", recording_train)


def check_rows(rows: list[tuple[int, float, float, float, float]]) -> None:
    assert rows
    for t, lr_used, lr_logged, eps, beta in rows:
        lr, eps_expected, beta_expected = expected(t)
        assert lr_used == pytest.approx(lr, rel=1e-9, abs=1e-15), t
        assert lr_logged == pytest.approx(lr, rel=1e-9, abs=1e-15), t
        assert eps == pytest.approx(eps_expected, abs=1e-9), t
        assert beta == pytest.approx(beta_expected, abs=1e-9), t


def new_run(tmp_path: Path, name: str) -> tuple[RunDir, object]:
    config = load_config(SMOKE, OVERRIDES)
    return RunDir.create(tmp_path, name), config


def test_second_phase_starts_at_its_own_start_values(tmp_path, monkeypatch):
    recorder = Recorder(monkeypatch)
    run, config = new_run(tmp_path, "fresh")
    train(config, run, progress_bar=False)
    check_rows(recorder.rows)
    first_of_phase2 = next(row for row in recorder.rows if row[0] > PHASE1)
    # The first training call of phase 2 comes after one train_freq (4 steps x 4 slots = 16
    # transitions): its learning rate is the phase's start value to within 16/600 of the way.
    t, lr_used, lr_logged, eps, beta = first_of_phase2
    assert t - PHASE1 == 16
    assert lr_logged == pytest.approx(1e-4 - 9e-5 * 16 / PHASE2)
    assert lr_logged > 0.97e-4  # with run-wide progress it would be ~1e-4 - 9e-5 * 816/1400
    assert eps == pytest.approx(0.2 - 0.2 * 16 / 300)
    assert beta == pytest.approx(0.5 + 0.5 * 16 / 400)


@pytest.mark.parametrize("interrupt_at", [500, 1100], ids=["phase1", "phase2"])
def test_resumed_run_follows_the_same_schedules_per_timestep(tmp_path, monkeypatch, interrupt_at):
    recorder = Recorder(monkeypatch, interrupt_at=interrupt_at)
    run, config = new_run(tmp_path, "resumed")
    with pytest.raises(TrainingInterrupted):
        train(config, run, progress_bar=False)
    stopped_at = recorder.rows[-1][0]
    assert stopped_at >= interrupt_at
    before = len(recorder.rows)
    train(config, run, progress_bar=False, resume=True)
    after = recorder.rows[before:]
    # The resumed session continued the same phase from the checkpoint, not from step 0...
    assert after[0][0] > stopped_at
    assert after[-1][0] >= PHASE1 + PHASE2 - 16
    # ...and every value, before and after the interruption, is the uninterrupted schedule's.
    check_rows(recorder.rows)
