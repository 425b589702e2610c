"""A PettingZoo env of one's own that breaks its contract (docs/your-own-env.md) is named in one
line: exit 2 before any run folder exists where the config's check can know it (the
constructor, the spaces, a probe reset and step), else exit 1 with "the env failed at step N"
(training names its newest checkpoint and resumes from it). Frames, episodes that never end and
non-finite numbers in JSON too.

The env here (:class:`Line`) is a 25-line ``ParallelEnv``; each fault is one ``fault`` keyword,
instances other than the ones the probe of issue 74 tried."""

from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from gymnasium import spaces
from pettingzoo import AECEnv, ParallelEnv

from harness.cli import main
from tests.conftest import one_error_line

#: The environment variable that arms the faults of :class:`Line` that fire mid-training (a
#: resume runs with it unset: the env is "fixed").
ARMED = "HARNESS_TEST_ENV_FAULT"


class Line(ParallelEnv):
    """Two walkers on a line of 5 cells, rewarded minus their distance, truncated after
    ``max_steps``; ``fault`` breaks one thing (see the tests), ``at`` the episode step where a
    step fault strikes, ``after`` the env's steps before its episodes may fail."""

    metadata = {"name": "line_v0", "render_modes": ["rgb_array"]}  # noqa: RUF012

    def __init__(self, fault="", at=1, after=0, max_steps=15, render_mode=None):
        self.fault, self.at, self.after, self.max_steps = fault, at, after, max_steps
        self.render_mode, self.total = render_mode, 0
        self.possible_agents = ["w0", "w1"]
        self.rng = np.random.default_rng()
        size = 3 if fault == "long_observation" else 2
        self._obs = spaces.Box(0.0, 1.0, (2, 0) if fault == "empty_box" else (2,), np.float32)
        self._obs_given = np.zeros(size, np.float32)
        shifted = fault == "shifted_actions"
        self._act = spaces.Discrete(4, start=-1) if shifted else spaces.Discrete(3)

    def observation_space(self, agent):
        if self.fault == "space_raises":
            raise LookupError(f"no space for {agent}")
        return self._obs

    def action_space(self, agent):
        return self._act

    def reset(self, seed=None, options=None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.agents, self.t = list(self.possible_agents), 0
        self.cells = self.rng.integers(0, 5, 2)
        observations = {a: self._observe(c) for a, c in zip(self.agents, self.cells, strict=True)}
        return observations if self.fault == "obs_only_reset" else (observations, {})

    def step(self, actions):
        self.t += 1
        self.total += 1
        strikes = self.t == self.at and self.total > self.after and os.environ.get(ARMED) == "1"
        if strikes and self.fault == "raises":
            raise RuntimeError(f"the walkers fell off the line\n(step {self.t})")
        if strikes and self.fault == "exits":
            sys.exit(4)
        moves = np.array([actions.get(a, 1) - 1 for a in self.possible_agents])
        self.cells = np.clip(self.cells + moves, 0, 4)
        spread = float(abs(self.cells[0] - self.cells[1]))
        reward = float("nan") if strikes and self.fault == "nan_reward" else -spread
        coverage = float("nan") if self.fault == "nan_coverage" else 0.5
        ends = self.t >= self.max_steps and self.fault != "endless"
        observations = {a: self._observe(c) for a, c in zip(self.agents, self.cells, strict=True)}
        rewards = {a: reward for a in self.agents}
        terms = {a: False for a in self.agents}
        truncs = {a: ends for a in self.agents}
        infos = {a: {"coverage": coverage} for a in self.agents}
        if ends:
            self.agents = []
        if self.fault == "old_step":
            return observations, rewards, {a: ends for a in truncs}, infos
        return observations, rewards, terms, truncs, infos

    def _observe(self, cell):
        out = self._obs_given.copy()
        out[:2] = (cell / 4, self.cells.mean() / 4)
        return out

    def render(self):
        if self.fault == "render_none":
            return None
        if self.fault == "render_raises":
            raise ValueError("no screen")
        side = 1200 if self.fault == "huge_frames" else 8
        floats = self.fault == "float_frames"
        frame = np.zeros((side, side * 5, 3), np.float64 if floats else np.uint8)
        for c in self.cells:
            frame[:, side * c : side * (c + 1)] = (1.0, 0.6, 0.0) if floats else 200
        return frame


def line(**kwargs):
    """The import path's constructor: ``tests.test_env_contract:line``."""
    return Line(**kwargs)


def exits_on_construction(**kwargs):
    raise SystemExit(5)


class Lookalike:
    """Has possible_agents, reset and step, and is no ParallelEnv."""

    def __init__(self, **kwargs):
        self.inner = Line(**kwargs)
        self.possible_agents = self.inner.possible_agents
        self.reset, self.step = self.inner.reset, self.inner.step
        self.observation_space = self.inner.observation_space
        self.action_space = self.inner.action_space


def lookalike(**kwargs):
    return Lookalike(**kwargs)


class Repeats(AECEnv):
    """An AEC env whose first agent acts again and again: its agents do not act once per
    cycle, which aec_to_parallel cannot convert."""

    metadata = {"name": "repeats_v0", "is_parallelizable": True}  # noqa: RUF012

    def __init__(self, **kwargs):
        self.possible_agents, self.render_mode = ["a", "b"], None
        self._obs, self._act = spaces.Box(0.0, 1.0, (1,), np.float32), spaces.Discrete(2)

    def observation_space(self, agent):
        return self._obs

    def action_space(self, agent):
        return self._act

    def reset(self, seed=None, options=None):
        self.agents = list(self.possible_agents)
        self.agent_selection = "a"
        self.rewards = self._cumulative_rewards = {a: 0.0 for a in self.agents}
        self.terminations = {a: False for a in self.agents}
        self.truncations = {a: False for a in self.agents}
        self.infos = {a: {} for a in self.agents}

    def observe(self, agent):
        return np.zeros(1, np.float32)

    def step(self, action):
        self.agent_selection = "a"  # never b's turn


def repeats(**kwargs):
    return Repeats(**kwargs)


# ---------------------------------------------------------------------- helpers
def config(tmp_path: Path, make: str = "line", step_limit: int | None = None, **kwargs) -> Path:
    """A tiny config of ``tests.test_env_contract:<make>`` with ``kwargs``: 2 copies of 2
    walkers, 400 transitions, a checkpoint every 100, no evaluation."""
    source = {"make": f"tests.test_env_contract:{make}", "kwargs": kwargs}
    if step_limit is not None:
        source["step_limit"] = step_limit
    raw = {
        "name": "line",
        "seed": 0,
        "env": {"pettingzoo": source},
        "vec": {"copies": 2},
        "algo": {"net_arch": [16], "buffer_size": 1000, "learning_starts": 40},
        "phases": [
            {
                "name": "only",
                "timesteps": 400,
                "learning_rate": 1.0e-3,
                "exploration": {"start": 1.0, "end": 0.1, "steps": 200},
            }
        ],
        "eval": {"every": 0, "episodes": 2},
        "checkpoint": {"every": 100},
    }
    path = tmp_path / f"{make}-{kwargs.get('fault', '')}.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def run(path: Path, runs: Path, *extra: str) -> int:
    return main(["run", str(path), "--no-progress", "--runs-dir", str(runs), *extra])


def failure_line(err: str) -> str:
    """The error line of a run that started: the last one, after the run's own two lines."""
    *before, last = err.strip().splitlines()
    assert [line.split(":")[0] for line in before] == ["run folder", "replay buffer"], err
    return one_error_line(last)


# ---------------------------------------------------------------------- known at the check: exit 2
@pytest.mark.parametrize(
    ("make", "fault", "message"),
    [
        ("exits_on_construction", "", "the constructor failed (SystemExit(5): it called sys.exit)"),
        ("lookalike", "", "returned Lookalike, not a PettingZoo env"),
        ("repeats", "", "the env failed at step 1: AssertionError: expected agent b got agent a"),
        ("line", "shifted_actions", "Discrete(4, start=-1) is not Discrete(n) with n >= 1"),
        ("line", "empty_box", "has shape (2, 0): the network needs at least one number"),
        ("line", "space_raises", "observation_space() or action_space() failed (LookupError: "),
        ("line", "obs_only_reset", "the env failed at reset: reset() returned a dict, not the"),
        ("line", "old_step", "step() returned a tuple of 4, not five dicts"),
        ("line", "long_observation", "the observation of 'w0' has shape (3,), not the observation"),
    ],
)
def test_a_broken_contract_is_refused_before_the_run_folder(tmp_path, capsys, make, fault, message):
    kwargs = {"fault": fault} if fault else {}
    runs = tmp_path / "runs"
    assert run(config(tmp_path, make, **kwargs), runs) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith("harness: error: ") and message in line, line
    assert not runs.exists()


def test_a_constructor_that_raises_keyboard_interrupt_is_ctrl_c(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(Line, "__init__", _interrupt)
    assert run(config(tmp_path), tmp_path / "runs") == 130
    assert capsys.readouterr().err.strip() == "harness: interrupted"


def _interrupt(self, **kwargs):
    raise KeyboardInterrupt


# ---------------------------------------------------------------------- mid-training: exit 1
def test_an_env_that_fails_mid_training_names_the_step_and_the_checkpoint_and_resumes(
    tmp_path, capsys, monkeypatch
):
    monkeypatch.setenv(ARMED, "1")
    runs = tmp_path / "runs"
    # Each copy's 5th episode (after 60 of its steps) raises at its step 11: transition 284.
    assert run(config(tmp_path, fault="raises", at=11, after=60), runs) == 1
    line = failure_line(capsys.readouterr().err)
    (folder,) = runs.iterdir()
    assert "the env failed at step 11: RuntimeError: the walkers fell off the line (step" in line
    assert "(after 280 transitions); training stopped, the newest checkpoint is " in line
    assert f"{folder / 'checkpoints'}" in line and f"harness run --resume {folder}" in line
    monkeypatch.delenv(ARMED)  # the env fixed
    assert main(["run", "--resume", str(folder), "--no-progress"]) == 0
    assert (folder / "model.zip").is_file()


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ("nan_reward", "the env failed at step 3: the reward of 'w0' is nan, not a finite number"),
        ("exits", "the env failed at step 3: SystemExit(4): it called sys.exit"),
    ],
)
def test_a_fault_before_the_first_checkpoint_says_so(tmp_path, capsys, monkeypatch, fault, message):
    monkeypatch.setenv(ARMED, "1")
    runs = tmp_path / "runs"
    assert run(config(tmp_path, fault=fault, at=3), runs) == 1
    line = failure_line(capsys.readouterr().err)
    assert message in line and "no checkpoint yet" in line, line
    (folder,) = runs.iterdir()
    monkeypatch.delenv(ARMED)  # a resume with no checkpoint starts the run again
    assert main(["run", "--resume", str(folder), "--no-progress"]) == 0


