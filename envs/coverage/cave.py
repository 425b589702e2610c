"""The seeded generator of the shipped cave map ``cave_100x50``.

The thesis (§4.3) tested on a map "based on a real cave environment with a lot of dead ends and
multiple small closed areas"; that map was not published, so this generator makes a stand-in the
way cave maps are usually made for games and robotics benchmarks, with a cellular automaton:

1. fill the grid with rock at random (``rock_share`` of the cells) inside a closed border;
2. smooth it ``iterations`` times with the "4-5 rule": a rock cell stays rock when at least 4 of
   its 8 neighbours are rock, a free cell turns to rock when at least 5 are (the outside counts as
   rock). Noise becomes irregular chambers and winding passages; a high rock share leaves many
   separate pockets;
3. fill pockets of fewer than ``min_region`` cells, then join the remaining ones one at a time:
   from the region holding the largest pocket, a winding tunnel (a random walk biased towards the
   target, one or two cells wide) is dug to the nearest cell of another region. The tunnels are
   the narrow passages; the pockets' far ends are the dead ends;
4. fill everything not connected to the largest free area (nothing, after step 3; the step guards
   the promise that all free cells are connected).

The map is re-made, byte for byte, by::

    python -m envs.coverage.cave            # writes envs/maps/cave_100x50.txt

and variants (another seed, a more open or a tighter cave) by, e.g.::

    python -m envs.coverage.cave --rock-share 0.5 --out /tmp/cave_open.txt

The earlier stand-in, a maze of one-cell corridors, is shipped as ``maze_100x50``
(:mod:`envs.coverage.maze`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import ndimage

from envs.coverage.maps import fill_unreachable, format_map, label_free_components

CAVE_SEED = 2021
CAVE_SHAPE = (50, 100)
ROCK_SHARE = 0.55  # the shipped cave's initial rock share: narrow passages, ~1,300 free cells
_STEPS = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])


def generate_cave(
    seed: int = CAVE_SEED,
    height: int = CAVE_SHAPE[0],
    width: int = CAVE_SHAPE[1],
    rock_share: float = ROCK_SHARE,
    iterations: int = 4,
    min_region: int = 12,
    wide_share: float = 0.5,
    wander_prob: float = 0.25,
) -> np.ndarray:
    """Make a cave map; returns a bool ``(height, width)`` grid, True = wall.

    Args:
        seed: Seed of the generator; the same seed gives the same map.
        height: Rows.
        width: Columns.
        rock_share: Share of rock in the initial noise; higher gives a tighter cave.
        iterations: Smoothing passes of the cellular automaton.
        min_region: Pockets smaller than this many cells are filled instead of joined.
        wide_share: Share of the joining tunnels that are two cells wide.
        wander_prob: Chance per tunnel step of a random step instead of one towards the target
            (how much the tunnels wind).
    """
    rng = np.random.default_rng(seed)
    rock = _pockets(rng, height, width, rock_share, iterations, min_region)
    while True:
        labels, n = label_free_components(rock)
        if n <= 1:
            break
        sizes = np.bincount(labels.ravel())[1:]
        main = labels == 1 + int(np.argmax(sizes))
        start, target = _nearest_pair(main, (labels > 0) & ~main)
        _dig_tunnel(
            rock, start, target, wide=rng.random() < wide_share, wander=wander_prob, rng=rng
        )
    return fill_unreachable(rock)


def _pockets(
    rng: np.random.Generator,
    height: int,
    width: int,
    rock_share: float,
    iterations: int,
    min_region: int,
) -> np.ndarray:
    """Steps 1-3 up to the joining (module docstring): the noise, smoothed, with the pockets
    smaller than ``min_region`` filled; True = rock."""
    rock = rng.random((height, width)) < rock_share
    _close_border(rock)
    for _ in range(iterations):
        rock = _smooth(rock)
    labels, n = label_free_components(rock)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    rock |= (sizes < min_region)[labels] & (labels > 0)
    return rock


def count_pockets(
    seed: int,
    height: int,
    width: int,
    rock_share: float = ROCK_SHARE,
    iterations: int = 4,
    min_region: int = 12,
) -> int:
    """The separate free regions that step 3 of :func:`generate_cave` joins one tunnel at a
    time for ``seed`` (each join relabels the whole map: the draw's cost is about this count
    times the cells), at the cost of one labelling."""
    rock = _pockets(np.random.default_rng(seed), height, width, rock_share, iterations, min_region)
    _, count = label_free_components(rock)
    return count


def _close_border(rock: np.ndarray) -> None:
    """Make the outermost rows and columns rock, in place."""
    rock[[0, -1], :] = True
    rock[:, [0, -1]] = True


def _smooth(rock: np.ndarray) -> np.ndarray:
    """One pass of the 4-5 cellular-automaton rule (outside the grid counts as rock)."""
    counts = ndimage.convolve(
        rock.astype(np.int8), np.ones((3, 3), np.int8), mode="constant", cval=1
    )
    neighbours = counts - rock
    out = np.where(rock, neighbours >= 4, neighbours >= 5)
    _close_border(out)
    return out


def _nearest_pair(source: np.ndarray, others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The closest (Euclidean) pair of cells: ``a`` in ``source``, ``b`` in ``others``.

    Ties go to the first ``b`` in reading order, so the result is deterministic.
    """
    distance, nearest = ndimage.distance_transform_edt(~source, return_indices=True)
    candidates = np.where(others, distance, np.inf)
    b = np.array(np.unravel_index(int(np.argmin(candidates)), source.shape))
    a = nearest[:, b[0], b[1]]
    return a, b


def _dig_tunnel(
    rock: np.ndarray,
    start: np.ndarray,
    target: np.ndarray,
    wide: bool,
    wander: float,
    rng: np.random.Generator,
) -> None:
    """Carve a winding passage from ``start`` to ``target`` in place, staying inside the border."""
    height, width = rock.shape
    r, c = int(start[0]), int(start[1])
    tr, tc = int(target[0]), int(target[1])
    while (r, c) != (tr, tc):
        if rng.random() < wander:
            dr, dc = _STEPS[rng.integers(4)]
        else:
            towards = [(int(np.sign(tr - r)), 0)] if r != tr else []
            towards += [(0, int(np.sign(tc - c)))] if c != tc else []
            dr, dc = towards[rng.integers(len(towards))]
        r = min(max(r + int(dr), 1), height - 2)
        c = min(max(c + int(dc), 1), width - 2)
        rock[r, c] = False
        if wide:
            rock[r : min(r + 2, height - 1), c : min(c + 2, width - 1)] = False


def main(argv: list[str] | None = None) -> None:
    """Write the shipped cave map, or a variant (seed, rock share), as text."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=CAVE_SEED)
    parser.add_argument(
        "--rock-share", type=float, default=ROCK_SHARE, help="initial rock share (0.4-0.6)"
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parents[1] / "maps" / "cave_100x50.txt"
    )
    args = parser.parse_args(argv)
    if not 0.0 < args.rock_share < 1.0:
        parser.error("--rock-share must be in (0, 1)")
    grid = generate_cave(args.seed, rock_share=args.rock_share)
    if not (~grid).any():
        parser.error(f"--rock-share {args.rock_share} leaves no free cell")
    args.out.write_text(format_map(grid), encoding="utf-8")
    print(f"wrote {args.out}: {grid.shape[0]}x{grid.shape[1]}, {int((~grid).sum())} free cells")


if __name__ == "__main__":
    main()
