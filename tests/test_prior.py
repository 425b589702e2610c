"""The map prior (``harness.prior``): the partial maps' codes, the network's input, the score
against hand-computed log-losses, the prior handed to the rollout chooser, and the prior's run
end to end on a tiny config (train, evaluate, stop and resume to the same weights)."""

from __future__ import annotations

import csv
import json
import os
import signal
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from envs.coverage.rollouts import SampledChooser, sampled_free
from harness.cli import main
from harness.config.loading import load_config
from harness.config.schema import ConfigError
from harness.prior.data import SEEN_FREE, SEEN_WALL, UNSEEN, code_team_map, record
from harness.prior.model import MapPrior, UNet, encode, load_prior
from harness.prior.score import EPS, density, score
from harness.results.rundir import RunDir
from harness.training import prior as prior_train
from harness.training.train import TrainingInterrupted
from tests.conftest import TINY_GOAL_RUN, one_error_line
from tests.test_teacher import W, corridor

#: A prior run of a few seconds: 21x31 mazes, 2 agents, 200 steps, a 2-level network.
TINY = """\
name: prior_tiny
seed: 3
env:
  map: {maze: {height: 21, width: 31}}
  n_agents: 2
  max_steps: 200
algo: {threads: 1}
prior: {channels: [4, 8], episodes: 6, snapshots: 4}
phases:
  - {name: a, timesteps: 12, learning_rate: 1.0e-3, batch_size: 4}
  - {name: b, timesteps: 12, learning_rate: [1.0e-3, 1.0e-4], batch_size: 4}
eval: {every: 8, episodes: 2}
checkpoint: {every: 5}
"""


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "prior_tiny.yaml"
    path.write_text(TINY)
    return path


def test_a_team_map_is_coded_seen_free_seen_wall_or_unseen() -> None:
    seen = np.array([[True, True, False], [False, True, True]])
    walls = np.array([[False, True, True], [False, False, True]])
    np.testing.assert_array_equal(
        code_team_map(seen, walls),
        [[SEEN_FREE, SEEN_WALL, UNSEEN], [UNSEEN, SEEN_FREE, SEEN_WALL]],
    )


def test_the_networks_input_is_one_hot_inside_the_map_and_padded_as_wall() -> None:
    states = np.array([[[SEEN_FREE, SEEN_WALL, UNSEEN]]], dtype=np.uint8)  # 1x3
    x = encode(states, 4).numpy()
    assert x.shape == (1, 4, 4, 4)
    np.testing.assert_array_equal(x[0, :3, 0, :3], np.eye(3))  # free, wall, unseen channels
    np.testing.assert_array_equal(x[0, 3], [[1, 1, 1, 0], [0, 0, 0, 0]] + [[0] * 4] * 2)
    # Outside the map: a seen wall, not inside.
    assert (x[0, 1, 1:] == 1).all() and (x[0, 1, 0, 3] == 1) and (x[0, [0, 2], 1:] == 0).all()


def test_the_score_is_the_mean_log_loss_of_the_unseen_cells_against_the_seen_share() -> None:
    from harness.prior.data import PartialMaps

    # One 2x2 partial map: a seen free and a seen wall cell (share 1/2), two unseen cells, the
    # first a wall. The prior gives 0.8 and 0.4: -ln 0.8 = 0.2231, -ln 0.6 = 0.5108; the
    # density prior 0.5 for both: ln 2 = 0.6931.
    states = np.array([[[SEEN_FREE, SEEN_WALL], [UNSEEN, UNSEEN]]], dtype=np.uint8)
    walls = np.array([[[False, True], [True, False]]])
    data = PartialMaps(states, walls, np.zeros(1, dtype=np.int64))

    def predict(s: np.ndarray) -> np.ndarray:
        return np.array([[[0.0, 1.0], [0.8, 0.4]]])

    result = score(predict, [data])
    assert result["unseen_logloss"] == pytest.approx((0.223144 + 0.510826) / 2, abs=1e-6)
    assert result["density_logloss"] == pytest.approx(np.log(2))
    assert result["ratio"] == pytest.approx(0.366985 / 0.693147, abs=1e-5)
    assert (result["cells"], result["maps"]) == (2, 1)
    # A certain prior that is wrong is clipped, not infinite: -ln(EPS).
    wrong = score(lambda s: np.array([[[0, 1], [0.0, 1.0]]]), [data])
    assert wrong["unseen_logloss"] == pytest.approx(-np.log(EPS))


