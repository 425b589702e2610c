"""DoubleDQN's update: its hooks (TD target, loss terms, weighting) on hand-computed tensors, the
non-finite guard, and the count of host reads per training call."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.buffers import ReplayBufferSamples
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv

import harness.sb3.losses
from harness import DoubleDQN
from harness.sb3.dqn import NonFiniteLossError, StepStats
from tests import test_action_mask as masking
from tests.replay_variants import (
    DevicePrioritizedDictReplayBuffer,
    DevicePrioritizedReplayBuffer,
    PrioritizedDictReplayBuffer,
)
from tests.test_double_dqn import (
    GAMMA,
    S_NEXT,
    S,
    add_transition,
    logged,
    make_linear_model,
    make_prioritized_model,
)


def batch(
    rewards: list[float],
    dones: list[float] | None = None,
    actions: list[int] | None = None,
    obs: Any = S,
    next_obs: Any = S_NEXT,
    **extra: th.Tensor,
) -> Any:
    """A batch of ``len(rewards)`` samples of the transition ``obs -> next_obs`` (arrays of one
    row, repeated), as a ``ReplayBufferSamples`` (with ``extra`` fields: a subclass adding
    them)."""
    n = len(rewards)

    def rows(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: th.as_tensor(v).float().repeat(n, 1) for k, v in x.items()}
        return th.as_tensor(x).repeat(n, 1)

    fields = {
        "observations": rows(obs),
        "actions": th.tensor(actions or [1] * n).reshape(-1, 1),
        "next_observations": rows(next_obs),
        "dones": th.tensor(dones or [0.0] * n).reshape(-1, 1),
        "rewards": th.tensor(rewards).reshape(-1, 1),
    }
    if not extra:
        return ReplayBufferSamples(**fields)
    samples = type("Samples", (), {**fields, **extra})
    return samples()


def column(values: list[float]) -> th.Tensor:
    return th.tensor(values).reshape(-1, 1)


# --------------------------------------------------------------------------------- TD target
# The linear model of tests/test_double_dqn.py: online Q(s') = [2, 1], target Q(s') = [0, 3],
# gamma = 0.5.


def test_td_target_hook_double_and_plain_hand_computed() -> None:
    model = make_linear_model()
    samples = batch(rewards=[1.0, -2.0], dones=[0.0, 1.0])
    # Double-Q: 1 + 0.5 * Q_target(s', argmax [2, 1] = 0) = 1 + 0.5 * 0 = 1; done: -2
    th.testing.assert_close(model._td_target(samples), column([1.0, -2.0]))
    model.double_q = False
    # plain: 1 + 0.5 * max(0, 3) = 2.5; done: -2
    th.testing.assert_close(model._td_target(samples), column([2.5, -2.0]))
    assert not model._td_target(samples).requires_grad


def test_td_target_hook_uses_the_samples_discounts() -> None:
    model = make_linear_model(double_q=False)
    samples = batch(rewards=[1.0, 1.0], discounts=column([GAMMA, GAMMA**2]))
    # 1 + 0.5 * 3 = 2.5 and 1 + 0.25 * 3 = 1.75
    th.testing.assert_close(model._td_target(samples), column([2.5, 1.75]))


@pytest.mark.parametrize(("double_q", "target"), [(True, 1.5), (False, 2.5)])
def test_td_target_hook_masks_the_next_observations_blocked_actions(
    double_q: bool, target: float
) -> None:
    # Online Q(s') = [0, 3, 1, 2], target Q(s') = [3, 4, 1, 7]; the next observation allows
    # actions 0 and 2. Double-Q: online argmax over {0, 2} = 2, target 1 -> 1 + 0.5 * 1 = 1.5.
    # Plain: max over {0, 2} of the target = 3 -> 1 + 0.5 * 3 = 2.5.
    model = masking.make_model(
        n_envs=1, q=[0.0, 3.0, 1.0, 2.0], target_q=[3.0, 4.0, 1.0, 7.0], double_q=double_q
    )
    obs = masking.observations([[1, 1, 1, 1]])
    next_obs = masking.observations([[1, 0, 1, 0]])
    samples = batch(rewards=[1.0], obs=obs, next_obs=next_obs)
    th.testing.assert_close(model._td_target(samples), column([target]))


# ------------------------------------------------------------------------------ loss terms


def test_td_loss_hook_is_the_per_sample_huber_loss() -> None:
    model = make_linear_model()
    current, target = column([0.0, 0.0, 3.0, -1.0]), column([0.5, 2.5, 3.0, 1.0])
    # |d| <= 1: d**2 / 2; above: |d| - 1/2. d = 0.5, 2.5, 0, 2 -> 0.125, 2.0, 0, 1.5
    th.testing.assert_close(model._td_loss(current, target), column([0.125, 2.0, 0.0, 1.5]))


def test_margin_loss_hook_hand_computed_and_its_statistics() -> None:
    model = make_linear_model(expert_action=1, margin=0.8, margin_weight=0.5)
    q = th.tensor([[0.0, 0.0], [2.0, 1.0], [1.0, 3.0]])
    stats = StepStats()
    term = model._margin_loss(batch(rewards=[0.0] * 3), q, stats)
    # max_a [Q + 0.8 (a != 1)] - Q(1): max(0.8, 0) - 0 = 0.8; max(2.8, 1) - 1 = 1.8;
    # max(1.8, 3) - 3 = 0; times the weight 0.5
    th.testing.assert_close(term, column([0.4, 0.9, 0.0]))
    values = stats.read()
    assert values["margin_loss"] == pytest.approx([(0.8 + 1.8 + 0.0) / 3])  # unweighted
    # greedy actions 0 (a tie goes to 0), 0, 1: one of three is the expert's
    assert values["expert_agreement"] == pytest.approx([1 / 3])


def test_margin_loss_hook_follows_each_sample_s_own_label_and_skips_unlabelled_ones() -> None:
    model = make_linear_model(margin=0.8, margin_weight=0.5)  # no expert_action: labels only
    q = th.tensor([[0.0, 0.0], [2.0, 1.0], [1.0, 3.0], [5.0, 0.0]])
    experts = th.tensor([[1], [0], [1], [-1]])  # the last sample has no label
    stats = StepStats()
    samples = batch(rewards=[0.0] * 4, experts=experts)
    term = model._margin_loss(samples, q, stats)
    # label 1: max(0.8, 0) - 0 = 0.8; label 0: max(2, 1.8) - 2 = 0; label 1: max(1.8, 3) - 3 =
    # 0; no label: 0. Times 0.5.
    th.testing.assert_close(term, column([0.4, 0.0, 0.0, 0.0]))
    values = stats.read()
    assert values["margin_loss"] == pytest.approx([0.8 / 3])  # over the 3 labelled
    # greedy 0, 0, 1 against labels 1, 0, 1: two of three
    assert values["expert_agreement"] == pytest.approx([2 / 3])
    # the term is part of the loss whenever the samples carry labels
    terms = model._loss_terms(samples, q, column([0.0] * 4), column([0.0] * 4))
    assert len(terms) == 2


def test_margin_loss_hook_reads_no_device_for_the_labels(monkeypatch: pytest.MonkeyPatch) -> None:
    # The labels' range is the buffer's check, where they enter (harness.sb3.decisions): the
    # term itself reads nothing back from the device, so a training call keeps its one read.
    model = make_linear_model(margin=0.8, margin_weight=0.5)
    samples = batch(rewards=[0.0] * 2, experts=th.tensor([[1], [-1]]))
    counts = count_host_reads(monkeypatch)
    model._margin_loss(samples, th.tensor([[0.0, 0.0], [2.0, 1.0]]), StepStats())
    assert counts == {}


def test_loss_terms_are_the_td_loss_then_the_margin() -> None:
    q = th.tensor([[2.0, 1.0]])
    current, target = column([1.0]), column([3.0])
    plain = make_linear_model()._loss_terms(batch(rewards=[0.0]), q, current, target)
    assert len(plain) == 1
    th.testing.assert_close(plain[0], column([1.5]))  # Huber(2) = 2 - 0.5
    model = make_linear_model(expert_action=1, margin=0.8, margin_weight=0.5)
    td, margin = model._loss_terms(batch(rewards=[0.0]), q, current, target)
    th.testing.assert_close(td, column([1.5]))
    th.testing.assert_close(margin, column([0.5 * (2.8 - 1.0)]))


class ConstantTermDQN(DoubleDQN):
    """A new loss term in one method: ``bonus`` added to every sample's loss."""

    bonus = 0.25

    def _loss_terms(self, replay_data: Any, *args: Any, **kwargs: Any) -> list[th.Tensor]:
        terms = super()._loss_terms(replay_data, *args, **kwargs)
        return [*terms, th.full_like(terms[0], self.bonus)]


