"""Agent groups of a PettingZoo env (issue 72): by name prefix or named in the config
(``env.pettingzoo.groups``), each group's return apart in an evaluation's summary (a competitive
env's sides), and a network per group (``algo.sharing: per_group``: the group's one-hot index
routes each agent to its group's network) through every command that takes its run or config, on
an in-file env with two sides."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from gymnasium import spaces
from pettingzoo import ParallelEnv

from harness.cli import main
from harness.config.loading import config_from_dict
from harness.config.pettingzoo import agent_groups
from harness.config.schema import ConfigError
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes, summarize
from harness.tasks import task_of
from tests.conftest import one_error_line, root_first_env


class Chase(ParallelEnv):
    """Two sides on a line: each chaser earns 1 per step on the runner's cell, the runner loses
    as much; 6 steps."""

    metadata = {"name": "chase_v0", "render_modes": []}  # noqa: RUF012

    def __init__(self, chasers=2, start=None, render_mode=None):
        self.possible_agents = [f"chaser_{i}" for i in range(chasers)] + ["runner_0"]
        self.start = start  # (every agent's first cell; None: drawn)
        self.rng = np.random.default_rng()
        self._observation = spaces.Box(0.0, 4.0, shape=(2,), dtype=np.float32)
        self._action = spaces.Discrete(3)

    def observation_space(self, agent):
        return self._observation

    def action_space(self, agent):
        return self._action

    def reset(self, seed=None, options=None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.agents, self.t = list(self.possible_agents), 0
        cells = self.rng.integers(0, 5, len(self.agents))
        if self.start is not None:
            cells[:] = self.start
        self.cells = dict(zip(self.agents, cells, strict=True))
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions):
        for a, action in actions.items():
            self.cells[a] = int(np.clip(self.cells[a] + action - 1, 0, 4))
        self.t += 1
        runner = self.cells["runner_0"]
        caught = sum(self.cells[a] == runner for a in self.agents if a != "runner_0")
        rewards = {a: float(self.cells[a] == runner) for a in self.agents if a != "runner_0"}
        rewards["runner_0"] = -float(caught)
        done = self.t >= 6
        obs = self._observe()
        infos = {a: {} for a in self.agents}
        terms = {a: False for a in self.agents}
        truncs = {a: done for a in self.agents}
        if done:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def _observe(self):
        runner = self.cells["runner_0"]
        return {a: np.array([c, runner], np.float32) for a, c in self.cells.items()}


def chase(**kwargs):
    return Chase(**kwargs)


def config(**pettingzoo) -> dict:
    return {
        "name": "chase",
        "env": {"pettingzoo": {"make": "tests.test_agent_groups:chase", **pettingzoo}},
        "vec": {"copies": 2},
        "algo": {"net_arch": [16], "buffer_size": 500, "learning_starts": 50},
        "phases": [
            {"name": "p", "timesteps": 120, "exploration": {"start": 1.0, "end": 0.1, "steps": 60}}
        ],
        "eval": {"every": 0, "episodes": 3},
        "checkpoint": {"every": 0},
    }


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])


def test_groups_by_name_prefix_or_named():
    agents = ("adversary_0", "adversary_1", "agent_0", "lone")
    assert agent_groups(agents) == {
        "adversary": ("adversary_0", "adversary_1"),
        "agent": ("agent_0",),
        "lone": ("lone",),
    }
    named = {"red": ["agent_0", "adversary_1"], "blue": ["adversary_0", "lone"]}
    assert agent_groups(agents, named) == {
        "red": ("adversary_1", "agent_0"),
        "blue": ("adversary_0", "lone"),
    }
    with pytest.raises(ValueError, match=r"groups\.red: 'agent_9' is no agent of the env"):
        agent_groups(agents, {"red": ["agent_9"]})
    with pytest.raises(ValueError, match="'agent_0' is in 'a' and 'b'"):
        agent_groups(agents, {"a": ["agent_0"], "b": ["agent_0", "adversary_0"]})
    with pytest.raises(ValueError, match="'lone' in no group"):
        agent_groups(agents, {"a": ["agent_0", "adversary_0", "adversary_1"]})


def test_each_sides_return_is_summarised_apart():
    env = config_from_dict(config()).env
    results = run_episodes(make_baseline("random", 0), env, 4, 0)
    summary = summarize(results)
    groups = summary["groups"]
    assert list(groups) == ["chaser", "runner"]
    assert groups["chaser"]["agents"] == ["chaser_0", "chaser_1"]
    chasers = [r.returns[0] + r.returns[1] for r in results]
    runners = [r.returns[2] for r in results]
    assert groups["chaser"]["return_mean"] == pytest.approx(np.mean(chasers))
    assert groups["runner"]["return_mean"] == pytest.approx(np.mean(runners))
    # The two sides cancel: the team's return (both added) is 0, each side's is not.
    assert summary["return_mean"] == pytest.approx(0.0)
    assert task_of(env).groups == {"chaser": ("chaser_0", "chaser_1"), "runner": ("runner_0",)}


def test_one_group_adds_no_group_numbers():
    env = config_from_dict(config(kwargs={"chasers": 0})).env
    summary = summarize(run_episodes(make_baseline("random", 0), env, 2, 0))
    assert "groups" not in summary


def per_group(**pettingzoo) -> dict:
    raw = config(**pettingzoo)
    raw["algo"]["sharing"] = "per_group"
    return raw


def test_named_groups_override_the_name_prefix():
    named = {"left": ["chaser_0"], "rest": ["runner_0", "chaser_1"]}
    env = config_from_dict(config(groups=named)).env
    assert task_of(env).groups == {"left": ("chaser_0",), "rest": ("chaser_1", "runner_0")}
    summary = summarize(run_episodes(make_baseline("random", 0), env, 2, 0))
    assert summary["groups"]["rest"]["agents"] == ["chaser_1", "runner_0"]


def test_an_agent_in_two_groups_is_refused_with_the_config():
    with pytest.raises(ConfigError, match="groups: 'chaser_0' is in 'a' and 'b'") as info:
        config_from_dict(config(groups={"a": ["chaser_0"], "b": ["chaser_0", "runner_0"]}))
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="groups: group 'b' has no agent"):
        config_from_dict(config(groups={"a": ["chaser_0"], "b": []}))


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        (
            config(groups={"a": ["chaser_0", "chaser_1"], "b": ["runner_9"]}),
            "env.pettingzoo.groups.b: 'runner_9' is no agent of the env",
        ),
        (
            config(groups={"a": ["chaser_0", "chaser_1"]}),
            "env.pettingzoo.groups: 'runner_0' in no group",
        ),
        (
            per_group(kwargs={"chasers": 0}),
            "algo.sharing: per_group: the agents form one group ('runner': runner_0)",
        ),
        # env.pettingzoo.select names a group of two or more (checked at load where the groups
        # are named, else where the run starts)
        (
            config(select="hunter"),
            "env.pettingzoo.select: 'hunter' is no group of the env (its groups: chaser, runner)",
        ),
        (
            config(select="runner", kwargs={"chasers": 0}),
            "env.pettingzoo.select: 'runner': the agents form one group ('runner'), whose "
            "return is the team's: nothing to select",
        ),
        (
            config(select="c", groups={"a": ["chaser_0", "chaser_1"], "b": ["runner_0"]}),
            "env.pettingzoo.select: 'c' is no group of the env (its groups: a, b)",
        ),
        (config(select=3), "env.pettingzoo.select: Input should be a valid string"),
    ],
    ids=[
        "unknown-agent", "agent-in-no-group", "one-group", "select-unknown", "select-one-group",
        "select-unknown-named", "select-not-a-name",
    ],
)  # fmt: skip
def test_groups_that_do_not_fit_the_env_are_refused_at_the_start(tmp_path, capsys, raw, expected):
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["run", str(path), "--runs-dir", str(tmp_path / "runs")]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert expected in line, line
    assert not (tmp_path / "runs").exists()


def test_per_group_is_refused_where_it_cannot_work():
    coverage = {"name": "c", "algo": {"sharing": "per_group"}}
    with pytest.raises(ConfigError, match=r"per_group: the agents form one group \('agent'"):
        config_from_dict(coverage)
    raw = per_group()
    raw["algo"]["policy"] = "MaskedMlpPolicy"
    with pytest.raises(ConfigError, match="per_group: MaskedMlpPolicy has no per-agent version"):
        config_from_dict(raw)


def q_values(raw: dict) -> dict[str, np.ndarray]:
    """Each agent's Q-values at the first step of an episode where every agent stands on one
    cell (so sees the same observation), from an untrained policy built as a run builds it."""
    import torch as th

    from harness.factory import make_env
    from harness.sb3.registry import POLICIES
    from harness.training.checks import network_kwargs

    cfg = config_from_dict(raw)
    env = make_env(cfg.env)
    observations, _ = env.reset(seed=0)
    env.close()
    th.manual_seed(0)
    spaces = cfg.env.spaces
    policy = POLICIES[cfg.algo.policy].load(per_agent=True)(
        spaces.observation_space,
        spaces.action_space,
        lambda _: 1e-3,
        **network_kwargs(cfg.algo, cfg.env.id_width),
    )
    agents = list(observations)
    with th.no_grad():
        q = policy.q_net(th.as_tensor(np.stack([observations[a] for a in agents])))
    return dict(zip(agents, q.numpy(), strict=True))


def test_the_groups_index_routes_each_agent_to_its_groups_network():
    q = q_values(per_group(kwargs={"start": 2}))
    assert np.array_equal(q["chaser_0"], q["chaser_1"])  # one group: one network
    assert not np.allclose(q["chaser_0"], q["runner_0"])  # two groups: two networks
    raw = per_group(kwargs={"start": 2})
    raw["algo"]["sharing"] = "per_agent"  # (the contrast: every agent its own network)
    q = q_values(raw)
    assert not np.allclose(q["chaser_0"], q["chaser_1"])


def test_per_group_trains_and_evaluates_each_group(tmp_path, capsys):
    from harness.sb3.dqn import DoubleDQN

    path = tmp_path / "chase.yaml"
    path.write_text(yaml.safe_dump(per_group()))
    run = tmp_path / "run"
    assert main(["run", str(path), "--into", str(run)]) == 0
    capsys.readouterr()
    model = DoubleDQN.load(run / "model.zip", device="cpu")
    assert model.q_net.n_agents == 2  # a network per group, not per agent (3)
    assert model.observation_space.shape == (2 + 2,)  # the group's one-hot index
    assert main(["eval", str(run), "--episodes", "3"]) == 0
    out = capsys.readouterr().out
    assert "group chaser (2 agents): return median" in out
    assert "group runner (1 agents)" in out
    three = "env.pettingzoo.groups={a: [chaser_0], b: [chaser_1], c: [runner_0]}"
    assert main(["eval", str(run), "--episodes", "1", "--set", three]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "one network per group for 2 groups; it cannot play the env's 3 groups" in line, line


def test_run_and_eval_report_each_group(tmp_path, capsys):
    path = tmp_path / "chase.yaml"
    path.write_text(yaml.safe_dump(config()))
    run = tmp_path / "run"
    assert main(["run", str(path), "--into", str(run)]) == 0
    capsys.readouterr()
    assert main(["eval", str(run), "--episodes", "3"]) == 0
    out = capsys.readouterr().out
    assert "group chaser (2 agents): return median" in out
    assert "group runner (1 agents)" in out
    saved = json.loads(next((run).rglob("eval*.json")).read_text())
    assert set(saved["groups"]) == {"chaser", "runner"}


def test_continuous_actions_are_refused_naming_the_agent(tmp_path, capsys):
    raw = config(make="tests.test_agent_groups:continuous")
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["run", str(path), "--runs-dir", str(tmp_path / "runs")]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "agent 'chaser_0': action space Box(" in line and "not Discrete" in line, line
    assert not (tmp_path / "runs").exists()


def continuous(**kwargs):
    env = Chase(**kwargs)
    env._action = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
    return env


# ------------------------------------------------- per_group with the other commands (issue 72)
class Drawn(Chase):
    """The chase env drawing ``rgb_array`` frames (``harness render`` plays only an env that
    draws): row 0 the runner's cell, row 1 the chasers'."""

    metadata = {"name": "chase_v0", "render_modes": ["rgb_array"]}  # noqa: RUF012

    def render(self):
        frame = np.zeros((2, 5, 3), np.uint8)
        for a, cell in self.cells.items():
            frame[int(a != "runner_0"), cell] = 255
        return frame


def drawn(**kwargs):
    return Drawn(**kwargs)


def per_group_file(folder, **pettingzoo) -> str:
    """A per_group config file in ``folder`` (evaluations and checkpoints every 60 steps)."""
    raw = per_group(**pettingzoo)
    raw["eval"]["every"] = raw["checkpoint"]["every"] = 60
    path = folder / "chase.yaml"
    path.write_text(yaml.safe_dump(raw))
    return str(path)


@pytest.fixture(scope="module")
def per_group_run(tmp_path_factory):
    """A per_group run of the drawing chase env, trained once for the module's commands."""
    root = tmp_path_factory.mktemp("per_group")
    config = per_group_file(root, make="tests.test_agent_groups:drawn")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])
        assert main(["run", config, "--no-progress", "--into", str(root / "run")]) == 0
    return root / "run"


