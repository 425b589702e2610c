"""SumTree and PrioritizedReplayBuffer: invariants, sampling law, IS weights, multi-env layout."""

from __future__ import annotations

import pickle
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st
from stable_baselines3.common.buffers import NStepReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import set_random_seed

from harness.sb3.buffers import (
    PrioritizedReplayBufferSamples,
    SumTree,
    _last_occurrences,
    importance_weights,
    n_step_returns,
    n_step_returns_on_device,
)
from harness.sb3.replay import PrioritizedReplayBuffer, Replay, replay_for
from tests.replay_variants import (
    DeviceDictReplayBuffer,
    DevicePrioritizedDictReplayBuffer,
    DevicePrioritizedReplayBuffer,
    DeviceReplayBuffer,
    PrioritizedDictReplayBuffer,
)

OBS_SPACE = spaces.Box(-1e6, 1e6, shape=(2,), dtype=np.float32)
#: The Dict buffer's twin of OBS_SPACE: the same vector plus a uint8 image holding its first value.
DICT_OBS_SPACE = spaces.Dict(
    {"vec": OBS_SPACE, "img": spaces.Box(0, 255, shape=(1, 2, 2), dtype=np.uint8)}
)
ACTION_SPACE = spaces.Discrete(4)


@pytest.fixture(
    params=[
        PrioritizedReplayBuffer,
        PrioritizedDictReplayBuffer,
        DevicePrioritizedReplayBuffer,
        DevicePrioritizedDictReplayBuffer,
    ],
    ids=["array", "dict", "device-array", "device-dict"],
)
def make_buffer(request: pytest.FixtureRequest) -> Callable[..., PrioritizedReplayBuffer]:
    """Factory of an empty buffer of the test's class: every buffer test runs on the host path
    and on the device path (on CPU tensors here: the same code as on an accelerator)."""
    buffer_class = request.param
    space = DICT_OBS_SPACE if issubclass(buffer_class, PrioritizedDictReplayBuffer) else OBS_SPACE

    def make(buffer_size: int, n_envs: int = 1, **kwargs: float) -> PrioritizedReplayBuffer:
        return buffer_class(buffer_size, space, ACTION_SPACE, device="cpu", n_envs=n_envs, **kwargs)

    return make


def _as_stored(buffer: PrioritizedReplayBuffer, vec: np.ndarray) -> Any:
    """``vec`` as the buffer stores it: the array, or the Dict with the image of ``vec[:, 0]``."""
    if not isinstance(buffer, PrioritizedDictReplayBuffer):
        return vec
    img = np.floor(vec[:, 0]).astype(np.uint8)[:, None, None, None]
    return {"vec": vec, "img": np.broadcast_to(img, (len(vec), 1, 2, 2))}


def first_values(observations: th.Tensor | dict[str, th.Tensor]) -> np.ndarray:
    """The first vector entry of each sampled observation (for a Dict batch, after checking
    that the image was read from the same slot as the vector)."""
    if not isinstance(observations, dict):
        return observations.numpy()[:, 0]
    values = observations["vec"].numpy()[:, 0]
    img = observations["img"].numpy()
    assert img.shape == (len(values), 1, 2, 2)
    np.testing.assert_array_equal(
        img, np.broadcast_to(np.floor(values)[:, None, None, None], img.shape)
    )
    return values


def add_step(
    buffer: PrioritizedReplayBuffer,
    step: int,
    done: bool = False,
    truncated: bool = False,
) -> None:
    """Add one step of all envs; the transition of (step, env) is recognisable by its values."""
    n = buffer.n_envs
    envs = np.arange(n)
    obs = np.stack([10.0 * step + envs, -np.ones(n)], axis=1).astype(np.float32)
    next_obs = obs + 0.5
    buffer.add(
        _as_stored(buffer, obs),
        _as_stored(buffer, next_obs),
        np.full(n, step % 4),
        (100.0 * step + envs).astype(np.float32),
        np.full(n, done),
        [{"TimeLimit.truncated": truncated} for _ in range(n)],
    )


def check_tree(tree: SumTree) -> None:
    """Every internal node is the sum of its children; the root is the sum of the leaves."""
    internal = np.arange(1, tree.size)
    np.testing.assert_array_equal(
        tree.nodes[internal], tree.nodes[2 * internal] + tree.nodes[2 * internal + 1]
    )
    assert tree.total == tree.nodes[tree.size :].sum()


def on_device(buffer: PrioritizedReplayBuffer) -> bool:
    return isinstance(buffer, DevicePrioritizedReplayBuffer)


def check_sampler(buffer: PrioritizedReplayBuffer) -> None:
    """The sampler agrees with the raw priorities: the host path's sum tree holds its sums, the
    device path's leaves are ``raw ** alpha`` (0 for an empty slot), from which it sums."""
    if not on_device(buffer):
        check_tree(buffer._tree)
        return
    raw = buffer.raw_priorities
    expected = np.where(raw > 0, raw**buffer.alpha, 0.0)
    # torch's pow and numpy's may differ in the last bit
    np.testing.assert_allclose(buffer.priorities, expected, rtol=1e-15, atol=0)


def sampler_total(buffer: PrioritizedReplayBuffer) -> float:
    """The sum of the sampling priorities, as the sampler holds it."""
    return float(buffer._leaves.sum()) if on_device(buffer) else buffer._tree.total


