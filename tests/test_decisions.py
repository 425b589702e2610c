"""Decisions per goal (issue 47): the goal action's ``hold`` (an agent keeps a target it chose in a
slot >= 1 until the target is visited or unreachable) on hand-built grids, the planner unchanged
under it, and the per-decision replay buffer (``algo.per_decision``: the steps of states that
allow one action merged into the transition of the decision before them, with the discount
``gamma ** tau``): its transitions by hand, episode ends, pickling, the config key's checks and a
tiny run end to end."""

from __future__ import annotations

import itertools
import pickle
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.common.utils import set_random_seed

from envs import coverage_v0
from envs.coverage.frontier import FrontierOptions
from envs.coverage.goals import ACTION_MASK_KEY, GOAL_FEATURES, GOALS_KEY
from harness import DoubleDQN
from harness.cli import main
from harness.config.schema import EnvConfig
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes
from harness.sb3.decisions import EXPERT_KEY
from harness.sb3.replay import PrioritizedReplayBuffer
from tests.conftest import refused_run, tiny_goal_run
from tests.replay_variants import (
    PerDecisionDictReplayBuffer,
    PerDecisionPrioritizedDictReplayBuffer,
)

ROOT = Path(__file__).resolve().parents[1]
F = {name: i for i, name in enumerate(GOAL_FEATURES)}


# ---------------------------------------------------------------------- the hold rule (env)
def corridor(hold: bool):
    """A 1x13 corridor (row 1 of a 3x13 grid), agents at columns 2 and 4: the known unvisited
    cells are columns 1, 3 and 5, three clusters."""
    grid = np.ones((3, 13), dtype=bool)
    grid[1] = False
    env = coverage_v0.parallel_env(
        height=3,
        width=13,
        n_agents=2,
        max_steps=30,
        observation={"teammap": {"crop": 7, "global_size": 6}},
        frontier={"action": {"goal": {"k": 4, "hold": hold}}, "planner": "order"},
    )
    obs, _ = env.reset(seed=0, options={"grid": grid, "starts": [(1, 2), (1, 4)]})
    return env, obs


def _cols(env, agent: int) -> list[int]:
    """The corridor columns of an agent's candidates (its cells, padded and flat)."""
    cells = env.frontier_state.candidates.cells[agent]
    return [int(c) % 15 - 1 for c in cells if c >= 0]


def test_a_deviation_is_held_until_its_target_is_visited() -> None:
    env, obs = corridor(hold=True)
    assert _cols(env, 0) == [1, 3, 5]  # the planner's column 1, then the clusters nearest first
    obs, *_ = env.step({"agent_0": 2, "agent_1": 0})  # agent 0 heads for column 5
    assert env.positions.tolist() == [[1, 3], [1, 3]]
    o = obs["agent_0"]
    # Held: one candidate, the held target in slot 0 (two columns to the right, not the
    # planner's choice), and the teammate reads where agent 0 heads.
    assert o[ACTION_MASK_KEY].tolist() == [1, 0, 0, 0] and _cols(env, 0) == [5]
    assert o[GOALS_KEY][0, F["col"]] == pytest.approx(2 / 13)
    assert o[GOALS_KEY][0, F["planner"]] == 0.0
    assert _cols(env, 1)[0] == 5 and obs["agent_1"][GOALS_KEY][0, F["heading"]] == 1.0
    obs, *_ = env.step({"agent_0": 0, "agent_1": 0})  # slot 0 walks on
    assert env.positions.tolist()[0] == [1, 4]
    assert obs["agent_0"][ACTION_MASK_KEY].tolist() == [1, 0, 0, 0] and _cols(env, 0) == [5]
    obs, *_ = env.step({"agent_0": 0, "agent_1": 0})  # reached: let go, choose again
    assert env.positions.tolist()[0] == [1, 5]
    assert env.frontier_state.held.tolist() == [-1, -1]
    assert obs["agent_0"][ACTION_MASK_KEY].tolist() == [1, 1, 0, 0]


def test_without_hold_the_agent_chooses_again_at_the_next_step() -> None:
    env, _ = corridor(hold=False)
    obs, *_ = env.step({"agent_0": 2, "agent_1": 0})
    assert env.positions.tolist() == [[1, 3], [1, 3]]
    assert obs["agent_0"][ACTION_MASK_KEY].sum() >= 2


