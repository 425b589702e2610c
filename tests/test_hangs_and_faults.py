"""Hangs and faults: SIGINT/SIGTERM stop a long in-training evaluation or a long
training call at once, with a checkpoint that resumes; a damaged replay buffer is found by the
SHA-256 its checkpoint keeps; Ctrl-C while the modules load, and a killed training process with
env worker processes, print no traceback."""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from harness.cli import main
from harness.sb3.dqn import DoubleDQN
from harness.training import train as train_module
from harness.training.checkpoints import TrainingState, complete_checkpoints
from tests.test_resume import TINY as RESUME_TINY

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
# A tiny run on one thread (a tiny net's second thread only waits): checkpoints at 400 and 800,
# evaluations at 600 and 1200.
TINY = [*RESUME_TINY, "algo.threads=1"]
#: An epochs table whose training call never ends on its own (10^8 gradient steps).
ENDLESS_EPOCHS = "phases.initial.epochs=[[0.0, 100000000]]"


def sets(*overrides: str) -> list[str]:
    """``--set`` options: :data:`TINY`, with ``overrides`` in place of those of the same keys."""
    merged = {o.partition("=")[0]: o for o in [*TINY, *overrides]}
    return [a for o in merged.values() for a in ("--set", o)]


def run_args(runs: Path, *overrides: str) -> list[str]:
    return ["run", str(SMOKE), "--runs-dir", str(runs), "--no-progress", *sets(*overrides)]


def resume(run: Path) -> int:
    return main(["run", "--resume", str(run), "--no-progress"])


def episodes(run: Path) -> list[dict[str, str]]:
    with (run / "episodes.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def logged_steps(run: Path) -> list[int]:
    """The ``timesteps`` of ``episodes.csv`` so far (read while the run writes it)."""
    path = run / "episodes.csv"
    lines = path.read_text().splitlines()[1:] if path.is_file() else []
    cells = [line.split(",") for line in lines]
    return [int(c[2]) for c in cells if len(c) > 2 and c[2].isdigit()]


def contiguous(run: Path) -> bool:
    numbers = [int(row["episode"]) for row in episodes(run)]
    return numbers == list(range(len(numbers)))


def evaluation_steps(run: Path) -> list[int]:
    path = run / "evaluations.csv"
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return [int(row["timesteps"]) for row in csv.DictReader(f)]


def state_of(checkpoint: Path) -> TrainingState:
    return TrainingState.from_json((checkpoint / "state.json").read_text())


def snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def harness_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("harness:")]


def signal_on_call(n: int, signum: int = signal.SIGTERM) -> Callable[[], None]:
    """A function that sends ``signum`` to this process on its ``n``-th call."""
    calls = [0]

    def tick() -> None:
        calls[0] += 1
        if calls[0] == n:
            os.kill(os.getpid(), signum)

    return tick


def signal_during_evaluation(mp: pytest.MonkeyPatch, n: int = 10) -> None:
    """The in-training evaluation's policy sends SIGTERM at its ``n``-th step."""
    original = train_module.model_policy
    tick = signal_on_call(n)

    def model_policy(model: Any, *args: Any, **kwargs: Any) -> Any:
        policy = original(model, *args, **kwargs)

        def signalling(obs: Any, envs: Any) -> Any:
            tick()
            return policy(obs, envs)

        return signalling

    mp.setattr(train_module, "model_policy", model_policy)


def signal_during_training(mp: pytest.MonkeyPatch, n: int = 5) -> None:
    """The ``n``-th gradient step sends SIGTERM (before its optimizer step)."""
    original = DoubleDQN._gradient_step
    tick = signal_on_call(n)

    def gradient_step(model: DoubleDQN, replay_data: Any, *args: Any) -> Any:
        tick()
        return original(model, replay_data, *args)

    mp.setattr(DoubleDQN, "_gradient_step", gradient_step)


