"""The Allocator interface: the :class:`Assignment` result, the protocol, the registry.

Every solver, classical or learned, answers one question: which AGV serves which task. It does
so through ``assign(agents, tasks, world=None) -> Assignment`` and is also a controller for the
simulator (``reset(env)`` / ``act(obs)``), so ``sim.evaluate(allocator.make(name), "6v6")``
scores any registry entry on the same episodes.
"""

from __future__ import annotations

import inspect
import math
import numbers
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from decimal import Decimal
from functools import lru_cache
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from allocator.paths import MAX_COORDINATE

if TYPE_CHECKING:  # pragma: no cover
    from torch import Tensor

    from sim.world import World

__all__ = [
    "Assignment",
    "Allocator",
    "ALLOCATORS",
    "register",
    "make",
    "option_names",
    "check_inputs",
    "as_real_array",
    "ClassicalAllocator",
    "CONTROLLER_OPTIONS",
    "check_controller_options",
    "MAX_COORDINATE",
    "PLAN_OPTIONS",
    "MAX_EXACT_PRIORITY",
    "priority_levels",
    "PlanOptions",
    "check_plan_options",
]

CONTROLLER_OPTIONS = (
    "avoidance", "planner", "max_speed", "brake", "reassign_every", "avoid_tasks",
    "avoidance_options", "waypoint_tolerance", "stuck_steps", "seed",
)
"""The keyword options of :class:`allocator.controller.AllocatorController` (a test keeps this
equal to its signature; listed here so that making an allocator does not import torch)."""


def _is_int(x: object) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _is_positive_real(x: object) -> bool:
    return (isinstance(x, (int, float, np.integer, np.floating))
            and not isinstance(x, (bool, np.bool_)) and math.isfinite(x) and x > 0)


_CONTROLLER_CHECKS: dict[str, tuple[Any, str]] = {
    "avoidance": (lambda x: isinstance(x, (bool, np.bool_)), "True or False"),
    "planner": (lambda x: x in ("auto", "ompl", "prm", "grid"),
                "one of 'auto', 'ompl', 'prm', 'grid'"),
    "max_speed": (lambda x: x is None or _is_positive_real(x), "None or a positive number"),
    "brake": (_is_positive_real, "a positive number"),
    "reassign_every": (lambda x: x is None or (_is_int(x) and x >= 1),
                       "None or a positive integer"),
    "avoid_tasks": (lambda x: isinstance(x, (bool, np.bool_)), "True or False"),
    "avoidance_options": (lambda x: x is None or isinstance(x, dict), "None or a dict"),
    "waypoint_tolerance": (_is_positive_real, "a positive number"),
    "stuck_steps": (lambda x: _is_int(x) and x >= 1, "a positive integer"),
    "seed": (lambda x: _is_int(x) and 0 <= x < 2**32 - 1, "an integer in [0, 2**32 - 1)"),
}


def check_controller_options(options: dict[str, Any]) -> None:
    """Check the values of :data:`CONTROLLER_OPTIONS` when an allocator is made, without
    importing torch (the controller is built later, on the first ``reset``).

    Raises
    ------
    ValueError
        Naming the option and its valid values.
    """
    for key, value in options.items():
        ok, valid = _CONTROLLER_CHECKS[key]
        try:
            good = bool(ok(value))
        except TypeError:  # e.g. an unhashable planner
            good = False
        if not good:
            raise ValueError(f"controller option {key} must be {valid}, got {value!r}")


