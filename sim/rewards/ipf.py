"""The paper's IPF reward, ``r_IPF + r_g + r_c``; the field itself is :mod:`sim.ipf`."""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch
from torch import Tensor

from sim.ipf import (
    AGENT_VALUE,
    DEFAULT_RESOLUTION,
    TASK_VALUE,
    IPFGrid,
    TaskBlockCache,
    check_resolution,
    ipf_grid,
)
from sim.rewards.assignment import optimal_assignment
from sim.state import SimState, StepContext
from sim.world import World

__all__ = ["IPFReward"]


def _finite(name: str, value: object, bound: str = "") -> float:
    """``value`` as a float, or a ValueError naming ``name`` unless it is a finite real number
    (not a bool) meeting ``bound``: ``""`` (none), ``">= 0"`` or ``"> 0"``."""
    ok = not isinstance(value, bool) and isinstance(value, numbers.Real) \
        and math.isfinite(value)
    if ok and bound:
        ok = value >= 0 if bound == ">= 0" else value > 0
    if not ok:
        rule = f" {bound}" if bound else ""
        raise ValueError(f"{name} must be a finite number{rule}, got {value!r}")
    return float(value)


class IPFReward:
    """The paper's IPF reward ``r = r_IPF + r_g + r_c``, per AGV, with each term reported.

    Terms (each ``(B, N)``, zero in environments that were already done):

    - ``"ipf"``: ``r_IPF``, AGV i's own field at its own cell, from the state after the step
      (claimed tasks have left the field; parked AGVs stay sources at -3 unless
      ``parked_sources=False``). Exact, via
      :meth:`sim.ipf.IPFGrid.reward_potentials`. A parked AGV stands on the task it serves and
      receives that task's value (+5), as an AGV on a target does in the paper: otherwise
      claiming a task (which removes its +5 from the field) would pay less than hovering just
      outside the capture radius, and learners learn to hover.
    - ``"goal"``: ``r_g = -sum over tasks of the distance to the nearest AGV`` (all tasks, as in
      the paper's R_t), shared by every AGV. The paper writes ``-sum_i min_j d_ij`` with
      ``d_ij`` the distance between AGV i and task j, which read literally sums over AGVs; we
      follow the design's reading, the MiniDist distance term, which rewards covering every
      task rather than crowding one.
    - ``"collision"``: ``r_c = -1`` if AGV i's disc overlaps any other AGV's (centres closer
      than two radii, the environment's collision rule; the paper writes ``<=``), else 0.
    - ``"time"`` (only with ``time_cost > 0``; not part of the paper's reward): ``-time_cost``
      for every AGV after each step that leaves any task unclaimed, 0 after the step that
      claims the last one. Summed over an episode it is ``-time_cost * (T - 1)`` for an
      episode whose last task is claimed at step T (the paper's time metric) and
      ``-time_cost * limit`` for an unfinished one, so the team pays for finishing late
      (issue 16; the variant ``"ipf-time"`` of :data:`sim.rewards.REWARD_VARIANTS`). It is 0
      at the final step so that the learners' absorbing terminal value (``r / (1 - gamma)``,
      :class:`learners.common.OffPolicyConfig`) does not charge it forever.
    - ``"assign"`` (only with ``assign_weight > 0``; not part of the paper's reward):
      ``-assign_weight * d(i, sigma(i))``, AGV i's distance after the step to the task a
      min-sum assignment of the idle AGVs to the unclaimed tasks gives it
      (:func:`sim.rewards.assignment.optimal_assignment`, Hungarian on straight-line
      distances), 0 for an AGV without one. A training signal that reads the whole state
      (centralized training); the policy still acts on its own observation (issue 16:
      ``benchmarks/time_probe.py --assign-weight``; not a registered variant, since it did not
      shorten the 6v6 time, ``docs/learners.md``).

    Parameters
    ----------
    resolution : float
        Grid cell size (default 0.05, on every shipped floor: grids whose dense Green's
        function would exceed :data:`sim.ipf.MAX_GREEN_BYTES` use the exact separator tree of
        :mod:`sim.ipf.hierarchy`, built on the first step). Only a grid whose tree would exceed
        :data:`sim.ipf.MAX_TREE_BYTES` is refused, with a resolution that fits named, to be
        passed as ``make_env(..., reward=IPFReward(resolution=...))``.
    task_value, agent_value : float
        The fixed potentials (+5, -3 in the paper).
    goal_weight : float
        The factor of the ``"goal"`` term, > 0 (default 1: the paper's reward).
    time_cost : float
        The per-step team cost of the ``"time"`` term while any task is unclaimed, >= 0
        (default 0: the paper's reward, without the term).
    assign_weight : float
        The factor of the ``"assign"`` term, >= 0 (default 0: the paper's reward, without
        the term).
    parked_sources : bool
        Whether parked AGVs stay sources at ``agent_value`` in the other AGVs' fields (default
        True, as every shipped policy was trained). False leaves them out, as claimed tasks
        are: with most AGVs parked, their -3 sources make the field negative over most of the
        floor and the walls (fixed at 0) its highest ground, so the term leads the last idle
        AGVs away from the last tasks (issue 16/17, ``benchmarks/time_diagnosis.py``'s
        ``late uphill``). Computed on the torch path (the fused kernel knows one rule).

    Raises
    ------
    ValueError
        For a resolution that is not a positive finite cell size, potentials that are not
        finite numbers, a goal weight that is not a finite number > 0, or a time cost or
        assign weight that is not a finite number >= 0; :meth:`setup` for a floor the
        resolution does not fit.
    """

    zeroes_inactive = True

    def __init__(
        self,
        resolution: float = DEFAULT_RESOLUTION,
        task_value: float = TASK_VALUE,
        agent_value: float = AGENT_VALUE,
        goal_weight: float = 1.0,
        time_cost: float = 0.0,
        assign_weight: float = 0.0,
        parked_sources: bool = True,
    ) -> None:
        self.resolution = check_resolution(resolution)
        self.task_value = _finite("task_value", task_value)
        self.agent_value = _finite("agent_value", agent_value)
        self.time_cost = _finite("time_cost", time_cost, ">= 0")
        self.assign_weight = _finite("assign_weight", assign_weight, ">= 0")
        self.goal_weight = _finite("goal_weight", goal_weight, "> 0")
        if not isinstance(parked_sources, bool):
            raise ValueError(f"parked_sources must be True or False, got {parked_sources!r}")
        self.parked_sources = parked_sources
        self._cache = TaskBlockCache()
        self._grid: IPFGrid | None = None
        self._kernels: Any = None

    def setup(self, world: World, kernels: Any = None) -> None:
        """Bind the reward to the floor of the environment and to the kernels it uses.

        Parameters
        ----------
        world : World
            The environment's floor; its grid is made here (the Green's function on the first
            step), so a resolution that does not fit the floor is refused now.
        kernels : ctypes.CDLL, optional
            The environment's fused kernels (:mod:`sim.native`), or None for the torch path.

        Raises
        ------
        ValueError
            If the reward is already bound to another floor or another choice of kernels (an
            ``IPFReward`` serves the environments of one floor and one kernel choice).
        """
        grid = ipf_grid(world, self.resolution)
        if self._grid is not None and (self._grid is not grid or self._kernels is not kernels):
            raise ValueError(
                "this IPFReward is already set up for another environment's floor or kernels; "
                "give each environment its own IPFReward(...)"
            )
        self._grid = grid
        self._kernels = kernels

    def __call__(self, state: SimState, ctx: StepContext) -> dict[str, Tensor]:
        if self._grid is None:
            raise ValueError("IPFReward.setup(world, kernels) must be called before the reward "
                             "(sim.make_env does it)")
        # ctx's collision counts and team terms are already 0 where the env was not running.
        goal = ctx.team_distance
        if self.goal_weight != 1.0:
            goal = goal * self.goal_weight
        collision = -ctx.collisions_per_agent.clamp_max(1.0)
        potential = self._grid.reward_potentials(
            state.agent_pos, state.task_pos, state.task_claimed, state.agent_task, ctx.active,
            kernels=self._kernels, task_value=self.task_value, agent_value=self.agent_value,
            cache=self._cache, dtype=goal.dtype, parked_sources=self.parked_sources,
        )
        terms = {"ipf": potential, "goal": goal, "collision": collision}
        if self.time_cost > 0:
            waiting = (~state.task_claimed).any(dim=1) & ctx.active  # (B,)
            terms["time"] = (-self.time_cost * waiting.to(goal.dtype)).unsqueeze(1).expand_as(
                goal).contiguous()
        if self.assign_weight > 0:
            task = optimal_assignment(ctx.agent_task_dist, state.agent_task < 0,
                                      ~state.task_claimed)  # (B, N)
            dist = ctx.agent_task_dist.gather(2, task.clamp_min(0).unsqueeze(-1)).squeeze(-1)
            keep = (task >= 0) & ctx.active.unsqueeze(1)
            terms["assign"] = torch.where(keep, -self.assign_weight * dist.to(goal.dtype),
                                          torch.zeros_like(goal))
        return terms
