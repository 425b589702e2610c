"""harness.sb3.graphs: a gradient step recorded as a CUDA graph trains as the step without one.

The recorded path needs a GPU (skipped elsewhere); what it relies on in the device buffer (the
draws given from outside, its numbers on the device, writes in place) is checked on CPU tensors.
"""

from __future__ import annotations

import pickle
import warnings
from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv

from harness import DoubleDQN
from harness.sb3.dqn import StepStats
from tests.replay_variants import DevicePrioritizedReplayBuffer, DeviceReplayBuffer
from tests.test_double_dqn import TinyEnv
from tests.test_dqn_update import cuda_synchronisations

cuda = pytest.mark.skipif(not th.cuda.is_available(), reason="needs CUDA")


def _model(
    device: str, *, graph: bool = True, uniform: bool = False, **buffer_kwargs: Any
) -> DoubleDQN:
    """A small DoubleDQN with the prioritized device buffer (``uniform``: the uniform one)."""
    per = {} if uniform else {"alpha": 0.6, "beta": 0.4}
    model = DoubleDQN(
        "MlpPolicy",
        DummyVecEnv([TinyEnv, TinyEnv]),
        policy_kwargs={"net_arch": [32, 32]},
        learning_rate=1e-3,
        buffer_size=64,
        device=device,
        replay_buffer_class=DeviceReplayBuffer if uniform else DevicePrioritizedReplayBuffer,
        replay_buffer_kwargs={**per, **buffer_kwargs},
        cuda_graph=graph,
        seed=0,
    )
    model.set_logger(configure(folder=None, format_strings=[]))
    return model