def test_a_target_a_teammate_visits_is_let_go() -> None:
    env, _ = corridor(hold=True)
    assert _cols(env, 1) == [3, 5, 1]
    # Agent 0 heads for column 5 (held), agent 1 steps onto it at once (its slot 1).
    obs, *_ = env.step({"agent_0": 2, "agent_1": 1})
    assert env.positions.tolist() == [[1, 3], [1, 5]]
    assert env.frontier_state.held.tolist()[0] == -1
    assert obs["agent_0"][ACTION_MASK_KEY].sum() >= 2
    # Agent 1 took a slot >= 1 as well, but reached its target in that step: nothing held.
    assert env.frontier_state.held.tolist()[1] == -1


def test_holds_end_with_the_episode() -> None:
    env, _ = corridor(hold=True)
    env.step({"agent_0": 2, "agent_1": 0})
    assert env.frontier_state.held.tolist()[0] >= 0
    grid = np.ones((3, 13), dtype=bool)
    grid[1] = False
    obs, _ = env.reset(seed=0, options={"grid": grid, "starts": [(1, 2), (1, 4)]})
    assert env.frontier_state.held.tolist() == [-1, -1]
    assert obs["agent_0"][ACTION_MASK_KEY].tolist() == [1, 1, 1, 0]


@pytest.mark.parametrize(("n_agents", "planner"), [(2, "pocket"), (3, "hungarian")])
def test_always_taking_slot_0_with_hold_is_the_planner(n_agents: int, planner: str) -> None:
    def config(hold: bool) -> EnvConfig:
        return EnvConfig(
            n_agents=n_agents,
            height=20,
            width=20,
            max_steps=200,
            observation={"teammap": {"crop": 7, "global_size": 6}},
            frontier={"action": {"goal": {"k": 4, "hold": hold}}, "planner": planner},
        )

    held = run_episodes(make_baseline("frontier_step", 0), config(True), 3, 10)
    plain = run_episodes(make_baseline("frontier_step", 0), config(False), 3, 10)
    assert [r.coverage for r in held] == [r.coverage for r in plain]
    assert [r.new_cells for r in held] == [r.new_cells for r in plain]
    assert [r.steps for r in held] == [r.steps for r in plain]


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_hold_must_be_a_boolean(value) -> None:
    with pytest.raises(ValueError, match=re.escape("frontier.action.goal.hold must be true or")):
        FrontierOptions.parse({"action": {"goal": {"k": 4, "hold": value}}, "planner": "order"})


def test_hold_s_config_form_round_trips_and_is_left_out_when_off() -> None:
    on = {"action": {"goal": {"k": 5, "hold": True}}, "planner": "minpos"}
    assert FrontierOptions.parse(on).config() == on
    off = FrontierOptions.parse({"action": {"goal": {"k": 5, "hold": False}}, "planner": "order"})
    assert off.config() == {"action": {"goal": {"k": 5}}, "planner": "order"}