def indices_of(batch: PrioritizedReplayBufferSamples) -> np.ndarray:
    """A batch's flat indices on the host (the device path returns a tensor)."""
    indices = batch.indices
    return indices.cpu().numpy() if isinstance(indices, th.Tensor) else indices


# ---------------------------------------------------------------------------------- SumTree


# Integer-valued priorities keep every sum exact in float64, so the checks can be exact.
updates_strategy = st.lists(
    st.tuples(st.integers(0, 1000), st.integers(0, 50)), min_size=1, max_size=60
)


@settings(max_examples=60, deadline=None)
@given(
    capacity=st.integers(1, 37),
    batches=st.lists(updates_strategy, min_size=1, max_size=4),
    fractions=st.lists(st.floats(0.0, 1.0, exclude_max=True), min_size=1, max_size=30),
)
def test_sum_tree_invariants_under_random_updates(
    capacity: int, batches: list[list[tuple[int, int]]], fractions: list[float]
) -> None:
    tree = SumTree(capacity)
    reference = np.zeros(capacity)
    for batch in batches:
        indices = np.array([i % capacity for i, _ in batch])
        values = np.array([float(v) for _, v in batch])
        tree.update(indices, values)
        for i, v in zip(indices, values, strict=True):  # sequential = last write wins
            reference[i] = v
        check_tree(tree)
        np.testing.assert_array_equal(tree.leaves, reference)
        assert tree.total == reference.sum()

    if tree.total > 0:
        queries = np.array(fractions) * tree.total
        leaves = tree.find_prefixsum(queries)
        cumulative = np.cumsum(reference)
        # The leaf i with cumulative[i - 1] <= q < cumulative[i]
        np.testing.assert_array_equal(leaves, np.searchsorted(cumulative, queries, side="right"))
        assert np.all(reference[leaves] > 0)


def test_sum_tree_duplicates_last_write_wins_and_rebuild() -> None:
    tree = SumTree(5)
    tree.update(np.array([1, 3, 1, 1]), np.array([7.0, 2.0, 9.0, 4.0]))
    np.testing.assert_array_equal(tree.leaves, [0, 4, 0, 2, 0])
    other = SumTree(5)
    other.rebuild(np.array([0, 4, 0, 2, 0.0]))
    np.testing.assert_array_equal(other.nodes, tree.nodes)
    check_tree(other)


def test_sum_tree_never_returns_zero_leaf_at_upper_edge() -> None:
    tree = SumTree(6)  # padded to 8 leaves
    tree.update(np.arange(3), np.array([0.1, 0.2, 0.3]))
    # Queries at and beyond the total (rounding at the last stratum) land on the last positive leaf.
    leaves = tree.find_prefixsum(np.array([-1.0, 0.0, tree.total, tree.total * 2]))
    np.testing.assert_array_equal(leaves, [0, 0, 2, 2])


def test_sum_tree_rejects_bad_input() -> None:
    tree = SumTree(4)
    with pytest.raises(IndexError):
        tree.update(np.array([4]), np.array([1.0]))
    with pytest.raises(ValueError):
        tree.update(np.array([0]), np.array([-1.0]))
    with pytest.raises(ValueError, match="empty"):
        tree.find_prefixsum(np.array([0.0]))


class NumpySumTree:
    """The reference for :class:`SumTree`'s compiled loops: its former NumPy implementation,
    vectorised over the items, one pass per tree level."""

    def __init__(self, capacity: int) -> None:
        self.size = 1 << (capacity - 1).bit_length()
        self.depth = self.size.bit_length() - 1
        self.nodes = np.zeros(2 * self.size)

    def update(self, indices: np.ndarray, values: np.ndarray) -> None:
        unique, first_in_reversed = np.unique(indices[::-1], return_index=True)
        nodes = unique + self.size
        self.nodes[nodes] = values[::-1][first_in_reversed]
        for _ in range(self.depth):
            nodes = nodes >> 1
            self.nodes[nodes] = self.nodes[2 * nodes] + self.nodes[2 * nodes + 1]

    def find_prefixsum(self, values: np.ndarray) -> np.ndarray:
        queries = np.maximum(np.asarray(values, dtype=np.float64), 0.0)
        idx = np.ones(queries.shape, dtype=np.int64)
        for _ in range(self.depth):
            left = 2 * idx
            left_sum = self.nodes[left]
            go_right = (queries >= left_sum) & (self.nodes[left + 1] > 0.0)
            queries = np.where(go_right, queries - left_sum, queries)
            idx = left + go_right
        return idx - self.size


# Real-valued priorities (as raw ** alpha makes them), zeros (empty slots) and repeated values.
priority_strategy = st.one_of(
    st.just(0.0),
    st.sampled_from([0.25, 1e-6]),
    st.floats(1e-12, 1e6, allow_nan=False, allow_infinity=False),
)


