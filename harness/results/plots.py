"""Figures of the harness: paths (thesis Figs. 4.2–4.15), test episodes (Fig. 4.11), learning
curves (``harness compare``) and animated GIFs of an episode (``harness render --gif``).

Everything draws on :class:`matplotlib.figure.Figure` objects, never through ``pyplot``, so no
window opens, no global figure state is kept, and the Agg renderer writes the PNGs whatever
backend the user's matplotlib is set to. Agent colours are the env's Okabe-Ito palette
(:data:`envs.coverage.render.AGENT_COLOURS`), which readers with colour-vision deficiencies can
tell apart; map colours are the env's own, so figures and ``rgb_array`` frames match.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator, PercentFormatter

from envs.coverage import render
from harness.evaluation.episodes import CHECKPOINT_FRACTIONS, EpisodeResult, run_episodes
from harness.results.rundir import atomic_write, write_figure

if TYPE_CHECKING:  # only for annotations: keeps this module importable without a cycle
    from harness.config.schema import EnvConfig
    from harness.evaluation.episodes import BatchPolicy

DPI = 150
#: Okabe-Ito colours as matplotlib hex strings, agent 0 first.
AGENT_HEX = tuple(to_hex(c / 255) for c in render.AGENT_COLOURS)
_WALL = render.WALL_COLOUR / 255
_FREE = np.array([1.0, 1.0, 1.0])
_SEEN = np.array([0.84, 0.84, 0.84])  # visited cells in the team panel (neutral under the paths)
_LINE_COLOUR = "#0072B2"  # Okabe-Ito blue
_HITS_COLOUR = "#D55E00"  # Okabe-Ito vermillion
_MEDIAN_COLOUR = "#000000"


# ---------------------------------------------------------------------- paths (Figs. 4.2-4.15)
def plot_paths(
    walls: np.ndarray,
    paths: Sequence[np.ndarray],
    out: str | Path,
    title: str = "",
    snapshots: bool = True,
) -> Path:
    """Draw the team's paths over the map, one panel per agent, and coverage snapshots.

    Top row: the map with every agent's path (start ``o``, end ``□``), then one panel per agent
    with only its own path and the cells credited to it. Bottom row (``snapshots``): the cells
    the team had covered at 33, 66 and 100 % of the episode, tinted by the agent credited with
    them, with the agents' positions at that step.

    Args:
        walls: ``bool (H, W)``, True = wall.
        paths: Per agent, ``(T + 1, 2)`` int ``(row, col)`` positions from step 0 to T, as
            ``run_episodes(..., record_paths=True)`` records them.
        out: PNG file to write (folders are created).
        title: Figure title.
        snapshots: Add the row of coverage snapshots.

    Returns:
        The path of the PNG.
    """
    walls, paths = _checked_paths(walls, paths)
    first_step, credited = first_visits(walls.shape, paths)
    layout = _PathsLayout.make(walls.shape, len(paths), snapshots, bool(title))
    fig = Figure(figsize=(layout.fig_w, layout.fig_h), dpi=DPI)
    y = layout.title_h + layout.row_top
    _draw_team_and_agents(layout.row(fig, len(paths) + 1, y), walls, paths, first_step, credited)
    y += layout.panel_h + layout.row_bottom
    _draw_paths_legend(fig, len(paths), 1 - (y + layout.legend_h / 2) / layout.fig_h)
    y += layout.legend_h
    if snapshots:
        heading = "Team coverage during the episode (cells tinted by the agent credited with them)"
        _heading(fig, heading, 1 - (y + layout.snap_head / 2) / layout.fig_h, "medium")
        y += layout.snap_head + layout.row_top
        axes = layout.row(fig, len(CHECKPOINT_FRACTIONS), y)
        _draw_snapshots(axes, walls, paths, first_step, credited)
    if title:
        _heading(fig, title, 1 - layout.title_h / 2 / layout.fig_h, "large")
    return _save(fig, out)


def _heading(fig: Figure, text: str, y: float, size: str) -> None:
    """A bold line of text centred across the figure at height ``y`` (figure fraction)."""
    fig.text(0.5, y, text, ha="center", va="center", fontsize=size, fontweight="bold")


def _checked_paths(
    walls: np.ndarray, paths: Sequence[np.ndarray]
) -> tuple[np.ndarray, list[np.ndarray]]:
    """The map as ``bool`` and the paths as ``int64 (T + 1, 2)`` arrays, all of one length."""
    walls = np.asarray(walls, dtype=bool)
    paths = [np.asarray(p, dtype=np.int64).reshape(-1, 2) for p in paths]
    if not paths:
        raise ValueError("plot_paths needs at least one agent's path")
    if any(len(p) != len(paths[0]) for p in paths):
        raise ValueError("all agents' paths must have the same length")
    return walls, paths


@dataclass(frozen=True)
class _PathsLayout:
    """Sizes of :func:`plot_paths`'s figure in inches, so every panel has the same size whatever
    the number of agents: [title] [team + agents] [legend] [snapshot header] [snapshots]."""

    panel_w: float
    panel_h: float
    fig_w: float
    fig_h: float
    title_h: float
    row_top: float = 0.55  # two-line panel titles
    row_bottom: float = 0.5  # tick labels and x label
    legend_h: float = 0.4
    snap_head: float = 0.55
    gap: float = 0.55

    @classmethod
    def make(
        cls, shape: tuple[int, int], n_agents: int, snapshots: bool, titled: bool
    ) -> _PathsLayout:
        height, width = shape
        top_n = n_agents + 1
        bottom_n = len(CHECKPOINT_FRACTIONS) if snapshots else 0
        panel_w = 2.8 if top_n <= 5 else 2.3
        panel_h = panel_w * height / width
        side, gap = 0.35, cls.gap
        title_h = 0.45 if titled else 0.1
        rows = cls.row_top + panel_h + cls.row_bottom
        snap = (cls.snap_head + rows) if snapshots else 0.0
        return cls(
            panel_w=panel_w,
            panel_h=panel_h,
            fig_w=side * 2 + max(top_n, bottom_n) * (panel_w + gap),
            fig_h=title_h + rows + cls.legend_h + snap,
            title_h=title_h,
        )

    def row(self, fig: Figure, n: int, top: float) -> list[Any]:
        """``n`` centred panels whose upper edge is ``top`` inches below the figure's top."""
        width_in = n * self.panel_w + (n - 1) * self.gap
        left = (self.fig_w - width_in) / 2
        bottom = self.fig_h - top - self.panel_h
        return [
            fig.add_axes(
                (
                    (left + k * (self.panel_w + self.gap)) / self.fig_w,
                    bottom / self.fig_h,
                    self.panel_w / self.fig_w,
                    self.panel_h / self.fig_h,
                )
            )
            for k in range(n)
        ]


