"""The seeded generator of office floors (the ``office`` map kind): a second style of floor plan.

Where :mod:`envs.coverage.rooms` cuts the floor at random into rooms of every size and shape, an
office floor is regular: straight hallways run the whole length of the floor, a row of rooms of
nearly equal width lines each side of each hallway, and some of the floor is open-plan space
with pillars. It exists so that what was learned on ``rooms`` plans (a map prior, a policy) can
be tried on floor plans of another look. There is no shipped office map. The plan is laid out
along the floor's longer side (a floor taller than it is wide is built on its side and turned,
a square one either way):

1. hallways: the fewest full-length hallways, 2 or 3 cells wide, that keep every row of rooms
   at most :data:`MAX_DEPTH` deep (two on a 50x100 floor, one on a 30x100 floor). Rooms lie between
   the outer wall and a hallway, or between two hallways: there as one row of rooms through from
   hallway to hallway or as two rows back to back behind a wall, whichever the depths allow
   (drawn at random when both do). The rows share the depth evenly, give or take a cell or two;
2. cross hallways: each pair of neighbouring hallways is joined by a short hallway across the
   rooms between them, at both ends (a ring), at one end (alternating: a U or an S) or near the
   middle (an H), one style per floor; a hallway beside the outer wall gets, with chance
   :data:`SIDE_HALL_CHANCE`, a side hallway through its rooms to the outer wall (a T, or a
   cross). The hallways are one connected piece;
3. open plan: stretches at one end of a row's segment (between cross hallways), about
   :data:`OPEN_SHARE` of the floor the rooms would take, become open-plan areas: one big room the
   whole depth between a hallway and the outer wall or the next hallway, with 1x1 or 2x2 pillars
   on a regular lattice (3 or 4 free cells apart and 2 or more from its walls, so none closes off
   floor) and 2-cell doors onto every hallway it lines, one per :data:`OPEN_DOOR_EVERY` cells;
4. rooms: the rest of each segment is split into rooms of one width drawn from :data:`ROOM_WIDTH`
   (the rooms of a segment differ by a cell at most; a little wider where no count of rooms
   fits the range in the segment's length) behind one-cell walls reaching to the outer
   wall or the next hallway. Each room gets exactly one door onto a hallway (1 cell, 2 with
   chance :data:`WIDE_DOOR_SHARE`, off the wall's ends), and neighbours in a row an inner door
   with chance :data:`INNER_DOOR_SHARE`. No furniture;
5. fill everything not connected to the largest free area (there is none by construction: every
   room and open area has a door onto the connected hallways; the step guards the promise that
   all free cells are connected).

The layout's numbers are the module's constants below, not parameters: the ``office`` kind
takes only a size (research/README.md, "The office generator's parameters", records the five
that were parameters until 2026-11-29).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envs.coverage.maps import fill_unreachable

#: ``(low, high)``: the range a row's room width is drawn from (a segment of a row shorter than
#: ``low`` is one narrower room; where no count of rooms fits the range in a segment, they are a
#: little wider than ``high``).
ROOM_WIDTH = (5, 9)
#: Most cells of a row of rooms across: the floor gets the fewest hallways that keep every row at
#: most this deep. At least twice :data:`MIN_DEPTH`, so some count of hallways always fits the
#: rows (checked for every floor up to 1,000 cells across by the tests).
MAX_DEPTH = 14
#: Chance that a room's door is 2 cells wide rather than 1.
WIDE_DOOR_SHARE = 0.2
#: Chance, per pair of neighbouring rooms in a row, of a 1-cell door between them.
INNER_DOOR_SHARE = 0.15
#: Share of the rooms' floor given to open-plan areas (about: an area is a stretch of a row's
#: segment, whole or at least :data:`_MIN_OPEN` long).
OPEN_SHARE = 0.2
#: Fewest cells of a row of rooms across (from its hallway's wall to the wall behind it).
MIN_DEPTH = 3
#: Fewest cells across the floor's shorter side: a 2-cell hallway between two rows of
#: :data:`MIN_DEPTH` behind walls, inside the border.
MIN_SIDE = 2 * MIN_DEPTH + 2 + 2 + 2
#: Chance that a hallway beside the outer wall gets a side hallway through its rooms to the wall.
SIDE_HALL_CHANCE = 1 / 3
#: Cells of an open-plan area's length per door onto each hallway it lines (at least one door).
OPEN_DOOR_EVERY = 12
#: Fewest cells of an open-plan area's length (a shorter stretch would be one more room).
_MIN_OPEN = 8

HALL, ROOM, OPEN = "hall", "room", "open"


@dataclass(frozen=True)
class Area:
    """A hallway, room or open-plan area: the free cells ``[top, bottom) x [left, right)``
    (an open area's pillars included).

    Attributes:
        kind: :data:`HALL`, :data:`ROOM` or :data:`OPEN`.
    """

    top: int
    left: int
    bottom: int
    right: int
    kind: str

    @property
    def cells(self) -> tuple[slice, slice]:
        """The area as an index into the map."""
        return slice(self.top, self.bottom), slice(self.left, self.right)

    @property
    def area(self) -> int:
        """Cells of floor (pillars included)."""
        return (self.bottom - self.top) * (self.right - self.left)

    def turned(self) -> Area:
        """The area on the map turned by a transpose."""
        return Area(self.left, self.top, self.right, self.bottom, self.kind)


@dataclass(frozen=True)
class OfficePlan:
    """An office floor and how it was built (the tests check the one against the other).

    Attributes:
        walls: Bool ``(height, width)`` grid, True = wall (pillars included).
        areas: The hallways, rooms and open-plan areas; a hallway and the cross hallway that
            meets it touch directly, every other pair is apart by a one-cell wall.
        doors: ``(area_a, area_b, cells)``: indices into ``areas`` (a room or open area first,
            then the hallway or the neighbouring room) and the wall cells opened between them.
        pillars: An open area's pillars as ``(top, left, bottom, right)``, ends exclusive.
    """

    walls: np.ndarray
    areas: tuple[Area, ...]
    doors: tuple[tuple[int, int, tuple[tuple[int, int], ...]], ...]
    pillars: tuple[tuple[int, int, int, int], ...]


@dataclass(frozen=True)
class _Band:
    """Rooms' rows ``[top, bottom)`` between the hallways ``above`` and ``below`` (indices, or
    ``None`` for the outer wall), with a back-to-back wall on row ``split`` or none."""

    top: int
    bottom: int
    above: int | None
    below: int | None
    split: int | None


def check_size(height: int, width: int) -> tuple[int, int]:
    """At least :data:`MIN_SIDE` cells each way.

    Raises:
        ValueError: Naming the least size.
    """
    if min(height, width) < MIN_SIDE:
        raise ValueError(
            f"an office floor needs at least {MIN_SIDE}x{MIN_SIDE} cells (a hallway with a row of "
            f"rooms each side), got {height}x{width}"
        )
    return int(height), int(width)


def generate_office(seed: int, height: int, width: int) -> np.ndarray:
    """Draw an office floor; returns a bool ``(height, width)`` grid, True = wall.

    Args:
        seed: Seed of the generator; the same seed gives the same floor.
        height: Rows (at least :data:`MIN_SIDE`: a hallway with a row of rooms each side).
        width: Columns (at least :data:`MIN_SIDE`).
    """
    return fill_unreachable(office_plan(seed, height, width).walls)


def office_plan(seed: int, height: int, width: int) -> OfficePlan:
    """The plan :func:`generate_office` draws (before its guard fills unreachable cells, of
    which there are none); same arguments."""
    height, width = check_size(height, width)
    rng = np.random.default_rng(seed)
    # Built with the hallways along the rows; a taller floor is built on its side.
    turned = height > width or (height == width and rng.random() < 0.5)
    rows, cols = (width, height) if turned else (height, width)
    halls, bands = _hallways(rng, rows)
    areas: list[Area] = [Area(top, 1, bottom, cols - 1, HALL) for top, bottom in halls]
    segments = _cross_hallways(rng, rows, cols, areas, bands)
    walls = np.ones((rows, cols), dtype=bool)
    doors: list[tuple[int, int, tuple[tuple[int, int], ...]]] = []
    pillars: list[tuple[int, int, int, int]] = []
    segments = _open_plan(rng, areas, bands, segments, doors, pillars)
    _rooms(rng, areas, bands, segments, doors)
    for area in areas:
        walls[area.cells] = False
    for _, _, cells in doors:
        walls[tuple(np.array(cells).T)] = False
    for top, left, bottom, right in pillars:
        walls[top:bottom, left:right] = True
    if turned:
        return OfficePlan(
            np.ascontiguousarray(walls.T),
            tuple(a.turned() for a in areas),
            tuple((a, b, tuple((c, r) for r, c in cells)) for a, b, cells in doors),
            tuple((left, top, right, bottom) for top, left, bottom, right in pillars),
        )
    return OfficePlan(walls, tuple(areas), tuple(doors), tuple(pillars))


def _hallways(rng: np.random.Generator, rows: int) -> tuple[list[tuple[int, int]], list[_Band]]:
    """Step 1: the full-length hallways' rows ``(top, bottom)`` and the bands of rooms."""
    inside = rows - 2
    drawn = rng.integers(2, 4, size=inside)  # the hallways' widths, if that many fit
    chosen = None
    for count in range(1, inside + 1):
        # The drawn widths first; all 2 cells when those leave the rows too little room.
        for widths in (drawn[:count], np.full(count, 2)):
            # A back-to-back wall per gap between hallways that is split in two rows.
            fits = []
            for back_to_back in range(count):
                depth = inside - int(widths.sum()) - 2 * count - back_to_back
                n_rows = count + 1 + back_to_back
                if n_rows * MIN_DEPTH <= depth <= n_rows * MAX_DEPTH:
                    fits.append(back_to_back)
            if fits:
                chosen = count, widths, fits
                break
        if chosen is not None:
            break
    if chosen is None:  # MAX_DEPTH >= 2 * MIN_DEPTH and MIN_SIDE rule this out (tests check it)
        raise AssertionError(f"no hallways fit {rows} rows with rows at most {MAX_DEPTH} deep")
    count, widths, fits = chosen
    back_to_back = int(rng.choice(fits))
    split = np.zeros(count - 1, dtype=bool)
    split[rng.permutation(count - 1)[:back_to_back]] = True
    n_rows = count + 1 + back_to_back
    depths = _share(rng, inside - int(widths.sum()) - 2 * count - back_to_back, n_rows, MAX_DEPTH)
    halls: list[tuple[int, int]] = []
    bands: list[_Band] = []
    row, d = 1, iter(depths)
    for i in range(count + 1):
        top = row
        if 0 < i < count and split[i - 1]:
            wall = top + next(d)
            row = wall + 1 + next(d)
        else:
            wall, row = None, top + next(d)
        bands.append(_Band(top, row, i - 1 if i else None, i if i < count else None, wall))
        if i < count:
            halls.append((row + 1, row + 1 + int(widths[i])))
            row += int(widths[i]) + 2
    assert row == rows - 1, (row, rows)  # the last band ends at the outer wall
    return halls, bands


