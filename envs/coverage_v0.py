"""Coverage: a team of agents explores and covers an unknown 2D grid map.

This is the environment of "Multi Agent Exploration with Reinforcement Learning" (2021), as a
PettingZoo ``ParallelEnv``.

.. code-block:: python

    from envs import coverage_v0

    env = coverage_v0.parallel_env(n_agents=4, max_steps=1000, render_mode="rgb_array")
    observations, infos = env.reset(seed=42)
    while env.agents:
        actions = {agent: env.action_space(agent).sample() for agent in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)
    print(infos["agent_0"]["coverage"])

========================  ==========================================================
Import                    ``from envs import coverage_v0``
Actions                   Discrete(5): 0 up, 1 down, 2 left, 3 right, 4 stay; Discrete(6)
                          with ``frontier={"action": "step"}`` (5: the frontier step)
Parallel API              yes (``parallel_env``); AEC through ``env()``
Agents                    ``agent_0 ... agent_{n-1}``
Observation shape         (13,) float32 (``observation="thesis"``); a ``Dict`` for
                          ``"teammap"``: ``local`` (5, crop, crop), ``global`` (6, G, G),
                          optional ``ego`` (5, E, E) uint8, ``vector`` (3,) float32
Observation values        thesis: window -1/0/1; coordinates [0, 1] or raw (row, col);
                          teammap: uint8 0..255 (255 = 1), vector in [0, 1]
========================  ==========================================================

**Map.** A grid of free cells and walls; outside the grid counts as wall. ``map="random"`` draws a
new map each reset: a wall share ``w ~ U(wall_fraction)``, ``round(w*H*W)`` walls on random cells,
then every free cell outside the largest 4-connected free area is filled, so all free ground is
reachable. ``map="cave_100x50"`` (or any shipped name, see :func:`envs.coverage.maps.shipped_maps`)
or a path to a text map (``#`` wall, ``.`` free, ``S`` start) fixes the map. ``map`` may also be
a map generator of :mod:`envs.coverage.generators` (``RandomMaps``, ``CaveMaps``, ``MazeMaps``,
``FileMap``, ``ShippedMap``, a weighted ``MixGenerator``), which draws each reset's map from the
env's random generator; its sizes may differ between resets (``env.height`` and ``env.width`` are
the current map's), and the observation space is made for the largest.

**Dynamics.** All agents act at once; moves are resolved in index order. A move into a wall or off
the grid leaves the agent in place and counts as a wall hit; ``stay`` never does. Agents may share
a cell. The team shares one visited map; start cells are visited at reset. An agent entering an
unvisited free cell is credited with it (the lower index wins a tie). There is no terminal state:
all agents are truncated after ``max_steps`` steps, and that step's infos hold
``"TimeLimit.truncated": True`` so Stable-Baselines3 treats it as a time-out.

**Observation** ``"thesis"``: the 3x3 window around the agent (row-major; -1 unvisited free,
0 visited free, 1 wall/outside), its own (row, col) and the (row, col) of its nearest teammate
(Euclidean, ties to the lower index; a lone agent sees itself). ``coords="normalized"`` divides by
(H-1, W-1); ``"raw"`` gives cell indices. New kinds plug in through
:data:`envs.coverage.observations.OBSERVATIONS`.

**Observation** ``"teammap"``: the team's knowledge as channel-first images, a gymnasium ``Dict``
per agent. A cell is *known* once it has been inside any agent's 3x3 window (start windows
included); outside the grid is known wall. Binary channels are 0 or 255.

* ``"local"`` ``Box(0, 255, (5, crop, crop), uint8)``: the ``crop`` x ``crop`` window centred on
  the agent; channels known wall (outside the grid too), visited, known free not yet visited,
  unknown, teammates present (other agents); with the planner extension (``frontier``) a sixth
  channel, the frontier field: with ``d`` the length of a shortest path
  through known free cells to the nearest known free cell not yet visited, a reachable known
  cell of the crop is ``clip(128 + 16 * (d(agent) - d(cell)), 1, 255)`` (brighter is nearer),
  other cells 0.
* ``"global"`` ``Box(0, 255, (6, G, G), uint8)`` with ``G = global_size``: the map cut into a
  G x G grid of blocks (block ``i`` holds rows ``floor(i*H/G) .. floor((i+1)*H/G) - 1``, likewise
  columns, so any size or aspect fits; a block with no cell, on a map smaller than G, counts as
  wall); channels ``round(255 * share)`` of the block's cells visited, known free not visited,
  unknown and known wall, then this agent's block and the teammates' blocks (255).
* ``"ego"`` ``Box(0, 255, (5, E, E), uint8)``, only when ``ego_size=E > 0``: a coarse map centred
  on the agent, E x E blocks of ``ego_block`` x ``ego_block`` cells (the centre block is centred on
  the agent's cell); channels the share of the block visited, known free not visited, unknown and
  known wall (outside the grid counts as wall), and teammates present (255). The same pattern
  means the same thing wherever the agent stands, unlike the absolute ``"global"`` view.
* ``"predicted_local"``, ``"predicted_global"``, ``"predicted_ego"`` ``Box(0, 255, (1, side,
  side), uint8)``, only with ``predicted: True`` and a map prior (``frontier={..., "prior": f}``):
  the prior's expected free floor on the cells nobody has seen, beside the view of the same side
  (each unseen cell ``round(255 * (1 - p_wall))``, other cells 0; a block, the share of its
  cells so expected), MapExRL's recipe (``envs/coverage/observations.py``).
* ``"vector"`` ``Box(0, 1, (3,), float32)``: own row/(H-1), own col/(W-1), steps/max_steps.
* ``"frontier"`` ``Box(0, 1, (5,), float32)``, only with ``frontier``: the frontier
  compass, 1 for each move (up, down, left, right) that takes the agent one step nearer the
  nearest known free unvisited cell, else 0, then ``d(agent) / (H + W)`` (at most 1; 1 when no
  such cell is reachable). When ``frontier`` names a planner the four moves mark instead that
  planner's move (``envs/coverage/frontier.py``: towards the nearest such cell that no
  lower-index teammate claimed this step; none when it would stay): ``"order"`` (the classical
  explorer's fixed neighbour order) or ``"pocket"`` (the cell with the fewest open neighbours).

The team map's options are passed as ``observation={"teammap": {"crop": 15, ...}}`` or
``observation=TeamMap(crop=15, ...)`` (``envs.coverage.observations.TeamMap``, which checks them):
``crop`` odd and >= 5 (>= 7 with the frontier field; default 15), ``global_size`` >= 6 (default
13), ``ego_size`` 0 (no ego view, the default) or odd and >= 5, ``ego_block`` odd (default 5),
``predicted`` (default false), each side at most 2,000: Stable-Baselines3 reads a uint8 image
as channel-first only when no side is smaller than its channel count. The local and
global images are updated incrementally (only the agents' new 3x3 windows), so they cost
O(agents * crop^2 + G^2) a step whatever the map's size; the ego view is pooled from one
summed-area table of the map per step.

**Agent indication** (``agent_id=True``, any observation kind): each agent's observation also
holds its one-hot index (Terry et al. 2020): ``n_agents`` floats appended to the thesis vector
(shape ``(13 + n_agents,)``), or an ``"agent_id"`` key ``Box(0, 1, (n_agents,), float32)`` in
the team map's ``Dict``. The harness sets it for ``algo.sharing: shared_id`` and ``per_agent``.

**Reward** (eq. 3.1): ``new_cell * n_new + wall_hit * hit + step``, by default
``2*new - 10*hit - 1``, per agent.

**Infos** (every step, per agent): ``coverage`` (team: visited / free cells), ``new_cells`` (cells
credited to this agent so far), ``wall_hits`` (this agent's count so far), ``steps``.

**Arguments** (all keywords): ``map="random"``, ``height=50``, ``width=50``,
``wall_fraction=(0.15, 0.20)``, ``n_agents=4``, ``max_steps=1000``, ``observation="thesis"``,
``coords="normalized"``, ``rewards={"new_cell": 2.0, "wall_hit": -10.0, "step": -1.0}``,
``starts=None`` (fixed start cells, else distinct random free cells each reset),
``render_mode=None | "rgb_array" | "ansi"``, ``frontier=None``, ``agent_id=False`` (13 in all).

**The planner extension** (``frontier``, needs the team map; one module owns it,
``envs/coverage/frontier.py``): ``None`` (off), or ``{"action": ..., "planner": ...}`` (or a
``FrontierOptions``). Any mapping adds the frontier field and compass. ``action="step"`` (an
entry of the registry ``ACTIONS``) adds a sixth action, 5, one step along the frontier compass,
i.e. the first move of a shortest path through known free cells to the nearest known free cell
not yet visited (drawn from the episode's generator when several moves tie; stay when no such
cell is reachable). It never hits a wall. ``planner`` (an entry of the registry ``PLANNERS``
that the env can follow: ``"order"`` or ``"pocket"``) makes the compass, so the step, that
planner's move for the agent: a team that always steps is the planner (``"pocket"``: the
``frontier_pocket`` baseline), and a learned policy chooses when to leave it. With the goal
action, ``"prior": f`` (a map prior: ``f(seen, free)`` of the team's ``(H, W)`` map gives each
cell's wall probability) adds two features to every candidate, the free cells ``f`` expects
behind it (``envs/coverage/goals.py``).

``reset(seed=None, options=None)``: ``options={"grid": bool_array, "starts": [(r, c), ...]}`` fixes
that episode's map and/or start cells. Bad input raises ``ValueError`` naming the problem.
``step(actions)`` takes a dict of every live agent to a Python or numpy integer of its action
space; anything else (a float, even ``2.0``, a bool, a string, ``None``, an array, a number out of
range) raises ``ValueError`` naming the agent, the value and the range, and steps nothing.

**The batched core.** The env is the batch-of-one view of
:class:`envs.coverage.core.CoverageCore`, which steps B copies of the episode in one compiled
call (``envs/coverage/step.py``); Stable-Baselines3's VecEnv over it is
``harness.training.adapters.CoreVecEnv``. ``env.core`` is the env's core;
``CoverageEnv.copy_of(core, b)`` is a read-only view of copy ``b`` of a larger one.

**State for baselines, rendering and tests** (read-only): ``env.walls``, ``env.visited``,
``env.known`` (the team's known cells, under any observation kind), ``env.positions``,
``env.credited_by``, ``env.free_cells``, ``env.coverage``, ``env.steps``.
"""

from __future__ import annotations

from typing import Any

from pettingzoo.utils import parallel_to_aec

from envs.coverage.env import CoverageEnv

__all__ = ["CoverageEnv", "env", "parallel_env", "raw_env"]


def parallel_env(**kwargs: Any) -> CoverageEnv:
    """Make the parallel environment (the form the harness trains on)."""
    return CoverageEnv(**kwargs)


def raw_env(**kwargs: Any):
    """Make the AEC form of the environment (agents act in turn)."""
    return parallel_to_aec(CoverageEnv(**kwargs))


env = raw_env
