"""``harness bench``: throughput and memory figures for the thesis's settings.

Benchmarks, not tests: they print figures and ratios measured in the same process, so a slow or
busy machine shifts all of them together. Nothing here asserts a time.

* ``env``: agent-steps per second of the bare ``parallel_env`` loop (thesis and team-map
  observations), of the training VecEnv with 1, 4, 16 and 64 copies on both backends (the
  batched core's and SuperSuit's over the PettingZoo env, alternately), and of 8 SuperSuit
  copies stepped by 1 or 2 processes;
* ``train``: gradient steps and transitions per second of ``DoubleDQN`` + PER against SB3's
  ``DQN`` + ``ReplayBuffer`` (same network, batch and train_freq), run alternately; gradient
  steps per second of both for the thesis's MLP 3x512, the team-map CNN and the goal action's
  slot scorer, on the CPU and, when torch sees one, the GPU (with the most ``goals_2agents`` can
  train on the CPU, its env free);
  gradient steps per second over batch sizes, network widths and torch thread counts;
* ``sharing``: gradient steps per second of each ``algo.sharing`` mode (one network, one with
  the agent's index, one parameter set per agent), same network and batch;
* ``eval``: episodes per second of ``harness eval`` for the random policy, an MLP policy and the
  frontier baselines;
* ``memory``: peak resident memory of a training process with a full 100,000-transition buffer.
"""

from __future__ import annotations

import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.config.schema import AlgoConfig, EnvConfig
from harness.processes import python_command

#: The thesis's setting: 50x50 random maps, 4 agents, 1000 steps.
THESIS_ENV = EnvConfig(n_agents=4, max_steps=1000)
THESIS_NET = [512, 512, 512]
#: The team map of the shipped configs with the pocket planner's step, 2 agents, 50x50 random
#: maps (``teammap_2agents_pocket`` less its map mix): ``bench eval``'s ``frontier_step`` rows.
TEAMMAP_ENV = EnvConfig(
    n_agents=2,
    max_steps=1000,
    observation={"teammap": {"crop": 15, "global_size": 13, "ego_size": 21, "ego_block": 5}},
    frontier={"action": "step", "planner": "pocket"},
)
#: The same with the goal action (k = 8), as ``goals_2agents``.
GOALS_ENV = TEAMMAP_ENV.model_copy(
    update={"frontier": {"action": {"goal": {"k": 8}}, "planner": "pocket"}}
)
#: The rollout chooser's setting (``--policy rollout``, docs/planners.md): the goal action with
#: 4 agents on 50x50 random maps, where it beats every written planner.
ROLLOUT_ENV = GOALS_ENV.model_copy(update={"n_agents": 4})
#: The map prior of ``bench env``'s goal-action row with ``env.prior`` (relative to the current
#: directory, as ``env.prior`` is; the row is left out where it is missing).
PRIOR_REFERENCE = "runs/reference/prior_rooms"
#: Env copies of the VecEnv figures (the batched core pays off with many).
VEC_COPIES = (1, 4, 16, 64)


def _rate(
    count: float, fn: Callable[[], Any], cpu: dict[str, float] | None = None, name: str = ""
) -> float:
    """``count`` over the wall time ``fn()`` takes; with ``cpu``, also ``cpu[name]``: ``count``
    over the process's CPU time (all its threads), which a busy machine moves less."""
    start, start_cpu = time.perf_counter(), time.process_time()
    fn()
    if cpu is not None:
        cpu[name] = count / max(time.process_time() - start_cpu, 1e-9)
    return count / (time.perf_counter() - start)


def machine_info() -> dict[str, Any]:
    """The machine and versions the figures were measured with."""
    import pettingzoo
    import stable_baselines3
    import supersuit
    import torch

    return {
        "machine": f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPUs",
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "stable_baselines3": stable_baselines3.__version__,
        "supersuit": getattr(supersuit, "__version__", "?"),
        "pettingzoo": pettingzoo.__version__,
        "numpy": np.__version__,
    }