@settings(max_examples=80, deadline=None)
@given(
    capacity=st.integers(1, 70),
    batches=st.lists(
        st.lists(st.tuples(st.integers(0, 10_000), priority_strategy), min_size=1, max_size=40),
        min_size=1,
        max_size=5,
    ),
    offsets=st.lists(st.floats(0.0, 1.0, exclude_max=True), min_size=1, max_size=40),
    extra=st.lists(st.floats(-1e7, 1e7, allow_nan=False), max_size=10),
)
def test_compiled_sum_tree_equals_the_numpy_one_bit_for_bit(
    capacity: int,
    batches: list[list[tuple[int, float]]],
    offsets: list[float],
    extra: list[float],
) -> None:
    # The same nodes after every update (duplicates included), the same leaves for any query,
    # the same strata, and the smallest positive leaf the updates track equals a scan's.
    tree, reference = SumTree(capacity), NumpySumTree(capacity)
    for batch in batches:
        indices = np.array([i % capacity for i, _ in batch], dtype=np.int64)
        values = np.array([v for _, v in batch])
        tree.update(indices, values)
        reference.update(indices, values)
        np.testing.assert_array_equal(tree.nodes, reference.nodes)
        positive = tree.leaves[tree.leaves > 0]
        assert tree.min_leaf == (positive.min() if positive.size else np.inf)
    if tree.total <= 0:
        return
    fractions = np.array(offsets)
    queries = np.concatenate([fractions * tree.total, extra, [tree.total, np.nan]])
    np.testing.assert_array_equal(tree.find_prefixsum(queries), reference.find_prefixsum(queries))
    n = len(fractions)
    strata = (np.arange(n) + fractions) * (tree.total / n)
    np.testing.assert_array_equal(tree.stratified(fractions), reference.find_prefixsum(strata))


def test_min_leaf_after_the_minimum_is_raised_emptied_and_rebuilt() -> None:
    tree = SumTree(4)
    assert tree.min_leaf == np.inf
    tree.update(np.array([0, 1, 2]), np.array([3.0, 1.0, 1.0]))
    assert tree.min_leaf == 1.0
    tree.update(np.array([1]), np.array([5.0]))  # one of the two minima raised
    assert tree.min_leaf == 1.0
    tree.update(np.array([2, 3]), np.array([0.0, 2.0]))  # the other emptied, a new leaf
    assert tree.min_leaf == 2.0
    tree.update(np.array([3, 3]), np.array([0.5, 4.0]))  # lowered, then raised: last wins
    assert tree.min_leaf == 3.0
    tree.rebuild(np.array([0.0, 0.0, 7.0, 0.0]))
    assert tree.min_leaf == 7.0
    tree.rebuild(np.zeros(4))
    assert tree.min_leaf == np.inf


@settings(max_examples=60, deadline=None)
@given(indices=st.lists(st.integers(0, 20), max_size=50))
def test_last_occurrences_equal_numpys_unique_of_the_reversed_indices(indices: list[int]) -> None:
    flat = np.array(indices, dtype=np.int64)
    code, unique, last = _last_occurrences(flat, np.zeros(len(flat)), 21)
    want_unique, first_in_reversed = np.unique(flat[::-1], return_index=True)
    assert code == 0
    np.testing.assert_array_equal(unique, want_unique)
    np.testing.assert_array_equal(last, len(flat) - 1 - first_in_reversed)


# ------------------------------------------------------------------- PrioritizedReplayBuffer


def test_samples_extend_sb3_samples(make_buffer: Callable[..., PrioritizedReplayBuffer]) -> None:
    fields = ReplayBufferSamples._fields
    assert PrioritizedReplayBufferSamples._fields[: len(fields)] == fields
    buffer = make_buffer(8)
    for step in range(3):
        add_step(buffer, step)
    batch = buffer.sample(5)
    assert batch.weights.shape == (5, 1)
    assert batch.weights.dtype == th.float32
    assert batch.rewards.shape == batch.dones.shape == (5, 1)
    assert batch.discounts is None
    assert indices_of(batch).dtype == np.int64
    assert batch.indices.shape == (5,)
    first_values(batch.observations)  # a Dict batch holds every key, read from one slot


def test_dict_observations_are_a_storage_option_of_the_one_buffer_class() -> None:
    buffer = PrioritizedReplayBuffer(8, DICT_OBS_SPACE, ACTION_SPACE, device="cpu")
    assert type(buffer) is PrioritizedReplayBuffer and isinstance(buffer.observations, dict)


