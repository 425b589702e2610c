"""Every shipped reference still is what its files say after the redesign: each
``runs/reference/*/config.yaml`` and ``docs/seeds/**/config.yaml`` (written in the layout of its
day) loads through the migration, and each reference's model plays the first episode of its
committed ``eval.json`` to the same coverage and wall hits (episode ``k`` is seeded with
``seed + k``, its action noise too, so the first episodes of the committed 100 repeat)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from harness.cli import main
from harness.config import ConfigError, load_config
from harness.tasks import task_of

ROOT = Path(__file__).resolve().parents[1]
#: The references of trained policies (a map prior's reference is tests/test_prior.py's).
REFERENCES = sorted(
    p.parent.name
    for p in (ROOT / "runs" / "reference").glob("*/eval.json")
    if "\nprior:" not in (p.parent / "config.yaml").read_text()
)
#: The ablation that measured a knob since retired (research/experiment-log.md).
RETIRED_ABLATION = ROOT / "docs" / "ablations" / "teammap_2agents_mask" / "config.yaml"
SAVED_CONFIGS = sorted(
    {*(ROOT / "runs" / "reference").glob("*/config.yaml"), *(ROOT / "docs").rglob("config.yaml")}
    - {RETIRED_ABLATION}
)


def test_every_reference_is_checked() -> None:
    assert len(REFERENCES) == 20


@pytest.mark.parametrize("path", SAVED_CONFIGS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_saved_config_loads(path: Path) -> None:
    if "mpe2." in path.read_text():  # docs/seeds/mpe_spread: the optional .[mpe] extra
        pytest.importorskip("mpe2")
    config = load_config(path)
    assert config.name and config.env.n_agents >= 1
    if not task_of(config.env).paths:  # a PettingZoo env: no coverage env keys
        return
    # Saved configs of the team map keep their sizes and planner options in today's layout.
    observation = config.env.observation
    assert observation == "thesis" or set(observation) == {"teammap"}
    if config.env.frontier is not None:
        assert set(config.env.frontier) == {"action", "planner"}


def test_a_saved_config_that_turned_a_retired_knob_on_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"algo\.action_mask: True: this knob was retired"):
        load_config(RETIRED_ABLATION)


@pytest.mark.parametrize("name", REFERENCES)
def test_reference_repeats_its_first_committed_episode(name: str, tmp_path: Path, capsys) -> None:
    ref = ROOT / "runs" / "reference" / name
    committed = json.loads((ref / "eval.json").read_text())
    copy = tmp_path / name  # evaluate a copy: the committed files stay as they are
    copy.mkdir()
    for f in ("config.yaml", "model.zip"):
        (copy / f).write_bytes((ref / f).read_bytes())
    capsys.readouterr()
    assert main(["eval", str(copy), "--episodes", "1", "--json"]) == 0
    (saved_file,) = copy.glob("eval*.json")
    saved = json.loads(saved_file.read_text())
    assert saved["temperature"] == committed["temperature"]
    assert saved["coverage"] == committed["coverage"][:1]
    assert saved["wall_hits"] == committed["wall_hits"][:1]


def test_check_references_repeats_a_reference_on_all_its_committed_episodes(capsys) -> None:
    import runpy

    script = runpy.run_path(str(ROOT / "scripts" / "check_references.py"))
    assert script["main"](["ddqn_15x15"]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert line.startswith("ddqn_15x15") and "100 episodes" in line and " same " in line


def test_check_references_repeats_a_stored_planner_evaluation(capsys) -> None:
    """``--baselines``: a stored written-policy evaluation of docs/baselines (a planner row of
    docs/results.md) evaluated again, every figure compared."""
    import runpy

    script = runpy.run_path(str(ROOT / "scripts" / "check_references.py"))
    assert script["main"](["--baselines", "ddqn_15x15-frontier_hungarian"]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert line.startswith("ddqn_15x15-frontier_hungarian") and " same " in line


def test_check_references_compares_the_figures_both_files_hold() -> None:
    import runpy

    same = runpy.run_path(str(ROOT / "scripts" / "check_references.py"))["_same_numbers"]
    stored = {"episodes": 2, "coverage_mean": 0.5, "coverage_median": 0.5, "wall_hits_mean": 0.0}
    assert same({**stored, "coverage_mean_ci": [0.4, 0.6], "env": {"a": 1}}, {**stored})
    assert same({**stored}, {**stored, "step_bonus": 0.0, "env": {"old": 2}})  # dropped since
    assert not same({**stored, "coverage_mean": 0.51}, {**stored})
    assert not same({"episodes": 2}, {**stored})  # a quoted figure missing


def test_check_references_refuses_an_unknown_name_in_one_line(capsys) -> None:
    import runpy

    script = runpy.run_path(str(ROOT / "scripts" / "check_references.py"))
    assert script["main"](["ddqn_15x1"]) == 2
    assert script["main"](["--baselines", "no-such-*"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and err[0].startswith("error: no reference 'ddqn_15x1'; known: ")
