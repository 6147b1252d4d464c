"""The rules of lifelong operation: orders, how they arrive, how AGVs serve them, breakdowns.

An order has an id, a pickup and a drop-off point, a release step, a priority (higher first)
and an optional deadline. An AGV serves one order at a time: idle -> to pickup (when a
dispatcher assigns it an order) -> loaded -> idle again once it has delivered. Reaching a point
is coming within the capture radius of it; optional service steps hold the AGV still at each
point. An idle AGV that reaches the pickup of an open order that nobody was given takes it (the
paper's claiming, so that decentralized policies need no dispatcher). An order may be given to
another AGV until it is picked up, never after. A broken AGV stops and stays an obstacle; an
order it was driving to returns to the open pool at once; a loaded order stays with it until
it is repaired. No order is ever lost: at every step, released = delivered + open + assigned +
loaded (:func:`order_balance`).

Every function here is batched over B environments (and N AGVs, Q order slots) and works on
the tensors of :class:`Orders` and :class:`Fleet`; :class:`sim.lifelong.LifelongEnv` composes
them into a step. The random draws (arrivals, order points, breakdowns) come from the
counter-based streams of :mod:`sim.streams`, keyed per environment, so that they are the same
for every controller and whatever the batching.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sim import streams
from sim.world import World

__all__ = [
    "AGENT_STATUS", "ORDER_STATUS", "FREE", "OPEN", "ASSIGNED", "LOADED", "DELIVERED",
    "IDLE", "TO_PICKUP", "CARRYING", "BROKEN", "Poisson", "Backlog", "Trace", "Breakdowns",
    "FaultSchedule", "Orders", "Fleet", "Events", "read_trace", "check_arrivals",
    "check_faults", "order_balance", "MAX_PRIORITY",
]

# Order status codes (int8).
FREE, OPEN, ASSIGNED, LOADED, DELIVERED = 0, 1, 2, 3, 4
ORDER_STATUS = ("free", "open", "assigned", "loaded", "delivered")
"""Names of the order status codes: a ``free`` slot holds no order; ``delivered`` rows stay in
the table for the step of their delivery only."""
# AGV status codes (int8).
IDLE, TO_PICKUP, CARRYING, BROKEN = 0, 1, 2, 3
AGENT_STATUS = ("idle", "to_pickup", "loaded", "broken")
"""Names of the AGV status codes of :attr:`Fleet.status`."""

MAX_PRIORITY = 1 << 20
"""Priorities lie in ``(-MAX_PRIORITY, MAX_PRIORITY)``."""
_ID_BITS = 40  # order ids below 2**40 (a trillion orders per environment)


# ---------------------------------------------------------------------- arrival processes
def _check_rate(name: str, value: Any, allow_zero: bool = False) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer,
                                                                   np.floating)):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


def _check_steps(name: str, value: Any, minimum: int = 0) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _check_deadline(value: Any) -> int | None:
    return None if value is None else _check_steps("deadline", value, 1)


@dataclass(frozen=True)
class Poisson:
    """Orders arrive as a Poisson process: a mean of ``rate`` orders per step.

    Pickups are drawn uniformly among the floor's pickup points, drop-offs among its stations.

    Parameters
    ----------
    rate : float
        Mean arrivals per step, positive and finite.
    deadline : int, optional
        Every order is due this many steps after its release (default: no deadline).
    """

    rate: float
    deadline: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "rate", _check_rate("arrival rate", self.rate))
        object.__setattr__(self, "deadline", _check_deadline(self.deadline))
        if self.rate > 1000:
            raise ValueError(f"arrival rate {self.rate} orders per step is beyond what the "
                             "simulator draws (at most 1000)")

    def counts_table(self) -> Tensor:
        """The cumulative distribution of the per-step count, (K,) float64, to search in."""
        lam = self.rate
        kmax = int(lam + 12.0 * math.sqrt(lam) + 20)
        k = torch.arange(kmax + 1, dtype=torch.float64)
        logp = k * math.log(lam) - lam - torch.lgamma(k + 1)
        return torch.cumsum(torch.exp(logp), 0)


@dataclass(frozen=True)
class Backlog:
    """Keep ``open`` orders released and not yet picked up, as the League of Robot Runners
    reveals tasks (about 1.5 N of them): a new order arrives as soon as one is picked up.

    Parameters
    ----------
    open : int
        Number of open orders to keep, >= 0. ``Backlog(0)``: no order ever arrives (a floor
        whose orders are kept outside the simulator, as ``agv serve --simulate`` does).
    deadline : int, optional
        Every order is due this many steps after its release.
    """

    open: int
    deadline: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "open", _check_steps("backlog open", self.open, 0))
        object.__setattr__(self, "deadline", _check_deadline(self.deadline))


TRACE_COLUMNS = ("release", "pickup_x", "pickup_y", "dropoff_x", "dropoff_y", "priority",
                 "deadline")
"""The columns of a CSV order log (``priority`` and ``deadline`` may be empty)."""


@dataclass(frozen=True, eq=False)
class Trace:
    """An order log replayed as given: every environment receives these orders at their
    release steps.

    Attributes
    ----------
    release : np.ndarray of int64, shape (T,)
        Non-decreasing release steps.
    pickup, dropoff : np.ndarray of float64, shape (T, 2)
    priority : np.ndarray of int64, shape (T,)
    deadline : np.ndarray of int64, shape (T,)
        Due step, -1 for none.

    Use :func:`read_trace` to read and check a CSV log against a floor.
    """

    release: np.ndarray
    pickup: np.ndarray
    dropoff: np.ndarray
    priority: np.ndarray
    deadline: np.ndarray

    def __post_init__(self) -> None:
        rel = np.asarray(self.release)
        if rel.ndim != 1 or len(rel) == 0:
            raise ValueError("a trace needs at least one order (release must be a 1-D array)")
        T = len(rel)
        for name, shape in (("pickup", (T, 2)), ("dropoff", (T, 2)), ("priority", (T,)),
                            ("deadline", (T,))):
            value = np.asarray(getattr(self, name))
            if value.shape != shape:
                raise ValueError(f"trace {name} must have shape {shape}, got {value.shape}")
        for name in ("release", "priority", "deadline"):
            value = np.asarray(getattr(self, name))
            if value.dtype.kind not in "iu":
                raise ValueError(f"trace {name} must hold integers, got dtype {value.dtype}")
        for name in ("pickup", "dropoff"):
            value = np.asarray(getattr(self, name))
            if value.dtype.kind not in "iuf" or not np.all(np.isfinite(value)):
                bad = np.flatnonzero(~np.isfinite(value.astype(float)).all(axis=1)) \
                    if value.dtype.kind in "iuf" else np.arange(T)
                raise ValueError(f"trace {name} must hold finite numbers; rows "
                                 f"{bad[:8].tolist()} do not")
        for name, dtype in (("release", np.int64), ("pickup", np.float64),
                            ("dropoff", np.float64), ("priority", np.int64),
                            ("deadline", np.int64)):
            arr = np.array(getattr(self, name), dtype=dtype)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        if self.release.min() < 0:
            row = int(np.argmin(self.release))
            raise ValueError(f"trace row {row}: release {int(self.release[row])} is negative")
        back = np.flatnonzero(np.diff(self.release) < 0)
        if back.size:
            row = int(back[0]) + 1
            raise ValueError(f"trace row {row}: release {int(self.release[row])} goes backwards "
                             f"(row {row - 1} has {int(self.release[row - 1])}); the log must "
                             "be sorted by release step")
        bad = np.flatnonzero(np.abs(self.priority) >= MAX_PRIORITY)
        if bad.size:
            raise ValueError(f"trace row {int(bad[0])}: priority {int(self.priority[bad[0]])} "
                             f"is outside (-{MAX_PRIORITY}, {MAX_PRIORITY})")
        late = np.flatnonzero((self.deadline >= 0) & (self.deadline < self.release))
        if late.size:
            row = int(late[0])
            raise ValueError(f"trace row {row}: deadline {int(self.deadline[row])} is before "
                             f"its release {int(self.release[row])}")
        if np.any(self.deadline < -1):
            row = int(np.flatnonzero(self.deadline < -1)[0])
            raise ValueError(f"trace row {row}: deadline must be a step >= 0 (or empty)")

    def __len__(self) -> int:
        return len(self.release)

    def check_floor(self, world: World) -> None:
        """Check every point against a floor: inside the walls, off the shelves, reachable.

        Raises
        ------
        ValueError
            Naming the first bad row (0-based, after the header) and the point.
        """
        for name in ("pickup", "dropoff"):
            pts = getattr(self, name)
            outside = np.flatnonzero(world.wall_distance(pts) < world.agent_radius - 1e-9)
            if outside.size:
                row = int(outside[0])
                raise ValueError(f"trace row {row}: {name} {pts[row].tolist()} lies outside the "
                                 f"floor (bounds {world.bounds}, an AGV of radius "
                                 f"{world.agent_radius} must fit)")
            if world.has_obstacles:
                inside = np.flatnonzero(~world.is_free(pts))
                if inside.size:
                    row = int(inside[0])
                    raise ValueError(f"trace row {row}: {name} {pts[row].tolist()} lies inside "
                                     "or too close to a shelf (an AGV must fit there)")
        unreachable = _unreachable_points(world, np.concatenate([self.pickup, self.dropoff]))
        if unreachable.size:
            k = int(unreachable[0])
            name, row = ("pickup", k) if k < len(self) else ("dropoff", k - len(self))
            pts = getattr(self, name)
            raise ValueError(f"trace row {row}: {name} {pts[row].tolist()} cannot be reached "
                             "from the rest of the floor (cut off by shelves)")


def _unreachable_points(world: World, points: np.ndarray) -> np.ndarray:
    """Indices of ``points`` outside the floor's main free region (see
    :func:`sim.floors.check_reachable`), empty when the floor check is not available."""
    try:
        from sim.floors import unreachable_points
    except ImportError:  # pragma: no cover - the floors module is part of the package
        return np.zeros(0, dtype=np.int64)
    return np.asarray(unreachable_points(world, points), dtype=np.int64)


def read_trace(path: str | os.PathLike[str], world: World | None = None) -> Trace:
    """Read a CSV order log with columns ``release,pickup_x,pickup_y,dropoff_x,dropoff_y,
    priority,deadline`` (a header row first; ``priority`` and ``deadline`` may be empty).

    Parameters
    ----------
    path : str or path-like
    world : World, optional
        When given, every point is checked against the floor (:meth:`Trace.check_floor`).

    Returns
    -------
    Trace

    Raises
    ------
    ValueError
        For a missing or wrong header, a row with the wrong number of fields, a value that is
        not a number (NaN included), release steps that go backwards, and with ``world``
        points outside the floor, inside shelves or cut off; the message names the row (the
        first data row is row 0) and the field.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise ValueError(f"trace {path!r} is a directory, expected a CSV file")
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ValueError(f"trace {path!r} is empty; expected a header "
                         f"{','.join(TRACE_COLUMNS)} and rows")
    header = [c.strip() for c in rows[0]]
    if header != list(TRACE_COLUMNS):
        raise ValueError(f"trace {path!r}: header must be {','.join(TRACE_COLUMNS)}, got "
                         f"{','.join(header)}")
    data = [r for r in rows[1:] if any(c.strip() for c in r)]
    if not data:
        raise ValueError(f"trace {path!r} has a header but no orders")
    cols: dict[str, list[Any]] = {c: [] for c in TRACE_COLUMNS}
    for i, row in enumerate(data):
        if len(row) != len(TRACE_COLUMNS):
            raise ValueError(f"trace {path!r} row {i}: {len(row)} fields, expected "
                             f"{len(TRACE_COLUMNS)} ({','.join(TRACE_COLUMNS)})")
        for name, text in zip(TRACE_COLUMNS, row, strict=True):
            text = text.strip()
            if name in ("priority", "deadline") and text == "":
                cols[name].append(0 if name == "priority" else -1)
                continue
            try:
                if name in ("release", "priority", "deadline"):
                    value: Any = int(text)
                else:
                    value = float(text)
                    if not math.isfinite(value):
                        raise ValueError
            except ValueError:
                kind = "an integer" if name in ("release", "priority", "deadline") \
                    else "a finite number"
                raise ValueError(f"trace {path!r} row {i}: {name} must be {kind}, got "
                                 f"{text!r}") from None
            cols[name].append(value)
    trace = Trace(
        release=np.array(cols["release"], dtype=np.int64),
        pickup=np.stack([cols["pickup_x"], cols["pickup_y"]], axis=1).astype(np.float64),
        dropoff=np.stack([cols["dropoff_x"], cols["dropoff_y"]], axis=1).astype(np.float64),
        priority=np.array(cols["priority"], dtype=np.int64),
        deadline=np.array(cols["deadline"], dtype=np.int64),
    )
    if world is not None:
        trace.check_floor(world)
    return trace