def test_a_new_loss_term_reaches_the_trained_loss() -> None:
    model = make_linear_model(cls=ConstantTermDQN)
    add_transition(model, reward=1.0)
    model.train(gradient_steps=1, batch_size=4)
    # test_double_q_update_hand_computed's Huber 0.5, plus the term's 0.25
    assert logged(model, "train/loss") == pytest.approx(0.5 + 0.25)


# ------------------------------------------------------------------------------- weighting


def test_weighted_loss_hook_is_the_is_weighted_mean() -> None:
    model = make_linear_model()
    losses = column([1.0, 2.0, 3.0, 4.0])
    # unweighted: 10 / 4; weights [1, 0.5, 0.25, 1]: (1 + 1 + 0.75 + 4) / 4 = 1.6875
    assert model._weighted_loss(losses, batch(rewards=[0.0] * 4)).item() == pytest.approx(2.5)
    weighted = batch(rewards=[0.0] * 4, weights=column([1.0, 0.5, 0.25, 1.0]))
    assert model._weighted_loss(losses, weighted).item() == pytest.approx(1.6875)


def test_weighted_loss_hook_with_per_agent_sets() -> None:
    from tests.test_sharing import TwoAgentTinyEnv

    model = DoubleDQN(
        "PerAgentMlpPolicy",
        DummyVecEnv([TwoAgentTinyEnv]),
        policy_kwargs={"net_arch": [], "n_agents": 2},
        device="cpu",
        seed=0,
    )
    agents = [0, 1, 1, 1]
    obs = th.tensor([[0.0, 0.0, 1.0 - a, float(a)] for a in agents])
    samples = ReplayBufferSamples(obs, th.zeros(4, 1), obs, th.zeros(4, 1), th.zeros(4, 1))
    losses = column([1.0, 2.0, 3.0, 4.0])
    # each set's mean over its own samples, summed: 1 + (2 + 3 + 4) / 3 = 4
    assert model._weighted_loss(losses, samples).item() == pytest.approx(4.0)
    # IS weights [1, 0.5, 1, 0.25], normalised by each agent's own largest (1 and 1):
    # agent 0: 1 * 1 = 1; agent 1: (0.5 * 2 + 1 * 3 + 0.25 * 4) / 3 = 5 / 3
    weighted = samples._replace(rewards=th.zeros(4, 1))
    weighted = type("Samples", (), {**weighted._asdict(), "weights": column([1, 0.5, 1, 0.25])})
    assert model._weighted_loss(losses, weighted()).item() == pytest.approx(1 + 5 / 3)
    model.env.close()