@dataclass(frozen=True)
class Assignment:
    """Which AGV serves which task, what it costs and how the AGVs get there.

    Attributes
    ----------
    task_of_agent : np.ndarray of int64, shape (N,)
        Task index served by each AGV, or -1 for an idle AGV.
    agent_of_task : np.ndarray of int64, shape (M,)
        AGV index serving each task, or -1 for an unserved task.
    cost : float
        Total travel distance of the plan: straight lines in an open world, obstacle-aware path
        lengths when the world has shelves.
    paths : list of (np.ndarray or None), optional
        Per AGV, the planned waypoints ``(K_i, 2)`` from its position to its task (``None`` for
        an idle AGV); ``None`` as a whole when no path planner was used.
    unserved : dict of int to str
        Why each unserved task is unserved (e.g. ``"no AGV left"`` when M > N, or
        ``"unreachable: ..."`` when the shelves cut it off from every AGV).
    method : str
        Name of the solver that produced it.
    """

    task_of_agent: np.ndarray  # (N,) int64, -1 = idle
    agent_of_task: np.ndarray  # (M,) int64, -1 = unserved
    cost: float
    paths: list[np.ndarray | None] | None = None
    unserved: dict[int, str] = field(default_factory=dict)
    method: str = ""

    def __post_init__(self) -> None:
        t = np.asarray(self.task_of_agent, dtype=np.int64).copy()
        a = np.asarray(self.agent_of_task, dtype=np.int64).copy()
        if t.ndim != 1 or a.ndim != 1:
            raise ValueError(
                f"task_of_agent and agent_of_task must be 1-D, got shapes {t.shape} and {a.shape}"
            )
        n, m = len(t), len(a)
        if np.any((t < -1) | (t >= m)) or np.any((a < -1) | (a >= n)):
            raise ValueError("assignment indices out of range")
        served = np.flatnonzero(t >= 0)
        if not np.array_equal(a[t[served]], served) or np.count_nonzero(a >= 0) != len(served):
            raise ValueError("task_of_agent and agent_of_task are not inverse of each other")
        if self.paths is not None and len(self.paths) != n:
            raise ValueError(f"paths must hold one entry per AGV ({n}), got {len(self.paths)}")
        t.setflags(write=False)
        a.setflags(write=False)
        object.__setattr__(self, "task_of_agent", t)
        object.__setattr__(self, "agent_of_task", a)
        object.__setattr__(self, "cost", float(self.cost))

    @property
    def num_served(self) -> int:
        """Number of (AGV, task) pairs in the plan."""
        return int(np.count_nonzero(self.task_of_agent >= 0))

    def pairs(self) -> np.ndarray:
        """The served ``(agent, task)`` pairs, shape (S, 2), sorted by agent."""
        agents = np.flatnonzero(self.task_of_agent >= 0)
        return np.stack([agents, self.task_of_agent[agents]], axis=1).astype(np.int64)

    @classmethod
    def from_pairs(
        cls,
        rows: np.ndarray,
        cols: np.ndarray,
        num_agents: int,
        num_tasks: int,
        cost: float,
        **kwargs: Any,
    ) -> Assignment:
        """Build an assignment from matched agent indices ``rows`` and task indices ``cols``."""
        task_of_agent = np.full(num_agents, -1, dtype=np.int64)
        agent_of_task = np.full(num_tasks, -1, dtype=np.int64)
        task_of_agent[rows] = cols
        agent_of_task[cols] = rows
        return cls(task_of_agent, agent_of_task, cost, **kwargs)


@runtime_checkable
class Allocator(Protocol):
    """What every registry entry offers.

    ``assign`` plans for one scene; ``reset`` / ``act`` drive the simulator (see
    :func:`sim.evaluate`), so every allocator is also a controller.
    """

    name: str

    def assign(
        self, agents: np.ndarray, tasks: np.ndarray, world: World | None = None
    ) -> Assignment: ...

    def reset(self, env: Any) -> None: ...

    def act(self, obs: Tensor) -> Tensor: ...


ALLOCATORS: dict[str, type] = {}
"""The registry: name -> allocator class (built with :func:`make`)."""

_T = TypeVar("_T", bound=type)


def register(name: str) -> Callable[[_T], _T]:
    """Class decorator adding an allocator class to :data:`ALLOCATORS` under ``name``."""

    def deco(cls: _T) -> _T:
        ALLOCATORS[name] = cls
        cls.name = name
        return cls

    return deco


@lru_cache(maxsize=256)
def _keyword_parameters(cls: type) -> tuple[tuple[str, ...], bool]:
    """The named keyword parameters of ``cls``'s constructor, and whether it takes
    ``**kwargs``."""
    params = inspect.signature(cls).parameters.values()
    named = tuple(
        p.name for p in params
        if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    )
    return named, any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


