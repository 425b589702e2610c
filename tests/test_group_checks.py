"""A seed group's file is held to its runs, and ``harness eval GROUP`` prints what it says:
``group.json`` naming a run or a seed twice, or a seed its run did not train, is refused in one
line; ``--json`` prints one JSON object; ``--plot X.png`` draws one picture per seed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from harness.cli import main
from tests.conftest import one_error_line
from tests.test_seeds_and_sweeps import TINY


@pytest.fixture(scope="module")
def trained_group(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A group of seeds 3 and 5 of the tiny config (trained once, read only)."""
    folder = tmp_path_factory.mktemp("group")
    config = folder / "tiny.yaml"
    config.write_text(TINY)
    runs = folder / "runs"
    args = ["run", str(config), "--seeds", "3,5", "--jobs", "2", "--runs-dir", str(runs),
            "--no-progress"]  # fmt: skip
    assert main(args) == 0
    (group,) = runs.iterdir()
    return group


@pytest.fixture
def group(trained_group: Path, tmp_path: Path) -> Path:
    copy = tmp_path / trained_group.name
    shutil.copytree(trained_group, copy)
    return copy


def test_eval_group_json_is_one_json_object_and_plot_draws_each_seed(group, tmp_path, capsys):
    plot = tmp_path / "pics" / "cov.png"
    plot.parent.mkdir()
    assert main(["eval", str(group), "--episodes", "3", "--json", "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    result = json.loads(out)  # nothing else on stdout
    names = [entry["run"] for entry in json.loads((group / "group.json").read_text())["runs"]]
    assert list(result["evaluations"]) == names
    assert all(ev["episodes"] == 3 for ev in result["evaluations"].values())
    assert sorted(p.name for p in plot.parent.iterdir()) == ["cov-seed3.png", "cov-seed5.png"]
    for picture in plot.parent.iterdir():
        assert picture.read_bytes()[:4] == b"\x89PNG"


def _edit_group_file(group: Path, edit) -> None:
    path = group / "group.json"
    data = json.loads(path.read_text())
    edit(data["runs"])
    path.write_text(json.dumps(data))


def _refused_eval(group: Path, capsys) -> str:
    assert main(["eval", str(group), "--episodes", "2"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    return one_error_line(captured.err)


def test_a_group_file_naming_one_run_twice_is_refused(group, capsys):
    def twice(runs: list) -> None:
        runs[1]["run"] = runs[0]["run"]

    _edit_group_file(group, twice)
    line = _refused_eval(group, capsys)
    assert "group.json: names run" in line and "twice" in line


def test_a_group_file_naming_one_seed_twice_is_refused(group, capsys):
    def twice(runs: list) -> None:
        runs[1]["seed"] = runs[0]["seed"]

    _edit_group_file(group, twice)
    assert "group.json: names seed 3 twice" in _refused_eval(group, capsys)


def test_a_group_file_whose_seeds_disagree_with_its_runs_is_refused(group, capsys):
    def swapped(runs: list) -> None:
        runs[0]["seed"], runs[1]["seed"] = runs[1]["seed"], runs[0]["seed"]

    _edit_group_file(group, swapped)
    line = _refused_eval(group, capsys)
    assert "as seed 5, but its config.yaml trains seed 3" in line
    assert not (group / "group-eval.json").exists()


def _members(group: Path) -> list[Path]:
    """The run folders ``group.json`` names, in seed order."""
    return [
        group / entry["run"] for entry in json.loads((group / "group.json").read_text())["runs"]
    ]


def test_a_group_evaluated_on_fewer_episodes_gets_its_own_numbers_over_seeds(group, capsys):
    # --episodes 3 --against frontier: each run's eval-3ep.json and against-frontier-3ep.json,
    # their numbers over seeds in group-eval-3ep.json and group-against-frontier-3ep.json, and
    # the standard group-eval.json and group-against-frontier.json left alone (not written).
    assert main(["eval", str(group), "--episodes", "3", "--against", "frontier"]) == 0
    captured = capsys.readouterr()
    printed = captured.out.strip().splitlines()
    runs = _members(group)
    evals = [json.loads((run / "eval-3ep.json").read_text()) for run in runs]
    assert [ev["episodes"] for ev in evals] == [3, 3]
    over = json.loads((group / "group-eval-3ep.json").read_text())
    keys = ("seed", "coverage_mean", "coverage_median", "wall_hits_mean")
    assert over["runs"] == {
        r.name: {k: ev[k] for k in keys} for r, ev in zip(runs, evals, strict=True)
    }
    # By hand: the runs' mean coverage, each the mean of its 3 episodes, averaged over 2 seeds.
    means = [sum(ev["coverage"]) / 3 for ev in evals]
    assert [ev["coverage_mean"] for ev in evals] == pytest.approx(means)
    mean = over["coverage_mean_over_seeds"]["mean"]
    assert over["coverage_mean_over_seeds"]["seeds"] == 2
    assert mean == pytest.approx(sum(means) / 2)
    assert printed[-2].startswith(f"== over 2 seeds: mean coverage {100 * mean:.1f} % [")
    comparisons = [json.loads((run / "against-frontier-3ep.json").read_text()) for run in runs]
    for ev, comparison in zip(evals, comparisons, strict=True):  # paired on the run's episodes
        assert comparison["coverage"] == ev["coverage"] and comparison["episodes"] == 3
        theirs = comparison["against_coverage"]
        by_hand = sum(a - b for a, b in zip(ev["coverage"], theirs, strict=True)) / 3
        assert comparison["difference"] == pytest.approx(by_hand)
    against = json.loads((group / "group-against-frontier-3ep.json").read_text())
    diffs = [c["difference"] for c in comparisons]
    assert against["differences"] == {r.name: d for r, d in zip(runs, diffs, strict=True)}
    difference = against["difference_over_seeds"]["mean"]
    assert difference == pytest.approx(sum(diffs) / 2)
    assert printed[-1].startswith(
        "== over 2 seeds against frontier (paired on each run's episodes), mean difference "
        f"(points of coverage) {100 * difference:+.2f} ["
    )
    assert f"saved {group / 'group-eval-3ep.json'}" in captured.err
    assert f"saved {group / 'group-against-frontier-3ep.json'}" in captured.err
    written = sorted(p.name for p in group.glob("group-*.json"))
    assert written == ["group-against-frontier-3ep.json", "group-eval-3ep.json"]
    assert not (group / "group-eval.json").exists()


def test_a_group_evaluated_with_a_seed_and_overrides_names_its_files_after_them(group, capsys):
    # Each run's file says the episodes, the seed and the --set; the group's file is named after
    # it, and --json gives its numbers over seeds.
    args = ["eval", str(group), "--episodes", "2", "--seed", "7", "--set", "env.max_steps=10"]
    assert main([*args, "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    runs = _members(group)
    evals = [json.loads((run / "eval-2ep_seed7_env.max_steps-10.json").read_text()) for run in runs]
    assert [(ev["seed"], ev["episodes"]) for ev in evals] == [(7, 2), (7, 2)]
    over = json.loads((group / "group-eval-2ep_seed7_env.max_steps-10.json").read_text())
    means = [ev["coverage_mean"] for ev in evals]
    assert over["coverage_mean_over_seeds"]["mean"] == pytest.approx(sum(means) / 2)
    assert result["coverage_mean_over_seeds"] == over["coverage_mean_over_seeds"]
    assert sorted(p.name for p in group.glob("group-*.json")) == [
        "group-eval-2ep_seed7_env.max_steps-10.json"
    ]


def test_a_group_against_set_is_over_seeds_in_files_of_its_own(group, capsys):
    # frontier reads no eval.rollout: the same differences as plain --against, in each run's
    # against-frontier-2ep+eval.rollout.after-0.5.json and the group's file named after it.
    plain = ["eval", str(group), "--episodes", "2", "--against", "frontier"]
    sets = ["--against-set", "eval.rollout.after=0.5"]
    assert main([*plain, *sets, "--against-set", "env.n_agents=3"]) == 2  # refused up front
    assert "env.n_agents makes the episodes" in one_error_line(capsys.readouterr().err)
    assert not list(group.glob("group-*.json"))
    assert main(plain) == 0 and main([*plain, *sets]) == 0
    printed = capsys.readouterr().out
    assert "== over 2 seeds against frontier --against-set eval.rollout.after=0.5 (" in printed
    name = "against-frontier-2ep+eval.rollout.after-0.5.json"
    ours = json.loads((group / f"group-{name}").read_text())
    theirs = json.loads((group / "group-against-frontier-2ep.json").read_text())
    assert ours["against_set"] == ["eval.rollout.after=0.5"]
    assert ours["differences"] == theirs["differences"]
    assert all((run / name).is_file() for run in _members(group))
