"""Recorded trajectories of the coverage env: the guard that a rewrite of the env's step keeps
every episode as it was.

``python -m tests.trajectories --write`` records, for each case of :data:`CASES`, a SHA-256 digest
of everything a seeded episode sequence gives (observations, rewards, terminations, truncations,
infos) under actions drawn from a separate seeded generator, across several episode ends;
``tests/test_core_equality.py`` replays the cases and compares. The file was written by the env
as it stood before the batched core (commit cdd377b: run from outside the repository with that
tree first on ``PYTHONPATH``), so the digests are the episodes of the env the core replaced; a
new case is recorded the same way.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from envs import coverage_v0
from envs.coverage import generators

PATH = Path(__file__).parent / "data" / "env_trajectories.json"

_MIX = [
    (3.0, generators.RandomMaps(12, 12, (0.15, 0.2))),
    (1.0, generators.RandomMaps(9, 14, (0.1, 0.25))),
    (1.0, generators.CaveMaps(14, 20)),
]

#: name -> (env kwargs, episodes, seed)
CASES: dict[str, tuple[dict[str, Any], int, int]] = {
    "thesis_1": ({"n_agents": 1, "height": 10, "width": 10, "max_steps": 40}, 3, 0),
    "thesis_2": ({"n_agents": 2, "height": 12, "width": 9, "max_steps": 35}, 3, 1),
    "thesis_4": ({"n_agents": 4, "height": 15, "width": 15, "max_steps": 50}, 3, 2),
    "thesis_4_raw_team": (
        {
            "n_agents": 4,
            "height": 8,
            "width": 11,
            "max_steps": 30,
            "coords": "raw",
            "rewards": {"team": 0.5, "new_cell": 3.0},
        },
        3,
        3,
    ),
    "thesis_3_agent_id": ({"n_agents": 3, "max_steps": 30, "agent_id": True}, 2, 4),
    "thesis_cave": ({"map": "cave_100x50", "n_agents": 2, "max_steps": 60}, 2, 5),
    "thesis_mix": ({"map": "MIX", "n_agents": 3, "max_steps": 25}, 6, 6),
    "thesis_starts": ({"n_agents": 2, "height": 9, "width": 9, "starts": [(0, 0), (8, 8)]}, 2, 7),
    "teammap_2": ({"n_agents": 2, "height": 14, "width": 14, "observation": "teammap"}, 2, 8),
    "teammap_ego_mix": (
        {
            "map": "MIX",
            "n_agents": 2,
            "max_steps": 30,
            "observation": {"teammap": {"crop": 7, "global_size": 6, "ego_size": 5}},
        },
        4,
        9,
    ),
    "step_pocket_3": (
        {
            "n_agents": 3,
            "height": 13,
            "width": 13,
            "max_steps": 40,
            "observation": {"teammap": {"crop": 7, "global_size": 6}},
            "frontier": {"action": "step", "planner": "pocket"},
        },
        2,
        10,
    ),
    "step_plain_2": (
        {
            "n_agents": 2,
            "height": 11,
            "width": 12,
            "max_steps": 40,
            "observation": {"teammap": {"crop": 7, "global_size": 6}},
            "frontier": {"action": "step"},
        },
        2,
        11,
    ),
    "teammap_ego_agent_id_3": (
        {
            "n_agents": 3,
            "height": 16,
            "width": 12,
            "max_steps": 30,
            "agent_id": True,
            "observation": {
                "teammap": {"crop": 9, "global_size": 7, "ego_size": 7, "ego_block": 3}
            },
            "frontier": {"action": "step", "planner": "pocket"},
        },
        2,
        13,
    ),
    "goal_2": (
        {
            "n_agents": 2,
            "height": 14,
            "width": 14,
            "max_steps": 40,
            "observation": {"teammap": {"crop": 7, "global_size": 6}},
            "frontier": {"action": {"goal": {"k": 4}}, "planner": "pocket"},
        },
        2,
        12,
    ),
}
for _name in ("order", "utility", "minpos", "hungarian"):
    CASES[f"step_{_name}_4"] = (
        {
            "n_agents": 4,
            "height": 12,
            "width": 12,
            "max_steps": 30,
            "observation": {"teammap": {"crop": 7, "global_size": 6}},
            "frontier": {"action": "step", "planner": _name},
        },
        2,
        20 + len(_name),
    )


def make(kwargs: dict[str, Any]) -> Any:
    """The env of a case (``"MIX"`` stands for a small map mix)."""
    kwargs = dict(kwargs)
    if kwargs.get("map") == "MIX":
        kwargs["map"] = generators.MixGenerator(_MIX)
    return coverage_v0.parallel_env(**kwargs)


def _feed(h: Any, value: Any) -> None:
    if isinstance(value, dict):
        for key in sorted(value, key=str):
            h.update(str(key).encode())
            item = value[key]
            if key == "action_mask" and isinstance(item, np.ndarray):
                # Recorded when the goal action's mask was float32; the env gives PettingZoo's
                # int8 since, with the same values, which the digest still holds to.
                item = item.astype(np.float32)
            _feed(h, item)
    elif isinstance(value, np.ndarray):
        h.update(str(value.dtype).encode() + str(value.shape).encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, (bool, np.bool_)):
        h.update(b"T" if value else b"F")
    elif isinstance(value, (float, np.floating)):
        h.update(np.float64(value).tobytes())
    elif isinstance(value, (int, np.integer)):
        h.update(str(int(value)).encode())
    else:
        h.update(repr(value).encode())


def digest(kwargs: dict[str, Any], episodes: int, seed: int) -> str:
    """SHA-256 of ``episodes`` seeded episodes of the case under seeded random actions."""
    env = make(kwargs)
    actions = np.random.default_rng(seed + 1000)
    h = hashlib.sha256()
    n = env.action_space("agent_0").n
    for episode in range(episodes):
        obs, infos = env.reset(seed=seed if episode == 0 else None)
        _feed(h, obs)
        _feed(h, infos)
        while env.agents:
            acts = {a: int(actions.integers(n)) for a in env.agents}
            out = env.step(acts)
            for part in out:
                _feed(h, part)
        _feed(h, env.credited_by)
    return h.hexdigest()


def main(argv: list[str]) -> None:
    found = {name: digest(*case) for name, case in CASES.items()}
    if "--write" in argv:
        PATH.write_text(json.dumps(found, indent=1, sort_keys=True) + "\n")
    print(json.dumps(found, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
