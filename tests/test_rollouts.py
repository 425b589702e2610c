"""The rollouts of the goal action's candidates (``envs.coverage.rollouts``) as the chooser that
sees only the team's map plays them: the sampled maps, the team's own estimate of its coverage,
the rule against chance gains, its choice on a hand-built corridor, and that nothing it does
depends on the cells nobody has seen (where the true-map teacher's scores do), nor on the
threads that score its maps. The rollouts' scores themselves are tests/test_teacher.py's."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from envs.coverage.planners import _FREE
from envs.coverage.rollouts import (
    RolloutRule,
    SampledChooser,
    believed_coverage,
    clear_of_noise,
    sampled_free,
)
from envs.coverage.teacher import RolloutTeacher
from harness.config.loading import load_config
from harness.factory import make_env
from tests.test_teacher import W, corridor, padded


def test_the_noise_rule_keeps_only_gains_clear_of_the_maps_noise() -> None:
    # Four sampled maps, slot 0 first. Slot 1 gains 2, 4, 6, 8 (mean 5, sd 2.582, se 1.291):
    # 3.87 standard errors. Slot 2 gains +30, -20, +30, -20 (mean 5, se 14.43): noise.
    per_map = np.array(
        [[100.0, 102.0, 130.0], [100.0, 104.0, 80.0], [100.0, 106.0, 130.0], [100.0, 108.0, 80.0]]
    )
    np.testing.assert_allclose(clear_of_noise(per_map, 0.0), [100.0, 105.0, 105.0])
    np.testing.assert_allclose(clear_of_noise(per_map, 3.0), [100.0, 105.0, 100.0])
    np.testing.assert_allclose(clear_of_noise(per_map, 4.0), [100.0, 100.0, 100.0])
    np.testing.assert_allclose(clear_of_noise(per_map[:1], 3.0), [100.0, 102.0, 130.0])


def test_the_corridors_coverage_as_the_team_can_tell_it() -> None:
    planner, _ = corridor([3])
    # Visited: columns 2..6 (5 cells); seen: columns 1..7, all free (share 1); unseen: the 14
    # other columns, expected free at that share: 5 / (7 + 14).
    assert believed_coverage(planner) == pytest.approx(5 / 21)
    # A seen wall lowers the share: column 1 a wall makes 6 of 7 seen cells free, so the 14
    # unseen ones count 12 free cells: 5 / (6 + 12).
    planner.grid[_FREE, planner.stride + 2] = False
    assert believed_coverage(planner) == pytest.approx(5 / 18)


def test_a_sampled_map_keeps_the_seen_cells_and_draws_the_rest_at_their_share() -> None:
    planner, _ = corridor([3])
    planner.grid[_FREE, planner.stride + 2] = False  # seen: 6 of 7 cells free
    maps = np.stack([sampled_free(planner, np.random.default_rng(s)) for s in range(400)])
    rows = maps.reshape(len(maps), 3, W + 2)
    assert not rows[:, [0, 2]].any() and not rows[:, 1, [0, -1]].any()  # the wall ring
    seen = np.zeros(W, dtype=bool)
    seen[1:8] = True
    inner = rows[:, 1, 1:-1]
    assert (inner[:, seen] == planner.free.reshape(3, -1)[1, 1:-1][seen]).all()
    # 5,600 draws: a standard error of 0.0047 around 6 / 7.
    assert inner[:, ~seen].mean() == pytest.approx(6 / 7, abs=0.02)


def test_the_chooser_leaves_the_dead_end_where_every_map_agrees() -> None:
    planner, cand = corridor([3])
    # Every seen cell free: each sampled map is the whole corridor free, the true one. With 10
    # steps left slot 0 finds 3 cells and slot 1 (the far end) 7 (tests/test_teacher.py), on
    # both maps alike. Scored by the steps to 99 % of the 21 cells (16 more, reached by neither
    # in 10 steps: counted as 11) and then the cells: -11 * (69 padded cells + 1) + cells. A
    # gain of 4 cells with no spread clears any number of standard errors.
    chooser = SampledChooser(samples=2, sigmas=4.0, after=0.0)
    per_map = chooser.per_map(planner, cand, 0, 10, np.random.default_rng(0))
    np.testing.assert_array_equal(per_map, [[-767, -763], [-767, -763]])
    assert chooser.decide(planner, cand, 10, np.random.default_rng(0)).tolist() == [1]
    # Before its coverage (5 / 21 of the corridor) it leaves the planner its choice.
    late = SampledChooser(samples=2, after=0.5)
    assert late.decide(planner, cand, 10, np.random.default_rng(0)).tolist() == [0]
    # An agent that holds a target does not decide.
    held = np.array([padded(7)])
    assert chooser.decide(planner, cand, 10, np.random.default_rng(0), held).tolist() == [0]


def test_the_choosers_parameters_are_checked() -> None:
    for bad in ({"samples": 0}, {"samples": 2.5}, {"sigmas": -1}, {"after": 1.5}, {"threads": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            SampledChooser(**bad)
    with pytest.raises(ValueError, match="horizon"):
        RolloutRule(horizon=0)
    with pytest.raises(TypeError):
        SampledChooser(margin=4)  # the rollouts' rule is the measured one


def _late_state(seed: int):
    """A 4-agent goal env on a 15x15 random map, the planner played to half coverage."""
    config = load_config(
        "configs/goals_4agents.yaml",
        ["env.map=random", "env.height=15", "env.width=15", "env.max_steps=200"],
    )
    env = make_env(config.env)
    env.reset(seed=seed)
    while believed_coverage(env.frontier_state.planner) < 0.5:
        env.step({agent: 0 for agent in env.agents})
    return env


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_nothing_the_chooser_does_depends_on_the_cells_nobody_has_seen(seed: int) -> None:
    env = _late_state(seed)
    frontier = env.frontier_state
    planner, cand = frontier.planner, frontier.candidates
    chooser = SampledChooser(samples=3, sigmas=0.0, after=0.4)
    steps_left = env.max_steps - env.steps
    teacher = RolloutTeacher(reach=0.99)

    def everything() -> tuple:
        rng = np.random.default_rng(seed)
        per_map = [chooser.per_map(planner, cand, a, steps_left, rng) for a in range(4)]
        slots = chooser.decide(planner, cand, steps_left, np.random.default_rng(seed))
        truth = [teacher.scores(planner, cand, a, steps_left) for a in range(4)]
        return believed_coverage(planner), per_map, slots, truth

    before = everything()
    # Redraw the true map where nobody has looked (the ring stays wall).
    unseen = ~planner.seen.reshape(-1, planner.stride)
    unseen[[0, -1]] = unseen[:, [0, -1]] = False
    assert unseen.any()
    true_free = planner.free.copy()
    flip = np.random.default_rng(seed).random(unseen.shape) < 0.5
    planner.free.reshape(unseen.shape)[unseen] = flip[unseen]
    after = everything()
    planner.free[:] = true_free
    assert after[0] == before[0]
    for a in range(4):
        np.testing.assert_array_equal(after[1][a], before[1][a])
    np.testing.assert_array_equal(after[2], before[2])
    # The true-map teacher reads those cells: its scores move (so this check can fail).
    changed = [not np.array_equal(x, y, equal_nan=True) for x, y in zip(after[3], before[3])]
    assert any(changed)


@pytest.mark.parametrize("seed", [3, 6])
def test_maps_scored_side_by_side_give_the_same_scores_and_choices(seed: int) -> None:
    env = _late_state(seed)
    frontier = env.frontier_state
    planner, cand = frontier.planner, frontier.candidates
    steps_left = env.max_steps - env.steps

    def play(chooser: SampledChooser) -> tuple:
        rng = np.random.default_rng(seed)
        per_map = [chooser.per_map(planner, cand, a, steps_left, rng) for a in range(4)]
        # The generator moved on by the same draws: the next episode's maps are the same too.
        return per_map, chooser.decide(planner, cand, steps_left, rng), rng.random()

    alone = play(SampledChooser(samples=5, sigmas=1.0, after=0.4))
    threaded = SampledChooser(samples=5, sigmas=1.0, after=0.4, threads=3)
    for chooser in (threaded, copy.deepcopy(threaded)):  # a copy makes its own threads
        side_by_side = play(chooser)
        for a in range(4):
            np.testing.assert_array_equal(side_by_side[0][a], alone[0][a])
        np.testing.assert_array_equal(side_by_side[1], alone[1])
        assert side_by_side[2] == alone[2]
    assert threaded._map is not map  # the maps were scored on its threads
