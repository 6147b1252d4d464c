"""Floors for lifelong operation: load them from a grid map or a JSON plan, build the warehouses.

A *floor* is a :class:`~sim.world.World` with pickup points (at the shelf faces), drop-off
stations and optionally a depot where the AGVs start. Three sources:

* :func:`load_floor` reads a MovingAI ``.map`` grid map of the MAPF benchmarks with the Kiva
  letters of the lifelong MAPF literature (``e`` a pickup endpoint, ``r`` a station), or a JSON
  floor plan in world units (the format :func:`save_floor_json` writes).
* :func:`warehouse_floor` builds the procedural floors of the ``warehouse-20``,
  ``warehouse-50`` and ``warehouse-100`` scenarios.
* :func:`check_reachable` refuses a floor whose pickups, stations or depot are cut off from one
  another by shelves; both of the above call it.

Grid maps
---------
The header is ``type <word>``, ``height H`` and ``width W`` (either order), ``map``; then H rows
of W characters. ``@ T O W`` are blocked, ``. G S`` free, ``e`` a free cell holding a pickup
point, ``r`` a free cell holding a station. Row 0 is the top of the map; the world's y axis
points up, so row ``i`` covers ``y in [(H - 1 - i) c, (H - i) c]`` for the cell size ``c``, and
the world's bounds are ``(0, 0, W c, H c)``. Pickups and stations sit at the centres of their
cells. The blocked cells become few axis-aligned shelves (:func:`grid_rectangles`).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from sim.io import atomic_write_text
from sim.world import World

__all__ = ["load_floor", "save_floor_json", "warehouse_floor", "check_reachable",
           "unreachable_points", "grid_rectangles"]

BLOCKED = "@TOW"
"""Grid-map characters of blocked cells (out of bounds, trees, water)."""
FREE = ".GS"
"""Grid-map characters of free cells."""
PICKUP = "e"
"""Kiva letter: a free cell with a pickup endpoint."""
STATION = "r"
"""Kiva letter: a free cell with a drop-off station."""

_JSON_REQUIRED = ("bounds", "pickups", "stations")
_JSON_OPTIONAL = ("shelves", "depot", "agent_radius", "capture_radius")
_DEFAULT_RADIUS = 0.15
_DEFAULT_CELL = 1.0
_MAX_RASTER_CELLS = 16_000_000


# ---------------------------------------------------------------------- blocked cells
def grid_rectangles(blocked: np.ndarray, cell_size: float = 1.0) -> np.ndarray:
    """Cover the blocked cells of a grid exactly with few disjoint axis-aligned rectangles.

    The method: each row is cut into its maximal runs of blocked cells; a run continues the
    rectangle of the row above when that rectangle has exactly the same columns, otherwise it
    starts a new one. The rectangles are disjoint and their union is the set of blocked cells;
    a solid block of cells becomes one rectangle. (Not the fewest rectangles in general, which
    is a harder problem, but few on shelf layouts.)

    Parameters
    ----------
    blocked : np.ndarray of bool, shape (H, W)
        ``blocked[i, j]``: cell of row ``i`` (row 0 at the top) and column ``j``.
    cell_size : float
        Side of a square cell in world units.

    Returns
    -------
    np.ndarray, shape (K, 4)
        Rectangles ``(xmin, ymin, xmax, ymax)`` in world coordinates, with the world's y axis
        pointing up: row ``i`` covers ``y in [(H - 1 - i) cell_size, (H - i) cell_size]``.
        Ordered by their top row, then their left column.

    Raises
    ------
    ValueError
        For an array that is not two-dimensional and boolean, or a cell size that is not a
        positive finite number.
    """
    grid = np.asarray(blocked)
    if grid.ndim != 2 or grid.dtype != np.bool_:
        raise ValueError(f"blocked must be an (H, W) bool array, got {grid.dtype} of shape "
                         f"{grid.shape}")
    cell = _positive(cell_size, "cell_size")
    H, W = grid.shape
    padded = np.zeros((H, W + 2), dtype=np.int8)
    padded[:, 1:-1] = grid
    edges = np.diff(padded, axis=1)  # +1 where a run starts, -1 one past where it ends
    starts_r, starts_c = np.nonzero(edges == 1)
    _, ends_c = np.nonzero(edges == -1)  # same row-major order as the starts
    done: list[tuple[int, int, int, int]] = []  # (top row, bottom row, col0, col1)
    open_: dict[tuple[int, int], int] = {}  # (col0, col1) -> top row, for rectangles still open
    row_of_run = np.split(np.stack([starts_c, ends_c], axis=1),
                          np.searchsorted(starts_r, np.arange(1, H)))
    for i, runs in enumerate(row_of_run):
        current = {(int(a), int(b)) for a, b in runs}
        for key in [k for k in open_ if k not in current]:
            done.append((open_.pop(key), i - 1, *key))
        for key in current:
            open_.setdefault(key, i)
    done.extend((top, H - 1, *key) for key, top in open_.items())
    done.sort(key=lambda rect: (rect[0], rect[2]))  # top row, then left column
    if not done:
        return np.zeros((0, 4), dtype=np.float64)
    top, bottom, c0, c1 = np.array(done, dtype=np.float64).T
    return np.stack([c0 * cell, (H - 1 - bottom) * cell, c1 * cell, (H - top) * cell], axis=1)


# ---------------------------------------------------------------------- reachability
def _free_raster(world: World, resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells where a slightly shrunk AGV disc fits, on a grid of cells at most ``resolution``.

    Returns ``(free (H, W) bool, x (W,) cell centres, y (H,) cell centres)``, row 0 at the
    bottom. The clearance is the AGV radius less the half-diagonal of a cell, so the cell
    holding any point where a full AGV disc fits is free, and so are the cells a path of such
    points passes through (edge-adjacent ones: a path over a cell corner passes within a
    half-diagonal of a side cell's centre).
    """
    xmin, ymin, xmax, ymax = world.bounds
    nx = max(1, math.ceil((xmax - xmin) / resolution - 1e-9))
    ny = max(1, math.ceil((ymax - ymin) / resolution - 1e-9))
    if nx * ny > _MAX_RASTER_CELLS:
        raise ValueError(
            f"the reachability check at resolution {resolution:g} needs {ny} x {nx} cells on "
            f"this {xmax - xmin:g} x {ymax - ymin:g} floor, more than {_MAX_RASTER_CELLS}; "
            "pass a coarser resolution (at most half the AGV radius)"
        )
    dx, dy = (xmax - xmin) / nx, (ymax - ymin) / ny
    x = xmin + (np.arange(nx) + 0.5) * dx
    y = ymin + (np.arange(ny) + 0.5) * dy
    c = world.agent_radius - 0.5 * math.hypot(dx, dy) - 1e-9
    free = np.ones((ny, nx), dtype=bool)
    free[:, (x - xmin < c) | (xmax - x < c)] = False
    free[(y - ymin < c) | (ymax - y < c), :] = False
    for x0, y0, x1, y1 in world.obstacles:
        # The cells whose centres lie within c of this shelf; only its neighbourhood is looked at.
        i0, i1 = np.searchsorted(x, [x0 - c, x1 + c])
        j0, j1 = np.searchsorted(y, [y0 - c, y1 + c])
        if i0 >= i1 or j0 >= j1:
            continue
        gx = np.maximum(np.maximum(x0 - x[i0:i1], x[i0:i1] - x1), 0.0)
        gy = np.maximum(np.maximum(y0 - y[j0:j1], y[j0:j1] - y1), 0.0)
        free[j0:j1, i0:i1] &= gy[:, None] ** 2 + gx[None, :] ** 2 >= c * c
    return free, x, y