def _fill(model: DoubleDQN, steps: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    buffer = model.replay_buffer
    assert buffer is not None
    for _ in range(steps):
        obs = rng.uniform(-1, 1, size=(2, 2)).astype(np.float32)
        nxt = rng.uniform(-1, 1, size=(2, 2)).astype(np.float32)
        buffer.add(
            obs,
            nxt,
            rng.integers(0, 2, size=(2, 1)),
            rng.normal(size=2).astype(np.float32),
            rng.random(2) < 0.2,
            [{}, {}],
        )


def _twins(**kwargs: Any) -> tuple[DoubleDQN, DoubleDQN]:
    """The same model with and without the recorded step: same weights, buffer and draws."""
    graphed, plain = _model("cuda", graph=True, **kwargs), _model("cuda", graph=False, **kwargs)
    plain.policy.load_state_dict(graphed.policy.state_dict())
    for model in (graphed, plain):
        _fill(model, 40)
    plain.replay_buffer._generator.set_state(graphed.replay_buffer._generator.get_state())  # type: ignore[union-attr]
    return graphed, plain


# ------------------------------------------------------------------ the device buffer, on CPU


def test_a_sample_is_the_sample_at_its_own_draws() -> None:
    model = _model("cpu")
    _fill(model, 20)
    buffer = model.replay_buffer
    assert isinstance(buffer, DevicePrioritizedReplayBuffer)
    buffer.update_priorities(th.arange(10), th.linspace(0.1, 3.0, 10))
    state = buffer._generator.get_state()
    want = buffer.sample(8)
    buffer._generator.set_state(state)
    draws = th.empty(8, dtype=th.float64)
    buffer._uniform(8, out=draws)
    got = buffer.sample_at(draws)
    assert th.equal(got.indices, want.indices) and th.equal(got.weights, want.weights)
    assert th.equal(got.observations, want.observations)


def test_the_buffers_numbers_on_the_device_follow_its_own() -> None:
    model = _model("cpu")
    buffer = model.replay_buffer
    assert isinstance(buffer, DevicePrioritizedReplayBuffer)
    capacity_rows = buffer.buffer_size  # 32 rows of 2 envs

    def cursor() -> list[int]:
        buffer._sync_cursor()  # as a sample does before it reads the cursor
        return buffer._cursor.tolist()

    assert cursor() == [0, capacity_rows - 1]
    _fill(model, 5)
    assert cursor() == [10, 4]  # 10 stored, newest row 4
    _fill(model, capacity_rows)  # wraps around: full, newest row 4 again
    assert cursor() == [2 * capacity_rows, 4]
    restored = pickle.loads(pickle.dumps(buffer))
    restored._sync_cursor()
    assert restored._cursor.tolist() == [2 * capacity_rows, 4]
    buffer.reset()
    assert cursor() == [0, capacity_rows - 1]
    buffer.beta = 0.7
    assert buffer._beta_tensor.item() == 0.7
    assert pickle.loads(pickle.dumps(buffer))._beta_tensor.item() == 0.7


def test_a_new_alpha_is_written_where_the_priorities_are_and_changes_the_key() -> None:
    model = _model("cpu")
    _fill(model, 6)
    buffer = model.replay_buffer
    assert isinstance(buffer, DevicePrioritizedReplayBuffer)
    buffer.update_priorities(th.tensor([0, 1]), th.tensor([1.0, 3.0]))
    where, key = buffer._leaves.data_ptr(), buffer.graph_key()
    buffer.alpha = 0.5
    assert buffer._leaves.data_ptr() == where  # a recorded graph still reads them
    assert buffer.priorities[:2] == pytest.approx(np.sqrt([1.0 + 1e-6, 3.0 + 1e-6]))
    assert buffer.graph_key() != key
    assert buffer.graph_key() == buffer.graph_key()


@pytest.mark.parametrize("uniform", [False, True])
def test_no_graph_is_recorded_on_the_cpu(uniform: bool) -> None:
    model = _model("cpu", uniform=uniform)
    _fill(model, 20)
    for _ in range(3):
        model.train(gradient_steps=2, batch_size=8)
    assert not model._graphs_wanted() and model._graph is None


def test_a_loaded_model_warms_up_again_before_recording(tmp_path: Any) -> None:
    # A resumed run's steps so far were another process's: its first steps set up this one.
    model = _model("cpu")
    _fill(model, 20)
    model.train(gradient_steps=6, batch_size=8)
    assert (model._n_updates, model._steps_here) == (6, 6)
    model.save(tmp_path / "model")
    loaded = DoubleDQN.load(tmp_path / "model", device="cpu")
    assert (loaded._n_updates, loaded._steps_here) == (6, 0)


def test_step_stats_latest_and_extend() -> None:
    stats = StepStats()
    for value in (1.0, 2.0):
        stats.extend({"loss": th.tensor(value), "td_error": th.tensor(value / 2)})
    assert {k: v.item() for k, v in stats.latest().items()} == {"loss": 2.0, "td_error": 1.0}
    assert stats.read()["loss"].tolist() == [1.0, 2.0]


# ------------------------------------------------------------------ the recorded step, on CUDA


@cuda
@pytest.mark.parametrize("uniform", [False, True], ids=["prioritized", "uniform"])
@pytest.mark.parametrize("n_steps", [1, 3])
def test_the_recorded_step_trains_as_the_step_without_it(n_steps: int, uniform: bool) -> None:
    graphed, plain = _twins(n_steps=n_steps, uniform=uniform)
    losses: dict[str, list[float]] = {"graphed": [], "plain": []}
    for call, steps in enumerate([2, 2, 5, 5, 3]):
        for name, model in (("graphed", graphed), ("plain", plain)):
            if not uniform:
                model.replay_buffer.beta = 0.4 + 0.1 * call  # type: ignore[union-attr]
            model.train(gradient_steps=steps, batch_size=8)
            losses[name].append(model.logger.name_to_value["train/loss"])
    assert graphed._graph is not None and plain._graph is None
    assert losses["graphed"] == pytest.approx(losses["plain"], rel=1e-5)
    for a, b in zip(graphed.policy.parameters(), plain.policy.parameters()):
        th.testing.assert_close(a, b)
    if not uniform:
        th.testing.assert_close(graphed.replay_buffer._leaves, plain.replay_buffer._leaves)  # type: ignore[union-attr]


@cuda
def test_a_cuda_run_keeps_uniform_replay_on_the_device(tmp_path: Any) -> None:
    from harness.cli import main
    from harness.sb3.replay import Replay
    from harness.training.checkpoints import complete_checkpoints

    args = ["run", "configs/smoke.yaml", "--runs-dir", str(tmp_path), "--no-progress"]
    for override in ("algo.prioritized=false", "algo.device=cuda", "checkpoint.every=400"):
        args += ["--set", override]
    assert main(args) == 0
    (run,) = tmp_path.iterdir()
    with (complete_checkpoints(run / "checkpoints")[-1] / "replay_buffer.pkl").open("rb") as f:
        buffer = pickle.load(f)
    assert type(buffer) is Replay and buffer.sampler.on_device and not buffer.sampler.prioritized


@cuda
def test_one_cuda_synchronisation_per_call_with_the_recorded_step() -> None:
    model = _model("cuda")
    _fill(model, 40)
    model.train(gradient_steps=4, batch_size=8)
    model.train(gradient_steps=2, batch_size=8)  # records the step
    assert model._graph is not None
    syncs = cuda_synchronisations(lambda: model.train(gradient_steps=5, batch_size=8))
    assert len(syncs) == 1, syncs


@cuda
def test_a_new_batch_size_or_alpha_records_the_step_again_and_saving_leaves_it_out(
    tmp_path: Any,
) -> None:
    model = _model("cuda")
    _fill(model, 40)
    model.train(gradient_steps=4, batch_size=8)
    model.train(gradient_steps=1, batch_size=8)
    first = model._graph
    model.train(gradient_steps=1, batch_size=8)
    assert model._graph is first
    model.train(gradient_steps=1, batch_size=16)
    second = model._graph
    assert second is not None and second is not first
    model.replay_buffer.alpha = 0.3  # type: ignore[union-attr]
    model.train(gradient_steps=1, batch_size=16)
    assert model._graph is not second
    model.save(tmp_path / "model")
    loaded = DoubleDQN.load(tmp_path / "model", device="cuda")
    assert loaded._graph is None and loaded.cuda_graph and loaded._steps_here == 0


@cuda
def test_a_step_that_cannot_be_recorded_warns_once_and_trains_without(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    graphed, plain = _twins()
    td_loss = graphed._td_loss

    def reading(current_q: th.Tensor, target_q: th.Tensor) -> th.Tensor:
        float(target_q.sum())  # a read of the device: no graph can hold it
        return td_loss(current_q, target_q)

    monkeypatch.setattr(graphed, "_td_loss", reading)
    with pytest.warns(RuntimeWarning, match="could not be recorded as a CUDA graph"):
        for model in (graphed, plain):
            model.train(gradient_steps=4, batch_size=8)
            model.train(gradient_steps=4, batch_size=8)
    assert graphed._graph_failed and graphed._graph is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        graphed.train(gradient_steps=2, batch_size=8)
        plain.train(gradient_steps=2, batch_size=8)
    for a, b in zip(graphed.policy.parameters(), plain.policy.parameters()):
        th.testing.assert_close(a, b)