def test_partial_maps_come_from_the_planners_episodes_with_their_true_maps() -> None:
    env = load_config_text(TINY).env
    sets = record(env, "frontier_pocket", 3, 11, 5)
    assert len(sets) == 1 and len(sets[0]) <= 15
    data = sets[0]
    seen = data.states != UNSEEN
    # Where the team has seen, the code is the truth; the border of a maze is rock.
    np.testing.assert_array_equal(data.states[seen] == SEEN_WALL, data.walls[seen])
    assert data.walls[:, 0].all() and data.unseen.any(axis=(1, 2)).all()
    again = record(env, "frontier_pocket", 3, 11, 5)[0]
    np.testing.assert_array_equal(again.states, data.states)  # a seed gives the same maps


def load_config_text(text: str):
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
        f.write(text)
    try:
        return load_config(f.name)
    finally:
        os.unlink(f.name)


def test_the_prior_keeps_the_seen_cells_and_reads_maps_of_any_size() -> None:
    torch.manual_seed(0)
    prior = MapPrior(UNet([4, 8, 8]))
    rng = np.random.default_rng(0)
    for h, w in ((5, 7), (13, 9)):
        seen = rng.random((h, w)) < 0.5
        free = rng.random((h, w)) < 0.7
        p = prior(seen, free)
        assert p.shape == (h, w)
        np.testing.assert_array_equal(p[seen], np.where(free[seen], 0.0, 1.0))
        assert ((p[~seen] > 0) & (p[~seen] < 1)).all()


def test_a_prior_zip_reads_back_the_same_and_nothing_else_reads_as_one(tmp_path: Path) -> None:
    torch.manual_seed(1)
    prior = MapPrior(UNet([4, 8]))
    prior.save(tmp_path / "p.zip")
    states = np.full((1, 6, 6), UNSEEN, dtype=np.uint8)
    states[0, :2] = SEEN_FREE
    np.testing.assert_array_equal(
        load_prior(tmp_path / "p.zip").logits(states), prior.logits(states)
    )
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as zf:
        zf.writestr("data", "{}")
    with pytest.raises(ValueError, match="not a map prior"):
        load_prior(tmp_path / "other.zip")
    with pytest.raises(ValueError, match="no such prior"):
        load_prior(tmp_path / "missing")


def test_a_sampled_map_draws_the_unseen_cells_from_the_priors_probabilities() -> None:
    planner, _ = corridor([3])
    seen = np.zeros((1, W), dtype=bool)
    seen[0, 1:8] = True
    # The density draw is unchanged by the new argument (the reference numbers keep).
    np.testing.assert_array_equal(
        sampled_free(planner, np.random.default_rng(5)),
        sampled_free(planner, np.random.default_rng(5), None),
    )
    walls = sampled_free(planner, np.random.default_rng(5), np.ones((1, W)))
    free = sampled_free(planner, np.random.default_rng(5), np.zeros((1, W)))
    inner_walls, inner_free = walls.reshape(3, -1)[1, 1:-1], free.reshape(3, -1)[1, 1:-1]
    assert inner_walls[seen[0]].all() and not inner_walls[~seen[0]].any()
    assert inner_free.all()
    # Half and half, cell by cell: 400 draws of the 14 unseen cells.
    half = np.full((1, W), 0.5)
    draws = np.stack([sampled_free(planner, np.random.default_rng(s), half) for s in range(400)])
    assert draws.reshape(400, 3, -1)[:, 1, 1:-1][:, ~seen[0]].mean() == pytest.approx(0.5, abs=0.03)


