"""Seed groups, statistics over seeds (rliable) and Optuna sweeps on the embedded store and on a
real PostgreSQL server (from the ``pgserver`` wheel), end to end on tiny configs."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from harness.cli import main
from harness.config.loading import load_config
from harness.results.groups import GroupError, parse_seeds, threads_per_job
from harness.results.stats import (
    curve_with_ci,
    paired_difference,
    probability_of_improvement,
    seed_statistics,
)
from harness.training.sweep import SweepError, load_space
from tests.conftest import root_first_env, spawn

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


@pytest.mark.parametrize("text", ["1001", ",".join(map(str, range(1001)))])
def test_a_group_holds_at_most_1000_runs_given_as_a_count_or_a_list(text):
    with pytest.raises(GroupError, match="at most 1,000 runs in a group"):
        parse_seeds(text, 10**6)
    assert len(parse_seeds(",".join(map(str, range(1000))), 10**6)) == 1000


def failing_seed(line: str, code: int) -> list[str]:
    """A seed's command that prints ``line`` (after a progress bar's carriage return) and exits
    with ``code``, as a ``harness run`` refusing its arguments does."""
    script = f"import sys; print('seed starting\\r' + {line!r}, file=sys.stderr); sys.exit({code})"
    return [sys.executable, "-c", script]


def test_failed_seeds_print_their_own_error_line(tiny, tmp_path, capsys, monkeypatch):
    from harness.results import groups

    error = "harness: error: --set algo.threads is given twice"
    monkeypatch.setattr(groups, "_start_command", lambda job, *a: failing_seed(error, 2))
    runs = tmp_path / "runs"
    assert main(["run", str(tiny), "--seeds", "2", "--runs-dir", str(runs)]) == 1
    err = capsys.readouterr().err
    (group,) = runs.iterdir()
    for seed in (0, 1):
        line = f"  seed {seed}: tiny-seed{seed} failed (exit 2): --set algo.threads is given twice"
        assert line in err.splitlines(), err
    # A later attempt that dies without a word shows no stale reason: it points at its log.
    monkeypatch.setattr(groups, "_start_command", lambda job, *a: failing_seed("", 3))
    assert main(["run", "--resume", str(group)]) == 1
    err = capsys.readouterr().err
    assert f"  seed 0: tiny-seed0 failed (exit 3, see {group / 'tiny-seed0.log'})" in err
    assert "given twice" not in err


def test_jobs_share_the_cores_this_process_may_use():
    # A group started under `taskset -c 0` (or a Slurm job with one CPU) must not give each job
    # the machine's full core count: the share follows the CPU affinity.
    code = (
        "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
        "from harness.results.groups import threads_per_job; "
        "print(threads_per_job(1), threads_per_job(2))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "1"]
    assert threads_per_job(1, cores=4) == 4 and threads_per_job(3, cores=4) == 1


@pytest.mark.slow
def test_seed_group_trains_evaluates_and_compares(tiny, tmp_path, capsys):
    runs = tmp_path / "runs"
    args = ["run", str(tiny), "--seeds", "2", "--jobs", "2", "--runs-dir", str(runs)]
    assert main(args) == 0
    (group,) = runs.iterdir()
    # Each seed's end is reported with its progress, and the group's last validations.
    err = capsys.readouterr().err
    for seed in (0, 1):
        assert re.search(rf"seed {seed}, [\d,]+ transitions(, validation [\d.]+%)?: done", err)
    assert "test them: harness eval" in err
    data = json.loads((group / "group.json").read_text())
    assert data["seeds"] == [0, 1]
    assert data["threads_per_job"] == max(1, len(os.sched_getaffinity(0)) // 2)
    members = [group / r["run"] for r in data["runs"]]
    for seed, run in zip((0, 1), members, strict=True):
        assert (run / "model.zip").is_file()
        assert load_config(run / "config.yaml").seed == seed
    # Different seeds, different training episodes.
    assert (members[0] / "episodes.csv").read_text() != (members[1] / "episodes.csv").read_text()
    capsys.readouterr()
    tune = ["tune", str(group), "--temperatures", "0.5", "3", "--episodes", "2", "--write"]
    assert main(tune) == 0
    for run in members:  # every seed chose on the validation episodes and kept its choice
        chosen = json.loads((run / "tune.json").read_text())["chosen"]
        assert chosen in (0.5, 3.0)
        assert load_config(run / "config.yaml").eval.temperature == chosen
    capsys.readouterr()
    assert main(["eval", str(group), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)  # stdout is the JSON object alone
    assert set(result["runs"]) == set(result["evaluations"]) == {m.name for m in members}
    assert result["coverage_mean_over_seeds"]["seeds"] == 2
    # Both seeds were tested on the same episodes.
    evals = [json.loads((m / "eval.json").read_text()) for m in members]
    assert evals[0]["seed"] == evals[1]["seed"]
    for run, ev in zip(members, evals, strict=True):  # at the temperature its tune chose
        assert ev["temperature"] == json.loads((run / "tune.json").read_text())["chosen"]
    # Against a baseline: each run paired with it on its episodes, the differences over seeds.
    group_eval = (group / "group-eval.json").read_text()
    assert main(["eval", str(group), "--against", "frontier"]) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    over = result["coverage_mean_over_seeds"]
    low, high = (f"{100 * x:.1f} %" for x in over["mean_ci95"])
    assert printed[-2].startswith(
        f"== over 2 seeds: mean coverage {100 * over['mean']:.1f} % [{low}, {high}], IQM "
    )
    diffs = [json.loads((m / "against-frontier.json").read_text())["difference"] for m in members]
    over_seeds = json.loads((group / "group-against-frontier.json").read_text())
    assert over_seeds["differences"] == {m.name: d for m, d in zip(members, diffs, strict=True)}
    mean = over_seeds["difference_over_seeds"]["mean"]
    assert mean == pytest.approx(sum(diffs) / 2)
    assert printed[-1].startswith(
        "== over 2 seeds against frontier (paired on each run's episodes), mean difference "
        f"(points of coverage) {100 * mean:+.2f} ["
    )
    assert (group / "group-eval.json").read_text() == group_eval  # its own file, untouched
    steps = [json.loads((m / "against-frontier.json").read_text())["steps_to_99"] for m in members]
    if all(s is not None for s in steps):  # the speed over seeds, where every seed has one
        over_steps = over_seeds["steps_to_99_difference_over_seeds"]
        assert over_steps["mean"] == pytest.approx(sum(s["difference"] for s in steps) / 2)
    else:
        assert "steps_to_99_difference_over_seeds" not in over_seeds
    out = tmp_path / "cmp.png"
    # A run of the group named again is refused (it would count twice); a copy elsewhere is a
    # run of its own.
    assert main(["compare", str(group), str(members[0]), "--out", str(out)]) == 2
    one = tmp_path / "one"
    shutil.copytree(members[0], one)
    assert main(["compare", str(group), str(one), "--labels", "g", "one", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| g | 2 |" in text and "| one | 1 |" in text
    assert "1 seed: no interval" in text
    assert "P(g > one)" in text
    for png in (out, tmp_path / "cmp-intervals.png", tmp_path / "cmp-curves-ci.png"):
        assert png.read_bytes()[:4] == b"\x89PNG"


def test_intervals_repeat_and_leave_numpys_global_generator_alone():
    # rliable resamples from the global np.random whatever random_state it is given.
    scores = {"a": [0.1, 0.2, 0.3, 0.9, 0.45]}
    np.random.seed(123)  # noqa: NPY002
    before = np.random.get_state()[1].copy()  # noqa: NPY002
    first = seed_statistics(scores, reps=300)["a"]
    assert np.array_equal(np.random.get_state()[1], before)  # noqa: NPY002
    np.random.random_sample(7)  # noqa: NPY002 (a different global state)
    assert seed_statistics(scores, reps=300)["a"] == first
    p = probability_of_improvement([0.5, 0.6, 0.4], [0.45, 0.55, 0.5], reps=300)
    assert probability_of_improvement([0.5, 0.6, 0.4], [0.45, 0.55, 0.5], reps=300) == p


def test_a_groups_interval_does_not_depend_on_the_other_groups():
    alone = seed_statistics({"a": [0.1, 0.2, 0.3, 0.9]}, reps=300)["a"]
    beside = seed_statistics({"b": [0.5, 0.7, 0.6], "a": [0.1, 0.2, 0.3, 0.9]}, reps=300)["a"]
    assert alone == beside


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


def test_paired_difference_is_the_mean_difference_with_a_bootstrap_interval():
    # Differences 1, 2, 3: mean 2; a resampled mean lies within [1, 3] and the interval around 2.
    mean, low, high = paired_difference([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    assert mean == 2.0 and 1.0 <= low < 2.0 < high <= 3.0
    # A constant difference has a zero-width interval; the sign follows a - b.
    assert paired_difference([0.5, 0.75], [1.5, 1.75]) == (-1.0, -1.0, -1.0)
    # Reproducible from its seed.
    x, y = np.arange(10.0), np.arange(10.0)[::-1]
    assert paired_difference(x, y) == paired_difference(x, y)


def _fake_run(folder: Path, coverage_mean: float, curve: dict[int, float], seed: int = 0) -> Path:
    """A run folder with hand-made files: the config, episodes, evaluations and eval JSON."""
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(f"{TINY}seed: {seed}\n")
    (folder / "episodes.csv").write_text(
        "episode,phase,timesteps,copy,coverage,reward_mean,wall_hits,new_cells,length\n"
        "0,0,20,0,0.5,0.1,0,10,20\n"
    )
    rows = "".join(f"{t},2,0,{c},{c},{c},{c},0\n" for t, c in curve.items())
    (folder / "evaluations.csv").write_text(
        "timesteps,episodes,temperature,coverage_median,coverage_q1,coverage_q3,"
        "coverage_mean,wall_hits_mean\n" + rows
    )
    ev = {"coverage_median": coverage_mean, "coverage_iqr": 0.0, "coverage_mean": coverage_mean,
          "wall_hits_mean": 1.0}  # fmt: skip
    (folder / "eval.json").write_text(json.dumps(ev))
    return folder


def _fake_group(folder: Path, scores: list[float], curves: list[dict[int, float]]) -> Path:
    for k, (score, curve) in enumerate(zip(scores, curves, strict=True)):
        _fake_run(folder / f"run-seed{k}", score, curve, seed=k)
    runs = [{"seed": k, "run": f"run-seed{k}"} for k in range(len(scores))]
    (folder / "group.json").write_text(json.dumps({"runs": runs}))
    return folder


def _row(text: str, name: str) -> list[str]:
    (line,) = [line for line in text.splitlines() if line.startswith(f"| {name} |")]
    return [cell.strip() for cell in line.strip("|").split("|")]


def _interval(cell: str) -> tuple[float, float, float]:
    """``"37.5 % [20.0 %, 60.0 %]"`` -> (37.5, 20.0, 60.0)."""
    point, bounds = cell.split(" [")
    low, high = bounds.rstrip("]").split(", ")
    return tuple(float(x.rstrip(" %")) for x in (point, low, high))  # type: ignore[return-value]


def test_compare_of_hand_made_groups_reports_mean_iqm_intervals_and_improvement(tmp_path, capsys):
    # a: mean (0.1 + 0.2 + 0.3 + 0.9) / 4 = 37.5 %, IQM (middle two) (0.2 + 0.3) / 2 = 25 %.
    # b: 0.5..0.8: mean = IQM = 65 %. P(b > a): b beats 0.1, 0.2, 0.3 always, 0.9 never: 12/16.
    curves_a = [{100: 0.1, 200: 0.4}, {100: 0.2, 200: 0.5}, {100: 0.3, 200: 0.6},
                {100: 0.9, 200: 0.7, 300: 0.8}]  # fmt: skip
    a = _fake_group(tmp_path / "a", [0.1, 0.2, 0.3, 0.9], curves_a)
    b = _fake_group(tmp_path / "b", [0.5, 0.6, 0.7, 0.8], [{100: 0.5, 200: 0.6}] * 4)
    one = _fake_run(tmp_path / "one", 0.42, {100: 0.3, 200: 0.42})
    out = tmp_path / "cmp.png"
    assert main(["compare", str(a), str(b), str(one), "--labels", "a", "b", "one",
                 "--out", str(out), "--reps", "300"]) == 0  # fmt: skip
    text = capsys.readouterr().out
    row_a, row_b, row_one = _row(text, "a"), _row(text, "b"), _row(text, "one")
    assert row_a[1] == "4" and row_b[1] == "4" and row_one[1] == "1"
    mean, low, high = _interval(row_a[2])
    assert mean == 37.5 and 10.0 <= low < mean < high <= 90.0
    iqm, low, high = _interval(row_a[3])
    assert iqm == 25.0 and 10.0 <= low <= iqm <= high <= 90.0
    assert _interval(row_b[2])[0] == 65.0 and _interval(row_b[3])[0] == 65.0
    # One seed: the value, and no interval.
    assert row_one[2] == row_one[3] == "42.0 % (1 seed: no interval)"
    assert "P(a > b) = 25.0 % (95 % CI [" in text
    assert "P(a > one) = 25.0 % (no interval: a group has 1 seed)" in text
    assert "P(b > one) = 100.0 % (no interval: a group has 1 seed)" in text
    for suffix in ("", "-intervals", "-curves-ci", "-improvement"):
        assert (tmp_path / f"cmp{suffix}.png").read_bytes()[:4] == b"\x89PNG"


def test_compare_of_two_single_runs_gives_no_probability_of_improvement(tmp_path, capsys):
    # One number against one: P(X > Y) could only be 0, 50 or 100 %; it is not printed as one.
    one = _fake_run(tmp_path / "one", 0.42, {100: 0.3, 200: 0.42})
    two = _fake_run(tmp_path / "two", 0.40, {100: 0.3, 200: 0.40})
    out = tmp_path / "cmp.png"
    assert main(["compare", str(one), str(two), "--labels", "one", "two",
                 "--out", str(out), "--reps", "300"]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "P(one > two): not estimated (one seed in each group)" in text
    assert "P(one > two) =" not in text
    assert not (tmp_path / "cmp-improvement.png").exists()


def test_compare_reads_another_evaluation_when_asked(tmp_path, capsys):
    a = _fake_group(tmp_path / "a", [0.1, 0.2, 0.3], [{100: 0.1}] * 3)
    for k, score in enumerate([0.5, 0.6, 0.7]):  # the same runs evaluated on other episodes
        ev = {"coverage_median": score, "coverage_iqr": 0.0, "coverage_mean": score,
              "wall_hits_mean": 0.0}  # fmt: skip
        (a / f"run-seed{k}" / "eval-env.map-random.json").write_text(json.dumps(ev))
    out = str(tmp_path / "cmp.png")
    assert main(["compare", str(a), "--labels", "a", "--out", out, "--reps", "200"]) == 0
    assert _interval(_row(capsys.readouterr().out, "a")[2])[0] == 20.0
    args = ["compare", str(a), "--labels", "a", "--out", out, "--reps", "200"]
    assert main([*args, "--eval", "eval-env.map-random"]) == 0
    assert _interval(_row(capsys.readouterr().out, "a")[2])[0] == 60.0
    # A run without that evaluation says so; a name that is not an evaluation is one line, 2.
    assert main([*args, "--eval", "eval-seed7"]) == 0
    out = capsys.readouterr().out
    assert "(no eval-seed7.json; has eval, eval-env.map-random: pick one with --eval eval)" in out
    # The table's columns stay apart whatever the names' lengths.
    header, first = out.splitlines()[:2]
    assert header.split() == ["experiment", "run", "median", "IQR", "wall", "hits"]
    assert first.split()[:2] == ["a", "run-seed0"]
    assert main([*args, "--eval", "../config"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["harness: error: '../config' is not an evaluation's name: 'eval' (eval.json) "
                   "or 'eval-...' (eval-env.map-random.json and the like, as harness eval names "
                   "them)"]  # fmt: skip


def test_learning_curve_over_seeds_is_the_iqm_at_the_common_timesteps():
    curves = [
        (np.array([100, 200]), np.array([0.1, 0.4])),
        (np.array([100, 200]), np.array([0.2, 0.5])),
        (np.array([100, 200]), np.array([0.3, 0.6])),
        (np.array([100, 200, 300]), np.array([0.9, 0.7, 0.8])),  # 300: not every seed has it
    ]
    steps, iqm, band = curve_with_ci(curves, reps=500)
    assert steps.tolist() == [100, 200]
    assert iqm == pytest.approx([0.25, 0.55])  # middle two of each column
    assert band is not None and band.shape == (2, 2)
    assert np.all(band[0] <= iqm) and np.all(iqm <= band[1])
    steps, iqm, band = curve_with_ci(curves[:1])
    assert iqm == pytest.approx([0.1, 0.4]) and band is None  # one seed: no band


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
        ("seed: {grid: [0]}\n", "--trials 2: the grid of"),
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


def test_a_storage_url_that_cannot_be_opened_is_one_line_and_makes_no_folder(
    tiny, tmp_path, capsys
):
    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "2", "--sweeps-dir",
            str(sweeps), "--storage", "nosuchdb://host/db"]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error: --storage: cannot open") and "\n" not in err
    assert not sweeps.exists()


def test_sweep_on_the_embedded_store_runs_the_trials_asked_and_writes_the_best(
    tiny, tmp_path, capsys
):
    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "3", "--sweeps-dir", str(sweeps)]
    capsys.readouterr()
    assert main(args) == 0
    folder = sweeps / "tiny"
    best = json.loads((folder / "best.json").read_text())
    # One line per finished trial while the sweep runs: number, parameters, value, state, best.
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("trial ")]
    assert [x.split()[1] for x in lines] == ["1/3", "2/3", "3/3"]
    assert all(x.split()[2] in ("complete:", "pruned:") and "algo.gamma=" in x for x in lines)
    assert f"(best {best['value']:.3f}, trial {best['trial']})" in lines[-1]
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
    # best.yaml is the config the best trial trained with: `harness run best.yaml` repeats it.
    assert config == load_config(Path(best["run"]) / "config.yaml")
    # The same command again is refused; --resume continues to a larger total.
    assert main(args) == 2
    assert main([*args[:5], "4", *args[6:], "--resume", "--quiet"]) == 0
    assert not [x for x in capsys.readouterr().err.splitlines() if x.startswith("trial ")]
    best = json.loads((folder / "best.json").read_text())
    assert best["trials"]["complete"] + best["trials"]["pruned"] == 4
    with (folder / "trials.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["number"]) for r in rows] == [0, 1, 2, 3]
    assert {"value", "state", "params_algo.gamma", "user_attrs_run"} <= set(rows[0])
    top = max((r for r in rows if r["state"] == "COMPLETE"), key=lambda r: float(r["value"]))
    assert int(top["number"]) == best["trial"]


def _journal(folder: Path):
    import optuna
    from optuna.storages.journal import JournalFileBackend

    folder.mkdir(parents=True, exist_ok=True)
    return optuna.storages.JournalStorage(JournalFileBackend(str(folder / "journal.log")))


def test_resume_fails_the_trial_a_dead_sweep_left_running_and_runs_it_again(tiny, tmp_path):
    import optuna

    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    storage = _journal(tmp_path / "sweeps" / "tiny")
    study = optuna.create_study(study_name="tiny", storage=storage, direction="maximize")
    dead = study.ask()  # a trial that a killed process never finished
    dead.suggest_float("algo.gamma", 0.8, 0.99)
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "1", "--resume"]
    assert main([*args, "--sweeps-dir", str(tmp_path / "sweeps")]) == 0
    trials = optuna.load_study(study_name="tiny", storage=storage).trials
    assert [t.state.name for t in trials] == ["FAIL", "COMPLETE"]
    # Queued again with the dead trial's value, and not counted twice.
    assert trials[1].params["algo.gamma"] == trials[0].params["algo.gamma"]
    assert trials[1].system_attrs["failed_trial"] == 0


def _instant_training(monkeypatch, during=None) -> list:
    """Trials train at once: one evaluation (coverage 0.5 at 80 transitions) is reported, after
    ``during(run)`` if given. Returns the list of the configs trained, filled as they are."""
    import harness.training.train as train_module

    configs = []

    def train(config, run, progress_bar=True, command=None, on_evaluation=None, **_):
        configs.append(config)
        if during is not None:
            during(run)
        on_evaluation(80, {"coverage_median": 0.5})
        return SimpleNamespace(num_timesteps=80)

    monkeypatch.setattr(train_module, "train", train)
    return configs


def _one_trial_sweep(tiny, tmp_path) -> tuple:
    """The sweeps folder and the command line of a one-trial sweep of ``tiny`` over SPACE."""
    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    return sweeps, ["sweep", str(tiny), "--space", str(space), "--trials", "1",
                    "--sweeps-dir", str(sweeps)]  # fmt: skip


def test_a_second_sweep_of_a_live_study_is_refused_and_leaves_its_trial_alone(
    tiny, tmp_path, monkeypatch, capsys
):
    sweeps, args = _one_trial_sweep(tiny, tmp_path)
    seen = {}

    def during(run):  # while the first sweep trains its trial: a second one, new or --resume
        if not seen:
            seen["nested"] = True  # (today's main trains again in here: once)
            seen["codes"] = [main([*args, "--resume"]), main(args)]
            seen["err"] = capsys.readouterr().err
            trials = optuna.load_study(study_name="tiny", storage=_journal(sweeps / "tiny")).trials
            seen["states"] = [t.state.name for t in trials]

    import optuna

    _instant_training(monkeypatch, during)
    assert main(args) == 0
    assert seen["codes"] == [2, 2]
    lines = seen["err"].strip().splitlines()
    assert len(lines) == 2
    for line in lines:
        assert line == (
            f"harness: error: {sweeps / 'tiny'}: in use by process {os.getpid()} (a sweep of "
            "this study still going); wait for it to end or stop it first"
        )
    assert seen["states"] == ["RUNNING"]  # the first sweep's trial was not failed
    trials = optuna.load_study(study_name="tiny", storage=_journal(sweeps / "tiny")).trials
    assert [t.state.name for t in trials] == ["COMPLETE"]  # trained once, and it counts


def test_a_sweep_held_by_another_process_is_refused_and_taken_over_once_it_died(
    tiny, tmp_path, monkeypatch, capsys
):
    from harness.results.rundir import RunDir

    sweeps, args = _one_trial_sweep(tiny, tmp_path)
    _instant_training(monkeypatch)
    assert main(args) == 0
    # Another process holds the sweep folder as a sweep does (RunDir.lock: flock on .lock).
    code = (
        "import sys, time; from pathlib import Path; from harness.results.rundir import RunDir\n"
        "with RunDir(Path(sys.argv[1])).lock('a sweep of this study'):\n"
        "    print('held', flush=True); time.sleep(600)\n"
    )
    env = root_first_env()
    holder = spawn(
        [sys.executable, "-c", code, str(sweeps / "tiny")], env=env, stdout=subprocess.PIPE
    )
    try:
        assert holder.stdout.readline() == b"held\n"
        capsys.readouterr()
        resume = [*args[:5], "2", *args[6:], "--resume"]
        assert main(resume) == 2
        err = capsys.readouterr().err.strip()
        assert f"in use by process {holder.pid} (a sweep of this study still going)" in err
        assert "\n" not in err
    finally:
        holder.kill()
        holder.wait()
    assert main(resume) == 0  # the dead holder's lock is taken over
    with RunDir(sweeps / "tiny").lock():  # and released when the sweep ends
        pass


def test_the_overrides_are_part_of_a_study_and_a_resume_refuses_others(
    tiny, tmp_path, monkeypatch, capsys
):
    import optuna

    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--sweeps-dir", str(sweeps)]
    configs = _instant_training(monkeypatch)
    sets = ["--set", "env.max_steps=30", "--set", "eval.episodes=3"]
    assert main([*args, "--trials", "1", *sets]) == 0
    storage = _journal(sweeps / "tiny")
    study = optuna.load_study(study_name="tiny", storage=storage)
    assert study.user_attrs["overrides"] == ["env.max_steps=30", "eval.episodes=3"]
    capsys.readouterr()
    # Another task for the same study: refused in one line naming what differs, nothing changed.
    assert main([*args, "--trials", "2", "--resume", "--set", "env.max_steps=40"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "harness: error: study tiny was started with --set env.max_steps=30 eval.episodes=3; "
        "this command differs in env.max_steps=40 (study: 30), no eval.episodes (study: 3): "
        "give the study's --set, or a new --study"
    )
    assert len(optuna.load_study(study_name="tiny", storage=storage).trials) == 1
    assert main([*args, "--trials", "2", "--resume"]) == 2  # none at all differs too
    # The same overrides (in another order, written otherwise, with a machine-only key) go on.
    same = ["--set", "eval.episodes=3", "--set", "env.max_steps=3.0e1", "--set", "algo.threads=1"]
    assert main([*args, "--trials", "2", "--resume", *same]) == 0
    assert [c.env.max_steps for c in configs] == [30, 30]
    # A study from before studies kept their overrides resumes as it did, with any overrides.
    old = optuna.create_study(study_name="old", storage=storage, direction="maximize")
    old.ask()  # a trial a killed process left running
    assert main([*args, "--study", "old", "--trials", "1", "--resume", *sets]) == 0
    assert "overrides" not in optuna.load_study(study_name="old", storage=storage).user_attrs


def test_a_section_valued_choice_in_a_space_file_keeps_the_sections_other_keys(
    tiny, tmp_path, monkeypatch
):
    space = tmp_path / "space.yaml"
    space.write_text("env: {choice: [{n_agents: 3}]}\n")
    configs = _instant_training(monkeypatch)
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "1",
            "--sweeps-dir", str(tmp_path / "sweeps")]  # fmt: skip
    with pytest.warns(UserWarning, match="categorical distribution"):  # Optuna's, on dicts
        assert main(args) == 0
    (config,) = configs
    assert config.env.n_agents == 3
    assert (config.env.max_steps, config.env.height, config.env.width) == (20, 8, 8)  # kept


@pytest.fixture
def lose_the_database(monkeypatch):
    """``lost["now"] = True`` makes every later word of Optuna's RDBStorage with its database
    fail as a dropped connection does (SQLAlchemy's OperationalError, inside the session)."""
    import contextlib

    import optuna.storages._rdb.storage as rdb
    from sqlalchemy.exc import OperationalError

    real = rdb._create_scoped_session
    lost = {"now": False}

    @contextlib.contextmanager
    def session(*args, **kwargs):
        with real(*args, **kwargs) as s:
            if lost["now"]:
                raise OperationalError(
                    "SELECT", {}, ConnectionError("server closed the connection unexpectedly")
                )
            yield s

    monkeypatch.setattr(rdb, "_create_scoped_session", session)
    return lost


def test_a_lost_database_stops_the_sweep_in_one_line_and_resume_finishes_it(
    tiny, tmp_path, monkeypatch, capsys, lose_the_database
):
    import threading

    import optuna

    from harness.training import sweep

    monkeypatch.setattr(sweep, "HEARTBEAT_S", 1)  # a heartbeat falls while the database is gone
    thread_errors = []
    monkeypatch.setattr(threading, "excepthook", thread_errors.append)

    def during(run):
        if run.path.name == "trial-0001":  # the second trial: the database dies as it trains
            lose_the_database["now"] = True
            time.sleep(1.5)

    configs = _instant_training(monkeypatch, during)
    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "3", "--storage", url,
            "--sweeps-dir", str(sweeps)]  # fmt: skip
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if not x.startswith("trial ")]
    assert lines == [
        "harness: error: --storage: lost the sweep's database (OperationalError: server closed "
        "the connection unexpectedly); the trials' run folders are kept (the last one started: "
        f"{sweeps / 'tiny' / 'trial-0001'}); once the database is back, continue with the same "
        "command and --resume"
    ]
    assert "Traceback" not in err and thread_errors == []  # the heartbeat thread too
    assert (sweeps / "tiny" / "trial-0001" / "config.yaml").parent.is_dir()
    # The database is back: --resume fails the lost trial at once (its folder is held by no
    # process; no wait for the heartbeat's grace) and trains it again, to the 3 asked.
    lose_the_database["now"] = False
    assert main([*args, "--resume"]) == 0
    storage = optuna.storages.RDBStorage(url)
    trials = optuna.load_study(study_name="tiny", storage=storage).trials
    storage.engine.dispose()
    assert [t.state.name for t in trials] == ["COMPLETE", "FAIL", "COMPLETE", "COMPLETE"]
    assert trials[2].system_attrs["failed_trial"] == 1  # trial 1 again, same parameters
    assert trials[2].params == trials[1].params and len(configs) == 4


