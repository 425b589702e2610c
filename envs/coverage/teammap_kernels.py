"""Compiled pieces of the team-map observation (:class:`envs.coverage.observations.
TeamMapObservation`): the update of the team's knowledge, the frontier field and compass, and
the ego view. The last two were the two largest costs of a team-map step in Python (a profile
of ``harness eval --policy frontier_step`` on ``teammap_2agents_pocket``: 32 % and 25 % of the
time).

Arrays are the builder's: ``cat`` the category of every cell of the padded grid, flat
(``KNOWN_WALL, VISITED, KNOWN_FREE, UNKNOWN`` = 0..3), ``wp`` the padded width.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from envs.coverage.types import CELL_UNVISITED, CELL_WALL

_KNOWN_WALL, _VISITED, _KNOWN_FREE, _UNKNOWN = 0, 1, 2, 3
_WALL = np.float32(CELL_WALL)
_UNVISITED = np.float32(CELL_UNVISITED)
#: Categories in the order of the ego view's share channels (visited, known free, unknown, wall).
_SHARE_ORDER = np.array([1, 2, 3, 0], dtype=np.int64)


@njit(cache=True, nogil=True)
def frontier_views(
    free: np.ndarray,
    cat: np.ndarray,
    wp: int,
    pad: int,
    positions: np.ndarray,
    scale: float,
    field: np.ndarray,
    compass: np.ndarray,
) -> None:
    """The frontier field ``(agents, crop, crop)`` uint8 and compass ``(agents, 5)`` float32
    (zeroed by the caller) of every agent.

    ``d`` is the length of a shortest path through ``free`` cells (flat, padded) to the
    nearest known free cell not yet visited: one multi-source breadth-first search from every
    such cell, then unknown cells set to infinity (they show nothing). Going through unknown
    cells never shortens a path (see the builder's docstring), so this is the search through
    known cells. Compass: the moves (up, down, left, right) that lower ``d`` by one, then
    ``min(d(agent) * scale, 1)`` (1 when no frontier is reachable). Field: a cell of the crop
    whose ``d`` and the agent's are finite is ``clip(128 + 16 * (d(agent) - d(cell)), 1, 255)``,
    others 0.
    """
    n_cells = cat.shape[0]
    n, crop = field.shape[0], field.shape[1]
    for i in range(n):
        compass[i, 4] = 1.0
    dist = np.full(n_cells, np.inf)
    queue = np.empty(n_cells, dtype=np.int64)
    tail = 0
    for k in range(n_cells):
        if cat[k] == _KNOWN_FREE:
            dist[k] = 0.0
            queue[tail] = k
            tail += 1
    if tail == 0:  # every known free cell is visited: no frontier left
        return
    moves = np.array([-wp, wp, -1, 1], dtype=np.int64)
    # Only the known free cells of the agents' crops are read: the search stops once all of
    # them have their distance (a breadth-first search never changes a distance it has set).
    needed = np.zeros(n_cells, dtype=np.bool_)
    remaining = 0
    for i in range(n):
        r, c = positions[i, 0], positions[i, 1]
        for a in range(crop):
            base = (r + a) * wp + c
            for b in range(crop):
                k = base + b
                if free[k] and cat[k] != _UNKNOWN and not needed[k]:
                    needed[k] = True
                    if dist[k] == np.inf:  # not a frontier cell itself
                        remaining += 1
    head = 0
    while head < tail and remaining > 0:
        u = queue[head]
        head += 1
        d = dist[u] + 1.0
        for m in moves:
            v = u + m
            if free[v] and dist[v] == np.inf:
                dist[v] = d
                queue[tail] = v
                tail += 1
                if needed[v]:
                    remaining -= 1
    for k in range(n_cells):
        if cat[k] == _UNKNOWN:
            dist[k] = np.inf
    for i in range(n):
        r, c = positions[i, 0], positions[i, 1]
        centre = (r + pad) * wp + (c + pad)
        own = dist[centre]
        for j in range(4):
            compass[i, j] = 1.0 if own - dist[centre + moves[j]] == 1.0 else 0.0
        compass[i, 4] = min(own * scale, 1.0)
        if own == np.inf:
            continue
        # Padded rows r .. r + crop - 1 are the crop centred on grid row r.
        for a in range(crop):
            base = (r + a) * wp + c
            for b in range(crop):
                value = dist[base + b]
                if value != np.inf:
                    field[i, a, b] = np.uint8(min(max(128.0 + 16.0 * (own - value), 1.0), 255.0))


@njit(cache=True, nogil=True)
def ego_views(
    cat: np.ndarray,
    wp: int,
    pad: int,
    height: int,
    width: int,
    positions: np.ndarray,
    edges: np.ndarray,
    block: int,
    ego: np.ndarray,
) -> None:
    """The ego views ``(agents, 5, E, E)`` uint8 (zeroed by the caller): E x E blocks of
    ``block`` x ``block`` cells around each agent (block k spans rows ``r + edges[k]`` ..
    ``r + edges[k + 1] - 1``), channels ``rint(255 * share)`` of the block's cells visited, known
    free not visited, unknown and known wall (the part outside the grid counts as wall), then the
    teammates' blocks (255)."""
    n, e = positions.shape[0], ego.shape[2]
    area = block * block
    factor = 255 / area
    counts = np.zeros(4, dtype=np.int64)
    for i in range(n):
        r, c = positions[i, 0], positions[i, 1]
        for bi in range(e):
            r0 = min(max(r + edges[bi], 0), height)
            r1 = min(max(r + edges[bi + 1], 0), height)
            for bj in range(e):
                c0 = min(max(c + edges[bj], 0), width)
                c1 = min(max(c + edges[bj + 1], 0), width)
                counts[:] = 0
                for rr in range(r0, r1):
                    base = (rr + pad) * wp + pad
                    for cc in range(c0, c1):
                        counts[cat[base + cc]] += 1
                counts[_KNOWN_WALL] += area - (r1 - r0) * (c1 - c0)
                for ch in range(4):
                    ego[i, ch, bi, bj] = np.uint8(np.rint(counts[_SHARE_ORDER[ch]] * factor))
        half, mid = block // 2, e // 2
        for j in range(n):
            if j != i:
                br = (positions[j, 0] - r + half) // block + mid
                bc = (positions[j, 1] - c + half) // block + mid
                if 0 <= br < e and 0 <= bc < e:
                    ego[i, 4, br, bc] = 255


@njit(cache=True, nogil=True)
def update_known(
    cells: np.ndarray,
    pad: int,
    positions: np.ndarray,
    cat: np.ndarray,
    planes: np.ndarray,
    counts: np.ndarray,
    block_of: np.ndarray,
    block_cells: np.ndarray,
    shares: np.ndarray,
) -> None:
    """Make the agents' 3x3 windows known: each cell of a window whose category changed (from
    ``cells`` ``(Hp, Wp)``: wall, unvisited free, visited) gets its new category in ``cat`` and
    in the 0/255 ``planes`` ``(4, Hp * Wp)``, moves between the category counts of its global
    block (``counts`` ``(G * G, 4)``), and the block's share channels ``shares`` ``(4, G * G)``
    become ``rint(255 * count / cells of the block)`` again."""
    wp = cells.shape[1]
    for i in range(positions.shape[0]):
        r, c = positions[i, 0] + pad, positions[i, 1] + pad
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                value = cells[r + dr, c + dc]
                if value == _WALL:
                    new = _KNOWN_WALL
                elif value == _UNVISITED:
                    new = _KNOWN_FREE
                else:
                    new = _VISITED
                k = (r + dr) * wp + (c + dc)
                old = cat[k]
                if old == new:
                    continue
                cat[k] = new
                planes[old, k] = 0
                planes[new, k] = 255
                b = block_of[k]
                if b < 0:  # the padding: outside every block
                    continue
                counts[b, old] -= 1
                counts[b, new] += 1
                n = max(block_cells[b], 1)
                for ch in range(4):
                    shares[ch, b] = np.uint8(np.rint(255.0 * (counts[b, _SHARE_ORDER[ch]] / n)))


@njit(cache=True, nogil=True)
def crop_and_block_views(
    planes: np.ndarray,
    wp: int,
    positions: np.ndarray,
    crop: int,
    shares: np.ndarray,
    row_block: np.ndarray,
    col_block: np.ndarray,
    g: int,
    local: np.ndarray,
    glob: np.ndarray,
) -> None:
    """The local crops' first five channels and the global view of every agent of one copy.

    ``local`` ``(agents, >= 5, crop, crop)``: the four category planes of the crop centred on
    the agent (``planes`` ``(4, cells)``, the padded grid flat; the padded grid's rows ``r ..
    r + crop`` are the crop centred on grid row ``r``), then the teammates in the crop (255).
    ``glob`` ``(agents, 6, blocks)``, all zero: the four share channels (``shares``), the agent's
    own block, then the blocks of its teammates (an agent's own block only when a teammate
    shares it); ``g`` blocks a side.
    """
    n = positions.shape[0]
    half = crop // 2
    for i in range(n):
        r, c = positions[i, 0], positions[i, 1]
        for ch in range(4):
            for y in range(crop):
                base = (r + y) * wp + c
                for x in range(crop):
                    local[i, ch, y, x] = planes[ch, base + x]
        local[i, 4] = 0
        for j in range(n):
            dr, dc = positions[j, 0] - r + half, positions[j, 1] - c + half
            if j != i and 0 <= dr < crop and 0 <= dc < crop:
                local[i, 4, dr, dc] = 255
    blocks = shares.shape[1]
    own = np.empty(n, dtype=np.int64)
    count = np.zeros(blocks, dtype=np.int64)
    for i in range(n):
        own[i] = row_block[positions[i, 0]] * g + col_block[positions[i, 1]]
        count[own[i]] += 1
    for i in range(n):
        glob[i, :4] = shares
        glob[i, 4, own[i]] = 255
        for j in range(n):
            if j != i or count[own[i]] > 1:
                glob[i, 5, own[j]] = 255
