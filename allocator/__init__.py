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

from allocator.base import ALLOCATORS, Allocator, Assignment, ClassicalAllocator, make, register
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
    "FloorDistances",
    "segments_clear",
    "AuctionResult",
    "decentralized_auction",
    "FifoDispatcher",
    "HungarianDispatcher",
]

_LAZY = {  # imported on first use (scipy's graph and spatial modules, torch)
    "FloorDistances": ("allocator.distances", "FloorDistances"),
    "segments_clear": ("allocator.distances", "segments_clear"),
    "AuctionResult": ("allocator.auction", "AuctionResult"),
    "decentralized_auction": ("allocator.auction", "auction"),
    "FifoDispatcher": ("allocator.dispatch", "FifoDispatcher"),
    "HungarianDispatcher": ("allocator.dispatch", "HungarianDispatcher"),
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
    **options
        Constructor options of the solver (e.g. ``planner="ompl"`` to get paths), checked when
        it is made (see :func:`allocator.base.make`).

    Returns
    -------
    Assignment
        ``task_of_agent`` (N,) task per AGV or -1, ``agent_of_task`` (M,) AGV per task or -1,
        ``cost`` the total travel distance, ``paths`` per-AGV waypoints when a planner was
        used, ``unserved`` the reason per unserved task.

    Raises
    ------
    ValueError
        On an unknown method or option, a bad option value, a ``world`` that is not a World,
        or bad positions: not an (N, 2) array of real numbers (None, ragged rows, strings,
        booleans, complex numbers, masked entries), empty, NaN or infinite, beyond 1e150,
        outside the world or inside a shelf. The message names the argument.

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
    """
    return make(method, **options).assign(agents, tasks, world=world)
