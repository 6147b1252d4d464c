"""Obstacle-aware travel costs and paths for a disc-shaped AGV among rectangular shelves.

Two tools, for two jobs:

- :class:`GridMap`: an 8-connected occupancy grid of the free floor, inflated by the AGV's
  radius, with shortest-path tables from :func:`scipy.sparse.csgraph.dijkstra`. It gives the
  (N, M) travel-cost matrix of a scene in one call (straight lines wherever the segment is
  clear, grid path lengths otherwise, ``inf`` where no path exists) and a string-pulled grid path.
- :class:`OMPLPlanner`: OMPL's RRTConnect with path simplification for one-off queries, or a
  PRM roadmap reused across the many queries that share one map. It returns smooth, checked,
  collision-free waypoints.

OMPL is imported on first use only.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = [
    "GridMap",
    "OMPLPlanner",
    "segment_clear",
    "path_is_free",
    "path_length",
    "travel_costs",
    "MAX_COORDINATE",
]

MAX_COORDINATE = 1e150
"""Largest accepted magnitude of a coordinate: the squared distance of two points within it,
at most ``8 * MAX_COORDINATE ** 2``, stays far from float64 overflow (about 1.8e308), and so
does the assignment's cost scaling. Larger coordinates are rejected, not clipped."""

DEFAULT_MARGIN = 0.01
"""Extra clearance (world units) that planned paths keep from shelves and walls."""


def path_length(path: np.ndarray) -> float:
    """Length of a polyline ``(K, 2)``."""
    p = np.asarray(path, dtype=np.float64)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def _inflated_boxes(world: World, clearance: float) -> np.ndarray:
    """Shelves grown by ``clearance`` on every side, (K, 4)."""
    return world.obstacles + np.array([-clearance, -clearance, clearance, clearance])


def segment_clear(
    starts: np.ndarray, ends: np.ndarray, world: World, clearance: float
) -> np.ndarray:
    """Whether each segment keeps a disc of radius ``clearance`` off every shelf.

    The test is conservative: shelves are grown into boxes (square corners), so a segment that
    grazes a rounded corner counts as blocked.

    Parameters
    ----------
    starts, ends : np.ndarray, shape (..., 2)

    Returns
    -------
    np.ndarray of bool, shape (...)
    """
    p0 = np.asarray(starts, dtype=np.float64)
    p1 = np.asarray(ends, dtype=np.float64)
    shape = np.broadcast_shapes(p0.shape, p1.shape)[:-1]
    if not world.has_obstacles:
        return np.ones(shape, dtype=bool)
    boxes = _inflated_boxes(world, clearance)
    d = (p1 - p0)[..., None, :]  # (..., 1, 2)
    o = p0[..., None, :]
    lo, hi = boxes[:, :2], boxes[:, 2:]  # (K, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    # Axis with zero direction: inside the slab -> (-inf, inf), outside -> empty.
    zero = d == 0
    inside = (o > lo) & (o < hi)
    tmin_ax = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    tmax_ax = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    tmin = np.maximum(tmin_ax[..., 0], tmin_ax[..., 1])
    tmax = np.minimum(tmax_ax[..., 0], tmax_ax[..., 1])
    hit = (tmin < tmax) & (tmax > 0.0) & (tmin < 1.0)
    return ~hit.any(axis=-1)


def path_is_free(path: np.ndarray, world: World, clearance: float, step: float = 0.005) -> bool:
    """Whether a disc of radius ``clearance`` moved along ``path`` (K, 2) stays in free space.

    Checks points every ``step`` world units along each segment (exact distances to the
    rectangles, unlike the conservative :func:`segment_clear`).
    """
    p = np.asarray(path, dtype=np.float64)
    pts = [p[:1]]
    for a, b in zip(p[:-1], p[1:], strict=True):
        k = max(int(math.ceil(np.linalg.norm(b - a) / step)), 1)
        pts.append(a + (b - a) * (np.arange(1, k + 1)[:, None] / k))
    return bool(np.all(world.is_free(np.concatenate(pts), clearance=clearance - 1e-9)))


