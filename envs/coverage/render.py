"""Rendering of the coverage environment: ``rgb_array`` images and ``ansi`` text."""

from __future__ import annotations

import numpy as np

#: Okabe-Ito palette: colours that readers with colour-vision deficiencies can tell apart.
AGENT_COLOURS = np.array(
    [
        [230, 159, 0],  # orange
        [86, 180, 233],  # sky blue
        [0, 158, 115],  # bluish green
        [204, 121, 167],  # reddish purple
        [0, 114, 178],  # blue
        [213, 94, 0],  # vermillion
        [240, 228, 66],  # yellow
        [120, 120, 120],  # grey
    ],
    dtype=np.uint8,
)
WALL_COLOUR = np.array([45, 45, 45], dtype=np.uint8)
FREE_COLOUR = np.array([240, 240, 240], dtype=np.uint8)
#: How far a visited cell's tint goes from white towards its agent's colour.
TINT = 0.45
#: Colour of a cell visited by agent ``i`` (row ``i % 8``): its colour tinted towards white.
VISITED_COLOURS = (255 * (1 - TINT) + AGENT_COLOURS.astype(np.float64) * TINT).astype(np.uint8)
CELL_PIXELS = 8


def agent_colour(i: int) -> np.ndarray:
    """RGB colour of agent ``i`` (the palette repeats after eight agents)."""
    return AGENT_COLOURS[i % len(AGENT_COLOURS)]


def cell_image(walls: np.ndarray, credited_by: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """One pixel per cell: walls dark, unvisited free light, visited cells tinted with the colour
    of the agent credited with them, agents in their full colour."""
    img = np.empty((*walls.shape, 3), dtype=np.uint8)
    img[:] = FREE_COLOUR
    img[walls] = WALL_COLOUR
    visited = credited_by >= 0
    img[visited] = VISITED_COLOURS[credited_by[visited] % len(AGENT_COLOURS)]
    for i, (r, c) in enumerate(positions.tolist()):
        img[r, c] = agent_colour(i)
    return img


def rgb_array(
    walls: np.ndarray, credited_by: np.ndarray, positions: np.ndarray, scale: int = CELL_PIXELS
) -> np.ndarray:
    """The map as an ``(H*scale, W*scale, 3)`` uint8 image."""
    img = cell_image(walls, credited_by, positions)
    return np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)


def ansi(walls: np.ndarray, visited: np.ndarray, positions: np.ndarray) -> str:
    """Text picture: ``#`` wall, ``.`` unvisited free, space visited, agents as 0-9 then a-z."""
    chars = np.where(walls, "#", np.where(visited, " ", ".")).astype("<U1")
    symbols = "0123456789abcdefghijklmnopqrstuvwxyz"
    # Draw higher indices first so the lowest index shows when agents share a cell.
    for i in range(len(positions) - 1, -1, -1):
        r, c = positions[i]
        chars[r, c] = symbols[i % len(symbols)]
    return "\n".join("".join(row) for row in chars)