def check_arrivals(arrivals: Any, world: World) -> Poisson | Backlog | Trace:
    """An arrival process checked against a floor.

    Parameters
    ----------
    arrivals : Poisson, Backlog, Trace, float (a Poisson rate) or a path to a CSV order log
    world : World

    Raises
    ------
    ValueError
        For anything else, a rate that is not positive and finite, or generated orders on a
        floor without pickup points or stations.
    """
    if isinstance(arrivals, (str, os.PathLike)):
        arrivals = read_trace(arrivals, world)
    elif isinstance(arrivals, (int, float, np.integer, np.floating)) \
            and not isinstance(arrivals, (bool, np.bool_)):
        arrivals = Poisson(arrivals)
    if isinstance(arrivals, Trace):
        arrivals.check_floor(world)
        return arrivals
    if not isinstance(arrivals, (Poisson, Backlog)):
        raise ValueError(f"arrivals must be sim.Poisson(rate), sim.Backlog(open), a "
                         f"sim.Trace, a rate or a CSV path, got {type(arrivals).__name__} "
                         f"{arrivals!r:.80}")
    if len(_points(world, "pickups")) == 0 or len(_points(world, "stations")) == 0:
        raise ValueError("generated orders need a floor with pickup points and stations "
                         "(World.pickups and World.stations); this floor has "
                         f"{len(_points(world, 'pickups'))} and "
                         f"{len(_points(world, 'stations'))}; use a warehouse-N scenario, "
                         "sim.load_floor(...), or a Trace")
    return arrivals


