"""Issue 38: inputs that slipped past the one-line errors. A ``{file: {path}}`` map source keeps
its hash (alone or in a mix), ``compare`` refuses numbers too large for it, a sweep stopped by
SIGTERM exits 143 with one line, and an override of ``env.map`` is applied before the map it
replaces is checked."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from harness.cli import main
from harness.config.loading import load_config

ROOT = Path(__file__).resolve().parents[1]
ROOM = "........\n..##....\n........\n....#...\n........\n........\n........\n........\n"
TINY = (
    "name: tiny\n"
    "env: {height: 8, width: 8, n_agents: 2, max_steps: 20}\n"
    "vec: {copies: 1}\n"
    "algo: {net_arch: [8], buffer_size: 1000, learning_starts: 50}\n"
    "phases: [{name: only, timesteps: 240, exploration: {start: 1.0, end: 0.1, steps: 160}}]\n"
    "eval: {every: 80, episodes: 2}\n"
    "checkpoint: {every: 0}\n"
)
SPACE = "algo.gamma: {float: [0.8, 0.99]}\n"
EPISODES = "episode,phase,timesteps,copy,coverage,reward_mean,wall_hits,new_cells,length\n"


def one_error_line(err: str) -> str:
    """The only line of ``err``, checked to be a harness error."""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("harness: error: ") and "Traceback" not in err
    return lines[0]


def with_map(tmp_path: Path, source: str) -> Path:
    """A tiny config on ``room.txt`` given as ``source`` (YAML of ``env.map``)."""
    (tmp_path / "room.txt").write_text(ROOM)
    path = tmp_path / "given.yaml"
    path.write_text(TINY.replace("max_steps: 20}", f"max_steps: 20, map: {source}}}"))
    return path


def saved(tmp_path: Path, config_path: Path) -> Path:
    """The config as a run keeps it (``config.yaml``)."""
    path = tmp_path / "config.yaml"
    path.write_text(load_config(config_path).to_yaml())
    return path


# ---------------------------------------------------------------------- 1. file sources' hashes
FILE_SOURCES = {
    "file": ("{file: {path: room.txt}}", lambda m: m["file"], "env.map: file: "),
    "mix": (
        "{mix: [{weight: 1, cave: {}}, {weight: 2, file: {path: room.txt}}]}",
        lambda m: m["mix"][1]["file"],
        "env.map: mix.1.file: ",
    ),
}


@pytest.mark.parametrize("form", list(FILE_SOURCES))
def test_a_file_source_keeps_its_hash_and_a_changed_file_is_one_line(
    tmp_path, monkeypatch, capsys, form
):
    source, pick, where = FILE_SOURCES[form]
    monkeypatch.chdir(tmp_path)
    path = saved(tmp_path, with_map(tmp_path, source))
    room = tmp_path / "room.txt"
    kept = pick(yaml.safe_load(path.read_text())["env"]["map"])
    assert kept["path"] == str(room) and len(kept["sha256"]) == 64
    assert load_config(path).env.map == load_config(path).env.map  # unchanged: loads
    room.write_text(ROOM.replace("#", "."))
    runs = tmp_path / "runs"
    capsys.readouterr()
    assert main(["run", str(path), "--runs-dir", str(runs), "--no-progress"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{where}map file '{room}' has changed since this config was written" in line
    assert not runs.exists()


def test_a_saved_file_source_without_a_hash_still_loads_and_gets_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = with_map(tmp_path, f"{{file: {{path: {tmp_path / 'room.txt'}}}}}")
    source = load_config(path).env.map
    assert source["file"]["path"] == str(tmp_path / "room.txt")
    assert len(source["file"]["sha256"]) == 64


def test_an_override_naming_another_map_file_drops_the_old_hash(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = saved(tmp_path, with_map(tmp_path, "{file: {path: room.txt}}"))
    (tmp_path / "hall.txt").write_text("." * 8 + "\n" + "." * 8 + "\n")
    config = load_config(path, ["env.map.file.path=hall.txt"])
    assert config.env.map["file"]["path"] == str(tmp_path / "hall.txt")
    string_form = saved(tmp_path, with_map(tmp_path, "room.txt"))
    assert load_config(string_form, ["env.map=hall.txt"]).env.map == str(tmp_path / "hall.txt")


# ---------------------------------------------------------------------- 2. compare's numbers
def fake_run(folder: Path, episodes: str, ev: str | None = None) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(TINY)
    (folder / "episodes.csv").write_text(EPISODES + episodes)
    if ev is not None:
        (folder / "eval.json").write_text(ev)
    return folder


HUGE = "1" + "0" * 400
HUGE_EVAL = f'{{"coverage_median": 0.5, "coverage_mean": {HUGE}, "wall_hits_mean": 1}}'
TOO_LARGE = [
    ({"eval.json": HUGE_EVAL}, "eval.json: the number 100000000000... (401 digits) is too large"),
    ({"episodes.csv": EPISODES + "1,0,1e300,0,0.5,0.1,0,10,20\n"},
     "episodes.csv, line 2: timesteps 1e300 is out of range"),
    ({"evaluations.csv": "timesteps,coverage_median\n1e300,0.5\n"},
     "evaluations.csv, line 2: timesteps 1e300 is out of range"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("files", "message"),
    TOO_LARGE,
    ids=["eval-json-400-digits", "episodes-1e300", "evaluations-1e300"],
)
def test_compare_refuses_numbers_too_large_in_one_line(tmp_path, capsys, files, message):
    run = fake_run(tmp_path / "run", "0,0,20,0,0.5,0.1,0,10,20\n")
    for name, text in files.items():
        (run / name).write_text(text)
    capsys.readouterr()
    assert main(["compare", str(run), "--out", str(tmp_path / "c.png"), "--reps", "10"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{run}/{message}" in line


def test_the_console_script_refuses_a_huge_eval_json_without_traceback(tmp_path):
    ev = f'{{"coverage_median": {HUGE}, "coverage_iqr": 0, "coverage_mean": 0.5}}'
    run = fake_run(tmp_path / "run", "0,0,20,0,0.5,0.1,0,10,20\n", ev)
    proc = subprocess.run(
        [sys.executable, "-m", "harness.cli", "compare", str(run), "--out",
         str(tmp_path / "c.png")],
        capture_output=True, text=True, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert proc.returncode == 2
    assert "is too large for an evaluation" in one_error_line(proc.stderr)


def test_large_but_finite_numbers_still_compare(tmp_path, capsys):
    ev = '{"coverage_median": 0.5, "coverage_iqr": 0, "coverage_mean": 0.5, "wall_hits_mean": 1}'
    run = fake_run(tmp_path / "run", "0,0,9000000000000000000,0,0.5,0.1,0,10,20\n", ev)
    assert main(["compare", str(run), "--out", str(tmp_path / "c.png"), "--reps", "10"]) == 0


# ---------------------------------------------------------------------- 3. sweeps and SIGTERM
def sweep_args(tmp_path: Path) -> list[str]:
    (tmp_path / "tiny.yaml").write_text(TINY)
    (tmp_path / "space.yaml").write_text(SPACE)
    return ["sweep", str(tmp_path / "tiny.yaml"), "--space", str(tmp_path / "space.yaml"),
            "--trials", "2", "--sweeps-dir", str(tmp_path / "sweeps")]  # fmt: skip


def trial_states(folder: Path) -> list[str]:
    import optuna
    from optuna.storages.journal import JournalFileBackend

    storage = optuna.storages.JournalStorage(JournalFileBackend(str(folder / "journal.log")))
    return [t.state.name for t in optuna.load_study(study_name="tiny", storage=storage).trials]


@pytest.mark.parametrize(
    ("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["sigterm", "sigint"]
)
def test_a_signal_outside_training_stops_a_sweep_in_one_line(
    tmp_path, monkeypatch, capfd, signum, code
):
    from harness.training import sweep

    def objective(*args, **kwargs):  # the signal lands between trials' training
        os.kill(os.getpid(), signum)
        time.sleep(5)
        raise AssertionError("the signal did not stop the trial")

    monkeypatch.setattr(sweep, "_objective", objective)
    args = sweep_args(tmp_path)
    before = signal.getsignal(signal.SIGTERM)
    capfd.readouterr()
    assert main([*args, "--quiet"]) == code
    err = capfd.readouterr().err
    assert err.strip() == (
        f"harness: sweep stopped by {signal.Signals(signum).name}; continue it with the same "
        "command and --resume"
    )
    assert trial_states(tmp_path / "sweeps" / "tiny") == ["FAIL"]
    assert signal.getsignal(signal.SIGTERM) == before  # put back


@pytest.mark.slow
def test_sigterm_to_a_training_sweep_exits_143_with_one_line(tmp_path):
    # Long enough a trial to be stopped in training: its checkpoint is written, then it fails.
    longer = ["--set", "phases.only.timesteps=200000", "--set", "eval.every=100000"]
    cmd = [sys.executable, "-m", "harness.cli", *sweep_args(tmp_path), *longer]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    episodes = tmp_path / "sweeps" / "tiny" / "trial-0000" / "episodes.csv"
    deadline = time.monotonic() + 300
    while not (episodes.is_file() and episodes.read_text().count("\n") > 2):
        assert proc.poll() is None and time.monotonic() < deadline, "the trial never trained"
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "failed" not in err
    harness_lines = [line for line in err.splitlines() if line.startswith("harness:")]
    assert harness_lines == [
        "harness: sweep stopped by SIGTERM; continue it with the same command and --resume"
    ]
    assert trial_states(tmp_path / "sweeps" / "tiny") == ["FAIL"]
    assert list((episodes.parent / "checkpoints").glob("step-*"))


# ---------------------------------------------------------------------- 4. overrides of the map
@pytest.fixture
def run_on_a_map_file(tmp_path: Path) -> Path:
    """A run folder (untrained model) whose map file has since been deleted."""
    from harness.training.adapters import make_vec_env
    from harness.training.train import build_model

    config = load_config(with_map(tmp_path, str(tmp_path / "room.txt")))
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(config.to_yaml())
    venv = make_vec_env(config.env, config.vec.copies, 0, seed=0)
    build_model(config, venv).save(run / "model.zip")
    venv.close()
    (tmp_path / "room.txt").unlink()
    return run


def test_eval_with_another_map_does_not_need_the_runs_map_file(run_on_a_map_file, capsys):
    run = run_on_a_map_file
    capsys.readouterr()
    assert main(["eval", str(run), "--episodes", "1"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"'{run.parent / 'room.txt'}' is not 'random'" in line
    assert main(["eval", str(run), "--episodes", "1", "--set", "env.map=random", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 1
    # A bad replacement still names the override.
    assert main(["eval", str(run), "--set", "env.map=nowhere.txt"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "with --set env.map=nowhere.txt: env.map: 'nowhere.txt' is not 'random'" in line
