"""Deadlock resolution on preferred velocities (:class:`DeadlockResolver`).

Rules, applied each step before the avoidance QP (see ``docs/safety.md`` for what they do and
do not guarantee):

1. symmetry breaking: every active AGV's preferred velocity gets a perturbation of size at most
   ``perturbation`` in a random direction (RVO2's examples use 1e-4 "to avoid deadlocks due to
   perfect symmetry"), drawn from the resolver's own seeded generator;
2. detection: an AGV that has a goal and made no progress for ``stall_steps`` steps is
   *stalled*; a neighbour within ``reach`` in front of it (inside a 145-degree cone around its
   preferred direction) *blocks* it (the wait-for relation);
3. priority yielding: every AGV has a distinct seeded random priority; a stalled AGV blocked by a
   higher-priority active AGV (parked and broken ones are obstacles, never yielded to) yields
   for ``yield_steps`` steps: it sidesteps to its right and backs off from its higher-priority
   blockers at half speed. In a wait-for cycle at least one AGV yields and the cycle's
   highest-priority AGV does not yield to its successor, so the cycle is broken;
4. roundabout: a stalled, blocked AGV that does not yield turns its preferred velocity to the
   right by 15 degrees per stalled step (at most 90), so that a symmetric jam rotates.

All of it is vectorised over the environments and AGVs through neighbour pairs.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DeadlockResolver", "neighbour_pairs"]


def neighbour_pairs(points: np.ndarray, radius: float) -> np.ndarray:
    """Pairs ``(P, 2)`` of AGVs of the same scene closer than ``radius``.

    Parameters
    ----------
    points : np.ndarray, shape (B, N, 2)
    radius : float

    Returns
    -------
    np.ndarray of int64, shape (P, 2)
        Flat indices ``b * N + i`` with ``i < j`` inside each pair.
    """
    B, N, _ = points.shape
    q = points.reshape(-1, 2)
    if B * N < 2:
        return np.zeros((0, 2), dtype=np.int64)
    if N <= 48:
        a, b = np.triu_indices(N, 1)
        base = (np.arange(B) * N)[:, None]
        pairs = np.stack([(base + a).ravel(), (base + b).ravel()], axis=1)
        d = np.linalg.norm(q[pairs[:, 0]] - q[pairs[:, 1]], axis=1)
        return pairs[d < radius]
    from scipy.spatial import cKDTree

    span = float(np.ptp(q, axis=0).max()) + 2 * radius + 1.0 + 2 * float(np.abs(q).max())
    shifted = q.copy()
    shifted[:, 0] += np.repeat(np.arange(B), N) * span
    return cKDTree(shifted).query_pairs(radius, output_type="ndarray").astype(np.int64)


class DeadlockResolver:
    """Stall detection, priority yielding and symmetry breaking for B scenes of N AGVs.

    Parameters
    ----------
    num_envs, num_agents : int
    radius : float
        AGV radius.
    seed : int
        Seed of the priorities and perturbations (``numpy.random.default_rng``).
    perturbation : float
        Largest symmetry-breaking perturbation of a preferred velocity (units/s).
    stall_steps : int
        Steps without progress after which an AGV counts as stalled.
    yield_steps : int
        How long a yielding AGV sidesteps.
    reach : float
        A neighbour closer than ``2 radius + reach`` in front blocks a stalled AGV.
    """

    def __init__(self, num_envs: int, num_agents: int, radius: float, seed: int = 0,
                 perturbation: float = 1e-4, stall_steps: int = 3, yield_steps: int = 4,
                 reach: float = 0.4, cone: float = 0.0) -> None:
        for name, v in (("num_envs", num_envs), ("num_agents", num_agents),
                        ("stall_steps", stall_steps), ("yield_steps", yield_steps)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        for name, v in (("radius", radius), ("reach", reach)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive, got {v!r}")
        if not (np.isfinite(perturbation) and perturbation >= 0):
            raise ValueError(f"perturbation must be >= 0, got {perturbation!r}")
        B, N = int(num_envs), int(num_agents)
        self.rng = np.random.default_rng(seed)
        self.priority = np.argsort(self.rng.random((B, N)), axis=1)
        self.radius = float(radius)
        self.perturbation = float(perturbation)
        self.stall_steps = int(stall_steps)
        self.yield_steps = int(yield_steps)
        self.reach = float(reach)
        self.cone = float(cone)
        self.stall = np.zeros((B, N), dtype=np.int64)
        self.yield_left = np.zeros((B, N), dtype=np.int64)
        self.yield_dir = np.zeros((B, N, 2))
        self.yields = 0

    def apply(self, pos: np.ndarray, preferred: np.ndarray, active: np.ndarray,
              progress: np.ndarray, speed: float,
              pushable: np.ndarray | None = None) -> np.ndarray:
        """The preferred velocities (B, N, 2) after the rules.

        Parameters
        ----------
        pos : np.ndarray, shape (B, N, 2)
            Where the AGVs are when the new velocity acts.
        preferred : np.ndarray, shape (B, N, 2)
        active : np.ndarray of bool, shape (B, N)
            AGVs that have a goal and may move.
        progress : np.ndarray of bool, shape (B, N)
            AGVs that made progress towards their goal in the last step.
        speed : float
            Cruise speed (the yielding speed is half of it).
        pushable : np.ndarray of bool, shape (B, N), optional
            AGVs without a goal that can move (lifelong: idle ones). One that blocks a stalled
            AGV steps out of its way at half speed (to the side and forwards).
        """
        B, N, _ = pos.shape
        if preferred.shape != (B, N, 2) or active.shape != (B, N) or progress.shape != (B, N):
            raise ValueError(f"preferred, active and progress must have shapes {(B, N, 2)}, "
                             f"{(B, N)}, {(B, N)}")
        if self.stall.shape != (B, N):
            raise ValueError(f"the resolver was made for {self.stall.shape}, got {(B, N)}")
        self.stall = np.where(active & ~progress, self.stall + 1, 0)
        pref = np.array(preferred, dtype=np.float64)
        if self.perturbation > 0:
            ang = self.rng.uniform(0.0, 2 * np.pi, (B, N))
            mag = self.rng.uniform(0.0, self.perturbation, (B, N))
            noise = mag[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
            pref += np.where(active[..., None], noise, 0.0)
        stalled = active & (self.stall >= self.stall_steps)
        yielding = (self.yield_left > 0) & active
        if stalled.any():
            flat_pos = pos.reshape(-1, 2)
            norm = np.linalg.norm(preferred, axis=-1)
            dirn = (preferred / np.maximum(norm, 1e-9)[..., None]).reshape(-1, 2)
            pairs = neighbour_pairs(pos, 2 * self.radius + self.reach)
            st = stalled.reshape(-1)
            prio = self.priority.reshape(-1)
            act = active.reshape(-1)
            block_from = []
            block_to = []
            blocked = np.zeros(B * N, dtype=bool)
            for a, b in ((pairs[:, 0], pairs[:, 1]), (pairs[:, 1], pairs[:, 0])):
                rel = flat_pos[b] - flat_pos[a]
                unit = rel / np.maximum(np.linalg.norm(rel, axis=1), 1e-9)[:, None]
                in_way = st[a] & ((unit * dirn[a]).sum(1) > self.cone)
                blocked[a[in_way]] = True
                blocks = in_way & (prio[b] > prio[a]) & act[b]  # never yield to a parked AGV
                block_from.append(a[blocks])
                block_to.append(b[blocks])
            src = np.concatenate(block_from)
            dst = np.concatenate(block_to)
            must = np.zeros(B * N, dtype=bool)
            must[src] = True
            must &= ~yielding.reshape(-1)
            if must.any():
                away = np.zeros((B * N, 2))
                rel = flat_pos[dst] - flat_pos[src]
                np.add.at(away, src, -rel / np.maximum(np.linalg.norm(rel, axis=1),
                                                       1e-9)[:, None])
                away /= np.maximum(np.linalg.norm(away, axis=1), 1e-9)[:, None]
                right = np.stack([dirn[:, 1], -dirn[:, 0]], -1)
                step = right + 0.7 * away
                step /= np.maximum(np.linalg.norm(step, axis=1), 1e-9)[:, None]
                ydir = self.yield_dir.reshape(-1, 2)
                ydir[must] = step[must]
                yl = self.yield_left.reshape(-1)
                yl[must] = self.yield_steps
                self.yields += int(must.sum())
            turn = np.minimum(self.stall, 6)[..., None] * (np.pi / 12)
            c, s = np.cos(turn), np.sin(turn)  # clockwise: a right turn
            rot = np.concatenate([c * pref[..., :1] + s * pref[..., 1:],
                                  -s * pref[..., :1] + c * pref[..., 1:]], -1)
            if pushable is not None and pushable.any():
                push = pushable.reshape(-1)
                shove = np.zeros((B * N, 2))
                for a, b in ((pairs[:, 0], pairs[:, 1]), (pairs[:, 1], pairs[:, 0])):
                    rel = flat_pos[b] - flat_pos[a]
                    unit = rel / np.maximum(np.linalg.norm(rel, axis=1), 1e-9)[:, None]
                    hit = st[a] & push[b] & ((unit * dirn[a]).sum(1) > self.cone)
                    d = dirn[a[hit]]
                    u = unit[hit]
                    side = u - (u * d).sum(1, keepdims=True) * d
                    right = np.stack([d[:, 1], -d[:, 0]], -1)
                    small = np.linalg.norm(side, axis=1) < 0.2
                    side = np.where(small[:, None], right, side)
                    side /= np.maximum(np.linalg.norm(side, axis=1), 1e-9)[:, None]
                    np.add.at(shove, b[hit], side + 0.5 * d)
                moved = np.linalg.norm(shove, axis=1) > 0
                if moved.any():
                    shove /= np.maximum(np.linalg.norm(shove, axis=1), 1e-9)[:, None]
                    flat = pref.reshape(-1, 2)
                    flat[moved] = 0.5 * speed * shove[moved]
                    pref = flat.reshape(B, N, 2)
            turning = stalled & blocked.reshape(B, N)
            pref = np.where(turning[..., None], rot, pref)
        yielding = (self.yield_left > 0) & active
        pref = np.where(yielding[..., None], 0.5 * speed * self.yield_dir, pref)
        self.yield_left = np.maximum(self.yield_left - 1, 0)
        return pref