def _line_sizes(walls: np.ndarray) -> tuple[float, float]:
    """Path line width and marker size for a map of this size."""
    size = max(walls.shape)
    return float(np.clip(90 / size, 0.6, 2.2)), float(np.clip(220 / size, 3.5, 9.0))


def _agent_hex(n_agents: int) -> list[str]:
    return [AGENT_HEX[i % len(AGENT_HEX)] for i in range(n_agents)]


def _draw_team_and_agents(
    axes: list[Any],
    walls: np.ndarray,
    paths: list[np.ndarray],
    first_step: np.ndarray,
    credited: np.ndarray,
) -> None:
    """The top row: the team's paths over the map, then each agent's own path and cells."""
    n_agents, steps = len(paths), len(paths[0]) - 1
    n_free = int((~walls).sum())
    colours = _agent_hex(n_agents)
    lw, marker = _line_sizes(walls)
    team_bg = _map_image(walls)
    team_bg[first_step >= 0] = _SEEN
    _show_map(axes[0], team_bg)
    # Small per-agent offsets keep overlapping stretches of path distinguishable.
    spread = 0.12 if n_agents > 1 else 0.0
    for i, path in enumerate(paths):
        offset = (i - (n_agents - 1) / 2) * spread
        _draw_path(axes[0], path, colours[i], 0.8 * lw, marker, offset)
    coverage = (first_step >= 0).sum() / n_free if n_free else 0.0
    axes[0].set_title(f"Team\n{100 * coverage:.1f} % covered", fontsize="medium")
    for i, path in enumerate(paths):
        ax = axes[i + 1]
        bg = _map_image(walls)
        mine = credited == i
        bg[mine] = 1 - render.TINT * (1 - render.agent_colour(i) / 255)
        _show_map(ax, bg, ylabel=False)
        _draw_path(ax, path, colours[i], lw, marker, 0.0)
        share = mine.sum() / n_free if n_free else 0.0
        useful = mine.sum() / steps if steps else 0.0
        ax.set_title(
            f"agent_{i}: {100 * share:.1f} % of map\n{100 * useful:.1f} % useful moves",
            fontsize="medium",
        )


def _draw_paths_legend(fig: Figure, n_agents: int, y: float) -> None:
    """One legend entry per agent, plus the start and end markers, centred at height ``y``."""
    colours = _agent_hex(n_agents)
    handles = [Line2D([], [], color=c, lw=2, label=f"agent_{i}") for i, c in enumerate(colours)]
    handles += [
        Line2D([], [], ls="", marker="o", mfc="white", mec="black", label="start"),
        Line2D([], [], ls="", marker="s", mfc="white", mec="black", label="end"),
    ]
    fig.legend(
        handles=handles,
        loc="center",
        bbox_to_anchor=(0.5, y),
        ncol=min(len(handles), 10),
        frameon=False,
    )


def _draw_snapshots(
    axes: list[Any],
    walls: np.ndarray,
    paths: list[np.ndarray],
    first_step: np.ndarray,
    credited: np.ndarray,
) -> None:
    """The bottom row: what the team had covered at 33, 66 and 100 % of the episode."""
    steps = len(paths[0]) - 1
    n_free = int((~walls).sum())
    colours = _agent_hex(len(paths))
    _, marker = _line_sizes(walls)
    tints = 1 - render.TINT * (1 - render.AGENT_COLOURS / 255)
    for k, (ax, frac) in enumerate(zip(axes, CHECKPOINT_FRACTIONS)):
        step = round(frac * steps)
        covered = (first_step >= 0) & (first_step <= step)
        img = _map_image(walls)
        img[covered] = tints[credited[covered] % len(tints)]
        _show_map(ax, img, ylabel=k == 0)
        for i, path in enumerate(paths):
            r, c = path[step]
            ax.plot(c, r, "o", ms=marker, mfc=colours[i], mec="black", mew=0.8)
        share = covered.sum() / n_free if n_free else 0.0
        ax.set_title(
            f"step {step} ({100 * frac:.0f} % of episode)\n{100 * share:.1f} % covered",
            fontsize="medium",
        )