def test_a_bad_hold_in_a_config_is_one_line_and_exit_code_2(capsys, tmp_path: Path) -> None:
    args = ["run", str(ROOT / "configs" / "goals_2agents.yaml"), "--runs-dir", str(tmp_path)]
    assert main([*args, "--set", "env.frontier.action.goal.hold=maybe"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error:") and "\n" not in err
    assert "frontier.action.goal.hold must be true or false, got 'maybe'" in err
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- the per-decision buffer
#: A tiny Dict space: a value (which step of which slot) and a mask over 3 actions.
SPACE = spaces.Dict(
    {
        "x": spaces.Box(-1e6, 1e6, shape=(1,), dtype=np.float32),
        ACTION_MASK_KEY: spaces.Box(0, 1, shape=(3,), dtype=np.int8),
    }
)
GAMMA = 0.5
DECIDE, FORCED, NONE = [1, 1, 0], [0, 1, 0], [0, 0, 0]


def obs(xs: list[float], masks: list[list[int]]) -> dict[str, np.ndarray]:
    return {
        "x": np.array(xs, dtype=np.float32).reshape(-1, 1),
        ACTION_MASK_KEY: np.array(masks, dtype=np.int8),
    }


@pytest.fixture(params=[PerDecisionDictReplayBuffer, PerDecisionPrioritizedDictReplayBuffer])
def buffer_class(request):
    return request.param


#: One step fed to the buffer: the observation values and masks, actions, rewards, dones, infos.
Step = tuple[list[float], list[list[int]], Any, Any, Any, Any]


def feed(buffer, steps: list[Step]) -> None:
    """Feed ``buffer`` (2 slots) one step per entry: the step's observation values and masks
    (the next step's are its next observation), actions, rewards, dones and infos; the last entry
    is the final next observation (its actions etc. unused)."""
    for (x, m, a, r, d, i), (x2, m2, *_) in itertools.pairwise(steps):
        buffer.add(obs(x, m), obs(x2, m2), np.array(a), np.array(r), np.array(d), i)


def stored(buffer) -> list[tuple[float, int, float, float, float, float, float]]:
    """Each stored transition: obs value, action, next obs value, reward, done, timeout,
    discount."""
    n = buffer.size()
    return [
        (
            float(buffer.observations["x"][k, 0, 0]),
            int(buffer.actions[k, 0, 0]),
            float(buffer.next_observations["x"][k, 0, 0]),
            float(buffer.rewards[k, 0]),
            float(buffer.dones[k, 0]),
            float(buffer.timeouts[k, 0]),
            float(buffer.step_discounts[k, 0]),
        )
        for k in range(n)
    ]


def test_forced_steps_merge_into_the_decision_before_them(buffer_class) -> None:
    buffer = buffer_class(100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA)
    no = [{}, {}]
    feed(
        buffer,
        [
            # slot 0 decides at 0 (action 2), is forced twice, decides again at 3 (action 1);
            # slot 1 decides every step (1-step transitions, as SB3's).
            ([0, 10], [DECIDE, DECIDE], [2, 0], [1.0, 5.0], [False, False], no),
            ([1, 11], [FORCED, DECIDE], [1, 1], [2.0, 6.0], [False, False], no),
            ([2, 12], [FORCED, DECIDE], [1, 2], [4.0, 7.0], [False, False], no),
            ([3, 13], [DECIDE, DECIDE], [1, 0], [8.0, 0.0], [False, False], no),
            ([4, 14], [DECIDE, DECIDE], None, None, None, None),
        ],
    )
    # In the order they complete (slot order within a step).
    assert stored(buffer) == [
        (10, 0, 11, 5.0, 0, 0, 0.5),
        (11, 1, 12, 6.0, 0, 0, 0.5),
        (0, 2, 3, 1 + 0.5 * 2 + 0.25 * 4, 0, 0, 0.125),  # R = 3, tau = 3
        (12, 2, 13, 7.0, 0, 0, 0.5),
        (3, 1, 4, 8.0, 0, 0, 0.5),
        (13, 0, 14, 0.0, 0, 0, 0.5),
    ]
    assert buffer.pending_steps.tolist() == [0, 0]


def test_an_episode_end_stores_the_pending_transition_and_a_time_out_is_no_terminal(
    buffer_class,
) -> None:
    buffer = buffer_class(100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA)
    no = [{}, {}]
    feed(
        buffer,
        [
            ([0, 10], [DECIDE, DECIDE], [2, 1], [1.0, 1.0], [False, False], no),
            # both forced; slot 0 ends terminally (its next obs is a terminal one, any mask),
            # slot 1 by the time limit.
            ([1, 11], [FORCED, FORCED], [1, 1], [2.0, 2.0], [True, True],
             [{}, {"TimeLimit.truncated": True}]),
            # after the reset: a forced first state starts a transition of its own.
            ([20, 30], [FORCED, NONE], [1, 0], [4.0, 3.0], [False, False], no),
            ([21, 31], [DECIDE, DECIDE], None, None, None, None),
        ],
    )  # fmt: skip
    assert stored(buffer) == [
        (0, 2, 20, 2.0, 1, 0, 0.25),
        (10, 1, 30, 2.0, 1, 1, 0.25),
        (20, 1, 21, 4.0, 0, 0, 0.5),
        (30, 0, 31, 3.0, 0, 0, 0.5),  # an all-zero mask allows every action: a decision
    ]
    samples = buffer._get_samples(np.arange(4))
    # SB3's rule: only dones that are not time-outs are terminal.
    assert samples.dones.flatten().tolist() == [1.0, 0.0, 0.0, 0.0]
    assert samples.discounts.flatten().tolist() == [0.25, 0.25, 0.5, 0.5]
    assert samples.rewards.flatten().tolist() == [2.0, 2.0, 4.0, 3.0]


def test_samples_carry_the_discounts_of_their_transitions(buffer_class) -> None:
    set_random_seed(0)
    buffer = buffer_class(100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA)
    no = [{}, {}]
    feed(
        buffer,
        [
            ([0, 10], [DECIDE, DECIDE], [2, 0], [1.0, 5.0], [False, False], no),
            ([1, 11], [FORCED, FORCED], [1, 1], [2.0, 6.0], [False, False], no),
            ([2, 12], [DECIDE, FORCED], [1, 2], [4.0, 7.0], [False, False], no),
            ([3, 13], [DECIDE, DECIDE], None, None, None, None),
        ],
    )
    by_obs = {row[0]: row for row in stored(buffer)}
    samples = buffer.sample(64)
    xs = samples.observations["x"].flatten().tolist()
    assert set(xs) == set(by_obs)
    assert samples.discounts.flatten().tolist() == [by_obs[x][6] for x in xs]
    assert samples.rewards.flatten().tolist() == [by_obs[x][3] for x in xs]
    assert samples.next_observations["x"].flatten().tolist() == [by_obs[x][2] for x in xs]
    if isinstance(buffer, PrioritizedReplayBuffer):  # flat indices are rows of the one column
        assert buffer.n_transitions == 3
        assert samples.indices.max() < 3


def test_a_decision_keeps_the_expert_label_given_at_its_step(buffer_class) -> None:
    buffer = buffer_class(
        100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA, labels=True
    )
    feed(
        buffer,
        [
            # slot 0: labelled 1 at its decision, then forced (a label given on a forced step
            # belongs to no decision); slot 1: labelled 2, then a decision without a label.
            ([0, 10], [DECIDE, DECIDE], [2, 0], [1.0, 5.0], [False, False],
             [{EXPERT_KEY: 1}, {EXPERT_KEY: 2}]),
            ([1, 11], [FORCED, DECIDE], [1, 1], [2.0, 6.0], [False, False],
             [{EXPERT_KEY: 0}, {}]),
            ([2, 12], [DECIDE, DECIDE], None, None, None, None),
        ],
    )  # fmt: skip
    by_obs = {row[0]: k for k, row in enumerate(stored(buffer))}
    labels = buffer.expert_actions[:, 0]
    assert labels[by_obs[0]] == 1
    assert labels[by_obs[10]] == 2
    assert labels[by_obs[11]] == -1
    set_random_seed(0)
    samples = buffer.sample(64)  # the learner's path (prioritized: weights and indices too)
    xs = samples.observations["x"].flatten().tolist()
    assert set(xs) == {0.0, 10.0, 11.0}
    assert samples.experts.flatten().tolist() == [int(labels[by_obs[x]]) for x in xs]
    assert samples.discounts.flatten().tolist() == [stored(buffer)[by_obs[x]][6] for x in xs]
    if isinstance(buffer, PrioritizedReplayBuffer):
        assert samples.weights.shape == (64, 1)
        assert samples.indices.tolist() == [by_obs[x] for x in xs]


@pytest.mark.parametrize("label", [3, -2])
def test_a_label_that_is_no_action_is_refused_where_it_enters(buffer_class, label) -> None:
    # The margin loss trusts the stored labels (it reads no device for a range check).
    buffer = buffer_class(
        100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA, labels=True
    )
    refused = rf"slot 1's {EXPERT_KEY} {label} is no action in \[0, 3\)"
    with pytest.raises(ValueError, match=refused):
        feed(
            buffer,
            [
                ([0, 10], [DECIDE, DECIDE], [2, 0], [1.0, 5.0], [False, False],
                 [{EXPERT_KEY: 1}, {EXPERT_KEY: label}]),
                ([1, 11], [DECIDE, DECIDE], None, None, None, None),
            ],
        )  # fmt: skip


def test_without_labels_the_samples_carry_no_experts(buffer_class) -> None:
    buffer = buffer_class(100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA)
    feed(
        buffer,
        [
            ([0, 10], [DECIDE, DECIDE], [2, 0], [1.0, 5.0], [False, False],
             [{EXPERT_KEY: 1}, {EXPERT_KEY: 2}]),
            ([1, 11], [DECIDE, DECIDE], None, None, None, None),
        ],
    )  # fmt: skip
    assert getattr(buffer.sample(4), "experts", None) is None


def test_a_pickled_buffer_continues_its_pending_transitions(buffer_class) -> None:
    def make():
        return buffer_class(100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA)

    no = [{}, {}]
    first = [
        ([0, 10], [DECIDE, DECIDE], [2, 0], [1.0, 5.0], [False, False], no),
        ([1, 11], [FORCED, FORCED], [1, 1], [2.0, 6.0], [False, False], no),
    ]
    rest = [
        ([1, 11], [FORCED, FORCED], [1, 1], [2.0, 6.0], [False, False], no),
        ([2, 12], [FORCED, DECIDE], [1, 2], [4.0, 7.0], [False, False], no),
        ([3, 13], [DECIDE, DECIDE], None, None, None, None),
    ]
    whole = make()
    feed(whole, first[:1] + rest)
    half = make()
    feed(half, first)
    assert half.size() == 0 and half.pending_steps.tolist() == [1, 1]
    loaded = pickle.loads(pickle.dumps(half))
    feed(loaded, rest)
    assert stored(loaded) == stored(whole) and loaded.size() == 3
    assert stored(loaded)[1] == (0, 2, 3, 1 + 0.5 * 2 + 0.25 * 4, 0, 0, 0.125)


def test_the_buffer_needs_a_mask_and_one_step_transitions() -> None:
    box = spaces.Box(0, 1, (2,), np.float32)
    with pytest.raises(ValueError, match="reads the observation's 'action_mask'"):
        PerDecisionDictReplayBuffer(10, box, spaces.Discrete(3), device="cpu")
    with pytest.raises(ValueError, match="reads the observation's 'action_mask'"):
        PerDecisionDictReplayBuffer(10, spaces.Dict({"x": box}), spaces.Discrete(3), device="cpu")
    with pytest.raises(ValueError, match="n_steps must be 1"):
        PerDecisionPrioritizedDictReplayBuffer(
            10, SPACE, spaces.Discrete(3), device="cpu", n_steps=3
        )


def test_reset_drops_the_pending_transitions(buffer_class) -> None:
    buffer = buffer_class(100, SPACE, spaces.Discrete(3), device="cpu", n_envs=2, gamma=GAMMA)
    feed(
        buffer,
        [
            ([0, 10], [DECIDE, DECIDE], [2, 0], [1.0, 5.0], [False, False], [{}, {}]),
            ([1, 11], [FORCED, DECIDE], None, None, None, None),
        ],
    )
    assert buffer.size() == 1 and buffer.pending_steps.tolist() == [1, 0]
    buffer.reset()
    assert buffer.size() == 0 and buffer.pending_steps.tolist() == [0, 0]


# ---------------------------------------------------------------------- the config key, a run
#: The shipped config with hold and per_decision (its teacher switched off where a test says so).
HOLD_CONFIG = ROOT / "configs" / "goals_2agents_teacher.yaml"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["env.frontier.action=step", "algo.policy=TeamMapPolicy"],
            "algo.per_decision reads the observation's action mask: it needs env.frontier.action",
        ),
        (["algo.prioritized=true", "algo.n_steps=3"], "algo.n_steps must be 1, got 3"),
    ],
)
def test_per_decision_is_refused_in_one_line_where_it_cannot_work(
    overrides: list[str], message: str, capsys, tmp_path: Path
) -> None:
    assert message in refused_run(HOLD_CONFIG, ["algo.teacher=null", *overrides], tmp_path, capsys)