def _floor_points(world: World) -> list[tuple[str, np.ndarray]]:
    """The named points that must reach one another: pickups, stations, depot centres."""
    depot = world.depot
    centres = np.stack([(depot[:, 0] + depot[:, 2]) / 2, (depot[:, 1] + depot[:, 3]) / 2], 1)
    return [("pickups", world.pickups), ("stations", world.stations), ("depot", centres)]


def _check_one_component(named: list[tuple[str, np.ndarray, np.ndarray]]) -> None:
    """Raise unless every point's component label is the same (label 0: a blocked cell).

    ``named`` holds ``(field, points (K, 2), labels (K,))``. The main component is the one with
    the most points (ties: the lowest label); the message names every point outside it.
    """
    labels = np.concatenate([lab for _, _, lab in named])
    if labels.size == 0:
        return
    counted = labels[labels > 0]
    main = int(np.bincount(counted).argmax()) if counted.size else -1
    if np.all(labels == main):
        return
    parts, total_off = [], 0
    for field_name, points, lab in named:
        off = np.flatnonzero(lab != main)
        total_off += off.size
        for k in off[:6]:
            parts.append(f"{field_name}[{int(k)}] at ({points[k, 0]:.6g}, {points[k, 1]:.6g})")
        if off.size > 6:
            parts.append(f"{off.size - 6} more {field_name}")
    raise ValueError(
        f"{total_off} of {labels.size} floor points cannot be reached from the others (shelves "
        f"or walls cut them off): {', '.join(parts)}; every pickup, station and depot must lie "
        "in one connected free area"
    )