def _points(world: World, name: str) -> np.ndarray:
    return np.asarray(getattr(world, name, np.zeros((0, 2))), dtype=np.float64).reshape(-1, 2)


# ---------------------------------------------------------------------- breakdowns
@dataclass(frozen=True)
class Breakdowns:
    """Random breakdowns: each working AGV breaks with probability ``rate`` per step and is
    repaired ``repair_steps`` steps later.

    Parameters
    ----------
    rate : float
        Probability per AGV-step, in (0, 1].
    repair_steps : int
        Steps a broken AGV stays broken, >= 1.
    """

    rate: float
    repair_steps: int = 50

    def __post_init__(self) -> None:
        rate = _check_rate("fault rate", self.rate)
        if rate > 1:
            raise ValueError(f"fault rate is a probability per AGV-step, in (0, 1]; got {rate}")
        object.__setattr__(self, "rate", rate)
        object.__setattr__(self, "repair_steps",
                           _check_steps("repair_steps", self.repair_steps, 1))


@dataclass(frozen=True)
class FaultSchedule:
    """Breakdowns at given steps: rows ``(step, agent, repair_steps)``, the same in every
    environment. An AGV already broken at its step is not broken again.

    Attributes
    ----------
    step, agent, repair_steps : np.ndarray of int64, shape (F,)
    """

    step: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    agent: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    repair_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @classmethod
    def from_rows(cls, rows: Any, num_agents: int) -> FaultSchedule:
        """Build and check a schedule from ``(step, agent, repair_steps)`` rows.

        Raises
        ------
        ValueError
            Naming the row, for a row that is not three integers, a step < 1, an AGV that does
            not exist (outside [0, num_agents)) or a repair time < 1.
        """
        try:
            rows = list(rows)
        except TypeError:
            raise ValueError(f"faults must be sim.Breakdowns(...) or a list of (step, agent, "
                             f"repair_steps) rows, got {rows!r:.80}") from None
        out = np.zeros((len(rows), 3), dtype=np.int64)
        for i, row in enumerate(rows):
            try:
                values = list(row)
            except TypeError:
                values = [row]
            if len(values) != 3 or any(
                    isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer))
                    for v in values):
                raise ValueError(f"fault row {i}: expected three integers (step, agent, "
                                 f"repair_steps), got {row!r}")
            step, agent, repair = (int(v) for v in values)
            if step < 1:
                raise ValueError(f"fault row {i}: step must be >= 1, got {step}")
            if not 0 <= agent < num_agents:
                raise ValueError(f"fault row {i}: AGV {agent} does not exist (the fleet has "
                                 f"{num_agents} AGVs, 0 to {num_agents - 1})")
            if repair < 1:
                raise ValueError(f"fault row {i}: repair_steps must be >= 1, got {repair}")
            out[i] = (step, agent, repair)
        return cls(out[:, 0].copy(), out[:, 1].copy(), out[:, 2].copy())


