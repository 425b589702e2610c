"""Seed groups and their state (``harness.results.groups``, ``harness.training.state``): a
stopped seed-grid sweep trains every grid point exactly once after ``--resume``; a seed group
stopped by SIGTERM passes it on to its seeds, says how to go on, and ``harness run --resume
GROUP`` finishes it; the state of each kind of folder, and the plan of a group's resume."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from harness.cli import main
from harness.config.loading import load_config
from harness.results.groups import GroupInterrupted, Job
from harness.results.rundir import RunDir
from harness.training import sweep
from harness.training.checkpoints import TrainingState
from harness.training.train import TrainingInterrupted
from tests.conftest import spawn
from tests.test_seeds_and_sweeps import TINY

ROOT = Path(__file__).resolve().parents[1]
#: Long enough to be stopped in the middle of a run.
LONGER = ["--set", "phases.only.timesteps=1200", "--set", "eval.every=400"]


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


def _study(folder: Path):
    import optuna
    from optuna.storages.journal import JournalFileBackend

    storage = optuna.storages.JournalStorage(JournalFileBackend(str(folder / "journal.log")))
    return optuna.load_study(study_name="tiny", storage=storage)


def _complete_seeds(folder: Path) -> list[int]:
    trials = _study(folder).trials
    return sorted(t.params["seed"] for t in trials if t.state.name == "COMPLETE")


def episode_numbers(run: Path) -> list[int]:
    with (run / "episodes.csv").open() as f:
        return [int(row["episode"]) for row in csv.DictReader(f)]


def processes_naming(text: str) -> list[int]:
    """The live processes whose command line holds ``text`` (zombies aside)."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            state = (proc / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if text in cmdline and state != "Z":
            found.append(int(proc.name))
    return found


# ---------------------------------------------------------------------- sweeps
@pytest.mark.parametrize("seeds", [[0, 1], [0, 1, 2]])
@pytest.mark.parametrize("stop_at", [0, 1])
def test_a_stopped_seed_grid_trains_every_seed_exactly_once_after_resume(
    tiny, tmp_path, monkeypatch, capsys, seeds, stop_at
):
    # Training faked (the value is the seed): trial `stop_at` is stopped by SIGTERM, as
    # `train` stops it (a checkpoint, then TrainingInterrupted: Optuna marks the trial failed).
    stop = {"at": stop_at}
    trained: list[int] = []

    def objective(trial, config_path, overrides, dims, folder, total, *_):
        sweep._claim(trial, total)
        params = {d.key: d.suggest(trial) for d in dims}
        if trial.number == stop["at"]:
            raise TrainingInterrupted(signal.SIGTERM, folder / "checkpoint")
        trained.append(params["seed"])
        return float(params["seed"])

    monkeypatch.setattr(sweep, "_objective", objective)
    space = tmp_path / "space.yaml"
    space.write_text(f"seed: {{grid: {seeds}}}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", str(len(seeds)),
            "--pruner", "none", "--sweeps-dir", str(sweeps)]  # fmt: skip
    assert main(args) == 128 + signal.SIGTERM
    assert "sweep stopped by SIGTERM" in capsys.readouterr().err
    stop["at"] = -1
    assert main([*args, "--resume"]) == 0
    # Every grid point trained once, the stopped one included; nothing left queued.
    assert sorted(trained) == seeds
    assert _complete_seeds(sweeps / "tiny") == seeds
    states = [t.state.name for t in _study(sweeps / "tiny").trials]
    assert states.count("FAIL") == 1 and "WAITING" not in states
    # A second resume trains nothing more.
    assert main([*args, "--resume"]) == 0
    assert sorted(trained) == seeds
    assert _complete_seeds(sweeps / "tiny") == seeds


def test_a_resume_never_queues_a_grid_point_that_has_its_trial(tiny, tmp_path, monkeypatch):
    # Three of four points complete, one stopped twice (two failed trials): one trial more.
    def objective(trial, config_path, overrides, dims, folder, total, *_):
        sweep._claim(trial, total)
        params = {d.key: d.suggest(trial) for d in dims}
        if params["seed"] == 2 and trial.number < 4:
            raise TrainingInterrupted(signal.SIGTERM, folder / "checkpoint")
        return float(params["seed"])

    monkeypatch.setattr(sweep, "_objective", objective)
    space = tmp_path / "space.yaml"
    space.write_text("seed: {grid: [0, 1, 2, 3]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "4", "--pruner", "none",
            "--sweeps-dir", str(sweeps), "--quiet"]  # fmt: skip
    code = main(args)
    while code != 0:
        code = main([*args, "--resume"])
    assert _complete_seeds(sweeps / "tiny") == [0, 1, 2, 3]
    trials = _study(sweeps / "tiny").trials
    assert all(t.params["seed"] == 2 for t in trials if t.state.name == "FAIL")


