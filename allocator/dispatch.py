"""Centralized dispatch for lifelong operation: who serves which order, re-planned on events.

A dispatcher is a lifelong controller (``reset(env)`` once, ``act(obs)`` each step, as
:func:`sim.evaluate_lifelong` calls it). On every step where ``env.events.any`` says something
happened in a floor (an arrival, a pickup, a delivery, a breakdown, a repair), it re-plans that
floor and hands the plan to ``env.assign``; then a driver moves every AGV that has a target
along its obstacle-aware path (:class:`allocator.distances.FloorDistances`): by default
:class:`WaypointDriver`, which only follows paths (fast, for throughput studies; AGVs may
touch), or ``driver=allocator.SafeDriver()`` (:mod:`allocator.traffic`: ORCA, the braking
shield that keeps AGVs apart and the deadlock rules, ``docs/safety.md``).

- :class:`FifoDispatcher`: the default strategy of OpenTCS, the oldest order (higher priority
  first) to its nearest idle AGV, one by one; an assignment stays until pickup.
- :class:`HungarianDispatcher`: min-sum over the AGVs (idle, on their way to a pickup, and
  loaded ones counted from their drop-off when they will be free there) and the orders not yet
  picked up (an optimum as :func:`scipy.optimize.linear_sum_assignment` gives, solved
  incrementally from the previous re-plan by :class:`allocator.lap.IncrementalLAP`), in
  estimated steps to the pickup,
  with priorities, deadlines (a discount for an order that misses its deadline unless served in
  this plan, a penalty per step an AGV would be late), a switching cost that keeps a plan
  unless another is better by more than it, and orders that have waited ``max_wait`` steps
  (default :data:`HUNGARIAN_MAX_WAIT`, 150) matched first, oldest first, so that none
  starves.
- :class:`MatchingDispatcher` with another matching rule: ``"greedy"``'s dispatcher.
- :class:`AuctionDispatcher`: the same costs, matched by the decentralized epsilon-auction of
  :mod:`allocator.auction` over the AGVs' communication graph, with the messages counted.

**Next orders.** ``env.assign`` gives an AGV one order at a time and a loaded AGV keeps the one
it carries, so a loaded AGV's match (its *next* order) is held in the dispatcher
(:attr:`MatchingDispatcher.next_order`): the order stays open in the env (any AGV may still be
matched to it at the next re-plan), and the match is handed to ``env.assign`` at the delivery,
which is itself an event that re-plans (the switching cost keeps the held match unless a better
one appeared meanwhile).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from allocator.auction import check_comm_range, component_auction
from allocator.distances import FloorDistances
from allocator.lap import IncrementalLAP, _lookup, _sub

__all__ = ["AuctionDispatcher", "FifoDispatcher", "HUNGARIAN_MAX_WAIT",
           "HUNGARIAN_OVERDUE_WEIGHT", "HungarianDispatcher", "LifelongDispatcher",
           "MatchingDispatcher", "WaypointDriver", "at_risk", "lateness", "next_empty"]

_OPEN, _ASSIGNED = 1, 2
_IDLE, _TO_PICKUP, _LOADED, _BROKEN = 0, 1, 2, 3
_BIG = 1e9
_INCREMENTAL_MIN_SIZE = 40_000
"""Cost entries below which a from-scratch ``linear_sum_assignment`` beats the warm start's
bookkeeping (measured: at 100 x 150 the solve is 0.5 ms, the bookkeeping about 1 ms)."""
_RETURNED_BONUS = 1e5
"""World units taken off an order a breakdown returned, for the AGVs free now: more than any
travel on a floor, so the next plan reassigns it while an AGV is free."""
HUNGARIAN_MAX_WAIT = 150.0
"""The default ``max_wait`` of :class:`HungarianDispatcher` (steps): an order that has waited
this long is matched before all others (with :data:`HUNGARIAN_OVERDUE_WEIGHT`, the older
overdue orders first), so that no order starves. Measured at saturation
(``benchmarks/load_curve.py --probe``, 1500 steps; deliveries per 1000 steps / the age of the
oldest order still open at the end; *w* = ``overdue_weight``):

==============  ====  ============  ===========  ============  ============  ============
floor           seed  inf           150          150, w 1      300           300, w 1
==============  ====  ============  ===========  ============  ============  ============
warehouse-50    0     392.7 / 1500  391.3 / 547  394.7 / 436   392.7 / 464   395.3 / 621
warehouse-50    1     390.0 / 1500  386.7 / 329  385.3 / 317   391.3 / 731   391.3 / 691
kiva-small      0     166.7 / 1500  165.3 / 331  164.0 / 320   165.3 / 515   165.3 / 511
kiva-small      1     172.0 / 1500  169.3 / 357  166.0 / 318   172.0 / 437   169.3 / 428
==============  ====  ============  ===========  ============  ============  ============

