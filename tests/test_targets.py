"""TD targets against hand-computed numbers."""

from __future__ import annotations

import pytest
import torch as th

from harness.sb3.targets import double_q_target, large_margin_loss, max_q_target

# Two transitions; the second one is terminal.
REWARDS = th.tensor([[1.0], [0.5]])
DONES = th.tensor([[0.0], [1.0]])
# Online net prefers action 0 in s'_0, target net prefers action 1 there: the two targets differ.
NEXT_Q_ONLINE = th.tensor([[5.0, 0.0], [0.0, 1.0]])
NEXT_Q_TARGET = th.tensor([[1.0, 3.0], [2.0, 5.0]])


def test_max_q_target_hand_computed() -> None:
    target = max_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET)
    # row 0: 1 + 0.9 * max(1, 3) = 3.7; row 1 is terminal: 0.5
    assert target.shape == (2, 1)
    assert th.allclose(target, th.tensor([[3.7], [0.5]]))


def test_double_q_target_uses_online_argmax_and_target_value() -> None:
    target = double_q_target(REWARDS, DONES, 0.9, NEXT_Q_ONLINE, NEXT_Q_TARGET)
    # row 0: argmax online = action 0, evaluated by the target net: 1 + 0.9 * 1.0 = 1.9
    # (the plain target would give 3.7); row 1 is terminal: 0.5
    assert target.shape == (2, 1)
    assert th.allclose(target, th.tensor([[1.9], [0.5]]))
    assert not th.allclose(target, max_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET))


def test_double_q_equals_max_q_when_networks_agree() -> None:
    target = double_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET, NEXT_Q_TARGET)
    assert th.allclose(target, max_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET))


def test_per_sample_discounts() -> None:
    # n-step style discounts gamma**k, no terminal.
    discounts = th.tensor([[0.9], [0.81]])
    dones = th.zeros(2, 1)
    target = double_q_target(REWARDS, dones, discounts, NEXT_Q_ONLINE, NEXT_Q_TARGET)
    # row 0: 1 + 0.9 * 1 = 1.9; row 1: argmax online = 1 -> 0.5 + 0.81 * 5 = 4.55
    assert th.allclose(target, th.tensor([[1.9], [4.55]]))
    plain = max_q_target(REWARDS, dones, discounts, NEXT_Q_TARGET)
    # row 0: 1 + 0.9 * 3 = 3.7; row 1: 0.5 + 0.81 * 5 = 4.55
    assert th.allclose(plain, th.tensor([[3.7], [4.55]]))


def test_max_q_target_matches_sb3_formula() -> None:
    gen = th.Generator().manual_seed(0)
    rewards = th.randn(16, 1, generator=gen)
    dones = (th.rand(16, 1, generator=gen) < 0.3).float()
    next_q = th.randn(16, 4, generator=gen)
    # The expression in stable_baselines3/dqn/dqn.py (DQN.train)
    expected = rewards + (1 - dones) * 0.99 * next_q.max(dim=1)[0].reshape(-1, 1)
    assert th.allclose(max_q_target(rewards, dones, 0.99, next_q), expected)


def test_flat_inputs_do_not_broadcast_to_a_matrix() -> None:
    # (B,) + (B, 1) would silently broadcast to (B, B); the functions reshape to columns.
    target = max_q_target(REWARDS.reshape(-1), DONES.reshape(-1), 0.9, NEXT_Q_TARGET)
    assert target.shape == (2, 1)
    assert th.allclose(target, th.tensor([[3.7], [0.5]]))


def test_shape_errors() -> None:
    with pytest.raises(ValueError, match="rewards"):
        max_q_target(th.zeros(3, 1), DONES, 0.9, NEXT_Q_TARGET)
    with pytest.raises(ValueError, match="n_actions"):
        max_q_target(REWARDS, DONES, 0.9, th.zeros(2))
    with pytest.raises(ValueError, match="same shape"):
        double_q_target(REWARDS, DONES, 0.9, th.zeros(2, 3), NEXT_Q_TARGET)


def test_blocked_actions_are_left_out_of_the_max_and_the_argmax() -> None:
    # Row 0's best actions are blocked in both networks: the target falls back to the free ones.
    blocked = th.tensor([[True, False], [False, False]])
    plain = max_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET, blocked)
    # row 0: max over action 1 only = 3 -> 3.7 (unchanged: 3 was already the max)
    assert th.allclose(plain, th.tensor([[3.7], [0.5]]))
    blocked_1 = th.tensor([[False, True], [False, False]])
    # row 0: max over action 0 only = 1 -> 1 + 0.9 * 1 = 1.9
    assert th.allclose(
        max_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET, blocked_1), th.tensor([[1.9], [0.5]])
    )
    # Double-Q: the online argmax (action 0) is blocked -> action 1, valued by the target net:
    # 1 + 0.9 * 3 = 3.7
    double = double_q_target(REWARDS, DONES, 0.9, NEXT_Q_ONLINE, NEXT_Q_TARGET, blocked)
    assert th.allclose(double, th.tensor([[3.7], [0.5]]))