@lru_cache(maxsize=256)
def _with_controller_options(cls: type) -> tuple[str, ...]:
    """The named keyword parameters of ``cls``'s constructor and :data:`CONTROLLER_OPTIONS`."""
    return tuple(sorted({*_keyword_parameters(cls)[0], *CONTROLLER_OPTIONS}))


def option_names(cls: type) -> tuple[str, ...] | None:
    """The keyword options ``cls(**options)`` accepts, sorted; None when it accepts any.

    A class may declare them with a callable ``option_names()`` attribute (as
    :class:`ClassicalAllocator` does, adding the controller's options); otherwise they are read
    from its constructor's signature, and a constructor taking ``**kwargs`` accepts any.
    """
    declared = getattr(cls, "option_names", None)
    if callable(declared):
        return tuple(sorted(declared()))
    try:
        named, takes_any = _keyword_parameters(cls)
    except (TypeError, ValueError):  # no introspectable signature (e.g. a C type)
        return None
    return None if takes_any else tuple(sorted(named))


def make(name: str, **options: Any) -> Allocator:
    """Build a registered allocator.

    Parameters
    ----------
    name : str
        A key of :data:`ALLOCATORS`, e.g. ``"hungarian"`` or ``"greedy"``.
    **options
        Passed to the allocator's constructor (e.g. ``planner="ompl"``, ``scenario="6v6"``);
        checked against :func:`option_names` before it is built.

    Returns
    -------
    Allocator
        Call ``.assign(agents, tasks, world)`` for a plan, or hand it to ``sim.evaluate``.

    Raises
    ------
    ValueError
        For a name that is not a registered string (the message lists the registered ones),
        or an option the allocator does not take (the message lists the ones it takes); the
        allocator's constructor raises ValueError for a bad option value.

    Examples
    --------
    >>> import allocator
    >>> solver = allocator.make("hungarian")
    >>> solver.assign([[0.0, 0.0], [1.0, 0.0]], [[0.9, 0.0], [0.1, 0.0]]).task_of_agent
    array([1, 0])
    >>> allocator.make("hungarian", plannr="grid")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: unknown option 'plannr' for allocator 'hungarian'; valid options: ...
    """
    if not isinstance(name, str) or name not in ALLOCATORS:
        raise ValueError(
            f"unknown allocator {name!r}: expected a name (str), one of {sorted(ALLOCATORS)}"
        )
    cls = ALLOCATORS[name]
    valid = option_names(cls)
    unknown = [key for key in options if valid is not None and key not in valid]
    if unknown:
        listed = ", ".join(repr(k) for k in unknown)
        raise ValueError(
            f"unknown option{'s' if len(unknown) > 1 else ''} {listed} for allocator {name!r}; "
            f"valid options: {', '.join(valid)}"
        )
    return cls(**options)


def _describe(values: object) -> str:
    """A short description of a value for an error message."""
    text = repr(values)
    return f"{type(values).__name__} {text if len(text) <= 60 else text[:57] + '...'}"


