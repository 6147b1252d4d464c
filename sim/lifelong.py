"""Lifelong operation: a floor, a fleet and a stream of transport orders, batched.

The simulator's second mode (``DESIGN.md``, "Lifelong operation"); the paper's episodes
(:mod:`sim.env`) stay exactly as they are. A :class:`LifelongScenario` is a floor with pickup
points and stations (:mod:`sim.floors`), a fleet size, an arrival process and optional
breakdowns; a :class:`LifelongEnv` steps B such floors at once with the same physics as the
episodes, the order rules of :mod:`sim.orders`, lifelong observations
(:class:`sim.observations.LifelongObsLayout`) and the lifelong rewards of
:mod:`sim.rewards.lifelong`.

After each step, :attr:`LifelongEnv.events` says what happened (arrivals, pickups,
deliveries, orders returned by a breakdown, breakdowns, repairs) and :attr:`LifelongEnv.orders`
is the order table, so that a centralized controller re-plans on events; it gives AGVs their
orders with :meth:`LifelongEnv.assign`. The controller protocol is the episodes' one:
``reset(env)`` once, ``act(obs)`` each step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sim import lifelong_native, physics, streams, tasks
from sim import native as native_kernels
from sim import orders as rules
from sim.checks import (
    as_actions,
    check_count,
    check_device,
    check_env_ids,
    check_seed,
    check_slots,
    real_array,
)
from sim.native import pointer
from sim.observations import LifelongObsLayout, lifelong_global_state, observe_lifelong
from sim.orders import (
    ASSIGNED,
    BROKEN,
    DELIVERED,
    FREE,
    LOADED,
    OPEN,
    Backlog,
    Breakdowns,
    Events,
    FaultSchedule,
    Fleet,
    Orders,
    Poisson,
    Trace,
)
from sim.rewards.base import check_reward_terms
from sim.spawn import Sampler, place_entities, uniform_sampler
from sim.state import LifelongContext, LifelongState
from sim.world import World

__all__ = ["LifelongEnv", "LifelongScenario", "lifelong_scenario", "depot_sampler"]


def depot_sampler(world: World) -> Sampler:
    """Candidates uniform over the floor's depot rectangles (weighted by area), an AGV radius
    in from their edges; uniform over the whole floor when it has no depot."""
    depot = np.asarray(getattr(world, "depot", np.zeros((0, 4))), dtype=np.float64).reshape(-1, 4)
    r = world.agent_radius
    if len(depot) == 0:
        return uniform_sampler(world, r)
    lo = torch.tensor(depot[:, :2] + r, dtype=torch.float32)
    span = torch.tensor(np.maximum(depot[:, 2:] - depot[:, :2] - 2 * r, 0.0), dtype=torch.float32)
    weight = (span[:, 0] * span[:, 1]).double()
    if float(weight.sum()) <= 0:
        raise ValueError("the floor's depot rectangles are too small to hold an AGV")
    cdf = torch.cumsum(weight / weight.sum(), 0)

    def sample(B: int, C: int, gen: torch.Generator, device: torch.device) -> Tensor:
        u = torch.rand(B, C, 3, generator=gen, device=device, dtype=torch.float64)
        k = torch.searchsorted(cdf.to(device), u[..., 0].contiguous()).clamp_max(len(cdf) - 1)
        return (lo.to(device)[k] + u[..., 1:].float() * span.to(device)[k])

    return sample


@dataclass(frozen=True)
class LifelongScenario:
    """A floor, a fleet and how orders arrive: one seeded family of lifelong runs.

    Attributes
    ----------
    name : str
    world : World
        The floor, with pickup points and stations (``World.pickups``, ``World.stations``)
        unless the orders come from a trace; AGVs start in ``World.depot`` if it has one.
    num_agents : int
        N AGVs.
    arrivals : Poisson, Backlog or Trace, optional
        Default ``Backlog(ceil(1.5 N))``, as the League of Robot Runners reveals tasks.
    faults : Breakdowns or FaultSchedule, optional
        Default none.
    service_steps : int
        Steps an AGV stands at a pickup and at a drop-off (default 0).
    max_steps : int
        Truncation horizon of a run (``done`` turns True there; lifelong operation itself has
        none). Default 1000.
    k_pickups, k_agents : int
        Open pickups and other AGVs in an observation (the nearest ones), each in
        [0, :data:`sim.checks.MAX_SLOTS`].
    sensing_range : float
        Entities farther than this are masked out of observations.
    """

    name: str
    world: World
    num_agents: int
    arrivals: Poisson | Backlog | Trace | None = None
    faults: Breakdowns | FaultSchedule | None = None
    service_steps: int = 0
    max_steps: int = 1000
    k_pickups: int = 4
    k_agents: int = 4
    sensing_range: float = math.inf
    agent_sampler: Sampler | None = field(default=None, repr=False, compare=False)

    lifelong = True
    """Lifelong scenarios say so (the episodic :class:`sim.scenarios.Scenario` does not)."""

    def __post_init__(self) -> None:
        if not isinstance(self.world, World):
            raise ValueError(f"world must be a sim.World, got {type(self.world).__name__}")
        n = check_count("num_agents", self.num_agents)
        object.__setattr__(self, "num_agents", n)
        for attr in ("max_steps",):
            object.__setattr__(self, attr, check_count(attr, getattr(self, attr)))
        v = self.service_steps
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f"service_steps must be an integer >= 0, got {v!r}")
        object.__setattr__(self, "service_steps", int(v))
        for attr in ("k_pickups", "k_agents"):
            object.__setattr__(self, attr, check_slots(attr, getattr(self, attr)))
        if not (isinstance(self.sensing_range, (int, float)) and self.sensing_range > 0):
            raise ValueError(f"sensing_range must be positive, got {self.sensing_range!r}")
        arrivals = self.arrivals if self.arrivals is not None else Backlog(math.ceil(1.5 * n))
        object.__setattr__(self, "arrivals", rules.check_arrivals(arrivals, self.world))
        object.__setattr__(self, "faults", rules.check_faults(self.faults, n))
        if self.agent_sampler is None:
            object.__setattr__(self, "agent_sampler", depot_sampler(self.world))
        try:
            self.spawn(2, torch.Generator().manual_seed(12345), torch.device("cpu"))
        except RuntimeError as err:
            raise ValueError(f"scenario {self.name!r}: {err} (the depot or floor has no room "
                             f"for {n} AGVs one diameter apart)") from None

    @property
    def pickups(self) -> np.ndarray:
        """The floor's pickup points, (P, 2)."""
        return rules._points(self.world, "pickups")

    @property
    def stations(self) -> np.ndarray:
        """The floor's drop-off stations, (S, 2)."""
        return rules._points(self.world, "stations")

    def spawn(self, B: int, gen: torch.Generator, device: torch.device,
              kernels: Any = None) -> Tensor:
        """Draw B starting fleets, (B, N, 2), AGVs one diameter apart (in the depot)."""
        agents, _ = place_entities(self.world, self.num_agents, 0, self.agent_sampler,
                                   self.agent_sampler, B, gen, device, kernels)
        return agents

    def with_options(self, **options: Any) -> LifelongScenario:
        """A copy with some fields replaced (e.g. ``arrivals=sim.Poisson(0.5)``)."""
        unknown = set(options) - set(self.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown scenario option(s) {sorted(unknown)}; expected some of "
                             f"{sorted(self.__dataclass_fields__)}")
        if "world" in options and "agent_sampler" not in options:
            options["agent_sampler"] = None
        return replace(self, **options)

    def throughput_bound(self, steps: int | None = None) -> float:
        """Orders per 1000 steps that no controller can beat on this floor.

        Every AGV always on a loaded trip, each as short as it can be: from within the capture
        radius of the pickup to within it of the drop-off, in a straight line at the top
        speed of the physics, plus the service steps at both ends. With a Poisson process the
        arrival rate bounds it too, and with a trace its number of orders over ``steps``.
        """
        w = self.world
        arr = self.arrivals
        if isinstance(arr, Trace):
            d = np.linalg.norm(arr.dropoff - arr.pickup, axis=1)
        else:
            p, s = self.pickups, self.stations
            d = np.linalg.norm(p[:, None, :] - s[None, :, :], axis=-1).ravel()
        per_step = w.physics.terminal_speed * w.physics.dt
        trip = np.maximum(d - 2 * w.capture_radius, 0.0) / per_step + 2 * self.service_steps
        bound = self.num_agents / max(float(trip.mean()), 1.0)
        if isinstance(arr, Poisson):
            bound = min(bound, arr.rate)
        if isinstance(arr, Trace) and steps:
            bound = min(bound, float(np.sum(arr.release < steps)) / steps)
        return 1000.0 * bound


