"""The seeded generator of the shipped maze map ``maze_100x50``, the hardest shipped map.

Until the cellular-automaton cave (:mod:`envs.coverage.cave`) replaced it, this map was the
stand-in for the thesis's cave (§4.3); it stays shipped as a harder benchmark: a labyrinth of
one-cell corridors on which even the frontier explorer covers only 58 % with 2 agents in 1000 steps.

1. start from solid rock and a lattice of passage nodes (every other cell);
2. carve a growing-tree maze over part of the lattice (``node_share``), preferring to extend the
   newest passage and to keep going straight, which makes long winding passages, and branching
   from earlier ones, which leaves dead ends;
3. open a few extra walls between carved nodes (``loop_prob``), so some passages form loops;
4. open a few small elliptical chambers along the passages;
5. remove single wall cells standing inside open ground and fill everything not connected to the
   largest free area (there is none by construction; the step guards the promise that all free
   cells are connected).

The map is re-made, byte for byte, by::

    python -m envs.coverage.maze            # writes envs/maps/maze_100x50.txt

and variants (another seed, a sparser or loopier maze) by, e.g.::

    python -m envs.coverage.maze --node-share 0.6 --out /tmp/maze_sparse.txt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from envs.coverage.maps import fill_unreachable, format_map

MAZE_SEED = 2021
MAZE_SHAPE = (50, 100)
NODE_SHARE = 0.85  # the shipped maze's share of the passage lattice that is carved
LOOP_PROB = 0.03  # the shipped maze's chance per lattice edge of an extra opening
_DIRECTIONS = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])


def generate_maze(
    seed: int = MAZE_SEED,
    height: int = MAZE_SHAPE[0],
    width: int = MAZE_SHAPE[1],
    node_share: float = NODE_SHARE,
    newest_prob: float = 0.7,
    straight_prob: float = 0.5,
    n_chambers: int = 14,
    loop_prob: float = LOOP_PROB,
) -> np.ndarray:
    """Carve a maze map; returns a bool ``(height, width)`` grid, True = wall.

    Args:
        seed: Seed of the generator; the same seed gives the same map.
        height: Rows.
        width: Columns.
        node_share: Share of the passage lattice that gets carved; the rest stays solid rock.
        newest_prob: Growing-tree choice: chance to extend the newest passage (long winding
            passages) rather than a random earlier one (branches, hence dead ends).
        straight_prob: Chance to keep the passage's direction when it can (longer runs).
        n_chambers: Number of small chambers opened along the passages.
        loop_prob: Chance per lattice edge of an extra opening, so a few passages form loops.
    """
    if height < 3 or width < 3:
        raise ValueError(f"a maze needs at least 3x3 cells, got {height}x{width}")
    rng = np.random.default_rng(seed)
    rock = np.ones((height, width), dtype=bool)
    # Passage lattice: node (i, j) is cell (1 + 2i, 1 + 2j); the cell between two neighbouring
    # nodes is the passage joining them; everything else stays rock (1-cell walls, closed border).
    n_rows, n_cols = (height - 1) // 2, (width - 1) // 2
    carved = np.zeros((n_rows, n_cols), dtype=bool)
    target = int(node_share * n_rows * n_cols)

    def open_node(i: int, j: int) -> None:
        carved[i, j] = True
        rock[1 + 2 * i, 1 + 2 * j] = False

    first = (n_rows // 2, n_cols // 2)
    open_node(*first)
    active: list[tuple[int, int, int]] = [(*first, int(rng.integers(4)))]
    while active and carved.sum() < target:
        k = len(active) - 1 if rng.random() < newest_prob else int(rng.integers(len(active)))
        i, j, last = active[k]
        options = [
            d
            for d, (di, dj) in enumerate(_DIRECTIONS)
            if 0 <= i + di < n_rows and 0 <= j + dj < n_cols and not carved[i + di, j + dj]
        ]
        if not options:
            active.pop(k)
            continue
        d = last if last in options and rng.random() < straight_prob else int(rng.choice(options))
        di, dj = _DIRECTIONS[d]
        rock[1 + 2 * i + di, 1 + 2 * j + dj] = False  # the passage between the two nodes
        open_node(i + di, j + dj)
        active.append((i + di, j + dj, d))

    # A few loops: open walls between neighbouring carved nodes.
    for i, j in np.argwhere(carved):
        for di, dj in ((1, 0), (0, 1)):
            ni, nj = i + di, j + dj
            if ni < n_rows and nj < n_cols and carved[ni, nj] and rng.random() < loop_prob:
                rock[1 + 2 * i + di, 1 + 2 * j + dj] = False

    nodes = np.argwhere(carved)
    for i, j in nodes[rng.choice(len(nodes), size=min(n_chambers, len(nodes)), replace=False)]:
        _carve_chamber(rock, 1 + 2 * int(i), 1 + 2 * int(j), rng)

    rock = _remove_pillars(rock)
    return fill_unreachable(rock)


def _carve_chamber(rock: np.ndarray, r: int, c: int, rng: np.random.Generator) -> None:
    """Open a small elliptical chamber centred near ``(r, c)``, in place (``rock`` changes)."""
    h, w = rock.shape
    ry, rx = rng.uniform(1.5, 3.0), rng.uniform(2.0, 4.0)
    rows, cols = np.ogrid[:h, :w]
    inside = ((rows - r) / ry) ** 2 + ((cols - c) / rx) ** 2 <= 1.0
    inside[[0, -1], :] = False
    inside[:, [0, -1]] = False
    rock[inside] = False


def _remove_pillars(rock: np.ndarray) -> np.ndarray:
    """Turn interior wall cells whose four neighbours are all free into free cells."""
    out = rock.copy()
    inner = rock[1:-1, 1:-1]
    free_nbrs = ~rock[:-2, 1:-1] & ~rock[2:, 1:-1] & ~rock[1:-1, :-2] & ~rock[1:-1, 2:]
    out[1:-1, 1:-1] = inner & ~free_nbrs
    return out


def main(argv: list[str] | None = None) -> None:
    """Write the shipped maze map, or a variant (seed, node share, loop chance), as text."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=MAZE_SEED)
    parser.add_argument(
        "--node-share", type=float, default=NODE_SHARE, help="share of the lattice carved"
    )
    parser.add_argument(
        "--loop-prob", type=float, default=LOOP_PROB, help="chance per edge of an extra opening"
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parents[1] / "maps" / "maze_100x50.txt"
    )
    args = parser.parse_args(argv)
    if not 0.0 < args.node_share <= 1.0 or not 0.0 <= args.loop_prob <= 1.0:
        parser.error("--node-share must be in (0, 1] and --loop-prob in [0, 1]")
    grid = generate_maze(args.seed, node_share=args.node_share, loop_prob=args.loop_prob)
    args.out.write_text(format_map(grid), encoding="utf-8")
    print(f"wrote {args.out}: {grid.shape[0]}x{grid.shape[1]}, {int((~grid).sum())} free cells")


if __name__ == "__main__":
    main()