def sweep_args(tiny: Path, tmp_path: Path) -> list[str]:
    (tmp_path / "space.yaml").write_text(SPACE)
    return ["sweep", str(tiny), "--space", str(tmp_path / "space.yaml"),
            "--trials", "2", "--sweeps-dir", str(tmp_path / "sweeps")]  # fmt: skip


def trial_states(folder: Path) -> list[str]:
    import optuna

    return [
        t.state.name for t in optuna.load_study(study_name="tiny", storage=_journal(folder)).trials
    ]


@pytest.mark.parametrize(
    ("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["sigterm", "sigint"]
)
def test_a_signal_outside_training_stops_a_sweep_in_one_line(
    tiny, tmp_path, monkeypatch, capfd, signum, code
):
    from harness.training import sweep

    def objective(*args, **kwargs):  # the signal lands between trials' training
        os.kill(os.getpid(), signum)
        time.sleep(5)
        raise AssertionError("the signal did not stop the trial")

    monkeypatch.setattr(sweep, "_objective", objective)
    args = sweep_args(tiny, tmp_path)
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
def test_sigterm_to_a_training_sweep_exits_143_with_one_line(tiny, tmp_path):
    # Long enough a trial to be stopped in training: its checkpoint is written, then it fails.
    longer = ["--set", "phases.only.timesteps=200000", "--set", "eval.every=100000"]
    cmd = [sys.executable, "-m", "harness.cli", *sweep_args(tiny, tmp_path), *longer]
    proc = spawn(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
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


def test_a_dead_trial_of_a_seed_grid_is_trained_again_not_lost(tiny, tmp_path):
    import optuna

    space = tmp_path / "space.yaml"
    space.write_text("seed: {grid: [0, 1, 2]}\n")
    storage = _journal(tmp_path / "sweeps" / "tiny")
    grid = optuna.samplers.GridSampler({"seed": [0, 1, 2]}, seed=0)
    study = optuna.create_study(
        study_name="tiny", storage=storage, direction="maximize", sampler=grid
    )
    study.ask()  # the first grid point, left RUNNING by a killed process
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "3", "--resume"]
    assert main([*args, "--pruner", "none", "--sweeps-dir", str(tmp_path / "sweeps")]) == 0
    trials = optuna.load_study(study_name="tiny", storage=storage).trials
    complete = [t for t in trials if t.state.name == "COMPLETE"]
    assert sorted(t.params["seed"] for t in complete) == [0, 1, 2]  # every seed once
    trained = sorted(load_config(Path(t.user_attrs["run"]) / "config.yaml").seed for t in complete)
    assert trained == [0, 1, 2]


def test_a_pruned_trial_ends_cleanly_with_its_run_folder(tiny, tmp_path, monkeypatch, capsys):
    import optuna

    from harness.results.rundir import RunDir
    from harness.training import sweep

    # A pruner that stops every trial at its first report (no coverage reaches 101 %).
    monkeypatch.setattr(sweep, "make_pruner", lambda name: optuna.pruners.ThresholdPruner(1.01))
    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "2", "--sweeps-dir", str(sweeps)]
    assert main(args) == 0
    assert "no trial has completed yet" in capsys.readouterr().out
    trials = optuna.load_study(study_name="tiny", storage=_journal(sweeps / "tiny")).trials
    assert [t.state.name for t in trials] == ["PRUNED", "PRUNED"]  # both count, no more run
    for trial in trials:
        run = RunDir(Path(trial.user_attrs["run"]))
        assert load_config(run.config).name == "tiny"
        # Pruned at the first evaluation (80 transitions of 240): one row, no final model.
        assert len(run.evaluations_csv.read_text().splitlines()) == 2
        assert list(trial.intermediate_values) == [80] and not run.model.exists()
        with run.lock():  # released: the folder can be resumed or inspected
            pass
    assert not (sweeps / "tiny" / "best.yaml").exists()


