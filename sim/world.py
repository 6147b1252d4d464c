"""Static world parameters: bounds, shelves, AGV size and the physics constants.

A :class:`World` never changes during an episode; the changing state lives in
:class:`sim.state.SimState`. Every geometric helper here works on numpy arrays so that the
classical solvers (``allocator``) and the IPF field share one definition of "free space".

A world may also be a *floor* for lifelong operation: it then carries its pickup points, its
drop-off stations and the depot where the AGVs start (:mod:`sim.floors` loads and builds
floors). The paper's worlds have none of these.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["World", "Physics", "segments_clear"]


@dataclass(frozen=True)
class Physics:
    """MPE physics constants (the values of ``mpe2``'s ``simple_spread``)."""

    dt: float = 0.1
    """Time step in seconds."""
    damping: float = 0.25
    """Fraction of the velocity lost per step."""
    mass: float = 1.0
    """AGV mass."""
    sensitivity: float = 5.0
    """Acceleration per unit action (MPE's ``accel`` default)."""
    contact_force: float = 1e2
    """Stiffness of the soft contact between AGV discs."""
    contact_margin: float = 1e-3
    """Softness of the contact (softplus width)."""
    max_speed: float | None = None
    """Optional speed cap (MPE: none)."""

    def __post_init__(self) -> None:
        for name in ("dt", "mass", "sensitivity", "contact_margin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"Physics.{name} must be a positive finite number, got {value!r}")
        if not (0.0 <= self.damping < 1.0):
            raise ValueError(f"Physics.damping must be in [0, 1), got {self.damping!r}")
        if not (math.isfinite(self.contact_force) and self.contact_force >= 0):
            raise ValueError(
                f"Physics.contact_force must be finite and >= 0, got {self.contact_force!r}"
            )
        if self.max_speed is not None and not (self.max_speed > 0):
            raise ValueError(f"Physics.max_speed must be positive or None, got {self.max_speed!r}")

    @property
    def terminal_speed(self) -> float:
        """Steady-state speed under full acceleration along one axis (about 1.5 for MPE)."""
        speed = self.sensitivity / self.mass * self.dt * (1.0 - self.damping) / self.damping
        return speed if self.max_speed is None else min(speed, self.max_speed)


def _as_obstacles(obstacles: object) -> np.ndarray:
    arr = np.asarray(obstacles, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 4), dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError(
            "obstacles must be an (K, 4) array of rectangles (xmin, ymin, xmax, ymax), "
            f"got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError("obstacles contain NaN or infinite coordinates")
    empty = np.flatnonzero((arr[:, 2] <= arr[:, 0]) | (arr[:, 3] <= arr[:, 1]))
    if empty.size:
        raise ValueError(f"every obstacle needs xmax > xmin and ymax > ymin (rows "
                         f"{_head(empty)} do not)")
    return arr


def _head(rows: np.ndarray, limit: int = 8) -> str:
    """``[3, 7, 9]`` or ``[3, 7, ..., 40 rows in all]`` for an error message."""
    listed = ", ".join(str(int(k)) for k in rows[:limit])
    return f"[{listed}]" if len(rows) <= limit else f"[{listed}, ... {len(rows)} rows in all]"


def _real_array(value: object, name: str, width: int, what: str) -> np.ndarray:
    """A read-only float64 copy of ``value`` with shape (K, width); empty input gives (0, width).

    Refuses strings, bools, complex numbers, objects, ragged rows, a wrong shape and NaN or
    infinite values, naming the field (and the rows).
    """
    try:
        raw = np.asarray(value)
    except ValueError:  # ragged rows
        raise ValueError(f"{name} must be an (K, {width}) array of {what}, got ragged rows"
                         ) from None
    if raw.size == 0:
        arr = np.zeros((0, width), dtype=np.float64)
    else:
        if raw.dtype.kind not in "iuf":
            raise ValueError(f"{name} must hold real numbers, got dtype {raw.dtype} "
                             "(complex, bool, strings and objects are refused)")
        if raw.ndim != 2 or raw.shape[1] != width:
            raise ValueError(f"{name} must be an (K, {width}) array of {what}, got shape "
                             f"{raw.shape}")
        arr = np.array(raw, dtype=np.float64)  # a copy: the caller's array stays writable
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if bad.size:
            raise ValueError(f"{name} rows {_head(bad)} contain NaN or infinite values")
    arr.setflags(write=False)
    return arr


def _describe(name: str, arr: np.ndarray, rows: np.ndarray, limit: int = 4) -> str:
    """``pickups[2] at (1.5, 0.2), pickups[7] at (3, 0.2)`` for an error message."""
    items = [f"{name}[{int(k)}] at ({arr[k, 0]:.6g}, {arr[k, 1]:.6g})" for k in rows[:limit]]
    more = f" and {len(rows) - limit} more" if len(rows) > limit else ""
    return ", ".join(items) + more


@dataclass(frozen=True)
class World:
    """The static description of a shop floor.

    Attributes
    ----------
    bounds : tuple of float
        ``(xmin, ymin, xmax, ymax)`` of the walls; default the MPE box ``[-1, 1]^2``.
    obstacles : np.ndarray
        ``(K, 4)`` axis-aligned rectangles ``(xmin, ymin, xmax, ymax)`` (shelves), may be empty.
    agent_radius : float
        Radius of every AGV disc (0.15 in the paper's scenarios).
    capture_radius : float
        An idle AGV claims a task once its centre is this close to it.
    walls : bool
        Keep AGVs inside ``bounds`` (disable only for the MPE parity check).
    physics : Physics
        The MPE constants.
    pickups : np.ndarray
        ``(P, 2)`` pickup points of a lifelong floor (at the shelf faces), may be empty.
    stations : np.ndarray
        ``(S, 2)`` drop-off stations of a lifelong floor, may be empty.
    depot : np.ndarray
        ``(D, 4)`` rectangles ``(xmin, ymin, xmax, ymax)`` where the AGVs start: every AGV disc
        lies wholly inside one of them. Empty: anywhere on the free floor.

    Every array field is stored as a read-only float64 array. Every pickup and station lies
    inside the walls with room for an AGV disc there, clear of the shelves; every depot
    rectangle lies inside the walls, holds at least one AGV disc and overlaps no shelf. Derive a
    changed world with :func:`dataclasses.replace` (the checks run again).
    """

    bounds: tuple[float, float, float, float] = (-1.0, -1.0, 1.0, 1.0)
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    agent_radius: float = 0.15
    capture_radius: float = 0.1
    walls: bool = True
    physics: Physics = field(default_factory=Physics)
    pickups: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    stations: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    depot: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def __post_init__(self) -> None:
        b = tuple(float(v) for v in self.bounds)
        if len(b) != 4 or not all(math.isfinite(v) for v in b):
            raise ValueError(f"bounds must be 4 finite numbers (xmin, ymin, xmax, ymax), got {b}")
        if b[2] <= b[0] or b[3] <= b[1]:
            raise ValueError(
                f"bounds {b} do not enclose an area: expected xmax > xmin and ymax > ymin"
            )
        object.__setattr__(self, "bounds", b)
        if not (math.isfinite(self.agent_radius) and self.agent_radius > 0):
            raise ValueError(f"agent_radius must be positive, got {self.agent_radius!r}")
        if not (math.isfinite(self.capture_radius) and self.capture_radius > 0):
            raise ValueError(f"capture_radius must be positive, got {self.capture_radius!r}")
        obstacles = _as_obstacles(self.obstacles)
        obstacles.setflags(write=False)
        object.__setattr__(self, "obstacles", obstacles)
        if 2 * self.agent_radius >= min(b[2] - b[0], b[3] - b[1]):
            raise ValueError(
                f"agent_radius {self.agent_radius} is too large for bounds {b}: "
                "an AGV must fit between the walls"
            )
        for name in ("pickups", "stations"):
            points = _real_array(getattr(self, name), name, 2, "points (x, y)")
            object.__setattr__(self, name, points)
            self._check_points_free(name, points)
        depot = _real_array(self.depot, "depot", 4, "rectangles (xmin, ymin, xmax, ymax)")
        object.__setattr__(self, "depot", depot)
        self._check_depot(depot)

    def _check_points_free(self, name: str, points: np.ndarray) -> None:
        """Every point inside the walls, with room for an AGV disc there, off the shelves."""
        if not len(points):
            return
        r = self.agent_radius
        walls = self.wall_distance(points)
        outside = np.flatnonzero(walls < -1e-9)
        if outside.size:
            raise ValueError(f"{_describe(name, points, outside)}: outside the world bounds "
                             f"{self.bounds}")
        shelves = self._near_obstacle_distance(points, r)
        in_shelf = np.flatnonzero(shelves < 0)
        if in_shelf.size:
            raise ValueError(f"{_describe(name, points, in_shelf)}: inside a shelf")
        # The test of is_free, on the nearby shelves only (a floor may have thousands).
        tight = np.flatnonzero((walls < r - 1e-9) | (shelves < r - 1e-9))
        if tight.size:
            raise ValueError(
                f"{_describe(name, points, tight)}: no room for an AGV disc of radius {r:g} "
                f"there (closer than {r:g} to a wall or a shelf); move the point into the aisle"
            )

    def _near_obstacle_distance(self, points: np.ndarray, reach: float) -> np.ndarray:
        """:meth:`obstacle_distance` where it is below ``reach``; ``inf`` or a value >= reach
        elsewhere.

        The shelves, grown by ``reach``, are entered into square buckets; each point is
        measured against the shelves of its own bucket only, so P points and K shelves cost
        about P + K instead of P x K (grid maps give thousands of each).
        """
        out = np.full(len(points), np.inf)
        obs = self.obstacles
        if not len(obs) or not len(points):
            return out
        xmin, ymin, xmax, ymax = self.bounds
        side = max(4.0 * reach, math.sqrt((xmax - xmin) * (ymax - ymin) / 4e6))
        nx = max(1, math.ceil((xmax - xmin) / side))
        ny = max(1, math.ceil((ymax - ymin) / side))

        def bucket(v: np.ndarray, lo: float, n: int) -> np.ndarray:
            return np.clip(np.floor((v - lo) / side), 0, n - 1).astype(np.int64)

        # Bucket ranges of every grown shelf, then one (bucket, shelf) entry per bucket covered.
        bx0, bx1 = bucket(obs[:, 0] - reach, xmin, nx), bucket(obs[:, 2] + reach, xmin, nx)
        by0, by1 = bucket(obs[:, 1] - reach, ymin, ny), bucket(obs[:, 3] + reach, ymin, ny)
        wide, tall = bx1 - bx0 + 1, by1 - by0 + 1
        count = wide * tall
        shelf = np.repeat(np.arange(len(obs)), count)
        local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        cells = ((by0[shelf] + local // wide[shelf]) * nx + bx0[shelf] + local % wide[shelf])
        order = np.argsort(cells, kind="stable")
        cells, shelf = cells[order], shelf[order]
        # Each point against the shelves entered in its bucket.
        own = bucket(points[:, 1], ymin, ny) * nx + bucket(points[:, 0], xmin, nx)
        start = np.searchsorted(cells, own, side="left")
        many = np.searchsorted(cells, own, side="right") - start
        point = np.repeat(np.arange(len(points)), many)
        pair = np.repeat(start, many) + np.arange(many.sum()) - np.repeat(np.cumsum(many) - many,
                                                                          many)
        rect = obs[shelf[pair]]  # (pairs, 4)
        p = points[point]  # (pairs, 2)
        lo, hi = rect[:, :2], rect[:, 2:]
        out_dist = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=-1)
        in_dist = np.min(np.minimum(p - lo, hi - p), axis=-1)
        signed = np.where(out_dist > 0, out_dist, -np.maximum(in_dist, 0.0))
        np.minimum.at(out, point, signed)
        return out

    def _check_depot(self, depot: np.ndarray) -> None:
        """Every depot rectangle inside the walls, at least one AGV disc big, off the shelves."""
        if not len(depot):
            return
        r = self.agent_radius
        empty = np.flatnonzero((depot[:, 2] <= depot[:, 0]) | (depot[:, 3] <= depot[:, 1]))
        if empty.size:
            raise ValueError(f"depot rows {_head(empty)} need xmax > xmin and ymax > ymin")
        small = np.flatnonzero(np.minimum(depot[:, 2] - depot[:, 0],
                                          depot[:, 3] - depot[:, 1]) < 2 * r - 1e-9)
        if small.size:
            k = int(small[0])
            raise ValueError(f"depot rows {_head(small)} are too small to hold an AGV disc of "
                             f"radius {r:g} (depot[{k}] = {depot[k].tolist()}); each side "
                             f"needs at least {2 * r:g}")
        xmin, ymin, xmax, ymax = self.bounds
        tol = 1e-9
        outside = np.flatnonzero((depot[:, 0] < xmin - tol) | (depot[:, 1] < ymin - tol)
                                 | (depot[:, 2] > xmax + tol) | (depot[:, 3] > ymax + tol))
        if outside.size:
            k = int(outside[0])
            raise ValueError(f"depot rows {_head(outside)} reach outside the world bounds "
                             f"{self.bounds} (depot[{k}] = {depot[k].tolist()})")
        if self.has_obstacles:
            lo = np.maximum(depot[:, None, :2], self.obstacles[None, :, :2])  # (D, K, 2)
            hi = np.minimum(depot[:, None, 2:], self.obstacles[None, :, 2:])
            overlap = np.all(hi - lo > tol, axis=-1)  # (D, K): positive-area intersection
            rows = np.flatnonzero(overlap.any(axis=1))
            if rows.size:
                k = int(rows[0])
                j = int(np.flatnonzero(overlap[k])[0])
                raise ValueError(f"depot rows {_head(rows)} overlap a shelf (depot[{k}] = "
                                 f"{depot[k].tolist()} overlaps obstacle {j} = "
                                 f"{self.obstacles[j].tolist()}); the depot must be free floor")

    # ------------------------------------------------------------------ geometry
    @property
    def size(self) -> tuple[float, float]:
        """Width and height of the world."""
        return self.bounds[2] - self.bounds[0], self.bounds[3] - self.bounds[1]

    @property
    def has_obstacles(self) -> bool:
        return len(self.obstacles) > 0

    @property
    def is_floor(self) -> bool:
        """Whether this is a lifelong floor: it has pickup points and drop-off stations."""
        return len(self.pickups) > 0 and len(self.stations) > 0

    def in_depot(self, points: np.ndarray) -> np.ndarray:
        """Whether an AGV centred at each point may start there.

        Inside a depot rectangle with its whole disc, or, for a world without a depot, anywhere
        an AGV disc fits (:meth:`is_free`).

        Parameters
        ----------
        points : np.ndarray, shape (..., 2)

        Returns
        -------
        np.ndarray of bool, shape (...)
        """
        pts = np.asarray(points, dtype=np.float64)
        if not len(self.depot):
            return self.is_free(pts)
        r = self.agent_radius - 1e-9
        p = pts[..., None, :]  # (..., 1, 2)
        lo, hi = self.depot[:, :2] + r, self.depot[:, 2:] - r  # (D, 2) centre ranges
        return np.all((p >= lo) & (p <= hi), axis=-1).any(axis=-1)

    @property
    def task_spacing(self) -> float:
        """Minimum distance between spawned tasks, 2 x (radius + capture radius)."""
        return 2.0 * (self.agent_radius + self.capture_radius)

    def obstacle_distance(self, points: np.ndarray) -> np.ndarray:
        """Distance from each point to the nearest shelf (negative inside one).

        Parameters
        ----------
        points : np.ndarray, shape (..., 2)

        Returns
        -------
        np.ndarray, shape (...)
            ``inf`` where the world has no obstacles.
        """
        pts = np.asarray(points, dtype=np.float64)
        if not self.has_obstacles:
            return np.full(pts.shape[:-1], np.inf)
        obs = self.obstacles
        p = pts[..., None, :]  # (..., 1, 2)
        lo, hi = obs[:, :2], obs[:, 2:]
        outside = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        out_dist = np.linalg.norm(outside, axis=-1)
        in_dist = np.min(np.minimum(p - lo, hi - p), axis=-1)
        signed = np.where(out_dist > 0, out_dist, -np.maximum(in_dist, 0.0))
        return signed.min(axis=-1)

    def wall_distance(self, points: np.ndarray) -> np.ndarray:
        """Distance from each point to the nearest wall (negative outside the bounds)."""
        pts = np.asarray(points, dtype=np.float64)
        xmin, ymin, xmax, ymax = self.bounds
        return np.minimum.reduce(
            [pts[..., 0] - xmin, xmax - pts[..., 0], pts[..., 1] - ymin, ymax - pts[..., 1]]
        )

    def is_free(self, points: np.ndarray, clearance: float | None = None) -> np.ndarray:
        """Whether a disc of radius ``clearance`` (default the AGV radius) fits at each point.

        Parameters
        ----------
        points : np.ndarray, shape (..., 2)
        clearance : float, optional

        Returns
        -------
        np.ndarray of bool, shape (...)
        """
        r = self.agent_radius if clearance is None else clearance
        pts = np.asarray(points, dtype=np.float64)
        ok = self.wall_distance(pts) >= r - 1e-9
        if self.has_obstacles:
            ok &= self.obstacle_distance(pts) >= r - 1e-9
        return ok

    def check_positions(self, points: object, what: str = "positions") -> np.ndarray:
        """Validate an ``(K, 2)`` array of positions and return it as float64.

        Raises
        ------
        ValueError
            On values that are not real numbers, a wrong shape, NaN or infinite values, a point
            outside the walls or inside a shelf.
        """
        try:
            raw = np.asarray(points)
        except ValueError:  # ragged rows
            raise ValueError(f"{what} must be an (K, 2) array of real numbers, got ragged "
                             "rows") from None
        if raw.dtype.kind not in "iuf":
            raise ValueError(f"{what} must hold real numbers, got dtype {raw.dtype} "
                             f"(complex, bool, strings and objects are refused)")
        arr = raw.astype(np.float64, copy=False)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"{what} must have shape (K, 2), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
            raise ValueError(f"{what} contain NaN or infinite values at rows {bad.tolist()}")
        outside = np.flatnonzero(self.wall_distance(arr) < -1e-9)
        if outside.size:
            raise ValueError(
                f"{what} rows {outside.tolist()} lie outside the world bounds {self.bounds}"
            )
        if self.has_obstacles:
            inside = np.flatnonzero(self.obstacle_distance(arr) < 0)
            if inside.size:
                raise ValueError(f"{what} rows {inside.tolist()} lie inside a shelf (obstacle)")
        return arr


# ---------------------------------------------------------------------- segments
_SEGMENT_TOL = 1e-9
"""Slack of :func:`segments_clear`'s clearance test (as in ``allocator.distances``)."""


def _point_rect_distance(p: np.ndarray, rect: np.ndarray) -> np.ndarray:
    """Distance (>= 0) from points (..., 2) to rectangles (..., 4); 0 inside."""
    gap = np.maximum(np.maximum(rect[..., :2] - p, p - rect[..., 2:]), 0.0)
    return np.hypot(gap[..., 0], gap[..., 1])


def _point_segment_distance(q: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Distance from points q (..., 2) to segments p0-p1 (..., 2)."""
    d = p1 - p0
    dd = np.einsum("...i,...i->...", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dd > 0, np.einsum("...i,...i->...", q - p0, d) / dd, 0.0)
    t = np.clip(t, 0.0, 1.0)
    foot = p0 + t[..., None] * d
    return np.linalg.norm(q - foot, axis=-1)


def _segment_rect_distance(p0: np.ndarray, p1: np.ndarray, rect: np.ndarray) -> np.ndarray:
    """Exact distance between segments p0-p1 (E, 2) and rectangles (E, 4); 0 if they meet.

    Two disjoint convex sets are closest at a vertex of one of them, so the distance is the
    least of the endpoints' distances to the rectangle and the corners' distances to the
    segment; a slab test tells whether the segment meets the rectangle.
    """
    lo, hi = rect[:, :2], rect[:, 2:]
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - p0) / d
        t2 = (hi - p0) / d
    zero = d == 0
    inside = (p0 >= lo) & (p0 <= hi)
    tmin = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=1)
    tmax = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=1)
    meets = (tmin <= tmax) & (tmax >= 0.0) & (tmin <= 1.0)
    best = np.minimum(_point_rect_distance(p0, rect), _point_rect_distance(p1, rect))
    for cx, cy in ((0, 1), (2, 1), (0, 3), (2, 3)):
        corner = np.stack([rect[:, cx], rect[:, cy]], axis=1)
        best = np.minimum(best, _point_segment_distance(corner, p0, p1))
    return np.where(meets, 0.0, best)


def segments_clear(starts: np.ndarray, ends: np.ndarray, world: World,
                   clearance: float | None = None) -> np.ndarray:
    """Whether a disc of radius ``clearance`` swept along each segment touches no shelf or wall.

    Exact for rectangular shelves (rounded corners, unlike the conservative boxes of
    :func:`allocator.paths.segment_clear`), with the tolerance of :meth:`sim.World.is_free`.

    Parameters
    ----------
    starts, ends : np.ndarray, shape (E, 2)
    world : sim.World
    clearance : float, optional
        Disc radius, default the AGV radius.

    Returns
    -------
    np.ndarray of bool, shape (E,)
    """
    p0 = np.asarray(starts, dtype=np.float64).reshape(-1, 2)
    p1 = np.asarray(ends, dtype=np.float64).reshape(-1, 2)
    r = world.agent_radius if clearance is None else float(clearance)
    ok = (world.wall_distance(p0) >= r - _SEGMENT_TOL) \
        & (world.wall_distance(p1) >= r - _SEGMENT_TOL)
    obs = world.obstacles
    if not len(obs) or not len(p0):
        return ok
    # Candidate pairs: the shelf's box grown by r meets the segment's bounding box.
    seg_lo = np.minimum(p0, p1) - r
    seg_hi = np.maximum(p0, p1) + r
    chunk = max(1, 4_000_000 // len(obs))
    for s in range(0, len(p0), chunk):
        lo, hi = seg_lo[s:s + chunk], seg_hi[s:s + chunk]
        near = ((obs[None, :, 0] <= hi[:, None, 0]) & (obs[None, :, 2] >= lo[:, None, 0])
                & (obs[None, :, 1] <= hi[:, None, 1]) & (obs[None, :, 3] >= lo[:, None, 1]))
        seg, rect = np.nonzero(near)
        if not seg.size:
            continue
        dist = _segment_rect_distance(p0[s + seg], p1[s + seg], obs[rect])
        blocked = np.zeros(len(lo), dtype=bool)
        blocked[seg[dist < r - _SEGMENT_TOL]] = True
        ok[s:s + chunk] &= ~blocked
    return ok
