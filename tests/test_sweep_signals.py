"""A signal to a sweep is never lost: one that reaches a trial's training too late to stop its
run (its final save, a round the pruner ends) stops the sweep before the next trial
(``harness.training.sweep._SignalState``)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

import harness.evaluation.episodes as episodes_module
import harness.training.train as train_module
from harness.cli import main
from tests.test_seeds_and_sweeps import TINY, sweep_args, trial_states


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


def _signal_on_first_call(
    mp: pytest.MonkeyPatch, module: object, name: str, signum: int, when: str = ""
) -> None:
    """``module.name`` sends ``signum`` to this process on its first call (whose arguments'
    text holds ``when``), then does its work."""
    original = getattr(module, name)
    sent: list[int] = []

    def signalling(*args: object, **kwargs: object) -> object:
        if not sent and when in str(args):
            sent.append(signum)
            os.kill(os.getpid(), signum)
        return original(*args, **kwargs)

    mp.setattr(module, name, signalling)


@pytest.mark.parametrize(
    ("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["sigterm", "sigint"]
)
def test_a_signal_during_a_trials_final_save_stops_the_sweep_before_the_next_trial(
    tiny, tmp_path, monkeypatch, capfd, signum, code
):
    # The final model is written after training's last look at its stop flag: the trial ends
    # complete, and the signal must still stop the sweep (it went on to trial 2 before).
    _signal_on_first_call(monkeypatch, train_module, "save_model", signum, "/model.zip")
    args = [*sweep_args(tiny, tmp_path), "--trials", "3", "--pruner", "none", "--quiet"]
    assert main(args) == code
    err = capfd.readouterr().err
    assert [line for line in err.splitlines() if line.startswith("harness:")] == [
        f"harness: sweep stopped by {signal.Signals(signum).name}; continue it with the same "
        "command and --resume"
    ]
    assert trial_states(tmp_path / "sweeps" / "tiny") == ["COMPLETE"]


def test_a_sigterm_in_a_round_the_pruner_ends_stops_the_sweep(tiny, tmp_path, monkeypatch):
    import optuna

    from harness.training import sweep

    # Every trial is pruned at its first evaluation, and SIGTERM lands in that evaluation: the
    # pruner's exception leaves training before it reads its stop flag.
    monkeypatch.setattr(sweep, "make_pruner", lambda name: optuna.pruners.ThresholdPruner(1.01))
    _signal_on_first_call(monkeypatch, episodes_module, "objective_value", signal.SIGTERM)
    args = [*sweep_args(tiny, tmp_path), "--trials", "3", "--quiet"]
    assert main(args) == 143
    assert trial_states(tmp_path / "sweeps" / "tiny") == ["PRUNED"]
