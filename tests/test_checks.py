"""harness/training/checks.py: the optimizer's fastest implementation of its own step."""

from __future__ import annotations

import pytest
import torch as th

from harness.training.checks import fast_optimizer_kwargs


def test_adam_gets_the_fused_step_and_rmsprop_the_multi_tensor_one() -> None:
    # Adam has a fused CPU kernel in the pinned torch; RMSprop has none.
    assert fast_optimizer_kwargs(th.optim.Adam, {"eps": 1e-5}) == {"fused": True, "eps": 1e-5}
    assert fast_optimizer_kwargs(th.optim.RMSprop, {}) == {"foreach": True}
    # An optimizer with neither keeps its arguments as they are.
    assert fast_optimizer_kwargs(th.optim.LBFGS, {"history_size": 5}) == {"history_size": 5}


@pytest.mark.parametrize("named", [{"foreach": False}, {"fused": False}, {"foreach": True}])
def test_a_choice_named_in_the_config_is_kept(named: dict) -> None:
    assert fast_optimizer_kwargs(th.optim.Adam, named) == named


@pytest.mark.parametrize("flag", ["differentiable", "capturable"])
def test_settings_of_torch_s_loops_keep_the_multi_tensor_step(flag: str) -> None:
    # As before the fused step was used: capturable on the CPU stays refused by the checks.
    kwargs = {flag: True}
    assert fast_optimizer_kwargs(th.optim.Adam, kwargs) == {"foreach": True, **kwargs}


def test_the_fused_step_is_the_same_update() -> None:
    """Ten Adam steps fused and in torch's default loop give the same weights (to rounding:
    the fused kernel orders a few operations differently)."""
    start = th.randn(64, 33, generator=th.Generator().manual_seed(0))
    weights = []
    for kwargs in ({"foreach": False}, fast_optimizer_kwargs(th.optim.Adam, {})):
        param = th.nn.Parameter(start.clone())
        optimizer = th.optim.Adam([param], lr=1e-2, **kwargs)
        grads = th.Generator().manual_seed(1)
        for _ in range(10):
            param.grad = th.randn(param.shape, generator=grads)
            optimizer.step()
        weights.append(param.detach())
    assert not th.equal(weights[1], start)
    th.testing.assert_close(weights[1], weights[0], rtol=0, atol=1e-6)


def test_the_optimizer_is_checked_on_the_models_device() -> None:
    # Capturable Adam steps on a GPU only: refused for the CPU, and for a CUDA model accepted
    # where there is a GPU (the check's probe runs where the model will).
    from harness.training.checks import check_optimizer

    with pytest.raises(ValueError, match=r"algo\.optimizer"):
        check_optimizer("Adam", {"capturable": True}, "cpu")
    if th.cuda.is_available():
        check_optimizer("Adam", {"capturable": True}, "cuda")


def test_a_buffer_kept_on_the_gpu_is_checked_against_the_gpus_free_memory(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # On CUDA the replay buffer is allocated on the GPU (harness.sb3.replay): a buffer
    # larger than the GPU's free memory is one line, not an out-of-memory error at the start.
    import harness.training.checks as checks
    from harness.config.schema import ExperimentConfig

    config = ExperimentConfig.model_validate(
        {"env": {"observation": "teammap"}, "vec": {"copies": 2},
         "algo": {"policy": "TeamMapPolicy", "buffer_size": 100_000, "prioritized": False}}
    )  # fmt: skip
    need = checks.check_replay_memory(config, available=2**40)  # about 0.4 GB
    monkeypatch.setattr(checks, "buffer_on_device", lambda device: True)
    monkeypatch.setattr(th.cuda, "mem_get_info", lambda device=None: (need // 2, 2 * need))
    with pytest.raises(ValueError, match=r"free on the GPU$"):
        checks.check_replay_memory(config)
    monkeypatch.setattr(th.cuda, "mem_get_info", lambda device=None: (2 * need, 4 * need))
    assert checks.check_replay_memory(config) == need
