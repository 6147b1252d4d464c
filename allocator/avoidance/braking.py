"""A certified safety filter for the simulator's exact discrete dynamics (:class:`BrakingShield`).

The simulator moves an AGV with its *current* velocity first and only then applies the action::

    p' = p + v dt
    v' = (1 - c) v + g a,     a in [-1, 1]^2,  g = sensitivity dt / mass

From a state ``(p, v)`` the *braking sequence* ``a_k = -min(1, (1 - c) u_k / g) v_k / u_k``
(``u_k = |v_k|_inf``; the action stays in the box) keeps the velocity parallel to ``v`` and
shrinks its largest component as ``u_{k+1} = max(0, (1 - c) u_k - g)``, so it stops in a few
steps on the straight *braking segment*::

    S(p, v) = [p, p + D(v)],    D(v) = dt v (u_0 + u_1 + ...) / u_0

which includes the already committed move ``p + v dt``. Braking from the next state keeps the AGV
on the same segment: ``S(p + v dt, B(v))`` is a sub-segment of ``S(p, v)``.

The invariant: every two AGVs' braking segments are at least ``2 r + margin`` apart, and every
AGV's segment is ``r + static_margin`` inside the walls and away from the shelves. Each step,
each AGV has an ordered list of candidate next velocities (the avoidance QP's choice first, then
blends towards braking) and the braking velocity last. :meth:`BrakingShield.filter` keeps for
every AGV the first candidate whose segment keeps the distances to every neighbour's current
choice *and* to that neighbour's braking segment; an AGV whose candidate fails moves on to its
next one, until nothing changes (each AGV only moves down its list, so this stops). Whatever the
final mix of choices and braking, every pair then keeps its distance (see ``docs/safety.md`` for
the theorem, its assumptions and the proof). A pair that starts closer than required (a given
scene) is held to the distance its braking segments have, which never decreases.

Everything is vectorised over the environments and AGVs: neighbours are the pairs of a k-d tree
query (environments shifted apart so that one tree serves all of them), and each round evaluates
segment distances over the pair arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["BrakingShield", "ShieldResult", "braking_velocity", "braking_offset",
           "segment_distance", "segment_rect_distance"]


def _check_positive(name: str, value: Any, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    v = float(value)
    ok = np.isfinite(v) and (v >= 0 if allow_zero else v > 0)
    if not ok:
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else 'positive'} and finite, "
                         f"got {value!r}")
    return v


def braking_velocity(vel: np.ndarray, damping: float, gain: float) -> np.ndarray:
    """The velocity after one step of maximum straight-line braking, shape of ``vel``.

    Parameters
    ----------
    vel : np.ndarray, shape (..., 2)
    damping, gain : float
        ``c`` and ``g`` of ``v' = (1 - c) v + g a``.
    """
    u = np.abs(vel).max(axis=-1, keepdims=True)
    scale = np.maximum(0.0, (1.0 - damping) * u - gain) / np.maximum(u, 1e-300)
    return np.where(u > 0, vel * scale, 0.0)


def braking_action(vel: np.ndarray, damping: float, gain: float) -> np.ndarray:
    """The action (in ``[-1, 1]^2``) that realises :func:`braking_velocity`, shape of ``vel``."""
    u = np.abs(vel).max(axis=-1, keepdims=True)
    mag = np.minimum(1.0, (1.0 - damping) * u / gain)
    return np.where(u > 0, -mag * vel / np.maximum(u, 1e-300), 0.0)


def braking_offset(vel: np.ndarray, dt: float, damping: float, gain: float,
                   max_steps: int = 64) -> np.ndarray:
    """``D(v)``: from ``p`` the braking sequence (the committed ``v dt`` included) ends at
    ``p + D(v)``; shape of ``vel``.

    ``D(v) = dt v sum_k u_k / u_0`` with ``u_{k+1} = max(0, (1 - c) u_k - g)``.
    """
    u0 = np.abs(vel).max(axis=-1)
    u = u0.copy()
    total = np.zeros_like(u0)
    for _ in range(max_steps):
        if not (u > 0).any():
            break
        total += u
        u = np.maximum(0.0, (1.0 - damping) * u - gain)
    if (u > 0).any():  # pragma: no cover - speeds of thousands of units per second
        raise ValueError("vel: braking does not stop within max_steps steps")
    return np.where((u0 > 0)[..., None], dt * vel * (total / np.maximum(u0, 1e-300))[..., None],
                    0.0)


def _point_segment(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    den = (ab * ab).sum(-1)
    t = np.clip(((q - a) * ab).sum(-1) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    t = np.where(den > 0, t, 0.0)
    d = q - (a + t[..., None] * ab)
    return np.sqrt((d * d).sum(-1))


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - \
        (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray,
                     b1: np.ndarray) -> np.ndarray:
    """Euclidean distance between segments ``[a0, a1]`` and ``[b0, b1]`` (degenerate ones
    allowed), elementwise over leading dimensions: shape ``(...,)`` from ``(..., 2)`` inputs.

    Two segments that properly cross are at distance 0; otherwise the closest pair of points
    has an endpoint of one of them, so the distance is the least of four point-segment ones.
    """
    d = np.minimum(np.minimum(_point_segment(a0, b0, b1), _point_segment(a1, b0, b1)),
                   np.minimum(_point_segment(b0, a0, a1), _point_segment(b1, a0, a1)))
    d1, d2 = _cross(b0, b1, a0), _cross(b0, b1, a1)
    d3, d4 = _cross(a0, a1, b0), _cross(a0, a1, b1)
    crossing = (d1 * d2 < 0) & (d3 * d4 < 0)
    return np.where(crossing, 0.0, d)


def segment_rect_distance(p0: np.ndarray, p1: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """Distance from each segment ``[p0, p1]`` (S, 2) to each rectangle ``(xmin, ymin, xmax,
    ymax)`` (K, 4): shape (S, K); 0 where the segment touches or enters the rectangle."""
    return _seg_rect(p0[:, None, :], p1[:, None, :], rects[None, :, :2], rects[None, :, 2:])


def _seg_rect(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Segment-rectangle distance with broadcasting: a, b, lo, hi of shape (..., 2)."""
    shape = np.broadcast_shapes(a.shape, b.shape, lo.shape, hi.shape)
    a, b = np.broadcast_to(a, shape), np.broadcast_to(b, shape)
    lo, hi = np.broadcast_to(lo, shape), np.broadcast_to(hi, shape)

    def point_rect(q: np.ndarray) -> np.ndarray:
        d = np.maximum(np.maximum(lo - q, q - hi), 0.0)
        return np.sqrt((d * d).sum(-1))

    best = np.minimum(point_rect(a), point_rect(b))
    for cx, cy in ((lo, lo), (hi, lo), (hi, hi), (lo, hi)):
        corner = np.stack([cx[..., 0], cy[..., 1]], axis=-1)
        best = np.minimum(best, _point_segment(corner, a, b))
    # Liang-Barsky: does the segment enter the rectangle?
    d = b - a
    t0 = np.zeros(shape[:-1])
    t1 = np.ones(shape[:-1])
    enters = np.ones(shape[:-1], dtype=bool)
    for axis in range(2):
        da = d[..., axis]
        zero = da == 0
        safe = np.where(zero, 1.0, da)
        ta = (lo[..., axis] - a[..., axis]) / safe
        tb = (hi[..., axis] - a[..., axis]) / safe
        inside = (a[..., axis] >= lo[..., axis]) & (a[..., axis] <= hi[..., axis])
        t0 = np.maximum(t0, np.where(zero, -np.inf, np.minimum(ta, tb)))
        t1 = np.minimum(t1, np.where(zero, np.inf, np.maximum(ta, tb)))
        enters &= ~zero | inside
    enters &= t0 <= t1
    return np.where(enters, 0.0, best)


