"""The optimal assignment (Hungarian / Jonker-Volgenant via scipy's ``linear_sum_assignment``).

Costs are straight-line distances in an open world and obstacle-aware path lengths when the
world has shelves (:func:`allocator.paths.travel_costs`). A task no AGV can reach is left
unserved with the reason; it is never matched at infinite cost.
"""

from __future__ import annotations

import numbers
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from allocator.base import (
    MAX_EXACT_PRIORITY,
    Assignment,
    ClassicalAllocator,
    as_real_array,
    check_inputs,
    check_plan_options,
    priority_levels,
    register,
    solve_with_options,
)
from allocator.paths import travel_costs

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = [
    "HungarianAllocator", "solve_cost_matrix", "check_cost_matrix", "priority_levels",
    "plan_paths", "unserved_reasons", "PLANNERS", "MAX_EXACT_PRIORITY",
]

UNREACHABLE = "unreachable: no AGV can reach this task (shelves or walls cut it off)"
NO_AGENT_LEFT = "no AGV left: every AGV serves another task"


PLANNERS = (None, "grid", "ompl", "rrtconnect", "prm")
"""Values of the ``planner`` option of the classical allocators (``"ompl"``: RRTConnect)."""


def check_planner_options(planner: object, resolution: object, seed: object) -> None:
    """Validate the ``planner``, ``resolution`` and ``seed`` options of a classical allocator.

    Raises
    ------
    ValueError
        Naming the option and what it accepts.
    """
    if not (planner is None or isinstance(planner, str) and planner in PLANNERS):
        raise ValueError(
            f"planner must be one of {list(PLANNERS)} (None: no paths; 'ompl' is RRTConnect), "
            f"got {planner!r}"
        )
    if isinstance(resolution, bool) or not isinstance(resolution, numbers.Real) or not (
        np.isfinite(float(resolution)) and float(resolution) > 0
    ):
        raise ValueError(f"resolution must be a positive number (world units), got {resolution!r}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not (
        0 <= int(seed) < 2**32 - 1
    ):
        raise ValueError(f"seed must be an integer in [0, 2**32 - 1) (OMPL's RNG seed), "
                         f"got {seed!r}")


def check_cost_matrix(cost: object) -> np.ndarray:
    """Validate a travel-cost matrix and return it as float64 (not copied if it already is).

    Parameters
    ----------
    cost : array-like, shape (N, M)
        Real numbers; ``+inf`` marks a forbidden pair.

    Returns
    -------
    np.ndarray of float64, shape (N, M)

    Raises
    ------
    ValueError
        If ``cost`` is not a 2-D array of real numbers, or holds NaN or ``-inf``.
    """
    arr = as_real_array(cost, "cost", "an (N, M) matrix of real numbers")
    if arr.ndim != 2:
        raise ValueError(f"cost must be a 2-D (N, M) matrix, got shape {arr.shape}")
    if arr.size and not arr.min() > -np.inf:  # the minimum is NaN or -inf
        for bad, name in ((np.isnan(arr), "NaN"), (arr == -np.inf, "-inf")):
            if bad.any():
                where = [tuple(ij) for ij in np.argwhere(bad)[:5].tolist()]
                raise ValueError(
                    f"cost holds {name} at (agent, task) {where}: use +inf for a forbidden pair"
                )
    return arr


