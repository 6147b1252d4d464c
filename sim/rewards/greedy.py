"""The individual Greedy reward: progress towards the AGV's own nearest unclaimed task."""

from __future__ import annotations

import torch
from torch import Tensor

from sim.rewards.base import zero_inactive
from sim.state import SimState, StepContext

__all__ = ["Greedy"]


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
        return zero_inactive(terms, ctx.active)
