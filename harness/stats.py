"""Statistics over training seeds, with rliable (Agarwal et al., 2021, "Deep Reinforcement
Learning at the Edge of the Statistical Precipice").

A group's score per seed is the mean test coverage of that seed's run (its ``eval.json``). Over
the seeds of a group: the mean and the interquartile mean (IQM), each with a 95 %
stratified-bootstrap confidence interval (``rliable.library.get_interval_estimates``); between two
groups: the probability of improvement ``P(X > Y)`` with its interval. With one seed there is no
interval, and the functions say so (``None``) rather than print a fake one.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: Bootstrap resamples (rliable's default is 50,000; 2,000 keeps ``compare`` under a second and
#: moves the 95 % bounds by well under a point of coverage here).
REPS = 2000


@dataclass
class SeedStats:
    """A group's test score over its seeds."""

    seeds: int
    mean: float
    iqm: float
    mean_ci: tuple[float, float] | None
    """95 % bootstrap interval of the mean; ``None`` with one seed (undefined)."""
    iqm_ci: tuple[float, float] | None


@contextmanager
def _quiet_arch() -> Iterator[None]:
    """rliable hands ``random_state`` to ``arch``, which warns that the keyword will change."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=FutureWarning, module="arch")
        yield


def _scores(values: Sequence[float]) -> np.ndarray:
    """rliable's layout: ``(runs, tasks)``, one task (the test episodes)."""
    return np.asarray(values, dtype=np.float64).reshape(-1, 1)


def seed_statistics(
    groups: Mapping[str, Sequence[float]], reps: int = REPS, seed: int = 0
) -> dict[str, SeedStats]:
    """Mean and IQM with 95 % stratified-bootstrap intervals, per group of per-seed scores."""
    from rliable import library as rly
    from rliable import metrics

    def aggregate(scores: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_mean(scores), metrics.aggregate_iqm(scores)])

    out: dict[str, SeedStats] = {}
    several = {name: _scores(v) for name, v in groups.items() if len(v) > 1}
    points, intervals = {}, {}
    if several:
        with _quiet_arch():
            points, intervals = rly.get_interval_estimates(
                several, aggregate, reps=reps, random_state=np.random.RandomState(seed)
            )
    for name, values in groups.items():
        if name in several:
            (mean, iqm), ci = points[name], intervals[name]
            out[name] = SeedStats(
                len(values),
                float(mean),
                float(iqm),
                (float(ci[0, 0]), float(ci[1, 0])),
                (float(ci[0, 1]), float(ci[1, 1])),
            )
        else:
            value = float(values[0])
            out[name] = SeedStats(1, value, value, None, None)
    return out


def probability_of_improvement(
    x: Sequence[float], y: Sequence[float], reps: int = REPS, seed: int = 0
) -> tuple[float, tuple[float, float] | None]:
    """``P(X > Y)`` (ties count half) between two groups' per-seed scores, with its 95 %
    bootstrap interval (``None`` when a group has one seed)."""
    from rliable import library as rly
    from rliable import metrics

    pair = (_scores(x), _scores(y))
    if len(x) < 2 or len(y) < 2:
        return float(metrics.probability_of_improvement(*pair)), None
    with _quiet_arch():
        points, intervals = rly.get_interval_estimates(
            {"x,y": pair},
            metrics.probability_of_improvement,
            reps=reps,
            random_state=np.random.RandomState(seed),
        )
    ci = intervals["x,y"]
    return float(points["x,y"]), (float(ci[0, 0]), float(ci[1, 0]))


def percent(x: float) -> str:
    return f"{100 * x:.1f} %"


def _with_ci(value: float, ci: tuple[float, float] | None) -> str:
    if ci is None:
        return f"{percent(value)} (1 seed: no interval)"
    return f"{percent(value)} [{percent(ci[0])}, {percent(ci[1])}]"


