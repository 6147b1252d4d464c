"""Obstacle-aware travel distances, paths and next waypoints at fleet scale.

One grid of the whole floor is built once per floor and shared by every query:

- The floor is rasterised into square cells of side ``resolution`` (default half the AGV radius,
  so that a one-AGV-wide gap between shelves holds at least three cell centres). A cell is free
  where an AGV disc centred on it clears every shelf and wall (:meth:`sim.World.is_free` at the
  cell centre, computed shelf by shelf on that shelf's neighbourhood only).
- Free cells are joined by moves to their 8 neighbours (a diagonal move only if both side cells
  are free) and, with ``connectivity=16`` (the default), by the 8 knight moves (2, 1) as well
  (only if the whole 2 x 3 box of cells is free). The 16-neighbourhood bounds the grid's
  overestimate of a straight run at 2.7% (8 neighbours: 8.2%).
- Distance fields (the grid distance from one cell to every cell) come from
  :func:`scipy.sparse.csgraph.dijkstra`. The fields of the floor's fixed points (its pickups and
  stations) are computed when the floor is first used and kept as one table; fields of other
  target cells are computed on demand and kept in a bounded cache.

A point is snapped to its nearest free cell (the nearest free cell of the cell holding it) and
joined to that cell's centre by a straight connector, whose length is added. Paths are read
from a distance field by steepest descent and string-pulled with an exact test of the disc
against every shelf (:func:`segments_clear`), so a smoothed segment never leaves free space.

Grid moves keep the disc off the shelves when every shelf is at least one cell thick in x and y
(true of :func:`sim.warehouse_floor` and of ``.map`` floors): at resolutions up to the AGV
radius a free cell clears by a small margin (``resolution ** 2 / (4 * agent_radius)``, 0.009
at the default), see ``_free_raster``; at coarser resolutions only when the shelves are aligned
with the cells, as on a ``.map`` floor at ``resolution=cell_size``.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse import csgraph

from sim.world import segments_clear

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["FloorDistances", "segments_clear", "floor_grid_cache_clear"]

_TOL = 1e-9
_MAX_CELLS = 16_000_000
"""Largest grid accepted (cells); a larger floor needs a coarser ``resolution``."""
_DEFAULT_TABLE_BYTES = 512 * 2**20
"""Memory for the fixed points' distance table; beyond it their fields are computed on demand."""
_DEFAULT_CACHE_BYTES = 256 * 2**20
"""Memory for the cache of on-demand distance fields."""

def table_fits(targets: int, free_cells: int, table_bytes: int) -> bool:
    """Whether ``targets`` float32 fields over ``free_cells`` cells fit in ``table_bytes``."""
    return targets * free_cells * 4 <= table_bytes


# Moves (drow, dcol), and for each the cells (drow, dcol) it crosses that must be free too.
_MOVES_8 = [((0, 1), ()), ((1, 0), ()), ((1, 1), ((0, 1), (1, 0))), ((1, -1), ((0, -1), (1, 0)))]
_MOVES_16 = _MOVES_8 + [  # a knight move needs its whole 2 x 3 box of cells free
    ((1, 2), ((0, 1), (0, 2), (1, 0), (1, 1))),
    ((2, 1), ((1, 0), (2, 0), (0, 1), (1, 1))),
    ((1, -2), ((0, -1), (0, -2), (1, 0), (1, -1))),
    ((2, -1), ((1, 0), (2, 0), (0, -1), (1, -1))),
]


def _symmetric(moves: list) -> list:
    """Each move and its reverse, with the crossed cells mirrored."""
    out = []
    for (di, dj), side in moves:
        out.append(((di, dj), side))
        out.append(((-di, -dj), tuple((-a, -b) for a, b in side)))
    return out


# segments_clear lives beside the floor it tests (sim.world), so that sim's planners use it
# too; it stays importable from here and from allocator.