# ---------------------------------------------------------------- 1. a signal during an evaluation
@pytest.fixture(scope="module")
def stopped_in_evaluation(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A tiny run stopped by SIGTERM in the middle of its evaluation at step 600 (checkpoints
    at 400 and 600), and what it printed."""
    runs = tmp_path_factory.mktemp("runs")
    err = io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stderr(err):
        signal_during_evaluation(mp)
        code = main(run_args(runs))
    assert code == 128 + signal.SIGTERM, err.getvalue()
    (run,) = runs.iterdir()
    return run, err.getvalue()


@pytest.fixture
def run_copy(stopped_in_evaluation: tuple[Path, str], tmp_path: Path) -> Path:
    run, _ = stopped_in_evaluation
    copy = tmp_path / run.name
    shutil.copytree(run, copy)
    return copy


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
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
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
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
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


# ------------------------------------------------------------------ 3. a damaged replay buffer
def flip_a_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # in the middle: the arrays' bytes, which unpickle regardless
    path.write_bytes(bytes(data))


def test_checkpoints_keep_the_sha256_of_their_replay_buffer(run_copy):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        stored = (checkpoint / "replay_buffer.pkl.sha256").read_text().split()
        digest = hashlib.sha256((checkpoint / "replay_buffer.pkl").read_bytes()).hexdigest()
        assert stored == [digest, "replay_buffer.pkl"]  # as sha256sum writes it


def test_a_flipped_byte_in_the_replay_buffer_falls_back_to_the_older_checkpoint(run_copy, capsys):
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    flip_a_byte(newest / "replay_buffer.pkl")
    assert resume(run_copy) == 0
    err = capsys.readouterr().err
    (line,) = [line for line in harness_lines(err) if "resuming from the older" in line]
    assert f"{newest / 'replay_buffer.pkl'}: unreadable (damaged: its SHA-256" in line
    assert line.endswith(f"resuming from the older {older.name}")
    assert (newest.parent / f"unusable-{newest.name}").is_dir()  # set aside, as a bad model is
    assert contiguous(run_copy) and evaluation_steps(run_copy) == [600, 1200]


def test_a_flipped_byte_in_the_only_checkpoint_is_a_one_line_refusal(run_copy, capsys):
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    shutil.rmtree(older)
    flip_a_byte(newest / "replay_buffer.pkl")
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("harness: error: ") and "Traceback" not in "\n".join(err)
    assert f"{newest / 'replay_buffer.pkl'}: unreadable (damaged: its SHA-256" in err[-1]
    assert snapshot(run_copy) == before


def written_before_guards(checkpoint: Path, *files: str) -> None:
    """Make ``checkpoint`` as written before it kept ``files``: without them, and with a
    ``state.json`` that does not list its guard files."""
    for name in files:
        (checkpoint / name).unlink()
    state = json.loads((checkpoint / "state.json").read_text())
    del state["guards"]
    (checkpoint / "state.json").write_text(json.dumps(state))


def test_checkpoints_without_a_stored_sha256_still_resume(run_copy):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        written_before_guards(checkpoint, "replay_buffer.pkl.sha256")
    assert resume(run_copy) == 0
    assert contiguous(run_copy)


def test_a_deleted_sha256_falls_back_to_the_older_checkpoint(run_copy, capsys):
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    assert state_of(newest).guards == ["replay_buffer.pkl.sha256", "config.yaml"]
    (newest / "replay_buffer.pkl.sha256").unlink()  # its buffer must not load unchecked
    assert resume(run_copy) == 0
    err = capsys.readouterr().err
    (line,) = [line for line in harness_lines(err) if "resuming from the older" in line]
    assert f"{newest / 'replay_buffer.pkl.sha256'}: missing (written with the checkpoint" in line
    assert line.endswith(f"resuming from the older {older.name}")
    assert (newest.parent / f"unusable-{newest.name}").is_dir()
    assert contiguous(run_copy)


def test_checkpoints_that_all_lost_their_sha256_are_a_one_line_refusal(run_copy, capsys):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        (checkpoint / "replay_buffer.pkl.sha256").unlink()
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("harness: error: ") and "Traceback" not in "\n".join(err)
    assert "replay_buffer.pkl.sha256: missing" in err[-1]
    assert snapshot(run_copy) == before


def test_a_state_listing_unknown_guards_is_unreadable():
    data = json.loads(TrainingState().to_json())
    for bad in ("config.yaml", ["model.zip"], [1]):
        with pytest.raises(ValueError, match="guards"):
            TrainingState.from_json(json.dumps({**data, "guards": bad}))


def test_a_state_without_pending_eval_still_reads():
    state = TrainingState(next_episode=3, num_timesteps=40)
    data = json.loads(state.to_json())
    del data["pending_eval"]  # as written before checkpoints kept it
    assert TrainingState.from_json(json.dumps(data)) == state
    for bad in (-1, True, 1.5):
        with pytest.raises(ValueError, match="pending_eval"):
            TrainingState.from_json(json.dumps({**data, "pending_eval": bad}))


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
        proc = subprocess.Popen(
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
    proc = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT, start_new_session=True
    )
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