def check_reachable(world: World, resolution: float | None = None) -> None:
    """Check that an AGV can drive between every pickup, station and depot of a floor.

    The floor is rasterised at ``resolution``; a cell is free where an AGV disc (shrunk by the
    cell's half-diagonal) clears the walls and shelves, the free cells are labelled into
    4-connected components (:func:`scipy.ndimage.label`) and every pickup, station and depot
    rectangle must lie in the component holding the most of them. No connection an AGV can
    drive is ever missed; a gap narrower than an AGV diameter by less than a cell diagonal
    (0.35 radius at the default resolution, 0.71 at the coarsest) may count as passable.

    Parameters
    ----------
    world : World
        A floor (a world without pickups, stations or depot passes trivially).
    resolution : float, optional
        Cell side of the raster, at most half the AGV radius; default a quarter of the AGV
        radius (coarser on very large floors, never above half the radius).

    Raises
    ------
    ValueError
        Naming (field, index and coordinates) every point cut off from the main component; for
        a resolution above half the AGV radius, or a floor too large to rasterise at it.
    """
    resolution = _resolution(world, resolution)
    named_points = _floor_points(world)
    if not any(len(p) for _, p in named_points):
        return
    labels, cell_of = _labelled(world, resolution)
    _check_one_component([(name, points, labels[cell_of(points)])
                          for name, points in named_points])


def _resolution(world: World, resolution: float | None) -> float:
    """The checked raster resolution of :func:`check_reachable` (its default when None)."""
    if not isinstance(world, World):
        raise ValueError(f"world must be a sim.World, got {type(world).__name__}")
    r = world.agent_radius
    if resolution is None:
        width, height = world.size
        resolution = max(r / 4, math.sqrt(width * height / (_MAX_RASTER_CELLS / 4)))
        resolution = min(resolution, r / 2)
    resolution = _positive(resolution, "resolution")
    if resolution > r / 2 + 1e-12:
        raise ValueError(f"resolution must be at most half the AGV radius ({r / 2:g}), got "
                         f"{resolution:g}")
    return resolution


