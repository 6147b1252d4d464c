"""ORCA-style collision avoidance as one batched velocity QP.

Every AGV i picks its next velocity v_i as close as possible to its preferred velocity,
subject to linear constraints ``l <= a . v_i <= u``:

- the reciprocal ORCA half-planes of its nearest neighbours (RVO2's construction, each AGV
  taking half the responsibility; parked AGVs are static and the mover takes all of it, and so
  are "committed" AGVs, whose next velocity is already decided and is given),
- half-planes keeping it off points it must not touch (e.g. other AGVs' tasks, which it would
  otherwise claim in passing), the walls and the nearest shelves,
- its speed limit, as a regular polygon, and (optionally) the velocities its acceleration
  limit can reach in one step: ``(1 - damping) v + gain [-1, 1]^2``.

All AGVs of all scenes are solved at once. The default solver (``solver="exact"``,
:func:`solve_qp_2d`) is exact and vectorised over the AGVs: the optimum of a 2-D QP is the
preferred velocity, its projection onto one violated line, or a vertex where a violated line
meets another line, so the candidates of all AGVs are enumerated and checked as flat arrays.
``solver="osqp"`` solves one sparse block-diagonal OSQP problem whose sparsity pattern is fixed
(every AGV has the same number of rows, unused ones padded with ``a = 0`` and infinite bounds),
so consecutive steps only update the data and warm start.

When an AGV's constraints conflict, the QP of that AGV is infeasible. It then gets the "3-D"
program of ORCA: the velocity that minimises the largest (weighted) violation ``t`` of the soft
rows (plus a tiny pull towards the preferred velocity) while the speed and acceleration limits
stay hard; exact and vectorised as well (:func:`least_violation_2d`), or with OSQP
(:class:`LeastViolation`, AGVs found from OSQP's infeasibility certificate).
:class:`AvoidanceResult` reports who fell back.

The same QP is written in cvxpy in :func:`solve_reference` (readable, slow); the tests compare
the solvers. Build the rows (:meth:`VelocityAvoidance.constraints`) in one step and solve them
in another (:meth:`VelocityAvoidance.solve_rows`), as Python-RVO2 does.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = [
    "AvoidanceConfig",
    "AvoidanceResult",
    "ConstraintRows",
    "VelocityAvoidance",
    "orca_halfplanes",
    "solve_reference",
    "solve_qp_2d",
    "least_violation_2d",
    "LeastViolation",
    "HARD",
    "AGENT",
    "WALL",
    "POINT",
]

# Row kinds. Soft rows may be violated by the fallback, ``weight * t`` at most.
HARD, AGENT, WALL, POINT, PAD = 0, 1, 2, 3, 4
FALLBACK_WEIGHT = {AGENT: 1.0, WALL: 2.0, POINT: 4.0}
"""How much each soft kind may be violated relative to AGV-AGV rows in the fallback."""

_EPS = 1e-12


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
        if self.margin < 0:
            raise ValueError(f"AvoidanceConfig.margin must be >= 0, got {self.margin!r}")
        if self.solver not in ("exact", "osqp"):
            raise ValueError(
                f"AvoidanceConfig.solver must be 'exact' or 'osqp', got {self.solver!r}"
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


@dataclass
class ConstraintRows:
    """The QP of n AGVs: ``min ||v_i - pref_i||^2  s.t.  lower_i <= A_i v_i <= upper_i``.

    Attributes
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
        ``-inf`` / ``inf`` where unbounded; padded rows have ``A = 0`` and infinite bounds.
    preferred : np.ndarray, shape (n, 2)
    kind : np.ndarray of int, shape (R,)
        ``HARD``, ``AGENT``, ``WALL``, ``POINT`` or ``PAD`` per row slot.
    active : np.ndarray of bool, shape (n,)
        AGVs that move (static ones get velocity 0 and no rows).
    """

    A: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    preferred: np.ndarray
    kind: np.ndarray
    active: np.ndarray


@dataclass
class AvoidanceResult:
    """Output of one avoidance step.

    Attributes
    ----------
    velocity : np.ndarray, shape (..., N, 2)
        The new velocities (zero for static AGVs, the given ones for committed AGVs).
    fell_back : np.ndarray of bool, shape (..., N)
        AGVs whose constraints conflicted; their velocity minimises the largest violation.
    violation : np.ndarray, shape (..., N)
        That largest (weighted) violation ``t`` (0 where the QP was feasible).
    status : str
        ``"solved"`` (exact solver) or OSQP's status of the main solve.
    """

    velocity: np.ndarray
    fell_back: np.ndarray
    violation: np.ndarray
    status: str

    @property
    def any_fell_back(self) -> bool:
        return bool(self.fell_back.any())


def orca_halfplanes(
    rel_pos: np.ndarray,
    rel_vel: np.ndarray,
    velocity: np.ndarray,
    combined_radius: np.ndarray | float,
    time_horizon: float,
    dt: float,
    responsibility: np.ndarray | float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """RVO2's ORCA half-planes, vectorised: ``a . v <= b`` for each (agent, neighbour) pair.

    Parameters
    ----------
    rel_pos : np.ndarray, shape (..., 2)
        Neighbour position minus own position.
    rel_vel : np.ndarray, shape (..., 2)
        Own velocity minus neighbour velocity.
    velocity : np.ndarray, shape (..., 2)
        Own current velocity (the half-plane passes through ``velocity + responsibility * u``).
    combined_radius : float or np.ndarray, shape (...)
    time_horizon, dt : float
    responsibility : float or np.ndarray, shape (...)
        0.5 for reciprocal avoidance, 1 against a static obstacle.

    Returns
    -------
    a : np.ndarray, shape (..., 2)
        Outward normal of the allowed side is ``-a``; the constraint is ``a . v <= b``.
    b : np.ndarray, shape (...)
    """
    px, py = rel_pos[..., 0], rel_pos[..., 1]
    vx, vy = rel_vel[..., 0], rel_vel[..., 1]
    dist_sq = px * px + py * py
    R = np.broadcast_to(np.asarray(combined_radius, dtype=np.float64), dist_sq.shape)
    R_sq = R * R
    inv_t = 1.0 / time_horizon
    # No collision yet: the truncated velocity obstacle (cut-off circle or one of its legs).
    wx = vx - inv_t * px
    wy = vy - inv_t * py
    w_len_sq = wx * wx + wy * wy
    dot1 = wx * px + wy * py
    cutoff = (dot1 < 0.0) & (dot1 * dot1 > R_sq * w_len_sq)
    w_len = np.sqrt(np.maximum(w_len_sq, _EPS))
    # Leg directions: left (sign +1) or right (sign -1) of the cone.
    leg = np.sqrt(np.maximum(dist_sq - R_sq, 0.0))
    sign = np.where(px * wy - py * wx > 0.0, 1.0, -1.0)
    inv_d = 1.0 / np.maximum(dist_sq, _EPS)
    sleg = sign * leg
    dx = (sleg * px - R * py) * inv_d
    dy = (R * px + sleg * py) * inv_d
    dot2 = vx * dx + vy * dy
    # The half-plane's normal a = (dir_y, -dir_x) and u (the smallest change of velocity).
    ax, ay = dy, -dx
    ux, uy = dot2 * dx - vx, dot2 * dy - vy
    if cutoff.any():  # dir = (w_y, -w_x) / |w|, u = (R / t - |w|) w / |w|
        uwx, uwy = wx / w_len, wy / w_len
        scale = R * inv_t - w_len
        ax, ay = np.where(cutoff, -uwx, ax), np.where(cutoff, -uwy, ay)
        ux, uy = np.where(cutoff, scale * uwx, ux), np.where(cutoff, scale * uwy, uy)
    colliding = dist_sq <= R_sq
    if colliding.any():  # already overlapping: leave the overlap within one time step
        inv_dt = 1.0 / dt
        w2x = vx - inv_dt * px
        w2y = vy - inv_dt * py
        w2_len = np.sqrt(np.maximum(w2x * w2x + w2y * w2y, _EPS))
        uwx, uwy = w2x / w2_len, w2y / w2_len
        scale = R * inv_dt - w2_len
        ax, ay = np.where(colliding, -uwx, ax), np.where(colliding, -uwy, ay)
        ux, uy = np.where(colliding, scale * uwx, ux), np.where(colliding, scale * uwy, uy)
    resp = np.asarray(responsibility, dtype=np.float64)
    # RVO2: valid iff det(direction, point - v) <= 0  <=>  (dy, -dx) . v <= (dy, -dx) . point,
    # with point = velocity + responsibility * u.
    b = ax * (velocity[..., 0] + resp * ux) + ay * (velocity[..., 1] + resp * uy)
    a = np.stack([ax, ay], axis=-1)
    return a, b


def _nearest(dist: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k smallest entries along the last axis (sorted)."""
    c = dist.shape[-1]
    if k >= c:
        return np.argsort(dist, axis=-1, kind="stable")
    part = np.argpartition(dist, k - 1, axis=-1)[..., :k]
    order = np.argsort(np.take_along_axis(dist, part, axis=-1), axis=-1, kind="stable")
    return np.take_along_axis(part, order, axis=-1)