def markdown_table(stats: Mapping[str, SeedStats], wall_hits: Mapping[str, float]) -> str:
    """One row per group: seeds, mean and IQM of test coverage with 95 % CIs, wall hits."""
    lines = [
        "| group | seeds | mean test coverage [95 % CI] | IQM [95 % CI] | wall hits / episode |",
        "|---|---|---|---|---|",
    ]
    for name, s in stats.items():
        lines.append(
            f"| {name} | {s.seeds} | {_with_ci(s.mean, s.mean_ci)} | {_with_ci(s.iqm, s.iqm_ci)}"
            f" | {wall_hits[name]:.2f} |"
        )
    return "\n".join(lines)


def plot_intervals(stats: Mapping[str, SeedStats], out: Path) -> Path:
    """rliable's interval plot of mean and IQM per group (groups with one seed drawn as points)."""
    from matplotlib.figure import Figure

    names = list(stats)
    fig = Figure(figsize=(8.0, 0.6 + 0.5 * len(names)), dpi=120)
    axes = fig.subplots(1, 2, sharey=True)
    for ax, title, value, ci in (
        (axes[0], "mean", "mean", "mean_ci"),
        (axes[1], "IQM", "iqm", "iqm_ci"),
    ):
        for row, name in enumerate(names):
            s = stats[name]
            centre = 100 * getattr(s, value)
            interval = getattr(s, ci)
            if interval is not None:
                ax.barh(row, 100 * (interval[1] - interval[0]), left=100 * interval[0],
                        height=0.6, alpha=0.5, color="#0072B2")  # fmt: skip
            ax.plot([centre, centre], [row - 0.3, row + 0.3], color="black", lw=2)
        ax.set_title(f"{title} test coverage (95 % CI)")
        ax.set_xlabel("% of free cells")
        ax.set_yticks(range(len(names)), names)
        ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    return out


def curve_with_ci(
    curves: Sequence[tuple[np.ndarray, np.ndarray]], reps: int = REPS, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """IQM over seeds of the in-training evaluations at the timesteps every seed evaluated, with
    95 % bootstrap bands (``None`` with one seed).

    Args:
        curves: Per seed, ``(timesteps, coverage)`` from its ``evaluations.csv``.

    Returns:
        ``(timesteps, iqm, band)`` with ``band`` of shape ``(2, len(timesteps))``.
    """
    from rliable import library as rly
    from rliable import metrics

    common = sorted(set.intersection(*(set(t.tolist()) for t, _ in curves)))
    matrix = np.array([[dict(zip(t.tolist(), y))[x] for x in common] for t, y in curves])
    steps = np.asarray(common)
    if len(curves) < 2 or not common:
        return steps, matrix.mean(axis=0) if common else np.array([]), None

    def iqm_per_point(scores: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(scores[:, :, k]) for k in range(scores.shape[-1])])

    with _quiet_arch():
        points, intervals = rly.get_interval_estimates(
            {"g": matrix[:, None, :]},
            iqm_per_point,
            reps=reps,
            random_state=np.random.RandomState(seed),
        )
    return steps, points["g"], intervals["g"]


def plot_curves_with_ci(
    groups: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]], out: Path
) -> Path:
    """Validation coverage during training, IQM over seeds with 95 % bands, one line per group."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 4.0), dpi=120)
    ax = fig.add_subplot()
    for name, curves in groups.items():
        steps, iqm, band = curve_with_ci(curves)
        if not len(steps):
            continue
        (line,) = ax.plot(steps, 100 * iqm, label=f"{name} ({len(curves)} seeds)")
        if band is not None:
            ax.fill_between(steps, 100 * band[0], 100 * band[1], alpha=0.25, color=line.get_color())
    ax.set_xlabel("transitions")
    ax.set_ylabel("validation coverage, IQM over seeds (%)")
    ax.grid(alpha=0.3)
    ax.legend(frameon=False)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    return out


def describe(stats: SeedStats) -> dict[str, Any]:
    """JSON-ready form of :class:`SeedStats`."""
    return {
        "seeds": stats.seeds,
        "mean": stats.mean,
        "mean_ci95": stats.mean_ci,
        "iqm": stats.iqm,
        "iqm_ci95": stats.iqm_ci,
    }
