"""CPU time of one greedy action for every VecEnv slot of a config: SB3's ``policy.predict``
beside ``DoubleDQN.predict`` (its own conversion of the observation and mode switch,
docs/performance.md "Acting: the policy's mode and its input"), alternately, medians over rounds.

A fresh model (the config's policy and network) on the config's VecEnv, one torch thread. With an
action mask (the goal action) ``DoubleDQN.predict`` masks and SB3's does not, so only the times
compare; elsewhere the actions are checked equal.

    python experiments/predict_time.py configs/ddqn_4agents.yaml [ROUNDS]   # default 11; seconds
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from harness import DoubleDQN
from harness.config.loading import load_config
from harness.training.adapters import make_vec_env
from harness.training.checks import network_kwargs, policy_class_name


def cpu_us(call: Callable[[], Any], calls: int = 400) -> float:
    """CPU microseconds per call (after one untimed call)."""
    call()
    start = time.process_time()
    for _ in range(calls):
        call()
    return (time.process_time() - start) / calls * 1e6


def main(path: str, rounds: int) -> None:
    torch.set_num_threads(1)
    cfg = load_config(path)
    venv = make_vec_env(cfg.env, copies=cfg.vec.copies, seed=0)
    kwargs = network_kwargs(cfg.algo, cfg.env.n_agents)
    model = DoubleDQN(policy_class_name(cfg.algo), venv, buffer_size=1000, policy_kwargs=kwargs)
    obs = venv.reset()

    def sb3() -> Any:
        return model.policy.predict(obs, deterministic=True)[0]

    def ours() -> Any:
        return model.predict(obs, deterministic=True)[0]

    if not model.masked:
        assert np.array_equal(sb3(), ours())
    times: dict[str, list[float]] = {"sb3": [], "ours": []}
    for _ in range(rounds):
        times["sb3"].append(cpu_us(sb3))
        times["ours"].append(cpu_us(ours))
    a, b = (float(np.median(times[k])) for k in ("sb3", "ours"))
    print(f"{path}: SB3 policy.predict {a:.0f} us, DoubleDQN.predict {b:.0f} us, ratio {b / a:.2f}")
    venv.close()


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 11)