def groups_of(model_zip) -> int:
    """The parameter sets of a saved model's Q-network (a per_group model's: its groups)."""
    from harness.sb3.dqn import DoubleDQN

    return DoubleDQN.load(model_zip, device="cpu").q_net.n_agents


def test_a_stopped_per_group_run_resumes_to_the_end(tmp_path, capsys):
    import csv
    import signal

    from harness.sb3.dqn import DoubleDQN
    from tests.conftest import interrupted_past

    run = tmp_path / "run"
    args = ["run", per_group_file(tmp_path), "--no-progress", "--into", str(run)]
    with interrupted_past(70):
        assert main(args) == 128 + signal.SIGINT
    assert not (run / "model.zip").exists()
    assert main(["run", "--resume", str(run), "--no-progress"]) == 0
    assert "resuming at step" in capsys.readouterr().err
    with (run / "episodes.csv").open() as f:
        numbers = [int(row["episode"]) for row in csv.DictReader(f)]
    # 120 transitions are 6 episodes of 6 steps of 3 agents (2 copies); those the stop cut are
    # not resumed
    assert numbers == list(range(len(numbers))) and 4 <= len(numbers) <= 6
    with (run / "evaluations.csv").open() as f:
        assert [row["timesteps"] for row in csv.DictReader(f)] == ["60", "120"]
    model = DoubleDQN.load(run / "model.zip", device="cpu")
    assert model.num_timesteps >= 120 and model.q_net.n_agents == 2  # still a network per group
    assert groups_of(run / "best_model.zip") == 2
    assert main(["eval", str(run), "--episodes", "2"]) == 0
    assert "group runner (1 agents)" in capsys.readouterr().out


