"""Statistics over training seeds, with rliable (Agarwal et al., 2021, "Deep Reinforcement
Learning at the Edge of the Statistical Precipice").

A group's score per seed is the mean test coverage of that seed's run (its ``eval.json``). Over
the seeds of a group: the mean and the interquartile mean (IQM), each with a 95 %
stratified-bootstrap confidence interval (``rliable.library.get_interval_estimates``); between two
groups: the probability of improvement ``P(X > Y)`` with its interval. With one seed there is no
interval, and the functions say so (``None``) rather than print a fake one; with fewer than
:data:`CONCLUSIVE_SEEDS` the interval is printed and drawn with a caution (not conclusive). The
pictures are rliable's own (``rliable.plot_utils``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.results.rundir import write_figure

#: Bootstrap resamples (rliable's default is 50,000; 2,000 keeps ``compare`` under a second and
#: moves the 95 % bounds by well under a point of coverage here).
REPS = 2000
#: Seeds from which an interval over seeds is drawn like a conclusive one. A bootstrap over 2
#: seeds resamples 3 distinct sets (a a, a b, b b): its "interval" is the two values' range.
CONCLUSIVE_SEEDS = 3


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
def _bootstrap_rng(seed: int) -> Iterator[None]:
    """Run rliable's bootstrap reproducibly from ``seed``, leaving ``np.random`` as it was.

    rliable 1.2's ``StratifiedBootstrap.update_indices`` draws its resamples from the global
    ``np.random``, not from the ``random_state`` it is given (which it only hands to ``arch``, and
    ``arch`` warns that the keyword will change), so the same scores gave different intervals
    from run to run. The global state is seeded for the call and restored after it.
    """
    state = np.random.get_state()  # noqa: NPY002
    np.random.seed(seed)  # noqa: NPY002 (the generator rliable reads)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=FutureWarning, module="arch")
            yield
    finally:
        np.random.set_state(state)  # noqa: NPY002


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
    # One resampling stream per group, each from `seed`: a group's interval does not depend on
    # which other groups it is compared with (one shared stream would make it so).
    for name, scores in several.items():
        with _bootstrap_rng(seed):
            point, interval = rly.get_interval_estimates(
                {name: scores}, aggregate, reps=reps, random_state=np.random.RandomState(seed)
            )
        points[name], intervals[name] = point[name], interval[name]
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
    with _bootstrap_rng(seed):
        points, intervals = rly.get_interval_estimates(
            {"x,y": pair},
            metrics.probability_of_improvement,
            reps=reps,
            random_state=np.random.RandomState(seed),
        )
    ci = intervals["x,y"]
    return float(points["x,y"]), (float(ci[0, 0]), float(ci[1, 0]))


def paired_difference(
    a: Sequence[float], b: Sequence[float], reps: int = 10_000, seed: int = 0
) -> tuple[float, float, float]:
    """Mean of ``a - b`` over paired episodes (the same maps and starts) and its 95 %
    percentile-bootstrap interval over the episodes: how a policy and a baseline, or two
    policies, are compared episode by episode (``research/experiments/goal_validation.py``,
    ``research/experiments/goal_oracle.py``)."""
    diff = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    rng = np.random.default_rng(seed)
    means = diff[rng.integers(0, diff.size, (reps, diff.size))].mean(axis=1)
    return float(diff.mean()), float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def percent(x: float) -> str:
    return f"{100 * x:.1f} %"


def plain(x: float) -> str:
    """A score that is not a fraction (a PettingZoo env's team return): four digits."""
    return f"{x:.4g}"


def with_ci(
    value: float, ci: tuple[float, float] | None, fmt: Callable[[float], str] = percent
) -> str:
    if ci is None:
        return f"{fmt(value)} (1 seed: no interval)"
    return f"{fmt(value)} [{fmt(ci[0])}, {fmt(ci[1])}]"


def markdown_table(
    stats: Mapping[str, SeedStats],
    wall_hits: Mapping[str, float] | None,
    metric: str = "test coverage",
    fmt: Callable[[float], str] = percent,
) -> str:
    """One row per group: seeds, mean and IQM of test coverage with 95 % CIs, wall hits (or of
    another ``metric``, formatted by ``fmt``; ``wall_hits`` ``None``: no such column). An
    interval over fewer than :data:`CONCLUSIVE_SEEDS` seeds is marked ``(not conclusive)``,
    and a line under the table names those groups."""
    hits = wall_hits is not None
    lines = [
        f"| group | seeds | mean {metric} [95 % CI] | IQM [95 % CI] |"
        + (" wall hits / episode |" if hits else ""),
        "|---|---|---|---|" + ("---|" if hits else ""),
    ]
    few = []
    for name, s in stats.items():
        caution = " (not conclusive)" if 1 < s.seeds < CONCLUSIVE_SEEDS else ""
        if caution:
            few.append(f"{name} ({s.seeds} seeds)")
        lines.append(
            f"| {name} | {s.seeds} | {with_ci(s.mean, s.mean_ci, fmt)}{caution} | "
            f"{with_ci(s.iqm, s.iqm_ci, fmt)}{caution} |"
            + (f" {wall_hits[name]:.2f} |" if wall_hits is not None else "")
        )
    if few:
        lines += [
            "",
            f"Not conclusive: {', '.join(few)}; an interval needs at least {CONCLUSIVE_SEEDS} "
            "seeds (train more with harness run CONFIG --seeds N)",
        ]
    return "\n".join(lines)


def _label(name: str, seeds: int) -> str:
    """A group's label in the pictures: its seeds, and a caution below
    :data:`CONCLUSIVE_SEEDS`."""
    if seeds == 1:
        return f"{name} (1 seed: no interval)"
    if seeds < CONCLUSIVE_SEEDS:
        return f"{name} ({seeds} seeds: not conclusive)"
    return f"{name} ({seeds} seeds)"


def group_colours(names: Sequence[str]) -> dict[str, Any]:
    """One colour per group (matplotlib's ``tab10`` in the groups' order), the same in every
    figure of one comparison."""
    from matplotlib import colormaps

    return {name: colormaps["tab10"](i % 10) for i, name in enumerate(names)}


def plot_intervals(
    stats: Mapping[str, SeedStats],
    out: Path,
    colours: Mapping[str, Any] | None = None,
    xlabel: str = "test coverage (% of free cells), 95 % stratified-bootstrap CIs",
    scale: float = 100.0,
) -> Path:
    """rliable's interval plot (``plot_utils.plot_interval_estimates``) of mean and IQM test
    coverage per group; a group of one seed is drawn as its value alone (a dot), an interval
    over fewer than :data:`CONCLUSIVE_SEEDS` seeds as a grey hatched bar, each labelled so.
    ``colours``: per group (default :func:`group_colours` of these groups); ``xlabel`` and
    ``scale`` (drawn ``scale * value``) for another score (a PettingZoo env's team return)."""
    import matplotlib.pyplot as plt
    from rliable import plot_utils

    points, intervals, colours = {}, {}, {}
    palette = colours or group_colours(list(stats))
    seeds = {}
    for name, s in stats.items():
        label = _label(name, s.seeds)
        seeds[label] = s.seeds
        colours[label] = palette[name]
        points[label] = scale * np.array([s.mean, s.iqm])
        # Zero width for one seed: the bar vanishes and only the point is drawn.
        mean_ci, iqm_ci = s.mean_ci or (s.mean, s.mean), s.iqm_ci or (s.iqm, s.iqm)
        intervals[label] = scale * np.array([[mean_ci[0], iqm_ci[0]], [mean_ci[1], iqm_ci[1]]])
    row_height = 0.6
    fig, axes = plot_utils.plot_interval_estimates(
        points,
        intervals,
        metric_names=["Mean", "IQM"],
        colors=colours,
        xlabel=xlabel,
        subfigure_width=4.0,
        row_height=row_height,
        # rliable places the label in figure fractions: half an inch below, whatever the rows.
        xlabel_y_coordinate=-0.55 / (row_height * len(points)),
    )
    _caution_marks(np.atleast_1d(axes), points, seeds, colours)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        write_figure(fig, out, dpi=120, bbox_inches="tight")  # whole or not at all
    finally:
        plt.close(fig)  # rliable draws on pyplot figures; free them in long sessions
    return out


def _caution_marks(
    axes: Sequence[Any],
    points: Mapping[str, np.ndarray],
    seeds: Mapping[str, int],
    colours: Mapping[str, Any],
) -> None:
    """On rliable's interval axes (one per metric, a bar per group labelled as the group): a
    one-seed group's value as a dot in its colour (its bar has no width: the chart would look
    empty), and the bar of an interval over fewer than :data:`CONCLUSIVE_SEEDS` seeds grey and
    hatched in the group's colour (not to be read like a conclusive one)."""
    for metric, ax in enumerate(axes):
        for container in ax.containers:
            label = container.get_label()
            if seeds.get(label, CONCLUSIVE_SEEDS) >= CONCLUSIVE_SEEDS:
                continue
            if seeds[label] == 1:
                row = list(points).index(label)  # rliable's rows: the groups in order
                ax.plot(points[label][metric], row, "o", color=colours[label], ms=7, zorder=3)
                continue
            for bar in container:
                bar.set_facecolor("0.85")
                bar.set_edgecolor(colours[label])
                bar.set_hatch("///")
                bar.set_alpha(1.0)
        # A dot at the end of the range is drawn whole: bars hold the range at their edges
        # (sticky edges) unless told not to.
        ax.use_sticky_edges = False
        ax.margins(x=0.05)
        ax.autoscale_view()


def plot_improvement(
    pairs: Mapping[tuple[str, str], tuple[float, tuple[float, float]]], out: Path
) -> Path:
    """rliable's ``plot_utils.plot_probability_of_improvement`` of ``P(X > Y)`` per pair of
    groups (pairs with an interval only)."""
    from matplotlib.figure import Figure
    from rliable import plot_utils

    fig = Figure(figsize=(5.0, 0.8 + 0.6 * len(pairs)), dpi=120)
    ax = fig.add_subplot()
    plot_utils.plot_probability_of_improvement(
        {f"{x};{y}": p for (x, y), (p, _) in pairs.items()},
        {f"{x};{y}": np.array(ci) for (x, y), (_, ci) in pairs.items()},
        pair_separator=";",
        ax=ax,
        left_ylabel="group X",
        right_ylabel="group Y",
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    write_figure(fig, out, bbox_inches="tight")  # whole or not at all
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

    with _bootstrap_rng(seed):
        points, intervals = rly.get_interval_estimates(
            {"g": matrix[:, None, :]},
            iqm_per_point,
            reps=reps,
            random_state=np.random.RandomState(seed),
        )
    return steps, points["g"], intervals["g"]


def plot_curves_with_ci(
    groups: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]],
    out: Path,
    reps: int = REPS,
    colours: Mapping[str, Any] | None = None,
    ylabel: str = "validation coverage, IQM (%)",
    scale: float = 100.0,
    boundaries: Sequence[float] = (),
) -> Path:
    """Validation coverage during training, IQM over seeds with 95 % bands, one line per group
    (rliable's ``plot_utils.plot_sample_efficiency_curve``; one seed: its line, no band; fewer
    than :data:`CONCLUSIVE_SEEDS`: a hatched band, labelled not conclusive). ``colours``: per
    group (default :func:`group_colours` of these groups); ``ylabel`` and ``scale`` for another
    score (a PettingZoo env's median team return); ``boundaries``: the transitions where a
    training phase ends, drawn as dotted lines (the drop at ε = 0 is a phase's start, not a
    collapse)."""
    from matplotlib.figure import Figure
    from rliable import plot_utils

    from harness.results.plots import draw_phase_boundaries

    fig = Figure(figsize=(7.0, 4.0), dpi=120)
    ax = fig.add_subplot()
    colors = colours or group_colours(list(groups))
    for name, curves in groups.items():
        steps, iqm, band = curve_with_ci(curves, reps)
        if not len(steps):
            continue
        label = _label(name, len(curves))
        before = len(ax.collections)
        # The groups evaluated at their own timesteps: one call per group on the same axes.
        plot_utils.plot_sample_efficiency_curve(
            steps,
            {label: scale * iqm},
            {label: scale * (band if band is not None else np.stack([iqm, iqm]))},
            colors={label: colors[name]},
            ax=ax,
            xlabel="transitions",
            ylabel=ylabel,
            labelsize="medium",
            ticklabelsize="medium",
        )
        if 1 < len(curves) < CONCLUSIVE_SEEDS:
            for band_area in ax.collections[before:]:  # the band rliable just filled
                band_area.set_hatch("///")
                band_area.set_edgecolor(colors[name])
    draw_phase_boundaries(ax, boundaries)
    ax.legend(frameon=False)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    write_figure(fig, out)  # whole or not at all
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