def check_faults(faults: Any, num_agents: int) -> Breakdowns | FaultSchedule | None:
    """``faults`` as :class:`Breakdowns`, :class:`FaultSchedule` or None (no breakdowns).

    Raises
    ------
    ValueError
        For anything else (see :meth:`FaultSchedule.from_rows`).
    """
    if faults is None or isinstance(faults, Breakdowns):
        return faults
    if isinstance(faults, FaultSchedule):
        bad = np.flatnonzero((faults.agent < 0) | (faults.agent >= num_agents))
        if bad.size:
            raise ValueError(f"fault row {int(bad[0])}: AGV {int(faults.agent[bad[0]])} does not "
                             f"exist (the fleet has {num_agents} AGVs)")
        return faults
    if isinstance(faults, (str, bytes, dict)):
        raise ValueError(f"faults must be sim.Breakdowns(rate, repair_steps) or a list of "
                         f"(step, agent, repair_steps) rows, got {faults!r:.80}")
    return FaultSchedule.from_rows(faults, num_agents)


# ---------------------------------------------------------------------- the state
@dataclass
class Orders:
    """The order table of B environments: Q slots each (the table grows when it is full).

    All tensors are (B, Q) unless noted; a slot whose ``status`` is :data:`FREE` holds no
    order. The environment rebinds these tensors on every step and never writes into one it
    has handed out.

    Attributes
    ----------
    id : int64
        Order id, counting from 0 in each environment in release order (-1 in free slots); for
        a trace, the row of the log.
    status : int8
        :data:`ORDER_STATUS` codes.
    pickup, dropoff : float32, shape (B, Q, 2)
    release : int64
        Release step.
    priority : int64
        Higher first.
    deadline : int64
        Due step, -1 for none.
    agent : int64
        AGV assigned to the order or carrying it, -1 for none.
    picked : int64
        Step of the pickup, -1 before.
    finished : int64
        Step of the delivery (in the step's ``delivered`` rows), -1 before.
    """

    id: Tensor
    status: Tensor
    pickup: Tensor
    dropoff: Tensor
    release: Tensor
    priority: Tensor
    deadline: Tensor
    agent: Tensor
    picked: Tensor
    finished: Tensor

    @classmethod
    def empty(cls, B: int, Q: int, device: torch.device) -> Orders:
        """A table of B x Q free slots."""
        long = dict(dtype=torch.int64, device=device)
        return cls(
            id=torch.full((B, Q), -1, **long),
            status=torch.zeros(B, Q, dtype=torch.int8, device=device),
            pickup=torch.zeros(B, Q, 2, dtype=torch.float32, device=device),
            dropoff=torch.zeros(B, Q, 2, dtype=torch.float32, device=device),
            release=torch.full((B, Q), -1, **long),
            priority=torch.zeros(B, Q, **long),
            deadline=torch.full((B, Q), -1, **long),
            agent=torch.full((B, Q), -1, **long),
            picked=torch.full((B, Q), -1, **long),
            finished=torch.full((B, Q), -1, **long),
        )

    @property
    def capacity(self) -> int:
        """Q, the number of slots."""
        return self.status.shape[1]

    def grown(self, Q: int) -> Orders:
        """A copy with Q >= capacity slots (the new ones free)."""
        extra = Orders.empty(self.status.shape[0], Q - self.capacity, self.status.device)
        return Orders(**{f.name: torch.cat([getattr(self, f.name), getattr(extra, f.name)], 1)
                         for f in fields(self)})

    def select(self, rows: Tensor, other: Orders) -> Orders:
        """Rows from ``other`` where ``rows`` (B,) bool, else from self (same capacity)."""
        def pick(a: Tensor, b: Tensor) -> Tensor:
            return torch.where(rows.view(-1, *([1] * (a.dim() - 1))), b, a)
        return Orders(**{f.name: pick(getattr(self, f.name), getattr(other, f.name))
                         for f in fields(self)})

    def count(self, status: int) -> Tensor:
        """Orders with that status per environment, (B,) int64."""
        return (self.status == status).sum(dim=1)

    def as_dict(self, env: int = 0) -> dict[str, np.ndarray]:
        """The occupied rows of one environment as numpy columns (for printing and tests)."""
        keep = (self.status[env] != FREE).cpu().numpy()
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)[env].cpu().numpy()
            out[f.name] = value[keep]
        out["status_name"] = np.array([ORDER_STATUS[s] for s in out["status"]])
        return out