def lifelong_scenario(world: World, num_agents: int, name: str = "floor",
                      **options: Any) -> LifelongScenario:
    """A lifelong scenario on a floor (e.g. from :func:`sim.load_floor`) with N AGVs."""
    return LifelongScenario(name=name, world=world, num_agents=num_agents, **options)


class LifelongEnv:
    """B parallel lifelong floors: N AGVs serving a stream of orders.

    Parameters
    ----------
    scenario : LifelongScenario
    num_envs : int
        B.
    reward : str or callable
        ``"minidist"``, ``"greedy"``, ``"ipf"`` (their lifelong forms,
        :mod:`sim.rewards.lifelong`) or a callable ``(state, ctx) -> {term: (B, N)}`` of a
        :class:`sim.state.LifelongState` and :class:`sim.state.LifelongContext`.
    seed : int, optional
        Seed of the generator that draws the starting fleets and each run's stream key.
    device : str or torch.device
    native : bool, optional
        Use the fused CPU kernels (default: wherever they are available; ``True`` raises if
        they are not) or the torch reference path (``False``).

    Attributes
    ----------
    agent_pos, agent_vel : Tensor, shape (B, N, 2)
    orders : sim.orders.Orders
        The order table, (B, Q) tensors; Q grows when a floor has more orders than slots.
    fleet : sim.orders.Fleet
        Each AGV's order, status (:data:`sim.orders.AGENT_STATUS`), service and repair.
    events : sim.orders.Events
        What happened in the last step (or the reset).
    steps : Tensor of int64, shape (B,)
    done : Tensor of bool, shape (B,)
        True at the truncation horizon ``scenario.max_steps``.
    released, delivered : Tensor of int64, shape (B,)
        Orders released and delivered since the reset.
    reassignments : Tensor of int64, shape (B,)
        Times an assigned order was given to another AGV.
    """

    lifelong = True

    def __init__(
        self,
        scenario: LifelongScenario,
        num_envs: int = 1,
        reward: Any = "minidist",
        seed: int | None = None,
        device: str | torch.device = "cpu",
        native: bool | None = None,
    ) -> None:
        from sim.rewards import make_reward

        if not isinstance(scenario, LifelongScenario):
            raise ValueError(f"scenario must be a LifelongScenario, got "
                             f"{type(scenario).__name__}")
        if native is not None and not isinstance(native, (bool, np.bool_)):
            raise ValueError(f"native must be True, False or None, got {native!r}")
        self.scenario = scenario
        self.world = scenario.world
        self.num_envs = check_count("num_envs", num_envs)
        self.num_agents = scenario.num_agents
        self.max_steps = scenario.max_steps
        self.device = check_device(device)
        self.dtype = torch.float32
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(0 if seed is None else check_seed(seed))
        self.reward_fn = make_reward(reward, lifelong=True)
        self._check_terms = type(self.reward_fn).__module__.split(".")[0] != "sim"
        self.obs_layout = LifelongObsLayout(scenario.k_pickups, scenario.k_agents)
        self.obs_dim = self.obs_layout.size
        B, N = self.num_envs, self.num_agents
        dev = self.device
        self._eye = torch.eye(N, dtype=torch.bool, device=dev)
        self._triu = torch.triu(torch.ones(N, N, dtype=torch.bool, device=dev), 1)
        self._obstacles = torch.tensor(np.array(self.world.obstacles), dtype=self.dtype,
                                       device=dev)
        self._contacts = self.world.physics.contact_force > 0 and N > 1
        self._native = native_kernels.library_for(self.device, None if native is None
                                                  else bool(native))
        if native and self._native is None:
            reason = ("the kernels run on CPU tensors only" if self.device.type != "cpu"
                      else native_kernels.disabled_reason())
            raise ValueError(f"native=True but the fused kernels are unavailable: {reason}")
        self._shelves = (physics.shelf_kernel(self._native, self._obstacles,
                                              self.world.agent_radius)
                         if self._native is not None and self.world.has_obstacles else None)
        self._pickups = torch.tensor(scenario.pickups, dtype=self.dtype, device=dev)
        self._stations = torch.tensor(scenario.stations, dtype=self.dtype, device=dev)
        self._points32: tuple[Tensor, Tensor] | None = None  # float32 copies for the kernels
        arr = scenario.arrivals
        self._poisson_table = arr.counts_table() if isinstance(arr, Poisson) else None
        if isinstance(arr, Trace):
            self._trace = {name: torch.as_tensor(np.array(getattr(arr, name)), device=dev)
                           for name in ("release", "pickup", "dropoff", "priority", "deadline")}
        faults = scenario.faults
        if isinstance(faults, FaultSchedule):
            self._schedule = tuple(torch.as_tensor(np.asarray(getattr(faults, name)),
                                                   device=dev)
                                   for name in ("step", "agent", "repair_steps"))
        # The state; reset fills it.
        self._agent_pos = torch.zeros(B, N, 2, dtype=self.dtype, device=dev)
        self._agent_vel = torch.zeros_like(self._agent_pos)
        self._orders = Orders.empty(B, max(2 * N, 8), dev)
        self._fleet = Fleet.empty(B, N, dev)
        zeros = torch.zeros(B, dtype=torch.int64, device=dev)
        self._steps, self._released, self._delivered = zeros, zeros.clone(), zeros.clone()
        self._next_id, self._reassignments = zeros.clone(), zeros.clone()
        self._keys = zeros.clone()
        self._done = torch.zeros(B, dtype=torch.bool, device=dev)
        self._events = Events.none(B, self._orders.capacity, N, dev)
        self._pair: Tensor | None = None
        self._targets: tuple[Tensor, Tensor] | None = None
        setup = getattr(self.reward_fn, "setup", None)
        if setup is not None:
            setup(self.world, None)
        self.reset()

    # ------------------------------------------------------------------ state (read-only)
    @property
    def agent_pos(self) -> Tensor:
        """AGV positions (B, N, 2), float32."""
        return self._agent_pos

    @property
    def agent_vel(self) -> Tensor:
        """AGV velocities (B, N, 2), float32."""
        return self._agent_vel

    @property
    def orders(self) -> Orders:
        """The order table (B, Q) (see :class:`sim.orders.Orders`)."""
        return self._orders

    @property
    def fleet(self) -> Fleet:
        """The AGVs' orders, status, service and repair (see :class:`sim.orders.Fleet`)."""
        return self._fleet

    @property
    def agent_status(self) -> Tensor:
        """(B, N) int8 :data:`sim.orders.AGENT_STATUS` codes."""
        return self._fleet.status

    @property
    def events(self) -> Events:
        """What happened in the last step (see :class:`sim.orders.Events`)."""
        return self._events

    @property
    def steps(self) -> Tensor:
        return self._steps

    @property
    def done(self) -> Tensor:
        return self._done

    @property
    def released(self) -> Tensor:
        return self._released

    @property
    def delivered(self) -> Tensor:
        return self._delivered

    @property
    def reassignments(self) -> Tensor:
        return self._reassignments

    @property
    def keys(self) -> Tensor:
        """Each run's stream key (B,) int64: its arrivals, order points and breakdowns."""
        return self._keys

    @property
    def state(self) -> LifelongState:
        return LifelongState(self._agent_pos, self._agent_vel, self._orders, self._fleet,
                             self._steps, self._done)

    @property
    def state_dim(self) -> int:
        """Length of :meth:`global_state`'s rows, 11 N (for code that records an env's sizes,
        such as learner checkpoints)."""
        return 11 * self.num_agents

    @property
    def num_tasks(self) -> int:
        """The floor's pickup points P: the task points of a lifelong floor (orders come and
        go; this is the fixed count that code recording an env's sizes, such as learner
        checkpoints, reads)."""
        return len(self.scenario.pickups)

    @property
    def native(self) -> bool:
        """Whether this environment steps with the fused CPU kernels (see :mod:`sim.native`)."""
        return self._native is not None

    _SCALARS = ("agent_pos", "agent_vel", "steps", "released", "delivered", "next_id",
                "reassignments", "keys", "done")
    _TABLES = (("orders", Orders), ("fleet", Fleet), ("events", Events))

    def state_tensors(self) -> dict[str, Tensor]:
        """Everything a run needs to continue exactly as it would have: the fleet, the order
        table, the counters, the stream keys, the last events and the generator, as named
        tensors (copies), for training checkpoints (:meth:`load_state_tensors`)."""
        out = {name: getattr(self, "_" + name).clone() for name in self._SCALARS}
        for table, _ in self._TABLES:
            value = getattr(self, "_" + table)
            for f in fields(value):
                out[f"{table}.{f.name}"] = getattr(value, f.name).clone()
        out["generator"] = self.generator.get_state()
        return out

    def load_state_tensors(self, tensors: dict[str, Tensor]) -> None:
        """Put every run back as :meth:`state_tensors` saved it (same B and N).

        Raises
        ------
        ValueError
            For a missing tensor or one whose leading sizes are not this env's (B, N).
        """
        names = [*self._SCALARS, "generator"] + [f"{t}.{f.name}" for t, cls in self._TABLES
                                                 for f in fields(cls)]
        missing = [n for n in names if n not in tensors]
        if missing:
            raise ValueError(f"lifelong state lacks {missing}")
        B, N = self.num_envs, self.num_agents
        for name in ("agent_pos", "fleet.order", "orders.status", "steps"):
            t = tensors[name]
            want = (B, N) if name in ("agent_pos", "fleet.order") else (B,)
            if tuple(t.shape[:len(want)]) != want:
                raise ValueError(f"lifelong state {name!r} has shape {tuple(t.shape)}; this "
                                 f"env has B={B}, N={N}")
        for name in self._SCALARS:
            setattr(self, "_" + name, tensors[name].clone().to(self.device))
        for table, cls in self._TABLES:
            setattr(self, "_" + table, cls(**{f.name: tensors[f"{table}.{f.name}"].clone()
                                              .to(self.device) for f in fields(cls)}))
        self.generator.set_state(tensors["generator"])
        self._pair = None
        self._update_status()

    def order_balance(self) -> Tensor:
        """released - (delivered + open + assigned + loaded), (B,): always 0."""
        return rules.order_balance(self._orders, self._released, self._delivered)

    # ------------------------------------------------------------------ reset
    def _env_index(self, env_ids: Any) -> Tensor:
        return check_env_ids(env_ids, self.num_envs, self.device)

    def reset(self, env_ids: Any = None, seed: int | None = None) -> Tensor:
        """Start new runs in all environments or some: fresh fleets from the depot, empty
        order tables, new stream keys (all drawn from the generator), the orders of step 0.

        Parameters
        ----------
        env_ids : array-like of int or bool mask (B,), optional
        seed : int, optional
            Re-seed the generator first, in [0, 2**64).

        Returns
        -------
        Tensor, shape (B, N, O)
        """
        if seed is not None:
            self.generator.manual_seed(check_seed(seed))
        idx = self._env_index(env_ids)
        if idx.numel():
            agents = self.scenario.spawn(len(idx), self.generator, self.device)
            keys = torch.randint(0, 2**62, (len(idx),), generator=self.generator,
                                 device=self.device)
            self._start(idx, agents, keys)
        return self.observe()

    def set_state(self, agent_pos: Any, keys: Any = None, env_ids: Any = None) -> Tensor:
        """Start new runs with given AGV positions and stream keys.

        Parameters
        ----------
        agent_pos : (K, N, 2) real numbers, K = number of selected environments
        keys : (K,) integers in [0, 2**63), optional
            The runs' stream keys (default drawn from the generator). The same key gives the
            same orders and breakdowns, whatever the controller and the batching.
        env_ids : which environments (default all)

        Returns
        -------
        Tensor, shape (B, N, O)
        """
        idx = self._env_index(env_ids)
        K, N = len(idx), self.num_agents
        pos = np.asarray(real_array(agent_pos, "agent_pos"), dtype=np.float64) \
            if not isinstance(agent_pos, Tensor) else agent_pos.detach().double().cpu().numpy()
        if pos.shape != (K, N, 2):
            raise ValueError(f"agent_pos must have shape (K, N, 2) = {(K, N, 2)}, got "
                             f"{pos.shape}")
        self.world.check_positions(pos.reshape(-1, 2), "agent_pos")
        if keys is None:
            k = torch.randint(0, 2**62, (K,), generator=self.generator, device=self.device)
        else:
            arr = np.asarray(real_array(keys, "keys"))
            if arr.shape != (K,) or arr.dtype.kind not in "iu" or np.any(arr < 0):
                raise ValueError(f"keys must be {K} integers >= 0, got {arr!r:.80}")
            k = torch.as_tensor(arr.astype(np.int64), device=self.device)
        self._start(idx, torch.as_tensor(pos, dtype=self.dtype, device=self.device), k)
        return self.observe()

    def _start(self, idx: Tensor, agents: Tensor, keys: Tensor) -> None:
        B, N, dev = self.num_envs, self.num_agents, self.device
        rows = torch.zeros(B, dtype=torch.bool, device=dev)
        rows[idx] = True
        self._agent_pos = self._agent_pos.index_put((idx,), agents.to(self.dtype))
        self._agent_vel = self._agent_vel.index_put((idx,), torch.zeros_like(agents))
        self._orders = self._orders.select(rows, Orders.empty(B, self._orders.capacity, dev))
        self._fleet = self._fleet.select(rows, Fleet.empty(B, N, dev))
        zero = torch.zeros(B, dtype=torch.int64, device=dev)
        keep = ~rows
        self._steps = self._steps * keep
        self._released = self._released * keep
        self._delivered = self._delivered * keep
        self._next_id = self._next_id * keep
        self._reassignments = self._reassignments * keep
        self._keys = torch.where(rows, zero.index_put((idx,), keys.to(torch.int64)), self._keys)
        self._done = self._done & keep
        self._orders, arrived = self._arrivals(rows)  # may grow the order table
        events = Events.none(B, self._orders.capacity, N, dev)
        events.arrived = arrived
        self._events = self._merge_events(events, rows)
        self._update_status()
        self._pair = None

    def _merge_events(self, new: Events, rows: Tensor) -> Events:
        """Events of the environments in ``rows`` from ``new``, the others' kept."""
        old = self._events
        Q = self._orders.capacity
        out = {}
        for name in ("arrived", "picked_up", "delivered", "returned"):
            a = getattr(old, name)
            if a.shape[1] < Q:
                a = torch.cat([a, a.new_zeros(a.shape[0], Q - a.shape[1])], 1)
            out[name] = torch.where(rows.view(-1, 1), getattr(new, name), a)
        for name in ("breakdown", "repaired"):
            out[name] = torch.where(rows.view(-1, 1), getattr(new, name), getattr(old, name))
        return Events(**out)

    # ------------------------------------------------------------------ arrivals
    def _arrivals(self, rows: Tensor) -> tuple[Orders, Tensor]:
        """Release the orders of the current step in the environments ``rows``."""
        arr = self.scenario.arrivals
        o = self._orders
        if isinstance(arr, Trace):
            T = len(arr)
            release = self._trace["release"]
            # Orders of the log released by now that this run has not had yet.
            due = torch.searchsorted(release, self._steps, right=True)
            counts = torch.where(rows, (due - self._next_id).clamp_min(0), 0)
            counts = counts.clamp_max(T)
        elif isinstance(arr, Poisson):
            counts = rules.poisson_counts(self._poisson_table, self._keys, self._steps,
                                          kernels=self._native)
            counts = torch.where(rows, counts, 0)
            if self._native is not None:
                return self._insert_native(arr, counts, int(counts.sum()))
        elif self._native is not None:  # the backlog's count and its orders in C
            counts = torch.empty(self.num_envs, dtype=torch.int64)
            total = self._native.agv_backlog_counts(
                self.num_envs, o.capacity, pointer(o.status, torch.int8, o.status.shape,
                                                   "status"),
                pointer(rows, torch.bool, (self.num_envs,), "rows"), arr.open,
                counts.data_ptr())
            return self._insert_native(arr, counts, total)
        else:
            open_now = o.count(OPEN) + o.count(ASSIGNED)
            counts = torch.where(rows, (arr.open - open_now).clamp_min(0), 0)
        if not bool((counts > 0).any()):
            return o, torch.zeros_like(o.status, dtype=torch.bool)
        steps = self._steps
        if isinstance(arr, Trace):
            tr = self._trace

            def make(ids: Tensor, env: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
                return tr["pickup"][ids], tr["dropoff"][ids], tr["priority"][ids], \
                    tr["deadline"][ids]
        else:
            deadline_after = -1 if arr.deadline is None else arr.deadline

            def make(ids: Tensor, env: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
                pickup, dropoff = rules.generated_points(self._pickups, self._stations,
                                                         self._keys, ids, env,
                                                         kernels=self._native)
                prio = torch.zeros_like(ids)
                due = steps[env] + deadline_after if deadline_after > 0 \
                    else torch.full_like(ids, -1)
                return pickup, dropoff, prio, due
        orders, arrived, self._next_id = rules.insert_orders(o, counts, self._next_id, steps,
                                                             make)
        self._released = self._released + counts
        return orders, arrived

    def _insert_native(self, arr: Backlog | Poisson, counts: Tensor, total: int
                       ) -> tuple[Orders, Tensor]:
        """Generated orders released with the kernel of ``sim/_native/orders.h``: the same
        orders in the same slots as ``rules.insert_orders`` with ``rules.generated_points``
        (tested), in one C pass instead of some thirty small tensor operations.

        Parameters
        ----------
        arr : Backlog or Poisson
        counts : Tensor of int64, shape (B,)
            New orders per environment (0 where it does not run).
        total : int
            ``counts.sum()``.
        """
        o = self._orders
        B = self.num_envs
        if total == 0:
            return o, torch.zeros_like(o.status, dtype=torch.bool)
        lib = self._native
        deadline_after = -1 if arr.deadline is None else arr.deadline
        if self._points32 is None:
            self._points32 = (self._pickups.float().contiguous(),
                              self._stations.float().contiguous())
        points, stations = self._points32
        while True:
            Q = o.capacity
            out = Orders(**{f.name: torch.empty_like(getattr(o, f.name)) for f in fields(o)})
            arrived = torch.empty(B, Q, dtype=torch.bool)
            next_id = torch.empty_like(self._next_id)
            fields_in = [pointer(getattr(o, name), dtype, shape, name)
                         for name, dtype, shape in _order_fields(B, Q)]
            full = lib.agv_insert_generated(
                B, Q, pointer(counts, torch.int64, (B,), "counts"),
                pointer(self._next_id, torch.int64, (B,), "next_id"),
                pointer(self._steps, torch.int64, (B,), "steps"),
                pointer(self._keys, torch.int64, (B,), "keys"), streams.ORDER_POINTS,
                len(points), points.data_ptr(), len(stations), stations.data_ptr(),
                deadline_after, *fields_in,
                *(getattr(out, name).data_ptr() for name, _, _ in _order_fields(B, Q)),
                arrived.data_ptr(), next_id.data_ptr())
            if not full:
                break
            # Some floor lacks free slots: grow the table as insert_orders does, then again.
            free = (o.status == FREE).sum(1)
            need = int((counts - free).max())
            o = o.grown(max(2 * o.capacity, o.capacity + need))
        self._next_id = next_id
        self._released = self._released + counts
        return out, arrived

    # ------------------------------------------------------------------ dispatch
    def assign(self, order_of_agent: Any) -> None:
        """Give AGVs their orders (a centralized dispatcher's plan), until each is picked up.

        Parameters
        ----------
        order_of_agent : (B, N) integers
            For each AGV, the slot of the order it should serve next, or -1 for none. An
            entry for a loaded or broken AGV must be -1 or, for a loaded one, its own order
            (those AGVs keep what they have). An order that loses its AGV returns to the open
            pool; giving an assigned order to another AGV counts a reassignment.

        Raises
        ------
        ValueError
            For a wrong shape, a slot outside [-1, Q), a slot that holds no open or assigned
            order, one order given to two AGVs, or an order given to a broken or loaded AGV;
            the message names the environment, the AGV and the slot.
        """
        B, N, Q = self.num_envs, self.num_agents, self._orders.capacity
        arr = real_array(order_of_agent, "order_of_agent")
        want = torch.as_tensor(arr, device=self.device)
        if want.dtype.is_floating_point:
            if not bool(torch.all(want == torch.round(want))):
                raise ValueError("order_of_agent must hold integer slots")
            want = want.long()
        want = want.to(torch.int64)
        if tuple(want.shape) != (B, N):
            raise ValueError(f"order_of_agent must have shape (B, N) = {(B, N)}, got "
                             f"{tuple(want.shape)}")
        if want.numel() and (int(want.min()) < -1 or int(want.max()) >= Q):
            b, a = _first((want < -1) | (want >= Q))
            raise ValueError(f"env {b} AGV {a}: slot {int(want[b, a])} is outside [-1, {Q})")
        o, f = self._orders, self._fleet
        st = f.status
        fixed = (st == BROKEN) | (st == rules.CARRYING)
        bad = fixed & (want >= 0) & (want != f.order)
        if bool(bad.any()):
            b, a = _first(bad)
            kind = rules.AGENT_STATUS[int(st[b, a])]
            raise ValueError(f"env {b} AGV {a} is {kind}: it cannot take slot "
                             f"{int(want[b, a])} (give it -1)")
        want = torch.where(fixed, f.order, want)
        wanted = want >= 0
        slot = want.clamp_min(0)
        order_status = o.status.gather(1, slot)
        bad = wanted & ~fixed & (order_status != OPEN) & (order_status != ASSIGNED)
        if bool(bad.any()):
            b, a = _first(bad)
            name = rules.ORDER_STATUS[int(order_status[b, a])]
            raise ValueError(f"env {b} AGV {a}: slot {int(want[b, a])} holds a {name} order; "
                             "only open or assigned orders can be given")
        onehot = torch.zeros(B, N, Q, dtype=torch.bool, device=self.device)
        onehot.scatter_(2, slot.unsqueeze(2), wanted.unsqueeze(2))
        per_order = onehot.sum(1)
        if bool((per_order > 1).any()):
            b, q = _first(per_order > 1)
            agents = onehot[b, :, q].nonzero().flatten().tolist()
            raise ValueError(f"env {b}: slot {q} is given to several AGVs {agents}")
        # The new agent of every order that is not loaded.
        agents = torch.arange(N, device=self.device).view(1, -1, 1)
        new_agent = torch.where(onehot, agents, -1).max(dim=1).values  # (B, Q)
        movable_order = (o.status == OPEN) | (o.status == ASSIGNED)
        new_agent = torch.where(movable_order, new_agent, o.agent)
        changed = (o.status == ASSIGNED) & (new_agent >= 0) & (new_agent != o.agent)
        self._reassignments = self._reassignments + changed.sum(1)
        status = torch.where(movable_order,
                             torch.where(new_agent >= 0, ASSIGNED, OPEN).to(torch.int8),
                             o.status)
        self._orders = replace(o, status=status, agent=new_agent)
        self._fleet = replace(f, order=want)
        self._update_status()

    # ------------------------------------------------------------------ step
    def _prepare(self, actions: Any) -> tuple[Tensor, Tensor]:
        a = as_actions(actions, (self.num_envs, self.num_agents, 2), self.dtype, self.device)
        if not bool(torch.isfinite(a).all()):
            raise ValueError("actions contain NaN or infinite values; expected finite values")
        return a.clamp(-1.0, 1.0), ~self._done

    def step(self, actions: Tensor | np.ndarray) -> tuple[Tensor, Tensor, Tensor, dict]:
        """Advance every running floor by one step.

        In order: physics (broken AGVs and AGVs in service stand still); service and repair
        countdowns (a drop-off service that ends delivers); pickups (an AGV reaching the
        pickup of its assigned order, or an idle AGV reaching an open order nobody was
        given) and drop-offs (a loaded AGV reaching its drop-off); breakdowns; the arrivals
        of the new step. Rows delivered in the previous step are freed first.

        Parameters
        ----------
        actions : Tensor or array, shape (B, N, 2)
            Accelerations in [-1, 1]; ignored for AGVs that stand still.

        Returns
        -------
        obs : Tensor, shape (B, N, O)
        reward : Tensor, shape (B, N)
        done : Tensor of bool, shape (B,)
            True at the truncation horizon.
        info : dict
            ``reward_terms`` {name: (B, N)}, ``team_reward`` (B,), ``collision_pairs`` (B,),
            ``collisions_per_agent`` (B, N), ``active`` (B,), ``events``
            (:class:`sim.orders.Events`), ``delivered_now`` (B,) int64.
        """
        actions, active = self._prepare(actions)
        B, N = self.num_envs, self.num_agents
        prev_pos, prev_orders, prev_fleet = self._agent_pos, self._orders, self._fleet
        f = self._fleet
        # Floors without service steps or breakdowns skip those rules' tensor work.
        has_service = self.scenario.service_steps > 0
        has_faults = self.scenario.faults is not None
        running = active.unsqueeze(1).expand(B, N)
        working = ~f.broken if has_faults else None
        movable = running
        if has_faults:
            movable = movable & working
        if has_service:
            movable = movable & (f.service_left == 0)
        pair = self._pair_distances() if self._contacts else None
        self._agent_pos, self._agent_vel = physics.mpe_step(
            self._agent_pos, self._agent_vel, actions, movable, self.world, self._obstacles,
            pair, self._eye, shelves=self._shelves)
        self._pair = None
        self._steps = self._steps + active.long()
        o = self._orders
        # Rows delivered in the last step are freed.
        was_delivered = o.status == DELIVERED
        if bool(was_delivered.any()):
            o = replace(o, status=torch.where(was_delivered, FREE, o.status).to(torch.int8),
                        id=torch.where(was_delivered, -1, o.id))
        # Service and repair countdowns.
        fleet = replace(f)
        finish_dropoff = None
        ready = running
        if has_service:
            serving = running & (f.service_left > 0)
            if has_faults:
                serving = serving & working
            fleet.service_left = f.service_left - serving.long()
            finish_dropoff = serving & (fleet.service_left == 0) & f.serving_dropoff
            fleet.serving_dropoff = f.serving_dropoff & (fleet.service_left > 0)
            ready = ready & (fleet.service_left == 0) & ~finish_dropoff
        if has_faults:
            repairing = running & f.broken
            fleet.repair_left = f.repair_left - repairing.long()
            repaired = repairing & (fleet.repair_left == 0)
            ready = ready & ~fleet.broken
        else:
            repaired = torch.zeros_like(running)
        # Pickups (the fused kernel or the torch reference, sim.orders.pickups).
        cap = self.world.capture_radius
        if self._native is not None:  # pickups and drop-offs in one pass
            takes, slot, at_drop = lifelong_native.lifelong_pickups(
                self._agent_pos, ready.contiguous(), fleet.order, o.pickup, o.dropoff,
                o.status, rules.tie_key(o), cap)
        else:
            takes, slot = rules.pickups(self._agent_pos, ready, fleet.order, o, cap)
            at_drop = rules.dropoffs(self._agent_pos, ready, fleet.order, o, cap)
        picked_up = torch.zeros_like(o.status, dtype=torch.bool)
        service = self.scenario.service_steps
        if bool(takes.any()):
            env_i, agent_i = takes.nonzero(as_tuple=True)
            slot_i = slot[env_i, agent_i]  # distinct within an environment
            picked_up = picked_up.index_put((env_i, slot_i), torch.ones_like(slot_i, dtype=bool))
            o = replace(o, status=torch.where(picked_up, LOADED, o.status).to(torch.int8),
                        agent=o.agent.index_put((env_i, slot_i), agent_i),
                        picked=torch.where(picked_up, self._steps.unsqueeze(1), o.picked))
            fleet.order = torch.where(takes, slot, fleet.order)
            if service:
                fleet.service_left = torch.where(takes, service, fleet.service_left)
                self._agent_vel = self._agent_vel * (~takes).unsqueeze(-1)
            ready = ready & ~takes
        # Drop-offs: a loaded AGV (not one that just picked up: it had no loaded order before
        # this step's pickups) within reach of its drop-off, found with the pickups.
        slot = fleet.order.clamp_min(0)
        if service:
            fleet.service_left = torch.where(at_drop, service, fleet.service_left)
            fleet.serving_dropoff = fleet.serving_dropoff | at_drop
            self._agent_vel = self._agent_vel * (~at_drop).unsqueeze(-1)
            delivering = finish_dropoff
        else:
            delivering = at_drop
        delivered = torch.zeros_like(picked_up)
        if bool(delivering.any()):
            env_i, agent_i = delivering.nonzero(as_tuple=True)
            delivered = delivered.index_put((env_i, slot[env_i, agent_i]),
                                            torch.ones_like(env_i, dtype=torch.bool))
            delivered &= o.status == LOADED
            o = replace(o, status=torch.where(delivered, DELIVERED, o.status).to(torch.int8),
                        finished=torch.where(delivered, self._steps.unsqueeze(1), o.finished))
            fleet.order = torch.where(delivering, -1, fleet.order)
            self._delivered = self._delivered + delivered.sum(1)
        # Breakdowns.
        breakdown = self._breakdowns(active, fleet)
        returned = torch.zeros_like(picked_up)
        if bool(breakdown.any()):
            fleet.repair_left = torch.where(breakdown, self._repair_steps(breakdown),
                                            fleet.repair_left)
            fleet.service_left = torch.where(breakdown, 0, fleet.service_left)
            fleet.serving_dropoff = fleet.serving_dropoff & ~breakdown
            self._agent_vel = self._agent_vel * (~breakdown).unsqueeze(-1)
            slot = fleet.order.clamp_min(0)
            to_pickup = breakdown & (fleet.order >= 0) & (o.status.gather(1, slot) == ASSIGNED)
            env_i, agent_i = to_pickup.nonzero(as_tuple=True)
            returned = returned.index_put((env_i, slot[env_i, agent_i]),
                                          torch.ones_like(env_i, dtype=torch.bool))
            returned &= o.status == ASSIGNED
            o = replace(o, status=torch.where(returned, OPEN, o.status).to(torch.int8),
                        agent=torch.where(returned, -1, o.agent))
            fleet.order = torch.where(to_pickup, -1, fleet.order)
        self._orders, self._fleet = o, fleet
        # The new step's arrivals.
        self._orders, arrived = self._arrivals(active)
        Q = self._orders.capacity
        self._events = Events(
            arrived=arrived, picked_up=_pad(picked_up, Q), delivered=_pad(delivered, Q),
            returned=_pad(returned, Q), breakdown=breakdown, repaired=repaired)
        self._update_status()
        self._done = self._done | (self._steps >= self.max_steps)
        # Collisions, the team reward and the observations: fused kernels or torch.
        target, has_target = self.targets()
        o, f = self._orders, self._fleet
        obs = None
        if self._native is not None:
            obs, pair, per_agent, pairs = lifelong_native.lifelong_observe_collisions(
                self._agent_pos, self._agent_vel, f.status, f.service_left, target,
                has_target, o.pickup, o.status, self.obs_layout.k_pickups,
                self.obs_layout.k_agents, self.scenario.sensing_range, active,
                self.world.agent_radius)
            work = lifelong_native.remaining_work(self._agent_pos, o.status, o.pickup,
                                                  o.dropoff, o.agent, f.status, active)
            self._pair = pair
        else:
            pair = self._pair_distances()
            per_agent, pairs = physics.collisions(pair, active, self.world.agent_radius,
                                                  self._eye, self._triu)
            work = tasks.remaining_work(self._agent_pos, o, f.status, active)
        team = torch.where(active, -work - pairs, torch.zeros_like(pairs))
        shape = (-1, N)
        ctx = LifelongContext(
            prev_agent_pos=prev_pos, prev_orders=prev_orders, prev_fleet=prev_fleet,
            active=active, events=self._events, collisions_per_agent=per_agent,
            collision_pairs=pairs, team_reward=team,
            team_distance=(team + pairs).unsqueeze(1).expand(shape),
            team_collision=(-pairs).unsqueeze(1).expand(shape),
            target=target, has_target=has_target)
        terms = self.reward_fn(self.state, ctx)
        if self._check_terms:
            check_reward_terms(terms, (B, N), self.device)
        values = list(terms.values())
        if values:
            reward = sum(values[1:], values[0]) * active.unsqueeze(1)
        else:
            reward = torch.zeros_like(per_agent)
        info = {
            "reward_terms": terms,
            "team_reward": team,
            "collision_pairs": pairs,
            "collisions_per_agent": per_agent,
            "active": active,
            "events": self._events,
            "delivered_now": self._events.delivered.sum(1),
        }
        return (self.observe() if obs is None else obs), reward, self._done.clone(), info

    def _pair_distances(self) -> Tensor:
        """Pairwise AGV distances (B, N, N), cached until the AGVs move."""
        if self._pair is None:
            self._pair = physics.pair_distances(self._agent_pos)
        return self._pair

    def _breakdowns(self, active: Tensor, fleet: Fleet) -> Tensor:
        """AGVs that break down in this step, (B, N) bool."""
        faults = self.scenario.faults
        B, N = self.num_envs, self.num_agents
        can = active.unsqueeze(1) & ~fleet.broken
        if faults is None:
            return torch.zeros(B, N, dtype=torch.bool, device=self.device)
        if isinstance(faults, Breakdowns):
            if self._native is not None:  # the same draws, compared in the same pass
                out = torch.empty(B, N, dtype=torch.bool)
                can = can.contiguous()
                self._native.agv_fault_draws(
                    B, N, pointer(self._keys, torch.int64, (B,), "keys"), streams.FAULTS,
                    pointer(self._steps, torch.int64, (B,), "steps"), float(faults.rate),
                    pointer(can, torch.bool, (B, N), "can"), out.data_ptr())
                return out
            agents = torch.arange(N, device=self.device).view(1, -1)
            u = streams.uniform(self._keys.view(-1, 1), streams.FAULTS,
                                self._steps.view(-1, 1), agents)
            return can & (u < faults.rate)
        step, agent, _ = self._schedule
        hit = step.view(1, 1, -1) == self._steps.view(-1, 1, 1)  # (B, 1, F)
        at = agent.view(1, 1, -1) == torch.arange(N, device=self.device).view(1, -1, 1)
        return can & (hit & at).any(2)

    def _repair_steps(self, breakdown: Tensor) -> Tensor:
        faults = self.scenario.faults
        if isinstance(faults, Breakdowns):
            return torch.full_like(self._fleet.repair_left, faults.repair_steps)
        step, agent, repair = self._schedule
        N = self.num_agents
        hit = (step.view(1, -1) == self._steps.view(-1, 1))  # (B, F)
        at = agent.view(1, 1, -1) == torch.arange(N, device=self.device).view(1, -1, 1)
        longest = torch.where(hit.unsqueeze(1) & at, repair.view(1, 1, -1), 0).max(2).values
        return longest

    # ------------------------------------------------------------------ observations
    def _update_status(self) -> None:
        """The AGVs' status codes (and, with the kernels, their targets) after the fleet or the
        order table changed."""
        f, o = self._fleet, self._orders
        if self._native is None:
            f.status = rules.agent_status(f, o)
            self._targets = None
            return
        B, N, Q = self.num_envs, self.num_agents, o.capacity
        status = torch.empty(B, N, dtype=torch.int8)
        target = torch.empty(B, N, 2, dtype=self.dtype)
        has = torch.empty(B, N, dtype=torch.bool)
        self._native.agv_lifelong_status(
            B, N, Q, pointer(f.order, torch.int64, (B, N), "order"),
            pointer(f.repair_left, torch.int64, (B, N), "repair_left"),
            pointer(o.status, torch.int8, (B, Q), "order status"),
            pointer(o.pickup, torch.float32, (B, Q, 2), "pickup"),
            pointer(o.dropoff, torch.float32, (B, Q, 2), "dropoff"),
            status.data_ptr(), target.data_ptr(), has.data_ptr())
        f.status = status
        self._targets = (target, has)

    def targets(self) -> tuple[Tensor, Tensor]:
        """Each AGV's current target point and whether it has one, (B, N, 2) and (B, N) bool:
        a loaded AGV's drop-off, an assigned AGV's pickup; none for idle or broken AGVs."""
        if self._targets is not None:
            return self._targets
        o, f = self._orders, self._fleet
        B, N = self.num_envs, self.num_agents
        slot = f.order.clamp_min(0).unsqueeze(-1).expand(B, N, 2)
        status = f.status
        drop = o.dropoff.gather(1, slot)
        pick = o.pickup.gather(1, slot)
        target = torch.where((status == rules.CARRYING).unsqueeze(-1), drop, pick)
        has = (status == rules.CARRYING) | (status == rules.TO_PICKUP)
        return target * has.unsqueeze(-1), has

    def observe(self) -> Tensor:
        """Lifelong observations (B, N, O), O = ``obs_layout.size`` at any N (see
        :class:`sim.observations.LifelongObsLayout`)."""
        target, has = self.targets()
        if self._native is not None:
            f, o = self._fleet, self._orders
            obs, self._pair = lifelong_native.lifelong_observe(
                self._agent_pos, self._agent_vel, f.status, f.service_left, target, has,
                o.pickup, o.status, self.obs_layout.k_pickups, self.obs_layout.k_agents,
                self.scenario.sensing_range)
            return obs
        return observe_lifelong(self._agent_pos, self._agent_vel, self._fleet, self._orders,
                                target, has, self.obs_layout, self.scenario.sensing_range,
                                self._pair_distances() if self.obs_layout.k_agents else None,
                                self._eye)

    def global_state(self) -> Tensor:
        """Every AGV's position, velocity, status one-hot and target, (B, N * 11)."""
        target, has = self.targets()
        return lifelong_global_state(self._agent_pos, self._agent_vel, self._fleet.status,
                                     target, has)


def _order_fields(B: int, Q: int) -> list[tuple[str, torch.dtype, tuple[int, ...]]]:
    """The order table's fields in the order of ``agv_insert_generated``'s pointers."""
    i64 = torch.int64
    return [("id", i64, (B, Q)), ("status", torch.int8, (B, Q)),
            ("pickup", torch.float32, (B, Q, 2)), ("dropoff", torch.float32, (B, Q, 2)),
            ("release", i64, (B, Q)), ("priority", i64, (B, Q)), ("deadline", i64, (B, Q)),
            ("agent", i64, (B, Q)), ("picked", i64, (B, Q)), ("finished", i64, (B, Q))]


def _first(mask: Tensor) -> tuple[int, int]:
    idx = mask.nonzero()[0]
    return int(idx[0]), int(idx[1])


def _pad(mask: Tensor, Q: int) -> Tensor:
    if mask.shape[1] == Q:
        return mask
    return torch.cat([mask, mask.new_zeros(mask.shape[0], Q - mask.shape[1])], 1)
