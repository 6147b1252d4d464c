"""Greedy nearest-first assignment: the weak baseline every smarter method must beat.

AGVs take turns in index order; each takes the nearest task still free (by the same
obstacle-aware travel costs as :mod:`allocator.hungarian`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from allocator.base import (
    Assignment,
    ClassicalAllocator,
    check_inputs,
    check_plan_options,
    register,
    solve_with_options,
)
from allocator.hungarian import (
    _make_planner,
    check_cost_matrix,
    check_planner_options,
    plan_paths,
    unserved_reasons,
)
from allocator.paths import travel_costs

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["GreedyAllocator", "greedy_matching"]


def greedy_matching(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """AGVs in index order each take their cheapest free task (``inf``: never taken).

    Parameters
    ----------
    cost : array-like, shape (N, M)
        Real travel costs; ``+inf`` marks a pair that cannot be served (never taken). NaN and
        ``-inf`` are refused.

    Returns
    -------
    rows, cols : np.ndarray of int64
        Matched agent and task indices.

    Raises
    ------
    ValueError
        For a cost that is not a 2-D real matrix or holds NaN or ``-inf``.
    """
    work = check_cost_matrix(cost).copy()
    rows, cols = [], []
    for i in range(work.shape[0]):
        j = int(np.argmin(work[i]))
        if not np.isfinite(work[i, j]):
            continue
        rows.append(i)
        cols.append(j)
        work[:, j] = np.inf
        if len(cols) == work.shape[1]:
            break
    return np.array(rows, dtype=np.int64), np.array(cols, dtype=np.int64)


@register("greedy")
class GreedyAllocator(ClassicalAllocator):
    """Each AGV in turn takes its nearest free task.

    Parameters
    ----------
    planner : {None, "grid", "ompl", "prm"}
        Plan a path for every served AGV in :meth:`assign` (None: no paths in the result).
    resolution : float
        Cell size of the occupancy grid used for obstacle-aware costs.
    seed : int
        Seed of the OMPL planner.
    **controller_options
        Passed to :class:`~allocator.controller.AllocatorController`.

    Raises
    ------
    ValueError
        For a bad ``planner``, ``resolution`` or ``seed``, or an unknown option.
    """

    name = "greedy"

    @staticmethod
    def matching(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The matching rule on the (N, M) costs: :func:`greedy_matching`."""
        return greedy_matching(cost)

    def __init__(
        self, planner: str | None = None, resolution: float = 0.05, seed: int = 0,
        **controller_options: Any,
    ) -> None:
        super().__init__(**controller_options)
        check_planner_options(planner, resolution, seed)
        self.planner = planner
        self.resolution = resolution
        self.seed = seed
        self._planner: Any = None
        self._planner_world: Any = None

    def lifelong_dispatcher(self) -> Any:
        """:class:`allocator.dispatch.MatchingDispatcher` with this allocator's matching rule:
        lifelong floors, re-planned on events."""
        from allocator.dispatch import MatchingDispatcher

        return MatchingDispatcher(self.matching)

    def assign(
        self, agents: np.ndarray, tasks: np.ndarray, world: World | None = None, *,
        available: np.ndarray | None = None, priorities: np.ndarray | None = None,
        ready_positions: np.ndarray | None = None, ready_steps: np.ndarray | None = None,
        deadlines: np.ndarray | None = None, keep: np.ndarray | None = None, now: int = 0,
        speed: float = 1.0,
    ) -> Assignment:
        """Greedy nearest-first assignment of N AGVs to M tasks.

        Parameters
        ----------
        agents : array-like, shape (N, 2)
        tasks : array-like, shape (M, 2)
        world : World, optional
        available, priorities, ready_positions, ready_steps, deadlines, keep, now, speed
            As :meth:`allocator.hungarian.HungarianAllocator.assign`: the same costs; the
            service levels (priority, then a deadline that can still be met) are matched one
            after another, highest first, each by this allocator's rule on the AGVs left.

        Returns
        -------
        Assignment
            Same fields as :meth:`allocator.hungarian.HungarianAllocator.assign`; its cost is
            never below the Hungarian one.

        Raises
        ------
        ValueError
            On bad input (see :func:`allocator.base.check_inputs` and
            :func:`allocator.base.check_plan_options`).

        Examples
        --------
        >>> import allocator
        >>> agents = [[0.0, 0.0], [1.0, 0.0]]
        >>> tasks = [[0.6, 0.0], [-1.0, 0.0]]
        >>> allocator.make("greedy").assign(agents, tasks).task_of_agent   # AGV 0 grabs task 0
        array([0, 1])
        >>> allocator.make("hungarian").assign(agents, tasks).task_of_agent
        array([1, 0])
        """
        agents, tasks = check_inputs(agents, tasks, world)
        opts = check_plan_options(agents, tasks, world, available, priorities,
                                  ready_positions, ready_steps, deadlines, keep, now, speed)
        travel = travel_costs(opts.ready_positions, tasks, world, self.resolution)
        rows, cols = solve_with_options(travel, opts, self._by_levels)
        task_of_agent = np.full(len(agents), -1, dtype=np.int64)
        task_of_agent[rows] = cols
        agent_of_task = np.full(len(tasks), -1, dtype=np.int64)
        agent_of_task[cols] = rows
        paths = None
        if self.planner is not None:
            if self._planner_world is not world:
                self._planner = _make_planner(self.planner, world, self.seed)
                self._planner_world = world
            paths = plan_paths(opts.ready_positions, tasks, task_of_agent, world,
                               self._planner)
        return Assignment(
            task_of_agent, agent_of_task, float(travel[rows, cols].sum()), paths=paths,
            unserved=unserved_reasons(opts.cost(travel), agent_of_task), method=self.name,
        )

    def _by_levels(self, cost: np.ndarray, levels: np.ndarray | None,
                   cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """This allocator's rule, level by level (highest first) on the AGVs left."""
        if levels is None:
            return self.matching(cost)
        work = cost.copy()
        rows_out, cols_out = [], []
        for level in np.unique(levels)[::-1]:
            sel = np.flatnonzero(levels == level)
            r, c = self.matching(work[:, sel])
            rows_out.append(r)
            cols_out.append(sel[c])
            work[r, :] = np.inf
        return np.concatenate(rows_out), np.concatenate(cols_out)

    def __repr__(self) -> str:
        return f"GreedyAllocator(planner={self.planner!r})"