def first_visits(
    shape: tuple[int, int], paths: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """When and by whom each cell was first visited, from the agents' paths.

    Follows the env's crediting rule: cells are taken in step order, and within one step the
    lower agent index wins.

    Args:
        shape: ``(H, W)`` of the map.
        paths: Per agent ``(T + 1, 2)`` ``(row, col)`` positions.

    Returns:
        ``first_step`` and ``credited``, both int ``(H, W)``: the step a cell was first visited
        and the agent credited with it, -1 where nobody went.
    """
    height, width = shape
    stacked = np.stack([np.asarray(p).reshape(-1, 2) for p in paths], axis=1)  # (T+1, N, 2)
    n_agents = stacked.shape[1]
    flat = (stacked[..., 0] * width + stacked[..., 1]).ravel()  # step-major, then agent index
    cells, first = np.unique(flat, return_index=True)
    first_step = np.full(height * width, -1, dtype=np.int64)
    credited = np.full(height * width, -1, dtype=np.int64)
    first_step[cells] = first // n_agents
    credited[cells] = first % n_agents
    return first_step.reshape(shape), credited.reshape(shape)


def _map_image(walls: np.ndarray) -> np.ndarray:
    img = np.empty((*walls.shape, 3))
    img[:] = _FREE
    img[walls] = _WALL
    return img


def _show_map(ax: Any, img: np.ndarray, ylabel: bool = True) -> None:
    height, width = img.shape[:2]
    ax.imshow(img, interpolation="nearest", origin="upper")
    ax.set_aspect("equal")
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.xaxis.set_major_locator(MaxNLocator(5, integer=True))
    ax.yaxis.set_major_locator(MaxNLocator(5, integer=True))
    ax.tick_params(labelsize="small", length=2)
    ax.set_xlabel("column")
    if ylabel:
        ax.set_ylabel("row")


def _draw_path(
    ax: Any, path: np.ndarray, colour: str, lw: float, marker: float, offset: float
) -> None:
    rows, cols = path[:, 0] + offset, path[:, 1] + offset
    ax.plot(cols, rows, "-", color=colour, lw=lw, alpha=0.9, solid_capstyle="round")
    ax.plot(cols[0], rows[0], "o", ms=marker, mfc=colour, mec="black", mew=0.8)
    ax.plot(cols[-1], rows[-1], "s", ms=marker, mfc=colour, mec="black", mew=0.8)


# ---------------------------------------------------------------------- test episodes (Fig. 4.11)
def plot_eval_episodes(
    results_or_coverages: Sequence[EpisodeResult] | Sequence[float] | np.ndarray,
    wall_hits: Sequence[int] | np.ndarray | None,
    out: str | Path,
    title: str = "",
) -> Path:
    """Coverage of each test episode with its median, and wall hits on a second axis.

    Args:
        results_or_coverages: ``EpisodeResult`` objects from ``run_episodes``, or the team
            coverage of each episode as fractions in [0, 1].
        wall_hits: Team wall hits per episode; ``None`` takes them from the results (or draws
            none when only coverages are given).
        out: PNG file to write.
        title: Axes title.

    Returns:
        The path of the PNG.
    """
    coverage, hits = _episode_arrays(results_or_coverages, wall_hits)
    episodes = np.arange(1, len(coverage) + 1)
    median = float(np.median(coverage))

    fig = Figure(figsize=(7.0, 3.8), dpi=DPI)
    ax = fig.add_subplot()
    handles = [] if hits is None else [_draw_wall_hits(ax, episodes, hits)]
    (line,) = ax.plot(
        episodes,
        100 * coverage,
        "-o",
        color=_LINE_COLOUR,
        ms=3.5,
        lw=1.0,
        label="coverage",
    )
    med = ax.axhline(
        100 * median, color=_MEDIAN_COLOUR, ls="--", lw=1.2, label=f"median {100 * median:.1f} %"
    )
    _style_episode_axes(ax, len(coverage), [line, med, *handles])
    ax.set_title(title or f"Coverage of {len(coverage)} test episodes")
    fig.tight_layout()
    return _save(fig, out)


def plot_eval_returns(
    team_returns: Sequence[float] | np.ndarray,
    out: str | Path,
    title: str = "",
    groups: Mapping[str, Sequence[float]] | None = None,
) -> Path:
    """The team return of each test episode with its median (a PettingZoo env of one's own,
    whose episodes have no coverage or wall hits to draw), and each group's return per episode
    where ``groups`` names some.

    Args:
        team_returns: The team return of each episode (the sum of its agents' returns).
        out: PNG file to write.
        title: Axes title.
        groups: Per group name, its return in each episode (as many as ``team_returns``).

    Returns:
        The path of the PNG.
    """
    team = np.asarray(team_returns, dtype=float)
    if not len(team):
        raise ValueError("plot_eval_returns needs at least one episode")
    episodes = np.arange(1, len(team) + 1)
    median = float(np.median(team))

    fig = Figure(figsize=(7.0, 3.8), dpi=DPI)
    ax = fig.add_subplot()
    (line,) = ax.plot(episodes, team, "-o", color=_LINE_COLOUR, ms=3.5, lw=1.0, label="team")
    handles = [line]
    # The agents' colours less the two blues, which the team's line would be mistaken for.
    colours = [c for c in AGENT_HEX if c not in (_LINE_COLOUR.lower(), "#56b4e9")]
    for k, (name, values) in enumerate((groups or {}).items()):
        colour = colours[k % len(colours)]
        (part,) = ax.plot(
            episodes, np.asarray(values, dtype=float), "-", color=colour, lw=1.0, label=name
        )
        handles.append(part)
    handles.append(
        ax.axhline(median, color=_MEDIAN_COLOUR, ls="--", lw=1.2, label=f"median {median:.4g}")
    )
    ax.set_xlabel("test episode")
    ax.set_ylabel("return")
    ax.set_xlim(0.3, len(team) + 0.7)
    ax.xaxis.set_major_locator(MaxNLocator(10, integer=True))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.16),
        ncol=min(len(handles), 5),
        frameon=False,
    )
    ax.set_title(title or f"Team return of {len(team)} test episodes")
    fig.tight_layout()
    return _save(fig, out)