def test_tune_render_compare_and_export_of_a_per_group_run(per_group_run, tmp_path, capsys):
    run = per_group_run
    assert main(["tune", str(run), "--episodes", "2", "--temperatures", "0.5", "1"]) == 0
    assert "(team return)" in capsys.readouterr().out
    assert len(json.loads((run / "tune.json").read_text())["rows"]) == 2
    png, gif = tmp_path / "r.png", tmp_path / "r.gif"
    assert main(["render", str(run), "--gif", str(gif), "--out", str(png)]) == 0
    assert png.stat().st_size > 0 and gif.stat().st_size > 0
    capsys.readouterr()
    # A model of two groups plays two: render refuses three as eval does.
    three = "env.pettingzoo.groups={a: [chaser_0], b: [chaser_1], c: [runner_0]}"
    assert main(["render", str(run), "--out", str(png), "--set", three]) == 2
    assert "cannot play the env's 3 groups" in one_error_line(capsys.readouterr().err)
    # An env that does not draw is refused by design (one line, exit 2), per_group or not.
    plain = "env.pettingzoo.make=tests.test_agent_groups:chase"
    assert main(["render", str(run), "--out", str(tmp_path / "n.png"), "--set", plain]) == 2
    assert "does not render rgb_array frames" in one_error_line(capsys.readouterr().err)
    assert main(["eval", str(run), "--episodes", "2"]) == 0
    cmp = tmp_path / "cmp.png"
    assert main(["compare", str(run), "--out", str(cmp), "--reps", "100"]) == 0
    assert "mean test team return" in capsys.readouterr().out and cmp.is_file()
    ref = tmp_path / "reference" / "chase"
    assert main(["export", str(run), "--out", str(ref)]) == 0
    assert groups_of(ref / "model.zip") == 2
    capsys.readouterr()
    assert main(["eval", str(ref), "--episodes", "2"]) == 0
    assert "group chaser (2 agents): return median" in capsys.readouterr().out


