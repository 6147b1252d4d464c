"""A safety shield for any controller: its actions through the ORCA QP and the braking filter.

A learned policy (or any controller of the ``reset(env)`` / ``act(obs)`` protocol) says where
each AGV wants to go next: its action is an intended velocity, ``(1 - damping) v + g a`` in the
simulator's physics. :class:`SafetyShield` changes that intention as little as it can so that
no two AGVs overlap:

0. **Detours** (episodic scenes, ``detour=True``; off by default): an idle AGV whose
   intention drives straight at an open task through a parked AGV turns toward a shortest
   path round the parked AGVs (:class:`~allocator.detour.ParkedDetour`). Without it the
   braking filter holds such an AGV against the parked one until the step limit.
1. **Liveness** (on lifelong floors by default): the intended velocities go through
   :class:`~allocator.avoidance.liveness.DeadlockResolver`, as in the lifelong
   :class:`~allocator.traffic.SafeDriver`: symmetry-breaking perturbation, stall detection,
   priority yielding, a right-turning roundabout, and idle AGVs pushed out of a stalled AGV's
   way. Without it a crowd that the QP and the braking filter hold still stays still.
2. **ORCA QP** (optional, on by default): the intended velocities are the preferred ones of
   :class:`~allocator.avoidance.VelocityAvoidance`, solved from where every AGV will be when
   the new velocity acts (``pos + v dt``), with parked, broken and serving AGVs as static
   obstacles. This is what keeps the policy moving smoothly past its neighbours.
3. **Braking filter** (always): :class:`~allocator.avoidance.braking.BrakingShield` certifies
   every AGV's next velocity: the QP's, else a blend of it with braking, else braking. That is
   the guarantee of ``docs/safety.md``: if no two AGVs' braking segments touch at the start,
   none ever overlap, whatever the policy does.

An *intervention* is an AGV-step whose action the shield changed by more than ``tolerance``
(in action units, per axis); :attr:`SafetyShield.interventions` counts them, split by which
stage changed the action. The liveness rules only change preferred velocities, which the
braking filter certifies like any other: the safety guarantee does not depend on them.

Examples
--------
>>> import allocator, sim
>>> env = sim.make_env("3v3", num_envs=4, seed=0)
>>> ctl = allocator.SafetyShield(allocator.make("maddpg-ipf", scenario="3v3"))
>>> ctl.reset(env)
>>> obs = env.observe()
>>> obs, *_ = env.step(ctl.act(obs))
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np
import torch
from torch import Tensor

from allocator.avoidance import AvoidanceConfig, VelocityAvoidance
from allocator.avoidance.braking import BrakingShield, braking_velocity
from allocator.avoidance.liveness import DeadlockResolver
from allocator.detour import ParkedDetour, detour_model

__all__ = ["SafetyShield", "movable_agents"]


def movable_agents(env: Any) -> np.ndarray:
    """The AGVs the simulator moves in the next step, (B, N) bool.

    Lifelong envs (those with a ``fleet``): AGVs neither broken nor in service. Episodic envs:
    idle AGVs (no task claimed). In both, only in running environments (where ``env.done``
    is False, when the env has one).
    """
    fleet = getattr(env, "fleet", None)
    if fleet is not None:
        movable = ~fleet.broken.detach().cpu().numpy() \
            & (fleet.service_left.detach().cpu().numpy() == 0)
    else:
        movable = env.agent_task.detach().cpu().numpy() < 0
    done = getattr(env, "done", None)
    if done is not None:
        movable &= ~done.detach().cpu().numpy().reshape(-1, 1)
    return movable


def turn_right(velocity: np.ndarray, angle: float) -> np.ndarray:
    """``velocity`` (..., 2) turned ``angle`` radians clockwise: the lane discipline that lets
    opposite flows in an aisle pass each other instead of meeting head on."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * velocity[..., 0] + s * velocity[..., 1],
                     -s * velocity[..., 0] + c * velocity[..., 1]], -1)


