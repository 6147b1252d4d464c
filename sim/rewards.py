"""Reward functions, chosen by name in :func:`sim.make_env`.

A reward is a small callable ``reward(state, ctx) -> {term_name: (B, N) tensor}`` of the
state after the step (:class:`sim.state.SimState`) and the step's context; the
environment sums the terms into the per-agent reward and reports each term in
``info["reward_terms"]`` so that shaping can be audited. ``ctx`` is a
`sim.state.StepContext` holding the distances and collisions the environment already
computed for the step.

- ``minidist`` (global): every AGV gets the paper's R_t = -(sum over tasks of the distance to
  the nearest AGV) - (number of overlapping AGV pairs). Terms ``distance``, ``collision``.
- ``greedy`` (individual): each idle AGV gets the distance it closed to its nearest unclaimed
  task during the step, minus the number of AGVs it overlaps. Terms ``progress``,
  ``collision``.
- ``ipf``: r_IPF + r_g + r_c, the paper's information potential field reward
  (:class:`sim.ipf.IPFReward`). Terms ``ipf``, ``goal``, ``collision``.

Every term is a (B, N) tensor and is zero in environments that were already done before the
step (the environment zeroes their summed reward too, so the reported terms add up to it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import torch
from torch import Tensor

from sim.state import SimState, StepContext

__all__ = ["RewardFn", "MiniDist", "Greedy", "REWARDS", "make_reward"]


class RewardFn(Protocol):
    """``reward(state, ctx) -> {term: (B, N)}``; terms are summed into the agent's reward.

    A reward whose class sets ``zeroes_inactive = True`` promises that every term is already
    0 in environments that were not running; the step then skips masking the summed reward.
    A reward that needs static facts (the floor, whether the fused kernels run) defines
    ``setup(world, kernels)``, which the environment calls once when it is made.
    """

    def __call__(self, state: SimState, ctx: StepContext) -> dict[str, Tensor]: ...


def _active_only(terms: dict[str, Tensor], active: Tensor) -> dict[str, Tensor]:
    """Zero every (B, N) term in environments that were not running during the step."""
    keep = active.unsqueeze(1)
    return {name: torch.where(keep, value, torch.zeros_like(value))
            for name, value in terms.items()}


class MiniDist:
    """The paper's global MiniDist reward: every AGV receives the team reward R_t.

    Terms, each (B, N) and equal across the AGVs of an environment:
    ``distance`` = -(sum over all M tasks of the distance to the nearest AGV, after the step)
    and ``collision`` = -(number of AGV pairs whose discs overlap).
    """

    zeroes_inactive = True

    def __call__(self, state: SimState, ctx: StepContext) -> dict[str, Tensor]:
        # The environment splits R_t per AGV already (0 where it was not running).
        return {"distance": ctx.team_distance, "collision": ctx.team_collision}


class Greedy:
    """The individual Greedy reward: progress towards the AGV's own nearest unclaimed task.

    Terms, each (B, N): ``progress``, for an AGV idle before the step, ``d_before - d_after``
    where both distances are to the task that was its nearest unclaimed one before the step
    (so reaching and claiming a task is rewarded, not punished), and 0 for parked AGVs or when
    no task was open; ``collision`` = -(number of other AGVs whose discs overlap its own).
    """

    zeroes_inactive = True

    def __call__(self, state: SimState, ctx: StepContext) -> dict[str, Tensor]:
        inf = torch.tensor(float("inf"), device=ctx.agent_task_dist.device)
        open_tasks = ~ctx.prev_task_claimed.unsqueeze(1)  # (B, 1, M)
        d_before = torch.cdist(ctx.prev_agent_pos, state.task_pos)
        d_before = torch.where(open_tasks, d_before, inf)
        nearest_before, target = d_before.min(dim=2)  # (B, N)
        d_after = ctx.agent_task_dist.gather(2, target.unsqueeze(-1)).squeeze(-1)
        idle = (ctx.prev_agent_task < 0) & torch.isfinite(nearest_before)
        progress = torch.where(idle, nearest_before - d_after, torch.zeros_like(d_after))
        terms = {"progress": progress, "collision": -ctx.collisions_per_agent}
        return _active_only(terms, ctx.active)


def _ipf() -> RewardFn:
    from sim.ipf import IPFReward

    return IPFReward()


REWARDS: dict[str, Callable[[], RewardFn]] = {
    "minidist": MiniDist,
    "greedy": Greedy,
    "ipf": _ipf,
}
"""Registered rewards by name."""


def make_reward(reward: str | RewardFn) -> RewardFn:
    """Return the reward callable for a name, or the callable itself.

    Raises
    ------
    ValueError
        For an unknown name; the message lists the known ones.
    """
    if callable(reward) and not isinstance(reward, str):
        return reward
    if reward not in REWARDS:
        raise ValueError(f"unknown reward {reward!r}; expected one of {sorted(REWARDS)}")
    return REWARDS[reward]()
