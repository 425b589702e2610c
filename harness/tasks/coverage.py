"""The coverage env's task (:class:`CoverageTask`): the thesis's metrics (coverage, useful and
total coverage per agent, coverage at 33/66/100 % of the episode, Table 4.2; the steps to 90 and
99 %; wall hits), their summary and the selection rule, and the batched core's copies as the
episode loop plays them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from envs.coverage import CoverageEnv
from envs.coverage.core import CoverageCore
from harness.config.maps import describe_map
from harness.config.schema import EnvConfig
from harness.factory import check_env, make_core_spec
from harness.tasks.base import EpisodePlayer, Record, Task, mean_interval, sampling_note

#: Fractions of the episode at which coverage is recorded (Table 4.2).
CHECKPOINT_FRACTIONS = (0.33, 0.66, 1.0)
#: Team coverages whose first step is recorded: policies that both reach full coverage are then
#: compared on speed (the frontier planner's strength).
COVERAGE_TARGETS = (0.90, 0.99)
#: Info keys of the env's that SB3's ``VecMonitor`` keeps at an episode's end.
EPISODE_INFO_KEYS = ("coverage", "new_cells", "wall_hits")


@dataclass
class EpisodeResult:
    """Metrics of one finished episode."""

    task: ClassVar[type[Task]]
    """The task whose episode it is (:func:`harness.tasks.summarize` asks it)."""

    coverage: float
    """Team coverage at the end (visited free cells / free cells)."""
    coverage_at: list[float]
    """Team coverage at 33 %, 66 % and 100 % of the episode."""
    wall_hits: list[int]
    """Per agent."""
    new_cells: list[int]
    """Per agent: cells credited to it."""
    steps: int
    free_cells: int
    paths: list[np.ndarray] = field(default_factory=list)
    """Per agent ``(steps + 1, 2)`` positions, when recorded."""
    steps_to: dict[str, int | None] = field(default_factory=dict)
    """Steps the team took to reach each of :data:`COVERAGE_TARGETS` (``None``: not reached)."""
    walls: np.ndarray | None = None
    """``bool (H, W)`` map of the episode (True = wall), when paths are recorded."""
    frames: list[np.ndarray] = field(default_factory=list)
    """``rgb_array`` frames (``uint8 (H*k, W*k, 3)``) at step 0, every ``frames_every`` steps
    and the last step, when asked for."""


def _target_key(fraction: float) -> str:
    return f"steps_to_{round(fraction * 100)}"


def median_steps_to(results: list[EpisodeResult], key: str) -> float | None:
    """Median over episodes of the steps to reach a coverage (an episode that never reached it
    counts as infinitely slow); ``None`` when the median episode did not reach it."""
    values = [r.steps_to.get(key) for r in results]
    finite = np.array([np.inf if v is None else v for v in values], dtype=float)
    median = float(np.median(finite))
    return None if not np.isfinite(median) else median


#: The steps :func:`selection_score` counts for a median episode that never reaches 99 %.
SLOWEST = 1e5


def physical_bound(n_agents: int, steps: int, free_cells: int) -> float:
    """The most of a map a team can have covered: ``min(1, N * (T + 1) / F)`` for ``N`` agents,
    ``T`` steps and ``F`` free cells (each agent's start cell, then one new cell per move)."""
    return min(1.0, n_agents * (steps + 1) / free_cells)


def summarize(results: list[EpisodeResult]) -> dict[str, Any]:
    """The thesis's numbers over a list of episodes (all fractions in [0, 1]), and the physical
    limit beside them: ``bound`` (the mean over episodes of :func:`physical_bound`) and
    ``efficiency``, ``coverage_mean / bound``."""
    cov = np.array([r.coverage for r in results])
    q1, q3 = np.percentile(cov, [25, 75])
    n_agents = len(results[0].new_cells)
    per_agent = []
    for k in range(n_agents):
        credited = np.array([r.new_cells[k] for r in results], dtype=float)
        per_agent.append(
            {
                "agent": f"agent_{k}",
                "useful_coverage": float(np.mean(credited / [r.steps for r in results])),
                "total_coverage": float(np.mean(credited / [r.free_cells for r in results])),
            }
        )
    at = np.array([r.coverage_at for r in results])
    bound = float(np.mean([physical_bound(n_agents, r.steps, r.free_cells) for r in results]))
    low, high = mean_interval(cov)
    return {
        "episodes": len(results),
        "coverage_median": float(np.median(cov)),
        "coverage_mean": float(cov.mean()),
        "coverage_mean_ci": [low, high],
        "bound": bound,
        "efficiency": float(cov.mean()) / bound,
        "coverage_iqr": float(q3 - q1),
        "coverage_q1": float(q1),
        "coverage_q3": float(q3),
        "coverage_min": float(cov.min()),
        "coverage_max": float(cov.max()),
        "coverage_at_median": {
            f"{round(f * 100)}%": float(v)
            for f, v in zip(CHECKPOINT_FRACTIONS, np.median(at, axis=0))
        },
        **{_target_key(f): median_steps_to(results, _target_key(f)) for f in COVERAGE_TARGETS},
        "wall_hits_mean": float(np.mean([sum(r.wall_hits) for r in results])),
        "wall_hits_episodes": int(sum(1 for r in results if sum(r.wall_hits) > 0)),
        "per_agent": per_agent,
    }


class CoveragePlayer(EpisodePlayer):
    """The batched core's copies (one core per batch size: the last batch may be smaller),
    each copy handed to the policy as an env view (baselines read the map from it); all copies
    step in one call and end together, at ``max_steps``."""

    def __init__(self, env: EnvConfig, render_mode: str | None, record_paths: bool) -> None:
        self.spec = make_core_spec(env)
        self.render_mode, self.record_paths = render_mode, record_paths
        self.n_agents, self.max_steps = env.n_agents, env.max_steps
        self.marks = [max(1, round(f * self.max_steps)) for f in CHECKPOINT_FRACTIONS]
        self.targets = [(f, _target_key(f)) for f in COVERAGE_TARGETS]
        self.batches: dict[int, tuple[CoverageCore, list[CoverageEnv]]] = {}

    def reset(self, seeds: Sequence[int]) -> Any:
        size = len(seeds)
        if size not in self.batches:
            core = CoverageCore(self.spec, size)
            copies = [CoverageEnv.copy_of(core, b, self.render_mode) for b in range(size)]
            self.batches[size] = (core, copies)
        self.core, self.batch = self.batches[size]
        for e, seed in zip(self.batch, seeds, strict=True):
            e.reset(seed=seed)
        self.t = 0
        self.paths = [[e.positions] for e in self.batch] if self.record_paths else None
        self.at: list[list[float]] = [[] for _ in self.batch]
        self.reached: list[dict[str, int | None]] = [
            {key: None for _, key in self.targets} for _ in self.batch
        ]
        return CoverageCore.flat(self.core.observe())

    @property
    def playing(self) -> list[int]:
        return list(range(len(self.batch))) if self.t < self.max_steps else []

    def views(self) -> Sequence[Any]:
        return self.batch

    def step(self, actions: np.ndarray) -> Any:
        core, t = self.core, self.t + 1
        self.t = t
        core.step(np.asarray(actions).reshape(len(self.batch), self.n_agents))
        obs = core.observe()
        coverage = (core.n_visited / core.n_free).tolist()
        for i, e in enumerate(self.batch):
            if self.paths is not None:
                self.paths[i].append(e.positions)
            if t in self.marks:  # a short episode can hit one step for two marks
                self.at[i].extend([coverage[i]] * self.marks.count(t))
            for f, key in self.targets:
                if self.reached[i][key] is None and coverage[i] >= f:
                    self.reached[i][key] = t
        return CoverageCore.flat(obs)

    @property
    def stepped(self) -> list[tuple[int, int, bool]]:
        return [(i, self.t, self.t == self.max_steps) for i in range(len(self.batch))]

    def render(self, copy: int) -> np.ndarray:
        return self.batch[copy].render()

    def results(self, frames: list[list[np.ndarray]]) -> list[Any]:
        core, paths = self.core, self.paths
        return [
            EpisodeResult(
                coverage=e.coverage,
                coverage_at=self.at[i],
                wall_hits=core.wall_hits[i].tolist(),
                new_cells=core.new_cells[i].tolist(),
                steps=self.max_steps,
                free_cells=e.free_cells,
                paths=list(np.stack(paths[i], axis=1)) if paths is not None else [],
                steps_to=self.reached[i],
                walls=np.array(e.walls) if self.record_paths else None,
                frames=frames[i],
            )
            for i, e in enumerate(self.batch)
        ]


class CoverageTask(Task):
    """The coverage env (``env:`` with the keys of ``coverage_v0.parallel_env``)."""

    name = "coverage"
    metric = "coverage"
    prefix = "coverage"
    percent = True
    penalty = "wall_hits_mean"
    paths = True
    compare_keys = ("coverage_median", "coverage_iqr", "coverage_mean", "wall_hits_mean")
    tune_keys = (
        "coverage_median",
        "coverage_q1",
        "coverage_q3",
        "coverage_mean",
        "wall_hits_mean",
        "wall_hits_episodes",
    )
    group_keys = ("seed", "coverage_mean", "coverage_median", "wall_hits_mean")
    episode_columns = (
        "episode",
        "phase",
        "timesteps",
        "copy",
        "coverage",
        "reward_mean",
        "wall_hits",
        "new_cells",
        "length",
    )
    evaluation_columns = (
        "timesteps",
        "episodes",
        "temperature",
        "coverage_median",
        "coverage_q1",
        "coverage_q3",
        "coverage_mean",
        "wall_hits_mean",
    )
    episode_metric = "coverage"
    monitor_keys = EPISODE_INFO_KEYS
    batched_core = True
    env: EnvConfig

    @classmethod
    def takes(cls, env: Any) -> bool:
        # (or parallel_env's keyword arguments: benchmarks and tests build envs without a config)
        return isinstance(env, (EnvConfig, Mapping))

    @classmethod
    def owns_summary(cls, summary: dict[str, Any]) -> bool:
        return "source" not in summary  # (its summaries, older than the tasks, name none)

    def start(self, config: Any) -> tuple[Any, Any]:
        env = check_env(self.env)
        agent = env.possible_agents[0]
        return env.observation_space(agent), env.action_space(agent)

    def player(self, copies: int, render_mode: str | None, record_paths: bool) -> EpisodePlayer:
        return CoveragePlayer(self.env, render_mode, record_paths)

    @classmethod
    def summarize(cls, results: list[Any]) -> dict[str, Any]:
        return summarize(results)

    @classmethod
    def selection_score(cls, summary: dict[str, Any]) -> float:
        """The project's one rule for picking a policy: fewest wall hits first, then the highest
        median coverage (the thesis's tests show zero wall hits), then the fewest median steps
        to 99 % (teams that cover the whole map, 4 agents on 50x50, tie on coverage; speed is
        then the measure). Higher is better.

        One more wall hit over the evaluation episodes costs ``1000 / episodes`` and a median
        never exceeds 1; a median step costs ``1e-12`` (a median that never reaches 99 %
        counts as :data:`SLOWEST` steps, at most ``1e-7``), less than the smallest difference
        of two median coverages on maps of up to 500,000 free cells. So the order is
        lexicographic for fewer than 1000 episodes. A single float, because a checkpoint's
        training state keeps it.
        """
        steps = summary.get("steps_to_99")
        speed = -1e-12 * (SLOWEST if steps is None else float(steps))
        return float(summary["coverage_median"]) - 1000.0 * float(summary["wall_hits_mean"]) + speed

    @classmethod
    def per_episode(cls, results: list[Any]) -> dict[str, list[Any]]:
        return {
            "coverage": [r.coverage for r in results],
            "wall_hits": [sum(r.wall_hits) for r in results],
            # None where the episode never reached 99 %.
            "steps_to_99_each": [r.steps_to.get("steps_to_99") for r in results],
        }

    @classmethod
    def format_summary(cls, summary: dict[str, Any]) -> str:
        pct = "{:6.1%}".format
        env = summary["env"]
        where = describe_map(env["map"], env["height"], env["width"])
        at = summary["coverage_at_median"]
        how = sampling_note(summary.get("temperature"))
        lines = [
            f"policy    {summary['policy']}{f' ({how})' if how else ''}",
            f"episodes  {summary['episodes']} (seed {summary['seed']}), {where}; "
            f"{env['n_agents']} agent(s), {env['max_steps']} steps",
            f"coverage  median {pct(summary['coverage_median'])}   mean "
            f"{pct(summary['coverage_mean'])}   IQR {pct(summary['coverage_iqr'])} "
            f"({pct(summary['coverage_q1'])} .. {pct(summary['coverage_q3'])})",
            f"bound     {pct(summary['bound'])} (every move a new cell)   efficiency "
            f"{summary['efficiency']:.3f} (mean / bound)",
            "steps to 90 % / 99 % (median): "
            + " / ".join(
                "not reached" if summary[k] is None else f"{summary[k]:g}"
                for k in ("steps_to_90", "steps_to_99")
            ),
            "at 33 % / 66 % / 100 % of the episode (median): "
            + " / ".join(pct(v).strip() for v in at.values()),
            f"wall hits {summary['wall_hits_mean']:.2f} per episode; "
            f"{summary['wall_hits_episodes']} episode(s) with any",
            "",
            f"{'agent':<10}{'useful coverage':>17}{'total coverage':>17}",
        ]
        for a in summary["per_agent"]:
            lines.append(
                f"{a['agent']:<10}{pct(a['useful_coverage']):>17}{pct(a['total_coverage']):>17}"
            )
        return "\n".join(lines)

    @classmethod
    def format_tune(cls, result: dict[str, Any]) -> list[str]:
        pct = "{:>9.1%}".format
        lines = [
            f"{'T':>6}{'median':>9}{'q1':>9}{'q3':>9}{'mean':>9}{'wall hits':>11}{'episodes':>10}",
        ]
        for r in result["rows"]:
            mark = "  <- chosen" if r["temperature"] == result["chosen"] else ""
            lines.append(
                f"{r['temperature']:>6g}{pct(r['coverage_median'])}{pct(r['coverage_q1'])}"
                f"{pct(r['coverage_q3'])}{pct(r['coverage_mean'])}{r['wall_hits_mean']:>11.2f}"
                f"{r['wall_hits_episodes']:>10}{mark}"
            )
        return lines

    @classmethod
    def compare_header(cls) -> str:
        return f"{'median':>8}{'IQR':>8}{'wall hits':>11}"

    @classmethod
    def compare_row(cls, summary: dict[str, Any]) -> str:
        return (
            f"{summary['coverage_median']:>8.1%}{summary['coverage_iqr']:>8.1%}"
            f"{summary['wall_hits_mean']:>11.2f}"
        )

    def training_episode(self, infos: list[dict[str, Any]], record: Record) -> dict[str, Any]:
        eps = [info["episode"] for info in infos]
        row = {
            "coverage": float(eps[0]["coverage"]),
            "reward_mean": float(np.mean([e["r"] for e in eps])),
            "wall_hits": int(sum(e["wall_hits"] for e in eps)),
            "new_cells": ";".join(str(int(e["new_cells"])) for e in eps),
            "length": int(eps[0]["l"]),
        }
        record("rollout/coverage", row["coverage"])
        record("rollout/wall_hits", row["wall_hits"])
        record("rollout/team_reward_mean", row["reward_mean"])
        return row

    @classmethod
    def record_evaluation(cls, summary: dict[str, Any], record: Record) -> None:
        for key in ("coverage_median", "coverage_mean", "wall_hits_mean"):
            record(f"eval/{key}", summary[key])


EpisodeResult.task = CoverageTask