def test_an_env_that_fails_in_a_worker_process_is_one_line(tmp_path, capfd, monkeypatch):
    monkeypatch.setenv(ARMED, "1")
    path = config(tmp_path, fault="raises", at=5)
    args = ["--set", "vec.num_cpus=2", "--set", "vec.backend=supersuit"]
    assert run(path, tmp_path / "runs", *args) == 1
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err
    assert "the env failed at step 5: RuntimeError: the walkers fell off" in err.splitlines()[-1]


# ---------------------------------------------------------------------- episodes that never end
def test_an_episode_that_never_ends_stops_at_the_step_limit(tmp_path, capsys, monkeypatch):
    from harness.tasks import pettingzoo

    monkeypatch.setattr(pettingzoo, "LONG_EPISODE_EVERY_S", 0.0)  # a line at every step
    path = config(tmp_path, step_limit=30, fault="endless")
    assert main(["eval", "--policy", "random", "--config", str(path), "--episodes", "2"]) == 1
    *progress, last = capsys.readouterr().err.strip().splitlines()
    assert last == (
        "harness: error: the env failed at step 30: its episode has not ended in 30 steps "
        "(env.pettingzoo.step_limit): end it with a truncation (a time limit), or raise the limit"
    )
    assert progress and "of at most 30 (env.pettingzoo.step_limit)" in progress[-1]
    runs = tmp_path / "runs"
    assert run(path, runs) == 1  # training: the same line, no checkpoint yet
    assert "the env failed at step 30: its episode has not ended" in capsys.readouterr().err


