"""What the learner alone costs a run (research/performance-history.md, "The learner's
floor"): the time of one gradient step of a config's ``DoubleDQN`` (built as ``harness run``
builds it, its buffer filled by the env with ε = 1), at one and at two torch threads, and the
transitions/s that the gradient steps alone would leave a run that spent nothing on collecting.

A run of ``--config`` takes ``epochs`` gradient steps every ``train_freq`` vector steps of
``copies x n_agents`` slots, so one gradient step per
``train_freq * copies * n_agents / epochs`` transitions. Its rate cannot exceed that number
over the step's time, whatever the env costs: the ceiling this script prints.

``--bf16`` also times the step under ``torch.autocast("cpu", dtype=torch.bfloat16)`` (mixed
precision, where the CPU has bf16 instructions): a measurement only, the harness has no such
option.

    python research/experiments/learner_floor.py [--config configs/goals_2agents.yaml] [--fill 4000]
        [--steps 40] [--rounds 3] [--threads 1 2] [--bf16]
"""

from __future__ import annotations

import argparse
import contextlib
import time

import numpy as np
import torch

from harness.config.loading import load_config
from harness.training.adapters import make_vec_env
from harness.training.train import apply_phase, build_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/goals_2agents.yaml")
    parser.add_argument("--fill", type=int, default=4000, help="transitions in the buffer")
    parser.add_argument("--steps", type=int, default=40, help="gradient steps per timing")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--bf16", action="store_true")
    args = parser.parse_args()

    config = load_config(args.config, [])
    phase = config.phases[0]
    venv = make_vec_env(config.env, copies=config.vec.copies, seed=0)
    model = build_model(config, venv)
    apply_phase(model, phase, 0)
    model.exploration_schedule = lambda _: 1.0
    model.learning_starts = 10**9  # fill only
    model.learn(args.fill)
    slots = config.vec.copies * config.env.n_agents
    per_step = phase.train_freq * slots / phase.epochs[0][1]
    batch = phase.batch_size
    print(f"{args.config}: one gradient step per {per_step:g} transitions (batch {batch})")

    variants = [(f"{t} thread{'s' * (t > 1)}", t, False) for t in args.threads]
    if args.bf16:
        variants += [(f"{t} thread{'s' * (t > 1)}, bf16", t, True) for t in args.threads]
    times: dict[str, list[float]] = {name: [] for name, _, _ in variants}
    for _ in range(args.rounds):  # alternately, the machine's drift shared
        for name, threads, bf16 in variants:
            torch.set_num_threads(threads)
            autocast = torch.autocast("cpu", dtype=torch.bfloat16)
            with autocast if bf16 else contextlib.nullcontext():
                model.train(2, batch)  # warm-up
                start = time.perf_counter()
                model.train(args.steps, batch)
            times[name].append((time.perf_counter() - start) / args.steps)
    venv.close()
    for name, values in times.items():
        ms = 1000 * float(np.median(values))
        print(
            f"{name:>18}: {ms:6.1f} ms a gradient step (rounds: "
            f"{', '.join(f'{1000 * v:.1f}' for v in values)}); "
            f"at most {per_step / ms * 1000:,.0f} transitions/s with free collection"
        )


if __name__ == "__main__":
    main()
