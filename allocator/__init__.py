"""Task allocation for AGV fleets: one interface, classical and learned solvers.

>>> import allocator
>>> result = allocator.assign([[0.0, 0.0], [1.0, 1.0]], [[1.0, 0.9], [0.1, 0.0]])
>>> result.task_of_agent        # AGV i serves task task_of_agent[i] (-1: idle)
array([1, 0])

Heavy dependencies (OMPL, cvxpy, osqp, torch) are imported on first use only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from allocator.auction_allocator import AuctionAllocator
from allocator.base import (
    ALLOCATORS,
    Allocator,
    Assignment,
    ClassicalAllocator,
    make,
    register,
)
from allocator.fifo import FifoAllocator
from allocator.greedy import GreedyAllocator
from allocator.hungarian import HungarianAllocator
from allocator.learned import register_all as _register_learned

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = [
    "Assignment",
    "Allocator",
    "ALLOCATORS",
    "make",
    "assign",
    "register",
    "ClassicalAllocator",
    "HungarianAllocator",
    "GreedyAllocator",
    "FifoAllocator",
    "AuctionAllocator",
    "FloorDistances",
    "segments_clear",
    "AuctionResult",
    "decentralized_auction",
    "FifoDispatcher",
    "HungarianDispatcher",
    "AuctionDispatcher",
    "MatchingDispatcher",
    "WaypointDriver",
    "SafeDriver",
    "BrakingShield",
    "SafetyShield",
]

_LAZY = {  # imported on first use (scipy's graph and spatial modules, torch)
    "FloorDistances": ("allocator.distances", "FloorDistances"),
    "segments_clear": ("allocator.distances", "segments_clear"),
    "AuctionResult": ("allocator.auction", "AuctionResult"),
    "decentralized_auction": ("allocator.auction", "auction"),
    "FifoDispatcher": ("allocator.dispatch", "FifoDispatcher"),
    "HungarianDispatcher": ("allocator.dispatch", "HungarianDispatcher"),
    "AuctionDispatcher": ("allocator.dispatch", "AuctionDispatcher"),
    "MatchingDispatcher": ("allocator.dispatch", "MatchingDispatcher"),
    "WaypointDriver": ("allocator.dispatch", "WaypointDriver"),
    "SafeDriver": ("allocator.traffic", "SafeDriver"),
    "BrakingShield": ("allocator.avoidance.braking", "BrakingShield"),
    "SafetyShield": ("allocator.shield", "SafetyShield"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'allocator' has no attribute {name!r}")

_register_learned(ALLOCATORS)


def assign(
    agents: np.ndarray,
    tasks: np.ndarray,
    method: str = "hungarian",
    world: World | None = None,
    available: np.ndarray | None = None,
    priorities: np.ndarray | None = None,
    ready_positions: np.ndarray | None = None,
    ready_steps: np.ndarray | None = None,
    deadlines: np.ndarray | None = None,
    keep: np.ndarray | None = None,
    **options: Any,
) -> Assignment:
    """Assign N AGVs to M tasks with a registered solver.

    Parameters
    ----------
    agents : array-like, shape (N, 2)
        AGV positions in world units: real numbers (a torch tensor is detached), at most
        :data:`allocator.paths.MAX_COORDINATE` (1e150) in magnitude, so that squared distances
        cannot overflow (larger coordinates are rejected). N >= 1; several AGVs may share a
        position (they are then interchangeable; the solver picks which serves, the same way
        every time).
    tasks : array-like, shape (M, 2)
        Task positions, likewise; M >= 1 and may differ from N.
    method : str
        A key of :data:`ALLOCATORS` (default ``"hungarian"``, the optimum).
    world : World, optional
        A :class:`sim.world.World`; shelves make costs obstacle-aware; positions are checked
        against bounds and shelves.
    available : array-like of bool, shape (N,), optional
        AGVs that may be given a task (default all); the others get -1.
    priorities : array-like of int, shape (M,), optional
        Non-negative integer priorities: when not every task can be served, higher ones are
        served first (exactly, at any size).
    ready_positions : array-like, shape (N, 2), optional
        Where each AGV will be free: a busy AGV's drop-off (default its position). The plan
        is then its next task, and travel is counted from there.
    ready_steps : array-like of int, shape (N,), optional
        The step at which each AGV is free at its ready position, >= ``now`` (default
        ``now``): a later AGV costs ``speed`` world units more per step.
    deadlines : array-like of int, shape (M,), optional
        The step by which each task should be reached (-1: none). Among tasks of equal
        priority, those whose deadline an available AGV can still meet are served first;
        every step an AGV would arrive late costs ``speed`` world units.
    keep : array-like of int, shape (K, 2), optional
        ``(agent, task)`` pairs that must stay in the plan (e.g. loaded AGVs).
    **options
        ``now`` (int, the current step, default 0) and ``speed`` (world units per step,
        default 1.0) for the step-valued options; ``weights`` for ``"hungarian"``; everything
        else goes to the solver's constructor (e.g. ``planner="ompl"``, ``comm_range=2.0``),
        checked when it is made (see :func:`allocator.base.make`).

    Returns
    -------
    Assignment
        ``task_of_agent`` (N,) task per AGV or -1, ``agent_of_task`` (M,) AGV per task or -1,
        ``cost`` the total travel distance (from the ready positions), ``paths`` per-AGV
        waypoints when a planner was used, ``unserved`` the reason per unserved task.

    Raises
    ------
    ValueError
        On an unknown method or option, a bad option value, a ``world`` that is not a World,
        or bad positions: not an (N, 2) array of real numbers (None, ragged rows, strings,
        booleans, complex numbers, masked entries), empty, NaN or infinite, beyond 1e150,
        outside the world or inside a shelf; plan options of the wrong shape or dtype, NaN,
        non-integer steps, a ready step in the past, a keep pair naming an unavailable AGV;
        plan options given to a learned allocator (it does not take them). The message names
        the argument.

    Examples
    --------
    >>> import numpy as np, allocator
    >>> agents = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    >>> tasks = np.array([[2.0, 0.5], [0.0, 0.5]])
    >>> r = allocator.assign(agents, tasks)
    >>> r.agent_of_task, r.task_of_agent
    (array([2, 0]), array([ 1, -1,  0]))
    >>> for agent, task in r.pairs():
    ...     print(f"AGV {agent} -> task {task}")
    AGV 0 -> task 1
    AGV 2 -> task 0

    AGV 2 is busy until step 10 at (0, 0); AGV 0 is charging; task 1 is due at step 3:

    >>> r = allocator.assign(agents, tasks, available=[False, True, True],
    ...                      ready_positions=[[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]],
    ...                      ready_steps=[0, 0, 10], deadlines=[-1, 3])
    >>> r.task_of_agent
    array([-1,  1,  0])
    """
    plan = {name: value for name, value in (
        ("available", available), ("priorities", priorities),
        ("ready_positions", ready_positions), ("ready_steps", ready_steps),
        ("deadlines", deadlines), ("keep", keep)) if value is not None}
    for name in ("now", "speed", "weights"):
        if name in options:
            plan[name] = options.pop(name)
    solver = make(method, **options)
    if plan and not getattr(solver, "supports_plan_options", False):
        raise ValueError(
            f"allocator {method!r} does not support the plan options "
            f"{', '.join(sorted(plan))}: a learned policy assigns from positions only; use "
            "'hungarian', 'greedy', 'fifo' or 'auction' for them"
        )
    if "weights" in plan and method != "hungarian":
        raise ValueError(f"weights is an option of 'hungarian' only, not of {method!r}")
    return solver.assign(agents, tasks, world=world, **plan)
