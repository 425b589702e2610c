"""Every registry entry walks through the commands that use it: each policy of
``harness.sb3.registry.POLICIES`` and each planner-backed action kind of
``envs.coverage.frontier.ACTIONS`` through ``harness run`` and ``harness eval`` on a tiny config,
each planner of ``envs.coverage.frontier.PLANNERS`` through ``harness run`` (as the goal
action's planner) and each baseline of ``harness.evaluation.baselines.BASELINES`` (one per
planner among them) through ``harness eval --policy``. The configs
are made from the entries' capabilities, never from their names, so a new entry is walked as
soon as it is registered; and what each entry says of itself is checked against what the
commands build."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from envs.coverage.frontier import ACTIONS, PLANNERS
from envs.coverage.observations import observation_options
from harness.cli import main
from harness.config.loading import config_from_dict
from harness.evaluation.baselines import BASELINES
from harness.sb3.registry import POLICIES, THESIS_NET_ARCH

#: A team map small enough for a 12x12 map that still holds the frontier field (crop >= 7).
TEAMMAP = {"teammap": {"crop": 7, "global_size": 6}}
#: A PettingZoo env whose observations carry an action mask (PettingZoo's Dict convention).
MASKED_ENV = "tests.test_action_masks_pettingzoo:parallel_env"
#: The planner of an action kind that needs one: the first the env can follow.
PLANNER = next(name for name, entry in PLANNERS.items() if entry.in_env)


def tiny_config(env: dict[str, Any], algo: dict[str, Any]) -> dict[str, Any]:
    """A config that trains 200 transitions (100 of them learning) on a 12x12 map, 2 agents
    (or on the pettingzoo env that ``env`` names)."""
    if "pettingzoo" not in env:
        env = {"height": 12, "width": 12, "n_agents": 2, "max_steps": 30, **env}
    return {
        "name": "walk",
        "seed": 0,
        "env": env,
        "vec": {"copies": 2},
        "algo": {
            "buffer_size": 500,
            "learning_starts": 100,
            "target_update_interval": 100,
            "features_dim": 16,
            "cnn_channels": [4, 8],
            **algo,
        },
        "phases": [
            {
                "name": "initial",
                "timesteps": 200,
                "learning_rate": 1e-3,
                "batch_size": 8,
                "train_freq": 2,
                "exploration": {"start": 1.0, "end": 0.1, "steps": 100},
            }
        ],
        "eval": {"every": 0, "episodes": 2},
        "checkpoint": {"every": 0},
    }


def fitting_env(policy: str) -> tuple[dict[str, Any], str | None]:
    """The env options a policy plays, and their action kind: its observation kind and, where
    that observation takes the planner extension, the first action kind whose actions are slots
    exactly when the policy scores slots (with a planner where the kind needs one)."""
    entry = POLICIES[policy]
    if entry.masked:  # a pettingzoo env's action-mask Dict: the tests' masked env
        return {"pettingzoo": {"make": MASKED_ENV, "kwargs": {}}}, None
    observation = TEAMMAP if entry.observation == "teammap" else entry.observation
    if not observation_options(observation).takes_frontier:
        assert not entry.slots, f"{policy} scores slots on an observation without the extension"
        return {"observation": observation}, None
    name, kind = next((n, k) for n, k in ACTIONS.items() if k.slots == entry.slots)
    frontier = {"action": kind().config(), "planner": PLANNER if kind.needs_planner else None}
    return {"observation": observation, "frontier": frontier}, name


#: One run per policy, each with the env it fits and that env's action kind (None: none).
RUNS = {policy: fitting_env(policy) for policy in POLICIES}


def write_config(tmp_path: Path, env: dict[str, Any], algo: dict[str, Any]) -> Path:
    path = tmp_path / "walk.yaml"
    path.write_text(yaml.safe_dump(tiny_config(env, algo), sort_keys=False))
    return path


def eval_json(capsys, *args: str) -> dict[str, Any]:
    capsys.readouterr()
    assert main(["eval", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


# ---------------------------------------------------------------------- the registries' facts
def test_the_walk_covers_every_policy_and_action_kind() -> None:
    assert set(RUNS) == set(POLICIES)
    walked = {action for _, action in RUNS.values() if action is not None}
    assert walked == set(ACTIONS), f"no policy plays {sorted(set(ACTIONS) - walked)}"


def test_each_policy_says_what_it_reads_and_takes() -> None:
    for name, entry in POLICIES.items():
        # Only a team-map policy reads the team map (its CNN needs the images).
        assert entry.team_map == (entry.observation == "teammap"), name
        # A slot scorer reads the slot features beside the team map.
        assert not entry.slots or entry.team_map, name


@pytest.mark.parametrize("policy", list(POLICIES))
def test_a_config_without_net_arch_gets_its_policys_default_head(policy: str) -> None:
    # The defaults as they were when each policy was added (behaviour pinned): the thesis's
    # 3x512 for the MLP policies, none for the team-map ones (their extractor ends in a
    # features_dim-wide layer), one layer of 128 for the slot scorer.
    pinned = {
        "MlpPolicy": [512, 512, 512],
        "DuelingMlpPolicy": [512, 512, 512],
        "TeamMapPolicy": [],
        "DuelingTeamMapPolicy": [],
        "SlotTeamMapPolicy": [128],
    }
    data = tiny_config(RUNS[policy][0], {"policy": policy})
    config = config_from_dict(data)
    assert config.algo.net_arch == list(POLICIES[policy].default_net_arch)
    if policy in pinned:
        assert config.algo.net_arch == pinned[policy]
    # A net_arch given is kept, whatever the policy.
    data["algo"]["net_arch"] = [7]
    assert config_from_dict(data).algo.net_arch == [7]


def test_a_config_that_names_no_policy_gets_the_thesis_head() -> None:
    config = config_from_dict(tiny_config({}, {}))
    assert config.algo.policy == "MlpPolicy"
    assert config.algo.net_arch == list(THESIS_NET_ARCH) == [512, 512, 512]


# ---------------------------------------------------------------------- policies and actions
@pytest.mark.parametrize("policy", list(RUNS))
def test_every_policy_and_action_kind_trains_and_evaluates(policy, tmp_path, capsys):
    from harness import DoubleDQN
    from harness.sb3.policies import DuelingQNetwork, SlotQNetwork, TeamMapExtractor

    entry, (env, action) = POLICIES[policy], RUNS[policy]
    config = write_config(tmp_path, env, {"policy": policy, "net_arch": [16]})
    runs = tmp_path / "runs"
    assert main(["run", str(config), "--runs-dir", str(runs), "--no-progress"]) == 0
    (run,) = runs.iterdir()
    # The model is the entry's class, with the network its capabilities say.
    model = DoubleDQN.load(run / "model.zip", device="cpu")
    assert model.num_timesteps >= 200
    assert type(model.policy) is entry.load()
    assert isinstance(model.q_net, DuelingQNetwork) == entry.dueling
    assert isinstance(model.q_net.features_extractor, TeamMapExtractor) == entry.team_map
    assert isinstance(model.q_net, SlotQNetwork) == entry.slots
    summary = eval_json(capsys, str(run), "--episodes", "2")
    if entry.masked:  # the masked env reports no coverage; it raises on a masked action
        assert summary["episodes"] == 2 and 0.0 <= summary["return_mean"] <= 20.0
        return
    assert summary["episodes"] == 2 and 0.0 < summary["coverage_mean"] <= 1.0
    # The baselines that play the env's action kind play it on the run's own config.
    for name, baseline in BASELINES.items():
        if baseline.needs_action and action is not None:
            if baseline.holds_goals and not ACTIONS[action].holdable:
                continue  # it keeps the goal action's targets: refused on the others
            args = ["--policy", name, "--config", str(run / "config.yaml"), "--episodes", "1"]
            out = eval_json(capsys, *args)
            assert out["policy"] == name and 0.0 < out["coverage_mean"] <= 1.0


def test_the_configs_policy_and_head_fields_name_the_registrys_policies_and_heads() -> None:
    # schema.py's docstrings of algo.policy and algo.net_arch (the configuration page's source)
    # name every policy and every default head the entries carry, and no policy that is not one.
    import inspect
    import re

    from harness.config.schema import AlgoConfig

    source = inspect.getsource(AlgoConfig)
    policy = source.split("policy: str =", 1)[1].split("net_arch:", 1)[0]
    heads = source.split("net_arch: list", 1)[1].split("dueling_aggregator:", 1)[0]
    assert set(re.findall(r"``(\w+Policy)``", policy)) == set(POLICIES)
    for entry in POLICIES.values():
        arch = list(entry.default_net_arch)
        written = f"``{arch}``" if arch else "``[]``"
        assert written.replace(" ", "") in heads.replace(" ", ""), (arch, heads)


# ---------------------------------------------------------------------- planners
#: The policy and action kind a planner is trained under: the first slot-scoring policy and the
#: first action kind that needs a planner (its slot 0 is the planner's choice).
SLOT_POLICY = next(name for name, entry in POLICIES.items() if entry.slots)
PLANNED_KIND = next(kind for kind in ACTIONS.values() if kind.needs_planner)


@pytest.mark.parametrize("planner", list(PLANNERS))
def test_every_planner_trains_under_harness_run_or_is_refused_in_one_line(
    planner, tmp_path, capsys
):
    # env.frontier.planner through `harness run` and the run's `harness eval`: the planners the
    # env can follow train, the others (a baseline only) are refused naming the ones it can.
    env = {
        "observation": TEAMMAP,
        "frontier": {"action": PLANNED_KIND().config(), "planner": planner},
    }
    config = write_config(tmp_path, env, {"policy": SLOT_POLICY, "net_arch": [16]})
    runs = tmp_path / "runs"
    capsys.readouterr()
    rc = main(["run", str(config), "--runs-dir", str(runs), "--no-progress"])
    err = capsys.readouterr().err
    if not PLANNERS[planner].in_env:
        assert rc == 2 and err.count("\n") == 1 and "frontier.planner" in err
        assert not runs.exists() or not any(runs.iterdir())
        return
    assert rc == 0, err
    (run,) = runs.iterdir()
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["env"]["frontier"]["planner"] == planner
    summary = eval_json(capsys, str(run), "--episodes", "2")
    assert summary["episodes"] == 2 and summary["wall_hits_mean"] == 0.0


# ---------------------------------------------------------------------- baselines
#: Three tiny envs: the thesis observation without the extension, the team map with the first
#: action kind that is no slots, and with the first whose actions are slots (so every baseline,
#: planner-backed action or not, has one to play).
BASELINE_ENVS = {
    "plain": {},
    "action": {
        "observation": TEAMMAP,
        "frontier": {"action": next(n for n, k in ACTIONS.items() if not k.slots)},
    },
    "slots": {
        "observation": TEAMMAP,
        "frontier": {
            "action": next(k for k in ACTIONS.values() if k.slots)().config(),
            "planner": PLANNER,
        },
    },
}


def _kind_name(action: str | dict[str, Any]) -> str:
    """The action kind's name in its config form (``NAME`` or ``{NAME: {options}}``)."""
    return action if isinstance(action, str) else next(iter(action))


