"""The ``"auction"`` registry entry: a decentralized epsilon-auction as an allocator.

The algorithm is :mod:`allocator.auction` (no solver state, numpy and scipy only); this module
wraps it in the Allocator interface, and its lifelong dispatcher is
:class:`allocator.dispatch.AuctionDispatcher`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from allocator.auction import ComponentAuction, _check, check_comm_range, component_auction
from allocator.base import (
    Assignment,
    ClassicalAllocator,
    check_inputs,
    check_plan_options,
    register,
    solve_with_options,
)
from allocator.hungarian import check_planner_options, unserved_reasons
from allocator.paths import travel_costs

__all__ = ["AuctionAllocator"]


@register("auction")
class AuctionAllocator(ClassicalAllocator):
    """A decentralized epsilon-auction over the AGVs' communication graph.

    Each task is announced to the AGV nearest it and flooded through that AGV's
    connected component (AGVs at most ``comm_range`` apart); the component's AGVs bid for
    it with :func:`allocator.auction.auction` (see
    :func:`allocator.auction.component_auction`): no central solver, conflicts
    resolved by messages only. In lifelong operation :class:`allocator.dispatch.
    AuctionDispatcher` re-plans on events the same way.

    Parameters
    ----------
    comm_range : float
        Radio range in world units, > 0 (default ``inf``: a complete graph).
    eps : float, optional
        Bid increment (default :func:`allocator.auction.default_eps`).
    max_rounds : int
        Round limit of each component's auction.
    resolution : float
        Cell size of the grid of obstacle-aware costs (as ``"hungarian"``).
    **controller_options
        Passed to :class:`~allocator.controller.AllocatorController`.

    Attributes
    ----------
    last_auction : ComponentAuction or None
        The last :meth:`assign`'s auction: ``messages``, ``rounds``, ``component``.
    messages : int
        Messages sent by every :meth:`assign` so far.

    Raises
    ------
    ValueError
        For ``comm_range`` not a positive number, a bad ``eps`` / ``max_rounds`` /
        ``resolution``, or an unknown option.
    """

    name = "auction"

    def __init__(self, comm_range: float = math.inf, eps: float | None = None,
                 max_rounds: int = 20_000, resolution: float = 0.05,
                 **controller_options: Any) -> None:
        super().__init__(**controller_options)
        check_planner_options(None, resolution, 0)
        self.comm_range = check_comm_range(comm_range)
        _check(np.zeros((1, 1)), np.zeros((1, 2)), self.comm_range, eps, max_rounds, None)
        self.eps = eps
        self.max_rounds = int(max_rounds)
        self.resolution = resolution
        self.last_auction: ComponentAuction | None = None
        self.messages = 0

    def lifelong_dispatcher(self) -> Any:
        """:class:`allocator.dispatch.AuctionDispatcher` with this range and eps."""
        from allocator.dispatch import AuctionDispatcher

        return AuctionDispatcher(self.comm_range, self.eps, self.max_rounds)

    def assign(
        self, agents: np.ndarray, tasks: np.ndarray, world: Any = None, *,
        available: np.ndarray | None = None, priorities: np.ndarray | None = None,
        ready_positions: np.ndarray | None = None, ready_steps: np.ndarray | None = None,
        deadlines: np.ndarray | None = None, keep: np.ndarray | None = None,
        now: int = 0, speed: float = 1.0,
    ) -> Assignment:
        """Assign N AGVs to M tasks by the component auction (maximising minus the cost).

        Parameters
        ----------
        agents : array-like, shape (N, 2)
            AGV positions (also where they talk from).
        tasks : array-like, shape (M, 2)
        world : World, optional
        available, priorities, ready_positions, ready_steps, deadlines, keep, now, speed
            As :meth:`allocator.hungarian.HungarianAllocator.assign`; the service levels
            become bonuses larger than any cost difference (lexicographic when the
            auction is exact); unavailable AGVs do not bid (they still relay messages).

        Returns
        -------
        Assignment
            ``cost`` the travel distance; :attr:`last_auction` the messages and rounds.

        Raises
        ------
        ValueError
            On bad input (see :func:`allocator.base.check_inputs` and
            :func:`allocator.base.check_plan_options`).
        """
        agents, tasks = check_inputs(agents, tasks, world)
        opts = check_plan_options(agents, tasks, world, available, priorities,
                                  ready_positions, ready_steps, deadlines, keep, now,
                                  speed)
        travel = travel_costs(opts.ready_positions, tasks, world, self.resolution)
        runs: list[ComponentAuction] = []

        def solve(cost: np.ndarray, levels: np.ndarray | None,
                  cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            rest = np.setdiff1d(np.arange(len(agents)), opts.keep_agents)
            finite = np.isfinite(cost)
            if not finite.any():
                return np.zeros(0, np.int64), np.zeros(0, np.int64)
            low, high = float(cost[finite].min()), float(cost[finite].max())
            benefit = -np.where(finite, cost, high + (high - low) + 1.0)
            if levels is not None:
                ranks = np.unique(levels, return_inverse=True)[1].reshape(-1)
                benefit = benefit + ranks[None, :] * (2.0 * (high - low) + 2.0)
            out = component_auction(benefit, agents[rest], tasks[cols], self.comm_range,
                                    eps=self.eps, max_rounds=self.max_rounds)
            runs.append(out)
            rows = np.flatnonzero(out.task_of_agent >= 0)
            return rows, out.task_of_agent[rows]

        rows, cols = solve_with_options(travel, opts, solve)
        self.last_auction = runs[-1] if runs else None
        self.messages += sum(r.messages for r in runs)
        task_of_agent = np.full(len(agents), -1, dtype=np.int64)
        task_of_agent[rows] = cols
        agent_of_task = np.full(len(tasks), -1, dtype=np.int64)
        agent_of_task[cols] = rows
        return Assignment(
            task_of_agent, agent_of_task, float(travel[rows, cols].sum()),
            unserved=unserved_reasons(opts.cost(travel), agent_of_task),
            method=self.name,
        )

    def __repr__(self) -> str:
        return f"AuctionAllocator(comm_range={self.comm_range!r})"