def test_the_chooser_asks_its_prior_once_a_step_with_the_teams_map() -> None:
    planner, cand = corridor([3])
    calls: list[tuple[np.ndarray, np.ndarray]] = []

    def all_walls(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        calls.append((seen.copy(), free.copy()))
        return np.where(seen, ~free, 1.0)

    # Unseen cells predicted walls: the far end of the corridor is a dead end too, and both
    # slots find the same cells on every map: slot 0 stays (the density prior's maps, all free
    # at the seen share 1, make slot 1 the better one: tests/test_rollouts.py).
    chooser = SampledChooser(samples=2, after=0.0, prior=all_walls)
    assert chooser.decide(planner, cand, 10, np.random.default_rng(0)).tolist() == [0]
    assert len(calls) == 1
    seen, free = calls[0]
    assert seen.shape == (1, W) and seen[0, 1:8].all() and not seen[0, 8:].any()
    density = SampledChooser(samples=2, after=0.0)
    assert density.decide(planner, cand, 10, np.random.default_rng(0)).tolist() == [1]


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return load_prior(path).net.state_dict()


def test_a_prior_run_trains_validates_and_is_scored_by_harness_eval(
    tiny: Path, tmp_path: Path, capsys
) -> None:
    runs = tmp_path / "runs"
    assert main(["run", str(tiny), "--runs-dir", str(runs), "--no-progress"]) == 0
    (run,) = runs.iterdir()
    files = RunDir(run)
    assert files.model.is_file() and files.best_model.is_file() and files.tb.is_dir()
    err = capsys.readouterr().err
    assert "validation unseen_logloss" in err and "training:" in err
    # The run's prior is the one validation chose (its best_model.zip).
    assert files.model.read_bytes() == files.best_model.read_bytes()
    assert main(["eval", str(run), "--episodes", "3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"unseen_logloss", "density_logloss", "ratio", "cells", "maps"} <= set(out)
    assert out["episodes"] == 3 and out["seed"] == 1_000_003 and out["cells"] > 0
    assert (run / "eval-3ep.json").is_file()
    # --against is a policy's comparison: one line, exit 2.
    assert main(["eval", str(run), "--against", "frontier"]) == 2
    assert "map prior" in one_error_line(capsys.readouterr().err)
    # Exported, the reference holds the same prior (copied whole) and its config.
    ref = tmp_path / "reference" / "prior_tiny"
    assert main(["export", str(run), "--out", str(ref)]) == 0
    assert (ref / "model.zip").read_bytes() == files.model.read_bytes()
    assert (ref / "config.yaml").is_file() and (ref / "reference.json").is_file()
    capsys.readouterr()
    # Resuming a finished prior run says so and changes nothing.
    before = files.model.read_bytes()
    assert main(["run", "--resume", str(run)]) == 0
    assert "already finished" in capsys.readouterr().err
    assert files.model.read_bytes() == before


def test_a_stopped_prior_run_resumes_to_the_weights_of_an_unstopped_one(
    tiny: Path, tmp_path: Path, monkeypatch
) -> None:
    config = load_config(tiny)
    whole = RunDir.create(tmp_path / "a", "whole")
    with whole.lock():
        prior_train.train_prior(config, whole, progress_bar=False)

    stopped = RunDir.create(tmp_path / "b", "stopped")
    real = prior_train.logloss
    steps = {"n": 0}

    def signalled(*args, **kwargs):  # SIGTERM during the 15th gradient step (phase b)
        steps["n"] += 1
        if steps["n"] == 15:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*args, **kwargs)

    monkeypatch.setattr(prior_train, "logloss", signalled)
    with stopped.lock(), pytest.raises(TrainingInterrupted) as stop:
        prior_train.train_prior(config, stopped, progress_bar=False)
    assert stop.value.checkpoint.name == "step-000000000015"
    assert not stopped.model.exists()
    monkeypatch.setattr(prior_train, "logloss", real)
    with stopped.lock():
        prior_train.train_prior(config, stopped, progress_bar=False, resume=True)
    for key, tensor in _weights(whole.model).items():
        torch.testing.assert_close(_weights(stopped.model)[key], tensor, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("override", "words"),
    [
        ("prior.planner=frontier_nowhere", "unknown prior.planner"),
        ("prior.snapshots=500", "more than the 200 steps"),
        ("prior.channels=[]", "prior.channels"),
    ],
)
def test_a_prior_config_that_cannot_work_is_refused_in_one_line(
    tiny: Path, tmp_path: Path, capsys, override: str, words: str
) -> None:
    runs = tmp_path / "runs"
    assert main(["run", str(tiny), "--runs-dir", str(runs), "--set", override]) == 2
    assert words in one_error_line(capsys.readouterr().err)
    assert not runs.exists() or list(runs.iterdir()) == []


def test_the_goal_action_is_no_env_to_record_a_prior_on(tiny: Path) -> None:
    with pytest.raises(ConfigError, match=r"drop env\.frontier\.action"):
        load_config(
            tiny,
            ["env.observation=teammap", "env.frontier={planner: minpos, action: {goal: {k: 4}}}"],
        )


def test_a_rollout_prior_that_is_no_prior_is_one_line(tmp_path: Path, capsys) -> None:
    args = ["eval", "--policy", "rollout", "--config", "configs/goals_2agents.yaml"]
    assert main([*args, "--set", f"eval.rollout.prior={tmp_path}", "--episodes", "1"]) == 2
    assert "eval.rollout.prior" in one_error_line(capsys.readouterr().err)


REFERENCE = Path(__file__).resolve().parents[1] / "runs" / "reference"


def _partial(shape: tuple[int, int]) -> np.ndarray:
    return np.full(shape, UNSEEN, dtype=np.uint8)


def test_the_maze_prior_continues_a_corridor_between_its_walls() -> None:
    prior = load_prior(REFERENCE / "prior_maze")
    # A one-cell corridor on row 25 seen from column 21 to 41 between walls on rows 24 and 26,
    # in a 51x101 maze with its rock border seen; the rest unseen.
    states = _partial((51, 101))
    states[[0, -1], :] = states[:, [0, -1]] = SEEN_WALL
    states[25, 21:42] = SEEN_FREE
    states[[24, 26], 20:43] = SEEN_WALL
    p = prior.wall_probability(states[None])[0]
    # The corridor's next cell is more likely free than the cells beside it, which more likely
    # continue its walls; the density prior gives all three the seen wall share (0.94 here:
    # the rock border is seen).
    assert density(states[None])[0] == pytest.approx(346 / 367)
    assert p[25, 43] < p[24, 43] and p[25, 43] < p[26, 43]
    assert p[25, 43] < 0.5 < min(p[24, 43], p[26, 43])


def test_the_rooms_prior_carries_a_rooms_wall_on() -> None:
    prior = load_prior(REFERENCE / "prior_rooms")
    # A room's top wall seen on row 10 from column 10 to 30, its floor seen below it (rows 11
    # to 18); beyond column 30 nothing is seen.
    states = _partial((50, 100))
    states[[0, -1], :] = states[:, [0, -1]] = SEEN_WALL
    states[10, 10:31] = SEEN_WALL
    states[11:19, 10:31] = SEEN_FREE
    p = prior.wall_probability(states[None])[0]
    # The wall goes on (a room's walls are straight), above it lies another room's floor or a
    # hallway, and the floor beside the seen one is more likely free than wall; the density
    # prior gives each the seen wall share (0.65 here: the border is seen).
    assert density(states[None])[0] == pytest.approx(317 / 485)
    assert p[10, 31] > 0.9 and p[9, 31] < 0.2 and p[14, 31] < 0.5


@pytest.mark.parametrize("name", ["prior_rooms", "prior_maze", "prior_cave", "prior_random"])
def test_a_reference_prior_beats_the_seen_wall_share_where_maps_have_structure(name: str) -> None:
    # The committed scores on the 100 test episodes (docs/results.md, "Map priors"): at most
    # 0.8 of the density prior's log-loss on floor plans, mazes and caves; on random maps,
    # whose walls are independent, no more than it (the null result), within 2 %.
    committed = json.loads((REFERENCE / name / "eval.json").read_text())
    assert committed["episodes"] == 100 and committed["seed"] == 1_000_003
    ratio = committed["unseen_logloss"] / committed["density_logloss"]
    assert committed["ratio"] == pytest.approx(ratio)
    if name == "prior_random":
        assert 0.98 <= ratio <= 1.02
    else:
        assert ratio <= 0.8


def test_a_reference_prior_repeats_its_committed_score(tmp_path: Path, capsys) -> None:
    ref = REFERENCE / "prior_random"
    committed = json.loads((ref / "eval.json").read_text())
    copy = tmp_path / "prior_random"  # scored as a copy: the committed files stay as they are
    copy.mkdir()
    for f in ("config.yaml", "model.zip"):
        (copy / f).write_bytes((ref / f).read_bytes())
    assert main(["eval", str(copy), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("unseen_logloss", "density_logloss", "cells", "maps"):
        assert out[key] == pytest.approx(committed[key], rel=1e-9)


def test_a_sweep_of_a_prior_minimises_its_validation_log_loss(tiny: Path, tmp_path: Path, capsys):
    space = tmp_path / "space.yaml"
    space.write_text("phases.a.learning_rate: {float: [1.0e-4, 3.0e-3], log: true}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(tiny), "--space", str(space), "--trials", "2", "--sweeps-dir", str(sweeps)]
    assert main(args) == 0
    best = json.loads((sweeps / "prior_tiny" / "best.json").read_text())
    assert best["trials"]["complete"] == 2 and "log-loss" in best["objective"]
    # A trial's value is minus its last validation's unseen_logloss (higher is better).
    trial = RunDir(Path(best["run"]))
    assert trial.model.is_file()
    with (trial.tb / "progress.csv").open() as f:
        scores = [row["eval/unseen_logloss"] for row in csv.DictReader(f)]
    assert best["value"] == pytest.approx(-float([x for x in scores if x][-1]))
    assert "validation unseen_logloss" in capsys.readouterr().err


def test_seeds_of_a_prior_train_into_a_group(tiny: Path, tmp_path: Path, capsys) -> None:
    runs = tmp_path / "runs"
    args = ["run", str(tiny), "--runs-dir", str(runs), "--seeds", "0,1", "--no-progress"]
    assert main(args) == 0
    (group,) = [p for p in runs.iterdir() if p.is_dir()]
    models = sorted(group.glob("*/model.zip"))
    assert len(models) == 2
    assert models[0].read_bytes() != models[1].read_bytes()  # two seeds, two priors


@pytest.mark.parametrize(
    ("command", "words"),
    [
        (["tune", "{ref}"], "not a policy"),
        (["render", "{ref}", "--out", "{tmp}/paths.png"], "not a policy"),
        (["compare", "{ref}", "{ref2}", "--out", "{tmp}/cmp.png"], "TensorBoard"),
        (["eval", "{ref}", "--plot", "{tmp}/plot.png"], "log-loss"),
    ],
)
def test_a_policys_command_on_a_prior_says_what_a_prior_takes(
    command: list[str], words: str, tmp_path: Path, capsys
) -> None:
    values = {"ref": REFERENCE / "prior_random", "ref2": REFERENCE / "prior_maze", "tmp": tmp_path}
    assert main([part.format(**values) for part in command]) == 2
    assert words in one_error_line(capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []


def test_the_rollout_baseline_plans_with_a_prior_end_to_end(capsys) -> None:
    # The whole path: eval.rollout.prior loaded by the harness's commands and handed to the
    # chooser, which decides from the start on 12x12 random maps (the random-map prior reads
    # any size): the episodes play to their end with no wall hit.
    args = ["eval", "--policy", "rollout", "--config", "configs/goals_2agents.yaml"]
    for key in ("env.map", "env.height", "env.width", "env.max_steps", "env.test_maps"):
        args += ["--set", f"{key}={TINY_GOAL_RUN[key]}"]
    args += ["--set", "eval.rollout.after=0.0", "--episodes", "2", "--json"]
    with_prior = [*args, "--set", f"eval.rollout.prior={REFERENCE / 'prior_random'}"]
    assert main(with_prior) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["episodes"] == 2 and out["wall_hits_mean"] == 0
    assert 0 < out["coverage_mean"] <= 1


def test_a_rollout_chooser_of_one_map_is_refused_in_one_line(capsys) -> None:
    # One map turns the noise rule off; measured, the team then walks back and forth.
    args = ["eval", "--policy", "rollout", "--config", "configs/goals_2agents.yaml"]
    assert main([*args, "--set", "eval.rollout.samples=1", "--episodes", "1"]) == 2
    assert "2 maps or more" in one_error_line(capsys.readouterr().err)


# ------------------------------------------------ the goal action's candidates read a prior
def test_the_predicted_features_are_the_expected_unseen_free_cells_of_the_windows() -> None:
    from envs.coverage.goals import predicted_features

    # A 5x6 map, nothing seen, every cell a wall with probability 1/4; one candidate at row 2,
    # column 3 (padded: row 3, column 4 of a stride of 8) and an empty slot. The 7x7 window
    # holds the map's 5 rows and 6 columns: 30 x 0.75 / 49 = 0.459; the 15x15 one all 30 cells:
    # 30 x 0.75 / 225 = 0.1. Seeing a cell takes it out (it is no longer to be found).
    h, w = 5, 6
    p = np.full((h, w), 0.25)
    seen = np.zeros((h + 2) * (w + 2), dtype=bool)
    cells = np.array([[3 * (w + 2) + 4, -1]])
    np.testing.assert_allclose(
        predicted_features(p, seen, cells)[0], [[0.45918, 0.1], [0, 0]], 1e-4
    )
    seen[3 * (w + 2) + 4] = True  # the candidate's own cell is seen
    np.testing.assert_allclose(
        predicted_features(p, seen, cells)[0, 0], [29 * 0.75 / 49, 29 * 0.75 / 225], 1e-6
    )


def test_the_goal_action_with_a_prior_carries_its_columns_and_the_same_moves() -> None:
    # A prior that calls every unseen cell a wall adds zero columns; one that calls them free
    # adds the unseen share of the windows. Either way the candidates, moves and the other
    # features are those of the env without a prior.
    from envs import coverage_v0
    from envs.coverage.goals import GOAL_FEATURES

    def all_walls(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        return np.where(seen, ~free, True).astype(float)

    def all_free(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        return np.where(seen, ~free, False).astype(float)

    kwargs = dict(
        height=14, width=16, n_agents=2, max_steps=30,
        observation={"teammap": {"crop": 7, "global_size": 6}},
    )  # fmt: skip
    goal = {"action": {"goal": {"k": 4}}, "planner": "pocket"}
    priors = (None, all_walls, all_free)
    envs = [coverage_v0.parallel_env(**kwargs, frontier={**goal, "prior": f}) for f in priors]
    n = len(GOAL_FEATURES)
    assert [e.observation_space("agent_0")["goals"].shape for e in envs] == [
        (4, n),
        (4, n + 2),
        (4, n + 2),
    ]
    obs = [e.reset(seed=5)[0] for e in envs]
    for _ in range(12):
        for o in obs[1:]:
            np.testing.assert_array_equal(o["agent_0"]["goals"][:, :n], obs[0]["agent_0"]["goals"])
        assert not obs[1]["agent_0"]["goals"][:, n:].any()
        mask = obs[2]["agent_1"]["action_mask"].astype(bool)
        assert (obs[2]["agent_1"]["goals"][mask, n:] > 0).any()
        actions = {a: int(o["action_mask"].nonzero()[0][-1]) for a, o in obs[0].items()}
        obs = [e.step(actions)[0] for e in envs]


def test_the_env_asks_its_prior_every_few_steps_and_at_each_episodes_start() -> None:
    from envs import coverage_v0
    from envs.coverage.goals import PRIOR_EVERY

    steps: list[int] = []

    def counting(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        steps.append(int(seen.sum()))
        return np.where(seen, ~free, False).astype(float)

    env = coverage_v0.parallel_env(
        height=14, width=16, n_agents=2, max_steps=12,
        observation={"teammap": {"crop": 7, "global_size": 6}},
        frontier={"action": {"goal": {"k": 4}}, "planner": "pocket", "prior": counting},
    )  # fmt: skip
    env.reset(seed=1)
    for _ in range(11):
        env.step({a: 0 for a in env.agents})
    assert len(steps) == len(range(0, 12, PRIOR_EVERY))  # steps 0, 5 and 10
    env.reset(seed=2)
    assert len(steps) == len(range(0, 12, PRIOR_EVERY)) + 1


@pytest.mark.parametrize("predicted", [False, True])
def test_env_prior_trains_a_goal_policy_that_reads_it(
    predicted: bool, tmp_path: Path, capsys
) -> None:
    # The whole path: env.prior loaded by the factory (once per process), the policy trained on
    # the wider candidate block (and the predicted views) and evaluated from its run folder.
    from tests.conftest import tiny_goal_run

    runs = tmp_path / "runs"
    args = tiny_goal_run(Path("configs/goals_2agents.yaml"), runs)
    args += ["--set", f"env.prior={REFERENCE / 'prior_random'}"]
    args += ["--set", f"env.observation.teammap.predicted={str(predicted).lower()}"]
    assert main(args) == 0
    (run,) = runs.iterdir()
    config = load_config(RunDir(run).config)
    assert config.env.prior == str(REFERENCE / "prior_random")
    assert config.env.observation["teammap"]["predicted"] is predicted
    capsys.readouterr()
    assert main(["eval", str(run), "--episodes", "2", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["wall_hits_mean"] == 0


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (["--set", "env.prior=no/such/prior"], "no prior run folder"),
        (
            [
                "--set",
                f"env.prior={REFERENCE / 'prior_random'}",
                "--set",
                "env.frontier.action=step",
            ],
            "feeds the goal action",
        ),
    ],
)
def test_an_env_prior_that_cannot_work_is_one_line(
    change: list[str], words: str, tmp_path: Path, capsys
) -> None:
    args = ["run", "configs/goals_2agents.yaml"]
    assert main([*args, *change, "--runs-dir", str(tmp_path / "runs")]) == 2
    assert words in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "runs").exists()


def test_the_env_refuses_a_prior_without_the_goal_action_or_that_is_no_function() -> None:
    from envs.coverage.frontier import FrontierOptions

    def flat(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        return np.zeros(seen.shape)

    with pytest.raises(ValueError, match="feeds the goal action"):
        FrontierOptions(action="step", planner="pocket", prior=flat)
    with pytest.raises(ValueError, match=r"env\.prior: RUN"):
        FrontierOptions.parse({"action": {"goal": {"k": 4}}, "planner": "pocket", "prior": "x"})
    options = FrontierOptions.parse(
        {"action": {"goal": {"k": 4}}, "planner": "pocket", "prior": flat}
    )
    assert options.prior is flat and "prior" not in options.config()


# ------------------------------------------------ the team map's predicted views read a prior
def _predicted_env(prior, ego: int = 5, **kwargs):
    from envs import coverage_v0

    return coverage_v0.parallel_env(
        height=14, width=16, n_agents=2, max_steps=30,
        observation={
            "teammap": {"crop": 7, "global_size": 6, "ego_size": ego, "ego_block": 3,
                        "predicted": True}
        },
        frontier={"action": {"goal": {"k": 4}}, "planner": "pocket", "prior": prior},
        **kwargs,
    )  # fmt: skip


def test_the_predicted_views_show_the_expected_free_floor_of_the_unseen_cells() -> None:
    # A prior that calls every unseen cell a wall with probability 1/4: each unseen cell shows
    # round(255 x 0.75) = 191 and every other cell 0, at every step (the cells seen since the
    # prior's last call count as seen), and each coarse block 0.75 x its unknown share (the
    # team map's own unknown channel: global channel 2, ego channel 2), to the rounding of the
    # two (one unit).
    def quarter(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        return np.where(seen, ~free, 0.25).astype(float)

    env = _predicted_env(quarter)
    space = env.observation_space("agent_0")
    assert space["predicted_local"].shape == (1, 7, 7)
    assert space["predicted_global"].shape == (1, 6, 6)
    assert space["predicted_ego"].shape == (1, 5, 5)
    obs = env.reset(seed=4)[0]
    for step in range(12):
        for o in obs.values():
            unknown = o["local"][3] == 255
            np.testing.assert_array_equal(o["predicted_local"][0], np.where(unknown, 191, 0))
            for view in ("global", "ego"):
                expected = 0.75 * o[view][2].astype(float)
                assert np.abs(o[f"predicted_{view}"][0] - expected).max() <= 1.0, (step, view)
        actions = {a: int(o["action_mask"].nonzero()[0][-1]) for a, o in obs.items()}
        obs = env.step(actions)[0]


def test_the_predicted_crop_lines_up_with_the_cells_of_the_map() -> None:
    # A prior whose wall probability grows with the column (col / 15 on a 16-column map): an
    # unseen cell of the crop at offset (dy, dx) from the agent at (r, c) shows
    # round(255 x (1 - (c + dx) / 15)), whatever its row; seen cells and outside the map 0.
    w = 16

    def ramp(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        cols = np.broadcast_to(np.arange(w) / (w - 1), seen.shape)
        return np.where(seen, ~free, cols).astype(float)

    env = _predicted_env(ramp, starts=[(6, 4), (6, 11)])
    obs = env.reset(seed=0)[0]
    obs = env.step({a: 0 for a in env.agents})[0]
    for agent, (_, c) in zip(env.agents, env.unwrapped.positions, strict=True):
        o = obs[agent]
        unknown = o["local"][3] == 255
        cols = c + np.arange(-3, 4)
        inside = (cols >= 0) & (cols < w)
        expected = np.rint(255 * (1 - np.clip(cols, 0, w - 1) / (w - 1))) * inside
        np.testing.assert_array_equal(
            o["predicted_local"][0], np.where(unknown, expected[None, :], 0)
        )
        assert unknown.any()


def test_without_the_ego_view_there_is_no_predicted_ego() -> None:
    def half(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        return np.where(seen, ~free, 0.5).astype(float)

    space = _predicted_env(half, ego=0).observation_space("agent_0")
    assert {k for k in space.spaces if k.startswith("predicted_")} == {
        "predicted_local",
        "predicted_global",
    }


def test_predicted_views_without_a_prior_are_refused() -> None:
    from envs import coverage_v0

    with pytest.raises(ValueError, match="needs one"):
        coverage_v0.parallel_env(
            height=14, width=16, n_agents=2,
            observation={"teammap": {"crop": 7, "global_size": 6, "predicted": True}},
            frontier={"action": {"goal": {"k": 4}}, "planner": "pocket"},
        )  # fmt: skip
    with pytest.raises(ValueError, match="true or false"):
        coverage_v0.parallel_env(observation={"teammap": {"predicted": 1}})


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (["predicted=true", "--set", "env.prior=null"], "needs one"),
        (["predicted=3"], "true or false"),
    ],
)
def test_a_predicted_config_that_cannot_work_is_one_line(
    change: list[str], words: str, tmp_path: Path, capsys
) -> None:
    args = ["run", "configs/goals_prior_rooms_4agents.yaml"]
    args += ["--set", f"env.observation.teammap.{change[0]}", *change[1:]]
    assert main([*args, "--runs-dir", str(tmp_path / "runs")]) == 2
    assert words in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "runs").exists()


def test_the_planners_play_a_config_with_predicted_views(capsys) -> None:
    # A baseline that walks the moves drops the goal action, the prior and its views together.
    args = [
        "eval",
        "--policy",
        "frontier_pocket",
        "--config",
        "configs/goals_prior_rooms_4agents.yaml",
    ]
    args += ["--set", "env.observation.teammap.predicted=true", "--episodes", "1", "--json"]
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["wall_hits_mean"] == 0