@dataclass
class Fleet:
    """The AGV side of lifelong operation, (B, N) tensors.

    Attributes
    ----------
    order : int64
        Slot of the order the AGV is assigned to or carries, -1 for none.
    status : int8
        :data:`AGENT_STATUS` codes (derived from the others after every step).
    service_left : int64
        Steps of service still to do at the current point (the AGV stands still meanwhile).
    serving_dropoff : bool
        Whether that service is the drop-off (the order is delivered when it ends).
    repair_left : int64
        Steps until repair, 0 for a working AGV.
    """

    order: Tensor
    status: Tensor
    service_left: Tensor
    serving_dropoff: Tensor
    repair_left: Tensor

    @classmethod
    def empty(cls, B: int, N: int, device: torch.device) -> Fleet:
        long = dict(dtype=torch.int64, device=device)
        return cls(order=torch.full((B, N), -1, **long),
                   status=torch.zeros(B, N, dtype=torch.int8, device=device),
                   service_left=torch.zeros(B, N, **long),
                   serving_dropoff=torch.zeros(B, N, dtype=torch.bool, device=device),
                   repair_left=torch.zeros(B, N, **long))

    @property
    def broken(self) -> Tensor:
        """(B, N) bool."""
        return self.repair_left > 0

    def select(self, rows: Tensor, other: Fleet) -> Fleet:
        """Rows from ``other`` where ``rows`` (B,) bool, else from self."""
        return Fleet(**{f.name: torch.where(rows.view(-1, 1), getattr(other, f.name),
                                            getattr(self, f.name)) for f in fields(self)})


