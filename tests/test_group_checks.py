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
