"""The task rules: who claims which task, and the paper's team reward R_t.

A task is claimed the first time an AGV that holds no task comes within the capture radius of
it; the AGV then holds it and parks. When several AGVs reach tasks in one step, each task goes
to its nearest eligible AGV and an AGV that wins several takes its nearest (the others wait for
the next step). The fused C step (``sim/_native/tasks.h``) applies the same rule and the same
R_t; tests check both against the functions here, and the classical controller's look-ahead
(:mod:`allocator.controller`) predicts claims with :func:`claim`.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["claim", "team_reward"]


def claim(
    dist: Tensor, agent_task: Tensor, task_claimed: Tensor, active: Tensor, capture_radius: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One round of claims.

    Parameters
    ----------
    dist : Tensor, shape (B, N, M)
        AGV-task distances (any float dtype).
    agent_task : Tensor of int64, shape (B, N)
        Task held by each AGV, -1 for none; only AGVs holding none may claim.
    task_claimed : Tensor of bool, shape (B, M)
    active : Tensor of bool, shape (B,)
        Environments that run; the others claim nothing.
    capture_radius : float
        An AGV claims a task within this distance (inclusive).

    Returns
    -------
    agent_task : Tensor of int64, shape (B, N)
        Tasks held after the round.
    task_claimed : Tensor of bool, shape (B, M)
    claimed_now : Tensor of bool, shape (B, M)
        Tasks claimed in this round.
    takes : Tensor of bool, shape (B, N)
        AGVs that claimed in this round (they park: their velocity becomes zero).

    Notes
    -----
    When nothing can be claimed, the given ``agent_task`` and ``task_claimed`` are returned
    themselves (``is`` tells the caller that nothing changed).
    """
    eligible = (
        (dist <= capture_radius)
        & (agent_task < 0).unsqueeze(2)
        & ~task_claimed.unsqueeze(1)
        & active.view(-1, 1, 1)
    )
    if not bool(eligible.any()):
        return (agent_task, task_claimed, torch.zeros_like(task_claimed),
                torch.zeros_like(agent_task, dtype=torch.bool))
    inf = torch.full_like(dist, float("inf"))
    best_agent = torch.where(eligible, dist, inf).min(dim=1, keepdim=True).indices  # (B, 1, M)
    agents = torch.arange(dist.shape[1], device=dist.device).view(1, -1, 1)
    won = eligible & (agents == best_agent)
    min_d, best_task = torch.where(won, dist, inf).min(dim=2)  # (B, N)
    takes = torch.isfinite(min_d)
    agent_task = torch.where(takes, best_task, agent_task)
    onehot = torch.nn.functional.one_hot(best_task, dist.shape[2]).bool() & takes.unsqueeze(-1)
    claimed_now = onehot.any(dim=1)
    return agent_task, task_claimed | claimed_now, claimed_now, takes


def team_reward(dist: Tensor, collision_pairs: Tensor, active: Tensor) -> Tensor:
    """The paper's team reward R_t: minus the sum over tasks of the distance to the nearest AGV,
    minus the number of colliding AGV pairs; 0 in inactive environments.

    Every task counts, claimed ones included (a claimed task's nearest AGV is the one parked
    on it, at distance at most the capture radius).

    Parameters
    ----------
    dist : Tensor, shape (B, N, M)
        AGV-task distances after the step.
    collision_pairs : Tensor, shape (B,)
        Overlapping pairs (:func:`sim.physics.collisions`).
    active : Tensor of bool, shape (B,)

    Returns
    -------
    Tensor, shape (B,)
    """
    nearest = dist.min(dim=1).values.sum(dim=1) if dist.shape[2] else collision_pairs * 0
    return torch.where(active, -nearest - collision_pairs, torch.zeros_like(collision_pairs))
