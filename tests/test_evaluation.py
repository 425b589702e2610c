"""Seeded greedy evaluation: repeatable, independent of batching, metrics in range."""

from __future__ import annotations

import numpy as np
import pytest

from harness.config.schema import EnvConfig
from harness.evaluation.episodes import run_episodes, summarize

ENV = EnvConfig(height=8, width=8, n_agents=2, max_steps=30)


def seeded_random_policy(obs, envs):
    # Depends only on the observations, so it is repeatable whatever the batching.
    return (
        np.abs(obs[:, 9:13].sum(axis=1) * 1000).astype(int) + obs[:, :9].sum(axis=1).astype(int)
    ) % 5


def test_evaluation_is_repeatable_and_independent_of_copies():
    done: list[int] = []  # episodes finished, after each batch of copies
    a = run_episodes(seeded_random_policy, ENV, episodes=5, seed=7, copies=2, progress=done.append)
    assert done == [2, 4, 5]
    b = run_episodes(seeded_random_policy, ENV, episodes=5, seed=7, copies=5)
    assert [r.coverage for r in a] == [r.coverage for r in b]
    assert [r.wall_hits for r in a] == [r.wall_hits for r in b]
    c = run_episodes(seeded_random_policy, ENV, episodes=5, seed=8, copies=2)
    assert [r.coverage for r in a] != [r.coverage for r in c]


def test_summary_keys_and_ranges():
    results = run_episodes(seeded_random_policy, ENV, episodes=6, seed=0, record_paths=True)
    summary = summarize(results)
    assert summary["episodes"] == 6
    for key in ("coverage_median", "coverage_mean", "coverage_iqr"):
        assert 0.0 <= summary[key] <= 1.0
    assert len(summary["per_agent"]) == 2
    for agent in summary["per_agent"]:
        assert 0.0 <= agent["useful_coverage"] <= 1.0 and 0.0 <= agent["total_coverage"] <= 1.0
    at = list(summary["coverage_at_median"].values())
    assert at == sorted(at) and at[-1] == pytest.approx(summary["coverage_median"])
    r = results[0]
    assert len(r.paths) == 2 and r.paths[0].shape == (31, 2)
    # Team coverage = (start cells + credited cells) / free cells.
    assert r.coverage == pytest.approx((2 + sum(r.new_cells)) / r.free_cells)


def test_softmax_sample_follows_the_hand_computed_cdf():
    from harness.evaluation.episodes import softmax_sample

    # softmax([0, ln 3]) = [0.25, 0.75]: draws below 0.25 pick action 0, the rest action 1.
    q = np.array([[0.0, np.log(3.0)]] * 4)
    picked = softmax_sample(q, 1.0, np.array([0.0, 0.24, 0.26, 0.999]))
    assert picked.tolist() == [0, 0, 1, 1]
    # Temperature 2 on [0, 2]: p0 = 1 / (1 + e) = 0.2689.
    q = np.array([[0.0, 2.0]] * 2)
    assert softmax_sample(q, 2.0, np.array([0.26, 0.28])).tolist() == [0, 1]
    # A wall-like action 10 below the best is (almost) never drawn at temperature 1 ...
    q = np.array([[0.0, -10.0, 0.0]])
    assert softmax_sample(q, 1.0, np.array([0.4999])).tolist() == [0]
    # ... and equal values are drawn uniformly.
    q = np.zeros((4, 4))
    assert softmax_sample(q, 0.5, np.array([0.1, 0.3, 0.6, 0.9])).tolist() == [0, 1, 2, 3]


def test_softmax_sample_matches_the_distribution():
    from harness.evaluation.episodes import softmax_sample

    rng = np.random.default_rng(0)
    q = np.tile([1.0, 0.0, -1.0, 0.5, -3.0], (200_000, 1))
    picked = softmax_sample(q, 0.7, rng.random(len(q)))
    expected = np.exp(q[0] / 0.7) / np.exp(q[0] / 0.7).sum()
    freq = np.bincount(picked, minlength=5) / len(picked)
    np.testing.assert_allclose(freq, expected, atol=4e-3)


