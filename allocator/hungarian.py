"""The optimal assignment (Hungarian / Jonker-Volgenant via scipy's ``linear_sum_assignment``).

Costs are straight-line distances in an open world and obstacle-aware path lengths when the
world has shelves (:func:`allocator.paths.travel_costs`). A task no AGV can reach is left
unserved with the reason; it is never matched at infinite cost.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from allocator.base import Assignment, ClassicalAllocator, check_inputs, register
from allocator.paths import travel_costs

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["HungarianAllocator", "solve_cost_matrix", "plan_paths", "unserved_reasons"]

UNREACHABLE = "unreachable: no AGV can reach this task (shelves or walls cut it off)"
NO_AGENT_LEFT = "no AGV left: every AGV serves another task"


def _check_task_vector(values: object, m: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} must be an array of M = {m} numbers: {err}") from None
    if arr.shape != (m,):
        raise ValueError(f"{what} must have shape (M,) = ({m},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} contain NaN or infinite values")
    return arr


def solve_cost_matrix(
    cost: np.ndarray,
    weights: np.ndarray | None = None,
    priorities: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Optimal matching of a (N, M) cost matrix that may hold ``inf`` (forbidden pairs).

    The matching serves as many pairs with finite cost as possible; among those, the largest
    total priority of served tasks; among those, the least total ``weights[j] * cost[i, j]``.

    Parameters
    ----------
    cost : np.ndarray, shape (N, M)
        Non-negative travel costs, ``inf`` for a pair that cannot be served.
    weights : np.ndarray, shape (M,), optional
        Positive per-task cost multipliers (default 1).
    priorities : np.ndarray, shape (M,), optional
        Non-negative integer priority levels (higher is served first when M > N).

    Returns
    -------
    rows, cols : np.ndarray of int64
        Matched agent and task indices, only pairs with finite cost.
    """
    n, m = cost.shape
    obj = cost if weights is None else cost * weights[None, :]
    finite = np.isfinite(obj)
    if priorities is None and finite.all():
        rows, cols = linear_sum_assignment(obj)
        return rows.astype(np.int64), cols.astype(np.int64)
    k = min(n, m)
    top = float(obj[finite].max()) if finite.any() else 0.0
    span = k * top + 1.0  # any set of finite pairs costs less than this
    work = np.where(finite, obj, 0.0)
    max_priority = 0.0
    if priorities is not None:
        work = work - span * priorities[None, :]
        max_priority = float(priorities.max())
    # Larger than any change of the finite part: serving one more pair always wins.
    unreachable = span * (2.0 + k * max_priority)
    work = np.where(finite, work, unreachable)
    rows, cols = linear_sum_assignment(work)
    keep = finite[rows, cols]
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)


def unserved_reasons(cost: np.ndarray, agent_of_task: np.ndarray) -> dict[int, str]:
    """Why each unserved task (``agent_of_task == -1``) is unserved."""
    reachable = np.isfinite(cost).any(axis=0)
    return {
        int(j): (NO_AGENT_LEFT if reachable[j] else UNREACHABLE)
        for j in np.flatnonzero(agent_of_task < 0)
    }


def plan_paths(
    agents: np.ndarray,
    tasks: np.ndarray,
    task_of_agent: np.ndarray,
    world: World | None,
    planner: Any,
) -> list[np.ndarray | None]:
    """Waypoints from every served AGV to its task (None for idle AGVs).

    ``planner`` has ``plan(start, goal) -> (K, 2) | None``; in an open world (or without a
    planner) the path is the straight segment.
    """
    out: list[np.ndarray | None] = []
    for i, j in enumerate(task_of_agent):
        if j < 0:
            out.append(None)
        elif planner is None or world is None or not world.has_obstacles:
            out.append(np.stack([agents[i], tasks[j]]))
        else:
            out.append(planner.plan(agents[i], tasks[j]))
    return out


def _make_planner(kind: str | None, world: World | None, seed: int) -> Any:
    if kind is None or world is None or not world.has_obstacles:
        return None
    if kind == "grid":
        from allocator.paths import grid_for

        return grid_for(world)
    if kind in ("ompl", "rrtconnect", "prm"):
        from allocator.paths import OMPLPlanner

        return OMPLPlanner(world, planner="prm" if kind == "prm" else "rrtconnect", seed=seed)
    raise ValueError(
        f"planner must be None, 'grid', 'ompl' (RRTConnect) or 'prm', got {kind!r}"
    )