def _style_episode_axes(ax: Any, n_episodes: int, handles: list[Any]) -> None:
    """Axes of coverage (in %) per test episode, the legend below them."""
    ax.set_xlabel("test episode")
    ax.set_ylabel("team coverage")
    ax.set_ylim(0, 105)
    ax.set_xlim(0.3, n_episodes + 0.7)
    ax.yaxis.set_major_formatter(PercentFormatter(100, decimals=0))
    ax.xaxis.set_major_locator(MaxNLocator(10, integer=True))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.16),
        ncol=len(handles),
        frameon=False,
    )


def _episode_arrays(
    results_or_coverages: Sequence[EpisodeResult] | Sequence[float] | np.ndarray,
    wall_hits: Sequence[int] | np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Coverage per episode and wall hits per episode (``None``: none to draw)."""
    items = list(results_or_coverages)
    if not items:
        raise ValueError("plot_eval_episodes needs at least one episode")
    if hasattr(items[0], "coverage"):
        coverage = np.array([r.coverage for r in items], dtype=float)
        if wall_hits is None:
            wall_hits = [sum(r.wall_hits) for r in items]
    else:
        coverage = np.asarray(items, dtype=float)
    hits = None if wall_hits is None else np.asarray(wall_hits, dtype=float)
    if hits is not None and len(hits) != len(coverage):
        raise ValueError(f"{len(hits)} wall-hit counts for {len(coverage)} episodes")
    return coverage, hits


def _draw_wall_hits(ax: Any, episodes: np.ndarray, hits: np.ndarray) -> Any:
    """Wall hits as bars behind the coverage line, on their own axis at the right."""
    ax_hits = ax.twinx()
    total = int(hits.sum())
    bars = ax_hits.bar(
        episodes,
        hits,
        width=0.8,
        color=_HITS_COLOUR,
        alpha=0.35,
        label=f"wall hits ({total} in {len(hits)} episodes)",
    )
    ax_hits.set_ylabel("wall hits per episode", color=_HITS_COLOUR)
    ax_hits.tick_params(axis="y", colors=_HITS_COLOUR)
    ax_hits.set_ylim(0, max(1.0, float(hits.max())) * 1.15)
    ax_hits.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_zorder(ax_hits.get_zorder() + 1)  # coverage drawn over the bars
    ax.patch.set_visible(False)
    return bars


# ---------------------------------------------------------------------- learning curves
def smooth(values: Sequence[float] | np.ndarray, window: int) -> np.ndarray:
    """Trailing rolling median: entry ``i`` is the median of the last ``window`` values up to
    ``i`` (fewer at the start). A median, not a mean, because episode coverage is skewed and
    the thesis reports medians.

    Args:
        values: A 1D series.
        window: Number of values per median (1 returns a copy).

    Returns:
        float64 array of the same length.
    """
    x = np.asarray(values, dtype=np.float64).ravel()
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    window = min(window, len(x))
    if window <= 1:
        return x.copy()
    out = np.empty_like(x)
    full = np.lib.stride_tricks.sliding_window_view(x, window)
    out[window - 1 :] = np.median(full, axis=1)
    for i in range(window - 1):
        out[i] = np.median(x[: i + 1])
    return out


def plot_learning_curves(
    curves: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]],
    out: str | Path,
    title: str = "",
    window: int = 20,
    band: str = "minmax",
    references: Mapping[str, float] | None = None,
    evaluations: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]] | None = None,
    metric: str | None = None,
    boundaries: Sequence[float] = (),
) -> Path:
    """Learning curves of several experiments, each over one or more runs (seeds).

    Each run's coverage is smoothed (:func:`smooth`), put on a common grid of timesteps, and
    per label the median across runs is drawn, with a shaded band across runs when a label has
    several. Where runs have different lengths, the band covers the steps that at least two runs
    reached.

    Args:
        curves: ``label -> [(timesteps, coverage), ...]``, one pair per run, e.g. from
            :func:`harness.results.rundir.read_episodes_csv`. Coverage as fractions.
        out: PNG file to write.
        title: Axes title.
        window: Episodes per rolling median.
        band: ``"minmax"`` (range across runs) or ``"iqr"`` (25-75 %).
        references: Optional ``label -> coverage`` horizontal lines (a baseline's or the
            thesis's median coverage).
        evaluations: Optional ``label -> [(timesteps, coverage_median), ...]`` from
            :func:`harness.results.rundir.read_evaluations_csv`: when any run has one, a second
            panel draws the test policy's evaluations during training (median across a label's runs,
            unsmoothed).
        metric: ``None``: the curves are team coverage (fractions, drawn in %); else what they
            are (``"team return"``, a PettingZoo env's), drawn as numbers.
        boundaries: Transitions where a training phase ends, drawn on both panels as dotted
            lines (:func:`draw_phase_boundaries`): the drop when ε reaches 0 in a new phase
            reads as the phase's start, not a collapse.

    Returns:
        The path of the PNG.
    """
    if band not in ("minmax", "iqr"):
        raise ValueError(f"band must be 'minmax' or 'iqr', got {band!r}")
    evaluations = {k: [r for r in v if len(r[0])] for k, v in (evaluations or {}).items()}
    evaluations = {k: v for k, v in evaluations.items() if v}
    colours = [*AGENT_HEX[4:6], *AGENT_HEX[:4]]  # blue, vermillion first: the most distinct
    fig = Figure(figsize=(12.0, 4.2) if evaluations else (7.0, 4.2), dpi=DPI)
    ax = fig.add_subplot(1, 2, 1) if evaluations else fig.add_subplot()
    drawn = 0
    scale = 100.0 if metric is None else 1.0
    for k, (label, runs) in enumerate(curves.items()):
        drawn += _draw_label_curve(ax, label, runs, colours[k % len(colours)], window, band, scale)
    if drawn == 0:
        raise ValueError("plot_learning_curves: no run has any episode")
    _draw_references(ax, references or {})
    draw_phase_boundaries(ax, boundaries)
    band_note = "" if band == "minmax" else " (band: IQR across runs)"
    _style_timesteps_axes(
        ax,
        f"{metric or 'team coverage'} (rolling median of {window} episodes)",
        (title or "Learning curves") + band_note,
        percent=metric is None,
    )
    if evaluations:
        right = fig.add_subplot(1, 2, 2)
        _plot_evaluations(right, evaluations, list(curves), colours, metric, boundaries)
    fig.tight_layout()
    return _save(fig, out)


def _draw_label_curve(
    ax: Any,
    label: str,
    runs: Sequence[tuple[np.ndarray, np.ndarray]],
    colour: str,
    window: int,
    band: str,
    scale: float = 100.0,
) -> bool:
    """One label's curve: the median of its runs' smoothed coverage, with a band across runs
    when it has several (drawn ``scale`` times: in %, or as numbers). Returns whether anything
    was drawn (a label whose runs are empty)."""
    runs = [(np.asarray(t, dtype=float), np.asarray(c, dtype=float)) for t, c in runs]
    runs = [(t, c) for t, c in runs if len(t)]
    if not runs:
        return False
    grid, stacked = _common_grid(runs, window)
    reached = np.sum(~np.isnan(stacked), axis=0)
    with _quiet_nan_warnings():
        middle = np.nanmedian(stacked, axis=0)
    n = len(runs)
    ax.plot(
        grid, scale * middle, color=colour, lw=1.6, label=f"{label} ({n} runs)" if n > 1 else label
    )
    if n > 1:
        ok = reached >= 2
        with _quiet_nan_warnings():
            if band == "iqr":
                lo, hi = np.nanpercentile(stacked[:, ok], [25, 75], axis=0)
            else:
                lo, hi = np.nanmin(stacked[:, ok], axis=0), np.nanmax(stacked[:, ok], axis=0)
        ax.fill_between(grid[ok], scale * lo, scale * hi, color=colour, alpha=0.2, lw=0)
    return True


def _draw_references(ax: Any, references: Mapping[str, float]) -> None:
    """Horizontal lines at reference coverages (a baseline's, the thesis's), dotted and dashed
    in turn."""
    for j, (label, value) in enumerate(references.items()):
        ax.axhline(
            100 * value,
            color="0.25",
            ls=(0, (1, 2)) if j % 2 == 0 else (0, (4, 2)),
            lw=1.1,
            label=f"{label} ({100 * value:.1f} %)",
        )


def draw_phase_boundaries(ax: Any, boundaries: Sequence[float]) -> None:
    """Dotted vertical lines at the transitions where a training phase ends (those inside the
    curves drawn; the axis keeps its range), labelled once "phase boundary"."""
    low, high = ax.get_xlim()
    inside = sorted({float(b) for b in boundaries if low < b < high})
    for k, x in enumerate(inside):
        ax.axvline(x, color="0.35", ls=":", lw=1.2, label="phase boundary" if k == 0 else None)
    ax.set_xlim(low, high)


def _style_timesteps_axes(ax: Any, ylabel: str, title: str, percent: bool = True) -> None:
    """Axes of coverage (in %; ``percent`` false: another score, as numbers) over timesteps,
    shared by both panels of the learning curves."""
    ax.set_xlabel("timesteps (agent transitions)")
    ax.set_ylabel(ylabel)
    if percent:
        ax.set_ylim(0, 102)
        ax.yaxis.set_major_formatter(PercentFormatter(100, decimals=0))
    ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4), useMathText=True)
    ax.grid(alpha=0.3)
    ax.set_title(title)
    ax.legend(loc="lower right", framealpha=0.9, fontsize="small")


def _plot_evaluations(
    ax: Any,
    evaluations: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]],
    labels: list[str],
    colours: list[str],
    metric: str | None = None,
    boundaries: Sequence[float] = (),
) -> None:
    """The evaluations panel: each label in its learning-curve colour (``metric``,
    ``boundaries``: see :func:`plot_learning_curves`)."""
    scale = 100.0 if metric is None else 1.0
    for label, runs in evaluations.items():
        k = labels.index(label) if label in labels else len(labels)
        grid = np.unique(np.concatenate([np.asarray(t, dtype=float) for t, _ in runs]))
        stacked = np.full((len(runs), len(grid)), np.nan)
        for i, (t, c) in enumerate(runs):
            # Runs evaluate at the same multiples of eval.every; others are left out (NaN).
            stacked[i, np.searchsorted(grid, np.asarray(t, dtype=float))] = c
        with _quiet_nan_warnings():
            middle = np.nanmedian(stacked, axis=0)
        ax.plot(
            grid, scale * middle, color=colours[k % len(colours)], lw=1.4, marker=".", label=label
        )
    draw_phase_boundaries(ax, boundaries)
    _style_timesteps_axes(
        ax,
        f"{metric or 'team coverage'} (median of the evaluation episodes)",
        "test policy during training (evaluations.csv)",
        percent=metric is None,
    )


def _common_grid(
    runs: Sequence[tuple[np.ndarray, np.ndarray]], window: int, points: int = 300
) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed runs interpolated onto one grid of timesteps (NaN outside each run's range)."""
    start = min(float(t[0]) for t, _ in runs)
    stop = max(float(t[-1]) for t, _ in runs)
    grid = np.linspace(start, stop, points) if stop > start else np.array([start])
    stacked = np.full((len(runs), len(grid)), np.nan)
    for i, (t, c) in enumerate(runs):
        inside = (grid >= t[0]) & (grid <= t[-1])
        stacked[i, inside] = np.interp(grid[inside], t, smooth(c, window))
    return grid, stacked


@contextmanager
def _quiet_nan_warnings() -> Iterator[None]:
    """Silence numpy's "All-NaN slice" warnings (grid points no run reached are expected)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


# ---------------------------------------------------------------------- episodes as GIF
def play_episode(
    env_cfg: EnvConfig, policy: BatchPolicy, seed: int, every: int = 1, frames: bool = True
) -> EpisodeResult:
    """Play one episode with a batched policy, recording paths, the map and ``rgb_array`` frames.

    It is episode 0 of ``run_episodes(..., seed=seed)`` (the same loop): the same map and start
    cells (and, for a deterministic policy, the same episode).

    Args:
        env_cfg: The env to build.
        policy: ``policy(obs, envs) -> actions`` (``harness.evaluation.episodes.BatchPolicy``).
        seed: Reset seed.
        every: Keep a frame every ``every`` steps (plus the first and the last).
        frames: Render frames at all (``False`` records only the paths).

    Returns:
        The episode, with ``paths``, ``walls`` and (with ``frames``) ``frames``.
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    (result,) = run_episodes(
        policy, env_cfg, 1, seed, copies=1, record_paths=True, frames_every=every if frames else 0
    )
    return result


def episode_frames(
    env_cfg: EnvConfig, policy: BatchPolicy, seed: int, every: int = 1
) -> list[np.ndarray]:
    """``rgb_array`` frames of one episode (see :func:`play_episode`), for :func:`write_gif`."""
    return play_episode(env_cfg, policy, seed, every=every).frames


def write_gif(
    frames: Sequence[np.ndarray],
    out: str | Path,
    fps: int = 10,
    hold: float = 0.0,
    palette: np.ndarray | None = None,
) -> Path:
    """Write ``uint8 (H, W, 3)`` frames as an animated GIF that loops forever.

    Pillow merges identical consecutive frames into one longer frame, so the file can hold
    fewer frames than given (e.g. when every agent stays put at the end of an episode).

    Args:
        frames: RGB images, all the same size.
        out: GIF file to write (folders are created).
        fps: Frames per second.
        hold: Seconds the last frame stays on screen beyond its own before the loop restarts.
        palette: ``uint8 (k, 3)`` colours (k <= 256) every pixel is mapped to, the nearest
            without dithering: for frames whose colours are known (:func:`gif_palette`), far
            faster than Pillow's own palette for each frame. ``None``: Pillow's.

    Returns:
        The path of the GIF.
    """
    from PIL import Image

    if not frames:
        raise ValueError("write_gif needs at least one frame")
    if fps < 1:
        raise ValueError(f"fps must be >= 1, got {fps}")
    if not hold >= 0:
        raise ValueError(f"hold must be >= 0, got {hold}")
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    if palette is not None:
        colours = np.asarray(palette, dtype=np.uint8).reshape(-1, 3)
        if not 1 <= len(colours) <= 256:
            raise ValueError(f"a GIF palette has 1 to 256 colours, got {len(colours)}")
        table = Image.new("P", (1, 1))
        table.putpalette(np.resize(colours, (256, 3)).ravel().tolist())
        images = [im.quantize(palette=table, dither=Image.Dither.NONE) for im in images]
    out = Path(out)
    duration = max(20, round(1000 / fps))  # browsers treat < 20 ms as 100 ms
    atomic_write(  # whole or not at all: a full disk leaves the GIF that was there
        out,
        lambda tmp: images[0].save(
            tmp,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=[duration] * (len(images) - 1) + [duration + round(1000 * hold)],
            loop=0,
        ),
    )
    return out


# ---------------------------------------------------------------------- the render GIF
#: Frames per second of ``harness render --gif``.
GIF_FPS = 10
#: Longest a GIF of ``harness render`` lasts without ``--every``: :func:`gif_every` keeps at
#: most ``GIF_FPS * GIF_SECONDS`` steps of the episode (plus its first frame).
GIF_SECONDS = 20
#: Seconds the last frame (the final coverage) stays before the GIF starts again.
GIF_HOLD = 2.0
#: Most bytes the frames of a ``harness render`` GIF may take in memory (:func:`gif_bytes`).
#: An episode's frames are all held until the GIF is written: a 20,000-step episode of a big map
#: at one frame per step would need ~19 GB; 2 GiB holds 1,000 frames of a 100x50 map.
MAX_GIF_BYTES = 2 << 30
#: A map drawn smaller than this many pixels (its longer side) is enlarged by a whole factor.
GIF_MIN_MAP_PIXELS = 400
_GIF_FONT_SIZE = 13
_GIF_MARGIN = 8
_GIF_SWATCH = 11  # legend squares and circles, pixels
_GIF_TEXT = (0, 0, 0)
_GIF_BACKGROUND = (255, 255, 255)
_GIF_RULE = (160, 160, 160)  # the line between the header and the map
_MARKER_OUTLINE = (0, 0, 0)


def gif_palette() -> np.ndarray:
    """``uint8 (k, 3)``: the colours of :func:`gif_frames`' frames, for :func:`write_gif`: the
    map's, the agents', and 32 greys for the header's text (smoothed at its edges)."""
    greys = np.repeat(np.linspace(0, 255, 32).round()[:, None], 3, axis=1)
    colours = [
        render.WALL_COLOUR[None],
        render.FREE_COLOUR[None],
        render.VISITED_COLOURS,
        render.AGENT_COLOURS,
        np.array([_GIF_RULE, _GIF_TEXT, _GIF_BACKGROUND, _MARKER_OUTLINE]),
        greys,
    ]
    return np.unique(np.concatenate(colours).astype(np.uint8), axis=0)


def gif_every(steps: int, fps: int = GIF_FPS, seconds: float = GIF_SECONDS) -> int:
    """The frame spacing that makes an episode of ``steps`` steps last at most ``seconds`` at
    ``fps``: ``ceil(steps / (fps * seconds))`` (1 for a short episode). An episode at least
    half that long then lasts between ``seconds / 2`` and ``seconds`` (10-20 s by default)."""
    return max(1, math.ceil(steps / (fps * seconds)))


def frame_steps(steps: int, every: int) -> list[int]:
    """The steps that :func:`play_episode` keeps a frame of: 0, every ``every``-th and the last."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    return [*range(0, steps + 1, every), *([steps] if steps % every else [])]


def gif_title(label: str, seed: int, coverage: float, note: str = "") -> str:
    """The GIF's title: the policy (a baseline's name or the model), the seed, the final
    coverage and, for a model sampling its actions, how (``sampling_note``)."""
    title = f"{label}, seed {seed}: final coverage {coverage:.1%}"
    return f"{title} ({note})" if note else title


def gif_status(step: int, steps: int, coverage: float) -> str:
    """The line of a frame under the title: the step counter and the coverage so far."""
    return f"step {step} / {steps}    coverage {coverage:.1%}"


def coverage_by_step(rec: EpisodeResult) -> np.ndarray:
    """``float (steps + 1,)``: the team's coverage after each step of a recorded episode (its
    ``paths`` and ``walls``): the free cells some agent has stood on, start cells included."""
    if rec.walls is None or not rec.paths:
        raise ValueError("coverage_by_step needs an episode played with its paths recorded")
    first = np.full(rec.walls.shape, rec.steps + 1, dtype=np.int64)
    for path in rec.paths:
        np.minimum.at(first, (path[:, 0], path[:, 1]), np.arange(len(path)))
    counts = np.bincount(first.ravel(), minlength=rec.steps + 2)[: rec.steps + 1]
    return np.cumsum(counts) / rec.free_cells if rec.free_cells else np.zeros(rec.steps + 1)


@dataclass(frozen=True)
class GifLayout:
    """Where things go on a frame of :func:`gif_frames`: a white header band (title, step
    counter and coverage, legend) above the map, whose pixels are the env's ``rgb_array``
    frame enlarged by ``scale`` (nearest neighbour) with the agents' markers drawn on them."""

    scale: int
    """Whole factor the env's frames are enlarged by (1 unless the map is small)."""
    width: int
    height: int
    band: int
    """Height of the header band; the map starts on this row."""
    map_x: int
    """Left column of the map (it is centred when the header is wider)."""
    status_y: int
    legend: tuple[tuple[str, int, int], ...]
    """Legend entries: (kind, x, y) of each entry's first swatch."""
    n_agents: int


