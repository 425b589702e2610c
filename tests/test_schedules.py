"""ε/β schedules (eq. 4.1) and the epochs-by-coverage table against hand-computed values."""

from __future__ import annotations

import pickle

import pytest

from harness.sb3.schedules import PhaseLinearSchedule, epochs_for, linear

THESIS_INITIAL = [(0.0, 1), (0.40, 5), (0.60, 7)]


@pytest.mark.parametrize(
    ("t", "expected"),
    [(0, 1.0), (250, 0.7625), (500, 0.525), (1000, 0.05), (5000, 0.05), (-3, 1.0)],
)
def test_linear_decay_then_constant(t, expected):
    assert linear(1.0, 0.05, 1000, t) == pytest.approx(expected)


def test_linear_rises_for_beta():
    assert linear(0.4, 1.0, 100, 50) == pytest.approx(0.7)
    assert linear(0.4, 1.0, 100, 100) == 1.0


def test_zero_steps_means_end_value():
    assert linear(1.0, 0.0, 0, 0) == 0.0


def test_phase_schedule_maps_progress_to_phase_steps():
    sched = PhaseLinearSchedule(start=1.0, end=0.0, steps=500, phase_timesteps=1000)
    assert sched(1.0) == 1.0  # first step of the phase
    assert sched(0.75) == pytest.approx(0.5)  # 250 of 500 steps
    assert sched(0.5) == 0.0  # step 500: done decaying
    assert sched(0.0) == 0.0
    assert pickle.loads(pickle.dumps(sched)) == sched  # SB3 may pickle schedules


@pytest.mark.parametrize(
    ("coverage", "epochs"),
    [(None, 1), (0.0, 1), (0.39, 1), (0.40, 5), (0.59, 5), (0.60, 7), (0.95, 7)],
)
def test_thesis_epochs_table(coverage, epochs):
    assert epochs_for(coverage, THESIS_INITIAL) == epochs


def test_epochs_table_below_first_threshold_uses_first_row():
    assert epochs_for(0.1, [(0.2, 3), (0.5, 4)]) == 3
