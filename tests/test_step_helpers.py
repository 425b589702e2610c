"""The step helpers (``envs/coverage/step.py``) do what their docstrings promise: the pure ones
change nothing they are given, ``credit_new_cells`` changes exactly the cells it credits."""

from __future__ import annotations

import numpy as np

from envs.coverage.step import credit_new_cells, resolve_moves, thesis_reward
from envs.coverage.types import CELL_UNVISITED, CELL_VISITED, CELL_WALL


def _grid() -> np.ndarray:
    # A 2x3 map padded by 1: a wall at map cell (0, 1), the rest unvisited.
    cells = np.full((4, 5), CELL_WALL, dtype=np.float32)
    cells[1:3, 1:4] = CELL_UNVISITED
    cells[1, 2] = CELL_WALL
    return cells


def test_resolve_moves_is_pure_and_stops_at_walls():
    cells = _grid()
    before = cells.copy()
    positions, actions = [(0, 0), (1, 0)], [3, 3]  # right into the wall; right onto free
    moved, hit = resolve_moves(cells, 1, positions, actions)
    assert moved == [(0, 0), (1, 1)] and hit == [1, 0]
    np.testing.assert_array_equal(cells, before)
    assert positions == [(0, 0), (1, 0)] and actions == [3, 3]


def test_thesis_reward_is_pure_and_follows_eq_3_1():
    credited, hit = [1, 0], [0, 1]
    assert thesis_reward(credited, hit, new_cell=2.0, wall_hit=-10.0, step=-1.0) == [1.0, -11.0]
    assert credited == [1, 0] and hit == [0, 1]


def test_credit_new_cells_changes_only_the_cells_it_credits():
    cells, credited_by = _grid(), np.full((2, 3), -1, dtype=np.int16)
    before = cells.copy()
    # Both agents enter (1, 2); agent 0 (the lower index) is credited, agent 1 is not.
    assert credit_new_cells(cells, 1, [(1, 2), (1, 2)], credited_by) == [1, 0]
    changed = np.argwhere(cells != before).tolist()
    assert changed == [[2, 3]] and cells[2, 3] == CELL_VISITED
    assert np.argwhere(credited_by >= 0).tolist() == [[1, 2]] and credited_by[1, 2] == 0


def test_team_share_pays_every_agent_for_the_team_cells():
    credited, hit = [1, 0, 1], [0, 1, 0]
    # team 1: every agent is paid for the team's 2 cells; team 0.5: half own, half the team's.
    assert thesis_reward(credited, hit, 2.0, -10.0, -1.0, team=1.0) == [3.0, -7.0, 3.0]
    assert thesis_reward(credited, hit, 2.0, -10.0, -1.0, team=0.5) == [2.0, -9.0, 2.0]