@pytest.mark.parametrize("setting", list(BASELINE_ENVS))
@pytest.mark.parametrize("baseline", list(BASELINES))
def test_every_baseline_evaluates_where_it_can_and_is_refused_where_not(
    baseline, setting, tmp_path, capsys
):
    env = BASELINE_ENVS[setting]
    kind = observation_options(env.get("observation", "thesis")).name
    slots = setting == "slots"
    holdable = "frontier" in env and ACTIONS[_kind_name(env["frontier"]["action"])].holdable
    # The config must name a policy that fits its env, though a baseline plays instead of it.
    policy = next(n for n, e in POLICIES.items() if e.observation == kind and e.slots == slots)
    config = write_config(tmp_path, env, {"policy": policy})
    args = ["eval", "--policy", baseline, "--config", str(config), "--episodes", "1", "--json"]
    capsys.readouterr()
    rc = main(args)
    out, err = capsys.readouterr()
    entry = BASELINES[baseline]
    if (entry.needs_action and "frontier" not in env) or (entry.holds_goals and not holdable):
        assert rc == 2 and not out
        assert err.count("\n") == 1 and "needs env.frontier.action" in err
        return
    assert rc == 0, err
    summary = json.loads(out)
    assert summary["policy"] == baseline and 0.0 < summary["coverage_mean"] <= 1.0
    # Every planner walks through known free cells only: its baseline never hits a wall.
    if baseline in {entry.baseline for entry in PLANNERS.values()}:
        assert summary["wall_hits_mean"] == 0.0


@pytest.mark.parametrize("command", ["eval", "render"])
def test_the_help_of_commands_that_play_baselines_lists_each_with_its_summary(command, capsys):
    assert all(entry.summary for entry in PLANNERS.values())
    # A planner's baseline says what the planner plays, from the planner's own entry.
    assert {BASELINES[e.baseline].summary for e in PLANNERS.values()} == {
        e.summary for e in PLANNERS.values()
    }
    assert main([command, "--help"]) == 0
    listed = capsys.readouterr().out.split("baselines (--policy NAME --config CONFIG):\n")[1]
    rows = [line.split(None, 1) for line in listed.strip().splitlines()]
    assert rows == [[name, entry.summary] for name, entry in BASELINES.items()]