class SafetyShield:
    """Wraps a controller; its actions reach the simulator only after the shield.

    Parameters
    ----------
    controller : object
        Anything with ``reset(env)`` and ``act(obs) -> (B, N, 2)`` actions (a learned
        allocator, a scripted controller, your own policy).
    qp : bool
        Pass the intended velocities through the ORCA QP first (default True). Without it
        only the braking filter acts: fewer interventions of a larger size.
    margin : float
        Gap kept between two AGVs' braking segments (>= 0; default 0.01).
    tolerance : float
        An action changed by more than this (per axis, action units) counts as an
        intervention (> 0; default 1e-3).
    avoidance_options : dict, optional
        Fields of :class:`~allocator.avoidance.AvoidanceConfig` for the QP. Defaults here:
        ``time_horizon=0.3``, ``obstacle_time_horizon=0.25``, ``margin=0.02`` (a shield
        should change the policy as little as it can; the braking filter is what guarantees
        safety) and a ``max_speed`` whose polygon holds every velocity the physics can
        reach.
    liveness : bool or None
        Run the deadlock rules of :class:`~allocator.avoidance.liveness.DeadlockResolver` on
        the intended velocities before the QP, as :class:`~allocator.traffic.SafeDriver`
        does. ``None`` (default): on for lifelong envs (those with a ``fleet``), off for
        episodic ones, whose results stay what they were. ``True`` / ``False`` force it.
    seed : int
        Seed of the resolver's priorities and perturbations (>= 0; default 0).
    cruise_speed : float
        The speed the liveness rules take as cruising (> 0; default 1.2, SafeDriver's): an
        AGV wants to move when its intended speed exceeds 20 % of it, makes progress when
        its speed exceeds 10 % of it, and yields or steps aside at half of it.
    keep_right : float
        Where the liveness rules run: turn the intended velocities this many radians to the
        right first, SafeDriver's lane discipline (in [0, pi/2); default 0, the policy's
        direction).
    detour : bool or str
        Episodic scenes: turn intentions that drive at an open task through a parked AGV round
        it first (:class:`~allocator.detour.ParkedDetour`; default False). True is the
        ``"discs"`` model, which plans round discs with the shield's own gaps and keeps an
        AGV's goal while it is turned; ``"squares"`` is the first model, the default of True
        before 2026-12-07 (see ``ParkedDetour``'s ``model``). A lifelong env refuses it at
        :meth:`reset`.

    Attributes
    ----------
    interventions : dict
        ``{"any": n, "qp": n, "brake": n, "liveness": n, "detour": n}``: AGV-steps changed at
        all, before braking (by the liveness rules or the QP), certified only by braking (or a
        blend with it), changed by the liveness rules, and turned by a detour, since
        :meth:`reset`.
    live : bool
        Whether the liveness rules run on the env given to :meth:`reset`.
    resolver : DeadlockResolver or None
        The liveness rules' state (``resolver.yields`` counts the yields), when they run.
    agent_steps : int
        Movable AGV-steps seen since :meth:`reset` (the denominator of the rates).
    last_changed : np.ndarray of bool, shape (B, N)
        The AGVs whose action the last call changed.

    Raises
    ------
    ValueError
        For a controller without ``reset`` and ``act``, or a margin, tolerance, liveness,
        seed, cruise speed or option that is not valid (the message names it).
    """

    def __init__(self, controller: Any, qp: bool = True, margin: float = 0.01,
                 tolerance: float = 1e-3, avoidance_options: dict[str, Any] | None = None,
                 liveness: bool | None = None, seed: int = 0, cruise_speed: float = 1.2,
                 keep_right: float = 0.0, detour: bool | str = False) -> None:
        if not (callable(getattr(controller, "reset", None))
                and callable(getattr(controller, "act", None))):
            raise ValueError(f"controller must have reset(env) and act(obs) methods, got "
                             f"{type(controller).__name__}")
        if not isinstance(qp, (bool, np.bool_)):
            raise ValueError(f"qp must be True or False, got {qp!r}")
        for name, value, low_ok in (("margin", margin, True), ("tolerance", tolerance, False)):
            if isinstance(value, bool) or not isinstance(value, numbers.Real) \
                    or not np.isfinite(value) or value < 0 or (value == 0 and not low_ok):
                bound = ">= 0" if low_ok else "> 0"
                raise ValueError(f"{name} must be a finite number {bound}, got {value!r}")
        if liveness is not None and not isinstance(liveness, (bool, np.bool_)):
            raise ValueError(f"liveness must be None (on for lifelong envs), True or False, "
                             f"got {liveness!r}")
        if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) \
                or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        if isinstance(cruise_speed, (bool, np.bool_)) \
                or not isinstance(cruise_speed, numbers.Real) \
                or not np.isfinite(cruise_speed) or cruise_speed <= 0:
            raise ValueError(f"cruise_speed must be a finite number > 0, got {cruise_speed!r}")
        if isinstance(keep_right, (bool, np.bool_)) or not isinstance(keep_right, numbers.Real) \
                or not np.isfinite(keep_right) or not 0 <= keep_right < np.pi / 2:
            raise ValueError(f"keep_right must be an angle in [0, pi/2) radians, got "
                             f"{keep_right!r}")
        model = detour_model(detour)
        if avoidance_options is not None and not isinstance(avoidance_options, dict):
            raise ValueError(f"avoidance_options must be a dict of AvoidanceConfig fields, "
                             f"got {type(avoidance_options).__name__}")
        self.controller = controller
        self.qp = bool(qp)
        self.margin = float(margin)
        self.tolerance = float(tolerance)
        self.avoidance_options = dict(avoidance_options or {})
        self.liveness = None if liveness is None else bool(liveness)
        self.seed = int(seed)
        self.cruise_speed = float(cruise_speed)
        self.keep_right = float(keep_right)
        self.detour = model is not None
        self.detour_model = model
        """``"squares"`` or ``"discs"`` (:class:`~allocator.detour.ParkedDetour`'s ``model``),
        None without detours."""
        self._detour: ParkedDetour | None = None
        self.live = False
        self.resolver: DeadlockResolver | None = None
        self.env: Any = None
        self._avoid: VelocityAvoidance | None = None
        self._brake: BrakingShield | None = None
        self.interventions = {"any": 0, "qp": 0, "brake": 0, "liveness": 0, "detour": 0}
        self.agent_steps = 0
        self.last_changed = np.zeros((0, 0), dtype=bool)

    def __repr__(self) -> str:
        return (f"SafetyShield({self.controller!r}, qp={self.qp}, liveness={self.liveness}, "
                f"detour={self.detour_model or False!r})")

    @property
    def name(self) -> str:
        """The wrapped controller's name with ``+shield``."""
        return f"{getattr(self.controller, 'name', type(self.controller).__name__)}+shield"

    def reset(self, env: Any) -> None:
        """Reset the wrapped controller and the counters; build the QP for ``env``'s world
        and, where the liveness rules run (see ``liveness``), a fresh resolver."""
        if self.detour:  # first: a lifelong env is refused before anything is bound
            self._detour = ParkedDetour(model=self.detour_model)
            self._detour.reset(env)
        else:
            self._detour = None
        self.controller.reset(env)
        self.env = env
        world = env.world
        ph = world.physics
        # The QP only smooths what the policy intends (the braking filter is the guarantee):
        # a short horizon and a small margin, and a speed polygon that holds every velocity
        # one action can reach (|v| <= the physics' cap, or the terminal speed per axis).
        top = float(ph.max_speed) if ph.max_speed is not None \
            else float(ph.terminal_speed) * np.sqrt(2.0)
        opts: dict[str, Any] = dict(time_horizon=0.3, obstacle_time_horizon=0.25, margin=0.02)
        opts.update(self.avoidance_options)
        sides = int(opts.get("polygon_sides", 12))
        opts.setdefault("max_speed", top / np.cos(np.pi / max(sides, 3)) * (1 + 1e-6))
        try:
            config = AvoidanceConfig.for_world(world, **opts)
        except TypeError as err:
            raise ValueError(f"avoidance_options: {err}") from None
        self._avoid = VelocityAvoidance(world, config) if self.qp else None
        self._brake = BrakingShield.for_world(world, margin=self.margin)
        self.live = self.liveness if self.liveness is not None \
            else getattr(env, "fleet", None) is not None
        self.resolver = DeadlockResolver(env.num_envs, env.num_agents, world.agent_radius,
                                         seed=self.seed) if self.live else None
        self.interventions = {"any": 0, "qp": 0, "brake": 0, "liveness": 0, "detour": 0}
        self.agent_steps = 0
        self.last_changed = np.zeros((env.num_envs, env.num_agents), dtype=bool)

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        """The wrapped controller's actions for ``obs``, made safe: (B, N, O) -> (B, N, 2)."""
        return self.filter(self.controller.act(obs))

    @torch.no_grad()
    def filter(self, actions: Tensor | np.ndarray) -> Tensor:
        """Make actions of the environment given to :meth:`reset` safe.

        The velocities the actions intend go through the liveness rules (where they run),
        the QP (``qp=True``) and the braking filter, in that order.

        Parameters
        ----------
        actions : Tensor or array, shape (B, N, 2)
            Intended accelerations (clipped to [-1, 1] as the simulator does).

        Returns
        -------
        Tensor, shape (B, N, 2)
            The certified actions, of the env's dtype and device. AGVs that do not move in
            this step (parked, broken, in service, finished scenes) keep their action: the
            simulator ignores it.

        Raises
        ------
        ValueError
            Before :meth:`reset`, or for actions of another shape or not finite.
        """
        env = self.env
        if env is None:
            raise ValueError("SafetyShield.filter needs reset(env) first")
        a = actions.detach().cpu().double().numpy() if isinstance(actions, Tensor) \
            else np.asarray(actions, dtype=np.float64)
        B, N = env.num_envs, env.num_agents
        if a.shape != (B, N, 2):
            raise ValueError(f"actions must have shape (B, N, 2) = {(B, N, 2)}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("actions contain NaN or infinite values")
        a = np.clip(a, -1.0, 1.0)
        pos = env.agent_pos.detach().cpu().double().numpy()
        vel = env.agent_vel.detach().cpu().double().numpy()
        movable = movable_agents(env)
        brake = self._brake
        assert brake is not None
        intended = brake.realised(vel, a)
        turned = np.zeros_like(movable)
        if self._detour is not None:
            turn, turned = self._detour.redirect(intended, movable)
            # the action toward the turned velocity, scaled (not clipped per axis) into the
            # box so that it keeps the detour's direction
            push = (turn - (1.0 - brake.damping) * vel) / brake.gain
            push /= np.maximum(1.0, np.abs(push).max(-1, keepdims=True))
            intended = np.where(turned[..., None], brake.realised(vel, push), intended)
        planned = intended
        ahead = pos + vel * env.world.physics.dt * movable[..., None]
        by_rules = np.zeros_like(movable)
        if self.resolver is not None:
            # SafeDriver's liveness step on the intended velocities: what the policy wants
            # is what the resolver takes as preferred, before the QP and the braking filter.
            speed = self.cruise_speed
            wanted = np.where(movable[..., None], intended, 0.0)
            if self.keep_right:  # SafeDriver's lane discipline
                wanted = turn_right(wanted, self.keep_right)
            wants = movable & (np.linalg.norm(wanted, axis=-1) > 0.2 * speed)
            progress = np.linalg.norm(vel, axis=-1) > 0.1 * speed
            pushable = None
            if callable(getattr(env, "targets", None)):
                has = env.targets()[1].detach().cpu().numpy().astype(bool)
                pushable = movable & ~has
            preferred = self.resolver.apply(ahead, wanted, wants, progress, speed,
                                            pushable=pushable)
            planned = brake.realised(vel, brake.action_for(vel, preferred))
            intended = np.where(movable[..., None], planned, intended)
            by_rules = movable & (np.abs(brake.action_for(vel, planned) - a).max(-1)
                                  > self.tolerance)
        if self._avoid is not None and movable.any():
            result = self._avoid.solve(ahead, np.where(movable[..., None], vel, 0.0),
                                       np.where(movable[..., None], intended, 0.0),
                                       static=~movable)
            planned = brake.realised(vel, brake.action_for(vel, result.velocity))
        stop = braking_velocity(vel, brake.damping, brake.gain)
        blends = [planned] + [stop + f * (planned - stop) for f in (0.6, 0.3)]
        out = brake.filter(pos, vel, np.stack(blends, axis=2), movable)
        safe = np.where(movable[..., None], out.action, a)
        qp_action = brake.action_for(vel, planned)
        by_qp = movable & (np.abs(qp_action - a).max(-1) > self.tolerance)
        changed = movable & (np.abs(safe - a).max(-1) > self.tolerance)
        braked = movable & (np.asarray(out.choice) > 0)
        self.interventions["any"] += int(changed.sum())
        self.interventions["qp"] += int(by_qp.sum())
        self.interventions["brake"] += int(braked.sum())
        self.interventions["liveness"] += int(by_rules.sum())
        self.interventions["detour"] += int(turned.sum())
        self.agent_steps += int(movable.sum())
        self.last_changed = changed
        return torch.as_tensor(safe, dtype=env.dtype, device=env.device)

    def intervention_rate(self) -> float:
        """Share of movable AGV-steps whose action was changed since :meth:`reset`."""
        return self.interventions["any"] / max(self.agent_steps, 1)
