"""Static world parameters: bounds, shelves, AGV size and the physics constants.

A :class:`World` never changes during an episode; the changing state lives in
:class:`sim.state.SimState`. Every geometric helper here works on numpy arrays so that the
classical solvers (``allocator``) and the IPF field share one definition of "free space".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["World", "Physics"]


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
    if np.any(arr[:, 2] <= arr[:, 0]) or np.any(arr[:, 3] <= arr[:, 1]):
        raise ValueError("every obstacle needs xmax > xmin and ymax > ymin")
    return arr


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
    """

    bounds: tuple[float, float, float, float] = (-1.0, -1.0, 1.0, 1.0)
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    agent_radius: float = 0.15
    capture_radius: float = 0.1
    walls: bool = True
    physics: Physics = field(default_factory=Physics)

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

    # ------------------------------------------------------------------ geometry
    @property
    def size(self) -> tuple[float, float]:
        """Width and height of the world."""
        return self.bounds[2] - self.bounds[0], self.bounds[3] - self.bounds[1]

    @property
    def has_obstacles(self) -> bool:
        return len(self.obstacles) > 0

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