@pytest.mark.parametrize("prioritized", [False, True])
def test_a_run_with_hold_and_per_decision_trains_resumes_and_evaluates(
    prioritized: bool, tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    args = tiny_goal_run(
        HOLD_CONFIG,
        runs,
        algo__teacher="null",
        algo__prioritized=str(prioritized).lower(),
        checkpoint__every="300",
    )
    assert main(args) == 0
    (run,) = runs.iterdir()
    assert (run / "model.zip").is_file()
    # The last checkpoint's buffer (as a resume loads it) holds every slot-step the model took:
    # merged into stored transitions (each with gamma ** tau, some tau > 1) or still pending.
    checkpoint = sorted((run / "checkpoints").glob("step-*"))[-1]
    model = DoubleDQN.load(checkpoint / "model.zip", device="cpu")
    with (checkpoint / "replay_buffer.pkl").open("rb") as f:
        model.load_replay_buffer(f)
    buffer = model.replay_buffer
    assert buffer.decisions is not None and buffer.sampler.prioritized == prioritized
    assert buffer.slots == 4 and buffer.n_envs == 1
    n = buffer.size()
    steps = np.rint(np.log(buffer.step_discounts[:n, 0]) / np.log(0.995)).astype(int)
    assert steps.min() >= 1 and steps.max() > 1
    assert int(steps.sum()) + int(buffer.pending_steps.sum()) == model.num_timesteps
    assert n < model.num_timesteps
    assert main(["eval", str(run), "--episodes", "2"]) == 0