def test_seeds_and_a_sweep_of_per_group(tmp_path, capsys):
    config = per_group_file(tmp_path)
    runs = tmp_path / "runs"
    assert main(["run", config, "--seeds", "2", "--no-progress", "--runs-dir", str(runs)]) == 0
    (group,) = runs.iterdir()
    assert "median team return" in capsys.readouterr().err
    assert [groups_of(m) for m in sorted(group.glob("*/model.zip"))] == [2, 2]
    assert main(["eval", str(group), "--episodes", "2"]) == 0
    out = capsys.readouterr().out
    assert out.count("group chaser (2 agents): return median") == 2  # each seed's groups
    over = json.loads((group / "group-eval-2ep.json").read_text())["return_mean_over_seeds"]
    assert over["seeds"] == 2
    space = tmp_path / "space.yaml"
    space.write_text("algo.gamma: {float: [0.8, 0.99]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", config, "--space", str(space), "--trials", "1", "--sweeps-dir", str(sweeps)]
    assert main(args) == 0
    best = json.loads((sweeps / "chase" / "best.json").read_text())
    assert best["objective"].startswith("median team return")
    assert groups_of(Path(best["run"]) / "model.zip") == 2  # the trial's model


# ------------------------------------------- a per_group model plays the groups it was trained for
def files_of(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file()}