def as_real_array(values: object, what: str, expected: str) -> np.ndarray:
    """``values`` as a float64 array, refusing anything that is not real numbers.

    Parameters
    ----------
    values : array-like
        Numbers: a nested sequence, a numpy array of integers or floats, or a torch tensor
        (detached and copied to the CPU, so ``requires_grad`` is fine).
    what : str
        Name of the argument, for the messages.
    expected : str
        What was expected, for the messages (e.g. ``"an (N, 2) array of real numbers"``).

    Returns
    -------
    np.ndarray of float64
        Same shape as ``values`` (not checked here); ``values`` itself when it already is a
        float64 array.

    Raises
    ------
    ValueError
        For ``None``, ragged sequences, strings, booleans, complex numbers (their imaginary
        part would be dropped), dates, masked entries, or numbers too large for a float.
    """
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(values, torch.Tensor):
        values = values.detach().cpu()
    if np.ma.isMaskedArray(values) and np.ma.is_masked(values):
        raise ValueError(f"{what} must be {expected}: got a masked array with masked entries")
    if values is None:
        raise ValueError(f"{what} must be {expected}, got None")
    try:
        raw = np.asarray(values)
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"{what} must be {expected} (rows of equal length): {err}"
        ) from None
    kind = raw.dtype.kind
    if kind == "O":
        for v in raw.flat:
            if isinstance(v, bool | np.bool_) or not isinstance(v, numbers.Real | Decimal):
                raise ValueError(f"{what} must be {expected}: found {_describe(v)}")
    elif kind not in "iuf":
        why = {"b": "booleans", "c": "complex numbers (the imaginary part would be dropped)",
               "U": "strings", "S": "bytes", "M": "dates", "m": "time spans"}.get(
                   kind, f"dtype {raw.dtype}")
        raise ValueError(f"{what} must be {expected}, got {why}")
    try:
        return np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as err:
        raise ValueError(f"{what} must be {expected}: {err}") from None


def _as_points(points: object, what: str, letter: str) -> np.ndarray:
    arr = as_real_array(points, what, f"an ({letter}, 2) array of real numbers")
    if arr.size == 0:
        raise ValueError(f"{what} is empty: expected at least one row of shape ({letter}, 2)")
    if arr.ndim != 2 or arr.shape[1] != 2:
        hint = " (one point is [[x, y]])" if arr.shape == (2,) else ""
        raise ValueError(f"{what} must have shape ({letter}, 2), got {arr.shape}{hint}")
    if not np.abs(arr).max() <= MAX_COORDINATE:  # also False for NaN
        if not np.all(np.isfinite(arr)):
            bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
            raise ValueError(f"{what} contain NaN or infinite values at rows {bad.tolist()}")
        huge = np.flatnonzero((np.abs(arr) > MAX_COORDINATE).any(axis=1))
        raise ValueError(
            f"{what} rows {huge.tolist()} have coordinates beyond +-{MAX_COORDINATE:g}: their "
            "squared distances would overflow (use smaller units)"
        )
    return arr