# ------------------------------------------------------------------------ non-finite guard


def test_a_nan_loss_stops_the_call_at_its_end_naming_the_first_update() -> None:
    model = make_linear_model(learning_rate=1e-3, buffer_size=4)
    add_transition(model, reward=float("nan"))
    model._n_updates = 7
    with pytest.raises(NonFiniteLossError, match=r"the loss became nan at step 0 \(update 7\)"):
        model.train(gradient_steps=3, batch_size=4)
    assert model._n_updates == 7  # the failed call counts no update


def test_check_finite_names_the_first_bad_update() -> None:
    model = make_linear_model()
    model._n_updates = 10
    model._check_finite({"loss": np.array([0.5, 1.0])})  # finite: nothing
    with pytest.raises(NonFiniteLossError, match=r"became inf at step 0 \(update 11\)"):
        model._check_finite({"loss": np.array([0.5, np.inf, np.nan])})


def test_a_nan_td_error_on_the_device_path_stops_the_call_at_its_end_naming_the_update() -> None:
    # The device path reads nothing per step: the NaN's priority is written, and the call's one
    # read finds the loss of the step that met it.
    model = make_prioritized_model(DevicePrioritizedReplayBuffer, learning_rate=1e-3)
    model.replay_buffer.rewards[0, 0] = float("nan")  # type: ignore[union-attr]
    model._n_updates = 4
    with pytest.raises(NonFiniteLossError, match=r"the loss became nan at step 0 \(update 4\)"):
        model.train(gradient_steps=3, batch_size=4)
    assert model._n_updates == 4