TRAINED = "{chaser: [chaser_0, chaser_1], runner: [runner_0]}"


@pytest.mark.parametrize(
    "groups",
    [
        "{chaser: [chaser_0, runner_0], runner: [chaser_1]}",  # agents swapped between groups
        "{runner: [runner_0], chaser: [chaser_0, chaser_1]}",  # the groups' order (their index)
        "{hunters: [chaser_0, chaser_1], prey: [runner_0]}",  # renamed
    ],
    ids=["swapped", "reordered", "renamed"],
)
def test_other_groups_of_as_many_are_refused_in_one_line(per_group_run, capsys, groups):
    from harness.sb3.dqn import DoubleDQN

    run = per_group_run
    policy = DoubleDQN.load(run / "model.zip", device="cpu").policy
    assert policy.groups == {"chaser": ("chaser_0", "chaser_1"), "runner": ("runner_0",)}
    before = files_of(run)
    other = f"env.pettingzoo.groups={groups}"
    for command in (["eval", str(run), "--episodes", "1"], ["tune", str(run), "--episodes", "1"]):
        assert main([*command, "--set", other]) == 2
        line = one_error_line(capsys.readouterr().err)
        assert f"per group for the groups {TRAINED}; the env's groups are {groups}" in line, line
    assert files_of(run) == before


