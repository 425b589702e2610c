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
    dist: np.ndarray,
    queue: np.ndarray,
    needed: np.ndarray,
    field: np.ndarray,
    compass: np.ndarray,
) -> None:
    """The frontier field ``(agents, crop, crop)`` uint8 and compass ``(agents, 5)`` float32
    (zeroed by the caller) of every agent.

    ``d`` is the length of a shortest path through ``free`` cells (flat, padded) to the
    nearest known free cell not yet visited: one multi-source breadth-first search from every
    such cell; unknown cells show nothing (their ``d`` counts as infinite). Going through
    unknown cells never shortens a path (see the builder's docstring), so this is the search
    through known cells. Compass: the moves (up, down, left, right) that lower ``d`` by one,
    then ``min(d(agent) * scale, 1)`` (1 when no frontier is reachable). Field: a cell of the
    crop whose ``d`` and the agent's are finite is ``clip(128 + 16 * (d(agent) - d(cell)), 1,
    255)``, others 0. ``dist``, ``queue`` (float64, int64) and ``needed`` (bool, all False) are
    scratch arrays of the grid's size, ``needed`` left all False again.
    """
    n_cells = cat.shape[0]
    n, crop = field.shape[0], field.shape[1]
    for i in range(n):
        compass[i, 4] = 1.0
    tail = 0
    # "Free and not yet reached", one byte per cell: the search tests it alone (as
    # envs.coverage.paths.breadth_first does, on unsigned indices;
    # research/performance-history.md, "The searches' inner loop").
    unseen = np.empty(n_cells, dtype=np.bool_)
    for k in range(n_cells):
        source = cat[k] == _KNOWN_FREE
        unseen[k] = free[k] and not source
        if source:
            dist[k] = 0.0
            queue[tail] = k
            tail += 1
        else:
            dist[k] = np.inf
    if tail == 0:  # every known free cell is visited: no frontier left
        return
    moves = np.array([-wp, wp, -1, 1], dtype=np.int64)
    # Only the known free cells of the agents' crops are read: the search stops once all of
    # them have their distance (a breadth-first search never changes a distance it has set).
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
    head, end = np.uint64(0), np.uint64(tail)
    down, right = np.uint64(wp), np.uint64(1)
    while head < end and remaining > 0:
        u = np.uint64(queue[head])
        head += right
        d = dist[u] + 1.0
        for v in (u - down, u + down, u - right, u + right):  # the order of ``moves``
            if unseen[v]:
                unseen[v] = False
                dist[v] = d
                queue[end] = v
                end += right
                if needed[v]:
                    remaining -= 1
    for i in range(n):
        r, c = positions[i, 0], positions[i, 1]
        for a in range(crop):  # leave the scratch array clean for the next call
            base = (r + a) * wp + c
            for b in range(crop):
                needed[base + b] = False
        centre = (r + pad) * wp + (c + pad)
        own = dist[centre]  # the agent's cell is visited: never unknown
        for j in range(4):
            v = centre + moves[j]
            near = dist[v] if cat[v] != _UNKNOWN else np.inf
            compass[i, j] = 1.0 if own - near == 1.0 else 0.0
        compass[i, 4] = min(own * scale, 1.0)
        if own == np.inf:
            continue
        # Padded rows r .. r + crop - 1 are the crop centred on grid row r.
        for a in range(crop):
            base = (r + a) * wp + c
            for b in range(crop):
                k = base + b
                value = dist[k]
                if value != np.inf and cat[k] != _UNKNOWN:
                    field[i, a, b] = np.uint8(min(max(128.0 + 16.0 * (own - value), 1.0), 255.0))


def ego_counts(height: int, width: int, block: int) -> np.ndarray:
    """The ego view's block counts at the start of an episode: ``(4, height + 2 * h, width +
    2 * h)`` uint8 with ``h = block // 2``, entry ``[category, h + R, h + C]`` the cells of
    each category (:data:`_KNOWN_WALL` .. :data:`_UNKNOWN`) in the ``block`` x ``block`` window
    centred on cell ``(R, C)``, for every centre whose window reaches the grid (a window that
    does not is all wall). Outside the grid counts as known wall, every cell inside is unknown;
    :func:`update_known` keeps the counts as cells become known."""
    half = block // 2
    # Interior indicator with 2 * half cells of outside around the map, summed over every
    # block x block window (a summed-area table).
    m = 2 * half
    inside = np.zeros((height + 2 * m, width + 2 * m), dtype=np.int64)
    inside[m : m + height, m : m + width] = 1
    table = np.zeros((inside.shape[0] + 1, inside.shape[1] + 1), dtype=np.int64)
    table[1:, 1:] = inside.cumsum(0).cumsum(1)
    unknown = (
        table[block:, block:] - table[:-block, block:] - table[block:, :-block]
        + table[:-block, :-block]
    )  # fmt: skip
    counts = np.zeros((4, *unknown.shape), dtype=np.uint8)
    counts[_UNKNOWN] = unknown
    counts[_KNOWN_WALL] = block * block - unknown
    return counts


