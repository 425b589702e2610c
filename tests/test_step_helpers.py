"""The compiled step kernels (``envs/coverage/step.py``) on hand-built batches: walls stop moves,
the lower index is credited first, eq. 3.1 with and without the team share, the thesis window,
and copies of one batch never touch each other."""

from __future__ import annotations

import numpy as np

from envs.coverage.step import move_agents, step_batch, thesis_observation, visit_cells
from envs.coverage.types import CELL_UNVISITED, CELL_VISITED, CELL_WALL


def _grid() -> np.ndarray:
    # A 2x3 map padded by 1: a wall at map cell (0, 1), the rest unvisited.
    cells = np.full((4, 5), CELL_WALL, dtype=np.float32)
    cells[1:3, 1:4] = CELL_UNVISITED
    cells[1, 2] = CELL_WALL
    return cells


def _step(cells, positions, actions, weights=(2.0, -10.0, -1.0, 0.0)):
    b, n = actions.shape
    out = {
        "steps": np.zeros(b, np.int64),
        "n_visited": np.zeros(b, np.int64),
        "new_cells": np.zeros((b, n), np.int64),
        "wall_hits": np.zeros((b, n), np.int64),
        "hit": np.zeros((b, n), np.int64),
        "credited": np.zeros((b, n), np.int64),
        "reward": np.zeros((b, n), np.float64),
    }
    credited_by = np.full((b, 2, 3), -1, np.int16)
    step_batch(
        cells, 1, positions, actions, credited_by, out["steps"], out["n_visited"],
        out["new_cells"], out["wall_hits"], np.array(weights), out["hit"], out["credited"],
        out["reward"],
    )  # fmt: skip
    return out, credited_by


def test_moves_stop_at_walls_and_the_edge_and_stay_never_hits():
    cells = _grid()[None]
    before = cells.copy()
    # right into the wall; right onto free; up off the grid; stay
    positions = np.array([[[0, 0], [1, 0], [0, 2], [1, 2]]], dtype=np.int64)
    hit = np.zeros((1, 4), np.int64)
    move_agents(cells, 1, positions, np.array([[3, 3, 0, 4]]), hit)
    assert positions[0].tolist() == [[0, 0], [1, 1], [0, 2], [1, 2]]
    assert hit.tolist() == [[1, 0, 1, 0]]
    np.testing.assert_array_equal(cells, before)  # moving visits nothing


def test_visit_credits_the_lower_index_and_changes_only_the_cells_it_credits():
    cells, credited_by = _grid()[None], np.full((1, 2, 3), -1, dtype=np.int16)
    before = cells.copy()
    credited = np.zeros((1, 2), np.int64)
    # Both agents stand on (1, 2); agent 0 (the lower index) is credited, agent 1 is not.
    visit_cells(cells, 1, np.array([[[1, 2], [1, 2]]]), credited_by, credited)
    assert credited.tolist() == [[1, 0]]
    assert np.argwhere(cells[0] != before[0]).tolist() == [[2, 3]]
    assert cells[0, 2, 3] == CELL_VISITED
    assert np.argwhere(credited_by[0] >= 0).tolist() == [[1, 2]] and credited_by[0, 1, 2] == 0


def test_reward_follows_eq_3_1():
    cells = _grid()[None]
    cells[0, 1, 1] = CELL_VISITED  # agent 1's own cell
    positions = np.array([[[1, 0], [0, 0]]], dtype=np.int64)
    out, _ = _step(cells, positions, np.array([[3, 3]]))  # onto new ground; into a wall
    assert out["reward"].tolist() == [[1.0, -11.0]]
    assert out["new_cells"].tolist() == [[1, 0]] and out["wall_hits"].tolist() == [[0, 1]]
    assert out["steps"].tolist() == [1] and out["n_visited"].tolist() == [1]


def test_team_share_pays_every_agent_for_the_team_cells():
    # Agents 0 and 2 find a new cell each, agent 1 hits the wall.
    cells = _grid()[None]
    cells[0, 1, 1] = CELL_VISITED  # agent 1's own cell
    positions = np.array([[[1, 0], [0, 0], [1, 2]]], dtype=np.int64)
    actions = np.array([[3, 3, 0]])
    out, _ = _step(cells.copy(), positions.copy(), actions, (2.0, -10.0, -1.0, 1.0))
    assert out["reward"].tolist() == [[3.0, -7.0, 3.0]]  # each paid for the team's 2 cells
    out, _ = _step(cells.copy(), positions.copy(), actions, (2.0, -10.0, -1.0, 0.5))
    assert out["reward"].tolist() == [[2.0, -9.0, 2.0]]  # half own, half the team's


def test_copies_of_a_batch_are_independent():
    cells = np.stack([_grid(), _grid()])
    cells[1, 1:3, 1:4] = CELL_VISITED  # copy 1: everything already visited
    positions = np.array([[[1, 0]], [[1, 0]]], dtype=np.int64)
    out, credited_by = _step(cells, positions, np.array([[3], [3]]))
    assert out["reward"].tolist() == [[1.0], [-1.0]]
    assert credited_by[0, 1, 1] == 0 and credited_by[1, 1, 1] == -1


def test_thesis_window_coordinates_and_nearest_teammate():
    cells = _grid()[None]
    positions = np.array([[[0, 0], [1, 2], [1, 1]]], dtype=np.int64)
    scale = np.array([[1.0, 0.5]], dtype=np.float32)  # 1/(H-1), 1/(W-1) of the 2x3 map
    out = np.zeros((1, 3, 13), np.float32)
    thesis_observation(cells, 1, positions, scale, out)
    w, u = CELL_WALL, CELL_UNVISITED
    assert out[0, 0, :9].tolist() == [w, w, w, w, u, w, w, u, u]
    assert out[0, 0, 9:].tolist() == [0.0, 0.0, 1.0, 0.5]  # nearest of agent 0: agent 2 at (1, 1)
    # Agent 2 at (1, 1) has agents 0 and 1 at distance^2 2 and 1: agent 1 is nearer.
    assert out[0, 2, 9:].tolist() == [1.0, 0.5, 1.0, 1.0]
    # Agent 1 at (1, 2): agent 2 (distance 1) beats agent 0 (distance^2 5).
    assert out[0, 1, 11:].tolist() == [1.0, 0.5]


def test_thesis_ties_go_to_the_lower_index_and_a_lone_agent_sees_itself():
    cells = _grid()[None]
    out = np.zeros((1, 3, 13), np.float32)
    # Agents 0 and 2 both at distance 1 from agent 1: agent 0 wins the tie.
    positions = np.array([[[1, 0], [1, 1], [1, 2]]], dtype=np.int64)
    thesis_observation(cells, 1, positions, np.ones((1, 2), np.float32), out)
    assert out[0, 1, 11:].tolist() == [1.0, 0.0]
    alone = np.zeros((1, 1, 13), np.float32)
    thesis_observation(cells, 1, positions[:, 2:], np.ones((1, 2), np.float32), alone)
    assert alone[0, 0, 9:].tolist() == [1.0, 2.0, 1.0, 2.0]