def check_inputs(
    agents: object, tasks: object, world: World | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Validate a scene and return ``(agents (N, 2), tasks (M, 2))`` as float64.

    Parameters
    ----------
    agents : array-like, shape (N, 2)
    tasks : array-like, shape (M, 2)
        Real numbers (see :func:`as_real_array`; torch tensors are detached), at most
        :data:`MAX_COORDINATE` in magnitude. Several AGVs (or tasks) may share a position.
    world : World, optional
        A :class:`sim.world.World` (e.g. ``sim.scenarios.warehouse_world()``) or None.

    Raises
    ------
    ValueError
        On a wrong type or shape, an empty array, NaN or infinite values, coordinates beyond
        :data:`MAX_COORDINATE`, a ``world`` that is not a World, or (with a world) a point
        outside the world's bounds or inside a shelf. The message names the array and rows.
    """
    if world is not None:
        from sim.world import World

        if not isinstance(world, World):
            raise ValueError(
                "world must be None or a sim.world.World (e.g. sim.scenarios.warehouse_world())"
                f", got {_describe(world)}"
            )
    a = _as_points(agents, "agents", "N")
    t = _as_points(tasks, "tasks", "M")
    if world is not None:
        world.check_positions(a, "agents")
        world.check_positions(t, "tasks")
    return a, t


MAX_EXACT_PRIORITY = 2**53
"""Float priorities above this may already have lost their last digits (float64 holds every
integer only up to 2**53): pass integers instead."""


def priority_levels(values: object, m: int) -> np.ndarray:
    """Check integer priorities of shape (M,) and return their dense ranks, shape (M,).

    The ranks (0 for the lowest priority given, 1 for the next, ...) order the tasks exactly
    as the priorities do, however large the integers, and stay small, so the costs keep their
    precision next to them. The plans are the same: the tasks a matching can serve form a
    matroid, whose best sets depend only on the order of the priorities.

    Raises
    ------
    ValueError
        For a wrong shape, negative, fractional, non-finite or boolean values, or float values
        beyond :data:`MAX_EXACT_PRIORITY`.
    """
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(values, torch.Tensor):
        values = values.detach().cpu()
    try:
        raw = np.asarray(values)
    except (TypeError, ValueError) as err:
        raise ValueError(f"priorities must be an array of M = {m} integers: {err}") from None
    if raw.shape != (m,):
        raise ValueError(f"priorities must have shape (M,) = ({m},), got {raw.shape}")
    ints = [v for v in raw.tolist() if isinstance(v, int) and not isinstance(v, bool)]
    if raw.dtype.kind not in "iu" and len(ints) != m:
        floats = as_real_array(raw, "priorities", f"an array of M = {m} integers")
        if not np.all(np.isfinite(floats)) or np.any(floats != np.round(floats)):
            raise ValueError("priorities must be non-negative integers")
        if np.any(np.abs(floats) > MAX_EXACT_PRIORITY):
            raise ValueError(
                f"priorities given as floats must be at most 2**53 = {MAX_EXACT_PRIORITY}: "
                "beyond it a float cannot hold every integer (pass integers instead)"
            )
        raw = floats
    elif raw.dtype.kind == "O":
        raw = np.array(ints, dtype=object)
    if np.any(raw < 0):
        raise ValueError("priorities must be non-negative integers")
    return np.unique(raw, return_inverse=True)[1].reshape(m).astype(np.float64)


PLAN_OPTIONS = ("available", "priorities", "ready_positions", "ready_steps", "deadlines",
                "keep", "now", "speed")
"""The per-call options of :func:`allocator.assign` (the scene's state, not the solver's
configuration): see :class:`PlanOptions`."""


@dataclass(frozen=True)
class PlanOptions:
    """The checked per-call options of a one-shot assignment (see :func:`check_plan_options`).

    Attributes
    ----------
    available : np.ndarray of bool, shape (N,)
        AGVs that may be given a task.
    priorities : np.ndarray of int64, shape (M,) or None
        Non-negative priority levels (higher served first).
    ready_positions : np.ndarray of float64, shape (N, 2)
        Where each AGV will be free (its position unless it is busy).
    lag : np.ndarray of float64, shape (N,)
        Steps from ``now`` until each AGV is free (``ready_steps - now``).
    latest : np.ndarray of float64, shape (M,)
        Steps from ``now`` until each task's deadline (``inf`` for none).
    keep_agents, keep_tasks : np.ndarray of int64, shape (K,)
        Pairs that must stay.
    now : int
    speed : float
        World units an AGV covers per step.
    given : tuple of str
        The options the caller gave.
    """

    available: np.ndarray
    priorities: np.ndarray | None
    ready_positions: np.ndarray
    lag: np.ndarray
    latest: np.ndarray
    keep_agents: np.ndarray
    keep_tasks: np.ndarray
    now: int
    speed: float
    given: tuple[str, ...]

    @property
    def has_deadlines(self) -> bool:
        return bool(np.isfinite(self.latest).any())

    def eta(self, travel: np.ndarray) -> np.ndarray:
        """Steps from now until AGV i reaches task j, (N, M): its lag plus ``travel / speed``."""
        return self.lag[:, None] + travel / self.speed

    def cost(self, travel: np.ndarray, lateness_weight: float = 1.0) -> np.ndarray:
        """The cost each solver minimises, (N, M), in world units: ``speed * eta`` plus
        ``lateness_weight * speed`` per step an AGV would reach a task past its deadline;
        ``inf`` for an unavailable AGV. Equal to ``travel`` when no option is given."""
        cost = travel + (self.speed * self.lag)[:, None]
        if self.has_deadlines and lateness_weight:
            late = self.eta(travel) - self.latest[None, :]
            with np.errstate(invalid="ignore"):
                cost = cost + lateness_weight * self.speed * np.where(late > 0, late, 0.0)
        return np.where(self.available[:, None], cost, np.inf)

    def levels(self, travel: np.ndarray) -> np.ndarray | None:
        """Exact service levels per task (M,), or None without priorities and deadlines:
        ``priority * (M + 1) + meetable``, where ``meetable`` says a task's deadline can still
        be met by an available AGV; so higher priorities are served first, then tasks whose
        deadline can be met, then the rest."""
        if self.priorities is None and not self.has_deadlines:
            return None
        m = travel.shape[1]
        p = np.zeros(m) if self.priorities is None else self.priorities.astype(np.float64)
        out = p * (m + 1)
        if self.has_deadlines and self.available.any():
            eta = self.eta(travel)[self.available]
            out = out + (np.isfinite(self.latest) & (eta.min(axis=0) <= self.latest))
        return out


def _int_vector(values: object, name: str, length: int, letter: str) -> np.ndarray:
    """``values`` as an int64 vector of the given length, or a ValueError naming ``name``."""
    raw = as_real_array(values, name, f"an ({letter},) = ({length},) array of integers")
    if raw.shape != (length,):
        raise ValueError(f"{name} must have shape ({letter},) = ({length},), got {raw.shape}")
    if not np.isfinite(raw).all():
        bad = np.flatnonzero(~np.isfinite(raw))
        raise ValueError(f"{name} holds NaN or infinite values at {bad[:8].tolist()}")
    if np.any(raw != np.round(raw)):
        bad = np.flatnonzero(raw != np.round(raw))
        raise ValueError(f"{name} must hold integers (steps), got {raw[bad[0]]!r} at "
                         f"{int(bad[0])}")
    if np.any(np.abs(raw) > 2**53):
        raise ValueError(f"{name} holds values beyond 2**53")
    return raw.astype(np.int64)


def check_plan_options(
    agents: np.ndarray,
    tasks: np.ndarray,
    world: World | None = None,
    available: object = None,
    priorities: object = None,
    ready_positions: object = None,
    ready_steps: object = None,
    deadlines: object = None,
    keep: object = None,
    now: object = 0,
    speed: object = 1.0,
) -> PlanOptions:
    """Check the per-call options of a one-shot assignment (:func:`allocator.assign`).

    Parameters
    ----------
    agents : np.ndarray, shape (N, 2)
        The checked AGV positions (:func:`check_inputs`).
    tasks : np.ndarray, shape (M, 2)
    world : World, optional
    available : array-like of bool, shape (N,), optional
        AGVs that may be given a task (default all).
    priorities : array-like of int, shape (M,), optional
        Non-negative integer priorities (higher served first when not every task can be).
    ready_positions : array-like, shape (N, 2), optional
        Where each AGV will be free: a busy AGV's drop-off (default its position).
    ready_steps : array-like of int, shape (N,), optional
        The step at which each AGV is free there, >= ``now`` (default ``now``).
    deadlines : array-like of int, shape (M,), optional
        The step by which each task should be reached, -1 for none.
    keep : array-like of int, shape (K, 2), optional
        ``(agent, task)`` pairs that must stay (e.g. loaded AGVs); each agent available, no
        agent or task twice.
    now : int
        The current step (>= 0).
    speed : float
        World units an AGV covers per step (> 0), to turn steps into travel.

    Returns
    -------
    PlanOptions

    Raises
    ------
    ValueError
        Naming the option: a wrong shape or dtype, NaN, non-integer steps, a ready step in the
        past, a negative deadline other than -1, a keep pair out of range, naming an
        unavailable AGV, or repeating an AGV or a task.
    """
    n, m = len(agents), len(tasks)
    given = tuple(name for name, v in (
        ("available", available), ("priorities", priorities),
        ("ready_positions", ready_positions), ("ready_steps", ready_steps),
        ("deadlines", deadlines), ("keep", keep)) if v is not None)
    if isinstance(now, (bool, np.bool_)) or not _is_int(now) or now < 0:
        raise ValueError(f"now must be an integer step >= 0, got {now!r}")
    now = int(now)
    if not _is_positive_real(speed):
        raise ValueError(f"speed must be a positive number (world units per step), got "
                         f"{speed!r}")
    if available is None:
        mask = np.ones(n, dtype=bool)
    else:
        torch = sys.modules.get("torch")
        if torch is not None and isinstance(available, torch.Tensor):
            available = available.detach().cpu().numpy()
        raw = np.asarray(available)
        if raw.dtype != np.bool_:
            raise ValueError(f"available must be an (N,) = ({n},) array of booleans, got "
                             f"dtype {raw.dtype}")
        if raw.shape != (n,):
            raise ValueError(f"available must have shape (N,) = ({n},), got {raw.shape}")
        mask = raw.copy()
    levels = None if priorities is None else priority_levels(priorities, m).astype(np.int64)
    if ready_positions is None:
        ready = agents
    else:
        ready = _as_points(ready_positions, "ready_positions", "N")
        if ready.shape != (n, 2):
            raise ValueError(f"ready_positions must have shape (N, 2) = ({n}, 2) like agents, "
                             f"got {ready.shape}")
        if world is not None:
            world.check_positions(ready, "ready_positions")
    if ready_steps is None:
        lag = np.zeros(n)
    else:
        steps = _int_vector(ready_steps, "ready_steps", n, "N")
        past = np.flatnonzero(steps < now)
        if past.size:
            raise ValueError(f"ready_steps[{int(past[0])}] = {int(steps[past[0]])} is in the "
                             f"past (now = {now}): an AGV is free at now or later")
        lag = (steps - now).astype(np.float64)
    latest = np.full(m, np.inf)
    if deadlines is not None:
        due = _int_vector(deadlines, "deadlines", m, "M")
        bad = np.flatnonzero(due < -1)
        if bad.size:
            raise ValueError(f"deadlines must be steps >= 0 or -1 (none), got "
                             f"{int(due[bad[0]])} at {int(bad[0])}")
        latest = np.where(due >= 0, (due - now).astype(np.float64), np.inf)
    keep_a = keep_t = np.zeros(0, dtype=np.int64)
    if keep is not None:
        raw = as_real_array(keep, "keep", "a (K, 2) array of (agent, task) index pairs")
        if raw.size == 0:
            raw = raw.reshape(0, 2)
        if raw.ndim != 2 or raw.shape[1] != 2:
            raise ValueError(f"keep must have shape (K, 2) of (agent, task) pairs, got "
                             f"{raw.shape}")
        if not np.isfinite(raw).all() or np.any(raw != np.round(raw)):
            raise ValueError("keep must hold integer (agent, task) index pairs")
        pairs = raw.astype(np.int64)
        keep_a, keep_t = pairs[:, 0], pairs[:, 1]
        out = np.flatnonzero((keep_a < 0) | (keep_a >= n) | (keep_t < 0) | (keep_t >= m))
        if out.size:
            raise ValueError(f"keep pair {pairs[out[0]].tolist()} is out of range (N = {n}, "
                             f"M = {m})")
        off = np.flatnonzero(~mask[keep_a])
        if off.size:
            raise ValueError(f"keep pair {pairs[off[0]].tolist()} names AGV "
                             f"{int(keep_a[off[0]])}, which is not available")
        for what, idx in (("AGV", keep_a), ("task", keep_t)):
            uniq, counts = np.unique(idx, return_counts=True)
            if (counts > 1).any():
                raise ValueError(f"keep names {what} {int(uniq[counts > 1][0])} twice")
    return PlanOptions(available=mask, priorities=levels, ready_positions=ready, lag=lag,
                       latest=latest, keep_agents=keep_a, keep_tasks=keep_t, now=now,
                       speed=float(speed), given=given)


def solve_with_options(
    travel: np.ndarray,
    options: PlanOptions,
    solve: Callable[[np.ndarray, np.ndarray | None, np.ndarray],
                    tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """Matched (rows, cols) under the plan options: the kept pairs fixed, the others solved
    by ``solve(cost, levels)`` on the remaining AGVs and tasks.

    Parameters
    ----------
    travel : np.ndarray, shape (N, M)
        Travel from each AGV's ready position to each task (``inf``: unreachable).
    options : PlanOptions
    solve : callable
        ``solve(cost (n', m'), levels (m',) or None, tasks (m',)) -> (rows, cols)`` on the
        sub-problem of the AGVs and tasks not kept (``tasks``: their indices).

    Returns
    -------
    rows, cols : np.ndarray of int64
        Matched agent and task indices, sorted by agent; only finite-cost pairs besides the
        kept ones.
    """
    n, m = travel.shape
    cost = options.cost(travel)
    levels = options.levels(travel)
    rest_a = np.setdiff1d(np.arange(n), options.keep_agents)
    rest_t = np.setdiff1d(np.arange(m), options.keep_tasks)
    sub = cost[np.ix_(rest_a, rest_t)]
    rows, cols = solve(sub, None if levels is None else levels[rest_t], rest_t)
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    ok = np.isfinite(sub[rows, cols]) if rows.size else np.zeros(0, dtype=bool)
    rows, cols = rows[ok], cols[ok]
    rows = np.concatenate([options.keep_agents, rest_a[rows]]).astype(np.int64)
    cols = np.concatenate([options.keep_tasks, rest_t[cols]]).astype(np.int64)
    order = np.argsort(rows, kind="stable")
    return rows[order], cols[order]


class ClassicalAllocator:
    """Shared base of the centralized allocators: ``assign`` plus the controller methods.

    ``reset(env)`` and ``act(obs)`` delegate to an :class:`allocator.controller.
    AllocatorController` built on first use with ``controller_options``.

    Parameters
    ----------
    **controller_options
        Passed to :class:`~allocator.controller.AllocatorController` (``avoidance``,
        ``planner``, ``max_speed``, ...: :data:`CONTROLLER_OPTIONS`).

    Raises
    ------
    ValueError
        For an option that is neither the class's own nor the controller's (the message lists
        the valid ones).
    """

    name = "classical"
    supports_plan_options = True
    """Whether :meth:`assign` takes the :data:`PLAN_OPTIONS` (learned allocators do not)."""

    def __init__(self, **controller_options: Any) -> None:
        unknown = [key for key in controller_options if key not in CONTROLLER_OPTIONS]
        if unknown:
            listed = ", ".join(repr(k) for k in unknown)
            raise ValueError(
                f"unknown option{'s' if len(unknown) > 1 else ''} {listed} for "
                f"{type(self).__name__}; valid options: {', '.join(self.option_names())}"
            )
        check_controller_options(controller_options)
        self.controller_options = controller_options
        self._controller: Any = None

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The constructor's own keyword options and the controller's, sorted."""
        return _with_controller_options(cls)

    def assign(
        self, agents: np.ndarray, tasks: np.ndarray, world: World | None = None
    ) -> Assignment:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def controller(self) -> Any:
        """The :class:`~allocator.controller.AllocatorController` driving the simulator."""
        if self._controller is None:
            from allocator.controller import AllocatorController

            self._controller = AllocatorController(self, **self.controller_options)
        return self._controller

    def lifelong_dispatcher(self) -> Any:
        """The dispatcher that drives a lifelong env for this allocator
        (:mod:`allocator.dispatch`); None where the allocator has none."""
        return None

    def reset(self, env: Any) -> None:
        """Plan for every environment of ``env`` (called by ``sim.evaluate`` after a reset, and
        by ``sim.evaluate_lifelong`` once per batch of lifelong runs)."""
        self._dispatcher = None
        if getattr(env, "lifelong", False):
            dispatcher = self.lifelong_dispatcher()
            if dispatcher is None:
                raise ValueError(f"{type(self).__name__} has no lifelong dispatcher; lifelong "
                                 "floors are dispatched by 'hungarian', 'greedy', 'fifo' and "
                                 "'auction'")
            dispatcher.reset(env)
            self._dispatcher = dispatcher
            return
        self.controller.reset(env)

    def act(self, obs: Tensor) -> Tensor:
        """Actions (B, N, 2) in [-1, 1] for the environment given to :meth:`reset`."""
        if getattr(self, "_dispatcher", None) is not None:
            return self._dispatcher.act(obs)
        return self.controller.act(obs)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
