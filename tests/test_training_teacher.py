"""The teacher in training (harness/training/teacher.py): its labels of a core's decisions, how
the core's VecEnv hands them to the replay buffer, the config's rules for ``algo.teacher``, and
a tiny run that distils the labels (DAgger)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from envs.coverage.core import CoverageCore
from envs.coverage.rollouts import shortest_walk
from envs.coverage.teacher import RolloutTeacher
from harness import DoubleDQN
from harness.cli import main
from harness.config.loading import load_config
from harness.config.schema import TeacherConfig
from harness.factory import make_core_spec
from harness.sb3.decisions import EXPERT_KEY
from harness.training.adapters import CoreVecEnv
from harness.training.teacher import TeacherLabeller
from tests.conftest import refused_run, tiny_goal_run

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "goals_2agents_teacher.yaml"
#: A small goal-action env with held targets: 16x16 random maps, 2 agents, k = 4.
SMALL = {
    "env.map": "random",
    "env.height": "16",
    "env.width": "16",
    "env.max_steps": "60",
    "env.test_maps": "[]",
    "env.observation": "{teammap: {crop: 7, global_size: 6}}",
    "env.frontier.action.goal.k": "4",
}


def small_core(copies: int = 3) -> CoverageCore:
    config = load_config(CONFIG, [f"{k}={v}" for k, v in SMALL.items()])
    core = CoverageCore(make_core_spec(config.env), copies)
    for b in range(copies):
        core.reset(b, seed=10 + b)
    core.observe()
    return core


@pytest.mark.parametrize("reach", [None, 0.3])
def test_the_labeller_gives_the_teacher_s_slot_to_every_deciding_agent(reach) -> None:
    # reach: the rollouts scored by the steps to that coverage (the 4-agent measure).
    core = small_core()
    rng = np.random.default_rng(0)
    teacher = RolloutTeacher(reach=reach)
    for _ in range(12):  # a few steps in, with some targets held
        labels = TeacherLabeller(TeacherConfig(reach=reach), seed=1)(core)
        assert labels.shape == (3, 2)
        for b in range(3):
            frontier = core.frontiers[b]
            cells = frontier.candidates.cells
            walks = {
                a: shortest_walk(frontier.planner, a, int(c))
                for a, c in enumerate(frontier.held.tolist())
                if c >= 0
            }
            wanted, _ = teacher.label(
                frontier.planner, frontier.candidates, core.max_steps - int(core.steps[b]), walks
            )
            assert labels[b].tolist() == wanted.tolist()
            for a in range(2):
                deciding = (cells[a] >= 0).sum() > 1 and frontier.held[a] < 0
                assert (labels[b, a] >= 0) == deciding
        # the policy's own choices: any allowed slot
        mask = core.observe()["action_mask"]
        actions = np.array([[rng.choice(np.flatnonzero(m)) for m in copy] for copy in mask])
        core.step(actions)
        core.observe()


def test_the_labeller_labels_a_share_of_the_copies_from_its_own_generator() -> None:
    core = small_core(copies=8)
    rngs = [core.rng(b).bit_generator.state for b in range(8)]
    half = TeacherLabeller(TeacherConfig(share=0.5), seed=3)
    labels = half(core)
    drawn = np.random.default_rng(3).random(8) < 0.5
    full = TeacherLabeller(TeacherConfig(), seed=3)(core)
    assert (labels[~drawn] == -1).all()
    assert labels[drawn].tolist() == full[drawn].tolist()
    # the episodes' generators are not touched
    assert [core.rng(b).bit_generator.state for b in range(8)] == rngs


def test_copies_labelled_side_by_side_get_the_labels_of_one_thread() -> None:
    core = small_core(copies=6)
    rng = np.random.default_rng(1)
    alone = TeacherLabeller(TeacherConfig(share=0.7, reach=0.3), seed=5)
    threaded = TeacherLabeller(TeacherConfig(share=0.7, reach=0.3), seed=5, threads=3)
    deciding = 0
    for _ in range(10):
        labels = threaded(core)
        np.testing.assert_array_equal(labels, alone(core))
        deciding += int((labels >= 0).sum())
        mask = core.observe()["action_mask"]
        actions = np.array([[rng.choice(np.flatnonzero(m)) for m in copy] for copy in mask])
        core.step(actions)
        core.observe()
    assert deciding > 10  # the threads had labels to give


def test_the_core_vecenv_puts_the_labels_in_the_step_s_infos() -> None:
    core = small_core(copies=2)
    calls = []

    def labeller(c: CoverageCore) -> np.ndarray:
        calls.append(c.steps.copy())  # before the step
        return np.array([[2, -1], [-1, 0]])

    venv = CoreVecEnv(core, labeller=labeller)
    masks = core.observe()["action_mask"].reshape(4, -1)
    venv.step_async(np.array([int(np.flatnonzero(m)[0]) for m in masks]))
    _, _, _, infos = venv.step_wait()
    assert calls[0].tolist() == [0, 0]
    assert [info.get(EXPERT_KEY) for info in infos] == [2, None, None, 0]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["algo.per_decision=false"], "algo.teacher labels decisions"),
        (["algo.imitation={margin: 0.8}"], "two experts for one margin loss"),
        (["vec.backend=supersuit"], "needs vec.backend: core"),
        (["algo.teacher.share=0"], "algo.teacher.share"),
    ],
)
def test_a_teacher_that_cannot_work_is_refused_in_one_line(
    overrides: list[str], message: str, capsys, tmp_path: Path
) -> None:
    assert message in refused_run(CONFIG, overrides, tmp_path, capsys)


@pytest.mark.parametrize("prioritized", [False, True])
def test_a_run_with_a_teacher_stores_its_labels_and_evaluates(
    prioritized: bool, tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    args = tiny_goal_run(
        CONFIG, runs, algo__prioritized=str(prioritized).lower(), checkpoint__every="300"
    )
    assert main(args) == 0
    (run,) = runs.iterdir()
    checkpoint = sorted((run / "checkpoints").glob("step-*"))[-1]
    model = DoubleDQN.load(checkpoint / "model.zip", device="cpu")
    with (checkpoint / "replay_buffer.pkl").open("rb") as f:
        model.load_replay_buffer(f)
    buffer = model.replay_buffer
    n = buffer.size()
    labels = buffer.expert_actions[:n, 0]
    assert buffer.labels and (labels >= 0).any()  # every copy-step labelled (share 1)
    assert ((labels >= -1) & (labels < 4)).all()
    logged = (run / "tb" / "progress.csv").read_text().splitlines()[0].split(",")
    assert {"teacher/labels", "teacher/deviations", "train/expert_agreement"} <= set(logged)
    assert main(["eval", str(run), "--episodes", "2"]) == 0
