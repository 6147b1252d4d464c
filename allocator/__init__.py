"""Task allocation for AGV fleets: one interface, classical and learned solvers.

>>> import allocator
>>> result = allocator.assign([[0.0, 0.0], [1.0, 1.0]], [[1.0, 0.9], [0.1, 0.0]])
>>> result.task_of_agent        # AGV i serves task task_of_agent[i] (-1: idle)
array([1, 0])

Heavy dependencies (OMPL, cvxpy, osqp, torch) are imported on first use only.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

import numpy as np

from allocator.base import ALLOCATORS, Allocator, Assignment, ClassicalAllocator, make, register
from allocator.greedy import GreedyAllocator
from allocator.hungarian import HungarianAllocator

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
]

# --- Hook for the learned allocators ("maddpg-ipf", "bicnet-greedy", ...). ------------------
# allocator/learned.py (owned by the learners engineer) adds its classes to ALLOCATORS when
# imported, e.g. ``ALLOCATORS["maddpg-ipf"] = ...`` or through ``register(name)``. Only a
# missing module is tolerated here; any other error inside it surfaces.
try:
    _learned = importlib.import_module("allocator.learned")
except ModuleNotFoundError as _err:  # pragma: no cover - until learned.py exists
    if _err.name != "allocator.learned":
        raise
else:  # pragma: no cover
    if callable(getattr(_learned, "register_all", None)):
        _learned.register_all(ALLOCATORS)
# ----------------------------------------------------------------------------------------------


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
        AGV positions in world units.
    tasks : array-like, shape (M, 2)
        Task positions; M may differ from N.
    method : str
        A key of :data:`ALLOCATORS` (default ``"hungarian"``, the optimum).
    world : World, optional
        Shelves make costs obstacle-aware; positions are checked against bounds and shelves.
    **options
        Constructor options of the solver (e.g. ``planner="ompl"`` to get paths).

    Returns
    -------
    Assignment
        ``task_of_agent`` (N,) task per AGV or -1, ``agent_of_task`` (M,) AGV per task or -1,
        ``cost`` the total travel distance, ``paths`` per-AGV waypoints when a planner was
        used, ``unserved`` the reason per unserved task.

    Raises
    ------
    ValueError
        On bad input or an unknown method.

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