# ---------------------------------------------------------------------- the grid
class _FloorGrid:
    """The free raster, graph and distance fields of one floor (shared through a cache)."""

    def __init__(self, world: World, resolution: float, connectivity: int,
                 table_bytes: int, cache_bytes: int) -> None:
        xmin, ymin, xmax, ymax = world.bounds
        nx = max(1, math.ceil((xmax - xmin) / resolution - 1e-9))
        ny = max(1, math.ceil((ymax - ymin) / resolution - 1e-9))
        if nx * ny > _MAX_CELLS:
            raise ValueError(
                f"resolution {resolution:g} needs {ny} x {nx} cells on this floor, more than "
                f"{_MAX_CELLS}; pass a coarser resolution"
            )
        self.world = world
        self.shape = (ny, nx)
        self.dx, self.dy = (xmax - xmin) / nx, (ymax - ymin) / ny
        self.x = xmin + (np.arange(nx) + 0.5) * self.dx
        self.y = ymin + (np.arange(ny) + 0.5) * self.dy
        self.free = self._free_raster()
        if not self.free.any():
            raise ValueError("the floor has no free cell for an AGV of this size; check the "
                             "shelves, the bounds and agent_radius")
        self.moves = _symmetric(_MOVES_16 if connectivity == 16 else _MOVES_8)
        self.graph = self._graph()
        # Nearest free cell (flat index) of every cell, by its centre.
        _, (ii, jj) = ndimage.distance_transform_edt(~self.free, sampling=(self.dy, self.dx),
                                                     return_indices=True)
        self.nearest_free = (ii.astype(np.int64) * nx + jj).ravel()
        self.cache_rows = max(1, cache_bytes // (8 * nx * ny))
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        fixed = np.concatenate([world.pickups, world.stations])
        self.fixed_cells = np.unique(self.snap(fixed)[0]) if len(fixed) else \
            np.zeros(0, np.int64)
        # The fixed points' fields, kept on the free cells only and in float32 (a relative
        # error under 6e-8), one row per free cell so that the fields at K AGV cells are K
        # contiguous rows: ``table[column[cell], row_of[target]]``.
        flat_free = self.free.ravel()
        self.column = np.full(nx * ny, -1, dtype=np.int64)
        self.column[flat_free] = np.arange(int(flat_free.sum()))
        self.table: np.ndarray | None = None
        self.row_of = np.full(nx * ny, -1, dtype=np.int64)
        self.row_of_cell: dict[int, int] = {}
        if len(self.fixed_cells) and table_fits(len(self.fixed_cells), int(flat_free.sum()),
                                                table_bytes):
            self.table = np.empty((int(flat_free.sum()), len(self.fixed_cells)), np.float32)
            chunk = max(1, (64 * 2**20) // (8 * nx * ny))  # bounds the float64 scratch
            for s in range(0, len(self.fixed_cells), chunk):
                rows = csgraph.dijkstra(self.graph, directed=False,
                                        indices=self.fixed_cells[s:s + chunk])
                self.table[:, s:s + chunk] = rows[:, flat_free].T
            self.row_of[self.fixed_cells] = np.arange(len(self.fixed_cells))
            self.row_of_cell = {int(c): k for k, c in enumerate(self.fixed_cells)}

    @property
    def nbytes(self) -> int:
        """Memory held: raster, graph, nearest-cell map, table and cached fields."""
        g = self.graph
        total = self.free.nbytes + self.nearest_free.nbytes + self.move_ok.nbytes
        total += self.column.nbytes + self.row_of.nbytes
        total += g.data.nbytes + g.indices.nbytes + g.indptr.nbytes
        total += 0 if self.table is None else self.table.nbytes
        return total + sum(row.nbytes for row in self._cache.values())

    def _free_raster(self) -> np.ndarray:
        """Cells whose centre holds an AGV disc, shelf by shelf on its neighbourhood only.

        At a resolution h up to the AGV radius r the disc must clear by a margin h^2 / (4 r)
        more: a move joins centres whose whole box of cells is free, and a shelf's rounded
        corner (radius r) poking between two free centres h apart reaches at most that far
        past them, so with the margin every grid move keeps the disc off the shelves.
        """
        world = self.world
        h = max(self.dx, self.dy)
        r = world.agent_radius + (h * h / (4 * world.agent_radius)
                                  if h <= world.agent_radius + 1e-12 else 0.0)
        xmin, ymin, xmax, ymax = world.bounds
        x, y = self.x, self.y
        free = np.ones(self.shape, dtype=bool)
        free[:, (x - xmin < r - _TOL) | (xmax - x < r - _TOL)] = False
        free[(y - ymin < r - _TOL) | (ymax - y < r - _TOL), :] = False
        for x0, y0, x1, y1 in world.obstacles:
            i0, i1 = np.searchsorted(x, [x0 - r, x1 + r])
            j0, j1 = np.searchsorted(y, [y0 - r, y1 + r])
            if i0 >= i1 or j0 >= j1:
                continue
            gx = np.maximum(np.maximum(x0 - x[i0:i1], x[i0:i1] - x1), 0.0)
            gy = np.maximum(np.maximum(y0 - y[j0:j1], y[j0:j1] - y1), 0.0)
            free[j0:j1, i0:i1] &= np.hypot(gy[:, None], gx[None, :]) >= r - _TOL
        return free

    def _graph(self) -> sp.csr_matrix:
        """The graph of the moves, and per move the cells it may leave from (``move_ok``)."""
        h, w = self.shape
        idx = np.arange(h * w).reshape(h, w)
        free = self.free
        self.move_ok = np.zeros((len(self.moves), h * w), dtype=bool)
        self.move_step = np.array([di * w + dj for (di, dj), _ in self.moves], dtype=np.int64)
        rows, cols, vals = [], [], []
        for k, ((di, dj), side) in enumerate(self.moves):
            i0, i1 = max(0, -di), h - max(0, di)
            j0, j1 = max(0, -dj), w - max(0, dj)
            if i0 >= i1 or j0 >= j1:
                continue
            ok = free[i0:i1, j0:j1] & free[i0 + di:i1 + di, j0 + dj:j1 + dj]
            for si, sj in side:
                ok &= free[i0 + si:i1 + si, j0 + sj:j1 + sj]
            self.move_ok[k, idx[i0:i1, j0:j1][ok]] = True
            if di < 0 or (di == 0 and dj < 0):
                continue  # the reverse moves come from the symmetric matrix
            rows.append(idx[i0:i1, j0:j1][ok])
            cols.append(idx[i0 + di:i1 + di, j0 + dj:j1 + dj][ok])
            vals.append(np.full(rows[-1].size, math.hypot(di * self.dy, dj * self.dx)))
        r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        g = sp.coo_matrix((v, (r, c)), shape=(h * w, h * w)).tocsr()
        return (g + g.T).tocsr()

    # ------------------------------------------------------------------ queries
    def centres(self, cells: np.ndarray) -> np.ndarray:
        w = self.shape[1]
        return np.stack([self.x[cells % w], self.y[cells // w]], axis=-1)

    def snap(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest free cell (flat index) of each point (K, 2), and the connector length."""
        xmin, ymin = self.world.bounds[:2]
        h, w = self.shape
        col = np.clip(np.floor((points[:, 0] - xmin) / self.dx).astype(np.int64), 0, w - 1)
        row = np.clip(np.floor((points[:, 1] - ymin) / self.dy).astype(np.int64), 0, h - 1)
        cells = self.nearest_free[row * w + col]
        return cells, np.linalg.norm(points - self.centres(cells), axis=1)

    def fields(self, cells: np.ndarray) -> np.ndarray:
        """Distance fields (len(cells), H * W) to the given target cells."""
        cells = np.asarray(cells, dtype=np.int64)
        uniq, inv = np.unique(cells, return_inverse=True)
        out = np.empty((len(uniq), self.shape[0] * self.shape[1]))
        missing = []
        expanded = []
        for k, c in enumerate(uniq.tolist()):
            if c in self._cache:
                self._cache.move_to_end(c)
                out[k] = self._cache[c]
            elif (row := self.row_of_cell.get(c)) is not None:
                out[k] = np.inf  # a table row, spread over the grid once and then cached
                out[k, self.free.ravel()] = self.table[:, row]
                expanded.append(k)
            else:
                missing.append(k)
        for k in expanded:
            self._remember(int(uniq[k]), out[k].copy())
        if missing:
            new = csgraph.dijkstra(self.graph, directed=False, indices=uniq[missing])
            out[missing] = new
            for k, row in zip(missing, new, strict=True):
                self._remember(int(uniq[k]), row)
        return out[inv]

    def _remember(self, cell: int, row: np.ndarray) -> None:
        """Keep a full field in the bounded least-recently-used cache."""
        self._cache[cell] = row
        if len(self._cache) > self.cache_rows:
            self._cache.popitem(last=False)

    def descend(self, cells: np.ndarray, field_rows: np.ndarray,
                row_of: np.ndarray) -> np.ndarray:
        """One steepest-descent step from each cell on its field (the next cell of a shortest
        path); a cell at its target (or cut off) stays."""
        best = field_rows[row_of, cells]
        nxt = cells.copy()
        for k, step in enumerate(self.move_step):
            n = np.where(self.move_ok[k, cells], cells + step, cells)
            val = field_rows[row_of, n]
            better = val < best - 1e-12
            best = np.where(better, val, best)
            nxt = np.where(better, n, nxt)
        return nxt


_GRIDS: OrderedDict[tuple, _FloorGrid] = OrderedDict()
_MAX_GRIDS = 4


def floor_grid_cache_clear() -> None:
    """Forget every cached floor grid (their tables are rebuilt on next use)."""
    _GRIDS.clear()


def _grid_for(world: World, resolution: float, connectivity: int, table_bytes: int,
              cache_bytes: int) -> _FloorGrid:
    key = (world.bounds, world.obstacles.tobytes(), float(world.agent_radius),
           world.pickups.tobytes(), world.stations.tobytes(), float(resolution), connectivity,
           int(table_bytes), int(cache_bytes))
    grid = _GRIDS.get(key)
    if grid is None:
        grid = _FloorGrid(world, resolution, connectivity, table_bytes, cache_bytes)
        _GRIDS[key] = grid
        if len(_GRIDS) > _MAX_GRIDS:
            _GRIDS.popitem(last=False)
    else:
        _GRIDS.move_to_end(key)
    return grid


def _default_resolution(world: World, connectivity: int, table_bytes: int) -> float:
    """Half the AGV radius, coarsened (to at most the radius) where the fixed points' table
    would not fit ``table_bytes`` there, and where the grid would exceed ``_MAX_CELLS``.

    A fleet-scale floor (e.g. ``sim.warehouse_floor(1000)``: 2,245 pickups and stations)
    keeps its table at the AGV radius (341 MB) instead of computing every pickup's field on
    demand at half of it (1.3 GB, which does not fit).
    """
    r = world.agent_radius
    width, height = world.size
    floor_res = math.sqrt(width * height / _MAX_CELLS) * 1.001
    fixed = len(world.pickups) + len(world.stations)

    def cells(res: float) -> int:
        return math.ceil(width / res - 1e-9) * math.ceil(height / res - 1e-9)

    fine = max(r / 2, floor_res)
    if not fixed or table_fits(fixed, cells(fine), table_bytes) or floor_res > r:
        return fine
    probe = _FloorGrid(world, r, connectivity, 0, 1)  # its free fraction, no table
    share = float(probe.free.mean()) * 1.05
    for res in (r / 2, 2 * r / 3, 0.8 * r, r):
        if res >= floor_res and table_fits(fixed, int(cells(res) * share), table_bytes):
            return res
    return fine


# ---------------------------------------------------------------------- public face
class FloorDistances:
    """Obstacle-aware travel distances, smoothed paths and next waypoints on one floor.

    The grid and the fixed points' distance table are built on first use of a floor and cached
    (key: bounds, shelves, AGV radius, pickups, stations and the options), so building a second
    ``FloorDistances`` of the same floor costs nothing.

    Parameters
    ----------
    world : sim.World
        The floor; its ``pickups`` and ``stations`` (may be empty) get precomputed fields.
    resolution : float, optional
        Cell side in world units, default ``agent_radius / 2``, coarsened (up to
        ``agent_radius``) on fleet-scale floors so that the pickups' and stations' table fits
        ``table_bytes``, and on very large floors so that the grid stays under 16 million
        cells. At most ``2 * agent_radius``: a floor
        loaded from a ``.map`` grid with ``cell_size`` (at least an AGV diameter) is exact at
        ``resolution=cell_size``, the map's own cells (a free cell's centre holds an AGV).
    connectivity : {16, 8}
        Grid moves: 8 neighbours, or 8 neighbours and 8 knight moves (default).
    table_bytes : int
        Memory allowed for the fixed points' table (default 512 MiB; float32 fields over the
        free cells); if it would need more even at the coarsest default resolution,
        their fields are computed on demand like any other target.
    cache_bytes : int
        Memory for the least-recently-used cache of on-demand fields (default 256 MiB).

    Raises
    ------
    ValueError
        For a world that is not a :class:`sim.World`, a bad resolution or connectivity, or a
        floor with no free cell.

    Examples
    --------
    >>> import sim
    >>> floor = FloorDistances(sim.warehouse_floor(20))
    >>> d = floor.distance(floor.world.stations[:2], floor.world.pickups)   # (2, 48)
    """

    def __init__(self, world: World, resolution: float | None = None, connectivity: int = 16,
                 table_bytes: int = _DEFAULT_TABLE_BYTES,
                 cache_bytes: int = _DEFAULT_CACHE_BYTES) -> None:
        from sim.world import World as _World

        if not isinstance(world, _World):
            raise ValueError(f"world must be a sim.World, got {type(world).__name__}")
        r = world.agent_radius
        if resolution is None:
            resolution = _default_resolution(world, connectivity, table_bytes)
        if isinstance(resolution, bool) or not isinstance(resolution, (int, float)) or \
                not (math.isfinite(resolution) and 0 < resolution <= 2 * r + 1e-12):
            raise ValueError(f"resolution must be a number in (0, 2 * agent_radius = {2 * r:g}]"
                             f", got {resolution!r}")
        if connectivity not in (8, 16):
            raise ValueError(f"connectivity must be 8 or 16, got {connectivity!r}")
        self.world = world
        self.resolution = float(resolution)
        self.connectivity = connectivity
        self._grid = _grid_for(world, self.resolution, connectivity, table_bytes, cache_bytes)

    # ------------------------------------------------------------------ helpers
    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape (H, W)."""
        return self._grid.shape

    @property
    def nbytes(self) -> int:
        """Memory the floor's grid holds (raster, graph, table and cached fields)."""
        return self._grid.nbytes

    @property
    def fixed_in_table(self) -> bool:
        """Whether the pickups' and stations' fields are precomputed (within ``table_bytes``)."""
        return self._grid.table is not None

    def _points(self, value: object, name: str, batch: int | None = None) -> np.ndarray:
        try:
            raw = np.asarray(value)
        except ValueError:
            raise ValueError(f"{name} must be an (K, 2) array of points, got ragged rows"
                             ) from None
        if raw.dtype.kind not in "iuf":
            raise ValueError(f"{name} must hold real numbers, got dtype {raw.dtype}")
        pts = raw.astype(np.float64)
        if pts.ndim == 1 and batch is None and pts.shape == (2,):
            pts = pts[None]
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"{name} must have shape (K, 2), got {raw.shape}")
        if batch is not None and len(pts) != batch:
            raise ValueError(f"{name} must have shape ({batch}, 2) like a, got {raw.shape}")
        bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
        if bad.size:
            raise ValueError(f"{name} rows {bad[:8].tolist()} contain NaN or infinite values")
        out = np.flatnonzero(self.world.wall_distance(pts) < -_TOL)
        if out.size:
            raise ValueError(f"{name} rows {out[:8].tolist()} lie outside the floor "
                             f"{self.world.bounds}")
        return pts

    def _fixed_rows(self, b: np.ndarray) -> np.ndarray | None:
        """Table rows of b's points if every one snaps to a precomputed cell, else None."""
        g = self._grid
        if g.table is None:
            return None
        cells, _ = g.snap(b)
        rows = g.row_of[cells]
        return None if (rows < 0).any() else rows

    # ------------------------------------------------------------------ queries
    def distance(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Obstacle-aware travel distances from every point of ``a`` to every point of ``b``.

        Each point is snapped to the nearest free cell; the distance is the grid distance
        between the two cells plus both straight connectors. When every point of ``b`` is one of
        the floor's pickups or stations the precomputed table answers (a gather, no search).

        Parameters
        ----------
        a : array-like, shape (K, 2)
            Points on the floor (e.g. AGV positions).
        b : array-like, shape (M, 2)
            Targets (e.g. ``world.pickups``).

        Returns
        -------
        np.ndarray of float64, shape (K, M)
            ``inf`` where b's cell cannot be reached from a's.

        Raises
        ------
        ValueError
            Naming ``a`` or ``b`` for a wrong shape, NaN or a point outside the floor.
        """
        a = self._points(a, "a")
        b = self._points(b, "b")
        g = self._grid
        a_cells, a_off = g.snap(a)
        b_cells, b_off = g.snap(b)
        rows = self._fixed_rows(b)
        if rows is not None:
            uniq, inv = np.unique(rows, return_inverse=True)
            grid = g.table[g.column[a_cells]][:, uniq][:, inv].astype(np.float64)
        else:
            grid = g.fields(b_cells)[:, a_cells].T
        return grid + a_off[:, None] + b_off[None, :]

    def pairwise(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Obstacle-aware travel distance from ``a[k]`` to ``b[k]`` for every k.

        The diagonal of :meth:`distance` without the rest of the matrix: one gather when every
        point of ``b`` is one of the floor's pickups or stations.

        Parameters
        ----------
        a, b : array-like, shape (K, 2)

        Returns
        -------
        np.ndarray of float64, shape (K,)
            ``inf`` where ``b[k]`` cannot be reached from ``a[k]``.

        Raises
        ------
        ValueError
            Naming ``a`` or ``b`` for a wrong shape, NaN, a point outside the floor, or
            lengths that differ.
        """
        a = self._points(a, "a")
        b = self._points(b, "b", batch=len(a))
        g = self._grid
        a_cells, a_off = g.snap(a)
        b_cells, b_off = g.snap(b)
        rows = self._fixed_rows(b)
        if rows is not None:
            grid = g.table[g.column[a_cells], rows].astype(np.float64)
        else:
            uniq, inv = np.unique(b_cells, return_inverse=True)
            grid = g.fields(uniq)[inv, a_cells]
        return grid + a_off + b_off

    def path(self, a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
        """A smoothed collision-free path from ``a`` to ``b``.

        The grid path (steepest descent on b's distance field) is string-pulled: a waypoint is
        kept only where the disc's exact line of sight (:func:`segments_clear`) breaks.

        Parameters
        ----------
        a, b : array-like, shape (2,)

        Returns
        -------
        np.ndarray of float64, shape (P, 2) or None
            ``path[0] == a``, ``path[-1] == b``; None when b cannot be reached from a.
        """
        a = self._points(np.asarray(a, dtype=float).reshape(-1), "a")
        b = self._points(np.asarray(b, dtype=float).reshape(-1), "b")
        if len(a) != 1 or len(b) != 1:
            raise ValueError("a and b must be single points of shape (2,)")
        world = self.world
        if segments_clear(a, b, world)[0]:
            return np.concatenate([a, b])
        g = self._grid
        (sa,), _ = g.snap(a)
        (sb,), _ = g.snap(b)
        field = g.fields(np.array([sb]))
        if not np.isfinite(field[0, sa]):
            return None
        sa = self._entry_cell(a[0], sa, field[0])
        cells = [sa]
        zero = np.zeros(1, dtype=np.int64)
        cur = np.array([sa])
        for _ in range(field.shape[1]):
            if cur[0] == sb:
                break
            cur = g.descend(cur, field, zero)
            cells.append(int(cur[0]))
        pts = np.concatenate([a, g.centres(np.array(cells)), b])
        return self._pull(pts)

    def _entry_cell(self, point: np.ndarray, cell: int, field: np.ndarray,
                    reach: int = 3) -> int:
        """The free cell within ``reach`` cells of ``point``, in its line of sight, that is
        nearest the target counting the connector (``cell`` if none beats it)."""
        g = self._grid
        h, w = g.shape
        i, j = divmod(int(cell), w)
        di, dj = np.mgrid[-reach:reach + 1, -reach:reach + 1]
        ii, jj = (i + di).ravel(), (j + dj).ravel()
        inside = (ii >= 0) & (ii < h) & (jj >= 0) & (jj < w)
        near = ii[inside] * w + jj[inside]
        near = near[g.free.ravel()[near] & np.isfinite(field[near])]
        if not near.size:
            return int(cell)
        centres = g.centres(near)
        cost = np.linalg.norm(centres - point, axis=1) + field[near]
        order = np.argsort(cost)
        seen = segments_clear(np.repeat(point[None], len(order), 0), centres[order], self.world)
        best = near[order[np.flatnonzero(seen)[0]]] if seen.any() else cell
        return int(best)

    def _pull(self, pts: np.ndarray) -> np.ndarray:
        """Greedy string pulling: from each kept point jump to the farthest visible one."""
        out = [pts[0]]
        i, n = 0, len(pts)
        window = 512
        while i < n - 1:
            later = pts[i + 1:min(n, i + 1 + window)]
            ok = segments_clear(np.repeat(pts[i][None], len(later), 0), later, self.world)
            vis = np.flatnonzero(ok)
            j = i + 1 + (int(vis[-1]) if vis.size else 0)
            out.append(pts[j])
            i = j
        return np.array(out)

    def next_waypoint(self, a: np.ndarray, b: np.ndarray, max_cells: int = 4096) -> np.ndarray:
        """The first corner of each smoothed path from ``a[k]`` to ``b[k]``, batched.

        Every AGV walks down its target's distance field cell by cell (all AGVs in one array
        step), and the waypoint is the last cell before the disc's straight line of sight from
        ``a[k]`` breaks; ``b[k]`` itself when it is in sight. A driver heads for it.

        Parameters
        ----------
        a : array-like, shape (K, 2)
            Current positions.
        b : array-like, shape (K, 2)
            Goals.
        max_cells : int
            Longest walk looked at; a waypoint further along is cut there.

        Returns
        -------
        np.ndarray of float64, shape (K, 2)
            ``a[k]`` where ``b[k]`` cannot be reached.

        Raises
        ------
        ValueError
            Naming ``a`` or ``b`` for a wrong shape, NaN, a point outside the floor, or
            lengths that differ.
        """
        a = self._points(a, "a")
        b = self._points(b, "b", batch=len(a))
        world, g = self.world, self._grid
        out = b.copy()
        direct = segments_clear(a, b, world)
        todo = np.flatnonzero(~direct)
        if not todo.size:
            return out
        a_cells, _ = g.snap(a[todo])
        b_cells, _ = g.snap(b[todo])
        uniq, row_of = np.unique(b_cells, return_inverse=True)
        fields = g.fields(uniq)
        reach = np.isfinite(fields[row_of, a_cells])
        best = np.where(reach[:, None], g.centres(a_cells), a[todo])
        cur = a_cells.copy()
        active = reach & (cur != b_cells)
        for _ in range(max_cells):
            if not active.any():
                break
            k = np.flatnonzero(active)
            nxt = g.descend(cur[k], fields, row_of[k])
            seen = segments_clear(a[todo[k]], g.centres(nxt), world)
            stuck = nxt == cur[k]
            move = seen & ~stuck
            best[k[move]] = g.centres(nxt[move])
            cur[k[move]] = nxt[move]
            active[k[~move | (nxt == b_cells[k])]] = False
        # The goal itself when the walk reached its cell and it is in sight.
        at_goal = reach & (cur == b_cells)
        goal_seen = np.zeros(len(todo), dtype=bool)
        goal_seen[at_goal] = segments_clear(a[todo[at_goal]], b[todo[at_goal]], world)
        out[todo] = np.where(goal_seen[:, None], b[todo], best)
        unreached = todo[~reach]
        out[unreached] = a[unreached]
        return out