@pytest.mark.slow
def test_a_seed_grid_stopped_in_its_first_trial_resumes_to_one_trial_per_seed(tiny, tmp_path):
    space = tmp_path / "space.yaml"
    space.write_text("seed: {grid: [0, 1]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "2", "--pruner", "none",
            "--sweeps-dir", str(sweeps), *LONGER]  # fmt: skip
    proc = spawn(
        [sys.executable, "-m", "harness.cli", *args], stderr=subprocess.PIPE, text=True, cwd=ROOT
    )
    first = sweeps / "tiny" / "trial-0000"
    deadline = time.monotonic() + 600
    while not (first / "episodes.csv").is_file() or len(episode_numbers(first)) < 2:
        assert proc.poll() is None and time.monotonic() < deadline, "the trial never trained"
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err
    trials = _study(sweeps / "tiny").trials
    assert [t.state.name for t in trials] == ["FAIL"]
    assert main([*args, "--resume", "--quiet"]) == 0
    assert _complete_seeds(sweeps / "tiny") == [0, 1]
    complete = [t for t in _study(sweeps / "tiny").trials if t.state.name == "COMPLETE"]
    for trial in complete:  # each trained its own seed, to the end
        run = Path(trial.user_attrs["run"])
        assert load_config(run / "config.yaml").seed == trial.params["seed"]
        assert (run / "model.zip").is_file()
    assert main([*args, "--resume", "--quiet"]) == 0  # nothing more
    assert len(_study(sweeps / "tiny").trials) == 3


# ---------------------------------------------------------------------- seed groups
def _hand_made_group(folder: Path, config: Path) -> Path:
    """A group of four seeds: 0 finished, 1 stopped at a checkpoint, 2 stopped before its first
    checkpoint, 3 never started (a kill left its folder before its config.yaml)."""
    runs = []
    for seed in range(4):
        run = RunDir(folder / f"tiny-seed{seed}")
        run.checkpoints.mkdir(parents=True)
        run.tb.mkdir()
        runs.append({"seed": seed, "run": run.path.name})
        if seed == 3:
            continue
        run.config.write_text(load_config(config, [f"seed={seed}"]).to_yaml())
        if seed in (0, 1):
            step = run.checkpoints / "step-000000000240"
            step.mkdir()
            (step / "state.json").write_text(
                TrainingState(num_timesteps=240, finished=seed == 0).to_json()
            )
        if seed == 0:
            run.model.write_bytes(b"zip")
    data = {"name": "tiny", "config": str(config), "overrides": [], "seeds": [0, 1, 2, 3],
            "jobs": 2, "runs": runs}  # fmt: skip
    (folder / "group.json").write_text(json.dumps(data))
    return folder


def test_resuming_a_group_plans_each_seed_and_says_which(tiny, tmp_path):
    from harness.results.groups import plan_resume
    from harness.training.state import run_state

    group = _hand_made_group(tmp_path / "g", tiny)
    plan, lines = plan_resume(group, 2, run_state)
    assert lines == [
        "seed 0: finished (tiny-seed0), left alone",
        "seed 1: stopped at step 240, resuming it (tiny-seed1)",
        "seed 2: stopped before its first checkpoint, resuming it (tiny-seed2)",
        "seed 3: never started, starting it (tiny-seed3)",
    ]
    assert plan[0].cmd is None
    resume = plan[1].cmd
    assert resume is not None and resume[3:6] == ["run", "--resume", str(group / "tiny-seed1")]
    start = plan[3].cmd
    assert start is not None and start[-2:] == ["--into", str(group / "tiny-seed3")]
    # Started from a config inside the group (this hand-made one keeps no group-config.yaml:
    # a started seed's), never from the file group.json names.
    assert "seed=3" in start and str(group / "tiny-seed0" / "config.yaml") in start
    assert str(tiny) not in start
    assert not (group / "tiny-seed3").exists()  # the empty leftover is cleared for the start


def test_the_run_state_of_each_kind_of_folder(tiny, tmp_path):
    """The rules of harness/training/state.py on hand-made folders: the states --resume acts
    on, with the words of a group's line per seed."""
    from harness.training.state import RunState, run_state

    group = _hand_made_group(tmp_path / "g", tiny)
    seeds = [RunDir(group / f"tiny-seed{seed}") for seed in range(4)]
    status = [run_state(run) for run in seeds]
    assert [s.state for s in status] == [
        RunState.FINISHED,
        RunState.RESUMABLE,
        RunState.NO_CHECKPOINT,
        RunState.NEW,
    ]
    assert status[1].checkpoint == seeds[1].checkpoints / "step-000000000240"
    assert status[1].training is not None and status[1].training.num_timesteps == 240
    # A model.zip beside a newest checkpoint not marked finished: still to resume.
    seeds[1].model.write_bytes(b"zip")
    assert run_state(seeds[1]).state is RunState.RESUMABLE
    # An unreadable newest state.json: still to resume (from the older checkpoint), even with
    # a model.zip.
    (seeds[0].checkpoints / "step-000000000240" / "state.json").write_text("{")
    unreadable = run_state(seeds[0])
    assert unreadable.state is RunState.RESUMABLE and unreadable.training is None
    assert unreadable.words == "stopped (its newest checkpoint is unreadable)"
    # Finished, its checkpoints deleted since: finished, with no checkpoint to resume from.
    seeds[2].model.write_bytes(b"zip")
    cleaned = run_state(seeds[2])
    assert cleaned.state is RunState.FINISHED and cleaned.checkpoint is None
    assert cleaned.words == "finished"


