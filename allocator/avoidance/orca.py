"""The ORCA rows: RVO2's reciprocal half-planes (:func:`orca_halfplanes`) and every AGV's rows
of the velocity QP (:func:`build_rows`: neighbours, forbidden points, walls, shelves, the speed
polygon and the acceleration box)."""

from __future__ import annotations

from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from allocator.avoidance.config import AvoidanceConfig
from allocator.avoidance.rows import AGENT, HARD, POINT, WALL, ConstraintRows

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["orca_halfplanes", "build_rows", "speed_polygon", "neighbours", "DENSE_MAX"]

_EPS = 1e-12


def orca_halfplanes(
    rel_pos: np.ndarray,
    rel_vel: np.ndarray,
    velocity: np.ndarray,
    combined_radius: np.ndarray | float,
    time_horizon: float | np.ndarray,
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
    time_horizon : float or np.ndarray, shape (...)
    dt : float
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

DENSE_MAX = 64
"""Up to this many AGVs per scene the neighbours come from the dense distance matrix (fastest
for the paper's small scenes and large batches); above it from a k-d tree per scene."""


def neighbours(pos: np.ndarray, k: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Each AGV's ``k`` nearest other AGVs of its scene closer than ``radius``.

    Parameters
    ----------
    pos : np.ndarray, shape (B, N, 2)
    k : int
        At most ``N - 1``.
    radius : float

    Returns
    -------
    index : np.ndarray of int, shape (B, N, k)
        Neighbour indices within the scene, nearest first (any index where not ``valid``).
    valid : np.ndarray of bool, shape (B, N, k)
        A neighbour closer than ``radius``.

    Notes
    -----
    ``N <= DENSE_MAX``: the dense ``(B, N, N)`` distance matrix; above, a
    ``scipy.spatial.cKDTree`` query per scene, ``O(N log N)`` (a 1,000-AGV floor costs about a
    millisecond instead of the dense matrix's tens).
    """
    B, N, _ = pos.shape
    r_sq = radius * radius
    if N <= DENSE_MAX:
        rel = pos[:, None, :, :] - pos[:, :, None, :]
        d_sq = rel[..., 0] ** 2 + rel[..., 1] ** 2
        idx_n = np.arange(N)
        d_sq[:, idx_n, idx_n] = np.inf
        d_sq[d_sq >= r_sq] = np.inf
        nb = _nearest(d_sq, k)
        return nb, np.isfinite(np.take_along_axis(d_sq, nb, axis=-1))
    from scipy.spatial import cKDTree

    index = np.empty((B, N, k), dtype=np.intp)
    valid = np.empty((B, N, k), dtype=bool)
    own = np.arange(N)[:, None]
    for b in range(B):  # B is small wherever N is large
        d, j = cKDTree(pos[b]).query(pos[b], k=k + 1, distance_upper_bound=radius)
        j = j.reshape(N, k + 1)
        d = d.reshape(N, k + 1)
        # drop each AGV itself (first, unless another AGV sits exactly on it)
        d = np.where(j == own, np.inf, d)
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        d = np.take_along_axis(d, order, axis=1)
        j = np.take_along_axis(j, order, axis=1)
        ok = np.isfinite(d) & (d * d < r_sq)
        index[b] = np.where(ok, j, 0)
        valid[b] = ok
    return index, valid


@lru_cache(maxsize=8)
def speed_polygon(sides: int) -> tuple[np.ndarray, float]:
    """Unit normals ``(P, 2)`` of the regular speed polygon and ``cos(pi / P)`` (read-only)."""
    ang = 2 * np.pi * (np.arange(sides) + 0.5) / sides
    poly = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # (P, 2)
    poly.setflags(write=False)
    return poly, float(np.cos(np.pi / sides))


def build_rows(
    c: AvoidanceConfig,
    world: World | None,
    pos: np.ndarray,
    vel: np.ndarray,
    pref: np.ndarray,
    static: np.ndarray,
    points: np.ndarray | None,
    point_mask: np.ndarray | None,
    point_radius: float,
    fixed: np.ndarray,
    static_reference: np.ndarray | None = None,
) -> ConstraintRows:
    """Every AGV's rows of the velocity QP, for B scenes of N AGVs.

    The rows are written into preallocated ``(B, N, R, 2)`` / ``(B, N, R)`` arrays, block by
    block (neighbours, forbidden points, walls, shelves, speed polygon, acceleration box);
    unused slots keep ``A = 0`` and infinite bounds.

    Parameters
    ----------
    c : AvoidanceConfig
    world : World, optional
        Walls at its bounds and its shelves become rows.
    pos, vel, pref : np.ndarray, shape (B, N, 2)
        Positions, current and preferred velocities (validated, float64).
    static : np.ndarray of bool, shape (B, N)
        Parked AGVs: obstacles for the others, no rows themselves.
    points : np.ndarray, shape (B, P, 2), optional
        Forbidden points.
    point_mask : np.ndarray of bool, shape (B, N, P), optional
        Which AGV must avoid which point (given with ``points``).
    point_radius : float
        Radius of the forbidden points.
    fixed : np.ndarray of bool, shape (B, N)
        Committed (and not static) AGVs: no rows, full responsibility for their neighbours.
    static_reference : np.ndarray, shape (B, N, 2), optional
        The velocity each AGV's rows against static neighbours are built from (NaN: its
        current velocity), see :meth:`VelocityAvoidance.solve`.

    Returns
    -------
    ConstraintRows
        ``n = B * N`` AGVs (scene-major).
    """
    poly, poly_cos = speed_polygon(c.polygon_sides)
    B, N, _ = pos.shape
    K = min(c.max_neighbors, N - 1)
    Q = min(c.max_points, 0 if points is None else points.shape[1])
    W = 4 if world is not None else 0
    S = min(c.max_shelves, len(world.obstacles)) \
        if world is not None and world.has_obstacles else 0
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
        nb, ok = neighbours(pos, K, c.neighbor_dist)  # (B, N, K)
        rel_p = pos[bi, nb] - pos[:, :, None, :]  # p_j - p_i
        v_i = vel[:, :, None, :]
        st_j = static[bi, nb]
        if static_reference is not None:
            ref = static_reference[:, :, None, :]
            v_i = np.where(st_j[..., None] & np.isfinite(ref), ref, v_i)
        a, b = orca_halfplanes(
            rel_p, v_i - vel[bi, nb], v_i, 2 * c.radius + np.where(st_j, c.static_margin,
                                                                    c.margin),
            c.time_horizon if c.static_time_horizon is None
            else np.where(st_j, c.static_time_horizon, c.time_horizon),
            c.dt, np.where(st_j | fixed[bi, nb], 1.0, 0.5),
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
        xmin, ymin, xmax, ymax = world.bounds
        r = c.radius + c.static_margin
        inv_t = 1.0 / c.obstacle_time_horizon
        A[:, :, off:off + 4] = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
        hi[:, :, off] = (xmax - r - pos[..., 0]) * inv_t
        hi[:, :, off + 1] = (pos[..., 0] - xmin - r) * inv_t
        hi[:, :, off + 2] = (ymax - r - pos[..., 1]) * inv_t
        hi[:, :, off + 3] = (pos[..., 1] - ymin - r) * inv_t
    off += W
    if S:
        obs = world.obstacles
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
    A[:, :, off:off + P] = poly
    if c.damping is not None:
        centre = (1.0 - c.damping) * vel
        reach = (np.sqrt(centre[..., 0] ** 2 + centre[..., 1] ** 2) - c.gain) / poly_cos
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