@dataclass
class ShieldResult:
    """Output of :meth:`BrakingShield.filter`.

    Attributes
    ----------
    velocity : np.ndarray, shape (B, N, 2)
        The chosen next velocities.
    action : np.ndarray, shape (B, N, 2)
        The actions in ``[-1, 1]^2`` that realise them (0 for AGVs that do not move).
    choice : np.ndarray of int64, shape (B, N)
        Index of the chosen candidate; ``K`` (the number of candidates) means braking.
    braking : np.ndarray of bool, shape (B, N)
        Movable AGVs the filter made brake (none of their candidates was safe).
    rounds : int
        Rounds until no choice changed.
    min_pair_gap : float
        Least distance between two AGVs' chosen braking segments minus ``2 r`` (inf if none).
    """

    velocity: np.ndarray
    action: np.ndarray
    choice: np.ndarray
    braking: np.ndarray
    rounds: int
    min_pair_gap: float


class BrakingShield:
    """The braking-invariant safety filter (see the module docstring and ``docs/safety.md``).

    Parameters
    ----------
    radius : float
        AGV radius r; two AGVs overlap below ``2 r``.
    dt, damping, gain : float
        The simulator's step, damping ``c`` and action gain ``g = sensitivity dt / mass``.
    margin : float
        Kept between two AGVs' braking segments beyond ``2 r`` (covers float32 rounding and the
        soft contact force, which is below 1e-6 at a gap of 0.01).
    static_margin : float
        Kept between a segment and the walls or shelves beyond ``r``.
    bounds : tuple of 4 floats, optional
        ``(xmin, ymin, xmax, ymax)`` walls (None: no walls).
    obstacles : np.ndarray, shape (K, 4), optional
        Shelves ``(xmin, ymin, xmax, ymax)``.
    max_speed : float, optional
        The simulator's speed cap (``Physics.max_speed``), applied to predicted velocities.
    """

    def __init__(self, radius: float, dt: float, damping: float, gain: float,
                 margin: float = 0.01, static_margin: float = 0.005,
                 bounds: tuple[float, float, float, float] | None = None,
                 obstacles: np.ndarray | None = None, max_speed: float | None = None) -> None:
        self.radius = _check_positive("radius", radius)
        self.dt = _check_positive("dt", dt)
        self.damping = _check_positive("damping", damping, allow_zero=True)
        if self.damping >= 1.0:
            raise ValueError(f"damping must be below 1, got {damping!r}")
        self.gain = _check_positive("gain", gain)
        self.margin = _check_positive("margin", margin, allow_zero=True)
        self.static_margin = _check_positive("static_margin", static_margin, allow_zero=True)
        self.max_speed = None if max_speed is None else _check_positive("max_speed", max_speed)
        if self.damping == 0.0:
            # without damping a speed above g per step still stops: u - g per step
            pass
        if bounds is not None:
            b = np.asarray(bounds, dtype=np.float64)
            if b.shape != (4,) or not np.all(np.isfinite(b)) or b[2] <= b[0] or b[3] <= b[1]:
                raise ValueError(f"bounds must be (xmin, ymin, xmax, ymax) with min < max, got "
                                 f"{bounds!r}")
            self.bounds: np.ndarray | None = b
        else:
            self.bounds = None
        obs = np.zeros((0, 4)) if obstacles is None else np.asarray(obstacles, dtype=np.float64)
        if obs.ndim != 2 or obs.shape[1] != 4 or not np.all(np.isfinite(obs)):
            raise ValueError(f"obstacles must be finite (K, 4) rectangles, got shape {obs.shape}")
        self.obstacles = obs
        self._shelf_tree: Any = None
        if len(obs):
            from scipy.spatial import cKDTree

            centres = (obs[:, :2] + obs[:, 2:]) / 2
            self._shelf_half_diag = float(np.linalg.norm(obs[:, 2:] - obs[:, :2], axis=1).max()
                                          / 2)
            self._shelf_tree = cKDTree(centres)
        self.stats = {"calls": 0, "braked": 0, "rounds": 0}

    @classmethod
    def for_world(cls, world: Any, **overrides: Any) -> BrakingShield:
        """A shield with a simulator world's radius, physics, walls and shelves."""
        ph = world.physics
        kw = dict(radius=world.agent_radius, dt=ph.dt, damping=ph.damping,
                  gain=ph.sensitivity * ph.dt / ph.mass,
                  bounds=tuple(world.bounds) if world.walls else None,
                  obstacles=np.asarray(world.obstacles, dtype=np.float64),
                  max_speed=ph.max_speed)
        kw.update(overrides)
        return cls(**kw)

    # ------------------------------------------------------------------ dynamics
    def _cap(self, vel: np.ndarray) -> np.ndarray:
        if self.max_speed is None:
            return vel
        s = np.linalg.norm(vel, axis=-1, keepdims=True)
        return vel * (self.max_speed / np.maximum(s, self.max_speed))

    def realised(self, vel: np.ndarray, action: np.ndarray) -> np.ndarray:
        """The simulator's next velocity for ``action`` (clipped to the box), shape of vel."""
        return self._cap((1.0 - self.damping) * vel + self.gain * np.clip(action, -1.0, 1.0))

    def action_for(self, vel: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The action in ``[-1, 1]^2`` whose next velocity is nearest ``target`` per axis."""
        return np.clip((target - (1.0 - self.damping) * vel) / self.gain, -1.0, 1.0)

    def offset(self, vel: np.ndarray) -> np.ndarray:
        """:func:`braking_offset` with this shield's physics."""
        return braking_offset(vel, self.dt, self.damping, self.gain)

    # ------------------------------------------------------------------ checks
    def _static_gap(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        """Least clearance of each segment (S, 2)-(S, 2) to the walls and shelves, minus r."""
        gap = np.full(start.shape[0], np.inf)
        r = self.radius
        if self.bounds is not None:
            xmin, ymin, xmax, ymax = self.bounds
            for p in (start, end):
                gap = np.minimum(gap, np.minimum.reduce([p[:, 0] - xmin, p[:, 1] - ymin,
                                                         xmax - p[:, 0], ymax - p[:, 1]]) - r)
        if self._shelf_tree is not None and len(start):
            mid = (start + end) / 2
            half = np.linalg.norm(end - start, axis=1) / 2
            reach = float(half.max()) + r + self.static_margin + self._shelf_half_diag + 1e-9
            from scipy.spatial import cKDTree

            near = cKDTree(mid).sparse_distance_matrix(self._shelf_tree, reach,
                                                       output_type="ndarray")
            if len(near):
                seg = near["i"].astype(np.int64)
                shelf = near["j"].astype(np.int64)
                d = _segment_rect_pairs(start[seg], end[seg], self.obstacles[shelf])
                np.minimum.at(gap, seg, d - r)
        return gap

    # ------------------------------------------------------------------ filter
    def filter(self, pos: np.ndarray, vel: np.ndarray, candidates: np.ndarray,
               movable: np.ndarray) -> ShieldResult:
        """Choose every AGV's next velocity so that the braking invariant is kept.

        Parameters
        ----------
        pos, vel : np.ndarray, shape (B, N, 2)
            The current state (before the step's committed move ``pos + vel dt``).
        candidates : np.ndarray, shape (B, N, K, 2)
            Next velocities to try, best first. They must be reachable in one step (inside
            ``(1 - c) vel + g [-1, 1]^2``; pass them through :meth:`realised`); the braking
            velocity is always tried last.
        movable : np.ndarray of bool, shape (B, N)
            AGVs the simulator moves in this step; the others (parked, broken, in service,
            finished scenes) keep their state, and their braking segment is an obstacle.

        Returns
        -------
        ShieldResult
        """
        pos = np.asarray(pos, dtype=np.float64)
        vel = np.asarray(vel, dtype=np.float64)
        cand = np.asarray(candidates, dtype=np.float64)
        mov = np.asarray(movable, dtype=bool)
        if pos.ndim != 3 or pos.shape[-1] != 2:
            raise ValueError(f"pos must have shape (B, N, 2), got {pos.shape}")
        B, N, _ = pos.shape
        if vel.shape != pos.shape:
            raise ValueError(f"vel must have shape {pos.shape}, got {vel.shape}")
        if cand.ndim != 4 or cand.shape[:2] != (B, N) or cand.shape[3] != 2:
            raise ValueError(f"candidates must have shape ({B}, {N}, K, 2), got {cand.shape}")
        if mov.shape != (B, N):
            raise ValueError(f"movable must have shape {(B, N)}, got {mov.shape}")
        for name, arr in (("pos", pos), ("vel", vel), ("candidates", cand)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains NaN or infinite values")
        K = cand.shape[2]
        n = B * N
        p = pos.reshape(n, 2)
        v = vel.reshape(n, 2)
        m = mov.reshape(n)
        q = p + np.where(m[:, None], v * self.dt, 0.0)  # committed positions
        brake_v = np.where(m[:, None], self._cap(braking_velocity(v, self.damping, self.gain)),
                           v)
        brake_end = np.where(m[:, None], q + self.offset(brake_v), p + self.offset(v))
        c = cand.reshape(n, K, 2)
        cand_end = q[:, None, :] + self.offset(c)  # (n, K, 2)
        # options 0..K-1 the candidates, K braking; unmovable AGVs only brake (stand)
        ends = np.concatenate([cand_end, brake_end[:, None, :]], axis=1)  # (n, K + 1, 2)
        vels = np.concatenate([c, brake_v[:, None, :]], axis=1)
        # Walls and shelves, per option: keep min(r + static_margin, braking's clearance).
        s_gap = self._static_gap(np.repeat(q, K + 1, axis=0),
                                 ends.reshape(-1, 2)).reshape(n, K + 1)
        s_req = np.minimum(self.static_margin, s_gap[:, K])
        ok_static = s_gap >= s_req[:, None] - 1e-12
        ok_static[:, K] = True
        ok_static[~m, :K] = False
        # first statically allowed option
        choice = np.argmax(ok_static, axis=1)
        # Neighbour pairs: any two options' segments lie within reach of q.
        reach = np.linalg.norm(ends - q[:, None, :], axis=-1).max(axis=1)
        rmax = float(reach.max()) if n else 0.0
        d_need = 2 * self.radius + self.margin
        pairs = self._pairs(q, B, N, 2 * rmax + d_need + 1e-9)
        i, j = pairs[:, 0], pairs[:, 1]
        if len(pairs):
            keep = np.linalg.norm(q[i] - q[j], axis=1) <= reach[i] + reach[j] + d_need + 1e-9
            i, j = i[keep], j[keep]
        qi, qj = q[i], q[j]
        bb = segment_distance(qi, brake_end[i], qj, brake_end[j])
        req = np.minimum(d_need, bb) - 1e-12
        rounds = 0
        while True:
            rounds += 1
            ei, ej = ends[i, choice[i]], ends[j, choice[j]]
            d_cc = segment_distance(qi, ei, qj, ej)
            cc = d_cc < req
            nb_i, nb_j = choice[i] < K, choice[j] < K
            bi = segment_distance(qi, ei, qj, brake_end[j]) < req  # i's option vs j braking
            bj = segment_distance(qj, ej, qi, brake_end[i]) < req
            # Two options too close although each clears the other's braking segment: only
            # one AGV gives up its option, the one whose option ends nearer the other (it is
            # the one closing in). Failing both made two AGVs that start closer than
            # 2 r + margin brake for ever (the one leaving never got to leave).
            tie = cc & nb_i & nb_j & ~bi & ~bj
            closer_i = np.linalg.norm(ei - qj, axis=1) <= np.linalg.norm(ej - qi, axis=1)
            fail_i = nb_i & (bi | (cc & ~nb_j) | (tie & closer_i))
            fail_j = nb_j & (bj | (cc & ~nb_i) | (tie & ~closer_i))
            fail = np.zeros(n, dtype=bool)
            fail[i[fail_i]] = True
            fail[j[fail_j]] = True
            if not fail.any():
                break
            # move each failing AGV to its next statically allowed option
            idx = np.flatnonzero(fail)
            later = ok_static[idx] & (np.arange(K + 1)[None, :] > choice[idx][:, None])
            choice[idx] = np.argmax(later, axis=1)
        velocity = vels[np.arange(n), choice]
        action = np.where(
            (choice == K)[:, None], braking_action(v, self.damping, self.gain),
            self.action_for(v, velocity))
        action = np.where(m[:, None], action, 0.0)
        final = ends[np.arange(n), choice]
        gap = float((segment_distance(qi, final[i], qj, final[j]) - 2 * self.radius).min()) \
            if len(i) else float("inf")
        braked = m & (choice == K)
        self.stats["calls"] += 1
        self.stats["braked"] += int(braked.sum())
        self.stats["rounds"] += rounds
        return ShieldResult(velocity.reshape(B, N, 2), action.reshape(B, N, 2),
                            choice.reshape(B, N), braked.reshape(B, N), rounds, gap)

    @staticmethod
    def _pairs(q: np.ndarray, B: int, N: int, radius: float) -> np.ndarray:
        """Index pairs (P, 2) of AGVs of the same scene within ``radius`` of each other."""
        if B * N < 2:
            return np.zeros((0, 2), dtype=np.int64)
        if N <= 48:  # all pairs of a scene: cheaper than a tree for small fleets
            a, b = np.triu_indices(N, 1)
            base = (np.arange(B) * N)[:, None]
            return np.stack([(base + a).ravel(), (base + b).ravel()], axis=1)
        from scipy.spatial import cKDTree

        span = float(np.ptp(q, axis=0).max()) + 2 * radius + 1.0
        shifted = q.copy()
        shifted[:, 0] += np.repeat(np.arange(B), N) * (span + float(np.abs(q).max()) * 2)
        return cKDTree(shifted).query_pairs(radius, output_type="ndarray").astype(np.int64)


def _segment_rect_pairs(p0: np.ndarray, p1: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """Segment s against rectangle s (matched rows): shape (S,)."""
    return _seg_rect(p0, p1, rects[:, :2], rects[:, 2:])
