"""A child never outlives the harness command that started it (``harness.processes.
follow_parent``), and a ``--resume`` of a sweep whose killed command left its ``--jobs`` workers
running is refused until they have ended (``harness.training.sweep.WORKERS_LOCK``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from harness.cli import main
from harness.training.sweep import SweepError, _check_no_workers
from tests.conftest import one_error_line, root_first_env, spawn
from tests.test_seeds_and_sweeps import TINY, trial_states

#: A parent that starts ``python_command(CODE)`` (its pid on the first line), then waits.
PARENT = (
    "import subprocess, sys, time\n"
    "from harness.processes import python_command\n"
    "child = subprocess.Popen(python_command(sys.argv[1]))\n"
    "print(child.pid, flush=True)\n"
    "time.sleep(600)\n"
)


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped by its new parent, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rpartition(")")[2].split()[0] != "Z"


def wait_gone(pids: list[int], seconds: float) -> list[int]:
    """The pids of ``pids`` still running after at most ``seconds``."""
    deadline = time.monotonic() + seconds
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    return [p for p in pids if alive(p)]


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_a_child_ends_soon_after_its_parent_is_killed(tmp_path):
    code = "import time\ntime.sleep(600)\n"
    parent = spawn(
        [sys.executable, "-c", PARENT, code], stdout=subprocess.PIPE, text=True,
        env=root_first_env(),
    )  # fmt: skip
    with parent:
        child = int(parent.stdout.readline())
        assert alive(child)
        parent.kill()  # SIGKILL: nothing the parent could pass on
        parent.wait()
        left = wait_gone([child], 10)
        for pid in left:
            os.kill(pid, signal.SIGKILL)
        assert left == []


def test_a_child_whose_parent_is_gone_before_it_starts_ends_in_one_line(tmp_path):
    # The pid of a process that has ended (and been reaped) stands for a parent gone too soon.
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    pid = int(done.stdout)
    code = (
        "import subprocess, sys\n"
        "from harness import processes\n"
        f"cmd = processes.python_command('print(\"ran\")')\n"
        f"cmd[2] = cmd[2].replace('follow_parent({{}})'.format(__import__('os').getpid()), "
        f"'follow_parent({pid})')\n"
        "sys.exit(subprocess.run(cmd).returncode)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=root_first_env(), timeout=60)  # fmt: skip
    assert proc.returncode == 143 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        f"harness: error: the process that started this one ({pid}) has ended"
    ]


def test_a_child_of_a_live_parent_runs_to_its_end():
    from harness.processes import python_command

    proc = subprocess.run(python_command("import time; time.sleep(1.2); print('done')"),
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 0 and proc.stdout == "done\n", proc.stderr


def test_a_resume_waits_for_the_workers_of_a_killed_sweep(tmp_path):
    folder = tmp_path / "sweeps" / "study"
    folder.mkdir(parents=True)
    # A worker of the killed sweep, still alive: it holds .workers.lock as workers do.
    code = (
        "import sys, time\nfrom pathlib import Path\n"
        "from harness.training.sweep import _worker_hold\n"
        "with _worker_hold(Path(sys.argv[1])):\n"
        "    print('held', flush=True); time.sleep(600)\n"
    )
    worker = spawn([sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE,
                   text=True, env=root_first_env())  # fmt: skip
    with worker:
        try:
            assert worker.stdout.readline() == "held\n"
            match = "workers of an earlier sweep of this study are still"
            with pytest.raises(SweepError, match=match):
                _check_no_workers(folder)
        finally:
            worker.kill()
    _check_no_workers(folder)  # gone: the lock went with it


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_sigkill_to_a_two_worker_sweep_leaves_no_worker_and_a_resume_waits(tmp_path, capsys):
    config = tmp_path / "tiny.yaml"
    config.write_text(TINY)
    space = tmp_path / "space.yaml"
    space.write_text("seed: {grid: [5, 6, 7, 8]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(config), "--space", str(space), "--trials", "4",
            "--sweeps-dir", str(sweeps), "--pruner", "none",
            "--set", "phases.only.timesteps=400000", "--set", "eval.every=200000"]  # fmt: skip
    harness = Path(sys.executable).parent / "harness"
    parent = spawn([str(harness), *args, "--jobs", "2"], env=root_first_env(),
                   stderr=subprocess.DEVNULL)  # fmt: skip
    folder = sweeps / "tiny"
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 240
        # Both workers train: each trial's episode log has rows.
        while len([p for p in folder.glob("trial-*/episodes.csv")
                   if p.read_text().count("\n") > 1]) < 2:  # fmt: skip
            assert parent.poll() is None and time.monotonic() < deadline, "no training"
            time.sleep(0.2)
        workers += [int(p.read_text()) for p in folder.glob("trial-*/.lock")]
        assert len(workers) == 2 and all(alive(p) for p in workers)
        for pid in workers:  # held still, so that they outlive the resume below for sure
            os.kill(pid, signal.SIGSTOP)
        parent.kill()
        parent.wait()
        # While the workers live: refused, their trials left alone.
        assert main([*args, "--resume"]) == 2
        line = one_error_line(capsys.readouterr().err)
        assert "workers of an earlier sweep of this study are still running" in line
        assert trial_states(folder) == ["RUNNING", "RUNNING"]
        for pid in workers:
            os.kill(pid, signal.SIGCONT)
        assert wait_gone(workers, 60) == []  # they stopped by themselves, cleanly
        assert trial_states(folder) == ["FAIL", "FAIL"]  # stopped by SIGTERM, not left running
        for trial in folder.glob("trial-*"):
            assert list((trial / "checkpoints").glob("step-*")), "no checkpoint on the stop"
        _check_no_workers(folder)
    finally:
        parent.kill()
        parent.wait()
        for pid in workers:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        for pid in workers:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
