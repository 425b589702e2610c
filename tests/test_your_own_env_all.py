"""Issue 72's "done when" on one env of one's own: tests/envs/meet_all.py has action masks, a
walker that leaves mid-episode and no ``render_mode`` or ``metadata``; it passes PettingZoo's
``parallel_api_test`` and goes through run, ``--seeds``, eval (``--against random``), compare,
tune, sweep and render (refused in one line: it draws no frames). Envs the harness cannot train
(continuous actions, agents of different spaces) are refused in one line naming the agent, the
space and the wrapper that fits. Tiny budgets."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import pytest
import yaml
from pettingzoo.test import parallel_api_test

from harness.cli import main
from harness.config.loading import config_from_dict
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes
from tests.conftest import one_error_line
from tests.envs import meet_all, odd

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "tests" / "data" / "meet_all.yaml"
TINY = ["--set", "phases.initial.timesteps=300", "--set", "eval.every=300"]


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    # The seed groups' and sweeps' processes import tests.envs.meet_all too.
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(ROOT), path) if p))


def test_the_env_passes_pettingzoos_own_api_test_bare():
    env = meet_all.parallel_env()
    assert not hasattr(env, "render_mode") and not hasattr(env, "metadata")
    parallel_api_test(env, num_cycles=100)


def test_the_env_with_masks_and_a_leaving_agent_through_every_command(tmp_path, capsys):
    # The env raises on a masked action: no command plays one.
    run = tmp_path / "run"
    assert main(["run", str(CONFIG), "--no-progress", "--into", str(run), *TINY]) == 0
    with (run / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert rows and all(row["length"] == "10" for row in rows)
    # walker_2 leaves after 4 steps: its return and infos are its own 4 steps'.
    for row in rows:
        returns = [float(r) for r in row["returns"].split(";")]
        assert returns[2] >= 4 * -4 and returns[0] == returns[1]  # (a spread is at most 4)
        assert None not in json.loads(row["infos"])["spread"]
    capsys.readouterr()

    assert main(["eval", str(run), "--episodes", "4", "--against", "random"]) == 0
    out = capsys.readouterr().out
    assert "against   random on the same 4 episodes: mean team return " in out
    saved = json.loads((run / "eval-4ep.json").read_text())
    assert len(saved["team_return"]) == 4 and saved["length_mean"] == 10
    assert [a["agent"] for a in saved["per_agent"]] == ["walker_0", "walker_1", "walker_2"]

    assert main(["tune", str(run), "--episodes", "2", "--temperatures", "0.5", "1"]) == 0
    assert "(team return)" in capsys.readouterr().out

    png = tmp_path / "r.png"
    assert main(["render", str(run), "--gif", str(tmp_path / "r.gif"), "--out", str(png)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "meet_all:parallel_env does not render rgb_array frames (it has no metadata" in line
    assert not png.exists() and not (tmp_path / "r.gif").exists()

    runs = tmp_path / "runs"
    args = ["run", str(CONFIG), "--seeds", "2", "--no-progress", "--runs-dir", str(runs), *TINY]
    assert main(args) == 0
    (group,) = runs.iterdir()
    assert main(["eval", str(group), "--episodes", "100"]) == 0  # the standard test
    assert "mean team return" in capsys.readouterr().out
    over = json.loads((group / "group-eval.json").read_text())["return_mean_over_seeds"]
    assert over["seeds"] == 2
    cmp = tmp_path / "cmp.png"
    assert main(["compare", str(group), str(run), "--out", str(cmp), "--reps", "100"]) == 0
    assert "mean test team return" in capsys.readouterr().out and cmp.is_file()

    space = tmp_path / "space.yaml"
    space.write_text("algo.gamma: {float: [0.8, 0.99]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(CONFIG), "--space", str(space), "--trials", "1"]
    assert main([*args, "--sweeps-dir", str(sweeps), *TINY]) == 0
    best = json.loads((sweeps / "meet-all" / "best.json").read_text())
    assert best["objective"].startswith("median team return")


# ---------------------------------------------------------------------- what cannot train
@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (
            "tests.envs.odd:continuous",
            [
                "agent 'walker_0': action space Box(-1.0, 1.0, (1,), float32) is not Discrete",
                "continuous",
                "no SuperSuit wrapper makes such a space Discrete",
            ],
        ),
        (
            "tests.envs.odd:mixed_observations",
            ["agent 'walker_1': observation space Box(0.0, 1.0, (3,), float32)", "differs"],
        ),
        ("tests.envs.odd:mixed_actions", ["agent 'walker_1': action space Discrete(4)"]),
    ],
)
def test_what_cannot_train_is_one_line_naming_the_agent_the_space_and_the_wrapper(
    tmp_path, capsys, make, expected
):
    raw = yaml.safe_load(CONFIG.read_text())
    raw["env"]["pettingzoo"] = {"make": make, "kwargs": {}}
    raw["algo"].pop("policy")
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["run", str(path), "--runs-dir", str(tmp_path / "runs")]) == 2
    line = one_error_line(capsys.readouterr().err)
    wrapper = {
        "tests.envs.odd:mixed_observations": "SuperSuit's pad_observations_v0",
        "tests.envs.odd:mixed_actions": "SuperSuit's pad_action_space_v0",
    }.get(make, "")
    for part in [*expected, wrapper]:
        assert part in line, line
    assert not (tmp_path / "runs").exists()


def padded_observations(**kwargs):
    """:func:`tests.envs.odd.mixed_observations` padded as its refusal advises."""
    import supersuit

    return supersuit.pad_observations_v0(odd.mixed_observations(**kwargs))


def test_the_wrapper_the_refusal_names_makes_the_env_train():
    raw = yaml.safe_load(CONFIG.read_text())
    raw["env"]["pettingzoo"] = {"make": "tests.test_your_own_env_all:padded_observations"}
    raw["algo"].pop("policy")
    env = config_from_dict(raw).env
    assert env.spaces.observation_space.shape == (3,)
    results = run_episodes(make_baseline("random", 0), env, 2, 5)
    assert [r.length for r in results] == [10, 10]
