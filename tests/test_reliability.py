"""Reliability of training runs: checkpoints, resume after SIGKILL/SIGTERM, numerical faults."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from harness import DoubleDQN
from harness.cli import main
from harness.config.loading import load_config
from harness.training.checkpoints import (
    CheckpointError,
    TrainingState,
    complete_checkpoints,
    latest_checkpoint,
)

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
# A smoke run long enough to be killed mid-way, checkpointing often.
LONGER = [
    "--set", "phases.initial.timesteps=6000",
    "--set", "checkpoint.every=1000",
    "--set", "eval.every=1500",  # not a multiple of the checkpoints: rows to drop on resume
]  # fmt: skip


def start_run(runs: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "harness.cli", "run", str(SMOKE), "--runs-dir", str(runs)]
    return subprocess.Popen(
        [*cmd, "--no-progress", *LONGER], stderr=subprocess.PIPE, text=True, cwd=ROOT
    )


def wait_for_checkpoint(runs: Path, proc: subprocess.Popen, min_steps: int) -> Path:
    # generous: on a loaded 2-core machine the subprocess may take minutes to reach min_steps
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        assert proc.poll() is None, "the run ended before it could be stopped"
        for run in runs.glob("smoke-*"):
            found = complete_checkpoints(run / "checkpoints")
            if found and int(found[-1].name.split("-")[1]) >= min_steps:
                return run
        time.sleep(0.2)
    raise AssertionError("no checkpoint appeared")


def episode_numbers(run: Path) -> list[int]:
    with (run / "episodes.csv").open() as f:
        return [int(row["episode"]) for row in csv.DictReader(f)]


@pytest.mark.slow
def test_sigkill_then_resume_reaches_the_total_without_gaps_or_duplicates(tmp_path, capsys):
    proc = start_run(tmp_path)
    run = wait_for_checkpoint(tmp_path, proc, 2000)
    # While it runs, a second process on the same folder is refused (exit 2, one line).
    rows_before = episode_numbers(run)
    capsys.readouterr()
    assert main(["run", "--resume", str(run), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert f"in use by process {proc.pid}" in err and "\n" not in err
    assert episode_numbers(run)[: len(rows_before)] == rows_before
    proc.kill()  # SIGKILL: no chance to clean up
    proc.wait()
    assert not (run / "model.zip").exists()

    assert main(["run", "--resume", str(run), "--no-progress"]) == 0
    total = load_config(run / "config.yaml").total_timesteps
    model = DoubleDQN.load(run / "model.zip")
    # SB3 collects train_freq env steps (x 4 slots) at a time: each phase may overshoot a little.
    assert total <= model.num_timesteps < total + (2 + 4) * 4
    episodes = episode_numbers(run)
    assert episodes == list(range(len(episodes)))
    with (run / "evaluations.csv").open() as f:
        evals = [int(row["timesteps"]) for row in csv.DictReader(f)]
    every = load_config(run / "config.yaml").eval.every
    assert evals == sorted(set(evals))  # none logged twice across the kill
    assert [t // every for t in evals] == list(range(1, len(evals) + 1))  # and none missing
    # TensorBoard shows each evaluation once (the killed session's later events are purged) and
    # the first session's progress.csv is kept beside the resumed one's.
    events = EventAccumulator(str(run / "tb"))
    events.Reload()
    # (TensorBoard's reservoir may list the purged-and-continued steps out of order: compare sets)
    steps = [e.step for e in events.Scalars("eval/coverage_median")]
    assert sorted(steps) == evals and len(steps) == len(set(steps))
    for name in ("progress.csv", "progress-resume1.csv"):
        with (run / "tb" / name).open() as f:
            assert len(list(csv.DictReader(f))) > 0, name
    state = json.loads((latest_checkpoint(run / "checkpoints") / "state.json").read_text())
    assert state["finished"] is True and state["resumes"] == 1
    assert "resume" in (run / "command.txt").read_text().splitlines()[-1]

    # Resuming a finished run says so and changes nothing.
    capsys.readouterr()
    assert main(["run", "--resume", str(run)]) == 0
    assert "already finished" in capsys.readouterr().err


@pytest.mark.slow
def test_sigterm_writes_a_checkpoint_and_says_how_to_resume(tmp_path):
    proc = start_run(tmp_path)
    run = wait_for_checkpoint(tmp_path, proc, 1000)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM
    assert f"resume with: harness run --resume {run}" in err
    assert "Traceback" not in err
    newest = latest_checkpoint(run / "checkpoints")
    assert f"after writing {newest}" in err
    state = TrainingState.from_json((newest / "state.json").read_text())
    # At or past the checkpoint it waited for: the signal may land before the next env step.
    assert not state.finished and state.num_timesteps >= 1000


def test_half_written_checkpoints_are_ignored(tmp_path):
    folder = tmp_path / "checkpoints"
    (folder / ".step-000000000300.tmp").mkdir(parents=True)  # crash while writing
    (folder / "step-000000000200").mkdir()
    (folder / "step-000000000200" / "state.json").write_text(TrainingState().to_json())
    (folder / "step-000000000400").mkdir()  # no state.json: incomplete
    assert latest_checkpoint(folder).name == "step-000000000200"
    with pytest.raises(CheckpointError, match="no complete checkpoint"):
        latest_checkpoint(tmp_path / "nothing")


def test_training_state_json_round_trip():
    state = TrainingState(phase=1, phase_start=40, next_episode=7, best_eval=0.5, resumes=2)
    assert TrainingState.from_json(state.to_json()) == state
    fresh = TrainingState()
    assert TrainingState.from_json(fresh.to_json()).best_eval == float("-inf")


def test_resume_errors_are_one_line(tmp_path, capsys):
    assert main(["run", "--resume", str(tmp_path)]) == 2
    assert "not a run folder" in capsys.readouterr().err
    (tmp_path / "config.yaml").write_text(SMOKE.read_text())
    assert main(["run", "--resume", str(tmp_path), str(SMOKE)]) == 2
    assert "drop the other options" in capsys.readouterr().err


def test_non_finite_loss_stops_the_run_with_a_clear_message(tmp_path, capsys):
    args = [
        "run", str(SMOKE), "--runs-dir", str(tmp_path), "--no-progress",
        "--set", "algo.optimizer=SGD", "--set", "phases.initial.learning_rate=1e30",
        "--set", "eval.every=1500",  # not a multiple of the checkpoints: rows to drop on resume
    ]  # fmt: skip
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "the loss became nan" in err or "the loss became inf" in err
    assert "Traceback" not in err


def test_same_config_and_seed_give_the_same_episodes(tmp_path):
    short = ["--set", "phases.initial.timesteps=1200", "--set", "phases.optimizing.timesteps=400"]
    for name in ("a", "b"):
        args = ["run", str(SMOKE), "--runs-dir", str(tmp_path / name), "--no-progress", *short]
        assert main([*args, "--set", "eval.every=0"]) == 0
    (a,) = (tmp_path / "a").iterdir()
    (b,) = (tmp_path / "b").iterdir()
    rows = (a / "episodes.csv").read_text()
    assert rows.count("\n") > 10
    assert rows == (b / "episodes.csv").read_text()


def read_until(proc: subprocess.Popen, marker: str) -> str:
    """Lines of ``proc``'s stderr up to the first that contains ``marker``."""
    seen = ""
    for line in proc.stderr:
        seen += line
        if marker in line:
            return seen
    raise AssertionError(f"{marker!r} never came: {seen}")