def test_resuming_a_group_refuses_a_seed_folder_with_files_but_no_config(tiny, tmp_path, capsys):
    group = _hand_made_group(tmp_path / "g", tiny)
    (group / "tiny-seed3" / "notes.txt").write_text("mine")
    assert main(["run", "--resume", str(group), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "tiny-seed3: seed 3's folder has no config.yaml but holds files" in err
    assert "\n" not in err and (group / "tiny-seed3" / "notes.txt").is_file()


def test_a_group_in_use_is_not_resumed_twice(tiny, tmp_path, capsys):
    group = _hand_made_group(tmp_path / "g", tiny)
    holder = spawn(
        [sys.executable, "-c", "import time; from pathlib import Path\n"
         "from harness.results.rundir import RunDir\n"
         f"with RunDir(Path({str(group)!r})).lock():\n print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert main(["run", "--resume", str(group), "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert f"in use by process {holder.pid}" in err and "\n" not in err
    finally:
        holder.kill()
        holder.communicate()


def test_the_stop_line_names_the_seeds_by_state(tmp_path):
    jobs = [Job(k, RunDir(tmp_path / str(k))) for k in range(4)]
    jobs[0].returncode, jobs[1].returncode = 0, 128 + signal.SIGTERM
    stopped = GroupInterrupted(signal.SIGTERM, tmp_path, jobs)
    assert stopped.summary() == "seed 0 done, seed 1 stopped, seeds 2, 3 not started"


def test_jobs_goes_with_a_group_not_a_run(tmp_path, capsys):
    (tmp_path / "config.yaml").write_text(TINY)
    assert main(["run", "--resume", str(tmp_path), "--jobs", "2"]) == 2
    assert "--jobs goes with --seeds" in capsys.readouterr().err


@pytest.mark.slow
def test_sigterm_stops_a_seed_group_and_resume_finishes_every_seed(tiny, tmp_path, capsys):
    runs = tmp_path / "runs"
    cmd = [sys.executable, "-m", "harness.cli", "run", str(tiny), "--seeds", "0,1,2", "--jobs",
           "1", "--runs-dir", str(runs), "--no-progress", *LONGER]  # fmt: skip
    proc = spawn(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    deadline = time.monotonic() + 600
    while True:
        assert proc.poll() is None and time.monotonic() < deadline, "seed 0 never trained"
        found = list(runs.glob("tiny-*/tiny-seed0/episodes.csv"))
        if found and len(episode_numbers(found[0].parent)) >= 2:
            break
        time.sleep(0.2)
    group = found[0].parent.parent
    assert processes_naming(str(group))  # seed 0's process, in training
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err
    said = [line for line in err.splitlines() if line.startswith("harness:")]
    assert said == [
        "harness: seed group stopped by SIGTERM (seed 0 stopped, seeds 1, 2 not started); "
        f"continue it with: harness run --resume {group}"
    ]
    assert processes_naming(str(group)) == []  # no seed left training
    assert not (group / "tiny-seed1").exists() and not (group / "tiny-seed2").exists()
    seed0 = group / "tiny-seed0"
    assert not (seed0 / "model.zip").exists()
    assert re.search(r"stopped by SIGTERM.* after writing", (group / "tiny-seed0.log").read_text())

    capsys.readouterr()
    assert main(["run", "--resume", str(group), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "seed 0: stopped at step" in err and "resuming it (tiny-seed0)" in err
    assert "seed 1: never started, starting it (tiny-seed1)" in err
    assert "seed 2: never started, starting it (tiny-seed2)" in err
    for seed in (0, 1, 2):
        run = group / f"tiny-seed{seed}"
        assert (run / "model.zip").is_file()
        assert load_config(run / "config.yaml").seed == seed
        episodes = episode_numbers(run)
        assert len(episodes) > 10 and episodes == list(range(len(episodes)))
    # The first attempt's log is kept, the resume's appended to it.
    log = (group / "tiny-seed0.log").read_text()
    assert log.index("stopped by SIGTERM") < log.index("resuming at step")
    # A finished group is left alone.
    assert main(["run", "--resume", str(group), "--no-progress"]) == 0
    assert "seed 2: finished (tiny-seed2), left alone" in capsys.readouterr().err
    assert os.listdir(group).count("tiny-seed0") == 1
