"""PettingZoo's action-mask convention (issue 72): an env whose observations are a ``Dict`` of
``observation`` (a ``Box``) and an ``int8`` ``action_mask`` trains with ``MaskedMlpPolicy``, and
the mask is honoured in every choice: the ε-random and greedy actions of training, the greedy
and Boltzmann actions of evaluation. The env of this file raises on a masked action, so a run
or an evaluation that plays one fails."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.test import parallel_api_test

from harness.cli import main
from harness.config.loading import config_from_dict
from harness.evaluation.episodes import model_policy, run_episodes
from tests.conftest import one_error_line, root_first_env

MAKE = "tests.test_action_masks_pettingzoo:parallel_env"

#: Actions 2 and 3 are never allowed.
ALLOWED = np.array([1, 1, 0, 0], np.int8)


class MaskedEnv(ParallelEnv):
    """Two agents, four actions of which 2 and 3 are masked, ten steps: action 0 earns 1,
    action 1 nothing. A masked action breaks the contract: the env raises."""

    metadata = {"name": "masked_v0", "render_modes": []}  # noqa: RUF012

    def __init__(
        self, mask_size: int = 4, extra_key: bool = False, allowed=ALLOWED, render_mode=None
    ):
        self.possible_agents = ["a_0", "a_1"]
        self.allowed = np.asarray(allowed, np.int8)
        self.render_mode = render_mode
        parts = {
            "observation": spaces.Box(0.0, 1.0, (3,), np.float32),
            "action_mask": spaces.MultiBinary(mask_size),
        }
        if extra_key:
            parts["other"] = spaces.Box(0.0, 1.0, (1,), np.float32)
        self._observation = spaces.Dict(parts)
        self._action = spaces.Discrete(4)
        self.rng = np.random.default_rng()

    def observation_space(self, agent):
        return self._observation

    def action_space(self, agent):
        return self._action

    def reset(self, seed=None, options=None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.agents, self.t = list(self.possible_agents), 0
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions):
        for agent, action in actions.items():
            if not self.allowed[int(action)]:
                raise RuntimeError(f"masked action {int(action)} of {agent}")
        self.t += 1
        rewards = {a: float(int(actions[a]) == 0) for a in self.agents}
        done = self.t >= 10
        terms = {a: False for a in self.agents}
        truncs = {a: done for a in self.agents}
        infos = {a: {} for a in self.agents}
        obs = self._observe()
        if done:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def _observe(self):
        return {
            a: {
                "observation": self.rng.random(3, dtype=np.float32),
                "action_mask": self.allowed.copy(),
            }
            for a in self.possible_agents
        }


def parallel_env(**kwargs):
    return MaskedEnv(**kwargs)


def config(**algo) -> dict:
    """A tiny config of the masked env: 600 transitions, learning from the 100th."""
    return {
        "name": "masked",
        "seed": 0,
        "env": {"pettingzoo": {"make": MAKE, "kwargs": {}}},
        "vec": {"copies": 2},
        "algo": {
            "policy": "MaskedMlpPolicy",
            "net_arch": [16],
            "buffer_size": 2000,
            "learning_starts": 100,
            "target_update_interval": 200,
            **algo,
        },
        "phases": [
            {
                "name": "initial",
                "timesteps": 600,
                "learning_rate": 1.0e-3,
                "exploration": {"start": 1.0, "end": 0.1, "steps": 400},
            }
        ],
        "eval": {"every": 400, "episodes": 2},
        "checkpoint": {"every": 400},
    }


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    # SuperSuit's copies may run in processes that import this module.
    monkeypatch.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])


def test_the_env_passes_pettingzoos_api_test():
    parallel_api_test(MaskedEnv(), num_cycles=50)


def test_an_action_mask_env_is_read_with_its_mask():
    env = config_from_dict(config()).env
    space = env.spaces.observation_space
    assert isinstance(space, spaces.Dict) and set(space.spaces) == {"observation", "action_mask"}


def test_the_configs_first_step_plays_an_allowed_action():
    # Loading a config plays a first step: action 0 is masked here, action 1 is played.
    raw = config()
    raw["env"]["pettingzoo"]["kwargs"] = {"allowed": [0, 1, 0, 0]}
    assert config_from_dict(raw).env.n_agents == 2


@pytest.mark.parametrize(
    ("kwargs", "algo", "refusal"),
    [
        ({"mask_size": 3}, {}, "'action_mask' space MultiBinary(3) is not a MultiBinary or Box"),
        ({"extra_key": True}, {}, "keys ['action_mask', 'observation', 'other']: the harness"),
        ({}, {"policy": "MlpPolicy"}, "carry an action mask (PettingZoo's Dict of observation"),
        ({}, {"sharing": "shared_id"}, "algo.sharing: shared_id: the observations carry an"),
    ],
)
def test_what_cannot_work_is_refused_in_one_line(tmp_path, capsys, kwargs, algo, refusal):
    import yaml

    raw = config(**algo)
    raw["env"]["pettingzoo"]["kwargs"] = kwargs
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["run", str(path), "--runs-dir", str(tmp_path / "runs")]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert refusal in line, line
    assert not (tmp_path / "runs").exists()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A run of the masked env: it exits 0 only if no masked action was played (the env raises
    on one, which fails the run), ε-random ones included."""
    import yaml

    root = tmp_path_factory.mktemp("masked")
    path = root / "masked.yaml"
    path.write_text(yaml.safe_dump(config()))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])
        assert main(["run", str(path), "--no-progress", "--into", str(root / "run")]) == 0
    return root / "run"


def test_training_plays_no_masked_action(trained):
    assert (trained / "episodes.csv").read_text().count("\n") > 10  # episodes were played


@pytest.mark.parametrize("temperature", [None, "1.0"])
def test_eval_plays_no_masked_action(trained, temperature):
    args = ["eval", str(trained), "--episodes", "4"]
    if temperature is not None:
        args += ["--set", f"eval.temperature={temperature}"]
    assert main(args) == 0


def test_the_random_policy_plays_allowed_actions(trained, tmp_path):
    assert main(["eval", str(trained), "--episodes", "4", "--against", "random"]) == 0
    config = str(trained / "config.yaml")
    assert main(["eval", "--policy", "random", "--config", config, "--episodes", "4"]) == 0


@pytest.mark.parametrize("temperature", [0.0, 1.0])
def test_masked_actions_stay_out_even_when_their_q_values_are_best(temperature):
    """A network that values the masked actions far above the others: greedy and Boltzmann
    still choose allowed ones only (the observation part is what the network reads)."""
    from harness.sb3.dqn import DoubleDQN
    from harness.training.adapters import make_vec_env

    cfg = config_from_dict(config())
    venv = make_vec_env(cfg.env, 1, seed=0, backend="supersuit")
    try:
        model = DoubleDQN("MaskedMlpPolicy", venv, policy_kwargs={"net_arch": [8]})
    finally:
        venv.close()
    assert model.masked
    assert model.q_net.features_extractor._features_dim == 3  # the observation alone
    last = model.q_net.q_net[-1]
    with th.no_grad():
        last.weight.zero_()
        last.bias.copy_(th.tensor([0.0, 0.0, 100.0, 100.0]))
    results = run_episodes(model_policy(model, temperature), cfg.env, 4, seed=0)
    # Only allowed actions were played (the env raises on another): action 0 earns 1 a step.
    assert len(results) == 4 and all(r.length == 10 for r in results)
