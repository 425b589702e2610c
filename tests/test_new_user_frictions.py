"""The frictions a new user hit (issue 73, and issue 72's overrides): a shortened phase's ε and β
schedules are named in one warning line; a seed group names its folder before its seeds start;
compare finds a run's only evaluation; intervals over fewer than 3 seeds carry a caution;
compare's curves mark phase boundaries; a one-seed interval chart draws the seed; a file plus
its ``--set``s is what is validated."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

from harness.cli import main
from harness.config.loading import load_config
from harness.config.schema import ConfigError
from harness.results.stats import markdown_table, plot_intervals, seed_statistics
from harness.training.checks import schedule_warnings
from tests.test_cli_eval import fake_run
from tests.test_seeds_and_sweeps import TINY

ROOT = Path(__file__).resolve().parents[1]
#: The coverage env's shipped configs (a PettingZoo env's config runs its own constructor).
CONFIGS = [
    p for p in sorted((ROOT / "configs").glob("*.yaml")) if "pettingzoo:" not in p.read_text()
]
DDQN = ROOT / "configs" / "ddqn_15x15.yaml"
#: A phase of 600 transitions: invalid alone under the default learning_starts of 1,000.
SHORT = (
    "name: short\n"
    "env: {height: 8, width: 8, n_agents: 2, max_steps: 20}\n"
    "vec: {copies: 1}\n"
    "algo: {net_arch: [16], buffer_size: 1000}\n"
    "phases: [{name: only, timesteps: 600}]\n"
    "checkpoint: {every: 0}\n"
)


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


# ---------------------------------------------------------------------- overrides, then validation
def test_a_set_repairs_a_file_that_is_invalid_alone(tmp_path):
    path = tmp_path / "short.yaml"
    path.write_text(SHORT)
    with pytest.raises(ConfigError, match=r"short.yaml: .*learning_starts: 1,000 is not below"):
        load_config(path)
    assert load_config(path, ["algo.learning_starts=100"]).algo.learning_starts == 100
    # The file with its --sets is what is checked, and named so when it is still invalid.
    with pytest.raises(ConfigError, match=r"with --set algo.learning_starts=700: .*700 is not"):
        load_config(path, ["algo.learning_starts=700"])
    with pytest.raises(ConfigError, match=r"with --set algo.gamma=0.5: .*1,000 is not below"):
        load_config(path, ["algo.gamma=0.5"])


def test_a_valid_file_with_its_sets_is_unchanged_by_the_order(tiny):
    # phases.only.timesteps reaches the file's phase; env.height a section the file has.
    config = load_config(tiny, ["phases.only.timesteps=300", "env.height=9"])
    assert config.phases[0].timesteps == 300 and config.env.height == 9


# ---------------------------------------------------------------------- schedules of a short phase
def test_a_shortened_phase_names_its_schedules_and_the_set_that_fits_them():
    config = load_config(DDQN, ["phases.0.timesteps=8000"])
    lines = schedule_warnings(config)
    assert lines == [
        "phases.0 (initial): exploration.steps is 300,000, more than the phase's 8,000 "
        "timesteps: exploration goes 1 -> 0.975 and never reaches 0.05 in it (to fit: --set "
        "phases.0.exploration.steps=8000)",
        "phases.0 (initial): beta.steps is 600,000, more than the phase's 8,000 timesteps: beta "
        "goes 0.4 -> 0.408 and never reaches 1 in it (to fit: --set phases.0.beta.steps=8000)",
    ]
    fitted = ["phases.0.timesteps=8000", "phases.0.exploration.steps=8000"]
    assert schedule_warnings(load_config(DDQN, fitted)) == lines[1:]


@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_no_shipped_config_is_warned_about(path):
    assert schedule_warnings(load_config(path)) == []


def test_harness_run_prints_the_warning_once_before_training(tiny, tmp_path, capsys):
    runs = tmp_path / "runs"
    args = ["run", str(tiny), "--set", "phases.only.timesteps=100", "--runs-dir", str(runs)]
    assert main([*args, "--no-progress"]) == 0
    err = capsys.readouterr().err.splitlines()
    warnings = [line for line in err if line.startswith("harness: warning: ")]
    assert warnings == [
        "harness: warning: phases.0 (only): exploration.steps is 160, more than the phase's 100 "
        "timesteps: exploration goes 1 -> 0.438 and never reaches 0.1 in it (to fit: --set "
        "phases.0.exploration.steps=100)"
    ]
    assert err.index(warnings[0]) < next(i for i, x in enumerate(err) if x.startswith("run folder"))


# ---------------------------------------------------------------------- a seed group's folder first
def test_a_seed_group_names_its_folder_before_its_seeds_start(tiny, tmp_path, capsys, monkeypatch):
    from harness.results import groups

    script = "import time; time.sleep(0.5)"
    monkeypatch.setattr(groups, "_start_command", lambda job, *a: [sys.executable, "-c", script])
    runs = tmp_path / "runs"
    assert main(["run", str(tiny), "--seeds", "2", "--jobs", "2", "--runs-dir", str(runs)]) == 0
    err = capsys.readouterr().err.splitlines()
    (group,) = runs.iterdir()
    assert err[0] == f"group folder: {group}"
    for seed in (0, 1):
        started = err.index(f"  seed {seed}: started (log: {group / f'tiny-seed{seed}.log'})")
        done = next(
            i for i, x in enumerate(err) if x.startswith(f"  seed {seed}, ") and "done" in x
        )
        assert 0 < started < done
    # --no-progress keeps the folder's line: it is where to look, not progress.
    assert main(["run", str(tiny), "--seeds", "1", "--no-progress", "--runs-dir", str(runs)]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("group folder: ") and not any("started" in x for x in err)


# ------------------------------------------------------------------ compare finds the evaluation
EVAL = '{"coverage_median": %s, "coverage_iqr": 0.1, "coverage_mean": %s, "wall_hits_mean": 1}'
EPISODES = "".join(f"{i},0,{20 * (i + 1)},0,0.5,0.1,0,10,20\n" for i in range(30))


def test_compare_reads_a_runs_only_evaluation_and_names_it(tmp_path, capsys):
    run = fake_run(tmp_path / "run", EPISODES)
    (run / "eval-20ep.json").write_text(EVAL % (0.625, 0.5))
    out = tmp_path / "c.png"
    assert main(["compare", str(run), "--out", str(out), "--reps", "10"]) == 0
    printed = capsys.readouterr().out
    assert "62.5%" in printed and "(eval-20ep.json)" in printed
    assert "each seed's mean over its eval-20ep.json episodes" in printed
    # eval.json, the standard one, wins over the others, and is not named.
    (run / "eval.json").write_text(EVAL % (0.25, 0.25))
    assert main(["compare", str(run), "--out", str(out), "--reps", "10"]) == 0
    printed = capsys.readouterr().out
    assert "25.0%" in printed and "62.5%" not in printed and "(eval" not in printed
    # Two others and no eval.json: which ones, and how to choose, in one line.
    (run / "eval.json").unlink()
    (run / "eval-5ep.json").write_text(EVAL % (0.75, 0.75))
    assert main(["compare", str(run), "--out", str(out), "--reps", "10"]) == 0
    assert "(no eval.json; has eval-20ep, eval-5ep: pick one with --eval eval-20ep)" in (
        capsys.readouterr().out
    )
    assert main(["compare", str(run), "--out", str(out), "--reps", "10", "--eval", "eval-5ep"]) == 0
    printed = capsys.readouterr().out
    assert "75.0%" in printed and "(eval-5ep.json)" not in printed  # asked for: not named again


# ---------------------------------------------------------------------- intervals over few seeds
TWO_PHASES = TINY.replace(
    "phases: [{name: only, timesteps: 240, exploration: {start: 1.0, end: 0.1, steps: 160}}]",
    "phases: [{name: a, timesteps: 300}, {name: b, timesteps: 200}, {name: c, timesteps: 100}]",
)


def two_phase_group(folder: Path, scores: list[float]) -> Path:
    """A seed group of hand-made runs of a three-phase config (phases end at 300 and 500 of 600
    transitions), each with its episodes, in-training evaluations and ``eval.json``."""
    runs = []
    for seed, score in enumerate(scores):
        run = folder / f"run-seed{seed}"
        episodes = "".join(
            f"{i},0,{20 * (i + 1)},0,{0.3 + 0.01 * i},0.1,0,10,20\n" for i in range(30)
        )
        fake_run(run, episodes, EVAL % (score, score))
        (run / "config.yaml").write_text(f"seed: {seed}\n{TWO_PHASES}")
        rows = "".join(f"{t},{0.3 + t / 2000}\n" for t in (100, 200, 300, 400, 500, 600))
        (run / "evaluations.csv").write_text("timesteps,coverage_median\n" + rows)
        runs.append({"seed": seed, "run": run.name})
    (folder / "group.json").write_text(json.dumps({"runs": runs}))
    return folder


def test_an_interval_over_2_seeds_is_printed_as_not_conclusive():
    scores = {"one": [0.5], "two": [0.55, 0.65], "three": [0.6, 0.7, 0.75]}
    table = markdown_table(seed_statistics(scores, reps=100), None).splitlines()
    rows = {line.split(" | ")[0].strip("| "): line for line in table if line.startswith("| ")}
    assert rows["two"].count("] (not conclusive)") == 2
    assert "not conclusive" not in rows["three"] and "not conclusive" not in rows["one"]
    assert table[-1] == (
        "Not conclusive: two (2 seeds); an interval needs at least 3 seeds (train more with "
        "harness run CONFIG --seeds N)"
    )
    assert "Not conclusive" not in markdown_table(seed_statistics({"a": [0.1, 0.2, 0.3]}), None)


def captured(monkeypatch) -> list[Any]:
    """The figures the results pictures write (each still written)."""
    from harness.results import plots, stats

    figures: list[Any] = []
    for module in (plots, stats):
        real = module.write_figure

        def keep(fig, *args, _real=real, **kwargs):
            figures.append(fig)
            return _real(fig, *args, **kwargs)

        monkeypatch.setattr(module, "write_figure", keep)
    return figures


def test_the_interval_picture_hatches_2_seeds_and_draws_1_seed_as_a_dot(tmp_path, monkeypatch):
    figures = captured(monkeypatch)
    scores = {"one": [0.5], "two": [0.55, 0.65], "three": [0.6, 0.7, 0.75]}
    plot_intervals(seed_statistics(scores, reps=100), tmp_path / "i.png")
    (fig,) = figures
    for ax in fig.axes:
        bars = {c.get_label(): c.patches[0] for c in ax.containers}
        assert set(bars) == {"one (1 seed: no interval)", "two (2 seeds: not conclusive)",
                             "three (3 seeds)"}  # fmt: skip
        assert bars["two (2 seeds: not conclusive)"].get_hatch() == "///"
        assert not bars["three (3 seeds)"].get_hatch()
        (dot,) = [line for line in ax.lines if line.get_marker() == "o"]
        assert list(dot.get_xdata()) == [50.0]
        assert ax.get_xlim()[0] < 50.0  # whole, not cut at the axis' end


def test_a_one_seed_interval_picture_is_not_empty(tmp_path, monkeypatch):
    figures = captured(monkeypatch)
    plot_intervals(seed_statistics({"solo": [0.42]}), tmp_path / "i.png")
    for ax in figures[0].axes:
        (dot,) = [line for line in ax.lines if line.get_marker() == "o"]
        assert list(dot.get_xdata()) == [pytest.approx(42.0)]
        low, high = ax.get_xlim()
        assert low < 42.0 < high


# ---------------------------------------------------------------------- phase boundaries
def test_compare_marks_phase_boundaries_and_caution_on_its_curves(tmp_path, monkeypatch, capsys):
    two = two_phase_group(tmp_path / "two", [0.55, 0.65])
    three = two_phase_group(tmp_path / "three", [0.6, 0.7, 0.75])
    figures = captured(monkeypatch)
    out = tmp_path / "cmp.png"
    args = ["compare", str(two), str(three), "--labels", "two", "three", "--out", str(out)]
    assert main([*args, "--reps", "50"]) == 0
    printed = capsys.readouterr().out
    assert "| two | 2 |" in printed and "Not conclusive: two (2 seeds)" in printed
    assert "; not conclusive: a group has under 3 seeds)" in printed  # P(two > three)
    learning, _intervals, _improvement, curves_ci = figures
    # Both panels of the learning curves and the curves with intervals: 300 and 500, dotted.
    for ax in [*learning.axes, *curves_ci.axes]:
        lines = [line for line in ax.lines if line.get_label() == "phase boundary"]
        assert len(lines) == 1 and lines[0].get_linestyle() == ":"
        verticals = [line for line in ax.lines if line.get_linestyle() == ":"]
        assert sorted(line.get_xdata()[0] for line in verticals) == [300, 500]
    (ax,) = curves_ci.axes
    labels = [text.get_text() for text in ax.get_legend().get_texts()]
    assert "two (2 seeds: not conclusive)" in labels and "three (3 seeds)" in labels
    assert [band.get_hatch() for band in ax.collections] == ["///", None]