class VelocityAvoidance:
    """Batched ORCA velocity QP for all AGVs (exact vectorised solver, or OSQP).

    Parameters
    ----------
    world : World, optional
        Walls at its bounds and its shelves become constraints.
    config : AvoidanceConfig, optional
        Default :meth:`AvoidanceConfig.for_world` with a world, else ``AvoidanceConfig()``.
    **overrides
        Fields of :class:`AvoidanceConfig` to change.

    Examples
    --------
    Two AGVs heading at each other swerve instead of colliding:

    >>> import numpy as np
    >>> from allocator.avoidance import VelocityAvoidance
    >>> qp = VelocityAvoidance(radius=0.15)
    >>> pos = np.array([[-0.5, 0.0], [0.5, 0.0]])
    >>> vel = np.array([[1.0, 0.0], [-1.0, 0.0]])
    >>> out = qp.solve(pos, vel, preferred=vel)
    >>> bool(abs(out.velocity[0, 1]) > 0.1), out.fell_back.tolist()
    (True, [False, False])
    """

    def __init__(
        self, world: World | None = None, config: AvoidanceConfig | None = None,
        **overrides: Any,
    ) -> None:
        if config is None:
            config = AvoidanceConfig.for_world(world, **overrides) if world is not None \
                else AvoidanceConfig(**overrides)
        elif overrides:
            from dataclasses import replace

            config = replace(config, **overrides)
        self.config = config
        self.world = world
        ang = 2 * np.pi * (np.arange(config.polygon_sides) + 0.5) / config.polygon_sides
        self._poly = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # (P, 2)
        self._poly_cos = float(np.cos(np.pi / config.polygon_sides))
        self._solvers: dict[int, tuple[tuple[int, int], Any]] = {}
        self._fallback = LeastViolation()
        self.stats = {"solves": 0, "fallbacks": 0, "setup": 0}

    # ------------------------------------------------------------------ rows
    def constraints(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        preferred: np.ndarray,
        static: np.ndarray | None = None,
        points: np.ndarray | None = None,
        point_mask: np.ndarray | None = None,
        point_radius: float = 0.1,
        committed: np.ndarray | None = None,
    ) -> ConstraintRows:
        """Build every AGV's rows (see the module docstring); shapes as in :meth:`solve`.

        The rows are written into preallocated ``(B, N, R, 2)`` / ``(B, N, R)`` arrays, block
        by block (neighbours, forbidden points, walls, shelves, speed polygon, acceleration
        box); unused slots keep ``A = 0`` and infinite bounds.
        """
        c = self.config
        pos, vel, pref, static, points, point_mask = self._check(
            positions, velocities, preferred, static, points, point_mask
        )
        fixed = self._mask(committed, pos.shape[:2], positions, "committed") & ~static
        B, N, _ = pos.shape
        K = min(c.max_neighbors, N - 1)
        Q = min(c.max_points, 0 if points is None else points.shape[1])
        W = 4 if self.world is not None else 0
        S = min(c.max_shelves, len(self.world.obstacles)) \
            if self.world is not None and self.world.has_obstacles else 0
        P = c.polygon_sides
        D = 2 if c.damping is not None else 0
        sizes = ((K, AGENT), (Q, POINT), (W, WALL), (S, WALL), (P, HARD), (D, HARD))
        R = sum(k for k, _ in sizes)
        kind = np.concatenate([np.full(k, kd) for k, kd in sizes])
        A = np.zeros((B, N, R, 2))
        lo = np.full((B, N, R), -np.inf)
        hi = np.full((B, N, R), np.inf)
        nd_sq = c.neighbor_dist * c.neighbor_dist
        bi = np.arange(B)[:, None, None]

        # AGV neighbours (within one scene).
        if K:
            rel = pos[:, None, :, :] - pos[:, :, None, :]  # (B, N, N, 2): p_j - p_i
            d_sq = rel[..., 0] ** 2 + rel[..., 1] ** 2
            idx_n = np.arange(N)
            d_sq[:, idx_n, idx_n] = np.inf
            d_sq[d_sq >= nd_sq] = np.inf
            nb = _nearest(d_sq, K)  # (B, N, K)
            ok = np.isfinite(np.take_along_axis(d_sq, nb, axis=-1))
            rel_p = np.take_along_axis(rel, nb[..., None], axis=2)
            v_i = vel[:, :, None, :]
            st_j = static[bi, nb]
            a, b = orca_halfplanes(
                rel_p, v_i - vel[bi, nb], v_i, 2 * c.radius + np.where(st_j, c.static_margin,
                                                                        c.margin),
                c.time_horizon, c.dt, np.where(st_j | fixed[bi, nb], 1.0, 0.5),
            )
            A[:, :, :K] = np.where(ok[..., None], a, 0.0)
            hi[:, :, :K] = np.where(ok, b, np.inf)
        off = K

        # Forbidden points (static discs of radius point_radius).
        if Q:
            rel = points[:, None, :, :] - pos[:, :, None, :]  # (B, N, P, 2)
            d_sq = rel[..., 0] ** 2 + rel[..., 1] ** 2
            d_sq[~point_mask] = np.inf
            d_sq[d_sq >= nd_sq] = np.inf
            nb = _nearest(d_sq, Q)
            ok = np.isfinite(np.take_along_axis(d_sq, nb, axis=-1))
            rel_p = np.take_along_axis(rel, nb[..., None], axis=2)
            v_i = vel[:, :, None, :]
            a, b = orca_halfplanes(
                rel_p, v_i, v_i, point_radius + c.static_margin, c.obstacle_time_horizon, c.dt,
                1.0,
            )
            A[:, :, off:off + Q] = np.where(ok[..., None], a, 0.0)
            hi[:, :, off:off + Q] = np.where(ok, b, np.inf)
        off += Q

        # Walls: do not reach a wall (less radius and margin) within the obstacle horizon.
        if W:
            xmin, ymin, xmax, ymax = self.world.bounds
            r = c.radius + c.static_margin
            inv_t = 1.0 / c.obstacle_time_horizon
            A[:, :, off:off + 4] = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
            hi[:, :, off] = (xmax - r - pos[..., 0]) * inv_t
            hi[:, :, off + 1] = (pos[..., 0] - xmin - r) * inv_t
            hi[:, :, off + 2] = (ymax - r - pos[..., 1]) * inv_t
            hi[:, :, off + 3] = (pos[..., 1] - ymin - r) * inv_t
        off += W
        if S:
            obs = self.world.obstacles
            p = pos[:, :, None, :]
            closest = np.minimum(np.maximum(p, obs[:, :2]), obs[:, 2:])  # (B, N, O, 2)
            d_vec = p - closest
            d = np.sqrt(d_vec[..., 0] ** 2 + d_vec[..., 1] ** 2)
            nb = _nearest(d, S)
            d_s = np.take_along_axis(d, nb, axis=-1)
            dv = np.take_along_axis(d_vec, nb[..., None], axis=2)
            # A centre inside a shelf (only after a bad push) gives a zero row: no constraint.
            use = (d_s > 1e-9) & (d_s <= c.radius + c.neighbor_dist)
            normal = dv / np.maximum(d_s, 1e-9)[..., None]
            A[:, :, off:off + S] = np.where(use[..., None], -normal, 0.0)
            hi[:, :, off:off + S] = np.where(
                use, (d_s - c.radius - c.static_margin) / c.obstacle_time_horizon, np.inf
            )
        off += S

        # Speed polygon, widened where the current speed cannot be shed in one step.
        A[:, :, off:off + P] = self._poly
        if c.damping is not None:
            centre = (1.0 - c.damping) * vel
            reach = (np.sqrt(centre[..., 0] ** 2 + centre[..., 1] ** 2) - c.gain) / self._poly_cos
            hi[:, :, off:off + P] = np.maximum(c.max_speed, reach + 1e-6)[..., None]
        else:
            hi[:, :, off:off + P] = c.max_speed
        off += P

        # Acceleration box.
        if D:
            A[:, :, off, 0] = 1.0
            A[:, :, off + 1, 1] = 1.0
            lo[:, :, off:off + 2] = centre - c.gain
            hi[:, :, off:off + 2] = centre + c.gain

        # Static and committed AGVs: no rows (velocity 0, or the committed one).
        act = ~static & ~fixed
        if not act.all():
            A[~act] = 0.0
            lo[~act] = -np.inf
            hi[~act] = np.inf
        n = B * N
        return ConstraintRows(
            A.reshape(n, R, 2), lo.reshape(n, R), hi.reshape(n, R),
            np.where(act[..., None], pref, 0.0).reshape(n, 2), kind, act.reshape(n),
        )

    @staticmethod
    def _mask(mask: Any, shape: tuple[int, int], positions: Any, name: str) -> np.ndarray:
        """A (B, N) boolean mask from ``None`` (all False) or an (N,) / (B, N) array."""
        if mask is None:
            return np.zeros(shape, dtype=bool)
        m = np.asarray(mask, dtype=bool)
        single = np.ndim(positions) == 2
        m = m[None] if single and m.ndim == 1 else m
        if m.shape != shape:
            raise ValueError(f"{name} must have shape {shape[single:]}, got {m.shape[single:]}")
        return m

    def _check(
        self, positions: Any, velocities: Any, preferred: Any, static: Any, points: Any,
        point_mask: Any,
    ) -> tuple[np.ndarray, ...]:
        pos = np.asarray(positions, dtype=np.float64)
        single = pos.ndim == 2
        if single:
            pos = pos[None]
        if pos.ndim != 3 or pos.shape[-1] != 2:
            raise ValueError(f"positions must have shape (N, 2) or (B, N, 2), got {pos.shape}")
        B, N, _ = pos.shape
        out = [pos]
        for name, x in (("velocities", velocities), ("preferred", preferred)):
            arr = np.asarray(x, dtype=np.float64)
            arr = arr[None] if single else arr
            if arr.shape != pos.shape:
                raise ValueError(f"{name} must have the shape of positions {pos.shape[single:]}"
                                 f", got {arr.shape[single:]}")
            out.append(arr)
        for name, arr in zip(("positions", "velocities", "preferred"), out, strict=True):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contain NaN or infinite values")
        st = np.zeros((B, N), dtype=bool) if static is None else np.asarray(static, dtype=bool)
        st = st[None] if single and st.ndim == 1 else st
        if st.shape != (B, N):
            raise ValueError(f"static must have shape {(B, N)[single:]}, got {st.shape}")
        out.append(st)
        if points is None:
            out += [None, None]
        else:
            pts = np.asarray(points, dtype=np.float64)
            pts = pts[None] if single and pts.ndim == 2 else pts
            if pts.ndim != 3 or pts.shape[0] != B or pts.shape[2] != 2:
                raise ValueError(f"points must have shape (P, 2) or (B, P, 2), got {pts.shape}")
            m = np.ones((B, N, pts.shape[1]), dtype=bool) if point_mask is None else \
                np.asarray(point_mask, dtype=bool)
            m = m[None] if single and m.ndim == 2 else m
            if m.shape != (B, N, pts.shape[1]):
                raise ValueError(
                    f"point_mask must have shape {(B, N, pts.shape[1])[single:]}, got {m.shape}"
                )
            out += [pts, m]
        return tuple(out)

    # ------------------------------------------------------------------ solve
    def solve(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        preferred: np.ndarray,
        static: np.ndarray | None = None,
        points: np.ndarray | None = None,
        point_mask: np.ndarray | None = None,
        point_radius: float = 0.1,
        committed: np.ndarray | None = None,
    ) -> AvoidanceResult:
        """New velocities for every AGV, as close to ``preferred`` as the constraints allow.

        Parameters
        ----------
        positions, velocities, preferred : np.ndarray, shape (N, 2) or (B, N, 2)
            B independent scenes of N AGVs (AGVs of different scenes never interact).
            ``positions`` are where the AGVs are when the new velocity takes effect.
        static : np.ndarray of bool, shape (N,) or (B, N), optional
            Parked AGVs: obstacles for the others, velocity 0 themselves.
        points : np.ndarray, shape (P, 2) or (B, P, 2), optional
            Points to keep ``point_radius + margin`` away from (e.g. other AGVs' tasks).
        point_mask : np.ndarray of bool, shape (N, P) or (B, N, P), optional
            Which AGV must avoid which point (default all).
        point_radius : float
            Radius of the forbidden points.
        committed : np.ndarray of bool, shape (N,) or (B, N), optional
            AGVs whose next velocity is already decided, given in ``velocities`` (e.g. ones
            that could not honour their reciprocal rows): they get no rows and keep that
            velocity, and their neighbours take the full responsibility against them (with
            the moving margin). Ignored where ``static``.

        Returns
        -------
        AvoidanceResult
            ``velocity`` with the shape of ``positions``; ``fell_back`` marks AGVs whose
            constraints conflicted (their velocity least violates them).
        """
        rows = self.constraints(positions, velocities, preferred, static, points, point_mask,
                                point_radius, committed)
        vel, fell, viol, status = self.solve_rows(rows)
        shape = np.shape(positions)
        if committed is not None:  # committed AGVs keep their given velocity
            keep = np.asarray(committed, dtype=bool) & (
                True if static is None else ~np.asarray(static, dtype=bool))
            vel = np.where(np.broadcast_to(keep, shape[:-1]).reshape(-1, 1),
                           np.asarray(velocities, dtype=np.float64).reshape(-1, 2), vel)
        return AvoidanceResult(
            vel.reshape(shape), fell.reshape(shape[:-1]), viol.reshape(shape[:-1]), status
        )

    def solve_rows(self, rows: ConstraintRows) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        """Solve built rows: ``(velocity (n, 2), fell_back (n,), violation (n,), status)``.

        With ``config.solver == "exact"`` (default) every AGV's QP is solved exactly by
        :func:`solve_qp_2d`; the AGVs whose rows conflict get the exact least-violation
        velocity of :func:`least_violation_2d` (both vectorised over the AGVs).

        With ``"osqp"`` the problem (it separates per AGV) is solved as one block-diagonal OSQP
        problem, or several of ``config.chunk_size`` AGVs (each with its own warm-started
        solver): ADMM runs until its slowest block converges, and smaller problems stop sooner.
        """
        if self.config.solver == "exact":
            return self._solve_exact(rows)
        n = rows.A.shape[0]
        size = self.config.chunk_size
        if n <= size:
            return self._solve_chunk(rows, 0)
        parts = [
            self._solve_chunk(_take(rows, slice(k, min(k + size, n))), k // size)
            for k in range(0, n, size)
        ]
        status = next((p[3] for p in parts if not p[3].startswith("solved")), parts[0][3])
        return (
            np.concatenate([p[0] for p in parts]),
            np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]),
            status,
        )

    def _solve_exact(
        self, rows: ConstraintRows
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        n = rows.A.shape[0]
        self.stats["solves"] += 1
        v, ok = solve_qp_2d(rows.A, rows.lower, rows.upper, rows.preferred,
                            self.config.feasibility_tol)
        velocity = np.where(rows.active[:, None], v, 0.0)
        fell = np.zeros(n, dtype=bool)
        violation = np.zeros(n)
        bad = ~ok & rows.active
        if bad.any():
            idx = np.flatnonzero(bad)
            v, t = least_violation_2d(
                rows.A[idx], rows.lower[idx], rows.upper[idx], rows.preferred[idx],
                self._weight(rows.kind), self._fallback.regularization,
                self.config.feasibility_tol,
            )
            velocity[idx] = v
            fell[idx] = t > self.config.fallback_tol
            violation[idx] = np.where(fell[idx], t, 0.0)
            self.stats["fallbacks"] += int(fell.sum())
        return velocity, fell, violation, "solved"

    @staticmethod
    def _weight(kind: np.ndarray) -> np.ndarray:
        """Fallback weight per row slot (0: hard), shape (R,)."""
        return np.array([FALLBACK_WEIGHT.get(int(k), 0.0) for k in kind])

    def _solve_chunk(
        self, rows: ConstraintRows, chunk: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        import osqp

        n, R, _ = rows.A.shape
        self.stats["solves"] += 1
        solver = self._solvers.get(chunk)
        if solver is None or solver[0] != (n, R):
            self._solvers[chunk] = solver = ((n, R), self._setup(n, R))
        solver = solver[1]
        data = rows.A.transpose(0, 2, 1).reshape(-1)  # CSC order: column 2i then 2i+1
        lo = rows.lower.reshape(-1).copy()
        hi = rows.upper.reshape(-1).copy()
        q = -rows.preferred.reshape(-1)
        soft = (rows.kind != HARD) & (rows.kind != PAD)
        suspects = np.zeros(n, dtype=bool)
        # AGVs whose preferred velocity already satisfies their rows keep it: switch their
        # rows off so they cost the solver nothing (the pattern stays fixed).
        at_pref = np.einsum("nrk,nk->nr", rows.A, rows.preferred)
        free = ((at_pref <= rows.upper + 1e-12) & (at_pref >= rows.lower - 1e-12)).all(axis=1)
        if free.all():
            return np.where(rows.active[:, None], rows.preferred, 0.0), suspects, \
                np.zeros(n), "solved"
        lo[np.repeat(free, R)] = -np.inf
        hi[np.repeat(free, R)] = np.inf
        solver.update(q=q, l=lo, u=hi, Ax=data)
        for _ in range(6):
            res = solver.solve(raise_error=False)
            status = res.info.status
            if res.info.status_val in (osqp.SolverStatus.OSQP_SOLVED,
                                       osqp.SolverStatus.OSQP_SOLVED_INACCURATE):
                break
            if res.info.status_val == osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE:
                new = self._certificate_blocks(res.prim_inf_cert, n, R)
            else:  # stalled: treat every AGV whose rows the iterate violates as a suspect
                new = self._violated(res.x, rows)
            new &= rows.active & ~suspects
            if not new.any():
                new = rows.active & ~suspects
            suspects |= new
            # The suspects get their own least-violation program; the others are re-solved
            # with the suspects' soft rows switched off (warm started).
            relax = (suspects[:, None] & soft[None, :]).reshape(-1)
            solver.update(l=np.where(relax, -np.inf, lo), u=np.where(relax, np.inf, hi))
            if not (rows.active & ~suspects).any():
                break
        x = res.x.reshape(n, 2) if status.startswith("solved") else np.zeros((n, 2))
        velocity = np.where(rows.active[:, None], x, 0.0)
        violation = np.zeros(n)
        fell = np.zeros(n, dtype=bool)
        if suspects.any():
            idx = np.flatnonzero(suspects)
            v, t = self._fallback.solve(_take(rows, idx), self.config.eps)
            velocity[idx] = v
            fell[idx] = t > self.config.fallback_tol
            violation[idx] = np.where(fell[idx], t, 0.0)
            self.stats["fallbacks"] += int(fell.sum())
        return velocity, fell, violation, status

    @staticmethod
    def _certificate_blocks(cert: np.ndarray, n: int, R: int) -> np.ndarray:
        """AGVs whose rows carry OSQP's infeasibility certificate (a superset of the culprits:
        a wrongly suspected AGV gets t = 0 and its QP velocity from the fallback program)."""
        y = np.abs(np.asarray(cert, dtype=np.float64).reshape(n, R)).max(axis=1)
        top = y.max() if y.size else 0.0
        return y > 1e-6 * top if top > 0 else np.zeros(n, dtype=bool)

    @staticmethod
    def _violated(x: np.ndarray, rows: ConstraintRows, tol: float = 1e-4) -> np.ndarray:
        n = rows.A.shape[0]
        v = np.asarray(x, dtype=np.float64).reshape(n, 2)
        if not np.all(np.isfinite(v)) or np.abs(v).max() > 1e6:
            return rows.active.copy()
        av = np.einsum("nrk,nk->nr", rows.A, v)
        return ((av > rows.upper + tol) | (av < rows.lower - tol)).any(axis=1)

    def _setup(self, n: int, R: int) -> Any:
        import osqp

        self.stats["setup"] += 1
        c = self.config
        indptr = np.arange(2 * n + 1, dtype=np.int64) * R
        rows_idx = (np.arange(n)[:, None] * R + np.arange(R)[None, :])  # (n, R)
        indices = np.repeat(rows_idx, 2, axis=0).reshape(-1)
        A = sp.csc_matrix((np.ones(2 * n * R), indices, indptr), shape=(n * R, 2 * n))
        P = sp.identity(2 * n, format="csc")
        solver = osqp.OSQP()
        solver.setup(
            P, np.zeros(2 * n), A, np.full(n * R, -np.inf), np.full(n * R, np.inf),
            verbose=False, polishing=False, warm_starting=True, eps_abs=c.eps, eps_rel=c.eps,
            max_iter=c.max_iter, eps_prim_inf=1e-3, adaptive_rho=True,
        )
        return solver


def _take(rows: ConstraintRows, idx: Any) -> ConstraintRows:
    """The rows of some AGVs."""
    return ConstraintRows(rows.A[idx], rows.lower[idx], rows.upper[idx], rows.preferred[idx],
                          rows.kind, rows.active[idx])


def _one_sided(
    A: np.ndarray, lower: np.ndarray, upper: np.ndarray, weight: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rewrite ``lower <= A v <= upper`` as ``G v <= h`` with unit rows.

    Parameters
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
    weight : np.ndarray, shape (R,), optional
        Fallback weight of each row slot (0: hard).

    Returns
    -------
    G : np.ndarray, shape (n, K, 2)
        Unit normals (row slots whose bound is infinite for every AGV are dropped; a lower
        bound becomes the row ``-a . v <= -lower``). Zero rows get ``G = 0``.
    h : np.ndarray, shape (n, K)
        ``+inf`` where a row is absent (padding, or a zero row that holds anyway); negative
        where a zero row can never hold (the AGV is then infeasible).
    w : np.ndarray, shape (n, K)
        ``weight`` divided by the row's length (lower-bound rows are hard, as in
        :func:`solve_reference`); zeros without ``weight``.
    """
    up = np.isfinite(upper).any(axis=0)
    down = np.isfinite(lower).any(axis=0)
    wt = np.zeros(A.shape[1]) if weight is None else np.asarray(weight, dtype=np.float64)
    if down.any():
        G = np.concatenate([A[:, up], -A[:, down]], axis=1)
        h = np.concatenate([upper[:, up], -lower[:, down]], axis=1)
        wt = np.concatenate([wt[up], np.zeros(int(down.sum()))])
    else:
        G, h, wt = A[:, up], upper[:, up], wt[up]
    norm = np.sqrt(G[..., 0] ** 2 + G[..., 1] ** 2)
    zero = norm < 1e-12
    if zero.any():
        h = np.where(zero & (h >= 0.0), np.inf, h)
        norm = np.where(zero, 1.0, norm)
    inv = 1.0 / norm
    return G * inv[..., None], h * inv, wt * inv


def _intersect(
    n1x: np.ndarray, n1y: np.ndarray, d1: np.ndarray,
    n2x: np.ndarray, n2y: np.ndarray, d2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersections of the lines ``n1 . v = d1`` and ``n2 . v = d2`` (any equal shapes):
    ``(x, y, valid)``, valid where the lines are not (nearly) parallel and ``d`` finite."""
    det = n1x * n2y - n1y * n2x
    scale = np.sqrt((n1x * n1x + n1y * n1y) * (n2x * n2x + n2y * n2y))
    valid = (np.abs(det) > 1e-10 * scale) & np.isfinite(d1) & np.isfinite(d2) & (scale > 0)
    inv = np.where(valid, 1.0 / np.where(valid, det, 1.0), 0.0)
    d1 = np.where(valid, d1, 0.0)
    d2 = np.where(valid, d2, 0.0)
    return (d1 * n2y - d2 * n1y) * inv, (n1x * d2 - n2x * d1) * inv, valid


def _solve2(
    ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray, rx: np.ndarray,
    ry: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(alpha, beta, valid)`` with ``alpha a + beta b = r`` (2-vectors, any equal shapes)."""
    det = ax * by - ay * bx
    valid = np.abs(det) > 1e-14
    inv = np.where(valid, 1.0 / np.where(valid, det, 1.0), 0.0)
    return (rx * by - ry * bx) * inv, (ax * ry - ay * rx) * inv, valid


def _project(
    qx: np.ndarray, qy: np.ndarray, nx: np.ndarray, ny: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projections of the points ``q`` onto the lines ``n . v = d``: ``(x, y, valid)``."""
    nn = nx * nx + ny * ny
    valid = (nn > 1e-20) & np.isfinite(d) & np.isfinite(qx) & np.isfinite(qy)
    f = np.where(valid, (nx * qx + ny * qy - np.where(valid, d, 0.0)) / np.where(valid, nn, 1.0),
                 0.0)
    return qx - f * nx, qy - f * ny, valid


def solve_qp_2d(
    A: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    preferred: np.ndarray,
    tol: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``min ||v_i - pref_i||^2 s.t. lower_i <= A_i v_i <= upper_i`` for many 2-D QPs.

    The minimiser is the Euclidean projection of ``pref_i`` onto the feasible polygon, so it
    is ``pref_i`` itself, the projection of ``pref_i`` onto one violated line, or a vertex
    where a violated line meets another line (KKT: at least one active line is violated by
    ``pref_i``). The candidates of all AGVs are enumerated as flat arrays and checked at
    once (no loop over AGVs): first the projections onto the violated lines, ``E`` (AGV,
    line) pairs checked against all ``K`` rows, ``(E, K)``; then, only for AGVs none of whose
    projections is feasible, the vertices of each violated line with every other line whose
    KKT multipliers are non-negative, again ``(E', K)``. Any feasible point is at least as far
    from ``pref_i`` as the optimum, and the optimum is a candidate, so the feasible candidate
    nearest ``pref_i`` is the optimum (up to ``tol``).

    Parameters
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
        ``-inf`` / ``inf`` where unbounded (padded rows: ``A = 0``, infinite bounds).
    preferred : np.ndarray, shape (n, 2)
    tol : float
        A row holds when ``a . v <= b + tol`` (rows normalised to unit normals).

    Returns
    -------
    velocity : np.ndarray, shape (n, 2)
        The optimum; ``preferred`` where the rows conflict.
    feasible : np.ndarray of bool, shape (n,)
        False where no point satisfies every row (within ``tol``).
    """
    pref = np.asarray(preferred, dtype=np.float64)
    n = pref.shape[0]
    velocity = pref.copy()
    feasible = np.ones(n, dtype=bool)
    if n == 0 or A.shape[1] == 0:
        return velocity, feasible
    G, h, _ = _one_sided(A, lower, upper)
    gx, gy = G[..., 0], G[..., 1]
    s = gx * pref[:, None, 0] + gy * pref[:, None, 1] - h  # (n, K): violation at pref
    violated = s > tol
    need = violated.any(axis=1)
    if not need.any():
        return velocity, feasible
    K = h.shape[1]

    # 1. Projections onto the violated lines, one candidate per (AGV i, line k) pair:
    #    c = p - s_k g_k, where row j has slack g_j . c - h_j = s_j - s_k (g_j . g_k).
    ai, ki = np.nonzero(violated)  # (E,)
    sk = s[ai, ki]
    gram = gx[ai] * gx[ai, ki, None] + gy[ai] * gy[ai, ki, None]  # (E, K)
    ok = (s[ai] - sk[:, None] * gram <= tol).all(axis=1)
    done = np.zeros(n, dtype=bool)
    if ok.any():
        # The nearest feasible projection of each AGV (candidates sorted by AGV, then s_k).
        ai_ok, ki_ok, sk_ok = ai[ok], ki[ok], sk[ok]
        order = np.lexsort((sk_ok, ai_ok))
        first = np.unique(ai_ok[order], return_index=True)[1]
        sel = order[first]
        i, k = ai_ok[sel], ki_ok[sel]
        velocity[i] = pref[i] - sk_ok[sel, None] * G[i, k]
        done[i] = True
    rest = need & ~done
    if not rest.any():
        return velocity, feasible

    # 2. Vertices where a violated line j meets another line k, one candidate per (i, j, k);
    #    kept when the KKT multipliers of p - c = l_j g_j + l_k g_k are both >= 0 (that
    #    vertex is then the optimum if it is feasible).
    ai, ji = np.nonzero(violated & rest[:, None])
    E = ai.size
    ai = np.repeat(ai, K)
    ji = np.repeat(ji, K)
    ki = np.tile(np.arange(K), E)
    gjx, gjy, hj = gx[ai, ji], gy[ai, ji], h[ai, ji]
    gkx, gky, hk = gx[ai, ki], gy[ai, ki], h[ai, ki]
    det = gjx * gky - gjy * gkx
    pair = (np.abs(det) > 1e-12) & np.isfinite(hk)
    ai, ji, ki = ai[pair], ji[pair], ki[pair]
    gjx, gjy, hj, gkx, gky, hk = (x[pair] for x in (gjx, gjy, hj, gkx, gky, hk))
    inv = 1.0 / det[pair]
    cx = (hj * gky - hk * gjy) * inv
    cy = (gjx * hk - gkx * hj) * inv
    dx, dy = pref[ai, 0] - cx, pref[ai, 1] - cy
    lam_j = (dx * gky - dy * gkx) * inv
    lam_k = (gjx * dy - gjy * dx) * inv
    kkt = (lam_j >= -1e-6) & (lam_k >= -1e-6)  # loose: extra candidates cost nothing
    ai, cx, cy, dx, dy = ai[kkt], cx[kkt], cy[kkt], dx[kkt], dy[kkt]
    ok = (gx[ai] * cx[:, None] + gy[ai] * cy[:, None] - h[ai] <= tol).all(axis=1)
    if ok.any():
        ai, cx, cy = ai[ok], cx[ok], cy[ok]
        order = np.lexsort((dx[ok] ** 2 + dy[ok] ** 2, ai))
        first = np.unique(ai[order], return_index=True)[1]
        sel = order[first]
        velocity[ai[sel], 0] = cx[sel]
        velocity[ai[sel], 1] = cy[sel]
        rest[ai[sel]] = False
    feasible[rest] = False
    return velocity, feasible


@lru_cache(maxsize=64)
def _combinations(k: int, r: int) -> np.ndarray:
    """All r-subsets of range(k), shape (C(k, r), r)."""
    return np.array(list(combinations(range(k), r)), dtype=np.intp).reshape(-1, r)


def least_violation_2d(
    A: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    preferred: np.ndarray,
    weight: np.ndarray,
    regularization: float = 1e-3,
    tol: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact ORCA "3-D" program for many AGVs whose rows conflict, vectorised.

    Per AGV: ``min t + (r / 2) ||v - pref||^2`` s.t. ``a . v - w t <= upper`` on soft rows
    (``w > 0``), ``a . v <= upper`` on hard rows (``w = 0``), ``a . v >= lower`` (hard),
    ``t >= 0`` (the program of :class:`LeastViolation` and :func:`solve_reference`).

    With ``t(v) = max(0, max_soft (a . v - upper) / w)`` this is ``min t(v) + (r / 2)
    ||v - pref||^2`` over the hard polygon. Where the rows conflict, ``t > 0`` at the optimum
    and its KKT multipliers can be carried by at most three independent active constraints,
    one of them soft, so the optimum is one of: ``q_k = pref - (a_k / w_k) / r`` (one soft row),
    ``q_k`` projected onto a hard line, a hard vertex, ``q_j`` projected onto the "tie line"
    of two soft rows (where their scaled violations are equal), a tie line meeting a hard line,
    or two tie lines meeting. All these candidates are enumerated for all AGVs at once; the
    one with the least objective inside the hard polygon is the optimum.

    Parameters
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
    preferred : np.ndarray, shape (n, 2)
    weight : np.ndarray, shape (R,)
        ``w`` per row slot (0: hard).
    regularization : float
        ``r`` (> 0).
    tol : float
        Slack allowed on the hard rows.

    Returns
    -------
    velocity : np.ndarray, shape (n, 2)
        Zero where even the hard rows conflict.
    violation : np.ndarray, shape (n,)
        ``t`` at the optimum (``inf`` where the hard rows conflict).

    Notes
    -----
    Meant for infeasible QPs (call :func:`solve_qp_2d` first): where the rows are compatible,
    the optimum can have ``t = 0`` with no soft row active, which is not enumerated.
    """
    pref = np.asarray(preferred, dtype=np.float64)
    n = pref.shape[0]
    velocity = np.zeros((n, 2))
    violation = np.full(n, np.inf)
    if n == 0:
        return velocity, violation
    r = float(regularization)
    G, h, w = _one_sided(A, lower, upper, weight)
    present = np.isfinite(h).any(axis=0)
    S = np.flatnonzero((w > 0).any(axis=0) & present)
    H = np.flatnonzero(~(w > 0).any(axis=0) & present)
    gx, gy = G[..., 0], G[..., 1]
    px, py = pref[:, 0:1], pref[:, 1:2]
    ws = w[:, S]
    ux, uy, c = gx[:, S] / ws, gy[:, S] / ws, h[:, S] / ws  # scaled soft rows: u . v - c
    qx, qy = px - ux / r, py - uy / r
    hx, hy, hh = gx[:, H], gy[:, H], h[:, H]
    Ks, Kh = S.size, H.size
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    # Each candidate is kept only where its KKT multipliers have the right signs:
    # r (pref - v) = sum_soft mu_i u_i + sum_hard nu_l g_l, mu >= 0, sum mu = 1, nu >= 0.
    neg = -1e-7  # loose: an extra candidate costs nothing, a missing one the optimum
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        parts.append((qx, qy, np.isfinite(c)))  # one soft row: mu = 1
        if Kh:
            # q_k projected onto a hard line: nu = (r (p - v) - u_k) . g_l.
            x, y, ok = _project(qx[:, :, None], qy[:, :, None], hx[:, None], hy[:, None],
                                hh[:, None])
            nu = (r * (px[:, :, None] - x) - ux[:, :, None]) * hx[:, None] \
                + (r * (py[:, :, None] - y) - uy[:, :, None]) * hy[:, None]
            parts.append((x, y, ok & np.isfinite(c)[:, :, None] & (nu >= neg)))
            i1, i2 = _combinations(Kh, 2).T
            parts.append(_intersect(hx[:, i1], hy[:, i1], hh[:, i1],
                                    hx[:, i2], hy[:, i2], hh[:, i2]))  # hard vertex
        if Ks >= 2:
            j, k = _combinations(Ks, 2).T
            tx, ty, td = ux[:, j] - ux[:, k], uy[:, j] - uy[:, k], c[:, j] - c[:, k]
            # Two soft rows tie: r (p - v) - u_k = mu (u_j - u_k), 0 <= mu <= 1.
            x, y, ok = _project(qx[:, j], qy[:, j], tx, ty, td)
            mu = ((r * (px - x) - ux[:, k]) * tx + (r * (py - y) - uy[:, k]) * ty) \
                / (tx * tx + ty * ty)
            parts.append((x, y, ok & (mu >= neg) & (mu <= 1 - neg)))
            if Kh:
                # ... and a hard line: r (p - v) - u_k = mu (u_j - u_k) + nu g_l.
                x, y, ok = _intersect(tx[:, :, None], ty[:, :, None], td[:, :, None],
                                      hx[:, None], hy[:, None], hh[:, None])
                rx = r * (px[:, :, None] - x) - ux[:, k, None]
                ry = r * (py[:, :, None] - y) - uy[:, k, None]
                mu, nu, ok2 = _solve2(tx[:, :, None], ty[:, :, None], hx[:, None], hy[:, None],
                                      rx, ry)
                parts.append((x, y, ok & ok2 & (mu >= neg) & (mu <= 1 - neg) & (nu >= neg)))
        if Ks >= 3:
            j, k, l = _combinations(Ks, 3).T
            # Three soft rows tie: r (p - v) - u_j = mu_k (u_k - u_j) + mu_l (u_l - u_j).
            x, y, ok = _intersect(
                ux[:, j] - ux[:, k], uy[:, j] - uy[:, k], c[:, j] - c[:, k],
                ux[:, j] - ux[:, l], uy[:, j] - uy[:, l], c[:, j] - c[:, l],
            )
            mk, ml, ok2 = _solve2(ux[:, k] - ux[:, j], uy[:, k] - uy[:, j],
                                  ux[:, l] - ux[:, j], uy[:, l] - uy[:, j],
                                  r * (px - x) - ux[:, j], r * (py - y) - uy[:, j])
            parts.append((x, y, ok & ok2 & (mk >= neg) & (ml >= neg) & (mk + ml <= 1 - neg)))
    X = np.concatenate([p[0].reshape(n, -1) for p in parts], axis=1)
    Y = np.concatenate([p[1].reshape(n, -1) for p in parts], axis=1)
    ok = np.concatenate([p[2].reshape(n, -1) for p in parts], axis=1)
    ai, ci = np.nonzero(ok)
    x, y = X[ai, ci], Y[ai, ci]
    inside = (hx[ai] * x[:, None] + hy[ai] * y[:, None] - hh[ai] <= tol).all(axis=1)
    ai, x, y = ai[inside], x[inside], y[inside]
    t = np.maximum((ux[ai] * x[:, None] + uy[ai] * y[:, None] - c[ai]).max(axis=1, initial=0.0),
                   0.0)
    f = t + 0.5 * r * ((x - pref[ai, 0]) ** 2 + (y - pref[ai, 1]) ** 2)
    if ai.size:
        order = np.lexsort((f, ai))
        agents, first = np.unique(ai[order], return_index=True)
        sel = order[first]
        velocity[agents, 0] = x[sel]
        velocity[agents, 1] = y[sel]
        violation[agents] = t[sel]
    return velocity, violation


class LeastViolation:
    """ORCA's "3-D" program for AGVs whose rows conflict, batched in one OSQP problem.

    Per AGV: ``min t + (regularization / 2) ||v - pref||^2`` s.t. ``a . v - w t <= u`` on
    soft rows (``w`` from :data:`FALLBACK_WEIGHT`), the hard rows (speed polygon, acceleration
    box) unchanged, ``t >= 0``. Where the rows are compatible the optimum has ``t = 0`` and
    ``v`` equals the QP solution (the penalty on ``t`` is exact), so one solve serves all AGVs.
    The sparsity pattern is fixed per (n, R), so repeated calls update and warm start.
    """

    def __init__(self, regularization: float = 1e-3) -> None:
        self.regularization = regularization
        self._solver: Any = None
        self._key: tuple[int, int] | None = None

    def problem(
        self, rows: ConstraintRows
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(dense (n, R + 1, 3), lower (n, R + 1), upper (n, R + 1), q (3 n,))``."""
        n, R, _ = rows.A.shape
        weight = np.array([FALLBACK_WEIGHT.get(int(k), 0.0) for k in rows.kind])
        t_col = np.broadcast_to(-weight, (n, R))[..., None]
        dense = np.concatenate([rows.A, t_col], axis=2)
        t_row = np.zeros((n, 1, 3))
        t_row[..., 2] = 1.0
        dense = np.concatenate([dense, t_row], axis=1)
        lo = np.concatenate([rows.lower, np.zeros((n, 1))], axis=1)
        hi = np.concatenate([rows.upper, np.full((n, 1), np.inf)], axis=1)
        q = np.concatenate(
            [-self.regularization * rows.preferred, rows.active[:, None].astype(float)], axis=1
        ).reshape(-1)
        return dense, lo, hi, q

    def solve(self, rows: ConstraintRows, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Velocities (n, 2) and violations t (n,) (``inf`` where even the hard rows conflict).

        When the joint solve does not converge, each AGV is solved on its own (a stalled block
        must not cost the others their answer)."""
        import osqp

        n, R, _ = rows.A.shape
        dense, lo, hi, q = self.problem(rows)
        if self._solver is None or self._key != (n, R):
            R1 = R + 1
            indptr = np.arange(3 * n + 1, dtype=np.int64) * R1
            rows_idx = np.arange(n)[:, None] * R1 + np.arange(R1)[None, :]
            indices = np.repeat(rows_idx, 3, axis=0).reshape(-1)
            A = sp.csc_matrix((np.ones(3 * n * R1), indices, indptr), shape=(n * R1, 3 * n))
            P = sp.diags(np.tile([self.regularization, self.regularization, 0.0], n),
                         format="csc")
            self._solver = osqp.OSQP()
            self._solver.setup(
                P, q, A, lo.reshape(-1), hi.reshape(-1), verbose=False, polishing=False,
                eps_abs=eps * 0.1, eps_rel=eps * 0.1, max_iter=50000, warm_starting=True,
            )
            self._key = (n, R)
        self._solver.update(q=q, l=lo.reshape(-1), u=hi.reshape(-1),
                            Ax=dense.transpose(0, 2, 1).reshape(-1))
        res = self._solver.solve(raise_error=False)
        if not res.info.status.startswith("solved"):
            if n > 1:  # one slow block stalls ADMM for all: solve them one by one
                parts = [LeastViolation(self.regularization).solve(_take(rows, [i]), eps)
                         for i in range(n)]
                return np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts])
            return np.zeros((n, 2)), np.where(rows.active, np.inf, 0.0)
        z = res.x.reshape(n, 3)
        velocity = np.where(rows.active[:, None], z[:, :2], 0.0)
        return velocity, np.maximum(z[:, 2], 0.0) * rows.active


def solve_reference(
    rows: ConstraintRows, fallback_regularization: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """The same QP (and fallback) written in cvxpy, one small problem per AGV: the readable
    reference the OSQP path is tested against.

    Returns
    -------
    velocity : np.ndarray, shape (n, 2)
    fell_back : np.ndarray of bool, shape (n,)
    """
    import cvxpy as cp

    n = rows.A.shape[0]
    out = np.zeros((n, 2))
    fell = np.zeros(n, dtype=bool)
    weight = np.array([FALLBACK_WEIGHT.get(int(k), 0.0) for k in rows.kind])
    for i in np.flatnonzero(rows.active):
        A, lo, hi, pref = rows.A[i], rows.lower[i], rows.upper[i], rows.preferred[i]
        up, down = np.isfinite(hi), np.isfinite(lo)
        v = cp.Variable(2)
        cons = []
        if up.any():
            cons.append(A[up] @ v <= hi[up])
        if down.any():
            cons.append(A[down] @ v >= lo[down])
        prob = cp.Problem(cp.Minimize(cp.sum_squares(v - pref)), cons)
        prob.solve(solver=cp.CLARABEL)
        if prob.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            out[i] = v.value
            continue
        # Least violation: min t s.t. a.v - w t <= u (soft), hard rows kept.
        fell[i] = True
        t = cp.Variable()
        hard = weight == 0.0
        cons = [t >= 0]
        su, hu = up & ~hard, up & hard
        if su.any():
            cons.append(A[su] @ v - weight[su] * t <= hi[su])
        if hu.any():
            cons.append(A[hu] @ v <= hi[hu])
        if down.any():
            cons.append(A[down] @ v >= lo[down])
        obj = t + fallback_regularization / 2 * cp.sum_squares(v - pref)
        cp.Problem(cp.Minimize(obj), cons).solve(solver=cp.CLARABEL)
        out[i] = v.value
    return out, fell