def _share(rng: np.random.Generator, total: int, parts: int, most: int) -> list[int]:
    """``total`` cells split into ``parts`` depths in ``[MIN_DEPTH, most]``: evenly, with the
    odd cells and a few single-cell moves at random (rows alike but not all the same)."""
    depths = np.full(parts, total // parts)
    depths[rng.permutation(parts)[: total % parts]] += 1
    for _ in range(parts):
        give, take = rng.integers(parts, size=2)
        if depths[give] > MIN_DEPTH and depths[take] < most:
            depths[give] -= 1
            depths[take] += 1
    return [int(x) for x in depths]


def _cross_hallways(
    rng: np.random.Generator, rows: int, cols: int, areas: list[Area], bands: list[_Band]
) -> list[tuple[int, int, int]]:
    """Step 2: cross hallways between neighbouring hallways and side hallways to the outer wall
    (appended to ``areas``); returns the bands' segments ``(band, left, right)`` between them."""
    length = cols - 2
    style = ("ring", "end", "middle")[int(rng.integers(3))]
    cuts: list[list[tuple[int, int]]] = [[] for _ in bands]
    for b, band in enumerate(bands):
        wide = int(rng.integers(2, 4))
        if band.above is not None and band.below is not None:
            # Joins the two hallways: its rows reach from the one to the other, walls included.
            top, bottom = areas[band.above].bottom, areas[band.below].top
            if style == "ring":
                lefts = [1, cols - 1 - wide]
            elif style == "end":
                lefts = [1 if band.above % 2 else cols - 1 - wide]
            else:
                lefts = [int(rng.integers(length // 3, 2 * length // 3 - wide + 2))]
        elif rng.random() < SIDE_HALL_CHANCE:
            # From its hallway to the outer wall, somewhere in the middle half.
            hall = areas[band.below if band.below is not None else band.above]
            top, bottom = (1, hall.top) if band.below is not None else (hall.bottom, rows - 1)
            lefts = [int(rng.integers(length // 4, 3 * length // 4 - wide + 2))]
        else:
            continue
        for left in lefts:
            areas.append(Area(top, left, bottom, left + wide, HALL))
            cuts[b].append((left, left + wide))
    segments = []
    for b, band_cuts in enumerate(cuts):
        start = 1
        for left, right in sorted(band_cuts):
            if left - 1 > start:  # a wall column on each side of a cross hallway
                segments.append((b, start, left - 1))
            start = right + 1
        if cols - 1 > start:
            segments.append((b, start, cols - 1))
    return segments


def _open_plan(
    rng: np.random.Generator,
    areas: list[Area],
    bands: list[_Band],
    segments: list[tuple[int, int, int]],
    doors: list[tuple[int, int, tuple[tuple[int, int], ...]]],
    pillars: list[tuple[int, int, int, int]],
) -> list[tuple[int, int, int]]:
    """Step 3: open-plan areas at the ends of segments (appended to ``areas``, with their doors
    and pillars); returns the segments left for rooms."""
    depth = [band.bottom - band.top for band in bands]
    least_room = ROOM_WIDTH[0]
    left_over = OPEN_SHARE * sum(depth[b] * (right - left) for b, left, right in segments)
    kept = list(segments)
    for k in rng.permutation(len(segments)):
        if left_over <= 0:
            break
        b, left, right = segments[k]
        band, length = bands[b], right - left
        size = min(length, max(int(np.ceil(left_over / depth[b])), _MIN_OPEN))
        if length - size - 1 < least_room:  # what is left would not hold a room: take it all
            size = length
        left_over -= size * depth[b]
        kept.remove(segments[k])
        if rng.random() < 0.5:
            a0, a1 = left, left + size
            if size < length:
                kept.append((b, a1 + 1, right))
        else:
            a0, a1 = right - size, right
            if size < length:
                kept.append((b, left, a0 - 1))
        index = len(areas)
        areas.append(Area(band.top, a0, band.bottom, a1, OPEN))
        for hall, row in ((band.above, band.top - 1), (band.below, band.bottom)):
            if hall is None:
                continue
            n = max(1, size // OPEN_DOOR_EVERY)
            for j in range(n):
                centre = a0 + int((j + 0.5) * size / n)
                first = min(max(centre - 1, a0), a1 - 2) if size >= 2 else a0
                cells = tuple((row, c) for c in range(first, min(first + 2, a1)))
                doors.append((index, hall, cells))
        pillars.extend(_pillars(rng, areas[index]))
    kept.sort()
    return kept


def _pillars(rng: np.random.Generator, area: Area) -> list[tuple[int, int, int, int]]:
    """A centred lattice of 1x1 or 2x2 pillars, 3 or 4 free cells apart, 2 off the walls."""
    side = int(rng.integers(1, 3))
    gap = int(rng.integers(3, 5))
    pitch = side + gap
    blocks = []
    starts = []
    for low, high in ((area.top + 2, area.bottom - 2), (area.left + 2, area.right - 2)):
        room = high - low
        n = (room + gap) // pitch if room >= side else 0
        span = n * pitch - gap
        starts.append([low + (room - span) // 2 + i * pitch for i in range(n)])
    for r in starts[0]:
        for c in starts[1]:
            blocks.append((r, c, r + side, c + side))
    return blocks


def _rooms(
    rng: np.random.Generator,
    areas: list[Area],
    bands: list[_Band],
    segments: list[tuple[int, int, int]],
    doors: list[tuple[int, int, tuple[tuple[int, int], ...]]],
) -> None:
    """Step 4: rows of rooms on the segments (appended to ``areas``), each room with one door onto
    a hallway, neighbours with inner doors at random."""
    low, high = ROOM_WIDTH

    def door(cells: list[tuple[int, int]], size: int) -> tuple[tuple[int, int], ...]:
        n = len(cells)
        size = min(size, n)
        # Off the wall's ends when there is room: a doorway in a corner looks (and is) odd.
        first_low, first_high = (1, n - size - 1) if n >= size + 2 else (0, n - size)
        first = int(rng.integers(first_low, first_high + 1))
        return tuple(cells[first : first + size])

    for b, left, right in segments:
        band = bands[b]
        if band.split is None:
            facing = [h for h in (band.above, band.below) if h is not None]
            row_spans = [(band.top, band.bottom, facing)]
        else:
            row_spans = [
                (band.top, band.split, [band.above]),
                (band.split + 1, band.bottom, [band.below]),
            ]
        length = right - left
        for top, bottom, facing in row_spans:
            # As many rooms as a width drawn from the range asks, kept in the range where the
            # length allows; the cells the walls leave are shared out evenly. Where no count
            # fits the range, the most rooms no narrower than ``low``: a little wider instead.
            wanted = int(rng.integers(low, high + 1))
            fewest = -(-(length + 1) // (high + 1))
            most = (length + 1) // (low + 1)
            count = min(max(round((length + 1) / (wanted + 1)), fewest), most)
            count = max(count, 1)
            widths = np.full(count, (length - count + 1) // count)
            widths[rng.permutation(count)[: (length - count + 1) % count]] += 1
            start, previous = left, None
            for w in widths:
                index = len(areas)
                room = Area(top, start, bottom, start + int(w), ROOM)
                areas.append(room)
                hall = facing[int(rng.integers(len(facing)))]
                row = top - 1 if hall == band.above else bottom
                size = 2 if rng.random() < WIDE_DOOR_SHARE else 1
                side = [(row, c) for c in range(start, room.right)]
                doors.append((index, hall, door(side, size)))
                if previous is not None and rng.random() < INNER_DOOR_SHARE:
                    wall = [(r, start - 1) for r in range(top, bottom)]
                    doors.append((index, previous, door(wall, 1)))
                previous = index
                start = room.right + 1
            assert start == right + 1, (start, right)