@functools.cache
def _gif_font(bold: bool = False) -> Any:
    """DejaVu Sans, which matplotlib ships, at :data:`_GIF_FONT_SIZE`; Pillow's own font where
    that cannot be read (a Pillow built without FreeType)."""
    import matplotlib
    from PIL import ImageFont

    name = "DejaVuSans-Bold.ttf" if bold else "DejaVuSans.ttf"
    try:
        return ImageFont.truetype(
            str(Path(matplotlib.get_data_path(), "fonts", "ttf", name)), _GIF_FONT_SIZE
        )
    except (OSError, ImportError):
        return ImageFont.load_default()


def _text_size(font: Any, text: str) -> tuple[int, int]:
    """Width and height of ``text`` drawn at (0, 0): its box's right and bottom edges."""
    box = font.getbbox(text)
    return int(box[2]), int(box[3])


def _legend_entries(n_agents: int) -> list[tuple[str, str, int]]:
    """(kind, label, swatches) of the legend: walls, unvisited cells, visited cells in each
    agent's tint, the agents' markers."""
    shown = min(n_agents, len(render.AGENT_COLOURS))
    return [
        ("wall", "wall", 1),
        ("free", "unvisited", 1),
        ("visited", "visited (by agent)", shown),
        ("agent", "agents", shown),
    ]


