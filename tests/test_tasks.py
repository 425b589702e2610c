"""The task interface (issue 72): the coverage env and any PettingZoo env answer the same
questions (harness/tasks), one episode loop plays both, and a user's constructor runs where a run
starts, once, never while a config is validated."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from harness.cli import main
from harness.config.loading import config_from_dict, load_config
from harness.config.schema import EnvConfig
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes, summarize
from harness.tasks import (
    TASKS,
    headline,
    selection_score,
    task_of,
    task_of_columns,
    task_of_summary,
)
from harness.tasks.coverage import CoverageTask, EpisodeResult
from harness.tasks.pettingzoo import PettingZooTask, TeamEpisodeResult
from harness.training.checks import checked_config
from tests.conftest import one_error_line, root_first_env
from tests.envs.meet import MeetEnv

ROOT = Path(__file__).resolve().parents[1]
MEET = ROOT / "tests" / "data" / "meet.yaml"

#: Calls of :func:`counted` so far.
CALLS: list[dict] = []


def counted(**kwargs):
    """The meet env, each call of its constructor counted."""
    CALLS.append(kwargs)
    return MeetEnv(**kwargs)


def meet(make: str) -> dict:
    raw = yaml.safe_load(MEET.read_text())
    raw["env"]["pettingzoo"]["make"] = make
    return raw


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])
    CALLS.clear()


def test_validation_runs_no_constructor_and_the_run_start_runs_it_once():
    config = config_from_dict(meet("tests.test_tasks:counted"))
    assert CALLS == []  # validated, its sections resolved: the user's code has not run
    again = config_from_dict(yaml.safe_load(config.to_yaml()))
    assert CALLS == [] and again.env == config.env
    checked_config(config, "meet.yaml")  # the run's start: the env built once, its fit checked
    assert len(CALLS) == 1
    assert config.env.n_agents == 2 and config.n_slots == 4
    checked_config(config, "meet.yaml")
    assert len(CALLS) == 1  # (its spaces are kept)


def test_a_constructor_that_raises_leaves_no_run_folder(tmp_path, capsys):
    raw = meet("tests.envs.odd:failing")
    config_from_dict(raw)  # validation alone does not call it: nothing to refuse yet
    path = tmp_path / "failing.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["run", str(path), "--runs-dir", str(tmp_path / "runs")]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "env.pettingzoo" in line and "no such world" in line, line
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("command", ["eval", "render"])
def test_a_constructor_that_raises_at_an_evaluations_start_is_one_line(tmp_path, capsys, command):
    # No run built the env before: the evaluation's episode loop is where it is first built.
    path = tmp_path / "failing.yaml"
    path.write_text(yaml.safe_dump(meet("tests.envs.odd:failing")))
    args = [command, "--policy", "random", "--config", str(path)]
    if command == "render":
        args += ["--out", str(tmp_path / "out.png")]
    assert main(args) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "env.pettingzoo" in line and "no such world" in line, line


def test_what_the_spaces_decide_is_refused_at_the_run_start_in_one_line(tmp_path):
    raw = meet("tests.envs.odd:block")
    raw["algo"]["sharing"] = "shared_id"
    config = config_from_dict(raw)  # (the observation's shape is the env's: not known yet)
    with pytest.raises(ValueError, match=r"algo\.sharing: shared_id: .*has 4 dimensions"):
        checked_config(config, "block.yaml")


def test_each_env_section_has_its_task():
    assert isinstance(task_of(EnvConfig()), CoverageTask)
    config = config_from_dict(meet("tests.envs.meet:parallel_env"))
    task = task_of(config.env)
    assert isinstance(task, PettingZooTask)
    assert task.agents == ("walker_0", "walker_1") and task.n_agents == 2
    assert {cls.name for cls in TASKS} == {"coverage", "pettingzoo"}
    for cls in TASKS:
        assert task_of_columns(cls.episode_columns) is cls
        assert task_of_columns(cls.evaluation_columns) is cls
    assert task_of_columns(("a", "b")) is None


def test_one_loop_plays_both_tasks_and_each_summary_names_its_task():
    coverage = run_episodes(make_baseline("random", 0), EnvConfig(n_agents=2, max_steps=20), 3, 0)
    assert all(type(r) is EpisodeResult for r in coverage)
    summary = summarize(coverage)
    assert task_of_summary(summary) is CoverageTask and "source" not in summary
    assert headline(summary) == summary["coverage_median"]
    assert selection_score(summary) == CoverageTask.selection_score(summary)

    env = config_from_dict(meet("tests.envs.meet:parallel_env")).env
    team = run_episodes(make_baseline("random", 0), env, 3, 0, copies=2)
    assert all(type(r) is TeamEpisodeResult for r in team)
    summary = summarize(team)
    assert task_of_summary(summary) is PettingZooTask and summary["source"] == "pettingzoo"
    assert headline(summary, "mean") == summary["return_mean"] == selection_score(summary)
    # The same episodes whatever the copies side by side, in the one loop.
    alone = run_episodes(make_baseline("random", 0), env, 3, 0, copies=1)
    assert [r.length for r in alone] == [r.length for r in team]


def test_the_coverage_summary_keeps_its_keys():
    results = run_episodes(make_baseline("random", 0), EnvConfig(n_agents=2, max_steps=20), 2, 0)
    assert set(summarize(results)) == {
        "episodes",
        "coverage_median",
        "coverage_mean",
        "coverage_mean_ci",
        "bound",
        "efficiency",
        "coverage_iqr",
        "coverage_q1",
        "coverage_q3",
        "coverage_min",
        "coverage_max",
        "coverage_at_median",
        "steps_to_90",
        "steps_to_99",
        "wall_hits_mean",
        "wall_hits_episodes",
        "per_agent",
    }


def test_a_saved_pettingzoo_config_loads_without_building_its_env(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(meet("tests.test_tasks:counted")))
    config = load_config(path)
    assert CALLS == [] and config.env.pettingzoo.make == "tests.test_tasks:counted"
