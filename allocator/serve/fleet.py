"""The fleet service's state and rules: AGVs, orders, events, and the dispatch plan.

Everything here runs on the service's event loop (one thread), apart from
:meth:`Fleet.compute_plan`, which works on a snapshot and may run in a worker thread. A change
is checked against the current state, written to the :class:`~allocator.serve.store.Store`
in one committed transaction, and only then applied in memory; so what a client was told was
accepted is on disk, and memory never holds what the disk does not.

Order life: ``open`` -> (``assigned`` by the plan, may change until pickup) -> ``loaded`` (an
AGV reported ``picked_up``) -> ``delivered`` (it reported ``delivered``). ``withdrawn`` by the
client while not yet picked up. ``assigned`` is not stored: the plan is rebuilt from the open
orders after a restart.

AGV status as reported: ``idle``, ``busy``, ``broken``, ``charging``. For the dispatcher an
AGV is free (idle and without an order), on its way to a pickup, loaded, or unavailable
(broken, charging, or busy with work the service did not give it).
"""

from __future__ import annotations

import json
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from allocator.serve.store import Store

__all__ = ["Fleet", "Conflict", "NotFound", "Invalid", "AGENT_STATUSES", "ORDER_STATUSES",
           "EVENT_TYPES", "compute_paths"]

AGENT_STATUSES = ("idle", "busy", "broken", "charging")
ORDER_STATUSES = ("open", "assigned", "loaded", "delivered", "withdrawn")
EVENT_TYPES = ("picked_up", "delivered", "fault", "repaired")
_ACTIVE = ("open", "assigned", "loaded")
# The dispatcher's codes (allocator.dispatch): AGVs 0 free, 1 to pickup, 2 loaded, 3 out;
# orders 1 open, 2 assigned, 3 loaded.
_FREE, _TO_PICKUP, _LOADED, _OUT = 0, 1, 2, 3
_ORDER_CODE = {"open": 1, "assigned": 2, "loaded": 3}


class Conflict(Exception):
    """A request that contradicts the state (HTTP 409)."""


class NotFound(Exception):
    """An unknown AGV or order (HTTP 404)."""


class Invalid(Exception):
    """A value the floor refuses (HTTP 422), naming the field (``loc``)."""

    def __init__(self, loc: tuple[Any, ...], msg: str) -> None:
        super().__init__(msg)
        self.loc = loc
        self.msg = msg


@dataclass
class Agent:
    id: str
    x: float
    y: float
    status: str
    updated: float
    order: str | None = None  # assigned (to pickup) or loaded order
    loaded: bool = False
    path: list[list[float]] = field(default_factory=list)


@dataclass
class Order:
    id: str
    seq: int
    body: str
    pickup: tuple[float, float]
    dropoff: tuple[float, float]
    priority: int
    deadline: float | None
    status: str
    created: float
    agent: str | None = None
    picked_up: float | None = None
    delivered: float | None = None
    withdrawn: float | None = None

    def public(self) -> dict[str, Any]:
        return {"id": self.id, "status": self.status, "pickup": list(self.pickup),
                "dropoff": list(self.dropoff), "priority": self.priority,
                "deadline": self.deadline, "agent": self.agent, "created": self.created,
                "picked_up": self.picked_up, "delivered": self.delivered,
                "withdrawn": self.withdrawn}


def _order_from_row(row: dict[str, Any]) -> Order:
    return Order(id=row["id"], seq=int(row["seq"]), body=row["body"],
                 pickup=(row["pickup_x"], row["pickup_y"]),
                 dropoff=(row["dropoff_x"], row["dropoff_y"]), priority=int(row["priority"]),
                 deadline=row["deadline"], status=row["status"], created=row["created"],
                 agent=row["agent"], picked_up=row["picked_up"], delivered=row["delivered"],
                 withdrawn=row["withdrawn"])


