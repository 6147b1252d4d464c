"""The changing state of a batch of environments, and what one step tells the rewards.

The static parameters (bounds, shelves, AGV size, physics constants) live in
:mod:`sim.world`; everything here changes from step to step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from torch import Tensor

if TYPE_CHECKING:  # pragma: no cover
    from sim.orders import Events, Fleet, Orders

__all__ = ["LifelongContext", "LifelongState", "SimState", "StepContext"]


@dataclass
class SimState:
    """The changing state of B environments (views of the env's tensors, not copies)."""

    agent_pos: Tensor  # (B, N, 2) world units
    agent_vel: Tensor  # (B, N, 2) world units per second
    task_pos: Tensor  # (B, M, 2)
    task_claimed: Tensor  # (B, M) bool
    agent_task: Tensor  # (B, N) int64, task held by the AGV or -1
    steps: Tensor  # (B,) int64, steps taken in the current episode
    done: Tensor  # (B,) bool


@dataclass
class StepContext:
    """What a reward function may read about the step just taken.

    Distances are computed once by the environment and shared by every reward term.
    """

    prev_agent_pos: Tensor  # (B, N, 2) positions before the step
    prev_task_claimed: Tensor  # (B, M) bool, claims before the step
    prev_agent_task: Tensor  # (B, N) int64, tasks held before the step
    active: Tensor  # (B,) bool, environments that were running during the step
    agent_task_dist: Tensor  # (B, N, M) distances after the step
    collisions_per_agent: Tensor  # (B, N) float, overlapping discs per AGV (0 where inactive)
    collision_pairs: Tensor  # (B,) float, overlapping pairs after the step (0 where inactive)
    team_reward: Tensor  # (B,) float, the paper's R_t (0 where inactive)
    team_distance: Tensor  # (B, N) float, R_t + collision_pairs for every AGV (0 where inactive)
    team_collision: Tensor  # (B, N) float, -collision_pairs for every AGV


@dataclass
class LifelongState:
    """The changing state of B lifelong floors (views of the env's tensors, not copies)."""

    agent_pos: Tensor  # (B, N, 2)
    agent_vel: Tensor  # (B, N, 2)
    orders: Orders  # the order table, (B, Q) tensors
    fleet: Fleet  # each AGV's order, status, service and repair, (B, N) tensors
    steps: Tensor  # (B,) int64
    done: Tensor  # (B,) bool, the truncation horizon


@dataclass
class LifelongContext:
    """What a lifelong reward may read about the step just taken."""

    prev_agent_pos: Tensor  # (B, N, 2) positions before the step
    prev_orders: Orders  # the order table before the step
    prev_fleet: Fleet  # the fleet before the step
    active: Tensor  # (B,) bool
    events: Events  # what happened in the step
    collisions_per_agent: Tensor  # (B, N) float, 0 where inactive
    collision_pairs: Tensor  # (B,) float, 0 where inactive
    team_reward: Tensor  # (B,) the lifelong R_t (sim.tasks.remaining_work), 0 where inactive
    team_distance: Tensor  # (B, N) R_t + collision_pairs for every AGV
    team_collision: Tensor  # (B, N) -collision_pairs for every AGV
    target: Tensor  # (B, N, 2) each AGV's target after the step (0 where none)
    has_target: Tensor  # (B, N) bool: loaded (drop-off) or assigned (pickup)
