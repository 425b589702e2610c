"""The tasks the harness trains and evaluates (:class:`harness.tasks.base.Task`), and the one
place that tells which an ``env`` section, a summary or a log is: the coverage env
(:class:`~harness.tasks.coverage.CoverageTask`) and any PettingZoo env
(:class:`~harness.tasks.pettingzoo.PettingZooTask`). Everything else asks the task.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from harness.tasks.base import EpisodePlayer, EpisodesStopped, Task, TooManyFrames
from harness.tasks.coverage import CoverageTask
from harness.tasks.pettingzoo import PettingZooTask

__all__ = [
    "TASKS",
    "EpisodePlayer",
    "EpisodesStopped",
    "Task",
    "TooManyFrames",
    "headline",
    "objective_value",
    "selection_score",
    "summarize",
    "task_of",
    "task_of_columns",
    "task_of_summary",
]

#: Every task, the first one (the coverage env's) the default of what names none.
TASKS: tuple[type[Task], ...] = (CoverageTask, PettingZooTask)


def task_of(env: Any) -> Task:
    """The task of an ``env`` section."""
    for cls in TASKS:
        if cls.takes(env):
            return cls(env)
    raise TypeError(f"no task takes an env section of type {type(env).__name__}")


def task_of_summary(summary: dict[str, Any]) -> type[Task]:
    """The task of an evaluation's summary (an ``eval.json``, a tune row)."""
    for cls in TASKS:
        if cls.owns_summary(summary):
            return cls
    raise ValueError(f"no task made a summary of source {summary.get('source')!r}")


def task_of_columns(header: Sequence[str]) -> type[Task] | None:
    """The task whose ``episodes.csv`` or ``evaluations.csv`` has the columns ``header``
    (``None``: none has)."""
    for cls in TASKS:
        if tuple(header) in (cls.episode_columns, cls.evaluation_columns):
            return cls
    return None


def summarize(results: list[Any]) -> dict[str, Any]:
    """An evaluation's numbers over its episodes' results (their task's summary)."""
    return type(results[0]).task.summarize(results)


def headline(summary: dict[str, Any], stat: str = "median") -> float:
    """An evaluation's headline number: the ``stat`` (``median``, ``mean``, ``q1``, ``q3``,
    ``iqr``) of its task's headline metric (the team coverage; a PettingZoo env's team return).
    Sweeps, ``harness tune``, ``compare`` and seed groups read their number here."""
    return task_of_summary(summary).headline(summary, stat)


def objective_value(summary: dict[str, Any]) -> float:
    """A sweep's trial value: its task's :meth:`~harness.tasks.base.Task.objective_value` (the
    headline's median; a pettingzoo env's ``env.pettingzoo.select`` group's, if it names one)."""
    return task_of_summary(summary).objective_value(summary)


def selection_score(summary: dict[str, Any]) -> float:
    """The one number a policy is chosen by (its task's rule): ``best_model.zip`` (the best
    in-training evaluation) and ``harness tune`` (the test temperature) both choose by it (a
    pettingzoo env's: by the ``select`` group the summary names, if any). Higher is better."""
    return task_of_summary(summary).selection_score(summary)
