"""The parameters of the avoidance QP (:class:`AvoidanceConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["AvoidanceConfig"]


@dataclass(frozen=True)
class AvoidanceConfig:
    """Parameters of the avoidance QP (world units and seconds)."""

    radius: float = 0.15
    """AGV disc radius."""
    margin: float = 0.06
    """Safety margin added to the combined radius of two moving AGVs."""
    static_margin: float = 0.01
    """Margin against parked AGVs, walls, shelves and forbidden points (they do not move, so
    their positions are exact and a small margin suffices: gaps between parked AGVs stay open)."""
    time_horizon: float = 1.0
    """ORCA time horizon for AGV pairs: no collision within this time if both comply."""
    static_time_horizon: float | None = None
    """Time horizon against static (parked) AGVs; None: ``time_horizon``. A parked AGV is an
    obstacle, and RVO2 uses a shorter horizon for obstacles: with the full horizon an AGV
    creeps through a gap between two parked AGVs at a few cm/s."""
    obstacle_time_horizon: float = 0.25
    """Time horizon for walls, shelves and forbidden points."""
    dt: float = 0.1
    """Time step (used inside overlapping pairs, as RVO2 does)."""
    max_speed: float = 1.5
    """Speed limit, enforced as a regular polygon inscribed in this circle."""
    polygon_sides: int = 12
    max_neighbors: int = 8
    """AGV neighbours per AGV (nearest first)."""
    neighbor_dist: float = 2.0
    """Only AGVs closer than this are neighbours."""
    max_points: int = 4
    """Forbidden points per AGV (nearest first)."""
    max_shelves: int = 4
    """Shelves per AGV (nearest first)."""
    damping: float | None = None
    """With ``gain``: next velocity in ``(1 - damping) v + gain [-1, 1]^2`` (None: no limit)."""
    gain: float | None = None
    solver: str = "exact"
    """``"exact"``: :func:`solve_qp_2d`, the vectorised exact 2-D solver (default, fastest);
    ``"osqp"``: one block-diagonal OSQP problem per ``chunk_size`` AGVs."""
    native: bool | None = None
    """Exact solver only: run its C twin (:mod:`~allocator.avoidance.native`, the same
    candidates and tolerances, 10-20x faster at 1,000 AGVs). ``None`` (default): where it
    builds (a C compiler, no ``AGV_NATIVE=0``); ``False``: the numpy solvers; ``True``: the C
    solver or a ``RuntimeError``."""
    feasibility_tol: float = 1e-9
    """Exact solver: a row counts as satisfied within this slack (velocity units)."""
    eps: float = 1e-6
    """OSQP absolute and relative tolerance."""
    max_iter: int = 2000
    chunk_size: int = 128
    """AGVs per block-diagonal OSQP problem (larger batches are split)."""
    fallback_tol: float = 1e-4
    """An AGV counts as fallen back when its least violation exceeds this."""

    def __post_init__(self) -> None:
        for name in ("radius", "time_horizon", "obstacle_time_horizon", "dt", "max_speed",
                     "neighbor_dist", "eps"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"AvoidanceConfig.{name} must be positive, got {v!r}")
        if self.static_time_horizon is not None and not (
                np.isfinite(self.static_time_horizon) and self.static_time_horizon > 0):
            raise ValueError("AvoidanceConfig.static_time_horizon must be positive or None, "
                             f"got {self.static_time_horizon!r}")
        if self.margin < 0:
            raise ValueError(f"AvoidanceConfig.margin must be >= 0, got {self.margin!r}")
        if self.solver not in ("exact", "osqp"):
            raise ValueError(
                f"AvoidanceConfig.solver must be 'exact' or 'osqp', got {self.solver!r}"
            )
        if self.native not in (None, True, False):
            raise ValueError(
                f"AvoidanceConfig.native must be None, True or False, got {self.native!r}"
            )
        if not (np.isfinite(self.feasibility_tol) and self.feasibility_tol >= 0):
            raise ValueError("AvoidanceConfig.feasibility_tol must be finite and >= 0")
        if self.polygon_sides < 3:
            raise ValueError("AvoidanceConfig.polygon_sides must be at least 3")
        if (self.damping is None) != (self.gain is None):
            raise ValueError("give both damping and gain (the acceleration limit) or neither")

    @classmethod
    def for_world(cls, world: World, **overrides: Any) -> AvoidanceConfig:
        """Defaults matching a simulator world (radius, dt and the MPE acceleration limit)."""
        ph = world.physics
        base = dict(
            radius=world.agent_radius,
            dt=ph.dt,
            damping=ph.damping,
            gain=ph.sensitivity * ph.dt / ph.mass,
        )
        base.update(overrides)
        return cls(**base)