def no_temporary_files(run: Path) -> list[Path]:
    return [p for p in run.rglob("*") if p.name.endswith(".tmp")]


@pytest.mark.slow
def test_kill_as_soon_as_the_run_folder_exists_then_a_resume_starts_again_alone(tmp_path, capsys):
    short = ["--set", "phases.initial.timesteps=1200", "--set", "phases.optimizing.timesteps=400"]
    cmd = [sys.executable, "-m", "harness.cli", "run", str(SMOKE), "--runs-dir", str(tmp_path)]
    first = subprocess.Popen([*cmd, "--no-progress", *short], stderr=subprocess.PIPE, text=True)
    read_until(first, "run folder:")
    first.kill()  # at once: training has not even imported torch yet
    first.wait()
    (run,) = tmp_path.iterdir()
    resume_cmd = [sys.executable, "-m", "harness.cli", "run", "--resume", str(run), "--no-progress"]
    second = subprocess.Popen(resume_cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    read_until(second, "starting the run again from step 0")
    # While it trains, a third process on the folder is refused: exit 2, one line, its pid.
    capsys.readouterr()
    assert main(["run", "--resume", str(run), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert f"in use by process {second.pid}" in err and "\n" not in err
    _, rest = second.communicate(timeout=600)
    assert second.returncode == 0, rest
    assert (run / "model.zip").is_file()
    episodes = episode_numbers(run)
    assert len(episodes) > 10 and episodes == list(range(len(episodes)))
    assert no_temporary_files(run) == []


@pytest.mark.slow
def test_ctrl_c_twice_in_a_terminal_with_env_worker_processes_stops_without_traceback(tmp_path):
    # A terminal's Ctrl-C goes to the whole process group: the env worker processes too.
    cmd = [sys.executable, "-m", "harness.cli", "run", str(SMOKE), "--runs-dir", str(tmp_path)]
    cmd += ["--no-progress", *LONGER, "--set", "vec.backend=supersuit", "--set", "vec.num_cpus=2"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, start_new_session=True)
    run = wait_for_checkpoint(tmp_path, proc, 1000)
    os.killpg(proc.pid, signal.SIGINT)
    time.sleep(0.05)  # the second one lands while stopping (or saving) the first
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    # 130, or killed by the SIGINT itself while exiting after its message: $? is 130 in a shell
    assert proc.returncode in (128 + signal.SIGINT, -signal.SIGINT), err
    assert "Traceback" not in err and "error" not in err
    assert f"resume with: harness run --resume {run}" in err
    assert no_temporary_files(run) == []
    assert complete_checkpoints(run / "checkpoints")


def test_starting_again_over_a_damaged_log_is_one_line_and_changes_nothing(tmp_path, capsys):
    run = tmp_path / "killed-early"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.yaml").write_text(load_config(SMOKE).to_yaml())
    (run / "episodes.csv").write_text("not,the,header\n1,2,3\n")
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    assert main(["run", "--resume", str(run), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("harness: error: cannot start the run again:")
    assert "episodes.csv: line 1" in err[-1] and "Traceback" not in "\n".join(err)
    after = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".lock"}
    assert after == before


def test_evaluating_a_shipped_reference_changes_none_of_its_files(tmp_path, monkeypatch, capsys):
    reference = ROOT / "runs" / "reference" / "ddqn_15x15"
    before = {p.name: p.read_bytes() for p in reference.iterdir()}
    monkeypatch.chdir(tmp_path)  # results of a reference go to runs/evals/ under the cwd
    assert main(["eval", str(reference), "--episodes", "2"]) == 0
    assert {p.name: p.read_bytes() for p in reference.iterdir()} == before
    saved = Path("runs") / "evals" / "ddqn_15x15" / "eval-2ep.json"
    assert f"saved {saved}" in capsys.readouterr().err
    assert json.loads((tmp_path / saved).read_text())["episodes"] == 2
