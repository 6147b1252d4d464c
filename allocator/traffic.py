"""A lifelong driver that is safe and live: :class:`SafeDriver`.

The same interface as :class:`allocator.dispatch.WaypointDriver` (``reset(env)``, ``act(env)``
-> ``(B, N, 2)`` float32 actions, a ``distances`` attribute), so a dispatcher takes it as its
driver::

    from allocator.dispatch import HungarianDispatcher
    from allocator.traffic import SafeDriver
    m = sim.evaluate_lifelong(HungarianDispatcher(driver=SafeDriver()), "warehouse-50",
                              steps=2000, faults=sim.Breakdowns(rate=1e-3, repair_steps=50))

Each step:

1. preferred velocities along the floor's shortest paths (the first corner of
   :meth:`allocator.distances.FloorDistances.next_waypoint`, cached while an AGV drives to it,
   slowing down on the last metres);
   AGVs without a target prefer to stand;
2. liveness (:class:`~allocator.avoidance.liveness.DeadlockResolver`): perturbation, stall
   detection (no progress: slower than 10% of the cruise speed while wanting to move), priority
   yielding and right turns;
3. the ORCA QP (:class:`~allocator.avoidance.VelocityAvoidance`, walls and nearest shelves);
   broken AGVs and AGVs in service are static obstacles, idle ones move aside;
4. the braking shield (:class:`~allocator.avoidance.braking.BrakingShield`): no two AGVs ever
   overlap and none touches a shelf or a wall, under the assumptions of ``docs/safety.md``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch
from torch import Tensor

from allocator.avoidance import AvoidanceConfig, VelocityAvoidance
from allocator.avoidance.braking import BrakingShield, braking_velocity
from allocator.avoidance.liveness import DeadlockResolver
from allocator.distances import FloorDistances
from allocator.shield import movable_agents, turn_right

__all__ = ["SafeDriver"]


def _positive(name: str, value: Any, zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value) or (value < 0 if zero else value <= 0):
        raise ValueError(f"{name} must be a {'non-negative' if zero else 'positive'} finite "
                         f"number, got {value!r}")
    return float(value)


class SafeDriver:
    """Drive every AGV with a target along its path, with avoidance, a safety shield and
    deadlock resolution.

    Parameters
    ----------
    gain : float
        Desired velocity per unit distance to the waypoint (1/s), as in ``WaypointDriver``.
    max_speed : float
        Cruise speed (units/s).
    avoidance : bool
        Run the ORCA QP before the shield (False: the shield alone, faster, less smooth).
    margin : float
        Gap kept between two AGVs' braking segments beyond ``2 r``.
    perturbation : float
        Size of the symmetry-breaking perturbation of the preferred velocities.
    seed : int
        Seed of the priorities and perturbations.
    avoidance_options : dict, optional
        Overrides of :class:`~allocator.avoidance.AvoidanceConfig` (defaults here: margin
        0.02, time horizon 0.5 s).
    keep_right : float
        Angle (radians) by which the preferred velocity turns right of the path: lanes form
        in two-way aisles (0: none).

    Attributes
    ----------
    distances : FloorDistances
        The floor's distance table (set by :meth:`reset`; dispatchers read it).
    timing : dict
        Seconds spent in each part (``path``, ``avoid``, ``shield``, ``total``), summed.
    braked : int
        AGV-steps the shield turned into braking.
    """

    def __init__(self, gain: float = 4.0, max_speed: float = 1.2, avoidance: bool = True,
                 margin: float = 0.01, perturbation: float = 1e-4, seed: int = 0,
                 avoidance_options: dict[str, Any] | None = None,
                 keep_right: float = 0.8) -> None:
        self.gain = _positive("gain", gain)
        self.max_speed = _positive("max_speed", max_speed)
        if not isinstance(avoidance, (bool, np.bool_)):
            raise ValueError(f"avoidance must be True or False, got {avoidance!r}")
        self.avoidance = bool(avoidance)
        self.margin = _positive("margin", margin, zero=True)
        self.perturbation = _positive("perturbation", perturbation, zero=True)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.seed = int(seed)
        if avoidance_options is not None and not isinstance(avoidance_options, dict):
            raise ValueError(f"avoidance_options must be a dict, got {avoidance_options!r}")
        self.avoidance_options = dict(avoidance_options or {})
        self.keep_right = _positive("keep_right", keep_right, zero=True)
        self.distances: FloorDistances | None = None
        self.timing = {"path": 0.0, "avoid": 0.0, "shield": 0.0, "total": 0.0}
        self.braked = 0
        self.steps = 0
        self.refresh_distance = 0.3
        self.refresh_steps = 10

    def reset(self, env: Any) -> None:
        """Bind to the env's floor (distance table, avoidance QP, shield, resolver)."""
        world = env.world
        self.world = world
        self.physics = world.physics
        self.distances = FloorDistances(world)
        # The shield guarantees safety, so the QP may plan tighter than the episodic
        # controller's (margin 0.06, horizon 1.0): more AGVs pass each other in the aisles.
        opts = dict(max_speed=self.max_speed, margin=0.02, time_horizon=0.5)
        opts.update(self.avoidance_options)
        self._avoid = VelocityAvoidance(world, AvoidanceConfig.for_world(world, **opts))
        self.shield = BrakingShield.for_world(world, margin=self.margin)
        self.resolver = DeadlockResolver(env.num_envs, env.num_agents, world.agent_radius,
                                         seed=self.seed, perturbation=self.perturbation)
        self.timing = {k: 0.0 for k in self.timing}
        self._wp = None
        self.braked = 0
        self.steps = 0

    @torch.no_grad()
    def act(self, env: Any) -> Tensor:
        """Actions (B, N, 2) float32 for the env's current targets."""
        if self.distances is None:
            raise ValueError("SafeDriver.reset(env) must be called before act")
        t_start = time.perf_counter()
        ph = self.physics
        pos = env.agent_pos.double().cpu().numpy()
        vel = env.agent_vel.double().cpu().numpy()
        B, N, _ = pos.shape
        target, has = env.targets()
        target = target.double().cpu().numpy()
        has = has.cpu().numpy()
        movable = movable_agents(env)
        ahead = pos + np.where(movable[..., None], vel * ph.dt, 0.0)
        self._clip_to_walls(ahead)
        # 1. preferred velocities along the floor's paths
        t0 = time.perf_counter()
        go = has & movable
        pref = np.zeros_like(pos)
        if go.any():
            wp = self._waypoints(ahead, target, go)
            pref[go] = (wp[go] - ahead[go]) * self.gain
        speed = np.linalg.norm(pref, axis=-1, keepdims=True)
        pref = pref * (self.max_speed / np.maximum(speed, self.max_speed))
        if self.keep_right:  # lane discipline: drive a little to the right of the path
            pref = turn_right(pref, self.keep_right)
        self.timing["path"] += time.perf_counter() - t0
        # 2. liveness
        wants = go & (np.linalg.norm(pref, axis=-1) > 0.2 * self.max_speed)
        progress = np.linalg.norm(vel, axis=-1) > 0.1 * self.max_speed
        pref = self.resolver.apply(ahead, pref, wants, progress, self.max_speed,
                                   pushable=movable & ~has)
        # 3. ORCA
        t0 = time.perf_counter()
        if self.avoidance:
            out = self._avoid.solve(ahead, np.where(movable[..., None], vel, 0.0), pref,
                                    static=~movable)
            command = out.velocity
        else:
            command = pref
        self.timing["avoid"] += time.perf_counter() - t0
        # 4. the shield
        t0 = time.perf_counter()
        shield = self.shield
        planned = shield.realised(vel, shield.action_for(vel, command))
        brake = braking_velocity(vel, shield.damping, shield.gain)
        cands = np.stack([planned] + [brake + f * (planned - brake) for f in (0.6, 0.3)], 2)
        res = shield.filter(pos, vel, cands, movable)
        self.last_shield = res
        self.braked += int(res.braking.sum())
        self.timing["shield"] += time.perf_counter() - t0
        self.timing["total"] += time.perf_counter() - t_start
        self.steps += 1
        return torch.as_tensor(res.action, dtype=torch.float32)

    def _waypoints(self, ahead: np.ndarray, target: np.ndarray, go: np.ndarray) -> np.ndarray:
        """The first corner of every driving AGV's path, (B, N, 2), from a cache.

        :meth:`FloorDistances.next_waypoint` is the costly part of a step, and a corner stays
        the same while an AGV drives towards it, so it is looked up again only for AGVs whose
        target changed, that came within ``refresh_distance`` of their corner, or whose corner
        is ``refresh_steps`` old.
        """
        B, N, _ = ahead.shape
        if getattr(self, "_wp", None) is None or self._wp.shape != (B, N, 2):
            self._wp = np.zeros((B, N, 2))
            self._wp_target = np.full((B, N, 2), np.nan)
            self._wp_age = np.zeros((B, N), dtype=np.int64)
        stale = go & ((self._wp_target != target).any(-1)
                      | (np.linalg.norm(self._wp - ahead, axis=-1) < self.refresh_distance)
                      | (self._wp_age >= self.refresh_steps))
        if stale.any():
            self._wp[stale] = self.distances.next_waypoint(ahead[stale], target[stale])
            self._wp_target[stale] = target[stale]
            self._wp_age[stale] = 0
        self._wp_age += 1
        return self._wp

    def _clip_to_walls(self, pts: np.ndarray) -> None:
        w = self.world
        if w.walls:
            r = w.agent_radius
            xmin, ymin, xmax, ymax = w.bounds
            np.clip(pts, [xmin + r, ymin + r], [xmax - r, ymax - r], out=pts)
