"""Training callbacks: schedules, epochs by coverage, periodic calls."""

from __future__ import annotations

from collections import deque
from types import SimpleNamespace

import numpy as np
import pytest
from stable_baselines3.common.logger import Logger

from harness import DoubleDQN, PrioritizedReplayBuffer
from harness.config.schema import EnvConfig
from harness.sb3.schedules import PhaseLinearSchedule
from harness.training.adapters import make_vec_env
from harness.training.callbacks import (
    EpochsByCoverageCallback,
    PeriodicCallback,
    recent_coverages,
)


class StubModel(SimpleNamespace):
    """Just what a callback reads from a model."""

    def get_env(self):
        return None


def stub_model(**kw):
    return StubModel(logger=Logger(folder=None, output_formats=[]), num_timesteps=0, **kw)


def episodes(*coverages, n_agents=2):
    # VecMonitor adds one entry per agent slot; agents of a copy share the team coverage.
    return [{"r": 0.0, "l": 10, "coverage": c} for c in coverages for _ in range(n_agents)]


def test_recent_coverages_groups_agent_entries_into_episodes():
    buf = deque(episodes(0.1, 0.2, 0.3, n_agents=3))
    assert recent_coverages(buf, 2, 3) == [0.2, 0.3]
    assert recent_coverages(buf, 10, 3) == [0.1, 0.2, 0.3]
    assert recent_coverages(deque(), 5, 3) == []


def test_epochs_follow_median_of_recent_coverage():
    model = stub_model(ep_info_buffer=deque(maxlen=200), gradient_steps=99)
    cb = EpochsByCoverageCallback([(0.0, 1), (0.4, 5), (0.6, 7)], window=3, n_agents=2)
    cb.init_callback(model)
    cb.on_training_start({}, {})
    assert model.gradient_steps == 1  # no finished episode yet
    model.ep_info_buffer.extend(episodes(0.3, 0.35, 0.45))
    cb.on_rollout_end()
    assert model.gradient_steps == 1  # median 0.35
    model.ep_info_buffer.extend(episodes(0.5, 0.55))
    cb.on_rollout_end()
    assert model.gradient_steps == 5  # last 3: 0.45, 0.5, 0.55
    model.ep_info_buffer.extend(episodes(0.9, 0.95, 0.1))
    cb.on_rollout_end()
    assert model.gradient_steps == 7  # median 0.9
    model.ep_info_buffer.extend(episodes(0.1, 0.1))
    cb.on_rollout_end()
    assert model.gradient_steps == 1  # coverage fell: back to 1


def test_periodic_callback_fires_at_each_multiple():
    calls = []
    model = stub_model()
    cb = PeriodicCallback(10, lambda m: calls.append(m.num_timesteps))
    cb.init_callback(model)
    cb.on_training_start({}, {})
    for _ in range(12):
        model.num_timesteps += 4
        cb.on_step()
    assert calls == [12, 20, 32, 40]


def test_periodic_callback_zero_never_fires():
    calls = []
    model = stub_model()
    cb = PeriodicCallback(0, lambda m: calls.append(1))
    cb.init_callback(model)
    cb.on_training_start({}, {})
    for _ in range(5):
        model.num_timesteps += 100
        cb.on_step()
    assert calls == []


@pytest.fixture(scope="module")
def tiny_model():
    env = EnvConfig(height=6, width=6, n_agents=2, max_steps=20)
    venv = make_vec_env(env, copies=2, seed=0)
    model = DoubleDQN(
        "MlpPolicy",
        venv,
        learning_starts=50,
        buffer_size=2000,
        policy_kwargs={"net_arch": [16]},
        replay_buffer_class=PrioritizedReplayBuffer,
        replay_buffer_kwargs={"alpha": 0.6, "beta": 0.4},
    )
    yield model
    venv.close()


def test_phase_schedules_count_from_the_phase_start_not_the_run_start(tiny_model):
    # An earlier phase: 200 transitions (SB3's own progress would then run 1 -> 0 over 600).
    tiny_model.learn(200)
    seen = []
    probe = PeriodicCallback(
        1, lambda m: seen.append((m.num_timesteps, m.exploration_rate, m.replay_buffer.beta))
    )
    start = tiny_model.num_timesteps
    phase = 400
    tiny_model.start_phase(phase)
    tiny_model.exploration_schedule = PhaseLinearSchedule(1.0, 0.0, 200, phase)
    tiny_model.beta_schedule = PhaseLinearSchedule(0.4, 1.0, 400, phase)
    tiny_model.learn(phase, callback=probe, reset_num_timesteps=False)
    # The model applies a schedule after each env step (4 transitions each, 2 copies x 2 agents).
    # The probe runs before that update, so it sees the value set after the previous step.
    steps = np.array([t for t, _, _ in seen]) - start
    eps = np.array([e for _, e, _ in seen])
    beta = np.array([b for _, _, b in seen])
    expected_eps = np.clip(1.0 - (steps - 4) / 200, 0.0, 1.0)
    expected_beta = np.clip(0.4 + 0.6 * (steps - 4) / 400, 0.4, 1.0)
    np.testing.assert_allclose(eps[1:], expected_eps[1:], atol=1e-9)
    np.testing.assert_allclose(beta[1:], expected_beta[1:], atol=1e-9)
    assert eps[1] == pytest.approx(1.0 - 4 / 200)  # the phase's start, not 1/3 of the way
    assert tiny_model.exploration_rate == 0.0
    assert tiny_model.replay_buffer.beta == pytest.approx(1.0)


def test_periodic_callback_waits_for_its_condition():
    calls = []
    model = StubModel(num_timesteps=0, ok=False)
    cb = PeriodicCallback(10, lambda m: calls.append(m.num_timesteps), when=lambda m: m.ok)
    cb.init_callback(model)
    cb.on_training_start({}, {})
    for t, ok in [(8, True), (12, False), (16, False), (20, True), (24, True), (32, True)]:
        model.num_timesteps, model.ok = t, ok
        cb.on_step()
    assert calls == [20, 32]  # first step at/past 10 where ok; then at/past 30


def test_the_phase_progress_bar_names_the_phase_stops_at_its_total_and_shows_figures():
    from harness.training.adapters import make_vec_env
    from harness.training.callbacks import PhaseProgressBar

    venv = make_vec_env({"height": 8, "width": 8, "n_agents": 2, "max_steps": 10}, copies=3, seed=0)
    model = DoubleDQN("MlpPolicy", venv, learning_starts=10, buffer_size=500)
    total = 100  # SB3 collects whole rounds (train_freq 4 x 6 slots): 120 transitions
    bar = PhaseProgressBar("initial", total, n_agents=2, every=1)
    model.learn(total, callback=bar)
    assert model.num_timesteps == 120
    assert (bar.pbar.n, bar.pbar.total) == (100, 100)
    figures = bar.postfix()
    assert bar.pbar.desc.startswith("initial: cov ")
    assert set(figures) == {"cov", "ε", "loss"}
    assert figures["ε"] == f"{model.exploration_rate:.2f}"
    assert figures["cov"].endswith("%")
