"""Maps for the coverage environment: random maps, the text map format and shipped maps.

A map is a 2D ``bool`` array of shape ``(rows, cols)`` where ``True`` is a wall. Everything here is
a pure function of its inputs (and of the random generator it is handed), so maps are repeatable:
the same seed gives the same map.

Text format (one line per row)::

    #####
    #S..#      '#' wall, '.' free, 'S' free start cell (used as the agents' start cells)
    #..##
    #####

Blank lines at the end of the file and ``\\r`` are tolerated; anything else is a ``ValueError``
naming the file, the line and the column.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

#: 4-connectivity (no diagonal moves), used for reachability.
_FOUR_CONNECTED = ndimage.generate_binary_structure(2, 1)

WALL_CHAR, FREE_CHAR, START_CHAR = "#", ".", "S"


@dataclass(frozen=True)
class MapSpec:
    """A loaded map: its wall grid, optional start cells and where it came from."""

    grid: np.ndarray
    """``bool`` array ``(rows, cols)``, ``True`` = wall."""
    starts: tuple[tuple[int, int], ...] | None
    """Start cells from ``S`` marks in reading order, or ``None`` when the file has none."""
    source: str
    """File path or shipped name, for messages."""


def label_free_components(grid: np.ndarray) -> tuple[np.ndarray, int]:
    """Label the 4-connected components of free cells.

    Returns:
        ``(labels, n)``: ``labels`` is an int array with 0 on walls and 1..n on free components.
    """
    labels, n = ndimage.label(~grid, structure=_FOUR_CONNECTED)
    return labels, int(n)


def fill_unreachable(grid: np.ndarray) -> np.ndarray:
    """Return a copy of ``grid`` where every free cell outside the largest free component is wall.

    Ties between equally large components go to the one with the lowest label (first in reading
    order), so the result is deterministic.
    """
    labels, n = label_free_components(grid)
    if n <= 1:
        return grid.copy()
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    sizes[0] = 0  # label 0 is the walls
    keep = int(np.argmax(sizes))
    return labels != keep


def count_unreachable(grid: np.ndarray) -> int:
    """Number of free cells that are not in the largest 4-connected free component."""
    labels, n = label_free_components(grid)
    if n <= 1:
        return 0
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    return int(sizes.sum() - sizes.max())


def check_wall_fraction(value: Any) -> tuple[float, float]:
    """The one check of a ``wall_fraction`` range (env, map sources and configs call it).

    Raises:
        ValueError: unless ``value`` is a pair with ``0 <= low <= high < 1``.
    """
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"wall_fraction must be a pair (low, high), got {value!r}") from None
    if not (0.0 <= low <= high < 1.0):
        raise ValueError(f"wall_fraction must satisfy 0 <= low <= high < 1, got {value!r}")
    return low, high


def random_grid(
    height: int,
    width: int,
    wall_fraction: tuple[float, float],
    rng: np.random.Generator,
    keep_free: np.ndarray | None = None,
) -> np.ndarray:
    """Draw a random map as in the thesis (§4), with unreachable pockets filled in.

    The wall share ``w`` is drawn uniformly from ``wall_fraction``; ``round(w * height * width)``
    distinct cells become walls; then every free cell outside the largest 4-connected free component
    becomes wall too, so every free cell is reachable from every other.

    Args:
        keep_free: Optional ``(k, 2)`` cells (fixed start cells) that are never picked as walls.
            They can still be filled in if walls cut them off; the caller checks.
    """
    lo, hi = wall_fraction
    share = rng.uniform(lo, hi) if hi > lo else lo
    n_cells = height * width
    candidates = np.arange(n_cells)
    if keep_free is not None and len(keep_free):
        candidates = np.setdiff1d(candidates, keep_free[:, 0] * width + keep_free[:, 1])
    n_walls = min(round(share * n_cells), len(candidates))
    grid = np.zeros(n_cells, dtype=bool)
    grid[rng.choice(candidates, size=n_walls, replace=False)] = True
    return fill_unreachable(grid.reshape(height, width))


def parse_map(text: str, source: str = "<string>") -> MapSpec:
    """Parse the text map format (see the module docstring).

    Raises:
        ValueError: naming ``source``, the line and the column of the first problem.
    """
    lines = text.replace("\r", "").split("\n")
    while lines and lines[-1].strip() == "":
        lines.pop()
    if not lines:
        raise ValueError(f"{source}: map file is empty")
    width = len(lines[0])
    rows: list[list[bool]] = []
    starts: list[tuple[int, int]] = []
    for r, line in enumerate(lines):
        if len(line) != width:
            raise ValueError(
                f"{source}: line {r + 1}: row has {len(line)} columns, expected {width} "
                "(all rows must have the same length)"
            )
        row = []
        for c, ch in enumerate(line):
            if ch == WALL_CHAR:
                row.append(True)
            elif ch in (FREE_CHAR, START_CHAR):
                row.append(False)
                if ch == START_CHAR:
                    starts.append((r, c))
            else:
                raise ValueError(
                    f"{source}: line {r + 1}, column {c + 1}: unexpected character {ch!r} "
                    f"(use '{WALL_CHAR}' wall, '{FREE_CHAR}' free, '{START_CHAR}' start)"
                )
        rows.append(row)
    grid = np.array(rows, dtype=bool)
    if grid.all():
        raise ValueError(f"{source}: map has no free cell")
    return MapSpec(grid=grid, starts=tuple(starts) or None, source=source)


def format_map(grid: np.ndarray, starts: list[tuple[int, int]] | None = None) -> str:
    """Write a grid in the text map format (the inverse of :func:`parse_map`)."""
    chars = np.where(grid, WALL_CHAR, FREE_CHAR).astype("<U1")
    for r, c in starts or []:
        chars[r, c] = START_CHAR
    return "\n".join("".join(row) for row in chars) + "\n"


def shipped_maps() -> list[str]:
    """Names of the maps that ship with the package (``envs/maps/*.txt``)."""
    folder = resources.files("envs") / "maps"
    return sorted(p.name[:-4] for p in folder.iterdir() if p.name.endswith(".txt"))


def load_map(name_or_path: str | Path) -> MapSpec:
    """Load a shipped map by name (e.g. ``"cave_100x50"``) or a map file by path.

    Warns (``UserWarning``) when some free cells cannot be reached from the others: a given map is
    used as given, so those cells still count towards coverage.

    Raises:
        ValueError: unknown name, missing or unreadable file, or a malformed map.
    """
    name = str(name_or_path)
    if name in shipped_maps():
        source = f"shipped map {name!r}"
        text = (resources.files("envs") / "maps" / f"{name}.txt").read_text(encoding="utf-8")
    else:
        path = Path(name)
        if not path.is_file():
            raise ValueError(
                f"map {name!r} is neither a shipped map ({', '.join(shipped_maps())}) "
                "nor an existing file"
            )
        source = str(path)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{source}: cannot read map file ({exc})") from exc
    spec = parse_map(text, source)
    warn_if_unreachable(spec.grid, source)
    return spec


def warn_if_unreachable(grid: np.ndarray, source: str) -> None:
    """Warn when a user-given grid has free cells that cannot be reached from the others."""
    n = count_unreachable(grid)
    if n:
        warnings.warn(
            f"{source}: {n} free cell(s) cannot be reached from the largest free area; "
            "they still count towards coverage",
            UserWarning,
            stacklevel=3,
        )