def check_weights(values: object, m: int) -> np.ndarray:
    """Per-task cost multipliers as a float64 array of shape (M,), all positive and finite."""
    arr = as_real_array(values, "weights", f"an array of M = {m} positive numbers")
    if arr.shape != (m,):
        raise ValueError(f"weights must have shape (M,) = ({m},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("weights contain NaN or infinite values")
    if np.any(arr <= 0):
        raise ValueError("weights must be positive")
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
    cost : array-like, shape (N, M)
        Real travel costs; ``+inf`` marks a pair that cannot be served (never matched). NaN
        and ``-inf`` are refused. N or M may be 0 (nothing is matched).
    weights : array-like, shape (M,), optional
        Positive per-task cost multipliers (default 1).
    priorities : array-like of int, shape (M,), optional
        Non-negative integer priority levels (higher is served first when not every task can
        be served); handled exactly whatever their size (see :func:`priority_levels`).

    Returns
    -------
    rows, cols : np.ndarray of int64
        Matched agent and task indices, only pairs with finite cost.

    Raises
    ------
    ValueError
        For a cost that is not a 2-D real matrix or holds NaN or ``-inf``, bad weights or
        priorities, or weighted costs that overflow float64.

    Examples
    --------
    >>> import numpy as np
    >>> from allocator.hungarian import solve_cost_matrix
    >>> solve_cost_matrix([[1.0, np.inf], [2.0, 5.0]])
    (array([0, 1]), array([0, 1]))
    """
    cost = check_cost_matrix(cost)
    n, m = cost.shape
    w = None if weights is None else check_weights(weights, m)
    p = None if priorities is None else priority_levels(priorities, m)
    if n == 0 or m == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    with np.errstate(over="ignore"):
        obj = cost if w is None else cost * w[None, :]
    finite = np.isfinite(obj)
    if w is not None and not np.array_equal(finite, np.isfinite(cost)):
        raise ValueError("weights * cost overflows float64: use smaller weights or cost units")
    if p is None and finite.all():
        rows, cols = linear_sum_assignment(obj)
        return rows.astype(np.int64), cols.astype(np.int64)
    k = min(n, m)
    low = float(obj[finite].min()) if finite.any() else 0.0
    if low < 0.0:  # the scaling below needs costs >= 0; a shift keeps the optimum
        obj = obj - low
    top = float(obj[finite].max()) if finite.any() else 0.0
    span = k * top + 1.0  # any set of finite pairs costs less than this
    work = np.where(finite, obj, 0.0)
    max_priority = 0.0
    if p is not None:
        work = work - span * p[None, :]
        max_priority = float(p.max())
    # Larger than any change of the finite part: serving one more pair always wins.
    unreachable = span * (2.0 + k * max_priority)
    if not np.isfinite(unreachable):
        raise ValueError(
            f"cost values up to {top:g} are too large to rank the plans in float64: use "
            "smaller cost units"
        )
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
    from allocator.paths import OMPLPlanner

    return OMPLPlanner(world, planner="prm" if kind == "prm" else "rrtconnect", seed=seed)


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
        used as a controller (``avoidance``, ``max_speed``, ...).

    Raises
    ------
    ValueError
        For a bad ``planner``, ``resolution`` or ``seed``, or an unknown option (the message
        lists the valid ones).
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
        check_planner_options(planner, resolution, seed)
        self.planner = planner
        self.resolution = resolution
        self.seed = seed
        self._planners: dict[int, Any] = {}

    def lifelong_dispatcher(self) -> Any:
        """:class:`allocator.dispatch.HungarianDispatcher`: lifelong floors, re-planned on
        events."""
        from allocator.dispatch import HungarianDispatcher

        return HungarianDispatcher()

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
        available: np.ndarray | None = None,
        ready_positions: np.ndarray | None = None,
        ready_steps: np.ndarray | None = None,
        deadlines: np.ndarray | None = None,
        keep: np.ndarray | None = None,
        now: int = 0,
        speed: float = 1.0,
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
            Non-negative integer priority levels, exact at any size; when not every task can
            be served, higher levels are served first.
        available, ready_positions, ready_steps, deadlines, keep, now, speed
            The scene's state (see :func:`allocator.base.check_plan_options`): the cost of
            AGV i for task j is ``speed * (ready_steps[i] - now) + travel(ready_i, task_j)``
            plus ``speed`` per step it would arrive past j's deadline; kept pairs stay,
            unavailable AGVs get nothing; served first are higher priorities, then tasks whose
            deadline an available AGV can still meet (exact levels), then the least cost.

        Returns
        -------
        Assignment
            ``task_of_agent[i]`` is the task AGV i should go to (-1: idle),
            ``agent_of_task[j]`` the AGV serving task j (-1: unserved, with the reason in
            ``unserved[j]``), ``cost`` the total travel distance (unweighted; from the ready
            positions). ``min(N, M)`` pairs are served unless shelves cut tasks off or AGVs
            are unavailable.

        Raises
        ------
        ValueError
            On a wrong shape, an empty array, NaN or infinite positions, positions outside the
            world or inside a shelf, or bad weights / priorities / plan options (the message
            names the argument).

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
        w = None if weights is None else check_weights(weights, m)
        opts = check_plan_options(agents, tasks, world, available, priorities,
                                  ready_positions, ready_steps, deadlines, keep, now, speed)
        travel = self.cost_matrix(opts.ready_positions, tasks, world)

        def solve(cost: np.ndarray, levels: np.ndarray | None,
                  cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return solve_cost_matrix(cost, None if w is None else w[cols], levels)

        rows, cols = solve_with_options(travel, opts, solve)
        result_cost = float(travel[rows, cols].sum())
        task_of_agent = np.full(len(agents), -1, dtype=np.int64)
        task_of_agent[rows] = cols
        paths = None
        if self.planner is not None:
            paths = plan_paths(opts.ready_positions, tasks, task_of_agent, world,
                               self._planner_for(world))
        agent_of_task = np.full(m, -1, dtype=np.int64)
        agent_of_task[cols] = rows
        return Assignment(
            task_of_agent, agent_of_task, result_cost, paths=paths,
            unserved=unserved_reasons(opts.cost(travel), agent_of_task)
            if len(cols) < m else {},
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

