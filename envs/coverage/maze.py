"""The seeded generator of the shipped cave map ``cave_100x50``.

The thesis (§4.3) tested on a map "based on a real cave environment with a lot of dead ends and
multiple small closed areas"; that map was not published, so this generator makes a stand-in:

1. start from solid rock;
2. "tunnellers" walk from the centre with a preference for going straight (turning now and then),
   carving 1-cell passages and, rarely, 2-cell ones; they branch into new tunnellers, and each one
   ends after a random length, which leaves dead ends;
3. now and then a tunneller opens a small chamber (an ellipse a few cells across);
4. single wall cells left standing inside open ground are removed (rock pillars one cell wide look
   like noise), and everything not connected to the largest free area is filled (there is none
   by construction, the step only guards the promise that all free cells are connected).

The map is re-made, byte for byte, by::

    python -m envs.coverage.cave            # writes envs/maps/cave_100x50.txt

and variants (another seed, a sparser or loopier cave) by, e.g.::

    python -m envs.coverage.cave --node-share 0.6 --out /tmp/cave_open.txt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from envs.coverage.maps import fill_unreachable, format_map

CAVE_SEED = 2021
CAVE_SHAPE = (50, 100)
NODE_SHARE = 0.85  # the shipped map's share of the passage lattice that is carved
LOOP_PROB = 0.03  # the shipped map's chance per lattice edge of an extra opening
_DIRECTIONS = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]])


def generate_cave(
    seed: int = CAVE_SEED,
    height: int = CAVE_SHAPE[0],
    width: int = CAVE_SHAPE[1],
    node_share: float = NODE_SHARE,
    newest_prob: float = 0.7,
    straight_prob: float = 0.5,
    n_chambers: int = 14,
    loop_prob: float = LOOP_PROB,
) -> np.ndarray:
    """Carve a cave map; returns a bool ``(height, width)`` grid, True = wall.

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
    """Open a small elliptical chamber centred near ``(r, c)``."""
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
    """Write the shipped cave map, or a variant (seed, node share, loop chance), as text."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=CAVE_SEED)
    parser.add_argument(
        "--node-share", type=float, default=NODE_SHARE, help="share of the lattice carved"
    )
    parser.add_argument(
        "--loop-prob", type=float, default=LOOP_PROB, help="chance per edge of an extra opening"
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parents[1] / "maps" / "cave_100x50.txt"
    )
    args = parser.parse_args(argv)
    if not 0.0 < args.node_share <= 1.0 or not 0.0 <= args.loop_prob <= 1.0:
        parser.error("--node-share must be in (0, 1] and --loop-prob in [0, 1]")
    grid = generate_cave(args.seed, node_share=args.node_share, loop_prob=args.loop_prob)
    args.out.write_text(format_map(grid), encoding="utf-8")
    print(f"wrote {args.out}: {grid.shape[0]}x{grid.shape[1]}, {int((~grid).sum())} free cells")


if __name__ == "__main__":
    main()