# ---------------------------------------------------------------------- frames
def _render(tmp_path: Path, path: Path, *extra: str) -> int:
    out = ["--out", str(tmp_path / "r.png")]
    return main(["render", "--policy", "random", "--config", str(path), *out, *extra])


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ("render_none", "the env failed rendering at step 0: render() returned None"),
        ("render_raises", "the env failed rendering at step 0: ValueError: no screen"),
    ],
)
def test_render_that_gives_no_frame_is_one_line(tmp_path, capsys, fault, message):
    assert _render(tmp_path, config(tmp_path, fault=fault)) == 1
    assert message in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "r.png").exists()


def test_float_frames_in_0_1_are_scaled(tmp_path):
    from PIL import Image

    assert _render(tmp_path, config(tmp_path, fault="float_frames")) == 0
    picture = np.asarray(Image.open(tmp_path / "r.png"))
    assert picture.max() == 255 and set(np.unique(picture)) <= {0, 153, 255}


def test_a_gif_of_huge_frames_is_refused_from_its_first_frames(tmp_path, capsys, monkeypatch):
    from harness.results import plots

    monkeypatch.setattr(plots, "MAX_GIF_BYTES", 200_000_000)  # 5 frames of 1200x6000
    gif = tmp_path / "r.gif"
    assert _render(tmp_path, config(tmp_path, fault="huge_frames"), "--gif", str(gif)) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "the env's frames are 1200x6000 pixels (43,200,000 bytes each" in line
    assert "4 of them fit in 200,000,000: keep fewer with a larger --every" in line
    assert not gif.exists()


# ---------------------------------------------------------------------- JSON
def test_a_nan_info_is_null_in_json(tmp_path, capsys):
    runs = tmp_path / "runs"
    path = config(tmp_path, fault="nan_coverage")
    assert run(path, runs, "--set", "phases.only.timesteps=200") == 0
    (folder,) = runs.iterdir()
    with (folder / "episodes.csv").open() as f:  # JSON in a CSV column
        assert {row["infos"] for row in csv.DictReader(f)} == {'{"coverage":[null,null]}'}
    capsys.readouterr()
    assert main(["eval", str(folder), "--episodes", "2", "--json"]) == 0
    printed = capsys.readouterr().out
    assert "NaN" not in printed  # (json.loads would take it: the text is checked)
    summary = json.loads(printed)
    assert summary["coverage_mean"] is None and summary["coverage_median"] is None
    assert summary["infos"]["coverage"] is None
    saved = (folder / "eval-2ep.json").read_text()
    assert "NaN" not in saved and json.loads(saved)["coverage_mean"] is None