def test_the_same_groups_written_otherwise_still_play(per_group_run, capsys):
    same = "env.pettingzoo.groups={chaser: [chaser_1, chaser_0], runner: [runner_0]}"
    assert main(["eval", str(per_group_run), "--episodes", "1", "--set", same]) == 0
    assert "group chaser (2 agents): return median" in capsys.readouterr().out


@pytest.mark.parametrize("sharing", ["per_agent", "shared_id", "shared"])
def test_another_sharing_is_refused_naming_the_models(per_group_run, capsys, sharing):
    args = ["eval", str(per_group_run), "--episodes", "1", "--set", f"algo.sharing={sharing}"]
    assert main(args) == 2
    line = one_error_line(capsys.readouterr().err)
    expected = (
        f"the model was trained with algo.sharing: per_group (2 groups: {TRAINED}); "
        f"--set algo.sharing={sharing} asks for "
    )
    assert expected in line, line


def test_a_per_group_model_saved_before_it_recorded_its_groups(per_group_run, tmp_path, capsys):
    import shutil

    from harness.sb3.dqn import DoubleDQN

    run = tmp_path / "old"
    shutil.copytree(per_group_run, run)
    model = DoubleDQN.load(run / "model.zip", device="cpu")
    del model.policy_kwargs["groups"]  # (as such a model was saved)
    model.policy.groups = None
    model.save(run / "model.zip")
    assert DoubleDQN.load(run / "model.zip", device="cpu").policy.groups is None
    # It plays as before: the number of groups is all it carries.
    swapped = "env.pettingzoo.groups={chaser: [chaser_0, runner_0], runner: [chaser_1]}"
    assert main(["eval", str(run), "--episodes", "1", "--set", swapped]) == 0
    capsys.readouterr()
    three = "env.pettingzoo.groups={a: [chaser_0], b: [chaser_1], c: [runner_0]}"
    assert main(["eval", str(run), "--episodes", "1", "--set", three]) == 2
    assert "cannot play the env's 3 groups" in one_error_line(capsys.readouterr().err)
    # Its sharing is its run's config's.
    assert main(["eval", str(run), "--episodes", "1", "--set", "algo.sharing=per_agent"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "trained with algo.sharing: per_group (one network for each of 2 groups); " in line


# ------------------------------------------- env.pettingzoo.select: choices by one group's return
def test_the_selection_rule_reads_the_summarys_group():
    from harness.tasks import objective_value, selection_score

    groups = {
        "chaser": {"return_mean": 1.5, "return_median": 2.0},
        "runner": {"return_mean": -1.5, "return_median": -2.0},
    }
    summary = {"source": "pettingzoo", "return_mean": 0.0, "return_median": 0.0, "groups": groups}
    assert selection_score(summary) == objective_value(summary) == 0.0  # the team's
    assert selection_score({**summary, "select": "runner"}) == -1.5
    assert objective_value({**summary, "select": "runner"}) == -2.0
    assert selection_score({**summary, "select": "chaser"}) == 1.5


def selecting(select: str, **pettingzoo) -> dict:
    raw = config(select=select, **pettingzoo)
    # Six evaluations of a sampling policy (the greedy one of so short a run plays alike).
    raw["eval"].update(every=20, temperature=1.0)
    raw["algo"]["learning_starts"] = 10  # (Q-values that move between evaluations)
    raw["phases"][0].update(learning_rate=0.05, train_freq=1)
    return raw


def test_the_summary_carries_the_selected_group():
    env = config_from_dict(config(select="runner")).env
    summary = summarize(run_episodes(make_baseline("random", 0), env, 2, 0))
    assert summary["select"] == "runner"
    assert "select" not in summarize(
        run_episodes(make_baseline("random", 0), config_from_dict(config()).env, 2, 0)
    )


def test_best_model_follows_the_selected_group(tmp_path, monkeypatch):
    import csv

    from harness.tasks.pettingzoo import PettingZooTask
    from harness.training import train as training

    summaries, saved = [], []
    record, save = PettingZooTask.record_evaluation, training.save_model
    monkeypatch.setattr(
        PettingZooTask,
        "record_evaluation",
        staticmethod(lambda summary, rec: (summaries.append(summary), record(summary, rec))),
    )
    monkeypatch.setattr(
        training,
        "save_model",
        lambda model, path: (
            saved.append((int(model.num_timesteps), path.name)),
            save(model, path),
        ),
    )
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(selecting("chaser")))
    assert main(["run", str(path), "--no-progress", "--into", str(tmp_path / "run")]) == 0
    assert {s["return_mean"] for s in summaries} == {0.0}  # the team's: every evaluation ties
    best, expected = -np.inf, []
    with (tmp_path / "run" / "evaluations.csv").open() as f:
        steps = [int(row["timesteps"]) for row in csv.DictReader(f)]
    for step, s in zip(steps, summaries, strict=True):
        if s["groups"]["chaser"]["return_mean"] > best:
            best, expected = s["groups"]["chaser"]["return_mean"], [*expected, step]
    assert len(expected) > 1  # (the team's return would keep the first evaluation's model only)
    assert [step for step, name in saved if name == "best_model.zip"] == expected


def test_tune_chooses_by_the_selected_groups_return(per_group_run, capsys):
    args = ["tune", str(per_group_run), "--episodes", "3", "--temperatures", "0", "0.5", "1", "2"]
    assert main([*args, "--set", "env.pettingzoo.select=runner"]) == 0
    out = capsys.readouterr().out
    assert "(return of group runner)" in out and "(team return)" not in out
    tune = json.loads((per_group_run / "tune-env.pettingzoo.select-runner.json").read_text())
    rows = tune["rows"]
    assert {r["return_mean"] for r in rows} == {0.0}  # the team's: T = 0 by the tie rule
    runner = [r["groups"]["runner"]["return_mean"] for r in rows]
    assert tune["chosen"] == rows[runner.index(max(runner))]["temperature"] != 0.0


def test_a_sweeps_trial_value_is_the_selected_groups_return(tmp_path, capsys, monkeypatch):
    from harness.tasks.pettingzoo import PettingZooTask

    summaries = []
    summarize_ = PettingZooTask.summarize
    monkeypatch.setattr(
        PettingZooTask,
        "summarize",
        classmethod(lambda cls, results: summaries.append(summarize_(results)) or summaries[-1]),
    )
    raw = config(select="chaser")
    raw["eval"]["temperature"] = 1.0  # (the greedy chasers of so short a run catch nothing)
    path = tmp_path / "chase.yaml"
    path.write_text(yaml.safe_dump(raw))
    space = tmp_path / "space.yaml"
    space.write_text("algo.gamma: {float: [0.8, 0.99]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(path), "--space", str(space), "--trials", "2", "--sweeps-dir", str(sweeps)]
    assert main(args) == 0
    assert "validation return of group chaser" in capsys.readouterr().out
    best = json.loads((sweeps / "chase" / "best.json").read_text())
    assert best["objective"] == "median return of group chaser of the config's validation episodes"
    assert best["select"] == "chaser"
    chasers = [s["groups"]["chaser"]["return_median"] for s in summaries]
    assert best["value"] == max(chasers) != 0.0 and len(chasers) == 2  # (the team's median: 0)


@pytest.mark.parametrize("command", ["tune", "eval"])
def test_a_bad_select_through_set_is_one_line(per_group_run, command, capsys):
    args = [command, str(per_group_run), "--episodes", "1", "--set", "env.pettingzoo.select=hunter"]
    before = sorted(p.name for p in per_group_run.iterdir())
    assert main(args) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "env.pettingzoo.select: 'hunter' is no group of the env" in line, line
    assert sorted(p.name for p in per_group_run.iterdir()) == before