def _labelled(world: World, resolution: float | None) -> tuple[np.ndarray, Any]:
    """The 4-connected components of the floor's free raster, and a function from points
    (K, 2) to their cells' (row, col) index arrays."""
    resolution = _resolution(world, resolution)
    free, x, y = _free_raster(world, resolution)
    labels, _ = ndimage.label(free)  # 4-connected by default
    xmin, ymin, xmax, ymax = world.bounds
    dx, dy = (xmax - xmin) / len(x), (ymax - ymin) / len(y)

    def cell_of(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        col = np.clip(np.floor((points[:, 0] - xmin) / dx).astype(np.int64), 0, len(x) - 1)
        row = np.clip(np.floor((points[:, 1] - ymin) / dy).astype(np.int64), 0, len(y) - 1)
        return row, col

    return labels, cell_of


def unreachable_points(world: World, points: np.ndarray,
                       resolution: float | None = None) -> np.ndarray:
    """Indices of the points an AGV cannot reach from the floor's main free area.

    The main area is the 4-connected free component (as in :func:`check_reachable`) holding
    the most of the floor's own pickups, stations and depot, or, on a floor without them, the
    most of ``points``.

    Parameters
    ----------
    world : World
    points : np.ndarray, shape (K, 2)
    resolution : float, optional
        As in :func:`check_reachable`.

    Returns
    -------
    np.ndarray of int64, shape (U,)
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not len(pts):
        return np.zeros(0, dtype=np.int64)
    labels, cell_of = _labelled(world, resolution)
    own = np.concatenate([p for _, p in _floor_points(world)])
    ref = labels[cell_of(own)] if len(own) else labels[cell_of(pts)]
    counted = ref[ref > 0]
    main = int(np.bincount(counted).argmax()) if counted.size else -1
    return np.flatnonzero(labels[cell_of(pts)] != main).astype(np.int64)


# ---------------------------------------------------------------------- loading
def load_floor(path: str | os.PathLike[str], cell_size: float | None = None,
               agent_radius: float | None = None) -> World:
    """Load a floor from a MovingAI ``.map`` grid map or a JSON floor plan.

    Parameters
    ----------
    path : str or path-like
        ``*.map`` is read as a grid map, ``*.json`` as a floor plan; any other name by its
        content (a first line ``type ...``, or a JSON object).
    cell_size : float, optional
        Side of a grid cell in world units (default 1.0); at least one AGV diameter. Grid maps
        only: a JSON plan is already in world units, and passing it one is an error.
    agent_radius : float, optional
        AGV radius; default 0.15, or a JSON plan's own ``agent_radius`` (giving both, different,
        is an error).

    Returns
    -------
    World
        Bounds, shelves (``obstacles``), ``pickups`` (P, 2), ``stations`` (S, 2) and ``depot``
        (D, 4, grid maps: empty, so anywhere free). Every pickup, station and depot is
        reachable from every other (:func:`check_reachable`).

    Raises
    ------
    FileNotFoundError
        For a path that does not exist (the message names it).
    ValueError
        For anything else wrong with the file, each naming the line, row or field: a directory,
        an unknown format, a bad header or size, ragged rows, too few or too many rows, an
        unknown character, bad JSON, missing or unknown keys, wrong shapes, non-finite numbers,
        empty shelves, points outside the bounds or on a shelf, no pickups or no stations,
        points cut off by shelves, or a cell too small for an AGV.

    Examples
    --------
    >>> world = load_floor("kiva.map", cell_size=0.8)          # doctest: +SKIP
    >>> world.pickups.shape, world.stations.shape               # doctest: +SKIP
    ((P, 2), (S, 2))
    """
    source = os.fspath(path)
    file = Path(source)
    if file.is_dir():
        raise ValueError(f"floor path {source!r} is a directory, expected a .map or .json file")
    try:
        text = file.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise FileNotFoundError(f"floor file {source!r} does not exist") from None
    except UnicodeDecodeError:
        raise ValueError(f"floor file {source!r} is not a UTF-8 text file") from None
    suffix = file.suffix.lower()
    stripped = text.lstrip()
    if suffix == ".map" or (suffix != ".json" and stripped[:4].lower() == "type"):
        kind = "map"
    elif suffix == ".json" or stripped.startswith("{"):
        kind = "json"
    else:
        raise ValueError(
            f"floor file {source!r}: cannot tell its format; expected a MovingAI grid map "
            "(named .map, first line 'type octile') or a JSON floor plan (named .json, an object "
            "with 'bounds', 'shelves', 'pickups', 'stations')"
        )
    try:
        if kind == "map":
            return _load_map(text, cell_size, agent_radius)
        if cell_size is not None:
            raise ValueError("cell_size applies to grid maps (.map) only; a JSON floor plan is "
                             "in world units")
        return _load_json(text, agent_radius)
    except ValueError as err:
        raise ValueError(f"floor file {source!r}: {err}") from None


def _positive(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    number = float(value)
    if not (math.isfinite(number) and number > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return number


def _map_header(lines: list[str]) -> tuple[int, int]:
    """``(height, width)`` from the four header lines; errors name the line."""
    if not lines or not lines[0].strip():
        raise ValueError("line 1: expected the header 'type octile', got an empty line")
    first = lines[0].split()
    if first[0].lower() != "type" or len(first) != 2:
        hint = " (it looks like JSON; name it .json)" if lines[0].lstrip().startswith("{") else ""
        raise ValueError(f"line 1: expected the header 'type octile', got {lines[0]!r}{hint}")
    size: dict[str, int] = {}
    for number in (2, 3):
        line = lines[number - 1] if len(lines) >= number else ""
        words = line.split()
        if len(words) != 2 or words[0].lower() not in ("height", "width"):
            raise ValueError(f"line {number}: expected 'height H' or 'width W', got {line!r}")
        key, value = words[0].lower(), words[1]
        if key in size:
            raise ValueError(f"line {number}: {key} given twice")
        if not value.isdigit() or int(value) < 1:
            raise ValueError(f"line {number}: {key} must be a positive integer, got {value!r}")
        size[key] = int(value)
    line = lines[3] if len(lines) >= 4 else ""
    if line.strip().lower() != "map":
        raise ValueError(f"line 4: expected 'map' (the grid follows it), got {line!r}")
    return size["height"], size["width"]


def _load_map(text: str, cell_size: float | None, agent_radius: float | None) -> World:
    cell = _DEFAULT_CELL if cell_size is None else _positive(cell_size, "cell_size")
    r = _DEFAULT_RADIUS if agent_radius is None else _positive(agent_radius, "agent_radius")
    if 2 * r > cell + 1e-12:
        raise ValueError(f"cell_size {cell:g} is too small for an AGV of radius {r:g}: a cell "
                         f"must hold an AGV disc, so cell_size >= {2 * r:g}")
    lines = text.splitlines()
    height, width = _map_header(lines)
    rows = lines[4:]
    while rows and not rows[-1].strip():
        rows.pop()
    if len(rows) != height:
        many = "many" if len(rows) > height else "few"
        raise ValueError(f"too {many} rows: the grid has {len(rows)} rows after 'map' (lines 5 "
                         f"to {4 + len(rows)}), expected height {height}")
    for k, row in enumerate(rows):
        if len(row) != width:
            raise ValueError(f"line {5 + k} (grid row {k}) has {len(row)} characters, expected "
                             f"width {width}")
    grid = np.array([list(row) for row in rows], dtype="<U1").reshape(height, width)
    known = np.isin(grid, list(BLOCKED + FREE + PICKUP + STATION))
    if not known.all():
        k, j = (int(v) for v in np.argwhere(~known)[0])
        raise ValueError(f"line {5 + k}, column {j + 1}: unknown character {str(grid[k, j])!r}; "
                         f"expected blocked {' '.join(BLOCKED)}, free {' '.join(FREE)}, "
                         f"'{PICKUP}' (pickup) or '{STATION}' (station)")
    blocked = np.isin(grid, list(BLOCKED))

    def centres(letter: str) -> tuple[np.ndarray, np.ndarray]:
        i, j = np.nonzero(grid == letter)  # row-major: top row first
        return np.stack([(j + 0.5) * cell, (height - 1 - i + 0.5) * cell], axis=1), i * width + j

    pickups, pickup_cells = centres(PICKUP)
    stations, station_cells = centres(STATION)
    for letter, points, what in ((PICKUP, pickups, "pickup endpoints"),
                                 (STATION, stations, "stations")):
        if not len(points):
            raise ValueError(f"the map has no {what} (letter '{letter}'); a lifelong floor "
                             "needs pickups ('e') and stations ('r')")
    world = World(bounds=(0.0, 0.0, width * cell, height * cell),
                  obstacles=grid_rectangles(blocked, cell), agent_radius=r,
                  pickups=pickups, stations=stations)
    # On a grid of cells at least one AGV wide the cells' 4-neighbourhood is exact: an AGV
    # passes between two free cells exactly when they share a side.
    labels = ndimage.label(~blocked)[0].ravel()
    _check_one_component([("pickups", pickups, labels[pickup_cells]),
                          ("stations", stations, labels[station_cells])])
    return world


def _json_number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{where} must be a finite number, got {value!r}")
    return number


def _json_rows(data: dict[str, Any], key: str, width: int, what: str) -> np.ndarray:
    value = data.get(key, [])
    if not isinstance(value, list):
        raise ValueError(f"{key!r} must be a list of {what}, got {type(value).__name__}")
    rows = []
    for k, row in enumerate(value):
        if not isinstance(row, list) or len(row) != width:
            raise ValueError(f"{key}[{k}] must be {what}, got {row!r}")
        rows.append([_json_number(v, f"{key}[{k}][{i}]") for i, v in enumerate(row)])
    return np.array(rows, dtype=np.float64).reshape(-1, width)


def _load_json(text: str, agent_radius: float | None) -> World:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        hint = (" (it looks like a grid map; name it .map)"
                if text.lstrip()[:4].lower() == "type" else "")
        raise ValueError(f"not valid JSON: {err.msg} at line {err.lineno}, column {err.colno}"
                         f"{hint}") from None
    if not isinstance(data, dict):
        raise ValueError(f"a floor plan is a JSON object with the keys {list(_JSON_REQUIRED)} "
                         f"(and optionally {list(_JSON_OPTIONAL)}), got a {type(data).__name__}")
    missing = [k for k in _JSON_REQUIRED if k not in data]
    if missing:
        raise ValueError(f"missing key(s) {missing}; a floor plan needs {list(_JSON_REQUIRED)} "
                         f"and may have {list(_JSON_OPTIONAL)}")
    unknown = sorted(set(data) - set(_JSON_REQUIRED) - set(_JSON_OPTIONAL))
    if unknown:
        raise ValueError(f"unknown key(s) {unknown}; expected {list(_JSON_REQUIRED)} and "
                         f"optionally {list(_JSON_OPTIONAL)}")
    bounds = data["bounds"]
    if not isinstance(bounds, list) or len(bounds) != 4:
        raise ValueError(f"'bounds' must be [xmin, ymin, xmax, ymax], got {bounds!r}")
    box = tuple(_json_number(v, f"bounds[{i}]") for i, v in enumerate(bounds))
    rect = "[xmin, ymin, xmax, ymax]"
    shelves = _json_rows(data, "shelves", 4, rect)
    depot = _json_rows(data, "depot", 4, rect)
    for key, rects in (("shelves", shelves), ("depot", depot)):
        for k, (x0, y0, x1, y1) in enumerate(rects):
            if x1 <= x0 or y1 <= y0:
                axis = "xmax <= xmin" if x1 <= x0 else "ymax <= ymin"
                raise ValueError(f"{key}[{k}] = {rects[k].tolist()} has {axis}; a rectangle is "
                                 f"{rect} with xmax > xmin and ymax > ymin")
    points = {key: _json_rows(data, key, 2, "[x, y]") for key in ("pickups", "stations")}
    for key, pts in points.items():
        if not len(pts):
            raise ValueError(f"{key!r} is empty; a lifelong floor needs pickups and stations")
    options: dict[str, float] = {}
    if "capture_radius" in data:
        options["capture_radius"] = _json_number(data["capture_radius"], "capture_radius")
    r = _DEFAULT_RADIUS if agent_radius is None else _positive(agent_radius, "agent_radius")
    if "agent_radius" in data:
        own = _json_number(data["agent_radius"], "agent_radius")
        if agent_radius is not None and own != r:
            raise ValueError(f"agent_radius={r:g} was given, but the plan says agent_radius "
                             f"{own:g}; give one of them")
        r = own
    world = World(bounds=box, obstacles=shelves, agent_radius=r, pickups=points["pickups"],
                  stations=points["stations"], depot=depot, **options)
    check_reachable(world)
    return world


def save_floor_json(world: World, path: str | os.PathLike[str]) -> Path:
    """Write a floor as a JSON floor plan that :func:`load_floor` reads back unchanged.

    The plan holds the bounds, shelves, pickups, stations, depot, AGV radius and capture
    radius, every number written exactly (Python's shortest round-trip form). The physics
    constants and ``walls`` are not part of a floor plan. The file is written atomically
    (:func:`sim.io.atomic_write_text`).

    Parameters
    ----------
    world : World
        A floor: it has pickups and stations (``world.is_floor``).
    path : str or path-like
        Destination; its parent folders are created.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        For something that is not a World, or a world without pickups or stations (which
        :func:`load_floor` would refuse).
    """
    if not isinstance(world, World):
        raise ValueError(f"world must be a sim.World, got {type(world).__name__}")
    if not world.is_floor:
        raise ValueError(f"world has {len(world.pickups)} pickups and {len(world.stations)} "
                         "stations; a floor plan needs both (load_floor refuses one without)")

    def rows(arr: np.ndarray) -> str:
        if not len(arr):
            return "[]"
        return "[\n" + ",\n".join("    " + json.dumps([float(v) for v in row])
                                  for row in arr) + "\n  ]"

    fields = [
        f'"bounds": {json.dumps([float(v) for v in world.bounds])}',
        f'"shelves": {rows(world.obstacles)}',
        f'"pickups": {rows(world.pickups)}',
        f'"stations": {rows(world.stations)}',
        f'"depot": {rows(world.depot)}',
        f'"agent_radius": {json.dumps(float(world.agent_radius))}',
        f'"capture_radius": {json.dumps(float(world.capture_radius))}',
    ]
    return atomic_write_text(path, "{\n  " + ",\n  ".join(fields) + "\n}\n")


# ---------------------------------------------------------------------- the warehouses
# Lengths for an AGV of radius 0.15; a larger AGV scales the whole floor with it.
_SHELF_LENGTH = 1.2   # one shelf, along x; shelves stand side by side in blocks of k
_SHELF_DEPTH = 0.6
_AISLE = 0.8          # between shelf rows and along the walls: two AGVs wide and more
_CROSS_AISLE = 0.8    # between blocks, and between the station zone and the first blocks
_PICK_PITCH = 0.6     # pickups along a long face, the first half a pitch from its end
_STATION_PITCH = 0.8  # station columns and the stations in them
_MAX_BLOCK = 6        # shelves per block at most


def _warehouse_layout(n: int, r: float) -> dict[str, float]:
    """The rows, block columns and block length of the smallest floor that serves n AGVs.

    Every candidate with R shelf rows, C block columns and k shelves per block is sized
    (station columns as many as the station count needs, the depot as tall as its area
    needs); the feasible ones (at least 2n pickups, max(4, n // 5) stations) with a width to
    height ratio in [1.15, 1.4] are ranked by area, then by closeness of the ratio to 1.25.
    """
    s = max(1.0, r / _DEFAULT_RADIUS)
    need_stations = max(4, n // 5)
    top = 3 + math.isqrt(n)
    R, C, k = np.meshgrid(np.arange(1, top + 1), np.arange(1, top // 2 + 3),
                          np.arange(1, _MAX_BLOCK + 1), indexing="ij")
    R, C, k = R.ravel(), C.ravel(), k.ravel()
    shelf_height = _AISLE + R * (_SHELF_DEPTH + _AISLE)
    blocks_width = _CROSS_AISLE + C * (k * _SHELF_LENGTH + _CROSS_AISLE)
    best: tuple[Any, ...] | None = None
    for columns in range(1, need_stations + 1):  # station columns: the fewest that hold them
        width = s * (columns * _STATION_PITCH + blocks_width)
        depot_width = s * blocks_width
        depot = np.maximum(0.6 * s, np.ceil(4 * n * (2 * r) ** 2 / depot_width / (0.1 * s)
                                            - 1e-9) * 0.1 * s)
        height = depot + s * shelf_height
        per_column = np.floor((height - _STATION_PITCH * s) / (_STATION_PITCH * s) + 1e-9) + 1
        fits = (columns * per_column >= need_stations) & (4 * R * C * k >= 2 * n)
        if columns > 1:
            fits &= (columns - 1) * per_column < need_stations
        if not fits.any():
            continue
        ratio = width / height
        in_band = (ratio >= 1.15) & (ratio <= 1.4)
        key = np.stack([~in_band, np.round(width * height, 6), np.abs(ratio - 1.25)], axis=1)
        key = np.where(fits[:, None], key, np.inf)
        pick = int(np.lexsort(key.T[::-1])[0])
        cand = (tuple(key[pick]), dict(rows=int(R[pick]), block_columns=int(C[pick]),
                                       block=int(k[pick]), station_columns=columns,
                                       depot=float(depot[pick]), scale=s))
        if best is None or cand[0] < best[0]:
            best = cand
    assert best is not None  # at most n // 5 columns of stations always fit, with 2n pickups
    return best[1]


def warehouse_floor(num_agents: int, agent_radius: float = 0.15) -> World:
    """The procedural floor of the ``warehouse-<N>`` lifelong scenarios (deterministic).

    Shelf blocks (``k`` shelves of 1.2 x 0.6 side by side, one rectangle per block) stand in
    rows with aisles of 0.8 between the rows and along the walls, and cross aisles of 0.8
    between the blocks, so every aisle connects to every other. Pickups sit on both long faces
    of every block, ``agent_radius + 0.05`` out into the aisle, every 0.6 along the face.
    Drop-off stations stand in columns along the left wall (0.8 apart, the fewest columns that
    hold ``max(4, N // 5)``), with a cross aisle between them and the shelves. The depot is a
    strip along the bottom wall, right of the station zone, with at least ``4 N (2 r)^2`` of
    area. The numbers of rows, block columns and shelves per block are the smallest floor
    (ratio of width to height about 1.25) with at least ``2 N`` pickups. Lengths are for
    ``agent_radius`` 0.15; a larger AGV scales the floor with it.

    Parameters
    ----------
    num_agents : int
        N, the number of AGVs the floor is sized for (``warehouse-20``: 20).
    agent_radius : float
        AGV radius.

    Returns
    -------
    World
        Bounds ``(0, 0, width, height)``; ``obstacles`` (blocks, K x 4, bottom row first),
        ``pickups`` (P, 2, bottom to top, then left to right), ``stations`` (S, 2, by column
        from the wall, bottom to top), ``depot`` (1, 4).

    Raises
    ------
    ValueError
        For ``num_agents`` that is not an int >= 1, or a bad ``agent_radius``.
    """
    if isinstance(num_agents, bool) or not isinstance(num_agents, (int, np.integer)) \
            or num_agents < 1:
        raise ValueError(f"num_agents must be an int >= 1, got {num_agents!r}")
    n = int(num_agents)
    r = _positive(agent_radius, "agent_radius")
    plan = _warehouse_layout(n, r)
    s = plan["scale"]
    rows, columns, k = plan["rows"], plan["block_columns"], plan["block"]
    zone = plan["station_columns"] * _STATION_PITCH * s
    depot_height = plan["depot"]
    length, depth = k * _SHELF_LENGTH * s, _SHELF_DEPTH * s
    aisle, cross = _AISLE * s, _CROSS_AISLE * s
    width = zone + cross + columns * (length + cross)
    height = depot_height + aisle + rows * (depth + aisle)

    # Blocks: (rows, columns) of rectangles, bottom row first.
    x0 = zone + cross + np.arange(columns) * (length + cross)  # (C,)
    y0 = depot_height + aisle + np.arange(rows) * (depth + aisle)  # (R,)
    X0, Y0 = np.meshgrid(x0, y0)  # (R, C)
    shelves = np.stack([X0, Y0, X0 + length, Y0 + depth], axis=-1).reshape(-1, 4)

    # Pickups: both long faces of every block, every pitch along the face.
    offset = r + 0.05 * s
    along = (np.arange(2 * k) + 0.5) * _PICK_PITCH * s  # (2k,) from the block's left end
    px = (shelves[:, None, 0] + along[None, :]).ravel()  # (K * 2k,)
    below = np.repeat(shelves[:, 1] - offset, 2 * k)
    above = np.repeat(shelves[:, 3] + offset, 2 * k)
    pickups = np.concatenate([np.stack([px, below], 1), np.stack([px, above], 1)])
    order = np.lexsort((pickups[:, 0], pickups[:, 1]))  # bottom to top, left to right
    pickups = pickups[order]

    # Stations: columns along the left wall, from the bottom to the top.
    pitch = _STATION_PITCH * s
    per_column = int(math.floor((height - pitch) / pitch + 1e-9)) + 1
    sx = (np.arange(plan["station_columns"]) + 0.5) * pitch
    sy = (np.arange(per_column) + 0.5) * pitch
    SX, SY = np.meshgrid(sx, sy)
    stations = np.stack([SX.ravel(), SY.ravel()], axis=1)

    depot = np.array([[zone, 0.0, width, depot_height]])
    world = World(bounds=(0.0, 0.0, width, height), obstacles=shelves, agent_radius=r,
                  pickups=pickups, stations=stations, depot=depot)
    check_reachable(world)
    return world
