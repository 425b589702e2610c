"""A gradient step recorded once as a CUDA graph and launched again with one call.

On a GPU, a gradient step of :class:`~harness.sb3.dqn.DoubleDQN` is some hundred small kernels
(the stratified sample, two forward passes for the double-Q target, the loss terms, the
backward pass, the gradient clipping, the priority update), each launched from Python: on an
H200 the thesis's MLP made about 340 gradient steps/s that way, what the machine's CPU makes.
torch records the kernels of a function once (``torch.cuda.graph``) and launches all of them
again in one call; recorded so, the same step made about 2,300 steps/s
(research/performance-history.md, "One launch per gradient step").

A recorded step reads its tensors where they were when it was recorded and keeps every number
it read from Python then. So what changes from step to step lives on the device and is written
in place: the replay buffer's stored count and beta
(:class:`~harness.sb3.replay.Replay` on the device), the uniform draws of the
sample, which are drawn before each launch into the graph's input with the buffer's own
generator, in the order the step without a graph draws them, and the statistics, copied out
after each launch. The optimizer's step stays outside the graph: its learning rate follows the
schedule, and a fused or multi-tensor step is a few kernels. What stays fixed is the step's key
(:meth:`DoubleDQN._graph_key`: the batch size, the buffer's constants and storage, the loss's
settings, the weights' storage); the owner records the step again when it changes.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch as th

__all__ = ["GraphedStep", "record_step", "side_stream"]


@contextmanager
def side_stream(enabled: bool = True) -> Iterator[None]:
    """Run the block on a fresh CUDA stream ordered after and before the current one's work, as
    torch asks of the steps before a capture (lazy set-up such as cuBLAS's work spaces then
    happens outside the graph); a no-op when not ``enabled``."""
    if not enabled:
        yield
        return
    current = th.cuda.current_stream()
    stream = th.cuda.Stream()
    stream.wait_stream(current)
    with th.cuda.stream(stream):
        yield
    current.wait_stream(stream)


class GraphedStep:
    """One recorded step: its input (the uniform draws of the sample), its outputs (the step's
    statistics by name) and the gradients it writes, replayed by :meth:`replay`.

    Args:
        key: What the step held fixed when it was recorded (compared by the owner).
        step: The step to record: takes the draws ``(batch,)`` and returns its statistics by
            name, one-element tensors; it leaves its gradients in the parameters' ``grad``.
        batch: The number of draws a step takes (the sample's size).
        draw: Draws ``batch`` uniform numbers into the given tensor (the buffer's generator).
        parameters: The parameters whose gradients the step writes.
        device: The CUDA device.

    Raises:
        RuntimeError: The step cannot be recorded (it reads the device from the host, or makes
            a tensor whose shape depends on its values).
    """

    def __init__(
        self,
        key: tuple[Any, ...],
        step: Callable[[th.Tensor], dict[str, th.Tensor]],
        batch: int,
        draw: Callable[[int, th.Tensor], Any],
        parameters: list[th.nn.Parameter],
        device: th.device,
    ) -> None:
        self.key = key
        self._draw = draw
        self._draws = th.zeros(batch, dtype=th.float64, device=device)
        self._graph = th.cuda.CUDAGraph()
        with th.cuda.graph(self._graph):
            self._outputs = step(self._draws)
        # The gradients live in the graph's memory: every replay writes them there.
        self._grads = [(p, p.grad) for p in parameters]

    def replay(self) -> dict[str, th.Tensor]:
        """Draw the sample's numbers, launch the step, and return copies of its statistics
        (the next launch overwrites the outputs). Reads nothing from the device."""
        self._draw(self._draws.shape[0], self._draws)
        for parameter, grad in self._grads:
            # Anything that set the gradients to None since is undone: the step writes here.
            parameter.grad = grad
        self._graph.replay()
        return {name: value.clone() for name, value in self._outputs.items()}


def record_step(
    key: tuple[Any, ...],
    step: Callable[[th.Tensor], dict[str, th.Tensor]],
    batch: int,
    draw: Callable[[int, th.Tensor], Any],
    parameters: list[th.nn.Parameter],
    device: th.device,
) -> GraphedStep | None:
    """A :class:`GraphedStep` of these arguments, or ``None`` with a warning (training goes on
    without a graph) when the step cannot be recorded."""
    try:
        return GraphedStep(key, step, batch, draw, parameters, device)
    except RuntimeError as error:
        warnings.warn(
            f"DoubleDQN: the gradient step could not be recorded as a CUDA graph "
            f"({str(error).splitlines()[0]}); training goes on without one",
            RuntimeWarning,
            stacklevel=4,
        )
        return None
