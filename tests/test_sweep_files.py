"""A full disk during a sweep's trial ends the sweep in one line that names where (no Optuna
traceback), the trial marked failed (``harness.training.sweep.TrialFileError``)."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

import harness.training.train as train_module
from harness.cli import main
from tests.stopping import harness_lines
from tests.test_seeds_and_sweeps import TINY, sweep_args, trial_states


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


def full_disk(mp: pytest.MonkeyPatch) -> list[int]:
    """The trial's final model cannot be written: ENOSPC without a file name, as a write in
    the middle of a zip raises it. Returns a list that gets one item when it happened."""
    happened: list[int] = []

    def save_model(model: object, path: Path) -> None:
        if path.name == "model.zip":
            happened.append(1)
            raise OSError(errno.ENOSPC, "No space left on device")

    mp.setattr(train_module, "save_model", save_model)
    return happened


def test_a_full_disk_in_a_trial_is_one_line_naming_the_trials_folder(
    tiny, tmp_path, monkeypatch, capfd
):
    full_disk(monkeypatch)
    assert main([*sweep_args(tiny, tmp_path), "--pruner", "none", "--quiet"]) == 2
    folder = tmp_path / "sweeps" / "tiny"
    err = capfd.readouterr().err
    assert "Traceback" not in err and "failed because of" not in err
    assert harness_lines(err) == [
        f"harness: error: trial 0: No space left on device: {folder / 'trial-0000'} (a file of "
        "the trial's run folder); the trial is marked failed; once that is mended, continue "
        "with the same command and --resume"
    ]
    assert trial_states(folder) == ["FAIL"]


def test_a_full_disk_that_also_fails_the_journal_still_names_the_trial(
    tiny, tmp_path, monkeypatch, capfd
):
    from optuna.storages.journal import JournalFileBackend

    happened = full_disk(monkeypatch)
    append = JournalFileBackend.append_logs

    def append_logs(self: JournalFileBackend, logs: list) -> None:
        if happened:  # the same disk: Optuna cannot record how the trial ended either
            raise OSError(errno.ENOSPC, "No space left on device")
        append(self, logs)

    monkeypatch.setattr(JournalFileBackend, "append_logs", append_logs)
    assert main([*sweep_args(tiny, tmp_path), "--pruner", "none", "--quiet"]) == 2
    err = capfd.readouterr().err
    assert "Traceback" not in err
    (line,) = harness_lines(err)
    assert line.startswith("harness: error: trial 0: No space left on device: ")
    assert "trial-0000" in line
