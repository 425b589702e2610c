"""A training run's stops and faults (``harness.training.train``): SIGINT/SIGTERM stop a long
in-training evaluation or a long training call at once, with a checkpoint that resumes; SIGKILL
at any time, then a resume, gives every episode once and reaches the total; a non-finite loss
stops the run in one line; the same config and seed give the same episodes; Ctrl-C while the
modules load, and a killed training process with env worker processes, print no traceback."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from harness import DoubleDQN
from harness.cli import main
from harness.config.loading import load_config
from harness.training.checkpoints import TrainingState, complete_checkpoints, latest_checkpoint
from tests.conftest import group_left, spawn
from tests.stopping import (
    ENDLESS_EPOCHS,
    ROOT,
    SMOKE,
    contiguous,
    episodes,
    evaluation_steps,
    harness_lines,
    logged_steps,
    resume,
    run_args,
    signal_during_evaluation,
    signal_during_training,
    state_of,
)

# A smoke run long enough to be killed mid-way, checkpointing often.
LONGER = [
    "--set", "phases.initial.timesteps=6000",
    "--set", "checkpoint.every=1000",
    "--set", "eval.every=1500",  # not a multiple of the checkpoints: rows to drop on resume
]  # fmt: skip


def start_run(runs: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "harness.cli", "run", str(SMOKE), "--runs-dir", str(runs)]
    return spawn([*cmd, "--no-progress", *LONGER], stderr=subprocess.PIPE, text=True, cwd=ROOT)


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


# ---------------------------------------------------------------- 1. a signal during an evaluation
def test_a_signal_abandons_the_evaluation_and_writes_the_usual_checkpoint(stopped_in_evaluation):
    run, err = stopped_in_evaluation
    (line,) = harness_lines(err)
    newest = complete_checkpoints(run / "checkpoints")[-1]
    assert line == (
        "harness: stopped by SIGTERM during the evaluation at step 600 (abandoned; the resume "
        f"runs it) after writing {newest}; resume with: harness run --resume {run}"
    )
    assert "Traceback" not in err
    assert newest.name == "step-000000000600"
    state = state_of(newest)
    assert state.pending_eval == 600 and state.num_timesteps == 600
    # The checkpoint agrees with the logs: every episode logged before it, no evaluation.
    rows = episodes(run)
    assert len(rows) == state.next_episode and contiguous(run)
    assert all(int(row["timesteps"]) <= 600 for row in rows)
    assert evaluation_steps(run) == []


def test_the_resume_runs_the_abandoned_evaluation_then_finishes(run_copy, capsys):
    assert resume(run_copy) == 0
    assert "evaluating step 600 again" in capsys.readouterr().err
    assert evaluation_steps(run_copy) == [600, 1200]
    assert contiguous(run_copy)
    assert (run_copy / "model.zip").is_file()
    assert state_of(complete_checkpoints(run_copy / "checkpoints")[-1]).pending_eval is None


def test_an_endless_episode_evaluation_stops_on_a_signal(tmp_path, capsys):
    # env.max_steps = 10^12: neither the training episodes nor the evaluation's would ever end.
    with pytest.MonkeyPatch.context() as mp:
        signal_during_evaluation(mp)
        args = run_args(tmp_path, "env.max_steps=1000000000000", "eval.every=400")
        assert main(args) == 128 + signal.SIGTERM
    err = capsys.readouterr().err
    assert "during the evaluation at step 400 (abandoned" in err and "Traceback" not in err
    (run,) = tmp_path.iterdir()
    assert state_of(complete_checkpoints(run / "checkpoints")[-1]).pending_eval == 400


@pytest.mark.slow
def test_sigterm_during_a_long_evaluation_stops_in_seconds_and_resumes(tmp_path):
    cmd = [sys.executable, "-m", "harness.cli"]
    cmd += run_args(tmp_path, "eval.every=800", "eval.episodes=5000")
    proc = spawn(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    # The episodes of step 800 are logged just before its evaluation starts.
    err, took = sigterm_when(
        proc,
        lambda: any(max(logged_steps(run), default=0) >= 800 for run in tmp_path.iterdir()),
        settle=0.5,
    )
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert took < 10, f"stopping took {took:.1f} s"
    (run,) = tmp_path.iterdir()
    (line,) = harness_lines(err)
    assert "during the evaluation at step 800 (abandoned" in line
    assert f"resume with: harness run --resume {run}" in line and "Traceback" not in err

    assert resume(run) == 0
    assert contiguous(run) and evaluation_steps(run) == [800, 1600]
    assert (run / "model.zip").is_file()


# ------------------------------------------------------------- 2. a signal during a training call
def test_a_signal_cuts_a_long_training_call_short_and_the_checkpoint_resumes(tmp_path, capsys):
    with pytest.MonkeyPatch.context() as mp:
        signal_during_training(mp)
        assert main(run_args(tmp_path, ENDLESS_EPOCHS)) == 128 + signal.SIGTERM
    err = capsys.readouterr().err
    (run,) = tmp_path.iterdir()
    (line,) = harness_lines(err)
    # The first training call comes at the first round's end past learning_starts (200).
    newest = complete_checkpoints(run / "checkpoints")[-1]
    assert newest.name == "step-000000000208"
    assert line == (
        "harness: stopped by SIGTERM during a training call (cut short after 4 of its "
        f"100,000,000 gradient steps) after writing {newest}; resume with: harness run "
        f"--resume {run}"
    )
    assert len(episodes(run)) == state_of(newest).next_episode and contiguous(run)

    # The checkpoint resumes; the next training call is endless again and stops the same way.
    with pytest.MonkeyPatch.context() as mp:
        signal_during_training(mp)
        assert resume(run) == 128 + signal.SIGTERM
    err = capsys.readouterr().err
    assert "cut short after 4 of its 100,000,000" in err and "Traceback" not in err
    assert complete_checkpoints(run / "checkpoints")[-1].name == "step-000000000216"
    assert contiguous(run)


@pytest.mark.slow
def test_sigterm_during_an_endless_training_call_stops_in_seconds(tmp_path):
    cmd = [sys.executable, "-m", "harness.cli", *run_args(tmp_path, ENDLESS_EPOCHS)]
    proc = spawn(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    # The first episodes end at step 200; the first training call comes at 208.
    err, took = sigterm_when(
        proc, lambda: any(logged_steps(run) for run in tmp_path.iterdir()), settle=1.0
    )
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert took < 10, f"stopping took {took:.1f} s"
    (line,) = harness_lines(err)
    assert "during a training call (cut short after" in line and "Traceback" not in err


def sigterm_when(
    proc: subprocess.Popen, ready: Callable[[], bool], settle: float
) -> tuple[str, float]:
    """Send SIGTERM to ``proc`` ``settle`` seconds after ``ready()`` first holds (at most 600 s
    of waiting); its stderr and the seconds it took to stop. A process left running is killed."""
    try:
        deadline = time.monotonic() + 600
        while not ready():
            assert proc.poll() is None, "the run ended before it could be stopped"
            assert time.monotonic() < deadline, "the run never got there"
            time.sleep(0.1)
        time.sleep(settle)
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        _, err = proc.communicate(timeout=120)
        return err, time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ------------------------------------------------------------------ 3. killed, then resumed
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
    first = spawn([*cmd, "--no-progress", *short], stderr=subprocess.PIPE, text=True)
    read_until(first, "run folder:")
    first.kill()  # at once: training has not even imported torch yet
    first.wait()
    (run,) = tmp_path.iterdir()
    resume_cmd = [sys.executable, "-m", "harness.cli", "run", "--resume", str(run), "--no-progress"]
    second = spawn(resume_cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
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
    proc = spawn(cmd, stderr=subprocess.PIPE, text=True)  # a group of its own, as a terminal's
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
    assert not group_left(proc)  # its env workers ended with it


#: ``harness run`` whose logger closes slowly (a TensorBoard flush on a loaded machine), saying
#: so first: a Ctrl-C can then be sent while training cleans up, before it closes its workers.
SLOW_CLEANUP = (
    "import sys, time\n"
    "from stable_baselines3.common.logger import Logger\n"
    "close = Logger.close\n"
    "def slow_close(self):\n"
    "    print('closing the logger', file=sys.stderr, flush=True)\n"
    "    time.sleep(3)\n"
    "    close(self)\n"
    "Logger.close = slow_close\n"
    "from harness.cli import main\n"
    "sys.exit(main())\n"
)


@pytest.mark.slow
def test_a_second_ctrl_c_while_training_cleans_up_ends_it_and_its_env_workers(tmp_path):
    # The first Ctrl-C's clean stop is over (its checkpoint written): the second one is a
    # KeyboardInterrupt that cuts the cleanup short, before the env workers are closed.
    cmd = [sys.executable, "-c", SLOW_CLEANUP, "run", str(SMOKE), "--runs-dir", str(tmp_path)]
    cmd += ["--no-progress", *LONGER, "--set", "vec.backend=supersuit", "--set", "vec.num_cpus=2"]
    proc = spawn(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    run = wait_for_checkpoint(tmp_path, proc, 1000)
    os.killpg(proc.pid, signal.SIGINT)
    read_until(proc, "closing the logger")
    os.killpg(proc.pid, signal.SIGINT)
    sent = time.monotonic()
    _, err = proc.communicate(timeout=120)
    took = time.monotonic() - sent
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "Traceback" not in err, err
    newest = complete_checkpoints(run / "checkpoints")[-1]
    assert harness_lines(err) == [
        f"harness: interrupted (the newest checkpoint is {newest}); resume with: harness run "
        f"--resume {run}"
    ]
    assert not group_left(proc)  # its env workers ended with it
    assert took < 30, f"ending took {took:.1f} s"


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


# ------------------------------------------------------------------------ 4. no tracebacks
#: What the ``harness`` console script does, with a line once the package is loaded: from then on
#: the command's modules load (a Ctrl-C before, while Python itself starts, is Python's).
LAUNCHER = (
    "import sys; sys.argv[0] = 'harness'; import harness; print('loading', flush=True); "
    "from harness.cli import main; sys.exit(main())"
)


def _ctrl_c_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_while_the_modules_load_is_one_line_and_exit_130():
    # Each delay lands somewhere else: in the imports (seconds here), or in the command after
    # them; no case may print a traceback.
    cmd = [sys.executable, "-c", LAUNCHER, "eval", "--policy", "random", "--config", str(SMOKE)]
    cmd += ["--episodes", "100000"]
    outcomes = []
    for delay in (0.0, 0.01, 0.05, 0.15, 0.3, 0.5, 0.8):
        proc = spawn(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            # As from a terminal: a suite started in the background of a shell without job
            # control runs with SIGINT ignored, which the command (rightly) keeps.
            preexec_fn=_ctrl_c_default,
        )
        try:
            assert proc.stdout.readline() == "loading\n"
            time.sleep(delay)
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        outcomes.append((delay, proc.returncode, err))
    for delay, code, err in outcomes:
        assert "Traceback" not in err, (delay, err)
        assert code == 128 + signal.SIGINT, (delay, code, err)
        assert harness_lines(err) == ["harness: interrupted"], (delay, err)


@pytest.mark.slow
def test_sigkill_of_the_training_process_leaves_its_env_workers_quiet(tmp_path):
    cmd = [sys.executable, "-m", "harness.cli"]
    cmd += run_args(
        tmp_path, "vec.backend=supersuit", "vec.num_cpus=2", "phases.initial.timesteps=100000"
    )
    # A session of its own: the workers left behind can be found (and killed) after the test.
    proc = spawn(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT, start_new_session=True)
    try:
        deadline = time.monotonic() + 600
        while not any(complete_checkpoints(run / "checkpoints") for run in tmp_path.iterdir()):
            assert proc.poll() is None and time.monotonic() < deadline, "no checkpoint came"
            time.sleep(0.2)
        proc.kill()
        proc.wait()
        # The workers hold the stderr pipe too: its end means they are gone.
        err = proc.stderr.read()
    finally:
        with contextlib.suppress(ProcessLookupError):  # the workers, had they stayed
            os.killpg(proc.pid, signal.SIGKILL)
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