@register("hungarian")
class HungarianAllocator(ClassicalAllocator):
    """Minimum total travel distance assignment.

    Parameters
    ----------
    planner : {None, "grid", "ompl", "prm"}
        Plan a path for every served AGV in :meth:`assign` (None: no paths in the result).
        The controller plans its own paths whatever this is.
    resolution : float
        Cell size of the occupancy grid used for obstacle-aware costs.
    seed : int
        Seed of the OMPL planner.
    **controller_options
        Passed to :class:`~allocator.controller.AllocatorController` when the allocator is
        used as a controller (``avoidance``, ``planner``, ``max_speed``, ...).
    """

    name = "hungarian"

    def __init__(
        self,
        planner: str | None = None,
        resolution: float = 0.05,
        seed: int = 0,
        **controller_options: Any,
    ) -> None:
        super().__init__(**controller_options)
        if planner not in (None, "grid", "ompl", "rrtconnect", "prm"):
            raise ValueError(
                f"planner must be None, 'grid', 'ompl' (RRTConnect) or 'prm', got {planner!r}"
            )
        self.planner = planner
        self.resolution = resolution
        self.seed = seed
        self._planners: dict[int, Any] = {}

    def cost_matrix(
        self, agents: np.ndarray, tasks: np.ndarray, world: World | None = None
    ) -> np.ndarray:
        """The (N, M) travel costs the assignment minimises (``inf``: unreachable)."""
        return travel_costs(agents, tasks, world, self.resolution)

    def assign(
        self,
        agents: np.ndarray,
        tasks: np.ndarray,
        world: World | None = None,
        *,
        weights: np.ndarray | None = None,
        priorities: np.ndarray | None = None,
    ) -> Assignment:
        """Optimal assignment of N AGVs to M tasks (N and M may differ).

        Parameters
        ----------
        agents : array-like, shape (N, 2)
            AGV positions in world units.
        tasks : array-like, shape (M, 2)
            Task positions.
        world : World, optional
            With shelves, costs are obstacle-aware path lengths; positions are checked against
            its bounds and shelves.
        weights : array-like, shape (M,), optional
            Positive per-task multipliers of the travel cost (urgent tasks weigh more).
        priorities : array-like of int, shape (M,), optional
            Priority levels; when M > N, higher levels are served first.

        Returns
        -------
        Assignment
            ``task_of_agent[i]`` is the task AGV i should go to (-1: idle),
            ``agent_of_task[j]`` the AGV serving task j (-1: unserved, with the reason in
            ``unserved[j]``), ``cost`` the total travel distance (unweighted). ``min(N, M)``
            pairs are served unless shelves cut tasks off.

        Raises
        ------
        ValueError
            On a wrong shape, an empty array, NaN or infinite positions, positions outside the
            world or inside a shelf, or bad weights / priorities.

        Examples
        --------
        >>> import allocator
        >>> agents = [[0.0, 0.0], [2.0, 0.0]]
        >>> tasks = [[2.0, 1.0], [0.0, 1.0], [5.0, 5.0]]
        >>> result = allocator.make("hungarian").assign(agents, tasks)
        >>> result.task_of_agent, result.agent_of_task, round(result.cost, 3)
        (array([1, 0]), array([ 1,  0, -1]), 2.0)
        >>> result.unserved
        {2: 'no AGV left: every AGV serves another task'}
        """
        agents, tasks = check_inputs(agents, tasks, world)
        m = len(tasks)
        w = p = None
        if weights is not None:
            w = _check_task_vector(weights, m, "weights")
            if np.any(w <= 0):
                raise ValueError("weights must be positive")
        if priorities is not None:
            p = _check_task_vector(priorities, m, "priorities")
            if np.any(p < 0) or np.any(p != np.round(p)):
                raise ValueError("priorities must be non-negative integers")
        cost = self.cost_matrix(agents, tasks, world)
        rows, cols = solve_cost_matrix(cost, w, p)
        result_cost = float(cost[rows, cols].sum())
        task_of_agent = np.full(len(agents), -1, dtype=np.int64)
        task_of_agent[rows] = cols
        paths = None
        if self.planner is not None:
            paths = plan_paths(agents, tasks, task_of_agent, world, self._planner_for(world))
        agent_of_task = np.full(m, -1, dtype=np.int64)
        agent_of_task[cols] = rows
        return Assignment(
            task_of_agent, agent_of_task, result_cost, paths=paths,
            unserved=unserved_reasons(cost, agent_of_task) if len(cols) < m else {},
            method=self.name,
        )

    def _planner_for(self, world: World | None) -> Any:
        if world is None or not world.has_obstacles:
            return None
        key = id(world)
        if key not in self._planners:
            self._planners = {key: _make_planner(self.planner, world, self.seed)}
            self._planner_world = world  # keep the id valid
        return self._planners[key]

    def __repr__(self) -> str:
        return f"HungarianAllocator(planner={self.planner!r})"