@dataclass
class Events:
    """What happened in the last step (or at reset), batched.

    Attributes
    ----------
    arrived, picked_up, delivered, returned : Tensor of bool, shape (B, Q)
        Order slots released in the step; picked up; delivered (those rows keep status
        ``delivered`` until the next step); returned to the open pool by a breakdown.
    breakdown, repaired : Tensor of bool, shape (B, N)
        AGVs that broke down; that were repaired.
    """

    arrived: Tensor
    picked_up: Tensor
    delivered: Tensor
    returned: Tensor
    breakdown: Tensor
    repaired: Tensor

    @classmethod
    def none(cls, B: int, Q: int, N: int, device: torch.device) -> Events:
        q = torch.zeros(B, Q, dtype=torch.bool, device=device)
        n = torch.zeros(B, N, dtype=torch.bool, device=device)
        return cls(q, q, q, q, n, n)

    @property
    def any(self) -> Tensor:
        """(B,) bool: whether anything happened in each environment (a controller re-plans
        there)."""
        return (self.arrived.any(1) | self.picked_up.any(1) | self.delivered.any(1)
                | self.returned.any(1) | self.breakdown.any(1) | self.repaired.any(1))

    def counts(self) -> dict[str, Tensor]:
        """Events of each kind per environment, {name: (B,) int64}."""
        return {f.name: getattr(self, f.name).sum(dim=1) for f in fields(self)}


def order_balance(orders: Orders, released: Tensor, delivered: Tensor) -> Tensor:
    """released - (delivered + open + assigned + loaded) per environment, (B,) int64: 0 when
    no order is lost (``delivered`` counts every delivery so far, the rows still marked
    delivered included)."""
    held = orders.count(OPEN) + orders.count(ASSIGNED) + orders.count(LOADED)
    return released - delivered - held


