"""Seed groups, statistics over seeds (rliable) and Optuna sweeps on the embedded store and on a
real PostgreSQL server (from the ``pgserver`` wheel), end to end on tiny configs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from harness.cli import main
from harness.config import load_config
from harness.groups import GroupError, parse_seeds
from harness.stats import probability_of_improvement, seed_statistics
from harness.sweep import SweepError, load_space

ROOT = Path(__file__).resolve().parents[1]
TINY = (
    "name: tiny\n"
    "env: {height: 8, width: 8, n_agents: 2, max_steps: 20}\n"
    "vec: {copies: 1}\n"
    "algo: {net_arch: [16], buffer_size: 1000, learning_starts: 50}\n"
    "phases: [{name: only, timesteps: 240, exploration: {start: 1.0, end: 0.1, steps: 160}}]\n"
    "eval: {every: 80, episodes: 2}\n"
    "checkpoint: {every: 0}\n"
)
SPACE = (
    "algo.gamma: {float: [0.8, 0.99]}\n"
    "phases.only.learning_rate: {float: [1.0e-4, 1.0e-3], log: true}\n"
    "algo.policy: {choice: [MlpPolicy, DuelingMlpPolicy]}\n"
)


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


# ---------------------------------------------------------------------- seeds
@pytest.mark.parametrize(
    ("text", "seeds"), [("3", [0, 1, 2]), ("0,5,7", [0, 5, 7]), ("1", [0]), ("4, 2", [4, 2])]
)
def test_seeds_are_a_count_or_a_list(text, seeds):
    assert parse_seeds(text, 100) == seeds


@pytest.mark.parametrize("text", ["0,0", "a,b", "0", "-1,2", "1,200"])
def test_bad_seed_lists_are_errors(text):
    with pytest.raises(GroupError):
        parse_seeds(text, 100)


def test_seed_group_trains_evaluates_and_compares(tiny, tmp_path, capsys):
    runs = tmp_path / "runs"
    args = ["run", str(tiny), "--seeds", "2", "--jobs", "2", "--runs-dir", str(runs)]
    assert main(args) == 0
    (group,) = runs.iterdir()
    data = json.loads((group / "group.json").read_text())
    assert data["seeds"] == [0, 1] and data["threads_per_job"] == max(1, os.cpu_count() // 2)
    members = [group / r["run"] for r in data["runs"]]
    for seed, run in zip((0, 1), members, strict=True):
        assert (run / "model.zip").is_file()
        assert load_config(run / "config.yaml").seed == seed
    # Different seeds, different training episodes.
    assert (members[0] / "episodes.csv").read_text() != (members[1] / "episodes.csv").read_text()
    capsys.readouterr()
    assert main(["eval", str(group), "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(result["runs"]) == {m.name for m in members}
    assert result["coverage_mean_over_seeds"]["seeds"] == 2
    # Both seeds were tested on the same episodes.
    evals = [json.loads((m / "eval.json").read_text()) for m in members]
    assert evals[0]["seed"] == evals[1]["seed"]
    out = tmp_path / "cmp.png"
    assert (
        main(["compare", str(group), str(members[0]), "--labels", "g", "one", "--out", str(out)])
        == 0
    )
    text = capsys.readouterr().out
    assert "| g | 2 |" in text and "| one | 1 |" in text
    assert "1 seed: no interval" in text
    assert "P(g > one)" in text
    for png in (out, tmp_path / "cmp-intervals.png", tmp_path / "cmp-curves-ci.png"):
        assert png.read_bytes()[:4] == b"\x89PNG"


def test_statistics_over_seeds_hand_checked():
    # IQM of 4 values is the mean of the middle two; 1 seed: no interval.
    stats = seed_statistics({"a": [0.1, 0.2, 0.3, 0.9], "b": [0.5]}, reps=500)
    a, b = stats["a"], stats["b"]
    assert a.mean == pytest.approx(0.375) and a.iqm == pytest.approx(0.25)
    assert a.mean_ci is not None and a.mean_ci[0] <= a.mean <= a.mean_ci[1]
    assert a.mean_ci[0] >= 0.1 and a.mean_ci[1] <= 0.9
    assert b.seeds == 1 and b.mean_ci is None and b.iqm_ci is None and b.mean == 0.5
    # Every x beats every y: P(X > Y) = 1; identical groups: 0.5 (ties count half).
    p, ci = probability_of_improvement([0.8, 0.9, 0.85], [0.1, 0.2, 0.15], reps=500)
    assert p == 1.0 and ci is not None and ci[0] == pytest.approx(1.0)
    p, _ = probability_of_improvement([0.3, 0.3], [0.3, 0.3], reps=500)
    assert p == pytest.approx(0.5)


def test_compare_of_a_single_seed_says_the_interval_is_undefined():
    stats = seed_statistics({"only": [0.42]})
    assert stats["only"].mean_ci is None
    p, ci = probability_of_improvement([0.42], [0.3, 0.4])
    assert ci is None and 0 <= p <= 1
    assert np.isfinite(p)


# ---------------------------------------------------------------------- sweeps
@pytest.mark.parametrize(
    ("space", "message"),
    [
        ("algo.gama: {float: [0.8, 0.9]}\n", "space key algo.gama"),
        ("algo.gamma: {float: [0.8, 1.5]}\n", "algo.gamma=1.5"),
        ("algo.gamma: {float: [0.9, 0.8]}\n", "needs finite low < high"),
        ("algo.gamma: {uniform: [0.8, 0.9]}\n", "give exactly one of"),
        ("algo.gamma: {float: [0.0, 0.9], log: true}\n", "a log scale needs low > 0"),
        ("algo.policy: {choice: [MlpPolicy, Nope]}\n", "unknown policy 'Nope'"),
        ("seed: {grid: [0, 1]}\nalgo.gamma: {float: [0.8, 0.9]}\n", "must be all grids"),
        ("[1, 2]\n", "expected a mapping"),
        ("a: 1\na: 2\n", "duplicate key"),
    ],
)
def test_space_keys_are_checked_before_any_trial(tiny, tmp_path, capsys, space, message):
    path = tmp_path / "space.yaml"
    path.write_text(space)
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(path), "--trials", "2", "--sweeps-dir", str(sweeps)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error:") and message in err and "\n" not in err
    assert not sweeps.exists()


def test_sweep_on_the_embedded_store_runs_the_trials_asked_and_writes_the_best(tiny, tmp_path):
    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "3", "--sweeps-dir", str(sweeps)]
    assert main(args) == 0
    folder = sweeps / "tiny"
    best = json.loads((folder / "best.json").read_text())
    finished = best["trials"]["complete"] + best["trials"]["pruned"]
    assert finished == 3
    assert sorted(p.name for p in folder.glob("trial-*")) == [
        "trial-0000",
        "trial-0001",
        "trial-0002",
    ]
    config = load_config(folder / "best.yaml")
    for key, value in best["params"].items():
        section, name = key.split(".", 1)
        if section == "algo":
            assert getattr(config.algo, name) == pytest.approx(value)
    assert 0 <= best["value"] <= 1
    # The same command again is refused; --resume continues to a larger total.
    assert main(args) == 2
    assert main([*args[:5], "4", *args[6:], "--resume"]) == 0
    best = json.loads((folder / "best.json").read_text())
    assert best["trials"]["complete"] + best["trials"]["pruned"] == 4


def test_resume_marks_trials_a_dead_sweep_left_running_as_failed(tiny, tmp_path):
    import optuna
    from optuna.storages.journal import JournalFileBackend

    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    folder = tmp_path / "sweeps" / "tiny"
    folder.mkdir(parents=True)
    storage = optuna.storages.JournalStorage(JournalFileBackend(str(folder / "journal.log")))
    study = optuna.create_study(study_name="tiny", storage=storage, direction="maximize")
    study.ask()  # a trial that a killed process never finished
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "1", "--resume"]
    assert main([*args, "--sweeps-dir", str(tmp_path / "sweeps")]) == 0
    states = [t.state.name for t in optuna.load_study(study_name="tiny", storage=storage).trials]
    assert states[0] == "FAIL" and states.count("FAIL") == 1
    assert "COMPLETE" in states or "PRUNED" in states


@pytest.mark.slow
def test_two_workers_share_one_postgresql_study(tiny, tmp_path):
    import optuna
    import pgserver

    server = pgserver.get_server(str(tmp_path / "pg"), cleanup_mode="stop")
    try:
        server.psql("CREATE DATABASE sweeps;")
        socket_dir = server.get_uri().split("host=")[1]
        url = f"postgresql+psycopg://postgres@/sweeps?host={socket_dir}"
        space = tmp_path / "space.yaml"
        space.write_text(SPACE)
        cmd = [
            sys.executable, "-m", "harness.cli", "sweep", str(tiny), "--space", str(space),
            "--trials", "4", "--storage", url, "--study", "shared", "--pruner", "none",
            "--sweeps-dir", str(tmp_path / "sweeps"),
        ]  # fmt: skip
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        workers = [subprocess.Popen(cmd, cwd=ROOT, env=env, stderr=subprocess.PIPE) for _ in "ab"]
        for worker in workers:
            _, err = worker.communicate(timeout=600)
            assert worker.returncode == 0, err.decode()[-2000:]
        study = optuna.load_study(study_name="shared", storage=url)
        complete = [t for t in study.trials if t.state.name == "COMPLETE"]
        assert len(complete) == 4  # exactly what was asked, over both workers
        runs = [t.user_attrs["run"] for t in study.trials if "run" in t.user_attrs]
        assert len(runs) == 4 and len(set(runs)) == 4  # no trial ran twice
        # A worker that found the study full marked its extra trial skipped, without training.
        others = [t for t in study.trials if t.state.name != "COMPLETE"]
        assert all(t.state.name == "FAIL" and "skipped" in t.user_attrs for t in others)
        folder = tmp_path / "sweeps" / "shared"
        assert load_config(folder / "best.yaml").name == "tiny"
    finally:
        server.cleanup()


def test_load_space_reads_every_kind(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(SPACE + "phases.only.batch_size: {int: [16, 64], log: true}\n")
    dims = {d.key: d for d in load_space(path)}
    assert dims["algo.gamma"].values == (0.8, 0.99) and not dims["algo.gamma"].log
    assert dims["phases.only.learning_rate"].log
    assert dims["phases.only.batch_size"].kind == "int"
    assert dims["algo.policy"].values == ("MlpPolicy", "DuelingMlpPolicy")
    path.write_text("seed: {grid: [0, 1, 2]}\n")
    assert load_space(path)[0].kind == "grid"
    path.write_text("seed: {int: [0.5, 2]}\n")
    with pytest.raises(SweepError, match="int needs"):
        load_space(path)