def test_a_row_with_every_action_blocked_falls_back_to_all_actions() -> None:
    # Row 0 blocks both actions: it bootstraps as if unmasked, never from -inf. Row 1 is terminal
    # and blocks both too: (1 - done) * max must be 0, not 0 * -inf = NaN.
    blocked = th.tensor([[True, True], [True, True]])
    plain = max_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET, blocked)
    # row 0: 1 + 0.9 * max(1, 3) = 3.7; row 1: 0.5
    assert th.allclose(plain, th.tensor([[3.7], [0.5]]))
    double = double_q_target(REWARDS, DONES, 0.9, NEXT_Q_ONLINE, NEXT_Q_TARGET, blocked)
    # row 0: online argmax over both = action 0, target value 1 -> 1.9; row 1: 0.5
    assert th.allclose(double, th.tensor([[1.9], [0.5]]))
    assert th.isfinite(plain).all() and th.isfinite(double).all()
    # Only the fully blocked row falls back: row 1 (one action blocked) is still masked.
    mixed = th.tensor([[True, True], [False, True]])
    dones = th.zeros(2, 1)
    # row 1 not terminal now: max over action 0 only = 2 -> 0.5 + 0.9 * 2 = 2.3 (unmasked: 5)
    assert th.allclose(
        max_q_target(REWARDS, dones, 0.9, NEXT_Q_TARGET, mixed), th.tensor([[3.7], [2.3]])
    )


def test_blocked_must_match_the_q_values() -> None:
    with pytest.raises(ValueError, match="blocked must be"):
        max_q_target(REWARDS, DONES, 0.9, NEXT_Q_TARGET, th.tensor([True, False]))


# ------------------------------------------------------------------ DQfD's large-margin loss


def test_large_margin_loss_hand_computed() -> None:
    q = th.tensor([[1.5, 2.0, 0.5], [3.0, 1.0, 2.5], [0.0, 5.0, 1.0]])
    loss = large_margin_loss(q, th.tensor([1, 0, 1]), margin=0.8)
    # row 0, expert 1: max(1.5 + .8, 2.0, 0.5 + .8) - 2.0 = 0.3
    # row 1, expert 0: max(3.0, 1.0 + .8, 2.5 + .8) - 3.0 = 0.3
    # row 2, expert 1: leads by 4 >= 0.8 -> 0
    assert loss.shape == (3, 1)
    assert loss.flatten().tolist() == pytest.approx([0.3, 0.3, 0.0])


def test_large_margin_loss_one_expert_action_for_the_batch() -> None:
    q = th.tensor([[0.0, 0.0], [1.0, 0.0]])
    # expert 1 everywhere: row 0 max(0.5, 0) - 0 = 0.5; row 1 max(1.5, 0) - 0 = 1.5
    assert large_margin_loss(q, 1, margin=0.5).flatten().tolist() == pytest.approx([0.5, 1.5])
    # margin 0: the loss is how far the expert's action is below the best one
    assert large_margin_loss(q, 1, margin=0.0).flatten().tolist() == pytest.approx([0.0, 1.0])


def test_large_margin_gradient_raises_the_expert_and_lowers_the_best_rival() -> None:
    q = th.tensor([[1.0, 2.0, 0.0]], requires_grad=True)
    large_margin_loss(q, 2, margin=1.0).sum().backward()
    assert q.grad is not None
    assert q.grad.flatten().tolist() == [0.0, 1.0, -1.0]


@pytest.mark.parametrize(
    ("expert", "margin", "message"),
    [
        (3, 1.0, "expert actions must lie in"),
        (-1, 1.0, "expert actions must lie in"),
        (0, -0.5, "margin must be >= 0"),
    ],
)
def test_large_margin_loss_rejects_bad_arguments(expert: int, margin: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        large_margin_loss(th.zeros(2, 3), expert, margin)


def test_large_margin_loss_with_an_expert_set_separates_different_actions_only() -> None:
    q = th.tensor([[1.0, 2.0, 0.5], [3.0, 1.0, 0.5]])
    same = th.tensor([[True, False, True], [True, False, True]])  # action 0 does what 2 does
    loss = large_margin_loss(q, 2, margin=0.8, expert_set=same)
    # row 0: max(1 + 0, 2 + .8, .5 + 0) - max(1, .5) = 1.8 (action 1 is the different one)
    # row 1: max(3, 1 + .8, .5) - max(3, .5) = 0: the set's best leads action 1 by 2 >= .8
    assert loss.flatten().tolist() == pytest.approx([1.8, 0.0])
    # Without the set, action 0 is a rival like any other: row 1 is max(3 + .8, ...) - .5
    assert large_margin_loss(q, 2, margin=0.8)[1].item() == pytest.approx(3.3)
