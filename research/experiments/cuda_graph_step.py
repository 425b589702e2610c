"""How fast DoubleDQN's prioritized gradient step could run on a GPU as one replayed CUDA graph.

The probe that preceded ``harness.sb3.graphs`` (research/performance-history.md, "One launch
per gradient step"): it takes ``bench train``'s models (:func:`harness.bench._models`: the device
replay buffer, filled with random-policy transitions) and times, for each network of ``bench
train``:

- ``eager``: ``model.train(steps, batch)`` with ``cuda_graph=False`` (every kernel launched from
  Python);
- ``graph``: one gradient step (the buffer's stratified sample, :meth:`DoubleDQN._gradient_step`
  and the priority update) recorded by hand as a CUDA graph (``torch.cuda.graph``) and replayed
  ``steps`` times, with a capturable optimizer (RMSprop, as ``bench train`` uses), the optimizer
  inside the graph (its learning rate a constant of the recording).

It also checks that the replays train: the loss stays finite, the weights and the priorities
move. ``harness bench train`` now times the shipped path (``DoubleDQN``'s own recorded step)
against ``cuda_graph=False``.

Usage (a GPU machine; exits with 2 where there is none)::

    python research/experiments/cuda_graph_step.py [--steps 400] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import torch as th


def _rate(steps: int, run: Any) -> float:
    th.cuda.synchronize()
    start = time.perf_counter()
    run()
    th.cuda.synchronize()
    return steps / (time.perf_counter() - start)


def _capture(model: Any, batch: int) -> tuple[th.cuda.CUDAGraph, th.Tensor]:
    buffer = model.replay_buffer
    model.policy.optimizer = th.optim.RMSprop(
        model.policy.parameters(), lr=5e-5, foreach=True, capturable=True
    )
    model.policy.set_training_mode(True)

    def step() -> th.Tensor:
        data = buffer.sample(batch)
        loss, abs_td = model._gradient_step(data)
        buffer.update_priorities(data.indices, abs_td)
        return loss

    side = th.cuda.Stream()
    side.wait_stream(th.cuda.current_stream())
    with th.cuda.stream(side):  # warm-up: the optimizer's state, cuBLAS's work spaces
        for _ in range(3):
            step()
    th.cuda.current_stream().wait_stream(side)
    model.policy.optimizer.zero_grad(set_to_none=True)
    graph = th.cuda.CUDAGraph()
    graph.register_generator_state(buffer._generator)
    with th.cuda.graph(graph):
        loss = step()
    return graph, loss


def probe(name: str, steps: int, rounds: int) -> dict[str, Any]:
    from harness.bench import TRAIN_NETS, _models

    net = TRAIN_NETS[name]
    out: dict[str, Any] = {"batch": net.batch}
    ours, _plain, venv = _models(net, 1, "cuda")
    ours.cuda_graph = False
    try:
        ours.train(2, net.batch)
        eager = [_rate(steps, lambda: ours.train(steps, net.batch)) for _ in range(rounds)]
        out["eager"] = max(eager)
        weights = [p.detach().clone() for p in ours.policy.parameters()]
        leaves = ours.replay_buffer._leaves.clone()
        graph, loss = _capture(ours, net.batch)

        def replays() -> None:
            for _ in range(steps):
                graph.replay()

        out["graph"] = max(_rate(steps, replays) for _ in range(rounds))
        out["graph_over_eager"] = out["graph"] / out["eager"]
        out["loss_finite"] = bool(th.isfinite(loss).item())
        out["weights_moved"] = any(
            not th.equal(a, b) for a, b in zip(weights, ours.policy.parameters())
        )
        out["priorities_moved"] = not th.equal(leaves, ours.replay_buffer._leaves)
    finally:
        venv.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=400, help="gradient steps per timing")
    parser.add_argument("--rounds", type=int, default=3, help="timings per rate (the best kept)")
    args = parser.parse_args()
    if not th.cuda.is_available():
        print("cuda_graph_step.py: needs a CUDA GPU", file=sys.stderr)
        sys.exit(2)
    from harness.bench import TRAIN_NETS

    result = {name: probe(name, args.steps, args.rounds) for name in TRAIN_NETS}
    print(json.dumps({"device": th.cuda.get_device_name(0), **result}, indent=1))


if __name__ == "__main__":
    main()