def gif_layout(map_pixels: tuple[int, int], n_agents: int, steps: int, title: str) -> GifLayout:
    """The layout of a GIF frame for an env frame of ``map_pixels`` (rows, columns) pixels.

    The frame is as wide as the (enlarged) map or the header's text, whichever is wider; the
    legend wraps onto more rows when it does not fit on one.
    """
    bold, font = _gif_font(bold=True), _gif_font()
    longest = max(map_pixels)
    scale = max(1, GIF_MIN_MAP_PIXELS // longest) if longest else 1
    map_h, map_w = map_pixels[0] * scale, map_pixels[1] * scale
    m, gap = _GIF_MARGIN, _GIF_SWATCH + 3
    title_w, title_h = _text_size(bold, title)
    status_w, status_h = _text_size(font, gif_status(steps, steps, 1.0))
    entries = [
        (kind, n * gap + 3 + _text_size(font, label)[0])
        for kind, label, n in _legend_entries(n_agents)
    ]
    width = max(map_w, title_w + 2 * m, status_w + 2 * m, max(w for _, w in entries) + 2 * m)
    row_h = max(_GIF_SWATCH, _text_size(font, "Ag")[1]) + 4
    status_y = m + title_h + 4
    x, y = m, status_y + status_h + 6
    legend = []
    for kind, w in entries:
        if x > m and x + w > width - m:
            x, y = m, y + row_h
        legend.append((kind, x, y))
        x += w + 16
    band = y + row_h + m
    return GifLayout(
        scale, width, band + map_h, band, (width - map_w) // 2, status_y, tuple(legend), n_agents
    )


def gif_bytes(
    map_shape: tuple[int, int], n_agents: int, steps: int, every: int, title: str
) -> tuple[int, int]:
    """Memory the frames of a render GIF take, before the episode is played: ``(total, per
    frame)`` bytes for a map of ``map_shape`` cells (the largest its source makes). A frame
    counts the env's ``rgb_array`` image and the GIF's frame made from it (3 bytes a pixel);
    all of them are held until the GIF is written."""
    pixels = (map_shape[0] * render.CELL_PIXELS, map_shape[1] * render.CELL_PIXELS)
    layout = gif_layout(pixels, n_agents, steps, title)
    per_frame = 3 * (pixels[0] * pixels[1] + layout.height * layout.width)
    return len(frame_steps(steps, every)) * per_frame, per_frame


def byte_size(n: int) -> str:
    """``n`` bytes for a message: ``"2.1 GiB"``, ``"480.0 MiB"``, ``"12.0 KiB"``."""
    for unit, size in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{n} bytes"


def _draw_header(layout: GifLayout, title: str) -> np.ndarray:
    """The parts of the header band that every frame shares: title, legend, the rule."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (layout.width, layout.band), _GIF_BACKGROUND)
    draw = ImageDraw.Draw(img)
    bold, font = _gif_font(bold=True), _gif_font()
    m, s = _GIF_MARGIN, _GIF_SWATCH
    draw.text((m, m), title, fill=_GIF_TEXT, font=bold)
    labels = {kind: (label, n) for kind, label, n in _legend_entries(layout.n_agents)}
    for kind, x, y in layout.legend:
        label, n = labels[kind]
        for i in range(n):
            box = (x + i * (s + 3), y, x + i * (s + 3) + s - 1, y + s - 1)
            if kind == "agent":
                colour = tuple(int(v) for v in render.agent_colour(i))
                draw.ellipse(box, fill=colour, outline=_MARKER_OUTLINE)
            else:
                colour = {
                    "wall": render.WALL_COLOUR,
                    "free": render.FREE_COLOUR,
                    "visited": render.VISITED_COLOURS[i % len(render.VISITED_COLOURS)],
                }[kind]
                draw.rectangle(box, fill=tuple(int(v) for v in colour), outline=_GIF_RULE)
        text_y = y + s // 2 - _text_size(font, "Ag")[1] // 2
        draw.text((x + n * (s + 3) + 3, text_y), label, fill=_GIF_TEXT, font=font)
    draw.line((0, layout.band - 1, layout.width, layout.band - 1), fill=_GIF_RULE)
    return np.asarray(img)


def gif_frames(rec: EpisodeResult, every: int, title: str) -> list[np.ndarray]:
    """The frames of ``harness render --gif`` from an episode that :func:`play_episode` played
    with ``every`` (its paths and frames recorded): under a header band with ``title``, the step
    counter, the coverage so far and a legend, the map (enlarged when small) with each agent
    drawn as a disc in its colour with a dark outline, about three cells across on a big map.
    """
    from PIL import Image, ImageDraw

    steps = frame_steps(rec.steps, every)
    if len(rec.frames) != len(steps) or rec.walls is None:
        raise ValueError(
            f"gif_frames needs the episode's frames every {every} steps ({len(steps)}) and its "
            f"paths, got {len(rec.frames)} frames"
        )
    map_pixels = rec.frames[0].shape[:2]
    layout = gif_layout(map_pixels, len(rec.paths), rec.steps, title)
    header = _draw_header(layout, title)
    coverage = coverage_by_step(rec)
    font = _gif_font()
    cell = map_pixels[0] // rec.walls.shape[0] * layout.scale
    radius = max(0.75 * cell, 10.0)
    out = []
    for step, frame in zip(steps, rec.frames, strict=True):
        k = layout.scale
        enlarged = np.repeat(np.repeat(frame, k, axis=0), k, axis=1) if k > 1 else frame
        picture = Image.fromarray(np.ascontiguousarray(enlarged))
        draw = ImageDraw.Draw(picture)  # on the map alone: a disc at its edge is cut there
        # The lowest index on top where agents meet (as in the env's ansi picture).
        for i in range(len(rec.paths) - 1, -1, -1):
            r, c = rec.paths[i][step]
            x, y = (c + 0.5) * cell, (r + 0.5) * cell
            box = (x - radius, y - radius, x + radius, y + radius)
            colour = tuple(int(v) for v in render.agent_colour(i))
            draw.ellipse(box, fill=colour, outline=_MARKER_OUTLINE, width=2)
        canvas = np.empty((layout.height, layout.width, 3), dtype=np.uint8)
        canvas[:] = _GIF_BACKGROUND
        canvas[: layout.band] = header
        canvas[layout.band :, layout.map_x : layout.map_x + enlarged.shape[1]] = np.asarray(picture)
        img = Image.fromarray(canvas)
        status = gif_status(step, rec.steps, float(coverage[step]))
        ImageDraw.Draw(img).text((_GIF_MARGIN, layout.status_y), status, fill=_GIF_TEXT, font=font)
        out.append(np.asarray(img))
    return out


# ---------------------------------------------------------------------- helpers
def _save(fig: Figure, out: str | Path) -> Path:
    """Save a picture of this module, whole or not at all (:func:`write_figure`)."""
    return write_figure(fig, Path(out), format="png", dpi=DPI, facecolor="white")