def canonical_body(pickup: tuple[float, float], dropoff: tuple[float, float], priority: int,
                   deadline: float | None) -> str:
    """The canonical JSON of an order's content (what makes two posts of an id the same)."""
    return json.dumps({"pickup": [float(v) for v in pickup],
                       "dropoff": [float(v) for v in dropoff],
                       "priority": int(priority),
                       "deadline": None if deadline is None else float(deadline)},
                      sort_keys=True, separators=(",", ":"))


def compute_paths(distances: Any, start: np.ndarray, goal: np.ndarray,
                  max_corners: int = 24) -> list[np.ndarray]:
    """Corner waypoints from each ``start[k]`` to ``goal[k]``, batched over K.

    Repeats :meth:`allocator.distances.FloorDistances.next_waypoint` from the last corner
    found, for every path at once.

    Parameters
    ----------
    distances : allocator.distances.FloorDistances
    start, goal : np.ndarray, shape (K, 2)
    max_corners : int
        Longest path kept; a longer one ends at its last corner found.

    Returns
    -------
    list of np.ndarray, each of shape (P_k, 2)
        ``path[0] == start[k]``; ``path[-1] == goal[k]`` when the goal was reached; just
        ``[start[k]]`` when the goal cannot be reached.
    """
    K = len(start)
    if K == 0:
        return []
    pts = [start.astype(np.float64)]
    cur = pts[0]
    active = np.ones(K, dtype=bool)
    for _ in range(max_corners):
        k = np.flatnonzero(active)
        if not k.size:
            break
        nxt = cur.copy()
        nxt[k] = distances.next_waypoint(cur[k], goal[k])
        moved = np.linalg.norm(nxt - cur, axis=1) > 1e-9
        active &= moved
        active &= np.linalg.norm(nxt - goal, axis=1) > 1e-9
        pts.append(nxt)
        cur = nxt
    stack = np.stack(pts, axis=1)  # (K, S, 2)
    out = []
    for i in range(K):
        p = stack[i]
        keep = np.ones(len(p), dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9
        out.append(p[keep])
    return out


@dataclass
class PlanSnapshot:
    """What the dispatcher needs, copied off the live state."""

    agent_ids: list[str]
    pos: np.ndarray
    status: np.ndarray
    current: np.ndarray
    order_ids: list[str]
    order_status: np.ndarray
    pickup: np.ndarray
    dropoff: np.ndarray
    order_seq: np.ndarray
    priority: np.ndarray


class Fleet:
    """The live state of one floor's fleet, its durable store, and its plan.

    Parameters
    ----------
    world : sim.World
        The floor. Reported positions must lie inside its bounds; pickups and drop-offs must
        be free points reachable from each other.
    dispatcher : allocator.dispatch.LifelongDispatcher
        Its ``plan(...)`` (keyword arguments) makes the plan; its ``distances`` are set here.
    store : Store
    distances : allocator.distances.FloorDistances
    clock : callable, optional
        Wall-clock seconds (default :func:`time.time`).
    """

    def __init__(self, world: Any, dispatcher: Any, store: Store, distances: Any,
                 clock: Callable[[], float] = time.time) -> None:
        self.world = world
        self.dispatcher = dispatcher
        self.distances = distances
        dispatcher.distances = distances
        self.store = store
        self.clock = clock
        self.agents: dict[str, Agent] = {}
        self.orders: dict[str, Order] = {}  # active orders only (open, assigned, loaded)
        self.epoch = 0  # bumped by every change the plan depends on, positions aside
        self.moved = 0  # bumped by position reports
        self.plan_version = 0
        self.plan_time = 0.0
        self.listeners: list[Callable[[str, dict[str, Any]], None]] = []
        self.waits: deque[float] = deque(maxlen=2000)
        self.leads: deque[float] = deque(maxlen=2000)
        self.deliveries: deque[float] = deque(maxlen=100_000)
        self._load()

    # ------------------------------------------------------------------ start-up
    def _load(self) -> None:
        st = self.store
        for row in st.agents():
            self.agents[row["id"]] = Agent(id=row["id"], x=row["x"], y=row["y"],
                                           status=row["status"], updated=row["updated"])
        for row in st.orders(("open", "loaded")):
            o = _order_from_row(row)
            self.orders[o.id] = o
            if o.status == "loaded" and o.agent in self.agents:
                a = self.agents[o.agent]
                a.order, a.loaded = o.id, True
            elif o.status == "loaded":  # its AGV's row is gone: keep the order, no AGV state
                pass
        self.seq = st.max_seq()
        counts = st.counts()
        self.accepted = sum(counts.values())
        self.delivered_count = counts.get("delivered", 0)
        self.withdrawn_count = counts.get("withdrawn", 0)
        now = self.clock()
        for row in st.orders(("delivered",))[-2000:]:
            if row["picked_up"] is not None:
                self.waits.append(row["picked_up"] - row["created"])
            self.leads.append(row["delivered"] - row["created"])
            if row["delivered"] > now - 3600:
                self.deliveries.append(row["delivered"])

    # ------------------------------------------------------------------ notifications
    def _emit(self, kind: str, data: dict[str, Any]) -> None:
        for fn in list(self.listeners):
            fn(kind, data)

    # ------------------------------------------------------------------ checks
    def _check_point(self, point: tuple[float, float], loc: tuple[Any, ...],
                     free: bool) -> None:
        p = np.asarray(point, dtype=np.float64)
        if not np.all(np.isfinite(p)):
            raise Invalid(loc, "must hold finite numbers")
        w = self.world
        if float(w.wall_distance(p)) < 0:
            raise Invalid(loc, f"{list(point)} lies outside the floor bounds {list(w.bounds)}")
        if free and not bool(w.is_free(p)):
            raise Invalid(loc, f"{list(point)} is not a free point for an AGV (a shelf or a "
                          "wall is within the AGV radius)")

    # ------------------------------------------------------------------ orders
    def get_order(self, order_id: str) -> dict[str, Any]:
        o = self.orders.get(order_id)
        if o is not None:
            return o.public()
        row = self.store.order(order_id)
        if row is None:
            raise NotFound(f"no order {order_id!r}")
        return _order_from_row(row).public()

    def add_orders(self, items: list[dict[str, Any]]) -> list[tuple[dict[str, Any], bool]]:
        """Accept orders (all or none): ``[(order, created)]``; a replay is not created.

        Raises
        ------
        Invalid
            A pickup or drop-off off the floor, on a shelf, or not reachable.
        Conflict
            An id already used for a different order (or twice in the batch, differently).
        """
        now = self.clock()
        fresh: list[Order] = []
        results: list[tuple[str, Order | dict[str, Any], bool]] = []
        seen: dict[str, str] = {}
        seq = self.seq
        for k, it in enumerate(items):
            prefix: tuple[Any, ...] = ("body",) if not it.get("_batch") \
                else ("body", "orders", k)
            pickup, dropoff = tuple(it["pickup"]), tuple(it["dropoff"])
            body = canonical_body(pickup, dropoff, it.get("priority", 0), it.get("deadline"))
            oid = it["id"]
            if oid in seen:
                if seen[oid] != body:
                    raise Conflict(f"order {oid!r} appears twice in the batch with different "
                                   "content")
                continue
            seen[oid] = body
            old = self.orders.get(oid)
            old_row = None if old is not None else self.store.order(oid)
            if old is not None or old_row is not None:
                old_body = old.body if old is not None else old_row["body"]
                if old_body != body:
                    raise Conflict(f"order {oid!r} exists with different content; an id "
                                   "names one order for good")
                results.append((oid, old if old is not None else old_row, False))
                continue
            self._check_point(pickup, (*prefix, "pickup"), free=True)
            self._check_point(dropoff, (*prefix, "dropoff"), free=True)
            d = self.distances.distance(np.asarray([pickup]), np.asarray([dropoff]))[0, 0]
            if not np.isfinite(d):
                raise Invalid((*prefix, "dropoff"), "cannot be reached from the pickup")
            seq += 1
            o = Order(id=oid, seq=seq, body=body, pickup=(float(pickup[0]), float(pickup[1])),
                      dropoff=(float(dropoff[0]), float(dropoff[1])),
                      priority=int(it.get("priority", 0)), deadline=it.get("deadline"),
                      status="open", created=now)
            fresh.append(o)
            results.append((oid, o, True))
        if fresh:
            stmts = []
            for o in fresh:
                row = o.public() | {"seq": o.seq, "body": o.body, "pickup_x": o.pickup[0],
                                    "pickup_y": o.pickup[1], "dropoff_x": o.dropoff[0],
                                    "dropoff_y": o.dropoff[1]}
                stmts.append(Store.insert_order(row))
                stmts.append(Store.insert_event(now, None, "accepted", o.id))
            self.store.write(stmts)
            self.seq = seq
            for o in fresh:
                self.orders[o.id] = o
            self.accepted += len(fresh)
            self.epoch += 1
            self._emit("orders", {"accepted": [o.id for o in fresh]})
        out = []
        for _, o, created in results:
            out.append(((o.public() if isinstance(o, Order) else
                         _order_from_row(o).public()), created))
        return out

    def withdraw(self, order_id: str) -> dict[str, Any]:
        """Withdraw an order not yet picked up (a repeat answers the withdrawn order).

        Raises
        ------
        NotFound
        Conflict
            The order is loaded or delivered.
        """
        o = self.orders.get(order_id)
        if o is None:
            row = self.store.order(order_id)
            if row is None:
                raise NotFound(f"no order {order_id!r}")
            if row["status"] == "withdrawn":
                return _order_from_row(row).public()
            raise Conflict(f"order {order_id!r} is {row['status']}: it can no longer be "
                           "withdrawn")
        if o.status == "loaded":
            raise Conflict(f"order {order_id!r} was picked up by {o.agent!r}: an order can be "
                           "withdrawn only until pickup")
        now = self.clock()
        self.store.write([Store.update_order(order_id, status="withdrawn", withdrawn=now,
                                             agent=None),
                          Store.insert_event(now, None, "withdrawn", order_id)])
        if o.agent is not None and o.agent in self.agents:
            a = self.agents[o.agent]
            if a.order == order_id:
                a.order, a.path = None, []
        o.status, o.withdrawn, o.agent = "withdrawn", now, None
        del self.orders[order_id]
        self.withdrawn_count += 1
        self.epoch += 1
        self._emit("orders", {"withdrawn": [order_id]})
        return o.public()

    # ------------------------------------------------------------------ AGVs
    def agent_public(self, a: Agent) -> dict[str, Any]:
        return {"id": a.id, "position": [a.x, a.y], "status": a.status, "order": a.order,
                "loaded": a.loaded, "updated": a.updated}

    def get_agent(self, agent_id: str) -> dict[str, Any]:
        a = self.agents.get(agent_id)
        if a is None:
            raise NotFound(f"no AGV {agent_id!r}")
        return self.agent_public(a)

    def put_agent(self, agent_id: str, position: tuple[float, float], status: str,
                  persist: bool = True) -> tuple[dict[str, Any], bool]:
        """Record an AGV's reported state; ``(agent, created)``.

        ``broken`` or ``charging`` while on the way to a pickup returns that order to the
        open pool; a loaded order stays with its AGV.
        """
        self._check_point(position, ("body", "position"), free=False)
        now = self.clock()
        a = self.agents.get(agent_id)
        created = a is None
        x, y = float(position[0]), float(position[1])
        changed = created or a.status != status
        if persist or changed:
            stmts = [Store.upsert_agent(agent_id, x, y, status, now)]
            if changed:
                stmts.append(Store.insert_event(now, agent_id, f"status:{status}", None))
            self.store.write(stmts)
        if created:
            a = Agent(id=agent_id, x=x, y=y, status=status, updated=now)
            self.agents[agent_id] = a
        else:
            a.x, a.y, a.updated = x, y, now
            a.status = status
        if changed:
            if status in ("broken", "charging"):
                self._drop_assignment(a)
            self.epoch += 1
        self.moved += 1
        return self.agent_public(a), created

    def _drop_assignment(self, a: Agent) -> None:
        if a.order is not None and not a.loaded:
            o = self.orders.get(a.order)
            if o is not None and o.status == "assigned" and o.agent == a.id:
                o.status, o.agent = "open", None
            a.order, a.path = None, []

    def event(self, agent_id: str, kind: str, order_id: str | None) -> dict[str, Any]:
        """Apply an AGV's event: ``picked_up``, ``delivered`` (with an order), ``fault``,
        ``repaired``.

        Raises
        ------
        NotFound
            An unknown AGV or order.
        Conflict
            An event the state does not allow (the message says why).
        Invalid
            ``order`` missing for picked_up / delivered.
        """
        a = self.agents.get(agent_id)
        if a is None:
            raise NotFound(f"no AGV {agent_id!r}; report its state first (PUT "
                           f"/v1/agents/{agent_id})")
        now = self.clock()
        if kind in ("picked_up", "delivered"):
            if order_id is None:
                raise Invalid(("body", "order"), f"a {kind} event needs the order's id")
            o = self.orders.get(order_id)
            if o is None:
                row = self.store.order(order_id)
                if row is None:
                    raise NotFound(f"no order {order_id!r}")
                raise Conflict(f"order {order_id!r} is {row['status']}")
        if kind == "picked_up":
            if a.status in ("broken", "charging"):
                raise Conflict(f"AGV {agent_id!r} is {a.status}: it cannot pick up")
            if a.loaded:
                raise Conflict(f"AGV {agent_id!r} already carries order {a.order!r}")
            if o.status == "loaded":
                raise Conflict(f"order {order_id!r} was already picked up by {o.agent!r}")
            self.store.write([Store.update_order(order_id, status="loaded", agent=agent_id,
                                                 picked_up=now),
                              Store.upsert_agent(agent_id, a.x, a.y, "busy", now),
                              Store.insert_event(now, agent_id, kind, order_id)])
            if o.agent is not None and o.agent != agent_id and o.agent in self.agents:
                other = self.agents[o.agent]
                if other.order == order_id:
                    other.order, other.path = None, []
            if a.order is not None and a.order != order_id:
                self._drop_assignment(a)
            o.status, o.agent, o.picked_up = "loaded", agent_id, now
            a.order, a.loaded, a.status, a.updated = order_id, True, "busy", now
            self.waits.append(now - o.created)
        elif kind == "delivered":
            if o.status != "loaded" or o.agent != agent_id:
                raise Conflict(f"order {order_id!r} is not loaded on AGV {agent_id!r} "
                               f"(it is {o.status}" + (f" on {o.agent!r})" if o.agent else ")"))
            status = "idle" if a.status == "busy" else a.status
            self.store.write([Store.update_order(order_id, status="delivered", delivered=now),
                              Store.upsert_agent(agent_id, a.x, a.y, status, now),
                              Store.insert_event(now, agent_id, kind, order_id)])
            o.status, o.delivered = "delivered", now
            del self.orders[order_id]
            a.order, a.loaded, a.status, a.path, a.updated = None, False, status, [], now
            self.delivered_count += 1
            self.leads.append(now - o.created)
            self.deliveries.append(now)
        elif kind == "fault":
            self.store.write([Store.upsert_agent(agent_id, a.x, a.y, "broken", now),
                              Store.insert_event(now, agent_id, kind, None)])
            a.status, a.updated = "broken", now
            self._drop_assignment(a)
        elif kind == "repaired":
            if a.status != "broken":
                raise Conflict(f"AGV {agent_id!r} is {a.status}, not broken")
            status = "busy" if a.loaded else "idle"
            self.store.write([Store.upsert_agent(agent_id, a.x, a.y, status, now),
                              Store.insert_event(now, agent_id, kind, None)])
            a.status, a.updated = status, now
        else:  # pragma: no cover - the API's schema allows only the four
            raise Invalid(("body", "type"), f"unknown event type {kind!r}")
        self.epoch += 1
        self._emit("event", {"agent": agent_id, "type": kind, "order": order_id})
        return self.agent_public(a)

    # ------------------------------------------------------------------ plan
    def _code(self, a: Agent) -> int:
        if a.status in ("broken", "charging"):
            return _OUT
        if a.loaded:
            return _LOADED
        if a.order is not None:
            return _TO_PICKUP
        return _FREE if a.status == "idle" else _OUT

    def snapshot(self) -> PlanSnapshot:
        """Copy what the dispatcher needs off the live state (event-loop side)."""
        agents = sorted(self.agents.values(), key=lambda a: a.id)
        orders = sorted(self.orders.values(), key=lambda o: o.seq)
        slot = {o.id: k for k, o in enumerate(orders)}
        N, Q = len(agents), len(orders)
        pos = np.array([[a.x, a.y] for a in agents], dtype=np.float64).reshape(N, 2)
        status = np.array([self._code(a) for a in agents], dtype=np.int64)
        current = np.array([slot.get(a.order, -1) if a.order is not None else -1
                            for a in agents], dtype=np.int64)
        return PlanSnapshot(
            agent_ids=[a.id for a in agents], pos=pos, status=status, current=current,
            order_ids=[o.id for o in orders],
            order_status=np.array([_ORDER_CODE[o.status] for o in orders], dtype=np.int64),
            pickup=np.array([o.pickup for o in orders], dtype=np.float64).reshape(Q, 2),
            dropoff=np.array([o.dropoff for o in orders], dtype=np.float64).reshape(Q, 2),
            order_seq=np.array([o.seq for o in orders], dtype=np.int64),
            priority=np.array([o.priority for o in orders], dtype=np.int64))

    def compute_plan(self, s: PlanSnapshot) -> tuple[np.ndarray, list[np.ndarray]]:
        """The dispatcher's plan (slot per AGV or -1) and every AGV's path (thread-safe:
        reads only the snapshot and the floor)."""
        N = len(s.agent_ids)
        plan = np.full(N, -1, dtype=np.int64)
        if N and len(s.order_ids):
            current = np.where(s.status == _LOADED, -1, s.current)
            plan = np.asarray(self.dispatcher.plan(
                pos=s.pos, status=s.status, current=current, order_status=s.order_status,
                pickup=s.pickup, order_id=s.order_seq, priority=s.priority), dtype=np.int64)
            loaded = s.status == _LOADED
            plan[loaded] = s.current[loaded]
            plan[s.status == _OUT] = -1
        has = plan >= 0
        goal = np.zeros((N, 2))
        slot = plan.clip(min=0)
        if len(s.order_ids):
            goal = np.where((s.status == _LOADED)[:, None], s.dropoff[slot], s.pickup[slot])
        paths: list[np.ndarray] = [np.zeros((0, 2))] * N
        idx = np.flatnonzero(has)
        if idx.size:
            for i, p in zip(idx, compute_paths(self.distances, s.pos[idx], goal[idx]),
                            strict=True):
                paths[i] = p
        return plan, paths

    def apply_plan(self, s: PlanSnapshot, plan: np.ndarray, paths: list[np.ndarray]) -> bool:
        """Apply a plan made from ``s`` where it is still valid; True if assignments changed.

        An AGV's new order is taken only if the AGV is still free or on its way to a pickup
        and the order still open or assigned (to an AGV this plan moves off it)."""
        changed = False
        want: dict[str, str | None] = {}
        for i, aid in enumerate(s.agent_ids):
            if s.status[i] in (_FREE, _TO_PICKUP):
                want[aid] = s.order_ids[plan[i]] if plan[i] >= 0 else None
        # Release first, so that an order can move from one AGV to another.
        for aid, oid in want.items():
            a = self.agents.get(aid)
            if a is None or a.loaded or self._code(a) not in (_FREE, _TO_PICKUP):
                continue
            if a.order != oid and a.order is not None:
                self._drop_assignment(a)
                changed = True
        for aid, oid in want.items():
            a = self.agents.get(aid)
            if oid is None or a is None or self._code(a) != _FREE:
                continue
            o = self.orders.get(oid)
            if o is None or o.status != "open":
                continue
            o.status, o.agent = "assigned", aid
            a.order = oid
            changed = True
        for i, aid in enumerate(s.agent_ids):
            a = self.agents.get(aid)
            if a is None:
                continue
            if a.order is not None and plan[i] >= 0 and s.order_ids[plan[i]] == a.order:
                a.path = paths[i].round(4).tolist()
            elif a.order is None:
                a.path = []
        self.plan_version += 1
        self.plan_time = self.clock()
        return changed

    def plan_view(self) -> dict[str, Any]:
        """The current plan: every AGV with its order, leg and path; the active orders;
        the service's figures."""
        agents = []
        for a in sorted(self.agents.values(), key=lambda a: a.id):
            leg = None if a.order is None else ("dropoff" if a.loaded else "pickup")
            agents.append({"id": a.id, "position": [a.x, a.y], "status": a.status,
                           "order": a.order, "leg": leg, "path": a.path})
        orders = [{"id": o.id, "status": o.status, "pickup": list(o.pickup),
                   "dropoff": list(o.dropoff), "priority": o.priority, "agent": o.agent}
                  for o in sorted(self.orders.values(), key=lambda o: o.seq)]
        return {"version": self.plan_version, "time": self.plan_time, "agents": agents,
                "orders": orders, "stats": self.stats()}

    def stats(self) -> dict[str, Any]:
        now = self.clock()
        while self.deliveries and self.deliveries[0] < now - 3600:
            self.deliveries.popleft()
        recent = sum(1 for t in self.deliveries if t >= now - 60)
        waits = np.asarray(self.waits, dtype=np.float64)
        leads = np.asarray(self.leads, dtype=np.float64)

        def q(v: np.ndarray, p: float) -> float | None:
            return None if not v.size else round(float(np.percentile(v, p)), 3)

        counts = {s: 0 for s in _ACTIVE}
        for o in self.orders.values():
            counts[o.status] += 1
        return {"accepted": self.accepted, "delivered": self.delivered_count,
                "withdrawn": self.withdrawn_count, **counts,
                "agents": len(self.agents),
                "throughput_per_min": recent,
                "wait_mean_s": None if not waits.size else round(float(waits.mean()), 3),
                "wait_p95_s": q(waits, 95),
                "lead_mean_s": None if not leads.size else round(float(leads.mean()), 3)}

    def floor_view(self) -> dict[str, Any]:
        """The floor for drawing: bounds, shelves, pickups, stations, AGV radius."""
        w = self.world

        def rows(v: Any) -> list[list[float]]:
            return np.asarray(v, dtype=np.float64).round(4).tolist()

        return {"bounds": [float(v) for v in w.bounds], "shelves": rows(w.obstacles),
                "pickups": rows(w.pickups), "stations": rows(w.stations),
                "agent_radius": float(w.agent_radius),
                "capture_radius": float(w.capture_radius)}


def finite(value: float) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)
