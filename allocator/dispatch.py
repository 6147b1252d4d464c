"""Centralized dispatch for lifelong operation: who serves which order, re-planned on events.

A dispatcher is a lifelong controller (``reset(env)`` once, ``act(obs)`` each step, as
:func:`sim.evaluate_lifelong` calls it). On every step where ``env.events.any`` says something
happened in a floor (an arrival, a pickup, a delivery, a breakdown, a repair), it re-plans that
floor and hands the plan to ``env.assign``; then :class:`WaypointDriver` drives every AGV that
has a target along its obstacle-aware path (:class:`allocator.distances.FloorDistances`).

- :class:`FifoDispatcher`: the default strategy of OpenTCS, the oldest order (higher priority
  first) to its nearest available AGV, one by one; an assignment stays until pickup.
- :class:`HungarianDispatcher`: min-sum travel over the AGVs that are free or on their way to a
  pickup and the orders not yet picked up (:func:`scipy.optimize.linear_sum_assignment`), with a
  switching cost that keeps a plan unless another is better by more than it, and priorities as
  a discount on the cost.

Both are the first part of the classical lifelong dispatch (issue 14): the fleet-scale
controller with its safety and liveness guarantees comes next; the driver here only follows
paths (AGVs may still touch).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from allocator.distances import FloorDistances

__all__ = ["FifoDispatcher", "HungarianDispatcher", "LifelongDispatcher", "MatchingDispatcher",
           "WaypointDriver"]

_OPEN, _ASSIGNED = 1, 2
_IDLE, _TO_PICKUP = 0, 1


class WaypointDriver:
    """Each AGV with a target drives at the first corner of its path to it; the others brake.

    A proportional velocity command towards the waypoint (slowing down on the last leg),
    turned into the MPE acceleration action that reaches it in one step.

    Parameters
    ----------
    gain : float
        Desired velocity per unit distance to the waypoint (1/s).
    max_speed : float
        Cap on the commanded speed (world units per second).
    """

    def __init__(self, gain: float = 4.0, max_speed: float = 1.2) -> None:
        for name, value in (("gain", gain), ("max_speed", max_speed)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        self.gain = float(gain)
        self.max_speed = float(max_speed)
        self.distances: FloorDistances | None = None

    def reset(self, env: Any) -> None:
        """Bind to the env's floor (its distance table is built once per floor)."""
        self.distances = FloorDistances(env.world)
        self.physics = env.world.physics

    def act(self, env: Any) -> Tensor:
        """Actions (B, N, 2) for the env's current targets."""
        if self.distances is None:
            raise ValueError("WaypointDriver.reset(env) must be called before act")
        pos = env.agent_pos.double().cpu().numpy()
        vel = env.agent_vel.double().cpu().numpy()
        target, has = env.targets()
        target = target.double().cpu().numpy()
        has = has.cpu().numpy()
        cmd = np.zeros_like(pos)
        if has.any():
            a = pos[has]
            cmd[has] = (self.distances.next_waypoint(a, target[has]) - a) * self.gain
        speed = np.linalg.norm(cmd, axis=-1, keepdims=True)
        cmd = cmd * (self.max_speed / np.maximum(speed, self.max_speed))
        ph = self.physics
        action = (cmd - vel * (1.0 - ph.damping)) / (ph.sensitivity * ph.dt / ph.mass)
        return torch.as_tensor(np.clip(action, -1.0, 1.0), dtype=torch.float32)


class LifelongDispatcher:
    """Re-plan the floors where something happened, then drive (the shared loop).

    Subclasses define :meth:`plan`.

    Parameters
    ----------
    driver : WaypointDriver, optional
        How AGVs follow their targets (default :class:`WaypointDriver`).
    """

    def __init__(self, driver: WaypointDriver | None = None) -> None:
        if driver is not None and not hasattr(driver, "act"):
            raise ValueError(f"driver must have reset(env) and act(env), got {driver!r}")
        self.driver = driver or WaypointDriver()
        self.env: Any = None
        self.replans = 0

    def reset(self, env: Any) -> None:
        """Bind to a lifelong env and plan every floor."""
        if not getattr(env, "lifelong", False):
            raise ValueError("a lifelong dispatcher drives a lifelong env (sim.make_env("
                             "'warehouse-50', ...)); for episodes use allocator.make(...)")
        self.env = env
        self.driver.reset(env)
        self.distances = self.driver.distances
        self._replan(np.ones(env.num_envs, dtype=bool))

    def act(self, obs: Tensor | None = None) -> Tensor:
        """Re-plan where events happened, then the driver's actions (B, N, 2)."""
        env = self.env
        if env is None:
            raise ValueError("reset(env) must be called before act")
        todo = env.events.any.cpu().numpy()
        if todo.any():
            self._replan(todo)
        return self.driver.act(env)

    def _replan(self, floors: np.ndarray) -> None:
        env = self.env
        plan = env.fleet.order.clone()
        status = env.agent_status.cpu().numpy()
        plan[torch.as_tensor(status == 2)] = -1  # loaded AGVs keep their order (-1 = as is)
        o = env.orders
        pos = env.agent_pos.double().cpu().numpy()
        st = o.status.cpu().numpy()
        pickup = o.pickup.double().cpu().numpy()
        order_id = o.id.cpu().numpy()
        priority = o.priority.cpu().numpy()
        for b in np.flatnonzero(floors):
            row = self.plan(pos[b], status[b], plan[b].cpu().numpy(), st[b], pickup[b],
                            order_id[b], priority[b])
            plan[b] = torch.as_tensor(row)
        env.assign(plan)
        self.replans += int(floors.sum())

    def plan(self, pos: np.ndarray, status: np.ndarray, current: np.ndarray,
             order_status: np.ndarray, pickup: np.ndarray, order_id: np.ndarray,
             priority: np.ndarray) -> np.ndarray:
        """One floor's plan: the slot each AGV serves next (-1: none / keep a loaded one)."""
        raise NotImplementedError


