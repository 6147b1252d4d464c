"""Drive the simulator with any assignment solver: assign, follow paths, avoid, accelerate.

:class:`AllocatorController` is what ``sim.evaluate`` calls for the classical allocators
(``reset(env)`` after every batch of episodes starts, then ``act(obs)`` each step):

1. ``reset``: one assignment per environment (the solver's ``assign`` on that scene), and a
   path per AGV (a straight segment in an open world, OMPL around shelves).
2. ``act``: re-assign the environments where a claim went against the plan (or every
   ``reassign_every`` steps, or when :meth:`AllocatorController.reassign` is called); each
   idle AGV gets a preferred velocity along its path, braking on the last leg; the ORCA QP
   (:class:`~allocator.avoidance.VelocityAvoidance`) makes the velocities collision-free, and
   is solved again where an AGV will break its reciprocal rows (it claims a task and stops
   dead, or its rows conflicted): the others then take the full responsibility against it;
   each velocity becomes the acceleration action that reaches it in one step;
3. safety: the :class:`~allocator.avoidance.braking.BrakingShield` certifies every velocity
   against the simulator's exact discrete dynamics (each AGV keeps a braking segment that stays
   ``2 r + margin`` from every other's); a velocity it cannot certify becomes a blend towards
   braking, or braking (``docs/safety.md``);
4. liveness: preferred velocities carry a tiny seeded perturbation (RVO2's examples use 1e-4
   against perfectly symmetric deadlocks); an AGV that makes no progress for a few steps while a
   neighbour blocks its way yields when that neighbour has the higher (seeded, random) priority
   (it sidesteps to its right and backs off) and otherwise turns right progressively, so that a
   jam becomes a roundabout; an AGV stalled against a parked AGV is re-routed at once; and in
   open worlds the plan itself is untangled (:mod:`allocator.avoidance.ordering`): tasks are
   exchanged between AGVs where a leg would pass where another AGV parks first, above all
   through a gap between two parked AGVs (or one and a wall) narrower than an AGV needs.

The simulator moves positions with the *current* velocity before the action acts
(``pos += vel dt``; ``vel = (1 - damping) vel + action sensitivity dt / mass``), so the
controller plans from the predicted positions ``pos + vel dt`` and chooses the velocity of the
step after; the acceleration limit is a hard constraint of the QP.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch
from torch import Tensor

from allocator.avoidance import AvoidanceConfig, VelocityAvoidance
from allocator.avoidance.braking import BrakingShield, braking_velocity
from allocator.avoidance.liveness import DeadlockResolver
from sim.tasks import claim

__all__ = ["AllocatorController"]


class AllocatorController:
    """Turn an allocator into simulator actions (batched over the B environments).

    Parameters
    ----------
    allocator : object with ``assign(agents, tasks, world) -> Assignment``
    avoidance : bool
        Filter the preferred velocities through the ORCA QP (False: follow paths blindly).
    planner : {"auto", "ompl", "prm", "grid"}
        Paths around shelves: OMPL RRTConnect (``"ompl"``), a PRM roadmap shared by all
        queries (``"prm"``) or the string-pulled grid path; ``"auto"`` is ``"prm"``. Open
        worlds use straight segments.
    max_speed : float, optional
        Cruise speed (default the simulator's terminal speed).
    brake : float
        Deceleration (units/s^2) assumed by the speed profile on the last leg.
    reassign_every : int, optional
        Also re-assign idle AGVs every this many steps.
    avoid_tasks : bool
        Keep AGVs off tasks that are not theirs (an idle AGV claims any task it touches).
    avoidance_options : dict, optional
        Overrides of :class:`~allocator.avoidance.AvoidanceConfig` (defaults here with the
        shield on: ``time_horizon=0.3``, ``static_time_horizon=0.15``, ``margin=0.02``; the
        shield guarantees safety, so the QP need not be conservative), and seven keys of the
        controller's own: ``"shield"`` (bool, default True: the braking safety filter),
        ``"liveness"`` (bool, default True: perturbation, yielding and early re-routing),
        ``"shield_margin"`` (float, default 0.01: gap kept between two AGVs' braking segments),
        ``"perturbation"`` (float, default 1e-4: size of the symmetry-breaking noise) and
        ``"detour"`` (bool, default True: steer around a standing AGV that blocks the straight
        line to the next waypoint, on the side with room, as soon as it blocks; see
        :meth:`_detour`), ``"untangle"`` (bool, default True: in open worlds, exchange tasks
        of the allocator's plan so that fewer legs pass where another AGV parks first, see
        :func:`~allocator.avoidance.ordering.untangle`; plans of more than
        :attr:`UNTANGLE_MAX_AGENTS` idle AGVs are kept) and ``"untangle_weight"`` (float,
        default 0.2: distance paid per conflict removed).
    waypoint_tolerance : float
        Distance at which an intermediate waypoint counts as reached.
    stuck_steps : int
        Steps without progress towards its task after which an AGV is re-routed around parked AGVs.
    seed : int
        Seed of the OMPL planner.

    Attributes
    ----------
    task_of_agent : np.ndarray of int64, shape (B, N)
        The current plan (-1: no task).
    fallbacks : int
        AGV-steps in which the avoidance QP had to fall back.
    untangled : int
        Plans that :meth:`_untangle` changed (not reset by :meth:`reset`).
    resolves : int
        Scene-steps whose QP was solved again around AGVs that claim (and stop) or fall back
        in the next step (see :meth:`_avoid_step`); reset by :meth:`reset`.
    timing : dict
        Seconds spent assigning, planning and avoiding.
    """

    UNTANGLE_MAX_AGENTS = 32
    """Largest number of idle AGVs whose plan :meth:`_untangle` checks (its exchange rounds
    cost O(N^3) each)."""

    def __init__(
        self,
        allocator: Any,
        avoidance: bool = True,
        planner: str = "auto",
        max_speed: float | None = None,
        brake: float = 4.0,
        reassign_every: int | None = None,
        avoid_tasks: bool = True,
        avoidance_options: dict[str, Any] | None = None,
        waypoint_tolerance: float = 0.12,
        stuck_steps: int = 5,
        seed: int = 0,
    ) -> None:
        if planner not in ("auto", "ompl", "prm", "grid"):
            raise ValueError(f"planner must be 'auto', 'ompl', 'prm' or 'grid', got {planner!r}")
        self.allocator = allocator
        self.use_avoidance = avoidance
        self.planner_kind = "prm" if planner == "auto" else planner
        self.max_speed = max_speed
        self.brake = brake
        self.reassign_every = reassign_every
        self.avoid_tasks = avoid_tasks
        opts = dict(avoidance_options or {})
        self.shield = bool(opts.pop("shield", True))
        self.liveness = bool(opts.pop("liveness", True))
        self.shield_margin = float(opts.pop("shield_margin", 0.01))
        self.perturbation = float(opts.pop("perturbation", 1e-4))
        self.detour = bool(opts.pop("detour", True))
        self.untangle = bool(opts.pop("untangle", True))
        self.untangle_weight = float(opts.pop("untangle_weight", 0.2))
        if not (np.isfinite(self.shield_margin) and self.shield_margin >= 0):
            raise ValueError(f"avoidance_options['shield_margin'] must be >= 0, got "
                             f"{self.shield_margin!r}")
        if not (np.isfinite(self.untangle_weight) and self.untangle_weight >= 0):
            raise ValueError(f"avoidance_options['untangle_weight'] must be >= 0, got "
                             f"{self.untangle_weight!r}")
        if not (np.isfinite(self.perturbation) and self.perturbation >= 0):
            raise ValueError(f"avoidance_options['perturbation'] must be >= 0, got "
                             f"{self.perturbation!r}")
        self.avoidance_options = opts
        self.waypoint_tolerance = waypoint_tolerance
        self.stuck_steps = stuck_steps
        self.seed = seed
        self.env: Any = None
        self._world: Any = None
        self._planner: Any = None
        self._avoid: VelocityAvoidance | None = None
        self._shield: BrakingShield | None = None
        self.fallbacks = 0
        self.shield_brakes = 0
        self.yields = 0
        self.reassignments = 0
        self.untangled = 0
        self.timing = {"assign": 0.0, "plan": 0.0, "avoid": 0.0, "shield": 0.0, "act": 0.0}

    # ------------------------------------------------------------------ planning
    def reset(self, env: Any) -> None:
        """Plan for every environment of ``env`` (read its positions, tasks and world)."""
        self.env = env
        world = env.world
        if world is not self._world:
            self._world = world
            self._planner = None
            self._avoid = None
            self._shield = None
        B, N = env.num_envs, env.num_agents
        self.task_of_agent = np.full((B, N), -1, dtype=np.int64)
        self._paths: list[list[np.ndarray | None]] = [[None] * N for _ in range(B)]
        self._waypoints = np.zeros((B, N, 1, 2))
        self._num_waypoints = np.zeros((B, N), dtype=np.int64)
        self._next = np.zeros((B, N), dtype=np.int64)
        self._steps = 0
        self._stuck = np.zeros((B, N), dtype=np.int64)
        self._best = np.full((B, N), np.inf)
        self.replans = 0
        self.resolves = 0
        self._resolver = DeadlockResolver(B, N, world.agent_radius, seed=self.seed,
                                          perturbation=self.perturbation)
        self._last_dist = np.full((B, N), np.inf)
        self._last_next = np.zeros((B, N), dtype=np.int64)
        self._last_shape: tuple[int, ...] = ()
        self._detour_side = np.zeros((B, N))
        self._detour_from = np.full((B, N), -1, dtype=np.int64)
        self._detour_ref: np.ndarray | None = None
        self._boxed_version = np.full((B, N), -1, dtype=np.int64)
        self.detours = 0
        self.early_replans = 0
        self.reassign()

    def reassign(self, env_ids: Any = None) -> None:
        """Assign the idle AGVs to the unclaimed tasks again (all environments by default)."""
        env = self._require_env()
        ids = range(env.num_envs) if env_ids is None else np.atleast_1d(env_ids)
        pos = env.agent_pos.detach().cpu().double().numpy()
        tasks = env.task_pos.detach().cpu().double().numpy()
        held = env.agent_task.detach().cpu().numpy()
        claimed = env.task_claimed.detach().cpu().numpy()
        for b in ids:
            self._assign_env(int(b), pos[b], tasks[b], held[b], claimed[b])
        self._pack_paths()

    def _assign_env(
        self, b: int, pos: np.ndarray, tasks: np.ndarray, held: np.ndarray, claimed: np.ndarray
    ) -> None:
        world = self._world
        self.task_of_agent[b] = held  # parked AGVs keep their task
        for i in range(len(held)):
            self._paths[b][i] = None
        idle = np.flatnonzero(held < 0)
        open_tasks = np.flatnonzero(~claimed)
        if idle.size == 0 or open_tasks.size == 0:
            return
        t0 = time.perf_counter()
        result = self.allocator.assign(pos[idle], tasks[open_tasks], world=world)
        self.timing["assign"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        plan = np.asarray(result.task_of_agent, dtype=np.int64)
        if self.liveness and self.untangle and result.paths is None and not world.has_obstacles:
            plan = self._untangle(pos[idle], tasks[open_tasks], plan)
        for k, j in enumerate(plan):
            if j < 0:
                continue
            i, task = idle[k], open_tasks[j]
            self.task_of_agent[b, i] = task
            path = None
            if result.paths is not None and result.paths[k] is not None:
                path = result.paths[k]
            elif world.has_obstacles:
                path = self._plan(pos[i], tasks[task])
            if path is None:
                path = np.stack([pos[i], tasks[task]])
            self._paths[b][i] = np.asarray(path, dtype=np.float64)
        self.timing["plan"] += time.perf_counter() - t0

    def _untangle(self, agents: np.ndarray, tasks: np.ndarray, plan: np.ndarray) -> np.ndarray:
        """The allocator's plan with tasks exchanged so that fewer legs pass a parked AGV
        (:func:`~allocator.avoidance.ordering.untangle`; straight legs, open worlds)."""
        from allocator.avoidance.ordering import untangle

        world = self._world
        if len(agents) > self.UNTANGLE_MAX_AGENTS:
            return plan  # O(N^3) per exchange round: large scenes keep the allocator's plan
        step = self._cruise_speed() * world.physics.dt
        new = untangle(agents, tasks, plan, clearance=2 * world.agent_radius + 0.03,
                       capture=world.capture_radius, step=float(step),
                       weight=self.untangle_weight, radius=world.agent_radius,
                       bounds=world.bounds if world.walls else None,
                       gate_weight=3.0)
        self.untangled += int((new != plan).any())
        return new

    def _plan(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        if self._planner is None:
            if self.planner_kind == "grid":
                from allocator.paths import grid_for

                self._planner = grid_for(self._world)
            else:
                from allocator.paths import OMPLPlanner

                kind = "prm" if self.planner_kind == "prm" else "rrtconnect"
                self._planner = OMPLPlanner(self._world, planner=kind, seed=self.seed)
        return self._planner.plan(start, goal)

    def _pack_paths(self) -> None:
        """Paths into one padded array (B, N, W, 2) so the step is vectorised."""
        B, N = self.task_of_agent.shape
        longest = max([len(p) for row in self._paths for p in row if p is not None] + [1])
        wp = np.zeros((B, N, longest, 2))
        count = np.zeros((B, N), dtype=np.int64)
        for b in range(B):
            for i, p in enumerate(self._paths[b]):
                if p is not None:
                    wp[b, i, : len(p)] = p
                    wp[b, i, len(p):] = p[-1]
                    count[b, i] = len(p)
        self._waypoints = wp
        self._num_waypoints = count
        self._next = np.minimum(1, np.maximum(count - 1, 0))

    def _require_env(self) -> Any:
        if self.env is None:
            raise RuntimeError("call reset(env) before act(obs): the controller plans per scene")
        return self.env

    # ------------------------------------------------------------------ acting
    def _avoidance(self) -> VelocityAvoidance:
        if self._avoid is None:
            # The shield guarantees safety, so the QP may plan with short horizons and a small
            # margin (AvoidanceConfig's 1.0 s and 0.06 were chosen before the shield): AGVs
            # pass each other and parked AGVs sooner. 6v6 over seeds 0-9 (18,000 tasks):
            # 72 missed with 1.0 s / 0.06, 31 with these (benchmarks/results/antipodal).
            opts = dict(max_speed=self._cruise_speed())
            if self.shield:
                opts.update(time_horizon=0.3, static_time_horizon=0.15, margin=0.02)
            opts.update(self.avoidance_options)
            self._avoid = VelocityAvoidance(
                self._world, AvoidanceConfig.for_world(self._world, **opts)
            )
        return self._avoid

    def _cruise_speed(self) -> float:
        if self.max_speed is not None:
            return float(self.max_speed)
        ph = self._world.physics
        return float(ph.terminal_speed)

    @torch.no_grad()
    def act(self, obs: Tensor | None = None) -> Tensor:
        """Actions (B, N, 2) in [-1, 1] for the current state of the environment.

        ``obs`` is only used for its batch shape: the controller is centralized and reads the
        state of the environment given to :meth:`reset`.
        """
        t_start = time.perf_counter()
        env = self._require_env()
        ph = self._world.physics
        pos = env.agent_pos.detach().cpu().double().numpy()
        vel = env.agent_vel.detach().cpu().double().numpy()
        held = env.agent_task.detach().cpu().numpy()
        claimed = env.task_claimed.detach().cpu().numpy()
        done = env.done.detach().cpu().numpy()
        tasks = env.task_pos.detach().cpu().double().numpy()
        B, N, _ = pos.shape
        self._steps += 1

        # Re-plan where a claim went against the plan.
        plan = self.task_of_agent
        stolen = (plan >= 0) & (held != plan) & np.take_along_axis(
            claimed, np.maximum(plan, 0), axis=1
        )
        wrong = (held >= 0) & (held != plan)
        redo = (stolen | wrong).any(axis=1) & ~done
        if self.reassign_every and self._steps % self.reassign_every == 0:
            redo |= ~done
        if redo.any():
            self.reassignments += int(redo.sum())
            self.reassign(np.flatnonzero(redo))

        idle = (held < 0) & ~done[:, None]
        self._replan_stuck(pos, vel, held, tasks, idle)
        ahead = self._advance(pos, vel)  # where each AGV will be when the new velocity acts
        # AGVs that claim a task in this step stop dead at ``ahead`` (the simulator zeroes a
        # parked AGV's velocity): from now on they are static obstacles for the others.
        stopping, taken = self._claims(ahead, idle, claimed, tasks)
        moving = idle & ~stopping
        preferred = self._preferred(ahead, moving)
        self._detour_ref = None
        if self.liveness:
            self._reroute_blocked(ahead, held, tasks, moving)
            preferred = self._preferred(ahead, moving)
            if self.detour:
                preferred = self._detour(ahead, vel, preferred, moving, held, tasks)
            preferred = self._resolve_deadlocks(ahead, vel, preferred, moving)

        if self.use_avoidance:
            t0 = time.perf_counter()
            command = self._avoid_step(ahead, vel, preferred, moving, claimed | taken, tasks)
            self.timing["avoid"] += time.perf_counter() - t0
        else:
            command = preferred
        gain = ph.sensitivity * ph.dt / ph.mass
        action = np.clip((command - (1.0 - ph.damping) * vel) / gain, -1.0, 1.0)
        action = np.where(moving[..., None], action, 0.0)
        if self.shield:
            t0 = time.perf_counter()
            action = self._certify(pos, vel, action, idle)
            self.timing["shield"] = self.timing.get("shield", 0.0) + time.perf_counter() - t0
        self.timing["act"] += time.perf_counter() - t_start
        return torch.as_tensor(action, dtype=env.dtype, device=env.device)

    def _shield_filter(self) -> BrakingShield:
        if self._shield is None:
            self._shield = BrakingShield.for_world(self._world, margin=self.shield_margin)
        return self._shield

    def _certify(self, pos: np.ndarray, vel: np.ndarray, action: np.ndarray,
                 movable: np.ndarray) -> np.ndarray:
        """The actions after the braking shield: the planned velocity, else a blend of it
        with braking, else braking (``docs/safety.md``)."""
        shield = self._shield_filter()
        planned = shield.realised(vel, action)
        brake = braking_velocity(vel, shield.damping, shield.gain)
        blends = [planned] + [brake + f * (planned - brake) for f in (0.6, 0.3)]
        out = shield.filter(pos, vel, np.stack(blends, axis=2), movable)
        self.shield_brakes += int(out.braking.sum())
        self.last_shield = out
        return out.action

    def _reroute_blocked(self, ahead: np.ndarray, held: np.ndarray, tasks: np.ndarray,
                         moving: np.ndarray) -> None:
        """Re-route early an AGV stalled against a parked AGV (e.g. held between it and a
        wall): as soon as the deadlock resolver counts it stalled, instead of after
        ``stuck_steps`` steps without progress."""
        res = self._resolver
        xmin, ymin, xmax, ymax = self._world.bounds
        if (xmax - xmin) * (ymax - ymin) / 0.04 ** 2 > 4e6:
            return  # the re-planning grid map (0.04 cells) would be too large for this world
        stalled = moving & (res.stall >= res.stall_steps) & (self.task_of_agent >= 0) & \
            (self._stuck < self.stuck_steps)
        if not stalled.any():
            return
        r = self._world.agent_radius
        parked = held >= 0
        d = np.linalg.norm(ahead[:, :, None, :] - ahead[:, None, :, :], axis=-1)  # (B, N, N)
        near_parked = ((d < 2 * r + 0.1) & parked[:, None, :]).any(axis=2)
        todo = stalled & near_parked
        if todo.any():
            self._stuck = np.where(todo, self.stuck_steps, self._stuck)
            self._replan_stuck(ahead, np.zeros_like(ahead), held, tasks, moving,
                               count_progress=False)
            res.stall = np.where(todo, 0, res.stall)

    def _detour(self, ahead: np.ndarray, vel: np.ndarray, preferred: np.ndarray,
                moving: np.ndarray, held: np.ndarray, tasks: np.ndarray,
                again: bool = False) -> np.ndarray:
        """Preferred velocities that go around a standing AGV blocking the way at once.

        A moving AGV whose straight segment to its waypoint passes closer than ``2 r + 0.03``
        to a standing AGV (parked, stopping in this step, or without a task) heads for the
        tangent of that disc instead, on the side of the waypoint (the shorter way round)
        unless that side has no room, else on the other side. A side has no room when the
        passing point ``2 r + 0.03`` beside the blocker is too close to a wall, a shelf or
        another standing AGV, or when another standing AGV on that side stands closer to the
        blocker than two such clearances (no AGV fits between them). With no room on either
        side the AGV is re-planned at once on the grid map with the parked AGVs as obstacles
        (:meth:`_replan_stuck`; once per AGV and set of standing AGVs), instead of after the
        stall detection. The chosen side is kept while the same AGV blocks, so the detour
        does not flip, and the QP's rows against standing AGVs are linearised on that side
        (``static_reference``). Without this, ORCA's cone of the standing AGV deflects the
        mover to the side nearest its current velocity, which can lead into the gap between
        the blocker and a wall: the AGV is held there until the stall re-routing, too late for
        the 25-step episodes.
        """
        world = self._world
        r = world.agent_radius
        B, N, _ = ahead.shape
        wp = self._waypoints
        target = np.take_along_axis(wp, self._next[..., None, None].repeat(2, -1), 2)[:, :, 0]
        speed = np.linalg.norm(preferred, axis=-1)
        go = moving & (speed > 1e-9)
        standing = ~moving | (self.task_of_agent < 0)
        if not again:
            self._detour_ref = None
        if not (go.any() and standing.any()):
            self._detour_from[:] = -1
            return preferred
        clear = 2 * r + 0.03
        seg = target - ahead  # (B, N, 2)
        seg_len_sq = np.maximum((seg ** 2).sum(-1), 1e-12)
        c = ahead[:, None, :, :] - ahead[:, :, None, :]  # (B, N, N, 2): p_j - a_i
        u = np.clip((c * seg[:, :, None, :]).sum(-1) / seg_len_sq[..., None], 0.0, 1.0)
        gap = np.linalg.norm(seg[:, :, None, :] * u[..., None] - c, axis=-1)
        near_target = np.linalg.norm(target[:, :, None, :] - ahead[:, None, :, :], axis=-1)
        blocks = go[:, :, None] & standing[:, None, :] & (gap < clear) & (u > 0) \
            & (near_target >= clear) & ~np.eye(N, dtype=bool)[None]
        has = blocks.any(-1)
        if not has.any():
            self._detour_from[:] = -1
            return preferred
        along = np.where(blocks, u * np.sqrt(seg_len_sq)[..., None], np.inf)
        j = np.argmin(along, axis=-1)  # the first blocker on the way
        cj = np.take_along_axis(c, j[..., None, None].repeat(2, -1), 2)[:, :, 0]  # (B, N, 2)
        dj = np.maximum(np.linalg.norm(cj, axis=-1), 1e-9)
        unit = cj / dj[..., None]
        left = np.stack([-unit[..., 1], unit[..., 0]], -1)
        pj = ahead + cj
        others = standing[:, None, :] & (np.arange(N)[None, None, :] != j[..., None])
        rel_k = ahead[:, None, :, :] - pj[:, :, None, :]  # (B, N, N, 2): p_k - p_j
        dist_k = np.linalg.norm(rel_k, axis=-1)
        room = []
        for side in (1.0, -1.0):  # +1: pass on the left of the blocker, -1: on its right
            ok = np.ones((B, N), dtype=bool)
            # the quarter circle of radius ``clear`` round the blocker from the AGV's side to
            # the passing point must have room (not only the passing point: an AGV beside a
            # blocker at a wall cannot slide round it along the wall)
            for ang in np.linspace(0.0, np.pi / 2, 5):
                ca, sa = np.cos(-side * ang), np.sin(-side * ang)
                back = -unit
                w = pj + clear * np.stack([ca * back[..., 0] - sa * back[..., 1],
                                           sa * back[..., 0] + ca * back[..., 1]], -1)
                if world.walls:
                    xmin, ymin, xmax, ymax = world.bounds
                    m = r + 0.005
                    ok &= (w[..., 0] >= xmin + m) & (w[..., 0] <= xmax - m) \
                        & (w[..., 1] >= ymin + m) & (w[..., 1] <= ymax - m)
                if world.has_obstacles:
                    ok &= world.obstacle_distance(w.reshape(-1, 2)).reshape(B, N) >= r + 0.005
                dw = np.linalg.norm(w[:, :, None, :] - ahead[:, None, :, :], axis=-1)
                ok &= ~(others & (dw < 2 * r + 0.005)).any(-1)
            beside = (rel_k * (side * left)[:, :, None, :]).sum(-1) > 0.3 * dist_k
            ok &= ~(others & beside & (dist_k < 2 * clear)).any(-1)
            room.append(ok)
        room_l, room_r = room
        cross_goal = unit[..., 0] * seg[..., 1] - unit[..., 1] * seg[..., 0]
        cross_vel = unit[..., 0] * vel[..., 1] - unit[..., 1] * vel[..., 0]
        want = np.where(np.abs(cross_goal) > 1e-3 * np.sqrt(seg_len_sq), np.sign(cross_goal),
                        np.where(cross_vel > 0, 1.0, -1.0))
        keep = (self._detour_from == j) & (self._detour_side != 0)
        want = np.where(keep, self._detour_side, want)
        free_want = np.where(want > 0, room_l, room_r)
        free_other = np.where(want > 0, room_r, room_l)
        side = np.where(free_want, want, np.where(free_other, -want, 0.0))
        boxed = has & (side == 0) & (self.task_of_agent >= 0)
        # which set of standing AGVs an AGV was re-planned for (it changes when one parks)
        version = standing.sum(axis=1, keepdims=True) + 1000 * (held >= 0).sum(1, keepdims=True)
        boxed &= self._boxed_version != version
        if boxed.any() and not again:
            self._boxed_version = np.where(boxed, version, self._boxed_version)
            self._replan_around(ahead, tasks, standing, boxed)
            return self._detour(ahead, vel, self._preferred(ahead, moving), moving, held,
                                tasks, again=True)
        # an AGV re-planned around this very set of standing AGVs follows its new path
        use = has & (side != 0) & (self._boxed_version != version)
        self._detour_from = np.where(use, j, -1)
        self._detour_side = np.where(use, side, 0.0)
        if not use.any():
            return preferred
        # the tangent from the AGV to the disc of radius ``clear`` on that side
        sin_t = np.clip(clear / dj, 0.0, 1.0)
        cos_t = np.sqrt(1.0 - sin_t ** 2)
        s = side
        dirn = np.stack([unit[..., 0] * cos_t - s * unit[..., 1] * sin_t,
                         s * unit[..., 0] * sin_t + unit[..., 1] * cos_t], -1)
        inside = dj <= clear  # touching already: slide along it, a little outwards
        slide = s[..., None] * left - 0.3 * unit
        slide /= np.maximum(np.linalg.norm(slide, axis=-1, keepdims=True), 1e-9)
        dirn = np.where(inside[..., None], slide, dirn)
        self.detours += int(use.sum())
        out = np.where(use[..., None], dirn * speed[..., None], preferred)
        # the QP's rows against standing AGVs are linearised on the detour's side
        self._detour_ref = np.where(use[..., None], out, np.nan)
        return out

    def _replan_around(self, ahead: np.ndarray, tasks: np.ndarray, standing: np.ndarray,
                       todo: np.ndarray) -> None:
        """New paths for the AGVs in ``todo`` (B, N) around the standing AGVs as discs
        (:func:`~allocator.avoidance.detour.plan_around_discs`, centre distance
        ``2 r + 0.02``)."""
        from allocator.avoidance.detour import plan_around_discs

        r = self._world.agent_radius
        goal = np.take_along_axis(tasks, np.maximum(self.task_of_agent, 0)[..., None], 1)
        for b, i in np.argwhere(todo):
            centres = ahead[b][standing[b] & (np.arange(len(standing[b])) != i)]
            path = plan_around_discs(self._world, ahead[b, i], goal[b, i], centres,
                                     2 * r + 0.02)
            self.early_replans += 1
            if path is None:
                continue
            self.replans += 1
            self._paths[b][i] = path
            self._set_path(b, i, path)
            self._stuck[b, i] = 0
            self._best[b, i] = np.inf

    def _resolve_deadlocks(self, ahead: np.ndarray, vel: np.ndarray, preferred: np.ndarray,
                           moving: np.ndarray) -> np.ndarray:
        """Preferred velocities with the liveness rules of :class:`~allocator.avoidance.
        liveness.DeadlockResolver` applied (progress: the distance to the goal shrank)."""
        cruise = self._cruise_speed()
        wp = self._waypoints
        goal_pos = np.take_along_axis(wp, (self._num_waypoints - 1).clip(0)[
            ..., None, None].repeat(2, -1), 2)[:, :, 0]
        target = np.take_along_axis(wp, self._next[..., None, None].repeat(2, -1), 2)[:, :, 0]
        dist = np.linalg.norm(target - ahead, axis=-1)
        active = moving & (self.task_of_agent >= 0) & \
            (np.linalg.norm(goal_pos - ahead, axis=-1) > self._world.capture_radius)
        # progress: closer to the waypoint being driven to (or a new waypoint / path)
        same = (self._next == self._last_next) & (self._waypoints.shape == self._last_shape)
        progress = (dist < self._last_dist - 0.01 * cruise) | ~same
        self._last_dist = dist
        self._last_next = self._next.copy()
        self._last_shape = self._waypoints.shape
        out = self._resolver.apply(ahead, preferred, active, progress, cruise)
        self.yields = self._resolver.yields
        return out

    def _avoid_step(
        self, ahead: np.ndarray, vel: np.ndarray, preferred: np.ndarray, moving: np.ndarray,
        claimed: np.ndarray, tasks: np.ndarray,
    ) -> np.ndarray:
        """Velocity commands (B, N, 2) from the avoidance QP, re-solved where an AGV will not
        behave as its neighbours' ORCA rows assume.

        Reciprocal ORCA rows assume every neighbour keeps its velocity and takes half the
        responsibility. Two kinds of AGV break that, and both are known once the QP is
        solved (``ahead + v dt`` is where each AGV will be a step later):

        - an AGV whose command brings it within the capture radius of a task claims it there
          and stops dead (the simulator zeroes a parked AGV's velocity);
        - an AGV whose rows conflicted (fell back) violates them.

        Their commands are kept, and the scenes that have one are solved again with them as
        obstacles for the others, who take the full responsibility: a static disc at the
        stopping point, or a disc moving with the committed velocity. Those solves can
        produce new such AGVs, so this repeats until none appears (at most N times).
        """
        avoid = self._avoidance()
        capture = self._world.capture_radius
        dt = self._world.physics.dt
        plan = self.task_of_agent

        def solve(e: Any, p: np.ndarray, v: np.ndarray, static: np.ndarray,
                  committed: np.ndarray) -> Any:
            free = ~static & ~committed
            points = mask = None
            if self.avoid_tasks:
                own = np.arange(tasks.shape[1])[None, None, :] == plan[e][..., None]
                mask = ~claimed[e][:, None, :] & ~own & free[..., None]
                points = tasks[e]
            ref = None if self._detour_ref is None else self._detour_ref[e]
            return avoid.solve(
                p, v, np.where(free[..., None], preferred[e], 0.0), static=static,
                points=points, point_mask=mask, point_radius=capture, committed=committed,
                static_reference=ref,
            )

        everything = slice(None)
        out = solve(everything, ahead, np.where(moving[..., None], vel, 0.0), ~moving,
                    np.zeros_like(moving))
        command, fell = out.velocity, out.fell_back & moving
        fixed = np.zeros_like(moving)
        for _ in range(moving.shape[1]):
            nxt = self._advance(ahead, command)
            stop, _ = self._claims(nxt, moving, claimed, tasks)
            new = (stop | fell) & moving & ~fixed
            if not new.any():
                break
            fixed |= new
            e = np.flatnonzero(new.any(axis=1))
            st = stop[e] & fixed[e]
            go = fixed[e] & ~st
            p = np.where(st[..., None], nxt[e], ahead[e])
            v = np.where(go[..., None], (nxt[e] - ahead[e]) / dt,
                         np.where(moving[e][..., None] & ~st[..., None], vel[e], 0.0))
            out = solve(e, p, v, ~moving[e] | st, go)
            command[e] = np.where(fixed[e][..., None], command[e], out.velocity)
            fell[e] = np.where(fixed[e], fell[e], out.fell_back & moving[e])
            self.resolves += int(e.size)
        self.fallbacks += int(fell.sum())
        return command

    def _advance(self, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """Positions after one step at velocity ``vel``, clamped by the walls as the
        simulator clamps them (shelves are not modelled: the QP keeps AGVs off them)."""
        nxt = pos + vel * self._world.physics.dt
        if self._world.walls:
            r = self._world.agent_radius
            xmin, ymin, xmax, ymax = self._world.bounds
            nxt = np.clip(nxt, [xmin + r, ymin + r], [xmax - r, ymax - r])
        return nxt

    def _claims(
        self, where: np.ndarray, idle: np.ndarray, claimed: np.ndarray, tasks: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The simulator's claim rule (:func:`sim.tasks.claim`) at positions ``where`` (B, N, 2).

        Returns
        -------
        takes : np.ndarray of bool, shape (B, N)
            AGVs that claim (and park).
        taken : np.ndarray of bool, shape (B, M)
            Tasks claimed.
        """
        d = np.linalg.norm(where[:, :, None, :] - tasks[:, None, :, :], axis=-1)  # (B, N, M)
        holding = torch.as_tensor(np.where(idle, -1, 0))
        running = torch.ones(where.shape[0], dtype=torch.bool)
        # A claim decided by less than the simulator's float32 rounding is not predicted.
        _, _, taken, takes = claim(torch.as_tensor(d), holding, torch.as_tensor(claimed), running,
                                   self._world.capture_radius - 1e-5)
        return takes.numpy(), taken.numpy()

    def _replan_stuck(
        self, pos: np.ndarray, vel: np.ndarray, held: np.ndarray, tasks: np.ndarray,
        moving: np.ndarray, count_progress: bool = True,
    ) -> None:
        """Route AGVs that stopped short of their task around the parked AGVs.

        Paths are planned among the shelves only; an AGV that parks on a route can block it
        (ORCA is local and waits in front of a gap too narrow to pass). After
        ``stuck_steps`` slow steps away from its task, an AGV gets a grid path around the
        parked AGVs as discs (:func:`~allocator.avoidance.detour.plan_around_discs`).
        """
        goal = np.take_along_axis(tasks, np.maximum(self.task_of_agent, 0)[..., None], 1)
        dist = np.linalg.norm(goal - pos, axis=-1)
        if count_progress:
            active = moving & (self.task_of_agent >= 0) & \
                (dist > 2 * self._world.capture_radius)
            progress = dist < self._best - 0.02
            self._best = np.where(progress | ~active, dist, self._best)
            self._stuck = np.where(active & ~progress, self._stuck + 1, 0)
        todo = np.argwhere(self._stuck >= self.stuck_steps)
        if not len(todo):
            return
        from allocator.avoidance.detour import plan_around_discs

        world = self._world
        r = world.agent_radius
        for b, i in todo:
            # the parked AGVs are discs (a square box per AGV closed diagonal gaps that an
            # AGV passes; see allocator/avoidance/detour.py)
            parked = pos[b][(held[b] >= 0) & (np.arange(held.shape[1]) != i)]
            path = plan_around_discs(world, pos[b, i], goal[b, i], parked, 2 * r + 0.02)
            self._stuck[b, i] = 0
            self._best[b, i] = np.inf
            if path is None:
                continue
            self.replans += 1
            self._paths[b][i] = path
            self._set_path(b, i, path)

    def _set_path(self, b: int, i: int, path: np.ndarray) -> None:
        """Replace one AGV's waypoints (grows the padded array if needed)."""
        if len(path) > self._waypoints.shape[2]:
            extra = len(path) - self._waypoints.shape[2]
            pad = np.repeat(self._waypoints[:, :, -1:], extra, axis=2)
            self._waypoints = np.concatenate([self._waypoints, pad], axis=2)
        self._waypoints[b, i, : len(path)] = path
        self._waypoints[b, i, len(path):] = path[-1]
        self._num_waypoints[b, i] = len(path)
        self._next[b, i] = 1

    def _preferred(self, ahead: np.ndarray, moving: np.ndarray) -> np.ndarray:
        """Preferred velocities (B, N, 2) along the paths, braking on the last leg."""
        ph = self._world.physics
        B, N, _ = ahead.shape
        wp, count = self._waypoints, self._num_waypoints
        has_path = (count > 0) & (self.task_of_agent >= 0)
        # Advance past intermediate waypoints already reached.
        for _ in range(wp.shape[2]):
            target = np.take_along_axis(wp, self._next[..., None, None].repeat(2, -1), 2)[:, :, 0]
            near = np.linalg.norm(target - ahead, axis=-1) < self.waypoint_tolerance
            step = near & (self._next < count - 1)
            if not step.any():
                break
            self._next = self._next + step
        target = np.take_along_axis(wp, self._next[..., None, None].repeat(2, -1), 2)[:, :, 0]
        last = self._next >= count - 1
        delta = target - ahead
        dist = np.linalg.norm(delta, axis=-1)
        cruise = self._cruise_speed()
        # Last leg: the speed from which the AGV can still stop on the task, and at most the
        # speed that lands exactly on it next step.
        goal_speed = np.minimum(np.sqrt(2.0 * self.brake * dist), dist / ph.dt)
        speed = np.where(last, np.minimum(cruise, goal_speed), cruise)
        direction = delta / np.maximum(dist, 1e-9)[..., None]
        pref = direction * speed[..., None]
        return np.where((moving & has_path)[..., None], pref, 0.0)
