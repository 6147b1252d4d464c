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
           "EVENT_TYPES", "PathPlanner"]

AGENT_STATUSES = ("idle", "busy", "broken", "charging")
ORDER_STATUSES = ("open", "assigned", "loaded", "delivered", "withdrawn")
EVENT_TYPES = ("picked_up", "delivered", "fault", "repaired")
_ACTIVE = ("open", "assigned", "loaded")
# The dispatcher's codes (allocator.dispatch): AGVs 0 free, 1 to pickup, 2 loaded, 3 out;
# orders 1 open, 2 assigned, 3 loaded.
_FREE, _TO_PICKUP, _LOADED, _OUT = 0, 1, 2, 3
_ORDER_CODE = {"open": 1, "assigned": 2, "loaded": 3}
AGV_SPEED = 1.0
"""AGV speed (world units per second) the dispatcher assumes when it weighs an order's
deadline (wall-clock seconds) against the trip to its pickup."""


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


class Reachability:
    """Which free points of a floor are connected: the free cells of a raster (an AGV disc
    fits at the cell's centre) labelled by 8-connectivity, built once (cheap: no distance
    fields), so that checking an order's trip never runs a shortest-path search on the
    event loop.

    Parameters
    ----------
    world : sim.World
    resolution : float
        Cell side (the planner's grid resolution).
    """

    def __init__(self, world: Any, resolution: float) -> None:
        from scipy import ndimage

        xmin, ymin, xmax, ymax = world.bounds
        nx = max(1, int(np.ceil((xmax - xmin) / resolution - 1e-9)))
        ny = max(1, int(np.ceil((ymax - ymin) / resolution - 1e-9)))
        self.origin = (xmin, ymin)
        self.d = ((xmax - xmin) / nx, (ymax - ymin) / ny)
        xs = xmin + (np.arange(nx) + 0.5) * self.d[0]
        ys = ymin + (np.arange(ny) + 0.5) * self.d[1]
        grid = np.stack(np.meshgrid(xs, ys), axis=-1)  # (ny, nx, 2)
        free = world.is_free(grid.reshape(-1, 2)).reshape(ny, nx)
        self.labels, _ = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
        # Every cell's nearest free cell, for points whose own cell is not free.
        _, (ii, jj) = ndimage.distance_transform_edt(~free, return_indices=True)
        self.nearest = self.labels[ii, jj]

    def label(self, p: tuple[float, float]) -> int:
        j = int(np.clip((p[0] - self.origin[0]) // self.d[0], 0, self.labels.shape[1] - 1))
        i = int(np.clip((p[1] - self.origin[1]) // self.d[1], 0, self.labels.shape[0] - 1))
        return int(self.nearest[i, j])

    def connected(self, a: tuple[float, float], b: tuple[float, float]) -> bool:
        """Whether free points ``a`` and ``b`` lie in one connected part of the floor."""
        la = self.label(a)
        return la > 0 and la == self.label(b)


class PathPlanner:
    """Path waypoints for the plan, from :meth:`FloorDistances.path`, cached between the
    floor's fixed points.

    An AGV's trips run mostly between fixed points (it stands at a station after a delivery,
    at a pickup after a pickup), so a path starts from the nearest pickup or station when the
    AGV is within ``snap`` of it, and such paths are kept in a bounded cache: on a floor with
    P pickups and S stations at most 2 P S of them are ever computed. Other paths are
    computed within a time budget per plan; an AGV whose path is not computed yet keeps its
    last path for the same leg, or gets none (an empty list) until a later plan.

    Parameters
    ----------
    distances : allocator.distances.FloorDistances
    budget : float
        Seconds of path computation per plan (default 0.05).
    cache_size : int
        Paths kept (default 20000).
    """

    def __init__(self, distances: Any, budget: float = 0.05, cache_size: int = 20_000) -> None:
        from collections import OrderedDict

        self.distances = distances
        w = distances.world
        self.fixed = np.concatenate([np.asarray(w.pickups, dtype=np.float64).reshape(-1, 2),
                                     np.asarray(w.stations, dtype=np.float64).reshape(-1, 2)])
        self.snap = 2.0 * float(w.capture_radius)
        self.budget = float(budget)
        self.cache_size = int(cache_size)
        self.cache: OrderedDict[tuple, np.ndarray | None] = OrderedDict()
        self.computed = 0

    def _start(self, pos: np.ndarray) -> tuple[np.ndarray, bool]:
        """The fixed point within ``snap`` of each position (or the position itself)."""
        if not len(self.fixed) or not len(pos):
            return pos.copy(), np.zeros(len(pos), dtype=bool)
        d = np.linalg.norm(pos[:, None, :] - self.fixed[None, :, :], axis=-1)
        k = d.argmin(axis=1)
        near = d[np.arange(len(pos)), k] <= self.snap
        return np.where(near[:, None], self.fixed[k], pos), near

    def paths(self, pos: np.ndarray, goal: np.ndarray,
              previous: list[list[list[float]] | None]) -> list[list[list[float]]]:
        """Waypoints from each ``pos[k]`` to ``goal[k]`` (``previous[k]``: the AGV's last path
        for the same leg, or None).

        Returns
        -------
        list of lists of [x, y]
            ``path[0]`` the AGV's position and ``path[-1]`` its goal where computed; the
            previous path where not computed in time; ``[]`` for none yet or unreachable.
        """
        import time as _time

        start, fixed = self._start(pos)
        out: list[list[list[float]]] = []
        t_end = _time.perf_counter() + self.budget
        for k in range(len(pos)):
            key = (round(float(start[k, 0]), 3), round(float(start[k, 1]), 3),
                   round(float(goal[k, 0]), 3), round(float(goal[k, 1]), 3))
            path = self.cache.get(key, False) if fixed[k] else False
            if path is False:
                if _time.perf_counter() > t_end:
                    out.append(previous[k] if previous[k] is not None else [])
                    continue
                path = self.distances.path(start[k], goal[k])
                self.computed += 1
                if fixed[k]:
                    self.cache[key] = path
                    if len(self.cache) > self.cache_size:
                        self.cache.popitem(last=False)
            elif fixed[k]:
                self.cache.move_to_end(key)
            if path is None:
                out.append([])
                continue
            pts = np.asarray(path, dtype=np.float64)
            if fixed[k]:
                pts = np.concatenate([pos[k][None], pts[1:]]) if \
                    np.linalg.norm(pts[0] - pos[k]) > 1e-9 else pts
            out.append(pts.round(4).tolist())
        return out


class Planner:
    """The dispatcher's plan and the AGVs' paths for a :class:`PlanSnapshot`.

    Runs in the service's process or, so that planning never holds the event loop's
    interpreter lock, in a worker process (:func:`start_worker`, :func:`plan_in_worker`).
    """

    def __init__(self, dispatcher: Any, distances: Any, agv_speed: float = AGV_SPEED) -> None:
        self.dispatcher = dispatcher
        dispatcher.distances = distances
        # the dispatcher's time unit is then the second: its trip estimates (distance / speed)
        # are compared with the orders' deadlines in seconds from now
        dispatcher.speed = float(agv_speed)
        self.distances = distances
        self.paths = PathPlanner(distances)

    def compute(self, s: PlanSnapshot) -> tuple[np.ndarray, list[list]]:
        """The plan (an order slot per AGV, or -1) and every AGV's path."""
        N = len(s.agent_ids)
        plan = np.full(N, -1, dtype=np.int64)
        if N and len(s.order_ids):
            current = np.where(s.status == _LOADED, -1, s.current)
            due = None
            if s.deadline is not None and len(s.deadline) == len(s.order_ids):
                due = np.where(np.isnan(s.deadline), -1,
                               np.floor(np.clip(np.nan_to_num(s.deadline), 0.0, 1e12)))
                due = due.astype(np.int64)
            plan = np.asarray(self.dispatcher.plan(
                pos=s.pos, status=s.status, current=current, order_status=s.order_status,
                pickup=s.pickup, order_id=s.order_seq, priority=s.priority, deadline=due,
                now=0), dtype=np.int64)
            loaded = s.status == _LOADED
            plan[loaded] = s.current[loaded]
            plan[s.status == _OUT] = -1
        paths: list[list] = [[] for _ in range(N)]
        idx = np.flatnonzero(plan >= 0)
        if idx.size:
            slot = plan[idx]
            loaded = s.status[idx] == _LOADED
            goal = np.where(loaded[:, None], s.dropoff[slot], s.pickup[slot])
            previous = []
            for i, ld in zip(idx, loaded, strict=True):
                order, was_loaded, path = s.previous[s.agent_ids[i]]
                same = order == s.order_ids[plan[i]] and was_loaded == bool(ld) and path
                previous.append(path if same else None)
            for i, p in zip(idx, self.paths.paths(s.pos[idx], goal, previous), strict=True):
                paths[i] = p
        return plan, paths


_WORKER: Planner | None = None


def _worker_init(floor: str, method: str, parent: int) -> None:
    global _WORKER
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # The service may have died while this process was still importing: then its parent is
    # already another process, and it must not wait for work that will never come.
    _exit_with_parent(parent)
    from allocator.distances import FloorDistances
    from allocator.serve.floor import load_world, make_dispatcher

    world = load_world(floor)
    _WORKER = Planner(make_dispatcher(method), FloorDistances(world))


def _exit_with_parent(parent: int) -> None:
    """End this worker when the service dies, even by SIGKILL (no clean-up runs there)."""
    import os
    import threading

    try:  # Linux: a signal at the parent's death
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass

    if os.getppid() != parent:
        os._exit(0)

    def watch() -> None:
        import time as _time

        while os.getppid() == parent:
            _time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, daemon=True, name="agv-serve-parent-watch").start()


def _worker_ping() -> bool:
    return _WORKER is not None


def plan_in_worker(s: PlanSnapshot) -> tuple[np.ndarray, list[list]]:
    """:meth:`Planner.compute` in the worker process."""
    if _WORKER is None:  # pragma: no cover - the initializer always runs first
        raise RuntimeError("the planning worker was not initialised")
    return _WORKER.compute(s)


def start_worker(floor: str, method: str) -> tuple[Any, Any]:
    """A one-process pool (spawned, not forked) holding the floor and the dispatcher, and a
    future that is done when it is ready (it builds the floor's distances meanwhile)."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_worker_init,
                               initargs=(floor, method, os.getpid()))
    return pool, pool.submit(_worker_ping)


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
    previous: dict[str, tuple[str | None, bool, list]]
    deadline: np.ndarray | None = None
    """Seconds from the snapshot to each order's deadline (NaN: none; negative: late)."""


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
        self.planner = Planner(dispatcher, distances)
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
        self._trips_ok: set[tuple[float, float, float, float]] = set()
        self.reach = Reachability(world, float(getattr(distances, "resolution",
                                                       world.agent_radius / 2)))
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

    def _check_trip(self, pickup: tuple, dropoff: tuple, prefix: tuple[Any, ...]) -> None:
        """Pickup and drop-off free, and the drop-off reachable from the pickup (pairs that
        passed are remembered: most orders run between the floor's fixed points)."""
        key = (float(pickup[0]), float(pickup[1]), float(dropoff[0]), float(dropoff[1]))
        if key in self._trips_ok:
            return
        self._check_point(pickup, (*prefix, "pickup"), free=True)
        self._check_point(dropoff, (*prefix, "dropoff"), free=True)
        if not self.reach.connected(pickup, dropoff):
            raise Invalid((*prefix, "dropoff"), "cannot be reached from the pickup")
        if len(self._trips_ok) >= 100_000:
            self._trips_ok.clear()
        self._trips_ok.add(key)

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
            self._check_trip(pickup, dropoff, prefix)
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
        now = self.clock()
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
            priority=np.array([o.priority for o in orders], dtype=np.int64),
            previous={a.id: (a.order, a.loaded, a.path) for a in agents},
            deadline=np.array([np.nan if o.deadline is None else o.deadline - now
                               for o in orders], dtype=np.float64).reshape(Q))

    def compute_plan(self, s: PlanSnapshot) -> tuple[np.ndarray, list[list]]:
        """The plan of a snapshot, in this process (see :class:`Planner`)."""
        return self.planner.compute(s)

    def apply_plan(self, s: PlanSnapshot, plan: np.ndarray, paths: list[list]) -> bool:
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
            # Free now, or released just above (it may report busy while on its way).
            if oid is None or a is None or a.loaded or a.order is not None \
                    or a.status in ("broken", "charging"):
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
                a.path = paths[i]
            elif a.order is None:
                a.path = []
        self.plan_version += 1
        self.plan_time = self.clock()
        return changed

    def plan_view(self, orders: bool = True) -> dict[str, Any]:
        """The current plan: every AGV with its order, leg, goal point and path; the active
        orders (unless ``orders=False``); the service's figures."""
        agents = []
        for a in sorted(self.agents.values(), key=lambda a: a.id):
            leg = goal = None
            o = self.orders.get(a.order) if a.order is not None else None
            if o is not None:
                leg = "dropoff" if a.loaded else "pickup"
                goal = list(o.dropoff if a.loaded else o.pickup)
            agents.append({"id": a.id, "position": [a.x, a.y], "status": a.status,
                           "order": a.order, "leg": leg, "goal": goal, "path": a.path})
        view: dict[str, Any] = {"version": self.plan_version, "time": self.plan_time,
                                "agents": agents}
        if orders:
            view["orders"] = [{"id": o.id, "status": o.status, "pickup": list(o.pickup),
                               "dropoff": list(o.dropoff), "priority": o.priority,
                               "agent": o.agent}
                              for o in sorted(self.orders.values(), key=lambda o: o.seq)]
        view["stats"] = self.stats()
        return view

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