class _FixedQ:
    """Stands in for an SB3 model: every observation gets the same Q-values; the greedy choice
    (``predict``) is action 0."""

    class policy:  # mirrors ``model.policy``
        @staticmethod
        def obs_to_tensor(obs):
            import torch as th

            return th.as_tensor(obs), True

    @staticmethod
    def predict(obs, deterministic=True):
        return np.zeros(len(obs), dtype=int), None

    @staticmethod
    def q_net(obs):
        import torch as th

        return th.tensor([[0.0, 0.1, 0.0, 0.1, 0.05]]).repeat(len(obs), 1)


def test_boltzmann_never_picks_an_action_the_mask_rules_out():
    # The goal action's empty slots are masked for the greedy choice; sampling masks them too.
    from harness.evaluation.episodes import model_policy

    class DictQ:
        class policy:
            @staticmethod
            def obs_to_tensor(obs):
                import torch as th

                return {k: th.as_tensor(v) for k, v in obs.items()}, True

        @staticmethod
        def q_net(obs):
            import torch as th

            return th.tensor([[5.0, 0.0, 9.0, 0.0]]).repeat(len(obs["action_mask"]), 1)

    class Env:  # one draw per agent from the copy's generator
        np_random = np.random.default_rng(0)

    mask = np.tile(np.array([[1.0, 1.0, 0.0, 0.0]], dtype=np.float32), (4000, 1))
    mask[::2] = (0, 0, 0, 0)  # a row that allows nothing allows everything (allowed_actions)
    obs = {"x": np.zeros((4000, 1), np.float32), "action_mask": mask}
    picked = model_policy(DictQ(), temperature=2.0)(obs, [Env()])
    assert set(picked[1::2].tolist()) == {0, 1}  # never slot 2, the best but empty one
    assert set(picked[::2].tolist()) == {0, 1, 2, 3}


def test_boltzmann_evaluation_depends_on_the_seed_not_the_batching():
    from harness.evaluation.episodes import model_policy

    policy = model_policy(_FixedQ(), temperature=1.0)
    a = run_episodes(policy, ENV, episodes=5, seed=3, copies=2, record_paths=True)
    b = run_episodes(policy, ENV, episodes=5, seed=3, copies=5, record_paths=True)
    assert [r.coverage for r in a] == [r.coverage for r in b]
    for ra, rb in zip(a, b):
        assert all(np.array_equal(pa, pb) for pa, pb in zip(ra.paths, rb.paths))
    c = run_episodes(policy, ENV, episodes=5, seed=4, copies=5)
    assert [r.coverage for r in a] != [r.coverage for r in c]
    # Greedy (this stand-in always answers action 0, up) stays in one column: less ground.
    greedy = run_episodes(model_policy(_FixedQ()), ENV, episodes=5, seed=3)
    assert np.mean([r.coverage for r in greedy]) < np.mean([r.coverage for r in a])


def test_negative_temperature_is_rejected():
    from harness.evaluation.episodes import model_policy

    with pytest.raises(ValueError, match="temperature"):
        model_policy(_FixedQ(), temperature=-1.0)


def _batch(obs: dict) -> np.ndarray | dict:
    """A batch of one env's per-agent observations, in agent order (as a policy gets them)."""
    rows = list(obs.values())
    if isinstance(rows[0], dict):
        return {key: np.stack([r[key] for r in rows]) for key in rows[0]}
    return np.stack(rows)


def test_steps_to_90_and_99_percent_are_medians_with_none_for_not_reached() -> None:
    from harness.evaluation.episodes import EpisodeResult, median_steps_to, summarize

    def episode(s90, s99):
        return EpisodeResult(
            coverage=1.0 if s99 else 0.95,
            coverage_at=[0.5, 0.9, 1.0],
            wall_hits=[0],
            new_cells=[10],
            steps=100,
            free_cells=20,
            steps_to={"steps_to_90": s90, "steps_to_99": s99},
        )

    results = [episode(40, 80), episode(50, None), episode(60, 90)]
    assert median_steps_to(results, "steps_to_90") == 50
    assert median_steps_to(results, "steps_to_99") == 90  # None counts as slowest
    results.append(episode(70, None))
    summary = summarize(results)
    assert summary["steps_to_90"] == 55
    assert summary["steps_to_99"] is None  # the median episode never reached 99 %


def test_frontier_reaches_full_coverage_of_a_small_map_and_reports_its_speed() -> None:
    from harness.evaluation.baselines import make_baseline

    env = EnvConfig(height=8, width=8, n_agents=2, max_steps=200)
    results = run_episodes(make_baseline("frontier", 0), env, episodes=3, seed=1)
    for r in results:
        assert r.coverage == 1.0
        assert 0 < r.steps_to["steps_to_90"] <= r.steps_to["steps_to_99"] <= 200


