"""What each AGV observes, and where each feature sits in its observation vector.

An observation is, per AGV: its own velocity (2) and position (2); for each of the K nearest
unclaimed tasks within the sensing range the task's position relative to the AGV and a mask
bit; for each of the K nearest other AGVs in range their relative position, velocity and a
mask bit; last, whether the AGV holds a task. Missing entries are zero with mask 0. Code that
reads observations uses the named slices of :class:`ObsLayout`, never raw indices. The fused
C step (``sim/_native/observations.h``) writes the same vector; tests check it against
:func:`observe`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["AGENT_FEATURES", "HOLDING", "ObsLayout", "TASK_FEATURES", "global_state", "nearest",
           "observe"]

TASK_FEATURES = ("rel_x", "rel_y", "mask")
"""The features of one task slot, in order."""
AGENT_FEATURES = ("rel_x", "rel_y", "vx", "vy", "mask")
"""The features of one AGV slot, in order."""
HOLDING = slice(-1, None)
"""The "holds a task" bit: the last feature of every layout (:attr:`ObsLayout.holding`)."""


@dataclass(frozen=True)
class ObsLayout:
    """Named positions of the observation features for ``k_tasks`` and ``k_agents`` slots.

    Attributes are slices into the last dimension of an observation (B, N, size).
    """

    k_tasks: int
    k_agents: int

    def __post_init__(self) -> None:
        for name in ("k_tasks", "k_agents"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"ObsLayout.{name} must be an integer >= 0, got {value!r}")

    @property
    def vel(self) -> slice:
        """Own velocity (vx, vy)."""
        return slice(0, 2)

    @property
    def pos(self) -> slice:
        """Own position (x, y)."""
        return slice(2, 4)

    @property
    def tasks(self) -> slice:
        """All task slots: k_tasks x (rel_x, rel_y, mask)."""
        return slice(4, 4 + len(TASK_FEATURES) * self.k_tasks)

    @property
    def agents(self) -> slice:
        """All AGV slots: k_agents x (rel_x, rel_y, vx, vy, mask)."""
        start = self.tasks.stop
        return slice(start, start + len(AGENT_FEATURES) * self.k_agents)

    @property
    def holding(self) -> slice:
        """The "holds a task" bit (1.0 while the AGV holds a task and is parked)."""
        return slice(self.size - 1, self.size)

    @property
    def size(self) -> int:
        """Length O of an observation vector."""
        return self.agents.stop + 1

    def task_rel(self, k: int) -> slice:
        """Relative position (rel_x, rel_y) of the k-th nearest visible task."""
        return self._slot(k, self.k_tasks, self.tasks.start, TASK_FEATURES, "rel_x", 2)

    def task_mask(self, k: int) -> slice:
        """Mask bit of the k-th task slot (1.0 where a task is visible)."""
        return self._slot(k, self.k_tasks, self.tasks.start, TASK_FEATURES, "mask", 1)

    def agent_rel(self, k: int) -> slice:
        """Relative position (rel_x, rel_y) of the k-th nearest visible other AGV."""
        return self._slot(k, self.k_agents, self.agents.start, AGENT_FEATURES, "rel_x", 2)

    def agent_vel(self, k: int) -> slice:
        """Velocity (vx, vy) of the k-th nearest visible other AGV."""
        return self._slot(k, self.k_agents, self.agents.start, AGENT_FEATURES, "vx", 2)

    def agent_mask(self, k: int) -> slice:
        """Mask bit of the k-th AGV slot."""
        return self._slot(k, self.k_agents, self.agents.start, AGENT_FEATURES, "mask", 1)

    @staticmethod
    def _slot(k: int, count: int, start: int, features: tuple[str, ...], first: str,
              width: int) -> slice:
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < count:
            raise ValueError(f"slot k must be an integer in [0, {count}), got {k!r}")
        at = start + k * len(features) + features.index(first)
        return slice(at, at + width)


def nearest(feats: Tensor, dist: Tensor, k: int) -> Tensor:
    """Features of the k nearest finite-distance entries, zeroed where missing.

    A full stable sort is used (ties go to the lower index, as in the fused kernel); it is
    faster than ``topk`` for the small C of these scenes.

    Parameters
    ----------
    feats : Tensor, shape (B, N, C, F)
        Per candidate features, the last one the mask bit (1 when present).
    dist : Tensor, shape (B, N, C)
        Candidate distances, ``inf`` for hidden candidates.
    k : int

    Returns
    -------
    Tensor, shape (B, N, k F)
    """
    B, N, C, F = feats.shape
    d_sorted, idx = torch.sort(dist, dim=-1, stable=True)
    kk = min(k, C)
    d_sorted, idx = d_sorted[..., :kk], idx[..., :kk]
    picked = feats.gather(2, idx.unsqueeze(-1).expand(B, N, kk, F))
    picked = picked * torch.isfinite(d_sorted).unsqueeze(-1)
    if kk < k:
        picked = torch.cat([picked, picked.new_zeros(B, N, k - kk, F)], dim=2)
    return picked.reshape(B, N, k * F)


def observe(
    agent_pos: Tensor, agent_vel: Tensor, task_claimed: Tensor, agent_task: Tensor,
    layout: ObsLayout, sensing_range: float, task_offsets: tuple[Tensor, Tensor] | None,
    pair: Tensor | None, eye: Tensor,
) -> Tensor:
    """Local observations, (B, N, layout.size) (the torch reference).

    Parameters
    ----------
    agent_pos, agent_vel : Tensor, shape (B, N, 2)
    task_claimed : Tensor of bool, shape (B, M)
    agent_task : Tensor of int64, shape (B, N)
    layout : ObsLayout
    sensing_range : float
        Tasks and AGVs farther than this are hidden.
    task_offsets : (Tensor (B, N, M, 2), Tensor (B, N, M)), optional
        Task offsets ``t_j - p_i`` and their lengths (needed when ``layout.k_tasks``).
    pair : Tensor, shape (B, N, N), optional
        Pairwise AGV distances (needed when ``layout.k_agents``).
    eye : Tensor of bool, shape (N, N)
    """
    B, N = agent_pos.shape[:2]
    parts = [agent_vel, agent_pos]
    if layout.k_tasks:
        if task_offsets is None:
            raise ValueError("observe: task_offsets is needed when layout.k_tasks > 0")
        rel_t, d_t = task_offsets
        hidden = task_claimed.unsqueeze(1) | (d_t > sensing_range)
        feats = torch.cat([rel_t, torch.ones_like(d_t).unsqueeze(-1)], dim=-1)
        parts.append(nearest(feats, d_t.masked_fill(hidden, float("inf")), layout.k_tasks))
    if layout.k_agents:
        if pair is None:
            raise ValueError("observe: pair is needed when layout.k_agents > 0")
        delta = agent_pos.unsqueeze(2) - agent_pos.unsqueeze(1)
        vel_j = agent_vel.unsqueeze(1).expand(B, N, N, 2)
        feats = torch.cat([-delta, vel_j, torch.ones_like(pair).unsqueeze(-1)], dim=-1)
        d_a = pair.masked_fill(eye | (pair > sensing_range), float("inf"))
        parts.append(nearest(feats, d_a, layout.k_agents))
    parts.append((agent_task >= 0).to(agent_pos.dtype).unsqueeze(-1))
    return torch.cat(parts, dim=-1)


def global_state(agent_pos: Tensor, agent_vel: Tensor, task_pos: Tensor, task_claimed: Tensor,
                 agent_task: Tensor) -> Tensor:
    """Global state for centralized critics, (B, 5 N + 3 M): every AGV's position, velocity
    and holding bit, every task's position and claimed bit.

    Parameters
    ----------
    agent_pos, agent_vel : Tensor, shape (B, N, 2)
    task_pos : Tensor, shape (B, M, 2)
    task_claimed : Tensor of bool, shape (B, M)
    agent_task : Tensor of int64, shape (B, N)
    """
    B = agent_pos.shape[0]
    dtype = agent_pos.dtype
    agents = torch.cat(
        [agent_pos, agent_vel, (agent_task >= 0).to(dtype).unsqueeze(-1)], dim=-1,
    )
    tasks = torch.cat([task_pos, task_claimed.to(dtype).unsqueeze(-1)], dim=-1)
    return torch.cat([agents.reshape(B, -1), tasks.reshape(B, -1)], dim=-1)