def test_new_transitions_get_max_priority(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    buffer = make_buffer(8, eps=1e-6)
    add_step(buffer, 0)
    assert buffer.raw_priorities[0] == 1.0  # initial max priority
    buffer.update_priorities(np.array([0]), np.array([5.0]))
    add_step(buffer, 1)
    assert buffer.raw_priorities[1] == pytest.approx(5.0 + 1e-6)
    # The max is a running max: lowering the top priority does not lower it.
    buffer.update_priorities(np.array([0, 1]), np.array([0.1, 0.1]))
    add_step(buffer, 2)
    assert buffer.raw_priorities[2] == pytest.approx(5.0 + 1e-6)


def test_sampling_frequencies_follow_priorities(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    alpha = 0.6
    buffer = make_buffer(8, alpha=alpha, eps=1e-6)
    for step in range(8):
        add_step(buffer, step)
    td = np.array([0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0])
    buffer.update_priorities(np.arange(8), td)
    expected = (td + 1e-6) ** alpha
    expected /= expected.sum()

    set_random_seed(0)
    n_draws = 50_000
    counts = np.zeros(8)
    for _ in range(n_draws // 100):
        np.add.at(counts, indices_of(buffer.sample(100)), 1)
    frequencies = counts / n_draws
    # Tolerance: 5 binomial standard deviations per item (stratified sampling only lowers the
    # variance), at most 0.0096 here; alpha=1 or alpha=0 would miss the last item by > 0.07.
    tolerance = 5 * np.sqrt(expected * (1 - expected) / n_draws)
    np.testing.assert_array_less(np.abs(frequencies - expected), tolerance)


def test_importance_weights_hand_computed(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    # eps=1 and alpha=1 make the priorities integers: raw = |td| + 1 = [1, 2, 4, 8], total 15.
    buffer = make_buffer(4, alpha=1.0, beta=0.5, eps=1.0)
    for step in range(4):
        add_step(buffer, step)
    buffer.update_priorities(np.arange(4), np.array([0.0, 1.0, 3.0, 7.0]))
    # The max weight is the buffer's lowest-priority transition's (p=1):
    # w_i = (4 * p_i / 15) ** -0.5 / (4 * 1 / 15) ** -0.5 = sqrt(1 / p_i)
    # -> [1, 1/sqrt(2), 1/2, 1/sqrt(8)]. batch 15 -> 15 strata of width 1: 1, 2, 4, 8 per item.
    batch = buffer.sample(15)
    np.testing.assert_array_equal(np.sort(indices_of(batch)), np.repeat(np.arange(4), [1, 2, 4, 8]))
    expected = {0: 1.0, 1: 2**-0.5, 2: 0.5, 3: 8**-0.5}
    for index, weight in zip(indices_of(batch), batch.weights.numpy().ravel(), strict=True):
        assert weight == pytest.approx(expected[int(index)], rel=1e-6)

    # beta is settable and read at sampling time: beta=1 gives w_i = p_min / p_i.
    buffer.beta = 1.0
    batch = buffer.sample(15)
    for index, weight in zip(indices_of(batch), batch.weights.numpy().ravel(), strict=True):
        assert weight == pytest.approx(1.0 / 2 ** int(index), rel=1e-6)
    with pytest.raises(ValueError):
        buffer.beta = -0.1


def test_importance_weights_normalise_by_the_buffer_minimum_not_the_batch(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    # Priorities [1, 2, 4, 8] (total 15), beta 0.5. A batch of 2 has strata [0, 7.5) and
    # [7.5, 15): the first holds items 0, 1, 2 (cumulative 1, 3, 7) and item 3's range is [7, 15),
    # so draws land in item 0 only for offsets in [0, 1/7.5). Whatever the batch, a weight is
    # sqrt(p_min / p_i) with p_min = 1, the buffer's minimum: item 3 always weighs 1/sqrt(8),
    # even in a batch that misses item 0 (a batch-wide max would give it 1 there).
    buffer = make_buffer(4, alpha=1.0, beta=0.5, eps=1.0)
    for step in range(4):
        add_step(buffer, step)
    buffer.update_priorities(np.arange(4), np.array([0.0, 1.0, 3.0, 7.0]))
    set_random_seed(0)
    missed_item_0 = 0
    for _ in range(200):
        batch = buffer.sample(2)
        weights = batch.weights.numpy().ravel()
        expected = np.sqrt(1.0 / np.array([1.0, 2.0, 4.0, 8.0]))[indices_of(batch)]
        np.testing.assert_allclose(weights, expected, rtol=1e-6)
        missed_item_0 += int(0 not in indices_of(batch))
    assert missed_item_0 > 100  # the case that matters was exercised
    # A batch of one: item 3 alone weighs 1/sqrt(8), not 1.
    set_random_seed(1)
    for _ in range(20):
        single = buffer.sample(1)
        assert single.weights.item() == pytest.approx(
            np.sqrt(1.0 / [1.0, 2.0, 4.0, 8.0][int(indices_of(single)[0])]), rel=1e-6
        )


def test_importance_weights_function_hand_computed() -> None:
    # N = 4, P = [0.1, 0.2, 0.3, 0.4], beta = 1: w = (N P)^-1 / (N P_min)^-1 = P_min / P.
    probs = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(
        importance_weights(probs, 0.1, 1.0), [1.0, 0.5, 1 / 3, 0.25], rtol=1e-12
    )
    # beta = 0 disables the correction.
    np.testing.assert_array_equal(importance_weights(probs, 0.1, 0.0), np.ones(4))
    # A lower minimum elsewhere in the buffer lowers every weight of the batch.
    np.testing.assert_allclose(importance_weights(np.array([0.1]), 0.05, 0.5), [0.5**0.5])


def test_multi_env_flat_index_maps_to_the_right_transition(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    n_envs = 3
    buffer = make_buffer(12, n_envs=n_envs)  # 4 rows x 3 envs
    # Partially filled: only the first 2 * 3 flat indices are valid.
    add_step(buffer, 0)
    add_step(buffer, 1)
    set_random_seed(1)
    seen = set()
    for _ in range(50):
        batch = buffer.sample(12)
        seen.update(batch.indices.tolist())
        pos, env = np.divmod(indices_of(batch), n_envs)
        np.testing.assert_array_equal(first_values(batch.observations), 10 * pos + env)
        np.testing.assert_array_equal(first_values(batch.next_observations), 10 * pos + env + 0.5)
        np.testing.assert_array_equal(batch.rewards.numpy().ravel(), 100 * pos + env)
        np.testing.assert_array_equal(batch.actions.numpy().ravel(), pos % 4)
    assert seen == set(range(6))

    add_step(buffer, 2)
    add_step(buffer, 3)
    seen = set()
    for _ in range(50):
        seen.update(buffer.sample(12).indices.tolist())
    assert seen == set(range(12))


def test_wrap_around_overwrites_priorities(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    n_envs = 2
    buffer = make_buffer(6, n_envs=n_envs, alpha=1.0, eps=1.0)  # 3 rows x 2 envs
    for step in range(3):
        add_step(buffer, step)
    assert buffer.full
    buffer.update_priorities(np.arange(6), np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0]))
    assert buffer.max_priority == 6.0
    add_step(buffer, 3)  # overwrites row 0, i.e. flat indices 0 and 1
    np.testing.assert_array_equal(buffer.raw_priorities, [6.0, 6.0, 3.0, 4.0, 5.0, 6.0])
    np.testing.assert_array_equal(buffer.priorities, buffer.raw_priorities)  # alpha = 1
    check_sampler(buffer)
    assert buffer.n_transitions == 6
    set_random_seed(2)
    batch = buffer.sample(64)
    pos, env = np.divmod(indices_of(batch), n_envs)
    step = np.where(pos == 0, 3, pos)  # row 0 now holds step 3
    np.testing.assert_array_equal(first_values(batch.observations), 10 * step + env)


def test_alpha_change_rebuilds_tree(make_buffer: Callable[..., PrioritizedReplayBuffer]) -> None:
    buffer = make_buffer(8, alpha=1.0, eps=1.0)
    for step in range(5):
        add_step(buffer, step)
    buffer.update_priorities(np.arange(5), np.array([0.0, 1.0, 3.0, 7.0, 15.0]))
    raw = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(buffer.raw_priorities, raw)

    buffer.alpha = 0.5
    np.testing.assert_allclose(buffer.priorities, np.sqrt(raw))
    check_sampler(buffer)
    # alpha = 0: uniform over stored transitions, empty slots stay unsampleable.
    buffer.alpha = 0.0
    np.testing.assert_array_equal(buffer.priorities, [1, 1, 1, 1, 1, 0, 0, 0])
    assert set(buffer.sample(200).indices.tolist()) == set(range(5))
    # New priorities use the current alpha.
    buffer.alpha = 0.5
    buffer.update_priorities(np.array([0]), np.array([8.0]))
    assert buffer.priorities[0] == pytest.approx(3.0)
    with pytest.raises(ValueError):
        buffer.alpha = -1.0


def test_update_priorities_duplicates_last_wins(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    buffer = make_buffer(4, alpha=1.0, eps=1.0)
    for step in range(4):
        add_step(buffer, step)
    buffer.update_priorities(np.array([2, 1, 2]), th.tensor([5.0, -3.0, 1.0]))
    np.testing.assert_array_equal(buffer.raw_priorities, [1.0, 4.0, 2.0, 1.0])
    check_sampler(buffer)
    with pytest.raises(ValueError):
        buffer.update_priorities(np.array([0, 1]), np.array([1.0]))
    if not on_device(buffer):  # the device path checks no values: that would read them back
        with pytest.raises(ValueError):
            buffer.update_priorities(np.array([0]), np.array([np.nan]))


def test_timeouts_are_not_terminal(make_buffer: Callable[..., PrioritizedReplayBuffer]) -> None:
    buffer = make_buffer(4)
    add_step(buffer, 0, done=True, truncated=True)
    add_step(buffer, 1, done=True, truncated=False)
    batch = buffer.sample(64)
    dones = batch.dones.numpy().ravel()
    np.testing.assert_array_equal(dones, (indices_of(batch) == 1).astype(np.float32))


def test_unsupported_configurations_and_empty_buffer(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        make_buffer(8, optimize_memory_usage=True, handle_timeout_termination=False)
    with pytest.raises(ValueError, match="empty"):
        make_buffer(8).sample(4)


def test_reset_clears_priorities(make_buffer: Callable[..., PrioritizedReplayBuffer]) -> None:
    buffer = make_buffer(4)
    add_step(buffer, 0)
    buffer.update_priorities(np.array([0]), np.array([9.0]))
    buffer.reset()
    assert buffer.n_transitions == 0
    assert buffer.max_priority == 1.0
    assert sampler_total(buffer) == 0.0


def test_pickle_round_trip_keeps_priorities(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    # SB3's save_replay_buffer/load_replay_buffer pickle the whole buffer.
    buffer = make_buffer(6, n_envs=2, alpha=0.5)
    for step in range(2):
        add_step(buffer, step)
    buffer.update_priorities(np.arange(4), np.array([1.0, 2.0, 3.0, 4.0]))
    restored = pickle.loads(pickle.dumps(buffer))
    np.testing.assert_array_equal(restored.priorities, buffer.priorities)
    check_sampler(restored)
    assert sampler_total(restored) == sampler_total(buffer)
    assert (restored.alpha, restored.beta, restored.max_priority) == (0.5, 0.4, buffer.max_priority)


# ---------------------------------------------------------------------------- n-step returns
def test_n_step_returns_hand_computed() -> None:
    # One env column of 6 rows, gamma 0.5, n 3; row 2 ends an episode (done), row 4 is a
    # timeout, row 5 the newest row (its successor is not stored).
    rewards = np.array([[1.0], [2.0], [4.0], [8.0], [16.0], [32.0]], dtype=np.float32)
    dones = np.array([[0], [0], [1], [0], [1], [0]], dtype=np.float32)
    timeouts = np.array([[0], [0], [0], [0], [1], [0]], dtype=np.float32)
    rows = np.array([0, 1, 2, 3, 5])
    returns, discounts, last, terminal = n_step_returns(
        rewards, dones, timeouts, rows, np.zeros(5, dtype=np.int64), 3, 0.5, newest_row=5
    )
    # row 0: 1 + 0.5*2 + 0.25*4, stops at the done of row 2 (terminal: no bootstrap)
    # row 1: 2 + 0.5*4, done at row 2; row 2: 4, its own done
    # row 3: 8 + 0.5*16, a timeout at row 4: bootstraps from row 4's next obs with 0.25
    # row 5: 32, the newest row: bootstraps from its own next obs with 0.5
    np.testing.assert_allclose(returns, [3.0, 4.0, 4.0, 16.0, 32.0])
    np.testing.assert_allclose(discounts, [0.125, 0.25, 0.5, 0.25, 0.5])
    np.testing.assert_array_equal(last, [2, 2, 2, 4, 5])
    np.testing.assert_array_equal(terminal, [1, 1, 1, 0, 0])


def test_n_step_returns_wrap_around_a_full_buffer_but_not_past_the_newest_row() -> None:
    # 4 rows, full, pos = 2: the newest row is 1, the oldest 2. Two env columns differ.
    rewards = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0], [4.0, 40.0]], dtype=np.float32)
    zeros = np.zeros((4, 2), dtype=np.float32)
    returns, discounts, last, terminal = n_step_returns(
        rewards, zeros, zeros, np.array([3, 3, 0, 2]), np.array([0, 1, 1, 0]), 3, 0.5, 1
    )
    # (3, env 0): rows 3, 0, 1 -> 4 + 0.5*1 + 0.25*2 (row 1 is the newest: the sequence ends)
    # (3, env 1): 40 + 0.5*10 + 0.25*20; (0, env 1): rows 0, 1 -> 10 + 0.5*20
    # (2, env 0): rows 2, 3, 0 -> 3 + 0.5*4 + 0.25*1, full length
    np.testing.assert_allclose(returns, [5.0, 50.0, 20.0, 5.25])
    np.testing.assert_allclose(discounts, [0.125, 0.125, 0.25, 0.125])
    np.testing.assert_array_equal(last, [1, 1, 1, 0])
    np.testing.assert_array_equal(terminal, [0, 0, 0, 0])


def assert_n_step_samples_match_sb3(ours: Any) -> None:
    """``ours`` (8 rows, one env, n_steps=3, gamma=0.9) against SB3's NStepReplayBuffer given the
    same transitions (one env: its env draw is always 0): every row gives the same return,
    discount, bootstrap state and terminal flag."""
    sb3 = NStepReplayBuffer(8, OBS_SPACE, ACTION_SPACE, device="cpu", n_steps=3, gamma=0.9)
    ends = {2: (True, False), 6: (True, True), 9: (True, False)}  # step: (done, truncated)
    for step in range(11):  # wraps around: rows hold steps 3..10, pos = 3
        done, truncated = ends.get(step, (False, False))
        add_step(ours, step, done, truncated)
        add_step(sb3, step, done, truncated)
    rows = np.arange(8)
    expected = sb3._get_samples(rows)
    got = ours._get_samples_at(rows, np.zeros(8, dtype=np.int64))
    for name in ("rewards", "discounts", "dones"):
        th.testing.assert_close(getattr(got, name), getattr(expected, name))
    np.testing.assert_array_equal(
        first_values(got.next_observations), first_values(expected.next_observations)
    )
    assert got.rewards.shape == got.discounts.shape == got.dones.shape == (8, 1)
    assert (got.discounts < 0.9).any() and (got.discounts == 0.9).any()  # mixed lengths


def test_n_step_samples_match_sb3s_n_step_buffer(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    assert_n_step_samples_match_sb3(make_buffer(8, n_steps=3, gamma=0.9))


def test_prioritized_n_step_sample_carries_discounts_and_one_step_none(
    make_buffer: Callable[..., PrioritizedReplayBuffer],
) -> None:
    one, three = make_buffer(16, n_envs=2), make_buffer(16, n_envs=2, n_steps=3, gamma=0.5)
    for step in range(5):
        add_step(one, step)
        add_step(three, step)
    np.random.seed(0)  # noqa: NPY002
    assert one.sample(6).discounts is None
    batch = three.sample(6)
    # The transition of (step, env) holds reward 100*step + env: recompute its 3-step return.
    step, env = np.divmod(indices_of(batch), 2)
    k = np.minimum(3, 5 - step)  # step 4 is the newest row
    expected = [
        sum(0.5**i * (100.0 * (s + i) + e) for i in range(n))
        for s, e, n in zip(step, env, k, strict=True)
    ]
    np.testing.assert_allclose(batch.rewards.numpy()[:, 0], expected)
    np.testing.assert_allclose(batch.discounts.numpy()[:, 0], 0.5**k)
    np.testing.assert_allclose(
        first_values(batch.next_observations), 10.0 * (step + k - 1) + env + 0.5
    )


@pytest.mark.parametrize("n_steps", [0, 1.5, True])
def test_n_steps_must_be_a_positive_integer(n_steps: Any) -> None:
    with pytest.raises(ValueError, match="n_steps must be an integer >= 1"):
        PrioritizedReplayBuffer(8, OBS_SPACE, ACTION_SPACE, device="cpu", n_steps=n_steps)


def test_a_buffer_pickled_before_n_step_loads_as_one_step() -> None:
    buffer = PrioritizedReplayBuffer(8, OBS_SPACE, ACTION_SPACE, device="cpu")
    add_step(buffer, 0)
    state = buffer.__dict__.copy()
    del state["n_steps"], state["gamma"]  # what an older pickle holds
    old = PrioritizedReplayBuffer.__new__(PrioritizedReplayBuffer)
    old.__dict__.update(state)
    restored = pickle.loads(pickle.dumps(old))
    assert restored.n_steps == 1
    assert restored.sample(2).discounts is None


# ------------------------------------------------------------------------- the device path
def test_both_paths_draw_the_same_transitions_and_weights_from_the_same_offsets(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The same transitions and TD errors in both buffers (3 envs, wrapped around once): given the
    # same stratified offsets, the host's sum-tree descent and the device's search over the
    # cumulative priorities pick the same transitions, with the same IS weights.
    rng = np.random.default_rng(5)
    kwargs = dict(alpha=0.7, beta=0.5, eps=1e-3)
    host = PrioritizedReplayBuffer(15, OBS_SPACE, ACTION_SPACE, device="cpu", n_envs=3, **kwargs)
    dev = DevicePrioritizedReplayBuffer(15, OBS_SPACE, ACTION_SPACE, "cpu", n_envs=3, **kwargs)
    for step in range(7):  # 5 rows: steps 5 and 6 overwrite rows 0 and 1
        for buffer in (host, dev):
            add_step(buffer, step)
        flat = rng.integers(0, 15, size=6)
        errors = rng.exponential(2.0, size=6)
        host.update_priorities(flat, errors)
        dev.update_priorities(th.as_tensor(flat), th.as_tensor(errors))
    np.testing.assert_allclose(dev.raw_priorities, host.raw_priorities, rtol=1e-15)
    assert dev.max_priority == host.max_priority
    for batch_size in (1, 7, 64):
        offsets = rng.random(batch_size)
        monkeypatch.setattr(np.random, "random_sample", lambda n, o=offsets: o)
        monkeypatch.setattr(dev, "_uniform", lambda n, o=offsets: th.as_tensor(o))
        want, got = host.sample(batch_size), dev.sample(batch_size)
        np.testing.assert_array_equal(indices_of(got), want.indices)
        th.testing.assert_close(got.weights, want.weights)
        th.testing.assert_close(got.observations, want.observations)
        th.testing.assert_close(got.rewards, want.rewards)
        th.testing.assert_close(got.dones, want.dones)


def test_the_device_sampler_hand_computed_at_given_offsets(monkeypatch: pytest.MonkeyPatch) -> None:
    # Priorities [1, 2, 4, 8] (alpha 1, eps 1), total 15, cumulative [1, 3, 7, 15]. Batch 3:
    # strata of width 5. Offsets 0.1, 0.5, 0.9 -> queries 0.5, 7.5, 14.5 -> items 0, 3, 3;
    # offsets 0.25, 0, 0 -> queries 1.25, 5, 10 -> items 1, 2, 3 (a query on a boundary belongs
    # to the item the boundary starts). Weights sqrt(p_min / p_i), beta 0.5.
    buffer = DevicePrioritizedReplayBuffer(
        4, OBS_SPACE, ACTION_SPACE, "cpu", alpha=1.0, beta=0.5, eps=1.0
    )
    for step in range(4):
        add_step(buffer, step)
    buffer.update_priorities(th.arange(4), th.tensor([0.0, 1.0, 3.0, 7.0]))
    for offsets, items in (([0.1, 0.5, 0.9], [0, 3, 3]), ([0.25, 0.0, 0.0], [1, 2, 3])):
        monkeypatch.setattr(buffer, "_uniform", lambda n, o=offsets: th.tensor(o, dtype=th.float64))
        batch = buffer.sample(3)
        assert indices_of(batch).tolist() == items
        expected = np.sqrt(1.0 / np.array([1.0, 2.0, 4.0, 8.0])[items])
        np.testing.assert_allclose(batch.weights.numpy().ravel(), expected, rtol=1e-6)
    # A query at the top edge (rounding) takes the last stored transition, never an empty slot.
    monkeypatch.setattr(buffer, "_uniform", lambda n: th.ones(n, dtype=th.float64))
    assert indices_of(buffer.sample(2)).tolist() == [3, 3]


def test_n_step_returns_on_the_device_equal_the_hosts() -> None:
    rng = np.random.default_rng(3)
    rows_n, envs_n = 9, 3
    rewards = rng.normal(size=(rows_n, envs_n)).astype(np.float32)
    dones = (rng.random((rows_n, envs_n)) < 0.2).astype(np.float32)
    timeouts = dones * (rng.random((rows_n, envs_n)) < 0.5)
    rows = rng.integers(0, rows_n, 40)
    envs = rng.integers(0, envs_n, 40)
    want = n_step_returns(rewards, dones, timeouts, rows, envs, 4, 0.9, newest_row=5)
    got = n_step_returns_on_device(
        *map(th.as_tensor, (rewards, dones, timeouts, rows, envs)), 4, 0.9, newest_row=5
    )
    for w, g in zip(want, got, strict=True):
        np.testing.assert_allclose(g.numpy(), w, rtol=1e-6)


def test_a_pickled_device_buffer_draws_what_the_original_draws() -> None:
    # Resume: the checkpoint's buffer continues the original's draws (its generator is saved).
    buffer = DevicePrioritizedDictReplayBuffer(12, DICT_OBS_SPACE, ACTION_SPACE, "cpu", n_envs=2)
    for step in range(4):
        add_step(buffer, step)
    buffer.update_priorities(th.tensor([0, 3, 5]), th.tensor([2.0, 0.5, 4.0]))
    buffer.sample(5)
    restored = pickle.loads(pickle.dumps(buffer))
    assert isinstance(restored.observations["vec"], th.Tensor)
    for _ in range(3):
        want, got = buffer.sample(6), restored.sample(6)
        assert th.equal(got.indices, want.indices) and th.equal(got.weights, want.weights)
        buffer.update_priorities(want.indices, th.arange(6.0))
        restored.update_priorities(got.indices, th.arange(6.0))
    np.testing.assert_array_equal(restored.raw_priorities, buffer.raw_priorities)


def test_the_prioritized_buffer_is_the_devices_on_cuda_and_the_hosts_elsewhere() -> None:
    host = (PrioritizedReplayBuffer, {"placement": "host"})
    assert replay_for("cpu", prioritized=True) == host
    if th.backends.mps.is_available():  # no float64 on MPS: the host path
        assert replay_for("mps", prioritized=True) == host
    if th.cuda.is_available():
        assert replay_for("cuda", prioritized=True) == (
            PrioritizedReplayBuffer,
            {"placement": "device"},
        )
    # One transition per decision stays on the host (either sampler).
    per_decision = {"sampler": "prioritized", "per_decision": True}
    assert replay_for("cuda", prioritized=True, per_decision=True) == (Replay, per_decision)


# ------------------------------------------------------------------ uniform replay on the device


def _uniform(buffer_size: int = 8, n_envs: int = 2, **kwargs: Any) -> DeviceReplayBuffer:
    return DeviceReplayBuffer(
        buffer_size, OBS_SPACE, ACTION_SPACE, device="cpu", n_envs=n_envs, **kwargs
    )


def test_the_uniform_device_sampler_hand_computed_at_given_draws() -> None:
    buffer = _uniform()  # 4 rows of 2 envs
    for step in range(3):  # 6 transitions: flat index row * 2 + env
        add_step(buffer, step)
    draws = buffer.draw(4)  # brings the cursor up to date; the draws themselves replaced:
    draws.copy_(th.tensor([0.0, 0.2, 0.5, 0.999], dtype=th.float64))
    batch = buffer.sample_at(draws)
    # floor(u * 6) = 0, 1, 3, 5 -> (row, env) (0, 0), (0, 1), (1, 1), (2, 1): reward 100 row + env
    assert batch.rewards.ravel().tolist() == [0.0, 1.0, 101.0, 201.0]
    assert first_values(batch.next_observations).tolist() == [0.5, 1.5, 11.5, 21.5]
    assert batch.discounts is None and not hasattr(batch, "weights")


def test_the_uniform_device_sampler_draws_every_stored_transition_alike() -> None:
    buffer = _uniform(buffer_size=16, n_envs=2)  # 8 rows of 2 envs
    for step in range(5):  # 10 stored, rows 5-7 empty
        add_step(buffer, step)
    buffer._generator.manual_seed(0)
    rewards = th.cat([buffer.sample(1000).rewards.ravel() for _ in range(20)])
    values, counts = th.unique(rewards, return_counts=True)
    assert values.tolist() == [100.0 * s + e for s in range(5) for e in range(2)]
    # 20,000 draws over 10 transitions: each within 5 standard deviations of 2,000.
    assert (counts - 2000).abs().max() < 5 * (20000 * 0.1 * 0.9) ** 0.5


def test_uniform_device_n_step_samples_match_sb3s_n_step_buffer() -> None:
    assert_n_step_samples_match_sb3(_uniform(8, n_envs=1, n_steps=3, gamma=0.9))


def test_the_uniform_device_buffer_pickles_resets_and_refuses_what_it_cannot_do() -> None:
    buffer = _uniform()
    with pytest.raises(ValueError, match="empty"):
        buffer.sample(2)
    for step in range(6):  # wraps: full
        add_step(buffer, step)
    buffer._sync_cursor()  # as a sample does before it reads the cursor
    assert buffer.full and buffer._cursor.tolist() == [8, 1]
    restored = pickle.loads(pickle.dumps(buffer))
    want = buffer.sample(5)  # the restored copy draws what the original draws
    assert th.equal(restored.sample(5).rewards, want.rewards)
    buffer.reset()
    buffer._sync_cursor()
    assert buffer._cursor.tolist() == [0, 3] and buffer.size() == 0
    with pytest.raises(ValueError, match="VecNormalize"):
        restored.sample(2, env=object())  # type: ignore[arg-type]
    for bad in ({"n_steps": 0}, {"gamma": 0.0}, {"optimize_memory_usage": True}):
        with pytest.raises(ValueError):
            _uniform(**bad)


def test_the_uniform_device_dict_buffer_samples_dicts() -> None:
    space = spaces.Dict({"vec": OBS_SPACE})
    buffer = DeviceDictReplayBuffer(4, space, ACTION_SPACE, device="cpu", n_envs=1)
    for step in range(2):
        obs = {"vec": np.array([[step, 0.0]], dtype=np.float32)}
        buffer.add(obs, obs, np.array([[1]]), np.array([step]), np.array([False]), [{}])
    draws = buffer.draw(2)
    draws.copy_(th.tensor([0.0, 0.9], dtype=th.float64))
    batch = buffer.sample_at(draws)
    assert batch.observations["vec"][:, 0].tolist() == [0.0, 1.0]


def test_the_uniform_buffer_is_the_devices_on_cuda_and_sb3s_choice_elsewhere() -> None:
    assert replay_for("cpu", prioritized=False) == (None, {})
    if th.cuda.is_available():
        assert replay_for("cuda", prioritized=False) == (Replay, {"placement": "device"})