@njit(cache=True, nogil=True)
def ego_views(counts: np.ndarray, positions: np.ndarray, block: int, ego: np.ndarray) -> None:
    """The ego views ``(agents, 5, E, E)`` uint8 (zeroed by the caller): E x E blocks of
    ``block`` x ``block`` cells around each agent (block ``(bi, bj)`` centred on the agent's
    cell moved by ``(bi - E // 2, bj - E // 2)`` blocks), channels ``rint(255 * share)`` of the
    block's cells visited, known free not visited, unknown and known wall (the part outside the
    grid counts as wall), then the teammates' blocks (255). A block's shares are one read of
    the ``counts`` kept by :func:`update_known` (:func:`ego_counts`), or all wall for a block
    wholly outside the grid."""
    n, e = positions.shape[0], ego.shape[2]
    mid, half = e // 2, block // 2
    rows, cols = counts.shape[1], counts.shape[2]
    factor = 255 / (block * block)
    for i in range(n):
        r, c = positions[i, 0], positions[i, 1]
        for bi in range(e):
            row = r + (bi - mid) * block + half
            for bj in range(e):
                col = c + (bj - mid) * block + half
                if 0 <= row < rows and 0 <= col < cols:
                    for ch in range(4):
                        ego[i, ch, bi, bj] = np.uint8(
                            np.rint(counts[_SHARE_ORDER[ch], row, col] * factor)
                        )
                else:
                    ego[i, 3, bi, bj] = 255  # channel 3 is the wall share
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
    ego: np.ndarray,
    ego_block: int,
) -> None:
    """Make the agents' 3x3 windows known: each cell of a window whose category changed (from
    ``cells`` ``(Hp, Wp)``: wall, unvisited free, visited) gets its new category in ``cat`` and
    in the 0/255 ``planes`` ``(4, Hp * Wp)``, moves between the category counts of its global
    block (``counts`` ``(G * G, 4)``), and the block's share channels ``shares`` ``(4, G * G)``
    become ``rint(255 * count / cells of the block)`` again. With the ego view, the cell also
    moves between the counts of the ego blocks around it (``ego``, :func:`ego_counts`; an
    empty array without the view)."""
    wp = cells.shape[1]
    with_ego = ego.shape[1] > 0
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
                if with_ego:  # every ego block centre within half a block of the cell
                    row0 = r + dr - pad  # its grid row: centres row0 - half .. row0 + half
                    col0 = c + dc - pad
                    for rr in range(row0, row0 + ego_block):
                        for cc in range(col0, col0 + ego_block):
                            ego[old, rr, cc] -= 1
                            ego[new, rr, cc] += 1


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


@njit(cache=True, nogil=True)
def teammap_views(
    cells: np.ndarray,
    pad: int,
    positions: np.ndarray,
    time: float,
    cat: np.ndarray,
    planes: np.ndarray,
    counts: np.ndarray,
    block_of: np.ndarray,
    block_cells: np.ndarray,
    shares: np.ndarray,
    row_block: np.ndarray,
    col_block: np.ndarray,
    g: int,
    scale: np.ndarray,
    free: np.ndarray,
    frontier_scale: float,
    dist: np.ndarray,
    queue: np.ndarray,
    needed: np.ndarray,
    ego_counts: np.ndarray,
    ego_block: int,
    local: np.ndarray,
    glob: np.ndarray,
    ego: np.ndarray,
    vector: np.ndarray,
    compass: np.ndarray,
) -> None:
    """One step of the team-map observation of one copy, in one call: :func:`update_known`,
    then every agent's views into the zeroed outputs: ``local`` ``(agents, channels, crop,
    crop)`` and ``glob`` ``(agents, 6, G * G)`` (:func:`crop_and_block_views`), the frontier
    field (``local``'s last channel) and ``compass`` when ``free`` is not empty
    (:func:`frontier_views`), ``ego`` when ``ego_counts`` is not empty (:func:`ego_views`), and
    ``vector`` ``(agents, 3)``: row and column times ``scale``, then ``time``."""
    update_known(
        cells, pad, positions, cat, planes, counts, block_of, block_cells, shares,
        ego_counts, ego_block,
    )  # fmt: skip
    wp, crop = cells.shape[1], local.shape[2]
    crop_and_block_views(planes, wp, positions, crop, shares, row_block, col_block, g, local, glob)
    if free.shape[0] > 0:
        frontier_views(
            free, cat, wp, pad, positions, frontier_scale, dist, queue, needed,
            local[:, local.shape[1] - 1], compass,
        )  # fmt: skip
    if ego_counts.shape[1] > 0:
        ego_views(ego_counts, positions, ego_block, ego)
    for i in range(positions.shape[0]):
        vector[i, 0] = positions[i, 0] * scale[0]
        vector[i, 1] = positions[i, 1] * scale[1]
        vector[i, 2] = time
