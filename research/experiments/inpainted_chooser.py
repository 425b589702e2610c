"""The rollout chooser on whole layouts drawn from a map prior (CogniPlan's idea with the
harness's own prior): instead of drawing every unseen cell independently from the prior's
probabilities, the maps are drawn band by band outward from the seen region (``--width``
cells of distance a band), the prior re-read after each band with the cells drawn so far as
seen, its log-odds times ``--sharpen``. Walls then continue and rooms close, where cell-by-cell
draws speckle. Every agent deciding at a step reads the same maps (drawn once a step).

Runs ``harness eval`` with the chooser's map drawing replaced, so every ``harness eval`` option
applies (play it on validation episodes: ``--seed 2000003``)::

    python research/experiments/inpainted_chooser.py --width 2 --sharpen 2 -- \
        eval --policy rollout --config configs/goals_4agents.yaml \
        --set 'env.map={rooms: {height: 50, width: 100}}' --set 'env.test_maps=[]' \
        --set eval.rollout.prior=runs/reference/prior_rooms --set eval.rollout.after=0.5 \
        --seed 2000003 --episodes 10 --against frontier_pocket --json
"""

from __future__ import annotations

import argparse
import sys
import threading

import numpy as np
from scipy.ndimage import distance_transform_cdt

from envs.coverage import rollouts
from harness.cli import main as harness_main
from harness.prior.coding import SEEN_FREE, SEEN_WALL, code_team_map


def layouts(prior, seen, free, rng, n: int, width: int, sharpen: float) -> np.ndarray:
    """``n`` maps, ``bool (n, H, W)`` free cells, drawn band by band (module docstring)."""
    states = np.repeat(code_team_map(seen, ~free)[None], n, axis=0)
    dist = distance_transform_cdt(~seen, metric="chessboard")
    lo, top = 0, int(dist.max())
    while lo < top:
        band = (dist > lo) & (dist <= lo + width)
        lo += width
        logit = prior.logits(states).astype(np.float64) * sharpen
        wall = rng.random(states.shape) < 1.0 / (1.0 + np.exp(-logit))
        states[:, band] = np.where(wall[:, band], SEEN_WALL, SEEN_FREE)
    return states == SEEN_FREE


def patch(width: int, sharpen: float) -> None:
    cache: dict[int, tuple[int, int, list[np.ndarray]]] = {}
    lock = threading.Lock()

    def per_map(self, planner, candidates, agent, steps_left, rng, walks=None, p_wall=None):
        valid = np.flatnonzero(candidates.cells[agent] >= 0)
        key = (steps_left, int(planner.visited.sum()))
        with lock:
            hit = cache.get(id(planner))
        if hit is None or hit[:2] != key:
            seen, inner, _ = rollouts._seen_share(planner)
            drawn = layouts(self.prior, seen, inner, rng, self.samples, width, sharpen)
            maps = []
            for d in drawn:
                guess = np.asarray(planner.free, dtype=bool).reshape(-1, planner.stride).copy()
                guess[1:-1, 1:-1] = d
                maps.append(guess.ravel())
            with lock:
                cache[id(planner)] = (*key, maps)
        else:
            maps = hit[2]

        def score(f: np.ndarray) -> np.ndarray:
            return self.scores_on(f, planner, candidates, agent, steps_left, walks)[valid]

        return np.array(list(self._map(score, maps))).reshape(self.samples, valid.size)

    rollouts.SampledChooser.per_map = per_map


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--width", type=int, default=2)
    parser.add_argument("--sharpen", type=float, default=2.0)
    parser.add_argument("harness", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    patch(args.width, args.sharpen)
    rest = args.harness[1:] if args.harness[:1] == ["--"] else args.harness
    sys.exit(harness_main(rest))