# ---------------------------------------------------------------------- the rules
def agent_status(fleet: Fleet, orders: Orders) -> Tensor:
    """The AGV status codes (B, N) int8 from the fleet and the order table."""
    slot = fleet.order.clamp_min(0)
    st = orders.status.gather(1, slot)
    has = fleet.order >= 0
    code = torch.where(has & (st == LOADED), CARRYING,
                       torch.where(has & (st == ASSIGNED), TO_PICKUP, IDLE))
    return torch.where(fleet.broken, BROKEN, code).to(torch.int8)


def insert_orders(
    orders: Orders, counts: Tensor, next_id: Tensor, step: Tensor, make: Any,
) -> tuple[Orders, Tensor, Tensor]:
    """Release ``counts[b]`` new orders in each environment b, in its lowest free slots.

    Parameters
    ----------
    orders : Orders
    counts : Tensor of int64, shape (B,)
    next_id : Tensor of int64, shape (B,)
        Id of each environment's next order.
    step : Tensor of int64, shape (B,)
        The release step.
    make : callable
        ``make(ids (K,) int64, env (K,) int64) -> (pickup (K, 2), dropoff (K, 2), priority (K,),
        deadline (K,))`` for the K new orders.

    Returns
    -------
    orders : Orders
        Grown (doubling) when some environment lacks free slots.
    arrived : Tensor of bool, shape (B, Q)
    next_id : Tensor of int64, shape (B,)
    """
    free = orders.status == FREE
    need = int((counts - free.sum(1)).max()) if counts.numel() else 0
    if need > 0:
        orders = orders.grown(max(2 * orders.capacity, orders.capacity + need))
        free = orders.status == FREE
    rank = free.cumsum(1) - 1
    arrived = free & (rank < counts.unsqueeze(1))
    if not bool(arrived.any()):
        return orders, arrived, next_id
    env, slot = arrived.nonzero(as_tuple=True)
    ids = next_id[env] + rank[env, slot]
    pickup, dropoff, priority, deadline = make(ids, env)
    o = replace(orders)
    o.id = orders.id.index_put((env, slot), ids)
    o.status = orders.status.index_put((env, slot), torch.tensor(OPEN, dtype=torch.int8,
                                                                 device=ids.device))
    o.pickup = orders.pickup.index_put((env, slot), pickup.to(torch.float32))
    o.dropoff = orders.dropoff.index_put((env, slot), dropoff.to(torch.float32))
    o.release = orders.release.index_put((env, slot), step[env])
    o.priority = orders.priority.index_put((env, slot), priority.to(torch.int64))
    o.deadline = orders.deadline.index_put((env, slot), deadline.to(torch.int64))
    o.agent = orders.agent.index_put((env, slot), torch.full_like(ids, -1))
    o.picked = orders.picked.index_put((env, slot), torch.full_like(ids, -1))
    o.finished = orders.finished.index_put((env, slot), torch.full_like(ids, -1))
    return o, arrived, next_id + counts


def tie_key(orders: Orders) -> Tensor:
    """(B, Q) int64 ordering orders that are equally near: higher priority first, then the
    older (smaller id)."""
    return (orders.priority << _ID_BITS) - orders.id


def match(dist: Tensor, eligible: Tensor, key: Tensor) -> tuple[Tensor, Tensor]:
    """One round of pickups: each order goes to its nearest eligible AGV (ties to the lower
    index), and an AGV that wins several takes its nearest (equally near: the larger ``key``).

    Parameters
    ----------
    dist : Tensor, shape (B, N, Q)
    eligible : Tensor of bool, shape (B, N, Q)
    key : Tensor of int64, shape (B, Q)

    Returns
    -------
    takes : Tensor of bool, shape (B, N)
        AGVs that pick an order up.
    slot : Tensor of int64, shape (B, N)
        The slot each of them takes (meaningless where ``takes`` is False).
    """
    inf = torch.full_like(dist, float("inf"))
    best_agent = torch.where(eligible, dist, inf).argmin(dim=1, keepdim=True)  # (B, 1, Q)
    agents = torch.arange(dist.shape[1], device=dist.device).view(1, -1, 1)
    won = eligible & (agents == best_agent)
    d_won = torch.where(won, dist, inf)
    nearest = d_won.min(dim=2, keepdim=True).values
    takes = torch.isfinite(nearest.squeeze(2))
    lowest = torch.iinfo(torch.int64).min
    ranked = torch.where(won & (d_won == nearest), key.unsqueeze(1),
                         torch.full_like(dist, lowest, dtype=torch.int64))
    return takes, ranked.argmax(dim=2)


