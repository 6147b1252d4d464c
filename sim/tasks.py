"""The task rules: who claims which task, and the paper's team reward R_t (and its lifelong
form, :func:`remaining_work`).

A task is claimed the first time an AGV that holds no task comes within the capture radius of
it; the AGV then holds it and parks. When several AGVs reach tasks in one step, each task goes
to its nearest eligible AGV and an AGV that wins several takes its nearest (the others wait for
the next step). The fused C step (``sim/_native/tasks.h``) applies the same rule and the same
R_t; tests check both against the functions here, and the classical controller's look-ahead
(:mod:`allocator.controller`) predicts claims with :func:`claim`.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

__all__ = ["claim", "remaining_work", "team_reward"]


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


def remaining_work(agent_pos: Tensor, orders: Any, agent_status: Tensor, active: Tensor) -> Tensor:
    """The distance still to cover for every order in the table, per environment: the lifelong
    R_t is ``-remaining_work - collision_pairs``.

    An order not yet picked up (open or assigned) counts the distance from its pickup to the
    nearest AGV that could take it (idle or on its way to a pickup; the nearest AGV at all
    when none is) plus its loaded trip, pickup to drop-off; a loaded order counts the distance
    from its AGV to its drop-off. So the sum does not jump when an order is picked up (the
    AGV stands on the pickup) and drops to 0 for an order at its delivery, as the paper's sum
    over tasks drops to the capture radius when a task is claimed.

    Parameters
    ----------
    agent_pos : Tensor, shape (B, N, 2)
    orders : sim.orders.Orders
        The table after the step.
    agent_status : Tensor of int8, shape (B, N)
        :data:`sim.orders.AGENT_STATUS` codes.
    active : Tensor of bool, shape (B,)

    Returns
    -------
    Tensor, shape (B,), float32; 0 where inactive.
    """
    from sim.orders import ASSIGNED, BROKEN, CARRYING, LOADED, OPEN

    status = orders.status
    waiting = (status == OPEN) | (status == ASSIGNED)  # (B, Q)
    d = torch.cdist(orders.pickup, agent_pos, compute_mode="donot_use_mm_for_euclid_dist")
    available = (agent_status != CARRYING) & (agent_status != BROKEN)  # (B, N)
    inf = torch.tensor(float("inf"), dtype=d.dtype, device=d.device)
    near_avail = torch.where(available.unsqueeze(1), d, inf).min(dim=2).values
    near_any = d.min(dim=2).values if d.shape[2] else torch.zeros_like(near_avail)
    near = torch.where(available.any(1, keepdim=True), near_avail, near_any)
    trip = torch.linalg.vector_norm(orders.dropoff - orders.pickup, dim=-1)
    carrier = orders.agent.clamp_min(0).unsqueeze(-1).expand(-1, -1, 2)
    carried = torch.linalg.vector_norm(agent_pos.gather(1, carrier) - orders.dropoff, dim=-1)
    work = torch.where(waiting, near + trip, torch.where(status == LOADED, carried,
                                                         torch.zeros_like(trip)))
    return torch.where(active, work.sum(dim=1), torch.zeros_like(work[:, 0]))
