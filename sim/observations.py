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
from typing import Any

import torch
from torch import Tensor

__all__ = ["AGENT_FEATURES", "HOLDING", "LifelongObsLayout", "ObsLayout", "TASK_FEATURES",
           "global_state", "lifelong_global_state", "nearest", "nearest_index", "observe",
           "observe_lifelong"]

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


def nearest_index(dist: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Indices of the k nearest entries, nearest first, and whether each is finite.

    ``k`` rounds of ``argmin`` (which returns the first minimum: ties go to the lower index,
    as with the stable sort of :func:`nearest`); each round hides its pick with ``inf``.

    Parameters
    ----------
    dist : Tensor, shape (B, N, C)
        Candidate distances, ``inf`` for hidden candidates; overwritten (pass a fresh one).
    k : int

    Returns
    -------
    idx : Tensor of int64, shape (B, N, min(k, C))
    finite : Tensor of bool, shape (B, N, min(k, C))
    """
    kk = min(k, dist.shape[-1])
    if kk == 0:
        shape = (*dist.shape[:-1], 0)
        return (torch.zeros(shape, dtype=torch.int64, device=dist.device),
                torch.zeros(shape, dtype=torch.bool, device=dist.device))
    idx, fin = [], []
    for r in range(kk):
        i = dist.argmin(-1, keepdim=True)
        idx.append(i)
        fin.append(torch.isfinite(dist.gather(-1, i)))
        if r + 1 < kk:
            dist.scatter_(-1, i, float("inf"))
    return torch.cat(idx, -1), torch.cat(fin, -1)


def _slots(feats: Tensor, finite: Tensor, k: int) -> Tensor:
    """(B, N, kk, F) picked features, zeroed where missing and padded to k slots, as
    (B, N, k F)."""
    B, N, kk, F = feats.shape
    feats = feats * finite.unsqueeze(-1)
    if kk < k:
        feats = torch.cat([feats, feats.new_zeros(B, N, k - kk, F)], dim=2)
    return feats.reshape(B, N, k * F)


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


# ---------------------------------------------------------------------- lifelong mode
STATUS_FEATURES = ("idle", "to_pickup", "loaded", "broken")
"""The one-hot AGV status of a lifelong observation, in the order of
:data:`sim.orders.AGENT_STATUS`."""


@dataclass(frozen=True)
class LifelongObsLayout:
    """Named positions of the features of a lifelong observation.

    Per AGV, in order: own velocity (2) and position (2); its status one-hot (4, idle, to
    pickup, loaded, broken); whether it stands in service (1); its target relative to it and
    a mask bit (3: a loaded AGV's drop-off, an assigned AGV's pickup, none otherwise); the
    ``k_pickups`` nearest open pickups (orders released, not given to an AGV, not picked up)
    within the sensing range, relative position and mask (3 each); the ``k_agents`` nearest
    other AGVs in range, relative position, velocity and mask (5 each). The size does not
    depend on the fleet size N.
    """

    k_pickups: int
    k_agents: int

    def __post_init__(self) -> None:
        for name in ("k_pickups", "k_agents"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"LifelongObsLayout.{name} must be an integer >= 0, got "
                                 f"{value!r}")

    vel = slice(0, 2)
    """Own velocity."""
    pos = slice(2, 4)
    """Own position."""
    status = slice(4, 8)
    """Status one-hot (:data:`STATUS_FEATURES`)."""
    service = slice(8, 9)
    """1.0 while the AGV stands in service at a pickup or drop-off."""
    target_rel = slice(9, 11)
    """The target relative to the AGV (0 when it has none)."""
    target_mask = slice(11, 12)
    """1.0 when the AGV has a target."""

    @property
    def pickups(self) -> slice:
        """All pickup slots: k_pickups x (rel_x, rel_y, mask)."""
        return slice(12, 12 + len(TASK_FEATURES) * self.k_pickups)

    @property
    def agents(self) -> slice:
        """All AGV slots: k_agents x (rel_x, rel_y, vx, vy, mask)."""
        start = self.pickups.stop
        return slice(start, start + len(AGENT_FEATURES) * self.k_agents)

    @property
    def size(self) -> int:
        """Length O of an observation vector."""
        return self.agents.stop

    def pickup_rel(self, k: int) -> slice:
        """Relative position of the k-th nearest visible open pickup."""
        return ObsLayout._slot(k, self.k_pickups, self.pickups.start, TASK_FEATURES, "rel_x", 2)

    def pickup_mask(self, k: int) -> slice:
        """Mask bit of the k-th pickup slot."""
        return ObsLayout._slot(k, self.k_pickups, self.pickups.start, TASK_FEATURES, "mask", 1)

    def agent_rel(self, k: int) -> slice:
        """Relative position of the k-th nearest visible other AGV."""
        return ObsLayout._slot(k, self.k_agents, self.agents.start, AGENT_FEATURES, "rel_x", 2)

    def agent_vel(self, k: int) -> slice:
        """Velocity of the k-th nearest visible other AGV."""
        return ObsLayout._slot(k, self.k_agents, self.agents.start, AGENT_FEATURES, "vx", 2)

    def agent_mask(self, k: int) -> slice:
        """Mask bit of the k-th AGV slot."""
        return ObsLayout._slot(k, self.k_agents, self.agents.start, AGENT_FEATURES, "mask", 1)


def observe_lifelong(
    agent_pos: Tensor, agent_vel: Tensor, fleet: Any, orders: Any, target: Tensor,
    has_target: Tensor, layout: LifelongObsLayout, sensing_range: float,
    pair: Tensor | None, eye: Tensor,
) -> Tensor:
    """Lifelong observations, (B, N, layout.size).

    Parameters
    ----------
    agent_pos, agent_vel : Tensor, shape (B, N, 2)
    fleet : sim.orders.Fleet
    orders : sim.orders.Orders
    target : Tensor, shape (B, N, 2)
        Each AGV's target (0 where none).
    has_target : Tensor of bool, shape (B, N)
    layout : LifelongObsLayout
    sensing_range : float
    pair : Tensor, shape (B, N, N), optional
        Pairwise AGV distances (needed when ``layout.k_agents``).
    eye : Tensor of bool, shape (N, N)
    """
    from sim.orders import OPEN

    dtype = agent_pos.dtype
    status = torch.nn.functional.one_hot(fleet.status.long(), 4).to(dtype)
    service = (fleet.service_left > 0).to(dtype).unsqueeze(-1)
    rel_target = (target - agent_pos) * has_target.unsqueeze(-1)
    parts = [agent_vel, agent_pos, status, service, rel_target,
             has_target.to(dtype).unsqueeze(-1)]
    B, N = agent_pos.shape[:2]
    # The k nearest first (nearest_index), then the features of those k only: no
    # (B, N, C, F) feature tensor and no sort over all C candidates.
    if layout.k_pickups:
        # vector_norm, as the kernel in sim/_native/lifelong.h rounds (cdist may round the
        # other way on some CPUs: sim.lifelong_native.torch_norm_rounding).
        d = torch.linalg.vector_norm(orders.pickup.unsqueeze(1) - agent_pos.unsqueeze(2), dim=-1)
        hidden = (orders.status != OPEN).unsqueeze(1) | (d > sensing_range)
        idx, fin = nearest_index(d.masked_fill_(hidden, float("inf")), layout.k_pickups)
        kk = idx.shape[-1]
        pts = orders.pickup.gather(1, idx.reshape(B, -1, 1).expand(B, N * kk, 2))
        rel = pts.view(B, N, kk, 2) - agent_pos.unsqueeze(2)
        feats = torch.cat([rel, torch.ones_like(rel[..., :1])], dim=-1)
        parts.append(_slots(feats, fin, layout.k_pickups))
    if layout.k_agents:
        if pair is None:
            raise ValueError("observe_lifelong: pair is needed when layout.k_agents > 0")
        d_a = pair.masked_fill(eye | (pair > sensing_range), float("inf"))
        idx, fin = nearest_index(d_a, layout.k_agents)
        kk = idx.shape[-1]
        at = idx.reshape(B, -1, 1).expand(B, N * kk, 2)
        pos_j = agent_pos.gather(1, at).view(B, N, kk, 2)
        vel_j = agent_vel.gather(1, at).view(B, N, kk, 2)
        delta = agent_pos.unsqueeze(2) - pos_j
        feats = torch.cat([-delta, vel_j, torch.ones_like(delta[..., :1])], dim=-1)
        parts.append(_slots(feats, fin, layout.k_agents))
    return torch.cat(parts, dim=-1)


def lifelong_global_state(agent_pos: Tensor, agent_vel: Tensor, agent_status: Tensor,
                          target: Tensor, has_target: Tensor) -> Tensor:
    """Global state of a lifelong floor for centralized critics, (B, 11 N): every AGV's
    position, velocity, status one-hot, target and target mask."""
    B = agent_pos.shape[0]
    dtype = agent_pos.dtype
    status = torch.nn.functional.one_hot(agent_status.long(), 4).to(dtype)
    per = torch.cat([agent_pos, agent_vel, status, target, has_target.to(dtype).unsqueeze(-1)],
                    dim=-1)
    return per.reshape(B, -1)