@pytest.mark.slow
def test_seed_grid_on_two_local_workers_trains_every_seed_once(tiny, tmp_path):
    import optuna

    space = tmp_path / "space.yaml"
    space.write_text("seed: {grid: [3, 4, 5, 6]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "4", "--jobs", "2",
            "--pruner", "none", "--sweeps-dir", str(sweeps)]  # fmt: skip
    assert main(args) == 0
    folder = sweeps / "tiny"
    assert (folder / "worker-0.log").is_file() and (folder / "worker-1.log").is_file()
    trials = optuna.load_study(study_name="tiny", storage=_journal(folder)).trials
    complete = [t for t in trials if t.state.name == "COMPLETE"]
    assert sorted(t.params["seed"] for t in complete) == [3, 4, 5, 6]
    runs = {t.user_attrs["run"] for t in complete}
    assert len(runs) == 4
    # Each worker trained with its share of the cores; best.yaml is the plain config.
    threads = {load_config(Path(run) / "config.yaml").algo.threads for run in runs}
    assert threads == {max(1, (os.cpu_count() or 1) // 2)}
    assert load_config(folder / "best.yaml").algo.threads == load_config(tiny).algo.threads


@pytest.mark.slow
def test_two_workers_share_one_postgresql_study(tiny, tmp_path):
    import optuna
    import pgserver

    # Not under pytest's temporary folder: run as root, pgserver starts PostgreSQL as another
    # user, who must traverse the data folder's parents, and any pytest that starts meanwhile
    # (other sessions on the machine) makes /tmp/pytest-of-<user> private again.
    data = Path(tempfile.mkdtemp(prefix="harness-pg-"))
    server = pgserver.get_server(str(data / "pg"), cleanup_mode="stop")
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
        env = root_first_env()
        workers = [spawn(cmd, cwd=ROOT, env=env, stderr=subprocess.PIPE) for _ in "ab"]
        for worker in workers:
            _, err = worker.communicate(timeout=600)
            assert worker.returncode == 0, err.decode()[-2000:]
        storage = optuna.storages.RDBStorage(url)
        trials = optuna.load_study(study_name="shared", storage=storage).trials
        storage.engine.dispose()  # its connections closed before the server stops
        complete = [t for t in trials if t.state.name == "COMPLETE"]
        assert len(complete) == 4  # exactly what was asked, over both workers
        runs = [t.user_attrs["run"] for t in trials if "run" in t.user_attrs]
        assert len(runs) == 4 and len(set(runs)) == 4  # no trial ran twice
        # A worker that found the study full marked its extra trial skipped, without training.
        others = [t for t in trials if t.state.name != "COMPLETE"]
        assert all(t.state.name == "FAIL" and "skipped" in t.user_attrs for t in others)
        folder = tmp_path / "sweeps" / "shared"
        assert load_config(folder / "best.yaml").name == "tiny"
    finally:
        server.cleanup()
        shutil.rmtree(data, ignore_errors=True)


@pytest.mark.slow
def test_a_sweep_whose_postgresql_server_dies_stops_in_one_line_and_resumes(tmp_path):
    import optuna
    import pgserver
    from pgserver._commands import pg_ctl

    data = Path(tempfile.mkdtemp(prefix="harness-pg-"))  # (see the test above for why not tmp)
    server = pgserver.get_server(str(data / "pg"), cleanup_mode="stop")
    try:
        server.psql("CREATE DATABASE sweeps;")
        socket_dir = server.get_uri().split("host=")[1]
        url = f"postgresql+psycopg://postgres@/sweeps?host={socket_dir}"
        config = tmp_path / "long.yaml"  # long enough to lose the server in the middle
        config.write_text(TINY.replace("timesteps: 240", "timesteps: 1200"))
        space = tmp_path / "space.yaml"
        space.write_text("algo.gamma: {float: [0.8, 0.99]}\n")
        sweeps = tmp_path / "sweeps"
        cmd = [sys.executable, "-m", "harness.cli", "sweep", str(config), "--space", str(space),
               "--trials", "1", "--storage", url, "--study", "s", "--pruner", "none",
               "--sweeps-dir", str(sweeps)]  # fmt: skip
        env = root_first_env()
        sweep = spawn(cmd, cwd=ROOT, env=env, stderr=subprocess.PIPE)
        evaluations = sweeps / "s" / "trial-0000" / "evaluations.csv"
        deadline = time.monotonic() + 300
        while not (evaluations.is_file() and len(evaluations.read_text().splitlines()) >= 2):
            assert sweep.poll() is None and time.monotonic() < deadline
            time.sleep(0.2)
        # The server crashes (immediate shutdown: every connection dropped) mid-trial.
        pg_ctl(["-m", "immediate", "stop"], pgdata=server.pgdata, user=server.system_user)
        _, err = sweep.communicate(timeout=300)
        text = err.decode()
        assert sweep.returncode == 2, text[-3000:]
        assert "Traceback" not in text, text[-3000:]
        errors = [x for x in text.splitlines() if x.startswith("harness: error:")]
        assert len(errors) == 1 and "lost the sweep's database" in errors[0]
        assert "trial-0000" in errors[0] and evaluations.is_file()  # its run folder kept
        # The server is back: the same command with --resume finishes the sweep.
        with server._lock:
            server.ensure_postgres_running()
        done = subprocess.run([*cmd, "--resume"], cwd=ROOT, env=env, capture_output=True,
                              timeout=600)  # fmt: skip
        assert done.returncode == 0, done.stderr.decode()[-3000:]
        storage = optuna.storages.RDBStorage(url)
        trials = optuna.load_study(study_name="s", storage=storage).trials
        storage.engine.dispose()
        assert [t.state.name for t in trials] == ["FAIL", "COMPLETE"]
        assert trials[1].params == trials[0].params  # the lost trial, trained again
        assert load_config(sweeps / "s" / "best.yaml").name == "tiny"
    finally:
        server.cleanup()
        shutil.rmtree(data, ignore_errors=True)


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


def test_compare_labels_groups_by_their_config_name_and_keeps_two_groups_apart(tmp_path, capsys):
    a = _fake_group(tmp_path / "tiny-20260101T000000Z", [0.1, 0.2, 0.3], [{100: 0.1}] * 3)
    b = _fake_group(tmp_path / "tiny-20260102T000000Z", [0.5, 0.6, 0.7], [{100: 0.5}] * 3)
    out = str(tmp_path / "cmp.png")
    assert main(["compare", str(a), str(b), "--out", out, "--reps", "200"]) == 0
    text = capsys.readouterr().out
    name = load_config(a / "run-seed0" / "config.yaml").name
    # Labelled by the config's name, not the timestamped folder; the second group apart.
    assert _interval(_row(text, name)[2])[0] == 20.0
    assert _interval(_row(text, f"{name}#2")[2])[0] == 60.0
    assert "tiny-2026" not in text.split("\n\n")[-1]  # the table over seeds


def test_seed_progress_reads_the_last_complete_rows_of_the_run_logs(tmp_path):
    from harness.results.groups import Job, seed_progress, seed_progress_value
    from harness.results.rundir import RunDir

    run = RunDir(tmp_path / "run")
    run.path.mkdir()
    job = Job(3, run)
    assert seed_progress(job) == "seed 3, starting"
    run.episodes_csv.write_text(
        "episode,phase,timesteps,copy,coverage,reward_mean,wall_hits,new_cells,length\n"
        "0,initial,1200,0,0.5,1.0,0,3;4,150\n"
        "1,initial,2400,0,0.6,1.0,0,3;4,150\n"
        "2,initial,36"  # being written: skipped
    )
    assert seed_progress(job) == "seed 3, 2,400 transitions"
    run.evaluations_csv.write_text(
        "timesteps,episodes,temperature,coverage_median,coverage_q1,coverage_q3,"
        "coverage_mean,wall_hits_mean\n2400,10,0.0,0.625,0.5,0.7,0.6,0.0\n"
    )
    assert seed_progress(job) == "seed 3, 2,400 transitions, validation 62.5%"
    assert seed_progress_value(run) == 0.625


def test_compare_refuses_a_run_named_twice(tmp_path, capsys):
    a = _fake_group(tmp_path / "a", [0.1, 0.2, 0.3], [{100: 0.1}] * 3)
    out = str(tmp_path / "cmp.png")
    for args in ([str(a), str(a)], [str(a), str(a / "run-seed1")]):
        assert main(["compare", *args, "--out", out]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("harness: error:") and "run-seed" in err
        assert "is compared twice" in err and "\n" not in err
    assert not (tmp_path / "cmp.png").exists()


@pytest.mark.parametrize("study", ["../../x", "/tmp/abs", "a/b", ".hidden"])
def test_a_study_is_a_name_not_a_path(tiny, tmp_path, capsys, study):
    space = tmp_path / "space.yaml"
    space.write_text(SPACE)
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "1", "--sweeps-dir",
            str(sweeps), "--study", study]  # fmt: skip
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error: --study") and "a study name must be" in err
    assert "\n" not in err and not sweeps.exists()


def test_a_group_missing_a_seed_gets_no_group_eval(tmp_path):
    from harness.commands import evaluate_group

    group = _fake_group(tmp_path / "g", [0.1, 0.2, 0.3], [{100: 0.1}] * 3)
    for k in range(3):  # the keys group-eval.json keeps of each run's evaluation
        path = group / f"run-seed{k}" / "eval.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "seed": 1_000_003}))
    evaluated = []
    result, saved, missing = evaluate_group(group, evaluated.append)
    assert missing == [] and saved == group / "group-eval.json" and len(evaluated) == 3
    assert result["coverage_mean_over_seeds"]["seeds"] == 3
    saved.unlink()
    shutil.rmtree(group / "run-seed1")
    result, saved, missing = evaluate_group(group, evaluated.append)
    assert (result, saved, missing) == (None, None, ["run-seed1"])
    assert not (group / "group-eval.json").exists()


def test_group_files_are_named_after_each_runs_evaluation():
    from harness.results.groups import GROUP_EVAL_FILE, group_against_file, group_result_file
    from harness.results.rundir import against_filename, result_filename

    # The standard names, as they were.
    assert GROUP_EVAL_FILE == "group-eval.json"
    assert group_against_file("frontier_pocket") == "group-against-frontier_pocket.json"
    # Any other evaluation: the run's own file name after "group-".
    assert group_result_file(result_filename("eval", [], episodes=30)) == "group-eval-30ep.json"
    against = against_filename("frontier_pocket", [], episodes=30)
    assert group_result_file(against) == "group-against-frontier_pocket-30ep.json"
    overrides = ["env.max_steps=10"]
    name = result_filename("eval", overrides, "model", 2, "7")
    assert group_result_file(name) == "group-eval-2ep_seed7_env.max_steps-10.json"


def test_a_non_standard_group_evaluation_reads_and_writes_its_own_files(tmp_path):
    from harness.commands import evaluate_group

    group = _fake_group(tmp_path / "g", [0.1, 0.2, 0.3], [{100: 0.1}] * 3)
    scores = [0.25, 0.5, 0.6]  # each run's 30-episode evaluation, beside its eval.json
    for k, score in enumerate(scores):
        ev = {"seed": 1_000_003, "coverage_median": score, "coverage_iqr": 0.0,
              "coverage_mean": score, "wall_hits_mean": 2.0, "episodes": 30}  # fmt: skip
        (group / f"run-seed{k}" / "eval-30ep.json").write_text(json.dumps(ev))
    evaluated = []
    result, saved, missing = evaluate_group(group, evaluated.append, episodes=30)
    assert missing == [] and saved == group / "group-eval-30ep.json" and len(evaluated) == 3
    written = json.loads(saved.read_text())
    assert written["coverage_mean_over_seeds"]["seeds"] == 3
    # The 30-episode numbers, not eval.json's 0.1, 0.2, 0.3: (0.25 + 0.5 + 0.6) / 3.
    assert written["coverage_mean_over_seeds"]["mean"] == pytest.approx(1.35 / 3)
    assert [r["coverage_mean"] for r in written["runs"].values()] == scores
    assert not (group / "group-eval.json").exists()
    saved.unlink()
    shutil.rmtree(group / "run-seed2")  # a missing seed: no group file, as for the standard one
    result, saved, missing = evaluate_group(group, evaluated.append, episodes=30)
    assert (result, saved, missing) == (None, None, ["run-seed2"])
    assert sorted(p.name for p in group.glob("group-*")) == []


def test_a_trial_skipped_because_the_study_is_full_says_nothing():
    # Another worker's trials made up the total: Optuna's failure warning (with its traceback)
    # is left out and the progress line is not printed; a real failure still shows.
    import logging

    from harness.training.sweep import StudyFull, _QuietInterrupts, _Reporter

    def record(error: BaseException) -> logging.LogRecord:
        return logging.LogRecord(
            "optuna.study._optimize", logging.WARNING, __file__, 1, "Trial 2 failed", None,
            (type(error), error, None),
        )  # fmt: skip

    quiet = _QuietInterrupts()
    assert not quiet.filter(record(StudyFull(2)))
    assert quiet.filter(record(RuntimeError("boom")))  # a failure after it is still said
    lines = []
    reporter = _Reporter(lines.append, total=1)
    reporter(None, SimpleNamespace(user_attrs={"skipped": "the study already had its 1 trials"}))
    assert lines == []