# ---------------------------------------------------------------------- the wall shield
SHIELD_ROOM = """
#####
#...#
#.#.#
#####
"""


@pytest.mark.parametrize("observation", ["thesis", "teammap"])
def test_blocked_moves_read_the_walls_next_to_the_agent_from_its_observation(observation):
    from envs import coverage_v0
    from envs.coverage.observations import blocked_moves
    from tests.conftest import grid_from

    grid = grid_from(SHIELD_ROOM)
    env = coverage_v0.parallel_env(
        height=4,
        width=5,
        n_agents=2,
        observation=observation
        if observation == "thesis"
        else {"teammap": {"crop": 5, "global_size": 6}},
    )
    obs, _ = env.reset(seed=0, options={"grid": grid, "starts": [(1, 1), (1, 2)]})
    blocked = blocked_moves(_batch(obs))
    # (1, 1): wall above and left, (2, 1) below and (1, 2) right free.
    # (1, 2): wall above and below (2, 2), (1, 1) and (1, 3) free. Stay is never blocked.
    up, down, left, right, stay = True, False, True, False, False
    assert blocked.tolist() == [[up, down, left, right, stay], [True, True, False, False, False]]
    # With the frontier step (a sixth action, only ever through free cells): never blocked.
    six = blocked_moves(_batch(obs), 6)
    assert six[:, :5].tolist() == blocked.tolist() and not six[:, 5].any()


class FixedQModel:
    """A stand-in for an SB3 model whose Q-values prefer ``up``, then ``stay``, whatever it sees."""

    class policy:
        @staticmethod
        def obs_to_tensor(obs):
            import torch as th

            n = len(obs["local"]) if isinstance(obs, dict) else len(obs)
            return th.zeros(n, 1), True

    @staticmethod
    def predict(obs, deterministic=True):
        return np.zeros(len(obs), dtype=np.int64), None  # up, the best Q-value

    @staticmethod
    def q_net(x):
        import torch as th

        return th.tensor([[5.0, -3.0, -2.0, -4.0, 1.0]]).repeat(len(x), 1)


@pytest.mark.parametrize("temperature", [0.0, 0.5])
def test_shielded_test_policy_never_hits_a_wall_where_the_plain_one_pushes_into_it(temperature):
    from harness.evaluation.episodes import model_policy

    env = EnvConfig(height=8, width=8, n_agents=2, max_steps=40)
    plain = run_episodes(model_policy(FixedQModel, temperature), env, episodes=4, seed=3)
    shielded = run_episodes(
        model_policy(FixedQModel, temperature, shield=True), env, episodes=4, seed=3
    )
    assert sum(sum(r.wall_hits) for r in plain) > 40  # it walks up to the wall and pushes on
    assert all(sum(r.wall_hits) == 0 for r in shielded)
    # Shielded, the agents still follow the Q-values among the free moves: up while they can.
    assert all(r.coverage > 0 for r in shielded)


def test_shield_masks_blocked_actions_in_the_boltzmann_draw():
    from harness.evaluation.episodes import model_policy

    obs = np.zeros((3, 13), dtype=np.float32)
    obs[:, 1] = 1.0  # a wall above every agent: `up`, the best Q-value, is blocked

    class Env:  # episode_draws reads one np_random per env copy
        def __init__(self) -> None:
            self.np_random = np.random.default_rng(0)

    policy = model_policy(FixedQModel, temperature=0.5, shield=True)
    actions = policy(obs, [Env()])
    assert (actions != 0).all() and len(actions) == 3
    # Greedy and shielded: the best free move is stay (1.0 > -2.0 > -3.0 > -4.0).
    assert model_policy(FixedQModel, 0.0, shield=True)(obs, [Env()]).tolist() == [4, 4, 4]


class StepQModel(FixedQModel):
    """Six actions: Q = [5, -3, -2, -4, 1, 3.5]; the frontier step (5) is 1.5 below ``up``."""

    class action_space:
        n = 6

    @staticmethod
    def q_net(x):
        import torch as th

        return th.tensor([[5.0, -3.0, -2.0, -4.0, 1.0, 3.5]]).repeat(len(x), 1)