def test_a_nan_td_error_stops_a_prioritized_call_before_its_priorities_are_written() -> None:
    model = make_prioritized_model(learning_rate=1e-3)
    buffer = model.replay_buffer
    buffer.rewards[0, 0] = np.nan  # type: ignore[union-attr]
    before = buffer.raw_priorities.copy()  # type: ignore[union-attr]
    with pytest.raises(NonFiniteLossError, match=r"the loss became nan at step 0 \(update 0\)"):
        model.train(gradient_steps=3, batch_size=4)
    np.testing.assert_array_equal(buffer.raw_priorities, before)  # type: ignore[union-attr]


# ------------------------------------------------------------------------------ host reads


def test_step_stats_read_everything_in_one_transfer(monkeypatch: pytest.MonkeyPatch) -> None:
    reads = []
    to_host = harness.sb3.losses._to_host
    monkeypatch.setattr(harness.sb3.losses, "_to_host", lambda t: reads.append(t) or to_host(t))
    stats = StepStats()
    assert stats.read() == {} and reads == []  # nothing added: no read
    for step in range(3):
        stats.add("loss", th.tensor(float(step)))
        stats.add("mean", th.tensor([step / 4], dtype=th.float64))
    values = stats.read()
    assert len(reads) == 1
    assert values["loss"].tolist() == [0.0, 1.0, 2.0]
    assert values["mean"].tolist() == [0.0, 0.25, 0.5]
    assert values["loss"].dtype == np.float64
    assert stats.read() == {}  # read once: forgotten


READS = ("item", "tolist", "numpy", "cpu", "__bool__", "__float__", "__int__", "__index__")
READS += ("__array__", "__format__")
TORCH = str(Path(th.__file__).parent)


def count_host_reads(monkeypatch: pytest.MonkeyPatch) -> Counter[str]:
    """Count ``_to_host`` calls (under ``"_to_host"``), and any other read of a tensor's values
    from outside torch (under the reading function's name): ``.item()``, ``.cpu()``,
    ``bool(t)``, ``np.asarray(t)``, ... Reads inside torch (an optimizer's step counter, which
    lives on the CPU whatever the device) are torch's and left out."""
    counts: Counter[str] = Counter()
    to_host = harness.sb3.losses._to_host

    def counted_to_host(tensor: th.Tensor) -> np.ndarray:
        counts["_to_host"] += 1
        return to_host(tensor)

    monkeypatch.setattr(harness.sb3.losses, "_to_host", counted_to_host)
    for name in READS:
        original = getattr(th.Tensor, name)

        def spy(self: th.Tensor, *args: Any, _original: Any = original, **kwargs: Any) -> Any:
            caller = sys._getframe(1).f_code
            if not caller.co_filename.startswith(TORCH) and caller.co_name != "_to_host":
                counts[caller.co_name] += 1
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(th.Tensor, name, spy)
    return counts


def _uniform() -> DoubleDQN:
    model = make_linear_model(learning_rate=1e-3)
    add_transition(model, reward=1.0)
    return model


def _n_step() -> DoubleDQN:
    model = make_linear_model(learning_rate=1e-3, n_steps=2, buffer_size=8)
    for _ in range(3):
        add_transition(model, reward=1.0)
    return model


def _device_n_step() -> DoubleDQN:
    model = make_linear_model(
        learning_rate=1e-3,
        buffer_size=8,
        replay_buffer_class=DevicePrioritizedReplayBuffer,
        replay_buffer_kwargs=dict(n_steps=2, gamma=GAMMA),
    )
    for _ in range(3):
        add_transition(model, reward=1.0)
    return model


def _masked_prioritized_imitation(
    buffer_class: type[PrioritizedDictReplayBuffer] = PrioritizedDictReplayBuffer,
) -> DoubleDQN:
    model = masking.make_model(
        n_envs=1,
        q=masking.Q_ONLINE,
        expert_action=1,
        replay_buffer_class=buffer_class,
        replay_buffer_kwargs=dict(alpha=0.6, beta=0.4),
    )
    assert model.replay_buffer is not None
    for mask in ([1, 0, 1, 0], [0, 1, 1, 1], [0, 0, 0, 0]):
        model.replay_buffer.add(
            masking.observations([[1, 1, 1, 1]]), masking.observations([mask]),
            np.array([[0]]), np.array([1.0]), np.array([False]), [{}],
        )  # fmt: skip
    return model