# ---------------------------------------------------------------------- env
def bench_env(episodes: int = 3) -> dict[str, Any]:
    """Agent-steps per second of the bare env and of the training VecEnv."""
    from harness.factory import make_env
    from harness.training.adapters import make_vec_env

    n, steps = THESIS_ENV.n_agents, THESIS_ENV.max_steps
    rng = np.random.default_rng(0)
    moves = rng.integers(0, 5, (steps, n)).tolist()

    def bare_rate(
        observation: str | dict[str, Any],
        frontier: dict[str, Any] | None = None,
        base: EnvConfig = THESIS_ENV,
    ) -> float:
        env = make_env(base.model_copy(update={"observation": observation, "frontier": frontier}))
        env.reset(seed=0)
        actions = [dict(zip(env.possible_agents, a)) for a in moves]
        for a in actions[:10]:  # compiling (or loading from numba's cache) is not the step's speed
            env.step(a)

        def bare() -> None:
            for _ in range(episodes):
                env.reset()
                for a in actions:
                    env.step(a)

        return _rate(episodes * steps * n, bare)

    out: dict[str, Any] = {"env_bare_agent_steps_per_s": bare_rate("thesis")}
    # The team-map observation (images of the team's knowledge, built incrementally), same loop.
    out["env_bare_teammap_agent_steps_per_s"] = bare_rate("teammap")
    out["env_teammap_over_thesis"] = (
        out["env_bare_teammap_agent_steps_per_s"] / out["env_bare_agent_steps_per_s"]
    )
    # With the ego view of the shipped team-map configs (pooled from a summed-area table).
    out["env_bare_teammap_ego_agent_steps_per_s"] = bare_rate(
        {"teammap": {"ego_size": 21, "ego_block": 5}}
    )
    # With the planner extension's frontier field and compass (env.frontier: {}): one compiled
    # search a step.
    out["env_bare_teammap_frontier_agent_steps_per_s"] = bare_rate("teammap", {})
    # With the classical explorer's claimed moves in the compass (planner: order): its
    # incremental team map and one search per agent a step, on top of the frontier field.
    out["env_bare_teammap_claims_agent_steps_per_s"] = bare_rate("teammap", {"planner": "order"})
    # The same with the pocket tie-break (planner: pocket): a search finishes the nearest
    # distance layer to see every tied cell instead of stopping at the first.
    out["env_bare_teammap_pocket_agent_steps_per_s"] = bare_rate("teammap", {"planner": "pocket"})

    # The goal action (k = 8), and with a map prior on its candidates (env.prior: the floor
    # plans' reference prior, asked every PRIOR_EVERY steps), where the repository has it.
    goal = {"action": {"goal": {"k": 8}}, "planner": "pocket"}
    out["env_bare_goals_agent_steps_per_s"] = bare_rate("teammap", goal)
    if Path(PRIOR_REFERENCE).is_dir():
        prior_env = THESIS_ENV.model_copy(update={"prior": PRIOR_REFERENCE})
        out["env_bare_goals_prior_agent_steps_per_s"] = bare_rate("teammap", goal, prior_env)
        out["env_goals_prior_over_goals"] = (
            out["env_bare_goals_prior_agent_steps_per_s"] / out["env_bare_goals_agent_steps_per_s"]
        )
        # And its prediction as images too (the team map's predicted views), on the same calls.
        out["env_bare_goals_predicted_agent_steps_per_s"] = bare_rate(
            {"teammap": {"predicted": True}}, goal, prior_env
        )

    def vec_rate(copies: int, num_cpus: int = 0, backend: str = "core") -> float:
        venv = make_vec_env(THESIS_ENV, copies, num_cpus, seed=0, backend=backend)
        try:
            venv.reset()
            n_steps = max(200, (episodes * steps * n) // venv.num_envs)
            acts = rng.integers(0, 5, (n_steps, venv.num_envs))
            for a in acts[:10]:  # as bare_rate: the first steps compile
                venv.step(a)

            def run() -> None:
                for a in acts:
                    venv.step(a)

            return _rate(n_steps * venv.num_envs, run)
        finally:
            venv.close()

    # Both backends, alternately per size, so that machine load shifts both together.
    by: dict[str, dict[int, float]] = {"core": {}, "supersuit": {}}
    for c in VEC_COPIES:
        for backend in by:
            by[backend][c] = vec_rate(c, backend=backend)
    out["env_vec_by_copies"] = by["core"]
    out["env_vec_supersuit_by_copies"] = by["supersuit"]
    out["env_vec_core_over_supersuit"] = {c: by["core"][c] / by["supersuit"][c] for c in by["core"]}
    out["env_vec_agent_steps_per_s"] = by["core"][4]
    out["env_vec_over_bare"] = out["env_vec_agent_steps_per_s"] / out["env_bare_agent_steps_per_s"]
    out["env_vec_8_copies_by_processes"] = {p: vec_rate(8, p, backend="supersuit") for p in (0, 2)}
    return out


# ---------------------------------------------------------------------- train
@dataclass(frozen=True)
class TrainNet:
    """A network ``bench train`` times: the env it reads (4 copies), the ``algo`` section that
    sizes it (policy and network, as ``harness run`` reads them), the batch, how many random
    transitions fill each learner's buffer before the timing, and its share of the gradient
    steps per timed call (a slow net runs fewer, so that the section stays short)."""

    env: EnvConfig
    algo: AlgoConfig
    batch: int
    fill: int = 8_000
    buffer_size: int = 100_000
    steps_share: float = 1.0


#: The networks of ``bench train``'s table, each on every device: the thesis's MLP 3x512 on its
#: observation, the team-map CNN of the shipped team-map configs
#: (configs/teammap_2agents_pocket.yaml: its observation, frontier step, policy and batch) on
#: 50x50 random maps, and the slot scorer of the goal action (configs/goals_2agents.yaml: its
#: policy, network, Adam and batch, with PER as every row), the net whose gradient steps bound
#: that run's rate (docs/performance.md "The learner's floor"); the team-map nets with a
#: smaller buffer and fill, as a team-map transition is ~20 times a thesis one and its env
#: steps slower, and fewer gradient steps (a quarter for the CNN, ~4x slower than the MLP on a
#: CPU, and the slot scorer likewise).
TRAIN_NETS: dict[str, TrainNet] = {
    "mlp_3x512": TrainNet(THESIS_ENV, AlgoConfig(net_arch=THESIS_NET), batch=32),
    "teammap_cnn": TrainNet(
        TEAMMAP_ENV,
        AlgoConfig(policy="TeamMapPolicy", net_arch=[], features_dim=256, cnn_channels=(8, 16)),
        batch=64,
        fill=2_000,
        buffer_size=10_000,
        steps_share=0.25,
    ),
    "goal_slots": TrainNet(
        GOALS_ENV,
        AlgoConfig(
            policy="SlotTeamMapPolicy",
            net_arch=[128],
            features_dim=256,
            cnn_channels=(8, 16),
            optimizer="Adam",
        ),
        batch=64,
        fill=2_000,
        buffer_size=10_000,
        steps_share=0.25,
    ),
}
#: Transitions of ``configs/goals_2agents.yaml`` per gradient step (``train_freq`` 4 vector steps
#: of 8 copies x 2 agents, 4 gradient steps each; tests/test_bench.py reads it from the config):
#: with ``goal_slots``'s rate, the most that run can train whatever its env costs.
GOALS_TRANSITIONS_PER_STEP = 16
#: The net of the report's flat keys and targets (``train_grad_steps_per_s``, ...), on the CPU.
REPORT_NET = "mlp_3x512"
#: The learners of each row, in the order they are timed: ours, then SB3's.
TRAIN_LEARNERS = ("doubledqn_per", "dqn")
#: On CUDA, ours is timed a third time without its recorded step (``cuda_graph=False``).
NO_GRAPH = "doubledqn_per_no_graph"


def train_devices() -> tuple[str, ...]:
    """The devices ``bench train`` times: the CPU, and CUDA when torch sees a GPU."""
    import torch

    return ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",)


def _models(net: TrainNet, threads: int, device: str = "cpu") -> tuple[Any, Any, Any]:
    """DoubleDQN+PER and plain DQN (uniform replay) with ``net`` on ``device``, on the same
    VecEnv, both with a filled buffer: SB3's on the host, ours where ``harness run`` puts it
    (:func:`harness.sb3.replay.replay_for`: on the device on CUDA)."""
    import torch
    from stable_baselines3 import DQN
    from stable_baselines3.common.logger import configure

    from harness import DoubleDQN
    from harness.sb3.registry import POLICIES
    from harness.sb3.replay import replay_for
    from harness.training.adapters import make_vec_env
    from harness.training.checks import policy_class_name, policy_kwargs

    torch.set_num_threads(threads)
    venv = make_vec_env(net.env, copies=4, seed=0)
    common = {
        "learning_rate": 5e-5,
        "buffer_size": net.buffer_size,
        "batch_size": net.batch,
        "train_freq": (2, "step"),
        "gradient_steps": 1,
        # The network and its optimizer's step as `harness run` builds them from the algo
        # section (RMSprop's multi-tensor step; Adam's fused one on the CPU).
        "policy_kwargs": policy_kwargs(net.algo, net.env.n_agents, device),
        "device": device,
    }
    buffer_class, buffer_kwargs = replay_for(device, prioritized=True)
    ours = DoubleDQN(
        policy_class_name(net.algo),
        venv,
        replay_buffer_class=buffer_class,
        replay_buffer_kwargs={**buffer_kwargs, "alpha": 0.55, "beta": 0.4},
        **common,
    )
    # SB3's DQN knows only its own aliases: it gets the registry's class (SB3's MlpPolicy for
    # the MLP); it picks its DictReplayBuffer for a Dict observation by itself.
    plain = DQN(POLICIES[net.algo.policy].load(), venv, **common)
    for model in (ours, plain):
        model.set_logger(configure(None, []))
    # Fill both buffers with the same random-policy transitions (no training: learning_starts).
    for model in (ours, plain):
        model.learning_starts = 10**9
        model.learn(net.fill)
        model.learning_starts = 0
    return ours, plain, venv


def _grad_rate(model: Any, grad_steps: int, batch: int, device: str) -> float:
    """Gradient steps/s of one ``train`` call; on CUDA it waits for the queued kernels."""
    import torch

    def run() -> None:
        model.train(grad_steps, batch)
        if device == "cuda":
            torch.cuda.synchronize()

    return _rate(grad_steps, run)


def bench_train(
    rounds: int = 5,
    grad_steps: int = 100,
    transitions: int = 2_000,
    nets: dict[str, TrainNet] | None = None,
) -> dict[str, Any]:
    """Gradient steps/s, DoubleDQN+PER vs plain DQN (same net, batch and device), measured
    alternately, for each net of :data:`TRAIN_NETS` on each device of :func:`train_devices`
    (``train_grad_steps_by_device``: device -> net -> learner's rate and ``ratio``, ours over
    SB3's), ``grad_steps`` per call times each net's ``steps_share``; and, for
    :data:`REPORT_NET` on the CPU, the flat keys of the report's targets with the transitions/s
    of ``learn`` (``transitions`` per call). Medians over ``rounds``; ``nets`` replaces
    :data:`TRAIN_NETS` (tests)."""
    nets = TRAIN_NETS if nets is None else nets
    by_device: dict[str, dict[str, dict[str, float]]] = {}
    flat: dict[str, list[float]] = {}
    for device in train_devices():
        by_device[device] = {}
        for name, net in nets.items():
            steps = max(1, round(grad_steps * net.steps_share))
            ours, plain, venv = _models(net, 1, device)
            try:
                for model in (ours, plain):  # warm-up: first calls allocate (and on CUDA, load);
                    model.train(4, net.batch)  # on CUDA the second call records ours's step
                    model.train(2, net.batch)
                rates: dict[str, list[float]] = {learner: [] for learner in TRAIN_LEARNERS}
                # The report's net on the CPU also gives its transitions/s.
                learn = device == "cpu" and name == REPORT_NET
                for _ in range(rounds):
                    for learner, model in zip(TRAIN_LEARNERS, (ours, plain)):
                        rates[learner].append(_grad_rate(model, steps, net.batch, device))
                    if device == "cuda":
                        # Ours again without the recorded step (harness.sb3.graphs).
                        ours.cuda_graph = False
                        rate = _grad_rate(ours, steps, net.batch, device)
                        rates.setdefault(NO_GRAPH, []).append(rate)
                        ours.cuda_graph = True
                    if learn:
                        for learner, model in zip(TRAIN_LEARNERS, (ours, plain)):
                            flat.setdefault(learner, []).append(
                                _rate(
                                    transitions,
                                    lambda m=model: m.learn(transitions, reset_num_timesteps=False),
                                )
                            )
            finally:
                venv.close()
            row = {learner: float(np.median(r)) for learner, r in rates.items()}
            row["ratio"] = row["doubledqn_per"] / row["dqn"]
            if NO_GRAPH in row:
                row["graph_gain"] = row["doubledqn_per"] / row[NO_GRAPH]
            by_device[device][name] = row
    out: dict[str, Any] = {"train_grad_steps_by_device": by_device}
    mlp = by_device["cpu"].get(REPORT_NET)
    if mlp is not None:
        out["train_grad_steps_per_s"] = mlp["doubledqn_per"]
        out["train_grad_steps_per_s_plain_dqn"] = mlp["dqn"]
        out["train_grad_steps_ratio"] = mlp["ratio"]
        out["train_transitions_per_s"] = float(np.median(flat["doubledqn_per"]))
        out["train_transitions_per_s_plain_dqn"] = float(np.median(flat["dqn"]))
        out["train_transitions_ratio"] = (
            out["train_transitions_per_s"] / out["train_transitions_per_s_plain_dqn"]
        )
    return out


def bench_scaling(grad_steps: int = 60) -> dict[str, Any]:
    """DoubleDQN+PER gradient steps/s by network, batch size and torch threads."""
    nets = {"2x64": [64, 64], "2x256": [256, 256], "3x512": THESIS_NET}
    out: dict[str, Any] = {}
    for threads in (1, 2):
        for name, net in nets.items():
            for batch in (32, 64, 256):
                setting = TrainNet(THESIS_ENV, AlgoConfig(net_arch=net), batch)
                ours, _, venv = _models(setting, threads)
                venv.close()
                ours.train(5, batch)  # warm-up
                rate = _rate(grad_steps, lambda m=ours, b=batch: m.train(grad_steps, b))
                out[f"{name}/batch{batch}/threads{threads}"] = rate
    import torch

    torch.set_num_threads(1)
    return {"train_grad_steps_per_s_by_setting": out}


def bench_teacher(rounds: int = 3, copies: int = 8, warm_steps: int = 300) -> dict[str, Any]:
    """Decisions labelled per second by the true-map teacher of training (``algo.teacher``,
    :class:`harness.training.teacher.TeacherLabeller`, scored by the steps to 99 %) on one
    thread and on every core this process may use (what a run without ``algo.threads`` gives
    it), alternately: :data:`ROLLOUT_ENV`'s 4 agents in ``copies`` copies, each played by its
    planner (slot 0) for ``warm_steps`` steps, then every deciding agent labelled, every call
    on the same states. Medians over ``rounds``."""
    from envs.coverage.core import CoverageCore
    from harness.config.schema import TeacherConfig
    from harness.factory import make_core_spec
    from harness.processes import available_cores
    from harness.training.teacher import TeacherLabeller

    core = CoverageCore(make_core_spec(ROLLOUT_ENV), copies)
    for b in range(copies):
        core.reset(b, seed=b)
    core.observe()
    for _ in range(warm_steps):  # the planner's moves: every agent decides at every state
        core.step(np.zeros((copies, ROLLOUT_ENV.n_agents), dtype=np.int64))
        core.observe()
    cores = available_cores()
    labellers = {
        threads: TeacherLabeller(TeacherConfig(reach=0.99), seed=0, threads=threads)
        for threads in dict.fromkeys((1, cores))
    }
    labels = int((labellers[1](core) >= 0).sum())  # also compiles what the labels need
    rates: dict[int, list[float]] = {threads: [] for threads in labellers}
    for _ in range(rounds):
        for threads, labeller in labellers.items():
            rates[threads].append(_rate(labels, lambda labeller=labeller: labeller(core)))
    per_s = {threads: float(np.median(r)) for threads, r in rates.items()}
    return {
        "train_teacher_threads": cores,
        "train_teacher_copies": copies,
        "train_teacher_labels_per_s": per_s[cores],
        "train_teacher_1_thread_labels_per_s": per_s[1],
        "train_teacher_over_1_thread": per_s[cores] / per_s[1],
    }


# ---------------------------------------------------------------------- sharing
SHARING_MODES = ("shared", "shared_id", "per_agent")


def bench_sharing(
    net: list[int] | None = None, batch: int = 32, grad_steps: int = 60, fill: int = 4_000
) -> dict[str, Any]:
    """DoubleDQN+PER gradient steps/s of each ``algo.sharing`` mode, 1 torch thread, measured
    in turns. A ``per_agent`` step trains all 4 agents' sets, each on ``batch`` samples in
    expectation (``4 * batch`` drawn), so it does about 4 times the work of a shared step."""
    import torch

    from harness import DoubleDQN, PrioritizedReplayBuffer
    from harness.config.schema import AlgoConfig
    from harness.training.adapters import make_vec_env
    from harness.training.checks import policy_class_name, policy_kwargs

    torch.set_num_threads(1)
    net = THESIS_NET if net is None else net
    models, venvs = {}, []
    for mode in SHARING_MODES:
        env = THESIS_ENV.with_agent_id(mode != "shared")  # as algo.sharing sets it in a config
        venv = make_vec_env(env, copies=4, seed=0)
        venvs.append(venv)
        # The policy, its network and its optimizer's step as `harness run` builds them for
        # this mode (the thesis's RMSprop).
        algo = AlgoConfig(sharing=mode, net_arch=net)
        model = DoubleDQN(
            policy_class_name(algo),
            venv,
            buffer_size=100_000,
            batch_size=batch,
            learning_starts=10**9,  # fill the buffer without training
            replay_buffer_class=PrioritizedReplayBuffer,
            policy_kwargs=policy_kwargs(algo, THESIS_ENV.n_agents, "cpu"),
            device="cpu",
        )
        model.learn(fill)
        model.train(3, batch)  # warm-up
        models[mode] = model
    try:
        rates: dict[str, list[float]] = {mode: [] for mode in SHARING_MODES}
        for _ in range(3):
            for mode, model in models.items():
                rates[mode].append(_rate(grad_steps, lambda m=model: m.train(grad_steps, batch)))
    finally:
        for venv in venvs:
            venv.close()
    return {"train_grad_steps_per_s_by_sharing": {m: float(np.median(r)) for m, r in rates.items()}}


# ---------------------------------------------------------------------- eval
#: Rounds of the planners' rows in `bench eval` (each ratio to `frontier` is a median of rounds).
PLANNER_ROUNDS = 3


def bench_eval(episodes: int = 8) -> dict[str, Any]:
    """Episodes per second of greedy evaluation (MLP 3x512) and of every planner's baseline
    (``eval_<baseline>_episodes_per_s``, one per entry of ``envs.coverage.frontier.PLANNERS``),
    with each planner's speed over the classical explorer's (``eval_<baseline>_over_frontier``:
    the median over :data:`PLANNER_ROUNDS` rounds of the ratio within a round; the rates too),
    and every row per CPU second as well (``eval_episodes_per_cpu_s``: ``mlp``, ``random``, each
    baseline, ``teammap_frontier_step``, ``goals_frontier_step``, ``rollout_threads1`` and
    ``rollout_threadsN``); the rollout chooser's rows: :func:`_rollout_rates`."""
    import torch

    from envs.coverage.frontier import PLANNERS
    from harness import DoubleDQN
    from harness.evaluation.baselines import make_baseline
    from harness.evaluation.episodes import model_policy, run_episodes
    from harness.training.adapters import make_vec_env

    torch.set_num_threads(1)
    venv = make_vec_env(THESIS_ENV, copies=1, seed=0)
    # An untrained network of the thesis's size: the weights do not change the speed.
    model = DoubleDQN("MlpPolicy", venv, policy_kwargs={"net_arch": THESIS_NET}, device="cpu")
    venv.close()
    cpu: dict[str, float] = {}  # the same rates per CPU second, by row
    random = make_baseline("random", 0)
    for policy in (model_policy(model), random):  # every row's first episode is untimed
        run_episodes(policy, THESIS_ENV, 1, 0)
    mlp = _rate(
        episodes, lambda: run_episodes(model_policy(model), THESIS_ENV, episodes, 0), cpu, "mlp"
    )
    # `harness eval --policy random`: 100 episodes, 8 copies side by side (the command's default).
    rand = _rate(
        4 * episodes, lambda: run_episodes(random, THESIS_ENV, 4 * episodes, 0), cpu, "random"
    )

    names = [entry.baseline for entry in PLANNERS.values()]
    for name in names:
        # One episode first: compiling (or loading from numba's cache) what it needs is not
        # the planner's speed, and would fall on whichever row needs it first.
        run_episodes(make_baseline(name, 0), THESIS_ENV, 1, 0)
    # Three rounds, the planners in turn within each (every planner's episodes in one call,
    # as `harness eval` plays them): a drift of the machine's speed falls on every planner of a
    # round alike, so each ratio to `frontier` is taken within a round, and the median of the
    # rounds reported (the rates too: their medians).
    walls: dict[str, list[float]] = {name: [] for name in names}
    cpus: dict[str, list[float]] = {name: [] for name in names}
    for _ in range(PLANNER_ROUNDS):
        for name in names:
            round_cpu: dict[str, float] = {}
            walls[name].append(
                _rate(
                    episodes,
                    lambda name=name: run_episodes(make_baseline(name, 0), THESIS_ENV, episodes, 0),
                    round_cpu,
                    name,
                )
            )
            cpus[name].append(round_cpu[name])
    rates = {name: float(np.median(walls[name])) for name in names}
    cpu.update({name: float(np.median(cpus[name])) for name in names})
    over_frontier = {
        name: float(np.median(np.divide(walls[name], walls["frontier"]))) for name in names
    }
    out: dict[str, Any] = {
        "eval_episodes_per_s": mlp,
        "eval_100_episodes_s": 100 / mlp,
        "eval_random_episodes_per_s": rand,
        "eval_episodes_per_cpu_s": cpu,
    }
    # The planner's step through the team-map env and through the goal action's env (its
    # candidates built every step): `harness eval --policy frontier_step` on such configs.
    step = make_baseline("frontier_step", 0)
    for name, env in (("teammap", TEAMMAP_ENV), ("goals", GOALS_ENV)):
        run_episodes(step, env, 1, 0)  # compiles what the first episode needs
        count = max(1, episodes // 2)
        out[f"eval_{name}_frontier_step_episodes_per_s"] = _rate(
            count,
            lambda env=env, count=count: run_episodes(step, env, count, 0),
            cpu,
            f"{name}_frontier_step",
        )
    for name, rate in rates.items():
        out[f"eval_{name}_episodes_per_s"] = rate
        if name != "frontier":
            out[f"eval_{name}_over_frontier"] = over_frontier[name]
    out.update(_rollout_rates(max(1, episodes // 2), cpu))
    return out


def _rollout_rates(episodes: int, cpu: dict[str, float]) -> dict[str, Any]:
    """Episodes/s of ``--policy rollout`` on :data:`ROLLOUT_ENV` (its episodes as copies side
    by side, as ``harness eval`` plays them) on one thread and on every core this process may
    use (the command's default: the copies decide, and each decision scores its maps, side by
    side; the same episodes and choices), one after the other, after a short episode that
    compiles what they need."""
    from envs.coverage.rollouts import SampledChooser
    from harness.evaluation.baselines import BASELINES, RolloutPolicy
    from harness.evaluation.episodes import run_episodes
    from harness.processes import available_cores

    env = BASELINES["rollout"].env_config(ROLLOUT_ENV)
    small = env.model_copy(update={"height": 12, "width": 12, "max_steps": 100})
    run_episodes(RolloutPolicy(SampledChooser(after=0.0), threads=1), small, 1, 0)
    cores = available_cores()
    rates = {
        threads: _rate(
            episodes,
            lambda threads=threads: run_episodes(RolloutPolicy(threads=threads), env, episodes, 0),
            cpu,
            f"rollout_threads{threads}",
        )
        for threads in dict.fromkeys((1, cores))
    }
    return {
        "eval_rollout_threads": cores,
        "eval_rollout_episodes_per_s": rates[cores],
        "eval_rollout_1_thread_episodes_per_s": rates[1],
        "eval_rollout_over_1_thread": rates[cores] / rates[1],
    }


# ---------------------------------------------------------------------- memory
_MEMORY_SCRIPT = """
import resource, torch
from harness import DoubleDQN, PrioritizedReplayBuffer
from harness.training.adapters import make_vec_env
from harness.bench import THESIS_ENV, THESIS_NET
torch.set_num_threads(1)
venv = make_vec_env(THESIS_ENV, copies=4, seed=0)
model = DoubleDQN("MlpPolicy", venv, buffer_size=100_000, learning_starts=100_000,
                  replay_buffer_class=PrioritizedReplayBuffer, batch_size=32,
                  policy_kwargs={"net_arch": THESIS_NET}, device="cpu")
model.learn(100_000 + 2_000)  # fill the buffer, then train a little
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def bench_memory() -> dict[str, Any]:
    """Peak resident memory (MiB) of a training process with a full 100,000-transition buffer."""
    proc = subprocess.run(
        python_command(_MEMORY_SCRIPT), capture_output=True, text=True, check=True
    )
    kib = int(proc.stdout.strip().splitlines()[-1])
    # ru_maxrss is KiB on Linux, bytes on macOS.
    mib = kib / 1024 / (1024 if sys.platform == "darwin" else 1)
    return {"train_peak_memory_mib": mib, "bench_process_peak_memory_mib": _own_peak_mib()}


def _own_peak_mib() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024 / (1024 if sys.platform == "darwin" else 1)


SECTIONS: dict[str, list[Callable[[], dict[str, Any]]]] = {
    "env": [bench_env],
    "train": [bench_train, bench_scaling, bench_teacher],
    "sharing": [bench_sharing],
    "eval": [bench_eval],
    "memory": [bench_memory],
}
#: One line per section for ``harness bench --help`` (the module docstring says more).
SECTION_HELP = {
    "env": "agent-steps/s of the bare env and of the training VecEnv (both backends)",
    "train": "gradient steps/s of DoubleDQN + PER against SB3's DQN, per device and size; "
    "the true-map teacher's labels/s",
    "sharing": "gradient steps/s of each algo.sharing mode",
    "eval": "episodes/s of harness eval for the random, MLP, planner and rollout policies",
    "memory": "peak memory of a training process with a full buffer",
}


def run_bench(what: str) -> dict[str, Any]:
    """Run a section (or ``all``) and return every figure in one flat dict."""
    sections = list(SECTIONS) if what == "all" else [what]
    out: dict[str, Any] = dict(machine_info())
    for name in sections:
        for fn in SECTIONS[name]:
            out.update(fn())
    return out


def format_bench(r: dict[str, Any]) -> str:
    """A readable report with the targets of the performance issue beside each figure."""
    n = "{:>12,.0f}".format
    lines = [
        f"machine: {r['machine']}; Python {r['python']}, torch {r['torch']}, "
        f"SB3 {r['stable_baselines3']}, SuperSuit {r['supersuit']}, PettingZoo {r['pettingzoo']}",
        "setting: 50x50 random maps, 4 agents, 1000 steps; MLP 3x512, batch 32, train_freq 2",
    ]
    if "env_bare_agent_steps_per_s" in r:
        bare = r["env_bare_agent_steps_per_s"]
        lines += [
            "",
            "env (agent-steps/s)",
            f"  bare parallel_env loop     {n(bare)}   target >= 100,000",
        ]
        if "env_bare_teammap_agent_steps_per_s" in r:
            tm = r["env_bare_teammap_agent_steps_per_s"]
            lines.append(
                f"  bare loop, teammap obs.    {n(tm)}   {tm / bare:5.2f} x thesis; "
                "target >= 30,000"
            )
        for label, key in (
            ("teammap + ego view 21x21", "teammap_ego"),
            ("teammap + frontier field", "teammap_frontier"),
            ("... + frontier claims", "teammap_claims"),
            ("... + pocket tie-break", "teammap_pocket"),
            ("goal action (k = 8)", "goals"),
        ):
            if f"env_bare_{key}_agent_steps_per_s" in r:
                v = r[f"env_bare_{key}_agent_steps_per_s"]
                lines.append(f"  {label:<27}{n(v)}   {v / bare:5.2f} x thesis")
        if "env_bare_goals_prior_agent_steps_per_s" in r:
            go = r["env_bare_goals_agent_steps_per_s"]
            gp = r["env_bare_goals_prior_agent_steps_per_s"]
            lines.append(f"  ... + map prior (env.prior) {n(gp)}  {gp / go:5.2f} x goal action")
            if "env_bare_goals_predicted_agent_steps_per_s" in r:
                pv = r["env_bare_goals_predicted_agent_steps_per_s"]
                lines.append(f"  {'... + predicted views':<28}{n(pv)}  {pv / gp:5.2f} x map prior")
        ss = r.get("env_vec_supersuit_by_copies", {})
        for c, v in r["env_vec_by_copies"].items():
            tail = ""
            if c in ss:
                tail = f"   SuperSuit {ss[c]:>9,.0f}   core {v / ss[c]:5.1f} x SuperSuit"
            lines.append(f"  VecEnv, {c:>2} copies           {n(v)}   {v / bare:5.2f} x bare{tail}")
        lines.append(
            f"  VecEnv / bare (4 copies)   {r['env_vec_over_bare']:>12.2f}   target >= 0.50"
        )
        for p, v in r["env_vec_8_copies_by_processes"].items():
            lines.append(f"  SuperSuit, 8 copies, num_cpus={p}  {n(v)}")
    if "train_grad_steps_per_s" in r:
        lines += [
            "",
            "train (DoubleDQN + PER vs SB3 DQN + uniform replay, alternately, 1 torch thread)",
            f"  gradient steps/s           {n(r['train_grad_steps_per_s'])}   "
            f"plain DQN {r['train_grad_steps_per_s_plain_dqn']:,.0f}",
            f"  ratio                      {r['train_grad_steps_ratio']:>12.2f}   target >= 0.85",
            f"  transitions/s (epochs 1)   {n(r['train_transitions_per_s'])}   "
            f"plain DQN {r['train_transitions_per_s_plain_dqn']:,.0f} "
            f"(ratio {r['train_transitions_ratio']:.2f})",
        ]
    if "train_grad_steps_by_device" in r:
        lines += [
            "",
            "gradient steps/s by device and network (same batch and device, alternately; "
            "CPU: 1 torch thread)",
            f"  {'device':<8}{'network':<13}{'DDQN+PER':>10}{'SB3 DQN':>10}{'ratio':>8}"
            f"{'no graph':>10}",
        ]
        for device, by_net in r["train_grad_steps_by_device"].items():
            for net, row in by_net.items():
                # DDQN+PER without the CUDA graph (harness.sb3.graphs): CUDA rows only.
                no_graph = f"{row[NO_GRAPH]:>10,.0f}" if NO_GRAPH in row else f"{'-':>10}"
                lines.append(
                    f"  {device:<8}{net:<13}{row['doubledqn_per']:>10,.0f}{row['dqn']:>10,.0f}"
                    f"{row['ratio']:>8.2f}{no_graph}"
                )
        goal = r["train_grad_steps_by_device"].get("cpu", {}).get("goal_slots")
        if goal is not None:
            lines.append(
                f"  goals_2agents on the cpu: at most "
                f"{GOALS_TRANSITIONS_PER_STEP * goal['doubledqn_per']:,.0f} transitions/s "
                f"(a gradient step per {GOALS_TRANSITIONS_PER_STEP} transitions, the env free)"
            )
    if "train_teacher_labels_per_s" in r:
        lines += [
            "",
            f"true-map teacher's labels/s (4 agents, {r['train_teacher_copies']} copies): "
            f"{r['train_teacher_labels_per_s']:,.0f} on {r['train_teacher_threads']} threads, "
            f"{r['train_teacher_over_1_thread']:.2f} x 1 thread "
            f"({r['train_teacher_1_thread_labels_per_s']:,.0f})",
        ]
    if "train_grad_steps_per_s_by_setting" in r:
        lines += ["", "gradient steps/s by network, batch and torch threads (DoubleDQN + PER)"]
        lines.append(f"  {'network':<8}{'batch':>6}{'1 thread':>11}{'2 threads':>11}")
        s = r["train_grad_steps_per_s_by_setting"]
        for key in [k for k in s if k.endswith("threads1")]:
            net, batch, _ = key.split("/")
            two = s[f"{net}/{batch}/threads2"]
            lines.append(f"  {net:<8}{batch[5:]:>6}{s[key]:>11,.0f}{two:>11,.0f}")
    if "train_grad_steps_per_s_by_sharing" in r:
        by = r["train_grad_steps_per_s_by_sharing"]
        lines += ["", "gradient steps/s by algo.sharing (4 agents, batch 32 per set, 1 thread)"]
        for mode, rate in by.items():
            lines.append(f"  {mode:<10}{rate:>11,.0f}   {rate / by['shared']:5.2f} x shared")
    if "eval_episodes_per_s" in r:
        lines += [
            "",
            "eval (50x50, 4 agents, 1000 steps)",
            f"  MLP policy episodes/s      {r['eval_episodes_per_s']:>12.2f}   "
            f"100 episodes in {r['eval_100_episodes_s']:.0f} s (target < 60 s)",
            f"  frontier episodes/s        {r['eval_frontier_episodes_per_s']:>12.2f}",
        ]
        if "eval_random_episodes_per_s" in r:
            lines.append(f"  random episodes/s          {r['eval_random_episodes_per_s']:>12.2f}")
        for name in ("teammap", "goals"):
            key = f"eval_{name}_frontier_step_episodes_per_s"
            if key in r:
                lines.append(f"  frontier_step, {name + ':':<11} {r[key]:>12.2f}")
        for key, rate in r.items():
            name = key.removeprefix("eval_").removesuffix("_episodes_per_s")
            if key.endswith("_episodes_per_s") and name.startswith("frontier_"):
                ratio = r.get(f"eval_{name}_over_frontier")
                tail = f"   {ratio:5.2f} x frontier" if ratio is not None else ""
                lines.append(f"  {name + ' episodes/s':<29}{rate:>10.2f}{tail}")
    if "eval_rollout_episodes_per_s" in r:
        lines.append(
            f"  rollout episodes/s         {r['eval_rollout_episodes_per_s']:>12.3f}   "
            f"{r['eval_rollout_threads']} threads; {r['eval_rollout_over_1_thread']:.2f} x "
            f"1 thread ({r['eval_rollout_1_thread_episodes_per_s']:.3f})"
        )
    if "train_peak_memory_mib" in r:
        lines += [
            "",
            f"memory: peak RSS of training with a full 100,000-transition buffer: "
            f"{r['train_peak_memory_mib']:,.0f} MiB",
        ]
    return "\n".join(lines)