class FifoDispatcher(LifelongDispatcher):
    """OpenTCS's default: the oldest order (higher priority first) to its nearest free AGV.

    An AGV keeps an assigned order until it picks it up; only free (idle, working) AGVs and
    open orders are matched, one order at a time.
    """

    def plan(self, pos: np.ndarray, status: np.ndarray, current: np.ndarray,
             order_status: np.ndarray, pickup: np.ndarray, order_id: np.ndarray,
             priority: np.ndarray) -> np.ndarray:
        plan = current.copy()
        free = np.flatnonzero(status == _IDLE)
        waiting = np.flatnonzero(order_status == _OPEN)
        if not len(free) or not len(waiting):
            return plan
        order = waiting[np.lexsort((order_id[waiting], -priority[waiting]))]
        take = order[: len(free)]
        dist = self.distances.distance(pos[free], pickup[take])  # (F, T)
        available = np.ones(len(free), dtype=bool)
        for j in range(len(take)):
            d = np.where(available, dist[:, j], np.inf)
            i = int(np.argmin(d))
            if not np.isfinite(d[i]):
                continue
            plan[free[i]] = take[j]
            available[i] = False
        return plan


class MatchingDispatcher(LifelongDispatcher):
    """Match the free and to-pickup AGVs with the orders not yet picked up, by a matching rule
    on their travel costs.

    Parameters
    ----------
    matching : callable
        ``matching(cost (A, O)) -> (rows, cols)``, e.g. :func:`scipy.optimize.
        linear_sum_assignment` (min-sum) or :func:`allocator.greedy.greedy_matching`.
    switching_cost : float
        Added to every pair but an AGV's current one, so a plan changes only for a gain larger
        than this (world units; default 0.5).
    priority_weight : float
        Each priority level is worth this much travel (default 2.0).
    driver : WaypointDriver, optional
    """

    def __init__(self, matching: Any = linear_sum_assignment, switching_cost: float = 0.5,
                 priority_weight: float = 2.0, driver: WaypointDriver | None = None) -> None:
        super().__init__(driver)
        if not callable(matching):
            raise ValueError(f"matching must be a callable cost -> (rows, cols), got "
                             f"{matching!r}")
        for name, value in (("switching_cost", switching_cost),
                            ("priority_weight", priority_weight)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        self.matching = matching
        self.switching_cost = float(switching_cost)
        self.priority_weight = float(priority_weight)

    def plan(self, pos: np.ndarray, status: np.ndarray, current: np.ndarray,
             order_status: np.ndarray, pickup: np.ndarray, order_id: np.ndarray,
             priority: np.ndarray) -> np.ndarray:
        plan = current.copy()
        agents = np.flatnonzero((status == _IDLE) | (status == _TO_PICKUP))
        orders = np.flatnonzero((order_status == _OPEN) | (order_status == _ASSIGNED))
        if not len(agents) or not len(orders):
            return plan
        cost = self.distances.distance(pos[agents], pickup[orders])  # (A, O)
        cost = cost - self.priority_weight * priority[orders][None, :]
        keep = current[agents][:, None] == orders[None, :]
        cost = cost + self.switching_cost * ~keep
        big = 1e9
        cost = np.where(np.isfinite(cost), cost, big)
        rows, cols = self.matching(cost)
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        plan[agents] = -1
        ok = cost[rows, cols] < big
        plan[agents[rows[ok]]] = orders[cols[ok]]
        return plan


class HungarianDispatcher(MatchingDispatcher):
    """Min-sum travel (:func:`scipy.optimize.linear_sum_assignment`) over the free and
    to-pickup AGVs and the orders not yet picked up, with a switching cost and priorities
    (see :class:`MatchingDispatcher`)."""

    def __init__(self, switching_cost: float = 0.5, priority_weight: float = 2.0,
                 driver: WaypointDriver | None = None) -> None:
        super().__init__(linear_sum_assignment, switching_cost, priority_weight, driver)
