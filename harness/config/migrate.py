"""Configs written before the redesign still load: their renamed keys are moved to where they
live now, and their retired keys dropped, here and nowhere else.

Renamed (``env``): ``crop``, ``global_size``, ``ego_size``, ``ego_block`` became the options of
the team-map observation (``observation: {teammap: {crop: 15, ...}}``); ``frontier: true`` with
``frontier_action``, ``frontier_claims`` and ``frontier_tie_break`` became one option of the
planner extension (``frontier: {action: step, planner: pocket}``).

Retired (research/experiment-log.md says what each measured and which commit had it): ``env.trail``,
``eval.step_bonus``, ``algo.imitation.same_moves``, ``algo.action_mask``, ``prior.augment``,
``env.frontier.action.goal.gather``, ``algo.teacher.horizon`` and ``gain`` (the teacher's
rollouts go to the episode's end, any gain counts). A file that leaves
them at their old defaults (as every saved ``config.yaml`` does) loads; a file that turns one on
is refused, naming the key, since what it asked for no longer exists.
"""

from __future__ import annotations

import copy
from typing import Any

#: Team-map options that were keys of ``env``, with their old defaults.
TEAMMAP_KEYS = {"crop": 15, "global_size": 13, "ego_size": 0, "ego_block": 5}
#: Keys of the planner extension's old flags.
FRONTIER_FLAGS = ("frontier_action", "frontier_claims", "frontier_tie_break")
#: Retired keys and the value they may still have (their old default, a no-op).
RETIRED = {
    ("env", "trail"): 0,
    ("eval", "step_bonus"): None,
    ("algo", "action_mask"): False,
    ("algo", "imitation", "same_moves"): False,
    ("env", "frontier", "action", "goal", "gather"): "clusters",
    ("algo", "teacher", "horizon"): None,
    ("algo", "teacher", "gain"): 0.0,
    ("prior", "augment"): True,  # mirrored partial maps, always (research/README.md)
}


class MigrationError(ValueError):
    """An old config asks for a retired knob."""


def migrate(raw: dict[str, Any]) -> dict[str, Any]:
    """A config mapping in today's layout (a new dict; ``raw`` is not changed). Today's files
    pass through unchanged.

    Raises:
        MigrationError: naming the key, when a retired knob is on.
    """
    data = copy.deepcopy(raw)
    for path, default in RETIRED.items():
        _drop_retired(data, path, default)
    env = data.get("env")
    if isinstance(env, dict):
        _migrate_observation(env)
        _migrate_frontier(env)
    return data


def _drop_retired(data: dict[str, Any], path: tuple[str, ...], default: Any) -> None:
    node: Any = data
    for key in path[:-1]:
        node = node.get(key) if isinstance(node, dict) else None
    if not isinstance(node, dict) or path[-1] not in node:
        return
    value = node.pop(path[-1])
    if value != default:
        raise MigrationError(
            f"{'.'.join(path)}: {value!r}: this knob was retired (no shipped result needed it); "
            "research/experiment-log.md says what it measured and which commit had it"
        )


def _migrate_observation(env: dict[str, Any]) -> None:
    old = {key: env.pop(key) for key in TEAMMAP_KEYS if key in env}
    if not old:
        return
    kind = env.get("observation", "thesis")
    if kind == "teammap":
        env["observation"] = {"teammap": old}
    elif kind == "thesis" and all(TEAMMAP_KEYS[key] == value for key, value in old.items()):
        return  # the team map's defaults written out by a thesis run: they did nothing
    else:
        raise MigrationError(
            f"env: {', '.join(old)} and env.observation {kind!r} cannot both be given; write "
            "env.observation: {teammap: {crop: ..., global_size: ...}}"
        )


def _migrate_frontier(env: dict[str, Any]) -> None:
    flags = {key: env.pop(key) for key in FRONTIER_FLAGS if key in env}
    if "frontier" not in env or not isinstance(env["frontier"], bool):
        if flags:
            raise MigrationError(
                f"env: {', '.join(flags)} are old keys: write env.frontier: "
                "{action: step, planner: order}"
            )
        return
    if not env.pop("frontier"):
        if flags.get("frontier_action") or flags.get("frontier_claims"):
            raise MigrationError("env.frontier_action and frontier_claims needed env.frontier")
        env["frontier"] = None
        return
    claims = bool(flags.get("frontier_claims", False))
    tie_break = flags.get("frontier_tie_break", "order")
    if tie_break != "order" and not claims:
        raise MigrationError("env.frontier_tie_break needed env.frontier_claims: true")
    env["frontier"] = {
        "action": "step" if flags.get("frontier_action", False) else None,
        "planner": tie_break if claims else None,
    }