class GridMap:
    """An 8-connected grid over the free floor of a world, for costs and paths.

    Parameters
    ----------
    world : World
    resolution : float
        Cell size in world units.
    clearance : float, optional
        Radius of the disc that must fit at a free cell (default AGV radius + a small margin).

    Attributes
    ----------
    free : np.ndarray of bool, shape (H, W)
    x : np.ndarray, shape (W,)
        Cell-centre x coordinates.
    y : np.ndarray, shape (H,)
        Cell-centre y coordinates.
    graph : scipy.sparse.csr_matrix, shape (H * W, H * W)
        Edge lengths between neighbouring free cells (no corner cutting).
    """

    def __init__(
        self, world: World, resolution: float = 0.05, clearance: float | None = None
    ) -> None:
        if not (resolution > 0):
            raise ValueError(f"resolution must be positive, got {resolution!r}")
        self.world = world
        self.resolution = float(resolution)
        self.clearance = world.agent_radius + DEFAULT_MARGIN if clearance is None else clearance
        xmin, ymin, xmax, ymax = world.bounds
        w = max(int(math.ceil((xmax - xmin) / resolution)), 1)
        h = max(int(math.ceil((ymax - ymin) / resolution)), 1)
        self.x = xmin + (np.arange(w) + 0.5) * (xmax - xmin) / w
        self.y = ymin + (np.arange(h) + 0.5) * (ymax - ymin) / h
        self.shape = (h, w)
        centres = np.stack(np.meshgrid(self.x, self.y), axis=-1)  # (H, W, 2)
        self.free = world.is_free(centres, clearance=self.clearance)
        self.centres = centres.reshape(-1, 2)
        self.graph = self._build_graph()
        free_idx = np.flatnonzero(self.free.ravel())
        if free_idx.size == 0:
            raise ValueError(
                "the world has no free cell for an AGV of this size; "
                "check the shelves, the bounds and agent_radius"
            )
        self._free_idx = free_idx
        self._tree = cKDTree(self.centres[free_idx])
        self._components = csgraph.connected_components(self.graph, directed=False)[1]

    def _build_graph(self) -> sp.csr_matrix:
        h, w = self.shape
        free = self.free
        idx = np.arange(h * w).reshape(h, w)
        dx = (self.x[1] - self.x[0]) if w > 1 else self.resolution
        dy = (self.y[1] - self.y[0]) if h > 1 else self.resolution
        rows, cols, vals = [], [], []
        for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
            i0, i1 = max(0, -di), h - max(0, di)
            j0, j1 = max(0, -dj), w - max(0, dj)
            a = free[i0:i1, j0:j1]
            b = free[i0 + di : i1 + di, j0 + dj : j1 + dj]
            ok = a & b
            if di and dj:  # diagonal: both orthogonal neighbours must be free too
                ok &= free[i0 + di : i1 + di, j0:j1] & free[i0:i1, j0 + dj : j1 + dj]
            src = idx[i0:i1, j0:j1][ok]
            dst = idx[i0 + di : i1 + di, j0 + dj : j1 + dj][ok]
            rows.append(src)
            cols.append(dst)
            vals.append(np.full(src.size, math.hypot(di * dy, dj * dx)))
        r = np.concatenate(rows)
        c = np.concatenate(cols)
        v = np.concatenate(vals)
        g = sp.coo_matrix((v, (r, c)), shape=(h * w, h * w)).tocsr()
        return (g + g.T).tocsr()

    # ------------------------------------------------------------------ queries
    def snap(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest free cell of each point.

        Returns
        -------
        cells : np.ndarray of int64, shape (K,)
            Flat cell indices.
        offsets : np.ndarray, shape (K,)
            Distance from each point to its cell centre.
        """
        d, j = self._tree.query(np.asarray(points, dtype=np.float64).reshape(-1, 2))
        return self._free_idx[j], d

    def distances_from(self, points: np.ndarray) -> np.ndarray:
        """Grid path length from each point to every cell, shape (K, H * W) (``inf`` if cut off)."""
        cells, off = self.snap(points)
        uniq, inv = np.unique(cells, return_inverse=True)
        table = csgraph.dijkstra(self.graph, directed=False, indices=uniq)
        return table[inv] + off[:, None]

    def cost_matrix(self, agents: np.ndarray, tasks: np.ndarray) -> np.ndarray:
        """Travel costs (N, M): the straight distance where the segment is clear, the grid
        path length otherwise, ``inf`` where the task cannot be reached."""
        agents = np.asarray(agents, dtype=np.float64)
        tasks = np.asarray(tasks, dtype=np.float64)
        straight = np.linalg.norm(agents[:, None, :] - tasks[None, :, :], axis=-1)
        clear = segment_clear(agents[:, None, :], tasks[None, :, :], self.world, self.clearance)
        if clear.all():
            return straight
        a_cells, a_off = self.snap(agents)
        table = self.distances_from(tasks)  # (M, cells)
        grid = table[:, a_cells].T + a_off[:, None]  # (N, M)
        reach = self._components[a_cells][:, None] == self._components[self.snap(tasks)[0]][None]
        cost = np.where(clear, straight, np.maximum(grid, straight))
        return np.where(reach | clear, cost, np.inf)

    def path(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """A string-pulled grid path ``(K, 2)`` from ``start`` to ``goal``, or None if cut off."""
        start = np.asarray(start, dtype=np.float64)
        goal = np.asarray(goal, dtype=np.float64)
        if segment_clear(start, goal, self.world, self.clearance):
            return np.stack([start, goal])
        (s,), _ = self.snap(start[None])
        (g,), _ = self.snap(goal[None])
        dist, pred = csgraph.dijkstra(
            self.graph, directed=False, indices=s, return_predecessors=True
        )
        if not np.isfinite(dist[g]):
            return None
        cells = [g]
        while cells[-1] != s:
            cells.append(pred[cells[-1]])
        pts = np.concatenate([start[None], self.centres[cells[::-1]], goal[None]])
        return self.shortcut(pts)

    def plan(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """Same as :meth:`path` (the planner interface shared with :class:`OMPLPlanner`)."""
        return self.path(start, goal)

    def shortcut(self, pts: np.ndarray) -> np.ndarray:
        """Greedy string pulling: keep a waypoint only where line of sight breaks."""
        out = [pts[0]]
        i = 0
        n = len(pts)
        while i < n - 1:
            ok = segment_clear(np.repeat(pts[i][None], n - i - 1, 0), pts[i + 1 :], self.world,
                               self.clearance)
            # Farthest visible point (the next one is always kept).
            vis = np.flatnonzero(ok)
            j = i + 1 + (int(vis[-1]) if vis.size else 0)
            out.append(pts[j])
            i = j
        return np.array(out)


_GRIDS: dict[tuple, GridMap] = {}


def grid_for(world: World, resolution: float = 0.05, clearance: float | None = None) -> GridMap:
    """A cached :class:`GridMap` for ``world`` (worlds are frozen, so the map can be reused)."""
    c = world.agent_radius + DEFAULT_MARGIN if clearance is None else float(clearance)
    key = (world.bounds, world.obstacles.tobytes(), float(resolution), c)
    grid = _GRIDS.get(key)
    if grid is None:
        if len(_GRIDS) >= 8:
            _GRIDS.pop(next(iter(_GRIDS)))
        grid = _GRIDS[key] = GridMap(world, resolution, c)
    return grid


def travel_costs(
    agents: np.ndarray, tasks: np.ndarray, world: World | None = None, resolution: float = 0.05
) -> np.ndarray:
    """The (N, M) travel-cost matrix of a scene.

    Straight-line distances in an open world (or where a segment is clear of every shelf);
    obstacle-aware grid path lengths otherwise; ``inf`` for a task an AGV cannot reach.

    Parameters
    ----------
    agents : array-like, shape (N, 2)
    tasks : array-like, shape (M, 2)
        Finite coordinates, at most :data:`MAX_COORDINATE` in magnitude (so
        that no distance overflows to ``inf``, which would read as "unreachable").
    world : World, optional
    resolution : float
        Cell size of the occupancy grid.

    Returns
    -------
    np.ndarray, shape (N, M)

    Raises
    ------
    ValueError
        For coordinates that are not finite or beyond ``MAX_COORDINATE``.
    """
    agents = np.asarray(agents, dtype=np.float64)
    tasks = np.asarray(tasks, dtype=np.float64)
    for what, arr in (("agents", agents), ("tasks", tasks)):
        if arr.size and not np.abs(arr).max() <= MAX_COORDINATE:
            raise ValueError(
                f"{what} must hold finite coordinates within +-{MAX_COORDINATE:g} (their "
                "squared distances would overflow)"
            )
    if world is None or not world.has_obstacles:
        return cdist(agents, tasks)
    return grid_for(world, resolution).cost_matrix(agents, tasks)


# ---------------------------------------------------------------------- OMPL
def _validity_fn(world: World, clearance: float) -> Any:
    """A fast pure-Python state checker capturing only obstacle numbers (no OMPL objects)."""
    rects = [tuple(map(float, r)) for r in world.obstacles]
    c2 = clearance * clearance

    def valid(state: Any) -> bool:
        x = state[0]
        y = state[1]
        for x0, y0, x1, y1 in rects:
            dx = x0 - x if x < x0 else (x - x1 if x > x1 else 0.0)
            dy = y0 - y if y < y0 else (y - y1 if y > y1 else 0.0)
            if dx * dx + dy * dy < c2:
                return False
        return True

    return valid


_OMPL_SEED: int | None = None


class OMPLPlanner:
    """Collision-free waypoints for a disc among the shelves, planned with OMPL.

    Parameters
    ----------
    world : World
    planner : {"rrtconnect", "prm"}
        RRTConnect (a fresh tree per query) or PRM (one roadmap grown once and reused across
        queries on the same map, cleared with ``clearQuery`` between them).
    clearance : float, optional
        Disc radius to keep off shelves and walls (default AGV radius + a small margin).
    time_limit : float
        Seconds per query.
    simplify_time : float
        Seconds of path simplification per query.
    seed : int
        Seed of OMPL's global RNG. OMPL accepts one seed per process, before its first
        sample: the first planner built sets it, later ones share that stream.

    Notes
    -----
    Every returned path is checked densely with :func:`path_is_free`; if OMPL finds no exact
    path (or returns one that fails the check) the string-pulled grid path is returned instead,
    and None only when the goal is cut off.
    """

    def __init__(
        self,
        world: World,
        planner: str = "rrtconnect",
        clearance: float | None = None,
        time_limit: float = 0.5,
        simplify_time: float = 0.02,
        seed: int = 0,
        roadmap_time: float = 0.2,
    ) -> None:
        if planner not in ("rrtconnect", "prm"):
            raise ValueError(f"planner must be 'rrtconnect' or 'prm', got {planner!r}")
        from ompl import base as ob
        from ompl import geometric as og
        from ompl import util as ou

        global _OMPL_SEED
        ou.setLogLevel(ou.LogLevel.LOG_WARN)
        if _OMPL_SEED is None:  # OMPL's RNG can be seeded once per process, before sampling
            _OMPL_SEED = int(seed) + 1  # and rejects 0
            ou.RNG.setSeed(_OMPL_SEED)
        self.world = world
        self.kind = planner
        self.clearance = world.agent_radius + DEFAULT_MARGIN if clearance is None else clearance
        self.time_limit = time_limit
        self.simplify_time = simplify_time
        self.roadmap_time = roadmap_time
        self._ob, self._og = ob, og
        self._ss: Any = None
        self._prm: Any = None
        self._space: Any = None
        self.stats = {"queries": 0, "ompl": 0, "grid_fallback": 0}

    def _setup(self) -> Any:
        ob, og = self._ob, self._og
        space = ob.RealVectorStateSpace(2)
        xmin, ymin, xmax, ymax = self.world.bounds
        c = self.clearance
        bounds = ob.RealVectorBounds(2)
        bounds.setLow(0, xmin + c)
        bounds.setLow(1, ymin + c)
        bounds.setHigh(0, xmax - c)
        bounds.setHigh(1, ymax - c)
        space.setBounds(bounds)
        ss = og.SimpleSetup(space)
        ss.setStateValidityChecker(_validity_fn(self.world, c))
        si = ss.getSpaceInformation()
        extent = max(xmax - xmin, ymax - ymin)
        si.setStateValidityCheckingResolution(min(0.01, 0.005 / extent))
        return space, ss, si

    def plan(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """Waypoints ``(K, 2)`` from ``start`` to ``goal`` (both included), or None if cut off.

        Returns
        -------
        np.ndarray or None
            ``path[0] == start`` and ``path[-1] == goal``; a disc of radius ``clearance``
            moved along the polyline touches no shelf.
        """
        start = np.asarray(start, dtype=np.float64)
        goal = np.asarray(goal, dtype=np.float64)
        self.stats["queries"] += 1
        grid = grid_for(self.world, clearance=self.clearance)
        if segment_clear(start, goal, self.world, self.clearance):
            return np.stack([start, goal])
        path = self._plan_ompl(start, goal)
        if path is not None and path_is_free(path[1:-1], self.world, self.clearance) and \
                path_is_free(path, self.world, self.world.agent_radius):
            self.stats["ompl"] += 1
            return path
        self.stats["grid_fallback"] += 1
        return grid.path(start, goal)

    def _plan_ompl(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        og = self._og
        # Start or goal hugging a shelf closer than the clearance: plan between the nearest
        # valid points and join them with straight segments.
        valid = _validity_fn(self.world, self.clearance)
        s_in = _nudge(start, valid, self.world, self.clearance)
        g_in = _nudge(goal, valid, self.world, self.clearance)
        if s_in is None or g_in is None:
            return None
        if self.kind == "prm":
            if self._ss is None:
                self._space, self._ss, si = self._setup()
                self._prm = og.PRM(si)
                self._ss.setPlanner(self._prm)
                self._ss.setup()
                self._prm.growRoadmap(self.roadmap_time)
            else:
                self._prm.clearQuery()
            space, ss = self._space, self._ss
        else:
            space, ss, si = self._setup()
            ss.setPlanner(og.RRTConnect(si))
        s = space.allocState()
        s[0], s[1] = float(s_in[0]), float(s_in[1])
        g = space.allocState()
        g[0], g[1] = float(g_in[0]), float(g_in[1])
        ss.setStartAndGoalStates(s, g)
        ss.solve(self.time_limit)
        if not ss.haveExactSolutionPath():
            return None
        ss.simplifySolution(self.simplify_time)
        states = ss.getSolutionPath().getStates()
        pts = np.array([[st[0], st[1]] for st in states], dtype=np.float64)
        del states, s, g
        if self.kind != "prm":
            ss.clear()
            del ss, space
        pts = np.concatenate([start[None], pts, goal[None]])
        keep = np.ones(len(pts), dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9
        return pts[keep]

    def close(self) -> None:
        """Free the OMPL objects (a PRM roadmap is kept until then)."""
        self._ss = self._prm = self._space = None

    def __del__(self) -> None:
        self.close()


def _nudge(point: np.ndarray, valid: Any, world: World, clearance: float) -> np.ndarray | None:
    """``point`` if valid, else the nearest valid point within a small radius (or None)."""
    if valid(point) and world.wall_distance(point) >= clearance:
        return point
    for radius in (0.01, 0.02, 0.04, 0.08):
        ang = np.linspace(0, 2 * np.pi, 32, endpoint=False)
        cand = point + radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        ok = world.is_free(cand, clearance=clearance)
        if ok.any():
            return cand[np.flatnonzero(ok)[0]]
    return None