@pytest.mark.parametrize(
    ("setup", "priority_transfers"),
    [
        (_uniform, False),
        (_n_step, False),
        (lambda: make_prioritized_model(learning_rate=1e-3), True),
        (_masked_prioritized_imitation, True),
        # The device path: the priorities stay where the buffer is, one read per call in all.
        (lambda: make_prioritized_model(DevicePrioritizedReplayBuffer, learning_rate=1e-3), False),
        (lambda: _masked_prioritized_imitation(DevicePrioritizedDictReplayBuffer), False),
        (lambda: _device_n_step(), False),
    ],
    ids=[
        "uniform",
        "n-step",
        "prioritized",
        "masked-prioritized-imitation",
        "device-prioritized",
        "device-masked-prioritized-imitation",
        "device-prioritized-n-step",
    ],
)
def test_one_host_read_per_training_call_besides_the_priorities(
    monkeypatch: pytest.MonkeyPatch, setup: Any, priority_transfers: bool
) -> None:
    model = setup()
    steps = 5
    counts = count_host_reads(monkeypatch)
    for call in range(1, 3):
        counts.clear()
        model.train(gradient_steps=steps, batch_size=4)
        # the statistics once per call; with PER the new priorities once per gradient step
        assert counts == {"_to_host": 1 + (steps if priority_transfers else 0)}, call
        assert model._n_updates == steps * call
    assert np.isfinite(logged(model, "train/loss"))


def test_the_spy_sees_a_read_in_the_update(monkeypatch: pytest.MonkeyPatch) -> None:
    # The count above can fail: a hook that reads a value is seen.
    model = _uniform()
    td_loss = model._td_loss

    def reading_td_loss(current_q: th.Tensor, target_q: th.Tensor) -> th.Tensor:
        assert float(target_q.mean()) == pytest.approx(1.0)
        return td_loss(current_q, target_q)

    monkeypatch.setattr(model, "_td_loss", reading_td_loss)
    counts = count_host_reads(monkeypatch)
    model.train(gradient_steps=3, batch_size=4)
    assert counts == {"_to_host": 1, "reading_td_loss": 3}


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs CUDA; the spy above counts on CPU")
@pytest.mark.parametrize("n_steps", [1, 2])
def test_one_cuda_synchronisation_per_training_call_on_the_device_path(n_steps: int) -> None:
    # What the spy counts on CPU tensors, counted by CUDA itself: every synchronising operation
    # warns in torch's sync debug mode.

    model = make_linear_model(
        learning_rate=1e-3,
        buffer_size=8,
        device="cuda",
        replay_buffer_class=DevicePrioritizedReplayBuffer,
        replay_buffer_kwargs=dict(n_steps=n_steps, gamma=GAMMA),
    )
    for reward in (1.0, 3.0, 2.0):
        add_transition(model, reward=reward)
    model.train(gradient_steps=2, batch_size=4)  # first call: CUDA's lazy set-up
    syncs = cuda_synchronisations(lambda: model.train(gradient_steps=5, batch_size=4))
    assert len(syncs) == 1, syncs


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs CUDA")
def test_per_agent_sets_route_without_a_synchronisation_on_the_device_path() -> None:
    # The routing block is as wide as the batch on an accelerator: no read of the group sizes.
    from tests.test_sharing import TwoAgentTinyEnv

    model = DoubleDQN(
        "PerAgentMlpPolicy",
        DummyVecEnv([TwoAgentTinyEnv]),
        policy_kwargs={"net_arch": [8], "n_agents": 2},
        learning_rate=1e-3,
        buffer_size=8,
        device="cuda",
        replay_buffer_class=DevicePrioritizedReplayBuffer,
        seed=0,
    )
    model.set_logger(configure(folder=None, format_strings=[]))
    for agent in (0, 1, 1):
        obs = np.array([[0.5, -0.5, 1.0 - agent, float(agent)]], dtype=np.float32)
        model.replay_buffer.add(obs, obs, np.array([[1]]), np.array([1.0]), np.array([False]), [{}])
    model.train(gradient_steps=2, batch_size=4)  # first call: CUDA's lazy set-up
    syncs = cuda_synchronisations(lambda: model.train(gradient_steps=5, batch_size=4))
    assert len(syncs) == 1, syncs
    model.env.close()


def cuda_synchronisations(call: Any) -> list[str]:
    """The synchronising operations CUDA's sync debug mode reports while ``call()`` runs."""
    import warnings

    th.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            call()
    finally:
        th.cuda.set_sync_debug_mode("default")
    return [str(w.message) for w in caught if "synchroniz" in str(w.message)]