150 with w 1 keeps the oldest open order at 317-436 steps (FIFO's: 245-301) for 1.5% of the
throughput on average (+0.5% to -3.5%, the spread of single runs); 300 lets orders wait up to
731 steps: many orders are overdue at once, and with w 0 the min-sum plan prefers the near
ones among them again."""
HUNGARIAN_OVERDUE_WEIGHT = 1.0
"""The default ``overdue_weight`` of :class:`HungarianDispatcher` (world units per step
overdue, about 8 steps of travel): two overdue orders a few steps apart in age are matched
oldest first, whatever their travel."""
_OVERDUE_CAP = 4e4
"""The most world units an overdue order's age adds to its credit (``overdue_weight``): below
:data:`_RETURNED_BONUS` less :data:`_OVERDUE_BONUS`."""
_OVERDUE_BONUS = 1e3
"""World units taken off an order that has waited ``max_wait`` steps: more than any travel on
the built-in floors, less than :data:`_RETURNED_BONUS`, so overdue orders are matched first,
each to an AGV near it."""


def _check_nonneg(name: str, value: object, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or math.isnan(value) or (value <= 0 if positive else value < 0):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be a number {bound}, got {value!r}")
    return float(value)


def lateness(eta: np.ndarray, latest: np.ndarray) -> np.ndarray:
    """Steps by which each pair would miss its deadline: ``max(0, eta[i, j] - latest[j])``.

    Parameters
    ----------
    eta : np.ndarray, shape (A, O)
        Steps from now until AGV i could reach order j's pickup.
    latest : np.ndarray, shape (O,)
        Latest pickup step (relative to now) that still meets j's deadline; ``inf`` for an
        order without one.

    Returns
    -------
    np.ndarray of float64, shape (A, O)
    """
    with np.errstate(invalid="ignore"):
        late = eta - latest[None, :]
    return np.where(late > 0, late, 0.0)


def next_empty(distances: FloorDistances, dropoff: np.ndarray, pickup: np.ndarray,
               k: int = 1) -> np.ndarray:
    """The empty trip each order leaves behind: from its drop-off to the other open pickups.

    For order j, the mean travel from ``dropoff[j]`` to the ``k`` nearest pickups of the
    other orders (all of them when there are fewer; 0 for a lone order). An order that ends
    near other pickups shortens the next empty trip of the AGV that serves it.

    Parameters
    ----------
    distances : FloorDistances
    dropoff : np.ndarray, shape (O, 2)
    pickup : np.ndarray, shape (O, 2)
    k : int
        Nearest pickups averaged, >= 1.

    Returns
    -------
    np.ndarray of float64, shape (O,)
        World units (an unreachable pickup counts 0: it says nothing of the next trip).
    """
    n = len(pickup)
    if n < 2:
        return np.zeros(n)
    # Drop-offs repeat (stations): one row of the table per distinct point.
    uniq, inv = np.unique(dropoff, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    kk = min(k, n - 1)
    d = distances.distance(uniq, pickup)  # (U, O)
    # The kk + 1 nearest of each row; order j drops its own pickup when it is among them.
    near = np.argpartition(d, kk, axis=1)[:, :kk + 1] if kk + 1 < n else \
        np.broadcast_to(np.arange(n), (len(uniq), n))
    vals = np.take_along_axis(d, near, axis=1)  # (U, kk + 1)
    order = np.argsort(vals, axis=1)
    vals = np.take_along_axis(vals, order, axis=1)
    near = np.take_along_axis(near, order, axis=1)
    rows_v, rows_n = vals[inv], near[inv]  # (O, kk + 1)
    own = rows_n == np.arange(n)[:, None]
    keep = ~own
    # Without its own pickup among them, an order keeps the first kk (drop the farthest).
    keep[~own.any(axis=1), kk] = False
    keep &= np.isfinite(rows_v)
    return np.where(keep, rows_v, 0.0).sum(axis=1) / kk


def at_risk(eta: np.ndarray, latest: np.ndarray, horizon: float) -> np.ndarray:
    """Orders that can still meet their deadline, but only if they are served in this plan.

    An order is at risk when its best AGV reaches it in time (``min_i eta[i, j] <=
    latest[j]``) with less than ``horizon`` steps to spare: the next plan is about that far
    away for an order left out of this one.

    Parameters
    ----------
    eta : np.ndarray, shape (A, O)
    latest : np.ndarray, shape (O,)
        ``inf`` for an order without deadline (never at risk).
    horizon : float
        Steps (``inf``: every order that can still meet its deadline).

    Returns
    -------
    np.ndarray of bool, shape (O,)
    """
    if eta.shape[0] == 0:
        return np.zeros(eta.shape[1], dtype=bool)
    spare = latest - eta.min(axis=0)
    return np.isfinite(latest) & (spare >= 0) & (spare < horizon)


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

    def command(self, env: Any) -> tuple[np.ndarray, np.ndarray]:
        """The velocity commands (B, N, 2) toward each AGV's waypoint (zero without a
        target), and the unclipped actions (B, N, 2) that reach them in one step."""
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
        return cmd, action

    def act(self, env: Any) -> Tensor:
        """Actions (B, N, 2) for the env's current targets (:meth:`command`'s, clipped to
        [-1, 1] per axis)."""
        _, action = self.command(env)
        return torch.as_tensor(np.clip(action, -1.0, 1.0), dtype=torch.float32)


class LifelongDispatcher:
    """Re-plan the floors where something happened, then drive (the shared loop).

    Subclasses define :meth:`_solve` (or :meth:`plan`).

    Parameters
    ----------
    driver : WaypointDriver, optional
        How AGVs follow their targets (default :class:`WaypointDriver`).

    Attributes
    ----------
    replans : int
        Floors re-planned so far.
    next_order : np.ndarray of int64, shape (B, N)
        The order slot each loaded AGV is matched to next (held here until its delivery; -1
        for none); -1 everywhere for a dispatcher that does not plan ahead.
    speed : float
        World units an AGV covers per step in the estimates (the driver's top speed times dt).
    """

    def __init__(self, driver: WaypointDriver | None = None) -> None:
        if driver is not None and not hasattr(driver, "act"):
            raise ValueError(f"driver must have reset(env) and act(env), got {driver!r}")
        self.driver = driver or WaypointDriver()
        self.env: Any = None
        self.replans = 0
        self.next_order = np.zeros((0, 0), dtype=np.int64)
        self.speed = 1.0
        self.service_steps = 0
        self._floor = -1  # the floor being planned (-1: a direct plan() call)

    def reset(self, env: Any) -> None:
        """Bind to a lifelong env and plan every floor."""
        if not getattr(env, "lifelong", False):
            raise ValueError("a lifelong dispatcher drives a lifelong env (sim.make_env("
                             "'warehouse-50', ...)); for episodes use allocator.make(...)")
        self.env = env
        self.driver.reset(env)
        self.distances = self.driver.distances
        ph = env.world.physics
        self.speed = float(getattr(self.driver, "max_speed", ph.terminal_speed)) * ph.dt
        self.service_steps = int(env.scenario.service_steps)
        self.next_order = np.full((env.num_envs, env.num_agents), -1, dtype=np.int64)
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
        self.env.assign(torch.as_tensor(self.plan_floors(floors)))
        self.replans += int(floors.sum())

    def plan_floors(self, floors: np.ndarray) -> np.ndarray:
        """The plan of the bound env's floors where ``floors`` (B,) holds, without giving it.

        The other floors' rows keep each AGV's current order (a loaded AGV's as -1). Updates
        :attr:`next_order` (and a matching dispatcher's solver state) as a re-plan does;
        :meth:`act` gives the plan with ``env.assign``. A caller that keeps the plan to itself
        (an imitation teacher whose student claims orders by reaching them) reads it here.

        Returns
        -------
        np.ndarray of int64, shape (B, N)
            The order slot each AGV serves next (-1: none, or keep a loaded one).
        """
        env = self.env
        if env is None:
            raise ValueError("reset(env) must be called before plan_floors")
        fleet, o = env.fleet, env.orders
        current = fleet.order.cpu().numpy()
        status = env.agent_status.cpu().numpy()
        service_left = fleet.service_left.cpu().numpy()
        pos = env.agent_pos.double().cpu().numpy()
        st = o.status.cpu().numpy()
        pickup = o.pickup.double().cpu().numpy()
        dropoff = o.dropoff.double().cpu().numpy()
        order_id = o.id.cpu().numpy()
        priority = o.priority.cpu().numpy()
        release = o.release.cpu().numpy()
        deadline = o.deadline.cpu().numpy()
        now = env.steps.cpu().numpy()
        returned = env.events.returned.cpu().numpy()
        plan = np.full(current.shape, -1, dtype=np.int64)
        for b in np.flatnonzero(~floors):
            plan[b] = np.where(status[b] == _LOADED, -1, current[b])  # as they are
        for b in np.flatnonzero(floors):
            self._floor = int(b)
            row, nxt = self._solve(pos[b], status[b], current[b], st[b], pickup[b],
                                   order_id[b], priority[b], dropoff=dropoff[b],
                                   release=release[b], deadline=deadline[b], now=int(now[b]),
                                   service_left=service_left[b],
                                   next_order=self.next_order[b], returned=returned[b])
            plan[b] = row
            self.next_order[b] = nxt
        self._floor = -1
        return plan

    def plan(self, pos: np.ndarray, status: np.ndarray, current: np.ndarray,
             order_status: np.ndarray, pickup: np.ndarray, order_id: np.ndarray,
             priority: np.ndarray, *, dropoff: np.ndarray | None = None,
             release: np.ndarray | None = None, deadline: np.ndarray | None = None,
             now: int = 0, service_left: np.ndarray | None = None,
             next_order: np.ndarray | None = None,
             returned: np.ndarray | None = None) -> np.ndarray:
        """One floor's plan: the slot each AGV serves next (-1: none, or keep a loaded one).

        Parameters
        ----------
        pos : np.ndarray, shape (N, 2)
            AGV positions.
        status : np.ndarray of int, shape (N,)
            :data:`sim.orders.AGENT_STATUS` codes (0 idle, 1 to pickup, 2 loaded, 3 broken).
        current : np.ndarray of int, shape (N,)
            The slot each AGV is assigned to or carries (-1: none; a loaded AGV given -1 is
            left out of the plan, its drop-off unknown).
        order_status : np.ndarray of int, shape (Q,)
            :data:`sim.orders.ORDER_STATUS` codes per slot.
        pickup : np.ndarray, shape (Q, 2)
        order_id : np.ndarray of int, shape (Q,)
        priority : np.ndarray of int, shape (Q,)
        dropoff : np.ndarray, shape (Q, 2), optional
            Drop-offs: with them a loaded AGV is matched from its drop-off (its next order,
            held in :attr:`last_next`) and deadlines count the loaded trip.
        release, deadline : np.ndarray of int, shape (Q,), optional
            Release and due steps (deadline -1: none).
        now : int
            The current step (deadlines are absolute steps).
        service_left : np.ndarray of int, shape (N,), optional
            Steps of service each AGV still stands.
        next_order : np.ndarray of int, shape (N,), optional
            The next orders held from the previous plan (kept unless another plan is better
            by the switching cost).
        returned : np.ndarray of bool, shape (Q,), optional
            Orders a breakdown just took from their AGV: they go first to the AGVs free now
            (``env.events.returned``), so that each is reassigned at once while one is free.

        Returns
        -------
        np.ndarray of int64, shape (N,)
            For ``env.assign``; a loaded AGV's next order is in :attr:`last_next`.
        """
        row, nxt = self._solve(pos, status, current, order_status, pickup, order_id, priority,
                               dropoff=dropoff, release=release, deadline=deadline, now=now,
                               service_left=service_left, next_order=next_order,
                               returned=returned)
        self.last_next = nxt
        return row

    def _solve(self, pos: np.ndarray, status: np.ndarray, current: np.ndarray,
               order_status: np.ndarray, pickup: np.ndarray, order_id: np.ndarray,
               priority: np.ndarray, **extra: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(plan row (N,), next order per AGV (N,))`` for one floor."""
        raise NotImplementedError


class FifoDispatcher(LifelongDispatcher):
    """OpenTCS's default: the oldest order (higher priority first) to its nearest idle AGV.

    An AGV keeps an assigned order until it picks it up; only idle (working, free) AGVs and
    open orders are matched, one order at a time in (priority descending, id ascending) order,
    each to the nearest idle AGV left by travel distance; orders a breakdown just returned go
    first. It plans no next orders.
    """

    def _solve(self, pos: np.ndarray, status: np.ndarray, current: np.ndarray,
               order_status: np.ndarray, pickup: np.ndarray, order_id: np.ndarray,
               priority: np.ndarray, **extra: Any) -> tuple[np.ndarray, np.ndarray]:
        plan = np.where(status == _LOADED, -1, current).astype(np.int64)
        nxt = np.full(len(pos), -1, dtype=np.int64)
        free = np.flatnonzero(status == _IDLE)
        waiting = np.flatnonzero(order_status == _OPEN)
        if not len(free) or not len(waiting):
            return plan, nxt
        back = extra.get("returned")
        first = np.zeros(len(waiting), dtype=bool) if back is None else back[waiting]
        order = waiting[np.lexsort((order_id[waiting], -priority[waiting], ~first))]
        take = order[: len(free)]
        dist = self.distances.distance(pos[free], pickup[take])  # (F, T)
        available = np.ones(len(free), dtype=bool)
        for j in range(len(take)):  # a loop over at most F orders, each an array op
            d = np.where(available, dist[:, j], np.inf)
            i = int(np.argmin(d))
            if not np.isfinite(d[i]):
                continue
            plan[free[i]] = take[j]
            available[i] = False
        return plan, nxt


class MatchingDispatcher(LifelongDispatcher):
    """Match the AGVs with the orders not yet picked up, by a matching rule on estimated costs.

    The AGVs: idle and to-pickup ones from where they are, and (given drop-offs) loaded ones
    from their drop-off once there; broken ones never. The orders: open and assigned ones.
    The cost of AGV i for order j, in world units (steps times :attr:`speed`)::

        speed * eta[i, j]                                   # steps until i could be at j
        - priority_weight * priority[j]
        + lateness_weight * speed * max(0, eta[i, j] - latest[j])
        - deadline_bonus * at_risk[j]
        - 1e5 * (j was just returned by a breakdown and i is not loaded)
        + switching_cost * (j is not i's current or held order)
        + trip_weight * travel(pickup_j, dropoff_j)         # the loaded trip
        + next_weight * next_empty[j]                       # the empty trip j leaves behind
        - (1e3 + overdue_weight * (age[j] - max_wait))  # if age[j] >= max_wait

    with ``age[j] = now - release[j]``, ``eta[i, j] = lag[i] + travel(ready_i, pickup_j) /
    speed``; ``lag`` is 0 for an AGV
    that is free (plus service steps still to stand), and for a loaded AGV the remaining
    travel to its drop-off over ``speed`` plus the service steps there; ``latest[j]`` is the
    latest pickup step (from now) that meets j's deadline (its deadline minus the loaded
    trip's steps and the service at both ends; ``inf`` without deadline), and ``at_risk[j]``
    says j can still meet it but with less than ``deadline_horizon`` steps to spare
    (:func:`at_risk`), so that it is served now rather than in a later
    plan. A loaded AGV's match is its next order, held in :attr:`next_order`.

    Parameters
    ----------
    matching : callable
        ``matching(cost (A, O)) -> (rows, cols)``, e.g. :func:`scipy.optimize.
        linear_sum_assignment` (min-sum) or :func:`allocator.greedy.greedy_matching`.
    switching_cost : float
        World units added to every pair but an AGV's current one (default 0.5).
    priority_weight : float
        Each priority level is worth this much travel (default 2.0).
    deadline_bonus : float
        World units taken off an order at risk of missing its deadline (default 5.0).
    lateness_weight : float
        Cost per world unit an AGV would arrive past the order's latest pickup (default 1.0).
    deadline_horizon : float
        Steps of spare time below which an order is at risk (default 100).
    plan_ahead : bool
        Match loaded AGVs to their next orders (default True).
    trip_weight : float
        World units per unit of the order's loaded trip (pickup to drop-off) added to its
        column (default 0): > 0 prefers short trips at saturation. Measured on the Kiva floor
        at saturation it does not raise throughput (166 at 0, 159 at 1.0, 168 at 0.5 per 1000
        steps, 800 steps, seed 0) and lowers the p95 wait a little.
    ahead_steps : float
        With ``plan_ahead``, only loaded AGVs at most this many steps from being free are
        matched to a next order (default ``inf``: every loaded AGV).
    next_weight : float
        World units per unit of the empty trip an order leaves behind (:func:`next_empty`:
        the mean travel from its drop-off to the ``next_k`` nearest other open pickups)
        added to its column (default 0): > 0 prefers orders that end near other work.
        Measured on warehouse-50 at saturation (1500 steps, seed 0): 402.0 orders per 1000
        steps at 1.0 (``next_k`` 3) against 392.7 at 0, p95 wait 378.5 against 320.0; the
        spread between seeds is as large (docs/classical.md), so it is not the default.
    next_k : int
        Nearest other pickups :func:`next_empty` averages (default 1).
    max_wait : float
        Steps since its release after which an order not yet picked up is matched before
        all others (default here ``inf``: never; :class:`HungarianDispatcher`'s default is
        :data:`HUNGARIAN_MAX_WAIT`). A min-sum plan at saturation can leave an order that is
        far from every AGV unserved for good: without it, under Hungarian on warehouse-50 and
        on the Kiva floor the oldest open order after 1500 steps was released at step 0
        (``load_curve.py``, oldest open at end; FIFO's 245-301 steps).
    overdue_weight : float
        World units taken off an overdue order's column per step it has waited beyond
        ``max_wait`` (default 0 here, :data:`HUNGARIAN_OVERDUE_WEIGHT` for
        :class:`HungarianDispatcher`; at most 40,000): > 0 serves the overdue orders oldest
        first, where 0 lets the min-sum plan prefer the near ones among them.
    driver : WaypointDriver, optional
    """

    def __init__(self, matching: Any = linear_sum_assignment, switching_cost: float = 0.5,
                 priority_weight: float = 2.0, driver: WaypointDriver | None = None, *,
                 deadline_bonus: float = 5.0, lateness_weight: float = 1.0,
                 deadline_horizon: float = 100.0, plan_ahead: bool = True,
                 trip_weight: float = 0.0, ahead_steps: float = math.inf,
                 next_weight: float = 0.0, next_k: int = 1,
                 max_wait: float = math.inf, overdue_weight: float = 0.0) -> None:
        super().__init__(driver)
        if not callable(matching):
            raise ValueError(f"matching must be a callable cost -> (rows, cols), got "
                             f"{matching!r}")
        for name, value in (("switching_cost", switching_cost),
                            ("priority_weight", priority_weight),
                            ("deadline_bonus", deadline_bonus),
                            ("lateness_weight", lateness_weight),
                            ("trip_weight", trip_weight),
                            ("next_weight", next_weight)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        self.deadline_horizon = _check_nonneg("deadline_horizon", deadline_horizon, True)
        if not isinstance(plan_ahead, (bool, np.bool_)):
            raise ValueError(f"plan_ahead must be True or False, got {plan_ahead!r}")
        self.matching = matching
        self.switching_cost = float(switching_cost)
        self.priority_weight = float(priority_weight)
        self.deadline_bonus = float(deadline_bonus)
        self.lateness_weight = float(lateness_weight)
        self.plan_ahead = bool(plan_ahead)
        self.trip_weight = float(trip_weight)
        self.ahead_steps = _check_nonneg("ahead_steps", ahead_steps)
        if isinstance(next_k, (bool, np.bool_)) or not isinstance(next_k, (int, np.integer)) \
                or next_k < 1:
            raise ValueError(f"next_k must be an int >= 1, got {next_k!r}")
        self.next_weight = float(next_weight)
        self.next_k = int(next_k)
        self.max_wait = _check_nonneg("max_wait", max_wait, True)
        self.overdue_weight = _check_nonneg("overdue_weight", overdue_weight)
        self.last_cost: np.ndarray | None = None
        self._travel_cache: dict[int, tuple | None] = {}

    def reset(self, env: Any) -> None:
        """Bind to a lifelong env (forgetting the cached travel of every floor) and plan."""
        self._travel_cache = {}
        super().reset(env)

    def _travel(self, origin: np.ndarray, targets: np.ndarray, row_keys: np.ndarray,
                col_keys: np.ndarray) -> np.ndarray:
        """``self.distances.distance(origin, targets)`` (A, O), re-using the rows and columns of
        this floor's previous call whose key and point are unchanged (the same numbers: each
        entry depends on its two points only)."""
        cache = self._travel_cache.get(self._floor)
        self._travel_cache[self._floor] = None
        if cache is not None and cache[0] is not self.distances:  # another floor's table
            cache = None
        if cache is None or not len(cache[1]) or not len(cache[2]):
            out = self.distances.distance(origin, targets)
        else:
            _, old_rk, old_ck, old_origin, old_targets, old = cache
            ri, cj = _lookup(old_rk, row_keys), _lookup(old_ck, col_keys)
            fresh_r, fresh_c = ri < 0, cj < 0
            fresh_r[~fresh_r] = (old_origin[ri[~fresh_r]] != origin[~fresh_r]).any(axis=1)
            fresh_c[~fresh_c] = (old_targets[cj[~fresh_c]] != targets[~fresh_c]).any(axis=1)
            if fresh_r.mean() + fresh_c.mean() > 0.5:
                out = self.distances.distance(origin, targets)
            else:
                # A gather of the old matrix (none along an axis that kept its keys in
                # order), then the rows and columns whose point moved or is new.
                out = _sub(old, np.maximum(ri, 0), np.maximum(cj, 0))
                new_r, new_c = np.flatnonzero(fresh_r), np.flatnonzero(fresh_c)
                if len(new_r):
                    out[new_r] = self.distances.distance(origin[new_r], targets)
                if len(new_c):
                    out[:, new_c] = self.distances.distance(origin, targets[new_c])
        self._travel_cache[self._floor] = (self.distances, row_keys.copy(), col_keys.copy(),
                                           origin.copy(), targets.copy(), out)
        return out  # not to be written to: it is the next call's cache

    def _match(self, cost: np.ndarray, positions: np.ndarray,
               targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Matched (rows, cols) of the cost (A, O); AGVs at ``positions`` (A, 2), orders'
        pickups at ``targets`` (O, 2)."""
        rows, cols = self.matching(cost)
        return np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)

    def _solve(self, pos: np.ndarray, status: np.ndarray, current: np.ndarray,
               order_status: np.ndarray, pickup: np.ndarray, order_id: np.ndarray,
               priority: np.ndarray, *, dropoff: np.ndarray | None = None,
               release: np.ndarray | None = None, deadline: np.ndarray | None = None,
               now: int = 0, service_left: np.ndarray | None = None,
               next_order: np.ndarray | None = None,
               returned: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        n = len(pos)
        speed = self.speed
        plan = np.where(status == _LOADED, -1, current).astype(np.int64)
        nxt = np.full(n, -1, dtype=np.int64)
        held = np.full(n, -1, dtype=np.int64) if next_order is None else next_order
        loaded = (status == _LOADED) & (current >= 0) & (dropoff is not None) & self.plan_ahead
        if loaded.any() and math.isfinite(self.ahead_steps):
            # Only loaded AGVs that will be free within ahead_steps hold a next order.
            li = np.flatnonzero(loaded)
            left = self.distances.pairwise(pos[li], dropoff[current[li]]) / speed
            if service_left is not None:
                left = left + service_left[li]
            loaded[li[left > self.ahead_steps]] = False
        agents = np.flatnonzero((status == _IDLE) | (status == _TO_PICKUP) | loaded)
        orders = np.flatnonzero((order_status == _OPEN) | (order_status == _ASSIGNED))
        if not len(agents) or not len(orders):
            self.last_cost = np.zeros((len(agents), len(orders)))
            return plan, nxt
        origin = pos[agents].copy()
        lag = np.zeros(len(agents)) if service_left is None else \
            service_left[agents].astype(np.float64)
        is_loaded = loaded[agents]
        if is_loaded.any():
            carried = current[agents[is_loaded]]
            drop = dropoff[carried]
            remaining = self.distances.pairwise(origin[is_loaded], drop)
            lag[is_loaded] += remaining / speed + self.service_steps
            origin[is_loaded] = drop
        # (A, O) travel, then cost; rows and columns whose point did not move since the last
        # plan of this floor are copied from it, only the others gathered from the table.
        travel = self._travel(origin, pickup[orders], agents, order_id[orders])
        # The cost is the travel plus a column vector and a row vector (two passes over the
        # matrix), then a few sparse terms: the matrix is the re-plan's main memory cost.
        column = np.full(len(orders), self.switching_cost)  # every pair but the kept ones
        if self.trip_weight and dropoff is not None:
            column += self.trip_weight * self.distances.pairwise(pickup[orders],
                                                                 dropoff[orders])
        if self.next_weight and dropoff is not None:
            column += self.next_weight * next_empty(self.distances, dropoff[orders],
                                                    pickup[orders], self.next_k)
        if self.priority_weight:
            column -= self.priority_weight * priority[orders]
        if math.isfinite(self.max_wait) and release is not None:
            age = now - release[orders]
            over = age >= self.max_wait
            column[over] -= _OVERDUE_BONUS + np.minimum(
                self.overdue_weight * (age[over] - self.max_wait), _OVERDUE_CAP)
        late = None
        if deadline is not None and (deadline[orders] >= 0).any():
            due = np.flatnonzero(deadline[orders] >= 0)
            sel = orders[due]
            trip = np.zeros(len(due)) if dropoff is None else \
                self.distances.pairwise(pickup[sel], dropoff[sel]) / speed
            latest = deadline[sel] - now - trip - 2 * self.service_steps
            eta = travel[:, due] / speed + lag[:, None]  # (A, D), D the orders with deadline
            if self.lateness_weight:
                late = self.lateness_weight * speed * lateness(eta, latest)
            if self.deadline_bonus:
                column[due] -= self.deadline_bonus * at_risk(eta, latest,
                                                             self.deadline_horizon)
        cost = np.add(travel, column[None, :])
        cost += (speed * lag)[:, None]
        if late is not None:
            cost[:, due] += late
        if returned is not None and returned[orders].any():
            # Taken from a broken AGV: first to the AGVs free now (ahead of any travel).
            back = np.flatnonzero(returned[orders])
            free_rows = np.flatnonzero(~is_loaded)
            cost[np.ix_(free_rows, back)] -= _RETURNED_BONUS
        mine = np.where(plan[agents] >= 0, plan[agents], held[agents])
        mine = np.where(is_loaded, held[agents], mine)
        col_of = np.full(len(order_status), -1, dtype=np.int64)
        col_of[orders] = np.arange(len(orders))
        kept = np.flatnonzero((mine >= 0) & (col_of[np.maximum(mine, 0)] >= 0))
        cost[kept, col_of[mine[kept]]] -= self.switching_cost
        np.fmin(cost, _BIG, out=cost)  # unreachable (inf) and NaN pairs: _BIG
        self.last_cost = cost
        self._keys = (agents, order_id[orders])  # stable row / column identities
        rows, cols = self._match(cost, pos[agents], pickup[orders])
        ok = cost[rows, cols] < _BIG / 2
        rows, cols = rows[ok], cols[ok]
        plan[agents[~is_loaded]] = -1
        now_rows = ~is_loaded[rows]
        plan[agents[rows[now_rows]]] = orders[cols[now_rows]]
        nxt[agents[rows[~now_rows]]] = orders[cols[~now_rows]]
        return plan, nxt


class HungarianDispatcher(MatchingDispatcher):
    """Min-sum over the AGVs and the orders not yet picked up, on the costs of
    :class:`MatchingDispatcher`: loaded AGVs counted from where and when they will be free,
    priorities, deadlines, a switching cost.

    The matching is :class:`allocator.lap.IncrementalLAP`, one per floor: each re-plan starts
    from the previous optimum and its dual potentials (rows keyed by AGV, columns by order
    id), so an event that changes a few rows or columns costs a few shortest augmenting paths
    instead of a full solve; the result is an optimum of the same cost matrix, as
    :func:`scipy.optimize.linear_sum_assignment` would give (the same total cost; among tied
    optima it may pick another).

    Parameters
    ----------
    switching_cost, priority_weight, driver
        As :class:`MatchingDispatcher`.
    max_wait, overdue_weight : float
        As :class:`MatchingDispatcher`, but on by default: :data:`HUNGARIAN_MAX_WAIT` (150
        steps) and :data:`HUNGARIAN_OVERDUE_WEIGHT` (1.0); ``max_wait=math.inf`` gives the
        plain min-sum plan, which can starve orders at saturation.
    incremental : bool
        Warm-start each re-plan from the previous one (default True; used from 40,000 cost
        entries, e.g. 200 x 200: below, scipy from scratch is faster); False solves every
        re-plan from scratch with :func:`scipy.optimize.linear_sum_assignment`.
    **options
        The keyword options of :class:`MatchingDispatcher`.

    Attributes
    ----------
    lap : dict of int to IncrementalLAP
        The solver state per floor (key -1: direct :meth:`plan` calls).
    """

    def __init__(self, switching_cost: float = 0.5, priority_weight: float = 2.0,
                 driver: WaypointDriver | None = None, *, incremental: bool = True,
                 max_wait: float = HUNGARIAN_MAX_WAIT,
                 overdue_weight: float = HUNGARIAN_OVERDUE_WEIGHT, **options: Any) -> None:
        super().__init__(linear_sum_assignment, switching_cost, priority_weight, driver,
                         max_wait=max_wait, overdue_weight=overdue_weight, **options)
        if not isinstance(incremental, (bool, np.bool_)):
            raise ValueError(f"incremental must be True or False, got {incremental!r}")
        self.incremental = bool(incremental)
        self.lap: dict[int, IncrementalLAP] = {}

    def reset(self, env: Any) -> None:
        """Bind to a lifelong env (forgetting every floor's solver state) and plan."""
        self.lap = {}
        super().reset(env)

    def _match(self, cost: np.ndarray, positions: np.ndarray,
               targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self.incremental or self.matching is not linear_sum_assignment \
                or cost.size < _INCREMENTAL_MIN_SIZE:
            self.lap.pop(self._floor, None)  # a later large plan starts cold
            return super()._match(cost, positions, targets)
        lap = self.lap.get(self._floor)
        if lap is None:
            lap = self.lap[self._floor] = IncrementalLAP()
        rows, cols = self._keys
        return lap.solve(cost, rows, cols, copy=False)  # the cost is made anew every plan


class AuctionDispatcher(MatchingDispatcher):
    """The costs of :class:`MatchingDispatcher`, matched by a decentralized epsilon-auction
    (:func:`allocator.auction.auction`) over the AGVs' current communication graph.

    What an AGV knows: the warehouse system announces every order to the AGV nearest its
    pickup (straight-line distance; a terminal at the pickup calls the nearest vehicle), which
    floods it through its connected component of the graph (AGVs at most ``comm_range`` apart,
    broken ones left out). So every order is heard by exactly one component, and only that
    component's AGVs bid for it; conflicts inside a component are resolved by the auction's
    messages alone (each AGV's prices and holders to its neighbours). Each AGV's costs are its
    own (its travel and lag); priorities and deadlines travel with the announcement.

    Messages are counted: :attr:`last_messages` (the last re-plan), :attr:`messages` (all),
    :attr:`replan_messages` (one entry per re-planned floor), and :attr:`last_rounds`.

    Parameters
    ----------
    comm_range : float
        Radio range in world units, > 0 (``inf``: every AGV hears every other).
    eps : float, optional
        Bid increment (default :func:`allocator.auction.default_eps` of the benefits).
    max_rounds : int
        Round limit per component and re-plan.
    **options
        Those of :class:`MatchingDispatcher` (``switching_cost``, ``priority_weight``, ...).
    """

    def __init__(self, comm_range: float = math.inf, eps: float | None = None,
                 max_rounds: int = 20_000, **options: Any) -> None:
        super().__init__(linear_sum_assignment, **options)
        self.comm_range = check_comm_range(comm_range)
        if eps is not None:
            _check_nonneg("eps", eps, positive=True)
        if isinstance(max_rounds, bool) or not isinstance(max_rounds, (int, np.integer)) \
                or max_rounds < 1:
            raise ValueError(f"max_rounds must be an int >= 1, got {max_rounds!r}")
        self.eps = eps
        self.max_rounds = int(max_rounds)
        self.messages = 0
        self.last_messages = 0
        self.last_rounds = 0
        self.replan_messages: list[int] = []

    def _match(self, cost: np.ndarray, positions: np.ndarray,
               targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        benefit = -cost
        bad = cost >= _BIG / 2  # unreachable pairs: below every reachable one (then dropped)
        if bad.any():
            good = benefit[~bad]
            low = float(good.min() - (good.max() - good.min()) - 1.0) if good.size else -1.0
            benefit = np.where(bad, low, benefit)
        out = component_auction(benefit, positions, targets, self.comm_range, eps=self.eps,
                                max_rounds=self.max_rounds)
        self.last_messages = out.messages
        self.last_rounds = out.rounds
        self.messages += out.messages
        self.replan_messages.append(out.messages)
        rows = np.flatnonzero(out.task_of_agent >= 0)
        return rows, out.task_of_agent[rows]