def pickups(agent_pos: Tensor, ready: Tensor, agent_order: Tensor, orders: Orders,
            capture_radius: float) -> tuple[Tensor, Tensor]:
    """Which AGV picks which order up in this step (the torch reference of the fused kernel
    in ``sim/_native/orders.h``).

    A ready AGV may pick up its own assigned order or, when it has none, any open order, within
    the capture radius; then :func:`match`.

    Parameters
    ----------
    agent_pos : Tensor, shape (B, N, 2)
    ready : Tensor of bool, shape (B, N)
        AGVs that may pick up (running, working, not in service, not finishing a drop-off).
    agent_order : Tensor of int64, shape (B, N)
        Each AGV's order slot, -1 for none.
    orders : Orders
    capture_radius : float

    Returns
    -------
    takes : Tensor of bool, shape (B, N)
    slot : Tensor of int64, shape (B, N)
    """
    B, N = ready.shape
    Q = orders.capacity
    dist = torch.cdist(agent_pos, orders.pickup, compute_mode="donot_use_mm_for_euclid_dist")
    idle = ready & (agent_order < 0)
    mine = torch.zeros(B, N, Q, dtype=torch.bool, device=ready.device)
    mine.scatter_(2, agent_order.clamp_min(0).unsqueeze(2), (agent_order >= 0).unsqueeze(2))
    eligible = (dist <= capture_radius) & (
        (idle.unsqueeze(2) & (orders.status == OPEN).unsqueeze(1))
        | (ready.unsqueeze(2) & mine & (orders.status == ASSIGNED).unsqueeze(1)))
    if not bool(eligible.any()):
        return torch.zeros_like(ready), torch.zeros_like(agent_order)
    takes, slot = match(dist, eligible, tie_key(orders))
    return takes, torch.where(takes, slot, 0)


def dropoffs(agent_pos: Tensor, ready: Tensor, agent_order: Tensor, orders: Orders,
             capture_radius: float) -> Tensor:
    """Ready AGVs with a loaded order whose drop-off they reach (within the capture radius),
    (B, N) bool: the torch reference of the drop-offs in ``sim/_native/orders.h``."""
    B, N = ready.shape
    slot = agent_order.clamp_min(0)
    carrying = (agent_order >= 0) & (orders.status.gather(1, slot) == LOADED)
    drop = orders.dropoff.gather(1, slot.unsqueeze(-1).expand(B, N, 2))
    near = torch.linalg.vector_norm(agent_pos - drop, dim=-1) <= capture_radius
    return ready & carrying & near


def poisson_counts(table: Tensor, key: Tensor, step: Tensor, kernels: Any = None) -> Tensor:
    """Per-environment arrival counts of one step, (B,) int64, from the streams."""
    u = streams.uniform(key, streams.ARRIVALS, step, kernels=kernels)
    counts = torch.searchsorted(table.to(u.device), u.contiguous(), right=True)
    return counts.clamp_max(table.numel() - 1)


def generated_points(world_pickups: Tensor, world_stations: Tensor, key: Tensor, ids: Tensor,
                     env: Tensor, kernels: Any = None) -> tuple[Tensor, Tensor]:
    """Pickup and drop-off of generated orders: uniform among the floor's points, drawn from
    each order's own stream (so an order's points depend only on its id)."""
    k = key[env]
    P, S = len(world_pickups), len(world_stations)
    # Both draws in one call: the last counter is 0 for the pickup, 1 for the drop-off.
    u = streams.uniform(k.unsqueeze(1), streams.ORDER_POINTS, ids.unsqueeze(1),
                        torch.arange(2, device=ids.device), kernels=kernels)  # (K, 2)
    i = (u[:, 0] * P).long().clamp_max(P - 1)
    j = (u[:, 1] * S).long().clamp_max(S - 1)
    return world_pickups[i], world_stations[j]
