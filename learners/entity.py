"""Entity-token learners: one set of weights for any fleet size N (issue 17).

An observation (:class:`sim.observations.ObsLayout`) is read as **tokens**: the AGV's own
state, its K nearest task slots and its K nearest AGV slots, each slot with its mask bit.
Every network here is built from parts shared across AGVs and across tokens, and pools tokens
with masked attention, so

* the output does not depend on the order of the task (or AGV) slots (permutation invariance),
* padded slots (mask 0) do not change it, whatever their values, and neither does the number
  of slots K (a scene with K = 3 or K = 6 slots is read by the same weights),
* the parameter count depends on neither N nor K.

Two learners are registered (``learners.algorithms.ALGORITHMS``):

``maddpg-e`` (:class:`MADDPGE`)
    A decentralized actor shared by all AGVs (:class:`EntityActor`) and a centralized critic
    shared by all AGVs (:class:`PooledCritic`): Q_i reads AGV i's own tokens and action and the
    mean of the other AGVs' (observation, action) embeddings, so its cost grows linearly with
    N and its parameters do not depend on N. The actor update is MADDPG's: AGV i's action is
    replaced by mu(o_i), the other AGVs' actions are the stored ones.
``bicnet-e`` (:class:`BiCNetE`)
    BiCNet's communication kept: the per-AGV token embeddings go through a bidirectional GRU
    along the AGVs, which are ordered by a fixed rule (their position, x then y; not their
    index), then shared output layers. Actor and critic have that shape; the actor update is
    BiCNet's (every AGV's action credited with its effect on every Q).

On a lifelong floor (``lifelong=True``, :func:`lifelong_tokens`) the tokens are the AGV's own
state, its target (with the next waypoint round the shelves, :mod:`learners.floor`), the K
nearest open pickups, the K nearest AGVs and the nearest obstacle points.

``docs/learners.md`` ("Entity policies", "Lifelong operation") lists every change to the
papers' designs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from learners.buffer import Batch
from learners.common import (
    ActorCritic,
    OffPolicyConfig,
    check_bool,
    check_int,
    check_real,
    movable_mask,
)
from learners.floor import FloorWaypoints, obstacle_points
from sim.observations import AGENT_FEATURES, TASK_FEATURES, LifelongObsLayout, ObsLayout
from sim.world import Physics

__all__ = [
    "EntityConfig", "MADDPGEConfig", "BiCNetEConfig", "MADDPGE", "BiCNetE", "EntityEncoder",
    "EntityActor", "WaypointHead", "TaskChoiceHead", "arrive_action", "PooledCritic",
    "SortedBiRNN", "Tokens", "tokens",
    "infer_layout", "agent_order", "SELF_FEATURES", "TASK_TOKEN_FEATURES", "AGENT_TOKEN_FEATURES",
    "MARGIN_CLIP", "lifelong_tokens", "heard_idle", "LIFELONG_SELF_FEATURES",
    "PICKUP_TOKEN_FEATURES",
    "TARGET_TOKEN_FEATURES", "OBSTACLE_TOKEN_FEATURES", "PATH_CLIP", "sizes_look_lifelong",
]

SELF_FEATURES = 3
"""Own-state token: velocity (2) and the "holds a task" bit. The absolute position is left
out: the open box grows with N (half-width sqrt(N / 6)), so positions seen at N = 50 lie
outside every position seen in training at N <= 20."""
TASK_TOKEN_FEATURES = 5
"""Task token: relative position (2), distance, the margin (nearest visible other AGV's
distance to the task minus this AGV's, clipped to [-MARGIN_CLIP, MARGIN_CLIP]; +MARGIN_CLIP
when no other AGV is visible) and whether another AGV is visible at all."""
AGENT_TOKEN_FEATURES = 5
"""AGV token: relative position (2), velocity (2), distance; with
:attr:`EntityConfig.parked_token` (episodic) a sixth feature, the parked bit, and with
:attr:`EntityConfig.idle_token` (lifelong) the idle bit."""
MARGIN_CLIP = 1.0
"""Clip of the task tokens' margin feature (world units)."""
LIFELONG_SELF_FEATURES = 7
"""Lifelong own-state token: velocity (2), status one-hot (4: idle, to pickup, loaded,
broken) and the "in service" bit. No absolute position, as in the episodes."""
TARGET_TOKEN_FEATURES = 6
"""Lifelong target token (the AGV's own order's pickup or drop-off; masked when it has none):
the next waypoint toward it relative to the AGV (2) and its distance, the shortest-path length
to the target (clipped to PATH_CLIP), the straight-line offset to the target (2)."""
PICKUP_TOKEN_FEATURES = 8
"""Lifelong open-pickup token: relative position (2), distance, the next waypoint toward it
relative to the AGV (2), the shortest-path length (clipped to PATH_CLIP), the margin and the
"another AGV visible" bit of the episodic task token."""
OBSTACLE_TOKEN_FEATURES = 3
"""Obstacle token: the nearest point of a shelf or wall relative to the AGV (2), its distance
(the OBSTACLE_SLOTS nearest within learners.floor.OBSTACLE_RANGE)."""
PATH_CLIP = 10.0
"""Clip of the shortest-path lengths in lifelong tokens (world units)."""
HEAD_GAIN = 2.0
"""Initial gain of :class:`WaypointHead` (pre-tanh action per unit heading: tanh(2) = 0.96)."""
HEAD_TARGET_BIAS = 4.0
"""Initial score bonus of the AGV's own target in :class:`WaypointHead`."""
HEAD_PATH_WEIGHT = 1.0
"""Initial score penalty per unit of path length to an open pickup in :class:`WaypointHead`."""
CHOICE_DIST_WEIGHT = 2.0
"""Initial score penalty per unit of distance to a task in :class:`TaskChoiceHead` (the
untrained head drives mostly at the nearest visible task)."""
CHOICE_SPEED = 2.0
"""Speed cap of :func:`arrive_action` (the terminal speed of a unit action along a diagonal)."""
EPISODIC_PHYSICS = Physics()
"""The physics :func:`arrive_action` is computed for: the episodic scenarios' (the default,
which the lifelong floors share); :meth:`EntityLearner.reset` refuses a choice-head or
waypoint-drive learner an env with other physics."""
DRIVE_GAIN = 4.0
"""Velocity command per unit of offset to the next waypoint with
:attr:`EntityConfig.waypoint_drive`: the gain of ``allocator.dispatch.WaypointDriver``, the
classical dispatchers' driver (and the lifelong teachers'), so that the taught head drives
as its teacher does."""
DRIVE_SPEED = 1.2
"""Speed cap with :attr:`EntityConfig.waypoint_drive`: ``WaypointDriver``'s."""


# ---------------------------------------------------------------------- tokens
def infer_layout(num_agents: int, obs_dim: int) -> ObsLayout:
    """The observation layout of an ``NvM`` or ``warehouse`` scene from N and O alone.

    Those scenarios observe ``k_agents = min(N - 1, 5)`` AGV slots; the task slots follow from
    O = 5 + 3 k_tasks + 5 k_agents. Other layouts must be given (:meth:`EntityLearner.reset`
    or :meth:`EntityLearner.set_layout`).

    Raises
    ------
    ValueError
        If no layout with ``min(N - 1, 5)`` AGV slots has size O.
    """
    k_agents = min(int(num_agents) - 1, 5)
    rest = int(obs_dim) - 5 - len(AGENT_FEATURES) * k_agents
    if k_agents < 0 or rest < 0 or rest % len(TASK_FEATURES):
        raise ValueError(f"cannot read observations of size {obs_dim} for {num_agents} AGVs as "
                         f"an NvM layout (5 + 3 k_tasks + 5 min(N - 1, 5)); give the layout "
                         f"with set_layout(env.obs_layout) or reset(env)")
    return ObsLayout(rest // len(TASK_FEATURES), k_agents)


def sizes_look_lifelong(obs_dim: int, state_dim: int, num_agents: int) -> bool:
    """Whether (O, S, N) are a lifelong floor's sizes rather than an episodic scene's: S = 11 N
    (:meth:`sim.LifelongEnv.global_state`) and O no episodic layout for N AGVs."""
    if int(state_dim) != 11 * int(num_agents):
        return False
    try:
        infer_layout(num_agents, obs_dim)
    except ValueError:
        return True
    return False


@dataclass
class Tokens:
    """An observation read as tokens (B batch, N AGVs, Kt task slots, Ka AGV slots)."""

    own: Tensor
    """(B, N, SELF_FEATURES)"""
    task: Tensor
    """(B, N, Kt, TASK_TOKEN_FEATURES), zero in masked slots"""
    task_mask: Tensor
    """(B, N, Kt) bool"""
    agent: Tensor
    """(B, N, Ka, AGENT_TOKEN_FEATURES), zero in masked slots"""
    agent_mask: Tensor
    """(B, N, Ka) bool"""
    target: Tensor | None = None
    """Lifelong only: (B, N, 1, TARGET_TOKEN_FEATURES), zero when masked"""
    target_mask: Tensor | None = None
    """Lifelong only: (B, N, 1) bool"""
    obstacle: Tensor | None = None
    """Lifelong only: (B, N, OBSTACLE_SLOTS, OBSTACLE_TOKEN_FEATURES), zero when masked"""
    obstacle_mask: Tensor | None = None
    """Lifelong only: (B, N, OBSTACLE_SLOTS) bool"""
    pos: Tensor | None = None
    """(B, N, 2) the AGV's own position, which the observation holds (read only by the
    choice head's intent exchange, :attr:`EntityConfig.choice_rounds`, and the lifelong
    drive's sight line, :attr:`EntityConfig.drive_sight`)"""
    floor: FloorWaypoints | None = None
    """Lifelong only: the floor the tokens were read on (its paths, for
    :attr:`EntityConfig.drive_sight`)"""


def _slots(obs: Tensor, tasks: slice, agents: slice, kt: int,
           ka: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The task (or pickup) and AGV slots of observations (B, N, O), zeroed where masked.

    Returns
    -------
    t_rel (B, N, kt, 2), t_mask (B, N, kt), t_dist (B, N, kt), a_rel (B, N, ka, 2),
    a_mask (B, N, ka), a_vel (B, N, ka, 2)
    """
    B, N, _ = obs.shape
    t = obs[..., tasks].reshape(B, N, kt, len(TASK_FEATURES))
    a = obs[..., agents].reshape(B, N, ka, len(AGENT_FEATURES))
    t_mask, a_mask = t[..., 2] > 0.5, a[..., 4] > 0.5
    t_rel = t[..., :2] * t_mask.unsqueeze(-1)
    a_rel = a[..., :2] * a_mask.unsqueeze(-1)
    a_vel = a[..., 2:4] * a_mask.unsqueeze(-1)
    return t_rel, t_mask, torch.linalg.vector_norm(t_rel, dim=-1), a_rel, a_mask, a_vel


def tokens(obs: Tensor, layout: ObsLayout, margin_moving: bool = False,
           parked_token: bool = False) -> Tokens:
    """Split observations into masked tokens and derive the token features.

    Parameters
    ----------
    obs : Tensor, shape (B, N, layout.size)
    layout : ObsLayout
    margin_moving : bool
        The task tokens' margin and "another AGV visible" features count only the visible
        AGVs with a nonzero velocity (parked AGVs stand exactly still), see
        :attr:`EntityConfig.margin_moving`; False: every visible AGV.
    parked_token : bool
        The AGV tokens get a sixth feature, 1.0 for a visible AGV that stands exactly still
        (parked), see :attr:`EntityConfig.parked_token`.

    Returns
    -------
    Tokens
    """
    kt, ka = layout.k_tasks, layout.k_agents
    own = torch.cat([obs[..., layout.vel], obs[..., layout.holding]], dim=-1)
    t_rel, t_mask, t_dist, a_rel, a_mask, a_vel = _slots(obs, layout.tasks, layout.agents,
                                                          kt, ka)
    # margin: distance of the nearest visible other AGV to each task slot minus this AGV's
    moving = (a_vel != 0).any(-1)
    rivals = a_mask & moving if margin_moving else a_mask
    margin, seen = _margin(t_rel, t_dist, a_rel, rivals)
    task = torch.stack([t_rel[..., 0], t_rel[..., 1], t_dist, margin, seen], dim=-1)
    parts = [a_rel, a_vel, torch.linalg.vector_norm(a_rel, dim=-1, keepdim=True)]
    if parked_token:
        parts.append((a_mask & ~moving).unsqueeze(-1).to(obs.dtype))
    agent = torch.cat(parts, dim=-1)
    return Tokens(own, task * t_mask.unsqueeze(-1), t_mask, agent * a_mask.unsqueeze(-1),
                  a_mask, pos=obs[..., layout.pos])


def _margin(t_rel: Tensor, t_dist: Tensor, a_rel: Tensor, a_mask: Tensor) -> tuple[Tensor, Tensor]:
    """The task tokens' margin and "another AGV visible" features, (B, N, Kt) each."""
    ka = a_rel.shape[-2]
    other = torch.linalg.vector_norm(t_rel.unsqueeze(3) - a_rel.unsqueeze(2), dim=-1)
    other = other.masked_fill(~a_mask.unsqueeze(2), math.inf)
    nearest_other = other.amin(-1) if ka else torch.full_like(t_dist, math.inf)
    margin = (nearest_other - t_dist).clamp(-MARGIN_CLIP, MARGIN_CLIP)
    seen = a_mask.any(-1, keepdim=True).expand_as(t_dist).to(t_dist.dtype)
    return margin, seen


def lifelong_tokens(obs: Tensor, layout: LifelongObsLayout, floor: FloorWaypoints,
                    idle_token: bool = False) -> Tokens:
    """Split lifelong observations into masked tokens (``docs/learners.md``, "Lifelong
    operation").

    Own state, the AGV's target (one slot), the K nearest open pickups, the K nearest other
    AGVs, and the nearest obstacle points. Waypoints, path lengths and obstacle points come
    from ``floor`` at the AGV's absolute position (which the observation holds).

    Parameters
    ----------
    obs : Tensor, shape (B, N, layout.size)
    layout : LifelongObsLayout
    floor : FloorWaypoints
        Of the floor the observations come from.
    idle_token : bool
        The AGV tokens get a sixth feature, the idle bit of the AGV in the slot, and the
        pickup tokens' margin and "another AGV visible" count the idle AGVs only
        (:attr:`EntityConfig.idle_token`). Each slot is matched to the AGV of the same floor
        at its position (:func:`heard_idle`), so ``obs`` must hold whole floors.

    Returns
    -------
    Tokens
        With ``target``, ``target_mask``, ``obstacle``, ``obstacle_mask``, ``pos`` and
        ``floor`` set.
    """
    B, N, _ = obs.shape
    kt, ka = layout.k_pickups, layout.k_agents
    pos = obs[..., layout.pos]
    own = torch.cat([obs[..., layout.vel], obs[..., layout.status], obs[..., layout.service]],
                    dim=-1)
    # the target: waypoint, path length, straight offset
    g_mask = obs[..., layout.target_mask] > 0.5  # (B, N, 1)
    g_rel = obs[..., layout.target_rel] * g_mask
    g_wp, g_len = floor.query(pos, pos + g_rel, g_mask.squeeze(-1))
    g_wp_rel = (g_wp - pos) * g_mask
    target = torch.cat([g_wp_rel, torch.linalg.vector_norm(g_wp_rel, dim=-1, keepdim=True),
                        g_len.clamp_max(PATH_CLIP).unsqueeze(-1) * g_mask, g_rel], dim=-1)
    # the open pickups
    t_rel, t_mask, t_dist, a_rel, a_mask, a_vel = _slots(obs, layout.pickups, layout.agents,
                                                          kt, ka)
    at = pos.unsqueeze(2).expand(B, N, kt, 2)
    p_wp, p_len = floor.query(at, at + t_rel, t_mask)
    p_wp_rel = p_wp - at
    parts = [a_rel, a_vel, torch.linalg.vector_norm(a_rel, dim=-1, keepdim=True)]
    rivals = a_mask
    if idle_token:
        idle = heard_idle(obs, layout, a_rel, a_mask)
        parts.append(idle.unsqueeze(-1).to(obs.dtype))
        rivals = idle
    margin, seen = _margin(t_rel, t_dist, a_rel, rivals)
    task = torch.cat([t_rel, t_dist.unsqueeze(-1), p_wp_rel,
                      p_len.clamp_max(PATH_CLIP).unsqueeze(-1), margin.unsqueeze(-1),
                      seen.unsqueeze(-1)], dim=-1)
    agent = torch.cat(parts, dim=-1)
    o_rel, o_mask = obstacle_points(floor.world, pos)
    obstacle = torch.cat([o_rel, torch.linalg.vector_norm(o_rel, dim=-1, keepdim=True)], -1)
    return Tokens(own, task * t_mask.unsqueeze(-1), t_mask, agent * a_mask.unsqueeze(-1),
                  a_mask, (target * g_mask).unsqueeze(-2), g_mask,
                  obstacle * o_mask.unsqueeze(-1), o_mask, pos=pos, floor=floor)


def heard_idle(obs: Tensor, layout: LifelongObsLayout, a_rel: Tensor, a_mask: Tensor) -> Tensor:
    """Whether the AGV in each visible AGV slot is idle, as that AGV tells it
    (:attr:`EntityConfig.idle_token`), (B, N, Ka) bool.

    Each slot is matched to the AGV of the same floor nearest to the position the slot
    gives (the observation's offsets are exact to float rounding, and no two AGVs share a
    position), and that AGV's own status one-hot says whether it is idle.

    Parameters
    ----------
    obs : Tensor, shape (B, N, layout.size)
        Whole floors: every AGV's observation.
    layout : LifelongObsLayout
    a_rel : Tensor, shape (B, N, Ka, 2)
        The AGV slots' offsets.
    a_mask : Tensor of bool, shape (B, N, Ka)

    Returns
    -------
    Tensor of bool, shape (B, N, Ka)
        False in masked slots.
    """
    B, N, ka, _ = a_rel.shape
    if not ka:
        return a_mask
    pos = obs[..., layout.pos]
    seen = pos.unsqueeze(2) + a_rel  # (B, N, Ka, 2)
    gap = torch.linalg.vector_norm(seen.unsqueeze(3) - pos[:, None, None], dim=-1)
    who = gap.argmin(-1)  # (B, N, Ka)
    idle = obs[..., layout.status][..., 0] > 0.5  # (B, N)
    return idle.unsqueeze(1).expand(B, N, N).gather(2, who) & a_mask


def agent_order(obs: Tensor, layout: ObsLayout | LifelongObsLayout) -> Tensor:
    """The fixed order of the AGVs along BiCNet-E's recurrence: by x, then y, then index.

    Parameters
    ----------
    obs : Tensor, shape (B, N, O)

    Returns
    -------
    Tensor of int64, shape (B, N)
        ``order[b, r]`` is the AGV at rank r.
    """
    pos = obs[..., layout.pos]
    by_y = torch.argsort(pos[..., 1], dim=1, stable=True)
    x = pos[..., 0].gather(1, by_y)
    return by_y.gather(1, torch.argsort(x, dim=1, stable=True))


# ---------------------------------------------------------------------- networks
def _mlp(sizes: list[int], last_relu: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2 or last_relu:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def _pointer_layers(hidden: int) -> tuple[nn.Sequential, nn.Sequential]:
    """A pointer head's score MLP ([h, e_k] -> 1) and its residual MLP (h -> 2), the
    residual's last layer at a tenth of its usual scale and without bias, so that the
    untrained head's action is mostly its pointer's."""
    score = _mlp([2 * hidden, hidden, 1], last_relu=False)
    residual = _mlp([hidden, hidden, 2], last_relu=False)
    with torch.no_grad():
        residual[-1].weight.mul_(0.1)
        residual[-1].bias.zero_()
    return score, residual


def _masked_softmax(logits: Tensor, mask: Tensor) -> Tensor:
    """Softmax over the last axis where ``mask`` (same shape, bool) holds: masked entries get
    weight exactly 0 (exp(-1e9 - top) is 0), and a row with none visible all zeros."""
    logits = logits.masked_fill(~mask, -1e9)
    w = torch.exp(logits - logits.amax(-1, keepdim=True).detach()) * mask
    return w / w.sum(-1, keepdim=True).clamp_min(1e-30)


class _AttentionPool(nn.Module):
    """Masked single-head attention of a query (the own-state embedding) over tokens.

    A slot whose mask is 0 gets weight exactly 0 and its value is zeroed before the sum, so
    its content never reaches the output; with no visible token the pooled vector is 0.
    """

    def __init__(self, hidden: int) -> None:
        super().__init__()
        self.query = nn.Linear(hidden, hidden, bias=False)
        self.key = nn.Linear(hidden, hidden, bias=False)
        self.scale = 1.0 / math.sqrt(hidden)

    def forward(self, own: Tensor, emb: Tensor, mask: Tensor) -> Tensor:
        """(..., H), (..., K, H), (..., K) bool -> (..., H)."""
        if emb.shape[-2] == 0:
            return own.new_zeros(own.shape)
        # q . (W_k e) = (q W_k) . e: one (H, H) product per AGV, not one per token; K is
        # small (<= 6 here), so a broadcast product beats K-long batched matrix products
        qk = self.query(own) @ self.key.weight
        logits = (qk.unsqueeze(-2) * emb).sum(-1) * self.scale
        w = _masked_softmax(logits, mask)
        values = emb.masked_fill(~mask.unsqueeze(-1), 0.0)
        return (w.unsqueeze(-1) * values).sum(-2)


class EntityEncoder(nn.Module):
    """Own state + task tokens + AGV tokens -> one embedding per AGV, (B, N, H).

    Token encoders are shared by all slots (and all AGVs); each kind of token is pooled by
    masked attention with the own-state embedding as the query. With ``lifelong`` the tokens
    are :func:`lifelong_tokens`' (pickup tokens for task tokens) and two more kinds are pooled
    the same way: the AGV's target (one slot) and the obstacle points. ``agent_bit``: the
    AGV tokens carry a sixth feature, the parked bit (:attr:`EntityConfig.parked_token`,
    episodic) or the idle bit (:attr:`EntityConfig.idle_token`, lifelong).
    """

    def __init__(self, hidden: int, lifelong: bool = False, agent_bit: bool = False) -> None:
        super().__init__()
        self.lifelong = lifelong
        self.own = _mlp([LIFELONG_SELF_FEATURES if lifelong else SELF_FEATURES, hidden])
        self.task = _mlp([PICKUP_TOKEN_FEATURES if lifelong else TASK_TOKEN_FEATURES, hidden])
        self.agent = _mlp([AGENT_TOKEN_FEATURES + int(agent_bit), hidden])
        self.task_pool = _AttentionPool(hidden)
        self.agent_pool = _AttentionPool(hidden)
        kinds = 3
        if lifelong:
            self.target = _mlp([TARGET_TOKEN_FEATURES, hidden])
            self.obstacle = _mlp([OBSTACLE_TOKEN_FEATURES, hidden])
            self.target_pool = _AttentionPool(hidden)
            self.obstacle_pool = _AttentionPool(hidden)
            kinds = 5
        self.out = _mlp([kinds * hidden, hidden])

    def forward(self, tok: Tokens) -> Tensor:
        """Tokens -> (B, N, H)."""
        return self.encode(tok)[0]

    def encode(self, tok: Tokens) -> tuple[Tensor, Tensor, Tensor | None]:
        """Tokens -> the embedding (B, N, H), the task (lifelong: pickup) token embeddings
        (B, N, Kt, H) and, lifelong, the target token's (B, N, 1, H) (else None)."""
        own = self.own(tok.own)
        task_emb = self.task(tok.task)
        task = self.task_pool(own, task_emb, tok.task_mask)
        agent = self.agent_pool(own, self.agent(tok.agent), tok.agent_mask)
        parts = [own, task, agent]
        target_emb = None
        if self.lifelong:
            if tok.target is None or tok.obstacle is None:
                raise ValueError("a lifelong entity network reads lifelong tokens "
                                 "(lifelong_tokens), got episodic ones")
            target_emb = self.target(tok.target)
            parts.append(self.target_pool(own, target_emb, tok.target_mask))
            parts.append(self.obstacle_pool(own, self.obstacle(tok.obstacle),
                                            tok.obstacle_mask))
        return self.out(torch.cat(parts, dim=-1)), task_emb, target_emb


class WaypointHead(nn.Module):
    """The lifelong actors' head: steer along the waypoint of a chosen target.

    pre-tanh action = ``gain`` x sum_k w_k u_k + residual(h), where k runs over the AGV's own
    target and its K nearest open pickups, u_k is the unit vector to k's next waypoint round
    the shelves (from the tokens), w = softmax over the visible candidates of
    ``score([h, e_k]) + prior_k`` (e_k: the candidate's token embedding, h: the AGV's), and
    the prior is ``target_bias`` for the own target and ``-path_weight`` x path length for a
    pickup. ``gain``, ``target_bias`` and ``path_weight`` are trained with the rest; they
    start at :data:`HEAD_GAIN`, :data:`HEAD_TARGET_BIAS` and :data:`HEAD_PATH_WEIGHT`, and the
    residual's last layer starts at a tenth of its usual scale, so that the untrained policy
    drives to its target, or when idle toward the nearest open pickup by path, and training
    changes which candidate, how fast, and how to pass the others (``docs/learners.md``,
    "Lifelong operation"). The gradient reaches every parameter through the softmax weights.

    With ``drive`` (:attr:`EntityConfig.waypoint_drive`) the output is the action itself:
    the candidate of the largest weight is chosen outright, and the AGV drives at its next
    waypoint as ``allocator.dispatch.WaypointDriver`` does (:func:`arrive_action` at gain
    :data:`DRIVE_GAIN`, capped at :data:`DRIVE_SPEED`; it brakes with no candidate in view).
    ``gain`` and the residual are then not used, and no gradient reaches the action: such a
    head is taught its choice by imitation (the weights' cross-entropy), not by a critic.
    With ``sight`` too (:attr:`EntityConfig.drive_sight`) it drives at the first corner of
    the chosen candidate's path (:meth:`sim.floor_paths.FloorWaypoints.sight` on the tokens'
    floor) instead of the token's waypoint.
    """

    def __init__(self, hidden: int, drive: bool = False, sight: bool = False) -> None:
        super().__init__()
        self.score, self.residual = _pointer_layers(hidden)
        self.gain = nn.Parameter(torch.tensor(HEAD_GAIN))
        self.target_bias = nn.Parameter(torch.tensor(HEAD_TARGET_BIAS))
        self.path_weight = nn.Parameter(torch.tensor(HEAD_PATH_WEIGHT))
        self.drive = drive
        self.sight = sight

    def forward(self, h: Tensor, task_emb: Tensor, target_emb: Tensor, tok: Tokens
                ) -> tuple[Tensor, Tensor]:
        """(B, N, H), (B, N, Kt, H), (B, N, 1, H), lifelong tokens -> (B, N, 2) pre-tanh and
        the weights w (B, N, 1 + Kt) over the candidates (the own target first), zero where
        masked."""
        assert tok.target is not None and tok.target_mask is not None
        emb = torch.cat([target_emb, task_emb], dim=-2)  # (B, N, 1 + Kt, H)
        mask = torch.cat([tok.target_mask, tok.task_mask], dim=-1)
        wp = torch.cat([tok.target[..., 0:2], tok.task[..., 3:5]], dim=-2)
        length = torch.cat([tok.target[..., 3], tok.task[..., 5]], dim=-1)
        kind = torch.zeros_like(length)
        kind[..., 0] = 1.0
        prior = self.target_bias * kind - self.path_weight * length * (1.0 - kind)
        logits = self.score(torch.cat([h.unsqueeze(-2).expand_as(emb), emb], dim=-1))
        w = _masked_softmax(logits.squeeze(-1) + prior, mask)
        if self.drive:
            pick = nn.functional.one_hot(w.argmax(-1), w.shape[-1]).to(w.dtype) * mask
            if not self.sight:
                goal = (pick.unsqueeze(-1) * wp).sum(-2).detach()  # 0 (brake): none in view
            elif tok.floor is None or tok.pos is None:
                raise ValueError("a sight-line drive needs tokens read on a floor "
                                 "(lifelong_tokens)")
            else:  # the chosen candidate's straight offset, then its path's first corner
                off = torch.cat([tok.target[..., 4:6], tok.task[..., 0:2]], dim=-2)
                off = (pick.unsqueeze(-1) * off).sum(-2).detach()
                at = tok.pos.detach()
                goal = tok.floor.sight(at, at + off, pick.sum(-1) > 0) - at
            return arrive_action(goal, tok.own[..., 0:2], EPISODIC_PHYSICS, DRIVE_SPEED,
                                 DRIVE_GAIN), w
        unit = wp / torch.linalg.vector_norm(wp, dim=-1, keepdim=True).clamp_min(1e-6)
        return self.gain * (w.unsqueeze(-1) * unit).sum(-2) + self.residual(h), w


def arrive_action(rel: Tensor, vel: Tensor, physics: Physics = EPISODIC_PHYSICS,
                  max_speed: float = CHOICE_SPEED, gain: float | None = None) -> Tensor:
    """The action that drives an AGV at an offset and stops on it.

    Velocity command ``gain x rel`` (by default ``rel / dt``: arrive in one step) capped at
    ``max_speed``, turned into the MPE acceleration for the AGV's velocity and scaled (not
    clipped: the direction is kept) into [-1, 1]^2.

    Parameters
    ----------
    rel : Tensor, shape (..., 2)
        The goal relative to the AGV.
    vel : Tensor, shape (..., 2)
        The AGV's velocity (broadcast against ``rel``).
    physics : Physics
    max_speed : float
    gain : float or None
        Velocity per unit of offset (None: ``1 / physics.dt``).

    Returns
    -------
    Tensor, shape (..., 2)
    """
    v = rel / physics.dt if gain is None else rel * gain
    speed = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    v = v * (max_speed / speed.clamp_min(1e-12)).clamp_max(1.0)
    a = (v - (1.0 - physics.damping) * vel) / (physics.sensitivity * physics.dt / physics.mass)
    return a / a.abs().amax(-1, keepdim=True).clamp_min(1.0)


INTENT_FEATURES = 2
"""Per task slot, what a round of the intent exchange hears (:class:`_Intents`); with
``regret``, :data:`REGRET_FEATURES` more."""
REGRET_FEATURES = 2
"""With :attr:`EntityConfig.choice_regret`: per task slot, the least regret among the nearer
AGVs pointing at it, and the AGV's own regret (:meth:`_Intents.features`)."""
REGRET_CAP = 1.0
"""Regrets (how much farther an AGV's second choice is than its first) are capped here, and
an AGV with no second choice in view has this regret."""
SINKHORN_LOG_SCALE = 0.0
"""Initial log of the learned factor on the choice logits before the assignment exchange
(:attr:`EntityConfig.choice_sinkhorn`; 0: the logits as they are)."""
SINKHORN_TEMPERATURES = (3.0, 30.0)
"""The assignment exchange's inverse temperatures on the (scaled) choice logits: the first
round's and, by default, the last's (:attr:`EntityConfig.choice_sinkhorn_beta`), geometric
in between (:func:`_sinkhorn`)."""
SINKHORN_MAX_BETA = 1e4
"""The largest last-round inverse temperature :attr:`EntityConfig.choice_sinkhorn_beta`
takes."""
SINKHORN_MAX_ROUNDS = 256
"""The most rounds :attr:`EntityConfig.choice_sinkhorn` takes."""
SINKHORN_FLOOR = 1e-6
"""Demands below this count as this in the assignment exchange's price steps (a task no
AGV wants lowers its price by at most log(1e6) / s_t per round)."""
INTENT_MATCH = 1e-4
"""Two positions closer than this are the same task (or AGV) in :class:`_Intents`."""


def _distances(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise distances (G, P, 2), (G, Q, 2) -> (G, P, Q), computed as differences (not
    through a matrix product, whose rounding would blur positions 1e-4 apart)."""
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")


class _Intents:
    """The choice head's intent exchange (:attr:`EntityConfig.choice_rounds`): every idle
    AGV tells the AGVs that see it which task its pointer is on and how far it is from it;
    AGV i hears, for each of its task slots k, how many of the AGVs it sees point at that
    task (``any``) and how many of them are nearer to it than i (``nearer``).

    With ``regret`` every message also carries the sender's regret: how much farther the
    task its pointer weighs second is than the one it points at (capped at
    :data:`REGRET_CAP`, which is also the regret of an AGV with one task in view); AGV i
    hears, for each task slot k, the least regret among the nearer AGVs pointing at k
    (:data:`REGRET_CAP` if none) and its own regret. A nearer AGV with a small regret will
    hardly give the task up; one with a large regret is the one the least total distance
    serves, as in an auction.

    Tasks are told apart by position (AGV i's task k is at ``pos_i + rel_ik``, AGV j's
    pointed task at ``pos_j + rel_j``), AGVs by the relative positions in i's AGV slots,
    so i hears only the AGVs in its own view. Parked AGVs (the holding bit) point at nothing.
    Computed for a batch of scenes at once over the (B, N, N) pairs: O(B N^2 K_a) to find
    who hears whom, then O(B N^2 K_t) per round.
    """

    def __init__(self, tok: Tokens, regret: bool = False) -> None:
        if tok.pos is None:
            raise ValueError("the intent exchange needs the AGVs' positions (Tokens.pos)")
        self.tok = tok
        self.regret = regret
        pos = tok.pos
        self.tasks = pos.unsqueeze(-2) + tok.task[..., 0:2]  # (B, N, Kt, 2)
        idle = tok.own[..., 2] < 0.5
        # hears[b, i, j]: AGV j (idle, not i) is in one of AGV i's AGV slots
        B, n, _ = pos.shape
        offset = pos.unsqueeze(1) - pos.unsqueeze(2)  # (B, i, j, 2): j relative to i
        near = _distances(offset.reshape(B * n, n, 2),
                          tok.agent[..., 0:2].reshape(B * n, -1, 2)).reshape(B, n, n, -1)
        seen = ((near < INTENT_MATCH) & tok.agent_mask.unsqueeze(2)).any(-1)
        self.hears = seen & idle.unsqueeze(1) & ~torch.eye(n, dtype=torch.bool,
                                                            device=pos.device)

    def features(self, w: Tensor) -> Tensor:
        """The choice weights (B, N, Kt) -> (B, N, Kt, F): ``any`` and ``nearer`` (counts),
        with ``regret`` also the least regret among the nearer pointers and the AGV's own
        (F = :data:`INTENT_FEATURES` (+ :data:`REGRET_FEATURES`); 0 in masked slots)."""
        tok = self.tok
        B, N, K = w.shape
        top = w.argmax(-1, keepdim=True)  # (B, N, 1)
        has = tok.task_mask.any(-1)
        aim = torch.gather(self.tasks, 2, top.unsqueeze(-1).expand(B, N, 1, 2)).squeeze(2)
        dist = torch.gather(tok.task[..., 2], 2, top).squeeze(-1)  # (B, N)
        # same[b, i, k, j]: AGV j points at AGV i's task k
        same = _distances(self.tasks.reshape(B, N * K, 2), aim).reshape(B, N, K, N) \
            < INTENT_MATCH
        same &= (self.hears & has.unsqueeze(1)).unsqueeze(2)
        nearer = same & (dist[:, None, None, :] < tok.task[..., 2].unsqueeze(-1))
        feats = [same.sum(-1).to(w.dtype), nearer.sum(-1).to(w.dtype)]
        if self.regret:
            cap = torch.full_like(dist, REGRET_CAP)
            regret = cap
            if K > 1:  # the visible slot weighed most after the pointed one
                rest = w.masked_fill(~tok.task_mask, -1.0).scatter(-1, top, -2.0)
                nxt = rest.argmax(-1, keepdim=True)
                second = torch.gather(tok.task[..., 2], 2, nxt).squeeze(-1)
                has2 = torch.gather(tok.task_mask, 2, nxt).squeeze(-1)
                regret = torch.where(has2, (second - dist).clamp(0.0, REGRET_CAP), cap)
            least = regret[:, None, None, :].expand(B, N, K, N).masked_fill(~nearer,
                                                                             REGRET_CAP)
            feats += [least.amin(-1), regret.unsqueeze(-1).expand(B, N, K)]
        out = torch.stack(feats, dim=-1)
        return out * tok.task_mask.unsqueeze(-1)


def _task_groups(tasks: Tensor, mask: Tensor) -> Tensor:
    """Which visible task slots hold the same task: (B, N, K, 2) positions, (B, N, K) mask ->
    (B, N, K) group ids in [0, N K), the same for every slot (of any AGV of the scene) whose
    positions are within :data:`INTENT_MATCH` of each other; masked slots get N K.

    Exact and O(B N K log(N K)): sort by x and split where consecutive x differ by more than
    the tolerance (the copies of a task, read from different AGVs' relative positions, differ
    by rounding only, so they never split), then within each run sort by y and split the same
    way. Two distinct tasks land in one group only if they lie within about twice the
    tolerance of each other in both coordinates."""
    B, N, K, _ = tasks.shape
    M = N * K
    p = tasks.reshape(B, M, 2)
    valid = mask.reshape(B, M)
    far = torch.finfo(p.dtype).max / 4
    x = p[..., 0].masked_fill(~valid, far)
    xs, o1 = x.sort(-1)
    first = torch.ones(B, 1, dtype=torch.bool, device=p.device)
    xrun = torch.cat([first, xs.diff(dim=-1) > INTENT_MATCH], dim=-1).cumsum(-1)
    ys, o2 = p[..., 1].masked_fill(~valid, far).gather(1, o1).sort(dim=-1, stable=True)
    run, o3 = xrun.gather(1, o2).sort(dim=-1, stable=True)
    y = ys.gather(1, o3)
    order = o1.gather(1, o2.gather(1, o3))
    new = torch.cat([first, (run.diff(dim=-1) != 0) | (y.diff(dim=-1) > INTENT_MATCH)], dim=-1)
    ids = torch.empty_like(order).scatter_(1, order, new.cumsum(-1) - 1)
    return ids.masked_fill(~valid, M).reshape(B, N, K)


def _sinkhorn(logits: Tensor, tok: Tokens, hears: Tensor, rounds: int,
              whole: bool | None = None, beta: float = SINKHORN_TEMPERATURES[1]) -> Tensor:
    """The choice head's assignment exchange (:attr:`EntityConfig.choice_sinkhorn`):
    ``rounds`` rounds of an annealed Sinkhorn iteration over the idle AGVs' choice weights,
    with prices on the tasks -> the final weights (B, N, Kt), zero in masked slots.

    AGV i keeps a price g_ik >= 0 on each of its task slots (0 at the start) and weighs
    them by w_i = softmax(s_t (logits_i - g_i)), at an inverse temperature s_t that grows
    geometrically from :data:`SINKHORN_TEMPERATURES`'s first value to ``beta`` over the
    rounds. Each round every idle AGV tells the AGVs that see it its weight on each of its
    tasks; AGV i adds up, for each task slot k, its own weight and those heard on the same
    task (told apart by position, :func:`_task_groups`): the demand c_ik, and moves the
    price by log(c_ik) / s_t (up where more than one AGV's worth wants the task, down where
    less, never below 0). The weights after the last round are the output. With the whole
    scene in view every AGV computes the same demands, and the rounds are the
    epsilon-scaling form of Sinkhorn's iteration for the entropic assignment of AGVs to
    tasks, with at most one AGV per task (Cuturi, 2013; Schmitzer, 2019). They are
    differentiable, so the logits train through them.

    Parameters
    ----------
    logits : Tensor, shape (B, N, Kt)
    tok : Tokens
        Episodic tokens with ``pos``.
    hears : Tensor, shape (B, N, N) bool
        ``hears[b, i, j]``: AGV i hears idle AGV j (j != i), :class:`_Intents`.
    rounds : int
    whole : bool, optional
        Whether every idle AGV hears every other idle AGV (then one demand per task is summed
        for all); None: find out from ``hears``. False computes each listener's own sums.
    beta : float
        The last round's inverse temperature (:attr:`EntityConfig.choice_sinkhorn_beta`).
    """
    B, N, K = logits.shape
    mask = tok.task_mask
    assert tok.pos is not None
    idle = (tok.own[..., 2] < 0.5) & mask.any(-1)
    ids = _task_groups(tok.pos.unsqueeze(-2) + tok.task[..., 0:2], mask)  # (B, N, K)
    flat = ids.reshape(B, N * K)
    who = hears | torch.diag_embed(idle)  # (B, i, j): whose weights i adds up
    # with the whole scene in view every idle AGV hears every other: one sum per task
    if whole is None:
        whole = bool((who == idle.unsqueeze(1)).all(-1)[idle].all())
    index = flat.unsqueeze(1).expand(B, N, N * K)
    first, last = SINKHORN_TEMPERATURES[0], beta
    price = torch.zeros_like(logits)

    def weights(s: float) -> Tensor:
        return _masked_softmax(s * (logits - price), mask)

    for t in range(rounds):
        s = first * (last / first) ** (t / max(rounds - 1, 1))
        w = weights(s) * idle.unsqueeze(-1)
        if whole:  # one demand per task: (B, group)
            tot = w.new_zeros(B, N * K + 1).scatter_add(1, flat, w.reshape(B, N * K))
            col = tot.gather(1, flat).reshape(B, N, K)
        else:  # heard[b, j, i, k]: AGV j's weight on AGV i's task k
            per = w.new_zeros(B, N, N * K + 1).scatter_add(2, ids, w)  # (B, j, group)
            heard = per.gather(2, index).reshape(B, N, N, K)
            col = torch.einsum("bij,bjik->bik", who.to(w.dtype), heard)
        step = torch.log(col.clamp_min(SINKHORN_FLOOR)).masked_fill(~mask, 0.0)
        price = (price + step / s).clamp_min(0.0)
    return weights(last)


class TaskChoiceHead(nn.Module):
    """The episodic actors' choice head (:attr:`EntityConfig.choice_head`): point at a task.

    action = box(sum_k w_k arrive_k + residual(h)), where k runs over the AGV's visible task
    slots, ``arrive_k`` is :func:`arrive_action` toward task k (drive at it and stop on it),
    w = softmax over the visible slots of ``score([h, e_k]) - dist_weight * d_k`` (e_k: the
    task's token embedding, d_k its distance, h: the AGV's embedding) and ``box`` scales a
    vector into [-1, 1]^2 keeping its direction. The output is the action itself, not a
    pre-tanh value. ``dist_weight`` starts at :data:`CHOICE_DIST_WEIGHT`
    and the residual's last layer at a tenth of its usual scale, so that the untrained head
    drives mostly at the nearest task; training changes which task (the softmax is a pointer
    over the task tokens, which an imitation loss can train by cross-entropy, see
    :meth:`EntityLearner.policy_and_choice`) and how to pass the others. With no task visible
    the action is the residual's.

    With ``rounds`` > 0 (BiCNet-E's :attr:`EntityConfig.choice_rounds`) the pointer goes
    through that many rounds of an intent exchange (:class:`_Intents`): each round adds
    ``intent(any_k, nearer_k)`` (an MLP whose last layer starts at zero, so that the untrained
    exchange changes nothing) to the round-0 logits, the counts heard from the pointers of
    the round before. ``regret`` (:attr:`EntityConfig.choice_regret`): the messages also
    carry regrets (:class:`_Intents`). ``accumulate`` (:attr:`EntityConfig.choice_accumulate`):
    each round's bias adds to those of the rounds before instead of replacing them.

    With ``sinkhorn`` > 0 (BiCNet-E's :attr:`EntityConfig.choice_sinkhorn`) the final
    logits, times ``exp(sinkhorn_scale)`` (a learned log-scale that starts at
    :data:`SINKHORN_LOG_SCALE`), go through that many rounds of an assignment exchange
    (:func:`_sinkhorn`) before they weigh the actions.
    """

    def __init__(self, hidden: int, rounds: int = 0, regret: bool = False,
                 accumulate: bool = False, sinkhorn: int = 0,
                 sinkhorn_beta: float = SINKHORN_TEMPERATURES[1]) -> None:
        super().__init__()
        self.score, self.residual = _pointer_layers(hidden)
        self.dist_weight = nn.Parameter(torch.tensor(CHOICE_DIST_WEIGHT))
        self.rounds = rounds
        self.regret = regret
        self.accumulate = accumulate
        self.sinkhorn = sinkhorn
        self.sinkhorn_beta = sinkhorn_beta
        if sinkhorn:
            self.sinkhorn_scale = nn.Parameter(torch.tensor(SINKHORN_LOG_SCALE))
        self.intent = None
        if rounds:
            width = INTENT_FEATURES + (REGRET_FEATURES if regret else 0)
            self.intent = _mlp([width, hidden, 1], last_relu=False)
            with torch.no_grad():  # starts as no exchange: the pointer of round 0
                self.intent[-1].weight.zero_()
                self.intent[-1].bias.zero_()

    def forward(self, h: Tensor, task_emb: Tensor, tok: Tokens) -> tuple[Tensor, Tensor]:
        """(B, N, H), (B, N, Kt, H), episodic tokens -> the action (B, N, 2) in [-1, 1] and
        the choice weights w (B, N, Kt), zero in masked slots."""
        logits = self.score(torch.cat([h.unsqueeze(-2).expand_as(task_emb), task_emb], dim=-1))
        logits = logits.squeeze(-1) - self.dist_weight * tok.task[..., 2]
        w = _masked_softmax(logits, tok.task_mask)
        heard = _Intents(tok, self.regret) if self.intent is not None or self.sinkhorn else None
        if self.intent is not None:
            assert heard is not None
            total = torch.zeros_like(logits)
            for _ in range(self.rounds):
                bias = self.intent(heard.features(w.detach())).squeeze(-1)
                total = total + bias if self.accumulate else bias
                w = _masked_softmax(logits + total, tok.task_mask)
            logits = logits + total
        if self.sinkhorn:
            assert heard is not None
            w = _sinkhorn(logits * self.sinkhorn_scale.exp(), tok, heard.hears, self.sinkhorn,
                          beta=self.sinkhorn_beta)
        drive = arrive_action(tok.task[..., 0:2], tok.own[..., 0:2].unsqueeze(-2))
        a = (w.unsqueeze(-1) * drive).sum(-2) + self.residual(h)
        return a / a.abs().amax(-1, keepdim=True).clamp_min(1.0), w


class EntityActor(nn.Module):
    """Decentralized actor: AGV i's tokens -> its pre-tanh action, (B, N, 2).

    Episodic: an MLP head on the encoder's embedding, or with ``choice_head`` a
    :class:`TaskChoiceHead` (whose output is the action itself). Lifelong:
    :class:`WaypointHead` (with ``waypoint_drive``, its output is the action itself).
    """

    def __init__(self, hidden: int, lifelong: bool = False, agent_bit: bool = False,
                 choice_head: bool = False, waypoint_drive: bool = False,
                 drive_sight: bool = False) -> None:
        super().__init__()
        self.encoder = EntityEncoder(hidden, lifelong, agent_bit)
        self.lifelong = lifelong
        self.choose = TaskChoiceHead(hidden) if choice_head and not lifelong else None
        if lifelong:
            self.steer = WaypointHead(hidden, waypoint_drive, drive_sight)
        elif self.choose is None:
            self.head = _mlp([hidden, hidden, 2], last_relu=False)

    def forward(self, tok: Tokens, order: Tensor | None = None) -> Tensor:
        """Tokens -> (B, N, 2) (``order`` unused: no communication)."""
        return self.forward_choice(tok, order)[0]

    def forward_choice(self, tok: Tokens, order: Tensor | None = None
                       ) -> tuple[Tensor, Tensor | None]:
        """Tokens -> (B, N, 2) and, with a choice head, its weights (B, N, Kt); lifelong, the
        :class:`WaypointHead`'s (B, N, 1 + Kt); else None."""
        if self.choose is not None:
            h, task_emb, _ = self.encoder.encode(tok)
            return self.choose(h, task_emb, tok)
        if not self.lifelong:
            return self.head(self.encoder(tok)), None
        h, task_emb, target_emb = self.encoder.encode(tok)
        assert target_emb is not None
        return self.steer(h, task_emb, target_emb, tok)


class PooledCritic(nn.Module):
    """MADDPG-E's centralized critic, shared by the AGVs.

    Q_i = f(z_i, mean_{j != i} z_j) with z_j = g(encoder(o_j), a_j): every AGV's observation
    and action reach every Q through the mean, whose cost is linear in N and whose weights
    do not depend on N (Lowe et al. concatenate all N observations and actions instead).
    """

    def __init__(self, hidden: int, lifelong: bool = False, agent_bit: bool = False) -> None:
        super().__init__()
        self.encoder = EntityEncoder(hidden, lifelong, agent_bit)
        self.joint = _mlp([hidden + 2, hidden])
        self.head = _mlp([2 * hidden, hidden, 1], last_relu=False)

    def embed(self, tok: Tokens, action: Tensor, encoded: Tensor | None = None) -> Tensor:
        """z, (B, N, H): each AGV's (observation, action) embedding (``encoded``: the
        encoder's output for ``tok`` when already computed)."""
        enc = self.encoder(tok) if encoded is None else encoded
        return self.joint(torch.cat([enc, action], dim=-1))

    @staticmethod
    def others(z: Tensor) -> Tensor:
        """The mean of the other AGVs' embeddings, (B, N, H) (0 when N = 1)."""
        n = z.shape[1]
        return (z.sum(1, keepdim=True) - z) / max(n - 1, 1)

    def q(self, z_own: Tensor, z_others: Tensor) -> Tensor:
        """(B, N, H), (B, N, H) -> (B, N)."""
        return self.head(torch.cat([z_own, z_others], dim=-1)).squeeze(-1)

    def forward(self, tok: Tokens, action: Tensor, order: Tensor | None = None) -> Tensor:
        """Q_i(o, a) for every AGV, (B, N)."""
        z = self.embed(tok, action)
        return self.q(z, self.others(z))


class SortedBiRNN(nn.Module):
    """BiCNet-E's network: entity embeddings -> bidirectional GRU along the AGVs taken in a
    fixed order (:func:`agent_order`) -> shared output layers (the lifelong actor: a
    :class:`WaypointHead` on them).

    Parameters
    ----------
    hidden : int
    out_features : int
        2 (actor) or 1 (critic).
    action_input : bool
        Whether the AGV's action joins its embedding before the recurrence (critic).
    lifelong : bool
        Read lifelong tokens (:func:`lifelong_tokens`).
    agent_bit : bool
        AGV tokens with a sixth feature, the parked bit (:attr:`EntityConfig.parked_token`)
        or the idle bit (:attr:`EntityConfig.idle_token`).
    choice_head : bool
        The episodic actor ends in a :class:`TaskChoiceHead` on the recurrence's output
        (:attr:`EntityConfig.choice_head`); its output is then the action itself.
    choice_rounds : int
        The choice head's rounds of intent exchange (:attr:`EntityConfig.choice_rounds`).
    choice_regret : bool
        The intent messages carry regrets (:attr:`EntityConfig.choice_regret`).
    choice_accumulate : bool
        The rounds' biases add up (:attr:`EntityConfig.choice_accumulate`).
    choice_sinkhorn : int
        Rounds of the assignment exchange (:attr:`EntityConfig.choice_sinkhorn`).
    choice_sinkhorn_beta : float
        Its last round's inverse temperature (:attr:`EntityConfig.choice_sinkhorn_beta`).
    waypoint_drive : bool
        The lifelong actor's head drives at its chosen candidate
        (:attr:`EntityConfig.waypoint_drive`); its output is then the action itself.
    drive_sight : bool
        It drives at the path's first corner (:attr:`EntityConfig.drive_sight`).
    """

    def __init__(self, hidden: int, out_features: int, action_input: bool = False,
                 lifelong: bool = False, agent_bit: bool = False,
                 choice_head: bool = False, choice_rounds: int = 0,
                 choice_regret: bool = False, choice_accumulate: bool = False,
                 choice_sinkhorn: int = 0,
                 choice_sinkhorn_beta: float = SINKHORN_TEMPERATURES[1],
                 waypoint_drive: bool = False, drive_sight: bool = False) -> None:
        super().__init__()
        self.encoder = EntityEncoder(hidden, lifelong, agent_bit)
        self.action_input = action_input
        self.inp = _mlp([hidden + (2 if action_input else 0), hidden])
        self.rnn = nn.GRU(hidden, hidden, batch_first=True, bidirectional=True)
        actor = not action_input and out_features == 2
        # the lifelong actor steers with a WaypointHead on the recurrence's output, an
        # episodic one with choice_head points with a TaskChoiceHead
        self.steer = WaypointHead(hidden, waypoint_drive, drive_sight) \
            if lifelong and actor else None
        self.choose = None
        if choice_head and actor and not lifelong:
            self.choose = TaskChoiceHead(hidden, choice_rounds, choice_regret, choice_accumulate,
                                         choice_sinkhorn, choice_sinkhorn_beta)
        self.head = _mlp([2 * hidden, hidden]
                         if self.steer is not None or self.choose is not None
                         else [2 * hidden, hidden, out_features], last_relu=False)

    def forward(self, tok: Tokens, order: Tensor, action: Tensor | None = None) -> Tensor:
        """(B, N, out): the AGVs' outputs in their own (index) order."""
        return self.forward_choice(tok, order, action)[0]

    def forward_choice(self, tok: Tokens, order: Tensor, action: Tensor | None = None
                       ) -> tuple[Tensor, Tensor | None]:
        """:meth:`forward` and the actor's choice weights (:meth:`EntityActor.forward_choice`;
        None for a critic or an MLP head)."""
        h, task_emb, target_emb = self.encoder.encode(tok)
        if self.action_input:
            if action is None:
                raise ValueError("the BiCNet-E critic needs the actions")
            h = torch.cat([h, action], dim=-1)
        h = self.inp(h)
        at = order.unsqueeze(-1).expand_as(h)
        h, _ = self.rnn(h.gather(1, at))
        out = self.head(h)
        out = torch.empty_like(out).scatter_(1, order.unsqueeze(-1).expand_as(out), out)
        if self.choose is not None:
            return self.choose(torch.relu(out), task_emb, tok)
        if self.steer is None:
            return out, None
        assert target_emb is not None
        return self.steer(torch.relu(out), task_emb, target_emb, tok)


# ---------------------------------------------------------------------- learners
@dataclass
class EntityConfig(OffPolicyConfig):
    """Hyperparameters of the entity learners (``OffPolicyConfig``'s, and ``shield``)."""

    hidden: int = 32
    """Width of every layer (token encoders, attention, heads, GRU directions)."""
    batch_size: int = 512
    """Joint transitions per gradient update (each holds N AGVs' experience)."""
    shield: bool = False
    """Train with :class:`allocator.shield.SafetyShield` in the loop: the exploring action
    goes through the shield and the simulator executes the shield's action, while the policy's
    intended action is what is stored and what the critic is trained on (the shield is part of
    the environment: the critic learns what an intention leads to through it; storing the
    executed action instead did not raise the shielded throughput on warehouse-20, see
    ``docs/learners.md``). Evaluations (and so ``best.safetensors``) run shielded too: the
    policy is chosen in the mode it is trained for."""
    shield_keep_right: float = 0.0
    """With ``shield=True`` on a lifelong floor: the shield's lane angle
    (``SafetyShield(keep_right=...)``, radians in [0, pi/2); 0: none). A learned allocator
    serving these weights with ``shield=True`` uses the same angle."""
    margin_moving: bool = False
    """Episodic task tokens: the margin and "another AGV visible" features count only the
    visible AGVs that move (nonzero velocity in the observation), so that a parked AGV, which
    stands still and will never claim another task, does not make an open task look taken.
    False (the default, and what every run before this field did): every visible AGV counts."""
    parked_token: bool = False
    """Episodic AGV tokens get a sixth feature, the parked bit: 1.0 for a visible AGV that
    stands exactly still (a parked AGV; an idle one never does), so that the policy can tell
    a parked AGV, which it has to go around, from a slow one. It widens the AGV token layer,
    so the weights differ from those without it; a run with it may still start
    (``init_from``) from a checkpoint without it: the new input column starts at zero, which
    gives the checkpoint's actions and Q values (:meth:`EntityLearner.adapt_init_tensors`).
    False (the default, and what every run before this field did): five features."""
    shield_penalty: float = 0.0
    """With ``shield=True``: each AGV's stored reward loses ``shield_penalty`` times the
    length of the shield's change to its action, ``|a_intended - a_executed|`` (0 where the
    shield lets the action through), so that the policy learns to ask for actions the shield
    need not change (e.g. around a parked AGV rather than into it) instead of only learning
    what its intentions lead to. The training return (``train_return``) includes it;
    evaluations report the task metrics and the environment's reward only. 0 (the
    default, and what every run before this field did): no penalty."""

    choice_head: bool = False
    """Episodic actors end in a :class:`TaskChoiceHead`: a softmax pointer over the visible
    task tokens mixes the actions that drive at each task and stop on it, plus a small
    learned residual; the actor's output is then the action itself (no tanh). The actions
    are those of the default physics (:data:`EPISODIC_PHYSICS`; an env with other physics
    is refused). The weights differ from those without it. False (the default, and what
    every run before this field did): an MLP head and a tanh."""
    choice_rounds: int = 0
    """BiCNet-E with ``choice_head``: rounds of intent exchange before the pointer settles.
    Each round every idle AGV tells the AGVs that see it which task its pointer is on and
    how far it is from it, and each AGV's pointer adds a learned function of how many of
    them point at each of its tasks, and how many of those are nearer (BiCNet's
    communication across agents, made explicit; MADDPG-E's actors do not communicate and
    refuse it). 0 (the default, and what every run before this field did): none."""
    choice_regret: bool = False
    """With ``choice_rounds``: each intent message also carries the sender's regret (how much
    farther its second choice is than its first), and each AGV hears, per task, the least
    regret among the nearer AGVs pointing at it, and its own regret (:class:`_Intents`).
    It widens the intent layer's input from 2 to 4 features. False (the default, and what
    every run before this field did): counts only."""
    choice_accumulate: bool = False
    """With ``choice_rounds`` >= 2: each round's learned bias is added to those of the rounds
    before, instead of replacing them, so that a task an AGV gave up in one round is not
    taken up again by every AGV that gave it up (as when each round hears only the pointers
    of the round before, and two AGVs that both drop a task both come back to it). The
    weights are the same as without it. False (the default, and what every run before this
    field did): each round's bias replaces the last."""
    choice_sinkhorn: int = 0
    """BiCNet-E with ``choice_head``: rounds of an assignment exchange after the pointer's
    logits (and the intent rounds, if any) are computed. Each AGV keeps a price on each task
    it sees; each round every idle AGV tells the AGVs that see it its weight on each of its
    tasks, and each AGV raises a task's price where the weights it hears on it (and its own)
    add up to more than one AGV, lowers it (not below 0) where less, and reweighs its tasks
    by their logits less their prices, at a temperature that falls over the rounds: the
    annealed Sinkhorn iteration for the assignment of AGVs to tasks, run as communication
    (:func:`_sinkhorn`). The logits are multiplied by a learned factor first
    (``sinkhorn_scale``, its log starting at 0). It adds one parameter; a run may start from
    weights without it. MADDPG-E refuses it. 0 (the default, and what every run before this
    field did): none."""
    choice_sinkhorn_beta: float = SINKHORN_TEMPERATURES[1]
    """With ``choice_sinkhorn``: the assignment exchange's last inverse temperature (the
    first is :data:`SINKHORN_TEMPERATURES`'s 3, geometric in between), in [3, 1e4]. Higher
    ends nearer a hard assignment; with more rounds the prices have time to follow. It adds
    no parameter, so a policy file trained at one value runs at another. Any other value
    needs ``choice_sinkhorn`` >= 1. 30 (the default, and what every run before this field
    did)."""

    idle_token: bool = False
    """Lifelong AGV tokens get a sixth feature, the idle bit: 1.0 for a visible AGV that is
    idle (no order; :data:`sim.observations.STATUS_FEATURES`), heard from that AGV. Each AGV
    tells the AGVs that see it whether it is idle, so that an AGV weighing an open pickup can
    tell a rival that may claim it from one carrying an order (a one-bit message over the
    range of the view, made explicit; the observation itself does not carry the others'
    status). :func:`lifelong_tokens` matches each AGV slot to the AGV at that position, so
    observations are read as whole floors (B, N, O), as the learners always read them. It
    widens the AGV token layer; a run may start from a lifelong checkpoint without it (the
    new column starts at zero, :meth:`EntityLearner.adapt_init_tensors`). False (the default,
    and what every run before this field did): five features."""
    waypoint_drive: bool = False
    """Lifelong actors: the :class:`WaypointHead` chooses one candidate outright (the own
    target or an open pickup in view, the largest of its weights) and drives at its next
    waypoint round the shelves as the classical dispatchers' ``WaypointDriver`` does (gain
    :data:`DRIVE_GAIN`, speed :data:`DRIVE_SPEED`, the default physics); the actor's output
    is then the action itself (no tanh), and the head's gain and residual are not used. No
    gradient reaches the action through the choice, so such a policy is taught by
    imitation of a teacher's choices (``benchmarks/lifelong_dagger.py --waypoint-drive``),
    not trained by a critic. The weights are those without it, so a run may start from a
    lifelong policy file trained without it. False (the default, and what every run before
    this field did): the head steers along a softmax mix of the candidates' waypoints."""
    drive_sight: bool = False
    """With ``waypoint_drive``: head for the first corner of the chosen candidate's shortest
    path (the farthest path cell in a straight line of sight,
    :meth:`sim.floor_paths.FloorWaypoints.sight`), as ``WaypointDriver`` heads for
    ``FloorDistances.next_waypoint``, instead of the token's waypoint (a fixed number of
    grid cells ahead, whose heading zig-zags along the 8-neighbour grid: 16 degrees off the
    driver's on warehouse-50, median). It adds no parameter. False (the default, and what
    every run before this field did): the token's waypoint."""

    def validate(self) -> None:
        """Check every field (see :meth:`OffPolicyConfig.validate`), ``shield``,
        ``shield_keep_right``, ``margin_moving``, ``parked_token``, ``shield_penalty`` and
        ``choice_head``, ``choice_rounds``, ``choice_regret``, ``choice_accumulate`` and
        ``choice_sinkhorn``, ``choice_sinkhorn_beta``, ``idle_token``, ``waypoint_drive`` and
        ``drive_sight`` too."""
        super().validate()
        self.shield = check_bool("shield", self.shield)
        self.shield_keep_right = check_real("shield_keep_right", self.shield_keep_right, 0.0,
                                            math.pi / 2, high_open=True)
        self.margin_moving = check_bool("margin_moving", self.margin_moving)
        self.parked_token = check_bool("parked_token", self.parked_token)
        self.choice_head = check_bool("choice_head", self.choice_head)
        self.choice_rounds = check_int("choice_rounds", self.choice_rounds, 0, 8)
        if self.choice_rounds and not self.choice_head:
            raise ValueError(f"choice_rounds={self.choice_rounds} exchanges the choice head's "
                             "pointers; it needs choice_head=True")
        self.choice_regret = check_bool("choice_regret", self.choice_regret)
        if self.choice_regret and not self.choice_rounds:
            raise ValueError("choice_regret=True adds regrets to the intent exchange; it needs "
                             "choice_rounds >= 1")
        self.choice_accumulate = check_bool("choice_accumulate", self.choice_accumulate)
        self.choice_sinkhorn = check_int("choice_sinkhorn", self.choice_sinkhorn, 0,
                                         SINKHORN_MAX_ROUNDS)
        if self.choice_sinkhorn and not self.choice_head:
            raise ValueError(f"choice_sinkhorn={self.choice_sinkhorn} exchanges the choice "
                             "head's weights; it needs choice_head=True")
        self.choice_sinkhorn_beta = check_real("choice_sinkhorn_beta", self.choice_sinkhorn_beta,
                                               SINKHORN_TEMPERATURES[0], SINKHORN_MAX_BETA)
        if self.choice_sinkhorn_beta != SINKHORN_TEMPERATURES[1] and not self.choice_sinkhorn:
            raise ValueError(f"choice_sinkhorn_beta={self.choice_sinkhorn_beta} is the "
                             "assignment exchange's last inverse temperature; it needs "
                             "choice_sinkhorn >= 1")
        if self.choice_accumulate and self.choice_rounds < 2:
            raise ValueError("choice_accumulate=True adds the rounds' biases up; it needs "
                             f"choice_rounds >= 2, got {self.choice_rounds}")
        self.shield_penalty = check_real("shield_penalty", self.shield_penalty, 0.0, math.inf,
                                         high_open=True)
        self.waypoint_drive = check_bool("waypoint_drive", self.waypoint_drive)
        self.drive_sight = check_bool("drive_sight", self.drive_sight)
        if self.drive_sight and not self.waypoint_drive:
            raise ValueError("drive_sight=True chooses where the waypoint drive heads; it "
                             "needs waypoint_drive=True")
        self.idle_token = check_bool("idle_token", self.idle_token)
        if self.shield_penalty and not self.shield:
            raise ValueError(f"shield_penalty={self.shield_penalty} charges the shield's "
                             "changes to the actions; it needs shield=True")


@dataclass
class MADDPGEConfig(EntityConfig):
    """Hyperparameters of MADDPG-E (:class:`MADDPGE`)."""


@dataclass
class BiCNetEConfig(EntityConfig):
    """Hyperparameters of BiCNet-E (:class:`BiCNetE`)."""


class EntityLearner(ActorCritic):
    """What MADDPG-E and BiCNet-E share: token parsing, the observation layout, acting.

    Parameters
    ----------
    obs_dim, state_dim, num_agents : int
        The sizes of the scenario it is built for (the weights depend on none of them; the
        layout of the observations is inferred from N and O, see :func:`infer_layout`, until
        :meth:`reset` or :meth:`set_layout` gives it).
    config : EntityConfig
    lifelong : bool, optional
        Networks that read lifelong observations (:func:`lifelong_tokens`), for a lifelong
        floor; their input layers differ from the episodic ones, so one set of weights serves
        one mode. :func:`learners.train.train` and :class:`learners.policy.LearnedPolicy` set
        it from the scenario (it is not a hyperparameter: checkpoints say it through their
        scenario). None (what ``learners.algorithms.make_learner`` passes) infers it from the
        sizes: lifelong when the global state has a lifelong floor's 11 N features and the
        observation size is no episodic layout's for N AGVs (:func:`infer_layout`); an episodic
        scene's sizes always are (its state has 5 N + 3 M features and its observations an
        episodic layout).
    """

    def __init__(self, obs_dim: int, state_dim: int, num_agents: int,
                 config: EntityConfig, lifelong: bool | None = None) -> None:
        super().__init__(obs_dim, state_dim, num_agents, config)
        if lifelong is None:
            lifelong = sizes_look_lifelong(obs_dim, state_dim, num_agents)
        self.lifelong = check_bool("lifelong", lifelong)
        for key in ("margin_moving", "parked_token"):
            if self.lifelong and getattr(self.config, key):
                raise ValueError(f"{key} is for episodic scenarios (parked AGVs); on a "
                                 "lifelong floor no AGV parks: leave it False")
        if self.lifelong and self.config.choice_head:
            raise ValueError("choice_head is for episodic scenarios; lifelong actors steer "
                             "with their own WaypointHead: leave it False")
        if not self.lifelong and self.config.waypoint_drive:
            raise ValueError("waypoint_drive is for lifelong floors (a WaypointHead); episodic "
                             "actors drive at a chosen task with choice_head=True")
        if not self.lifelong and self.config.idle_token:
            raise ValueError("idle_token is for lifelong floors (AGV status); episodic AGV "
                             "tokens may carry the parked bit instead (parked_token=True)")
        self.agent_bit = self.config.parked_token or self.config.idle_token
        """Whether the AGV tokens carry a sixth feature (the parked or the idle bit)."""
        self.layout: ObsLayout | LifelongObsLayout | None = None
        self.floor: FloorWaypoints | None = None

    def set_layout(self, layout: ObsLayout | LifelongObsLayout,
                   floor: FloorWaypoints | None = None) -> None:
        """Read observations with this layout from now on (lifelong: and this floor).

        Raises
        ------
        ValueError
            For a layout of the other mode than the networks' (``self.lifelong``), or a
            lifelong layout without a floor.
        """
        want = LifelongObsLayout if self.lifelong else ObsLayout
        if not isinstance(layout, want):
            mode = "lifelong" if self.lifelong else "episodic"
            raise ValueError(f"these {self.name} networks read {mode} observations "
                             f"({want.__name__}), got a {type(layout).__name__}; lifelong and "
                             "episodic weights are separate (train on a warehouse-N scenario "
                             "for lifelong ones)")
        if self.lifelong:
            if not isinstance(floor, FloorWaypoints):
                raise ValueError("a lifelong layout needs the floor's FloorWaypoints")
            self.floor = floor
        self.layout = layout

    def reset(self, env: Any) -> None:
        """Take the observation layout of ``env`` (called by :func:`sim.evaluate` and
        :func:`sim.evaluate_lifelong`); for a lifelong env also its floor's waypoints (built
        once per floor and kept while the floor stays the same).

        Raises
        ------
        ValueError
            For an env of the other mode than the networks' (see :meth:`set_layout`).
        """
        layout = getattr(env, "obs_layout", None)
        physics = getattr(getattr(env, "world", None), "physics", EPISODIC_PHYSICS)
        if (self.config.choice_head or self.config.waypoint_drive) \
                and physics != EPISODIC_PHYSICS:
            kind = "choice-head" if self.config.choice_head else "waypoint-drive"
            raise ValueError(f"a {kind} actor drives with the default physics "
                             f"({EPISODIC_PHYSICS}); this env has {physics}")
        floor = None
        if isinstance(layout, LifelongObsLayout) and self.lifelong:
            world = env.world
            floor = self.floor if self.floor is not None and self.floor.world is world \
                else FloorWaypoints(world)
        self.set_layout(layout, floor)

    def _layout(self, obs: Tensor) -> ObsLayout | LifelongObsLayout:
        if obs.dim() != 3:
            raise ValueError(f"observations must have shape (B, N, O), got {tuple(obs.shape)}")
        if self.layout is not None and self.layout.size == obs.shape[-1]:
            return self.layout
        if self.lifelong:
            raise ValueError(f"lifelong observations of size {obs.shape[-1]} need their "
                             "layout and floor first: reset(env) or set_layout(layout, floor)")
        return infer_layout(obs.shape[1], obs.shape[-1])

    def _read(self, obs: Tensor) -> tuple[Tokens, Tensor]:
        layout = self._layout(obs)
        if isinstance(layout, LifelongObsLayout):
            assert self.floor is not None  # set_layout checks it
            return (lifelong_tokens(obs, layout, self.floor, self.config.idle_token),
                    agent_order(obs, layout))
        return (tokens(obs, layout, self.config.margin_moving, self.config.parked_token),
                agent_order(obs, layout))

    def _movable(self, obs: Tensor) -> Tensor:
        """1.0 for AGVs whose action moves them, (B, N, 1): episodic, all but parked ones
        (with ``mask_parked``); lifelong, all but broken ones and those in service (an AGV
        never parks in lifelong operation)."""
        if self.lifelong:
            layout = self._layout(obs)
            assert isinstance(layout, LifelongObsLayout)
            still = obs[..., layout.status][..., 3:4] + obs[..., layout.service]
            return (still < 0.5).to(obs.dtype)
        if self.config.mask_parked:
            return movable_mask(obs)
        return torch.ones_like(obs[..., :1])

    _AGENT_LAYER = "encoder.agent.0.weight"

    def adapt_init_tensors(self, tensors: dict[str, Tensor]) -> dict[str, Tensor]:
        """Training or policy tensors of a run without ``parked_token`` (or ``idle_token``)
        widened for networks with it: a zero column for the bit in every AGV token layer
        (actor, critic and their targets), so the networks compute what the checkpoint's did
        (with ``idle_token`` the pickups' margin counts the idle AGVs only, which changes
        them); in the Adam moments of that layer, a zero first moment and, as second moment,
        the mean of the row's other columns (the new weights then take steps of the size the
        others take). Tensors whose AGV token layer already fits are returned unchanged.

        Raises
        ------
        ValueError
            For tensors with the bit into networks without it (the bit's weights would be
            dropped).
        """
        key = f"actor.{self._AGENT_LAYER}"
        if key not in tensors:
            return tensors
        have, want = tensors[key].shape[-1], AGENT_TOKEN_FEATURES + int(self.agent_bit)
        if have == want:
            return tensors
        if have != AGENT_TOKEN_FEATURES or want != AGENT_TOKEN_FEATURES + 1:
            bit = "idle_token" if self.lifelong else "parked_token"
            raise ValueError(f"these tensors' AGV tokens have {have} features, the networks "
                             f"read {want} ({bit}={getattr(self.config, bit)}); a run "
                             f"without {bit} cannot start from one with it")
        out = dict(tensors)

        def widen(name: str, fill: str) -> None:
            if name in out:
                w = out[name]
                col = w.mean(-1, keepdim=True) if fill == "mean" else torch.zeros_like(w[..., :1])
                out[name] = torch.cat([w, col], dim=-1).contiguous()

        for prefix, module in (("actor", self.actor), ("critic", self.critic)):
            for net in (prefix, f"target_{prefix}"):
                widen(f"{net}.{self._AGENT_LAYER}", "zero")
            index = [n for n, _ in module.named_parameters()].index(self._AGENT_LAYER)
            widen(f"{prefix}_optimizer.{index}.exp_avg", "zero")
            widen(f"{prefix}_optimizer.{index}.exp_avg_sq", "mean")
        return out

    @torch.no_grad()
    def explore(self, obs: Tensor, noise_std: float, generator: torch.Generator) -> Tensor:
        """Actions with Gaussian exploration noise, clipped to [-1, 1], zero for AGVs that
        cannot move (:meth:`_movable`), (B, N, O) -> (B, N, 2)."""
        a = self.policy(obs)
        noise = torch.randn(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        a = (a + noise_std * noise).clamp(-1.0, 1.0)
        return a * self._movable(obs) if self.config.mask_parked or self.lifelong \
            else a

    def policy(self, obs: Tensor, target: bool = False) -> Tensor:
        """Deterministic actions, (B, N, O) -> (B, N, 2), zero for parked AGVs."""
        return self._policy(obs, *self._read(obs), target)

    def policy_and_choice(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`policy` with the head's weights over the candidates it points at.

        Parameters
        ----------
        obs : Tensor, shape (B, N, O)

        Returns
        -------
        action : Tensor, shape (B, N, 2)
        weights : Tensor, shape (B, N, Kt) or, lifelong, (B, N, 1 + Kt)
            The softmax pointer of :class:`TaskChoiceHead` over the task slots, or lifelong
            of :class:`WaypointHead` over the own target and the pickup slots (zero where
            masked), with the gradient attached: what an imitation loss trains by
            cross-entropy.

        Raises
        ------
        ValueError
            For episodic networks without a choice head (``config.choice_head`` False).
        """
        if not (self.config.choice_head or self.lifelong):
            raise ValueError("policy_and_choice needs a choice-head actor "
                             "(config.choice_head=True) or a lifelong one")
        tok, order = self._read(obs)
        a, w = self.actor.forward_choice(tok, order)
        assert w is not None
        return self._masked(obs, self._squash(a)), w

    def _squash(self, out: Tensor) -> Tensor:
        """The actor's raw output -> the action: tanh, or nothing for a choice head or a
        waypoint drive (whose output already is the action)."""
        return out if self.config.choice_head or self.config.waypoint_drive \
            else torch.tanh(out)

    def _masked(self, obs: Tensor, a: Tensor) -> Tensor:
        return a * self._movable(obs) if self.config.mask_parked or self.lifelong else a

    def _policy(self, obs: Tensor, tok: Tokens, order: Tensor, target: bool) -> Tensor:
        net = self.target_actor if target else self.actor
        return self._masked(obs, self._squash(net(tok, order)))

    def _clip_step(self, params: list[Tensor], grads: tuple[Tensor, ...],
                   optimizer: torch.optim.Optimizer) -> None:
        for p, g in zip(params, grads, strict=True):
            p.grad = g
        torch.nn.utils.clip_grad_norm_(params, self.config.grad_clip)
        optimizer.step()

    def _actor_step(self, actor_loss: Tensor, pre: Tensor, critic_loss: Tensor,
                    q: Tensor) -> dict[str, float]:
        """The end of both updates: the actor's step (with the pre-tanh L2 term), the soft
        update of the targets, and the logged losses."""
        reg = self.config.action_l2 * pre.pow(2).mean()
        actor_params = list(self.actor.parameters())
        self._clip_step(actor_params, torch.autograd.grad(actor_loss + reg, actor_params),
                        self.actor_optimizer)
        self._soft_update()
        self.updates += 1
        return {"critic_loss": critic_loss.item(), "actor_loss": actor_loss.item(),
                "q": q.detach().mean().item()}


class MADDPGE(EntityLearner):
    """MADDPG over entity tokens: shared decentralized actor, shared pooled centralized critic.

    Updates (mean over the batch and the AGVs, so that the step size does not depend on N):

    * critic: L = mean_{b, i} (Q_i(o, a) - y_i)^2, y_i = r_i + gamma Q'_i(o', mu'(o'));
    * actor: J = mean over movable AGVs of Q_i(o, a_1..mu(o_i)..a_N), the other AGVs' actions
      as stored (Lowe et al.'s per-agent gradient), plus the L2 penalty on the pre-tanh
      actions.
    """

    name = "maddpg-e"

    def __init__(self, obs_dim: int, state_dim: int, num_agents: int,
                 config: MADDPGEConfig | None = None, lifelong: bool | None = None) -> None:
        config = config or MADDPGEConfig()
        super().__init__(obs_dim, state_dim, num_agents, config, lifelong)
        if config.choice_rounds:
            raise ValueError(f"choice_rounds={config.choice_rounds} is communication between "
                             "the actors, which MADDPG-E's do not have: use bicnet-e or 0")
        if config.choice_sinkhorn:
            raise ValueError(f"choice_sinkhorn={config.choice_sinkhorn} is communication "
                             "between the actors, which MADDPG-E's do not have: use bicnet-e "
                             "or 0")
        self.actor = EntityActor(config.hidden, self.lifelong, self.agent_bit,
                                 config.choice_head, config.waypoint_drive, config.drive_sight)
        self.critic = PooledCritic(config.hidden, self.lifelong, self.agent_bit)
        self._finish_init()

    def q_values(self, obs: Tensor, action: Tensor, target: bool = False) -> Tensor:
        """Per-AGV Q, (B, N, O), (B, N, 2) -> (B, N)."""
        net = self.target_critic if target else self.critic
        return net(self._read(obs)[0], action)

    def update(self, batch: Batch) -> dict[str, float]:
        """One MADDPG-E update (see the class docstring); returns the losses and mean Q."""
        cfg = self.config
        with torch.no_grad():
            tok2, order2 = self._read(batch.next_obs)
            next_action = self._policy(batch.next_obs, tok2, order2, True)
            y = self.td_target(batch, self.target_critic(tok2, next_action))
        tok, order = self._read(batch.obs)
        q = self.critic(tok, batch.action)
        critic_loss = (q - y).pow(2).mean()
        critic_params = list(self.critic.parameters())
        self._clip_step(critic_params, torch.autograd.grad(critic_loss, critic_params),
                        self.critic_optimizer)

        movable = self._movable(batch.obs).squeeze(-1) \
            if cfg.mask_parked or self.lifelong else torch.ones_like(q)
        pre = self.actor(tok, order)
        mu = self._squash(pre) * movable.unsqueeze(-1)
        with torch.no_grad():  # the critic's side does not depend on the actor's weights
            encoded = self.critic.encoder(tok)
            others = self.critic.others(self.critic.embed(tok, batch.action, encoded))
        q_pi = self.critic.q(self.critic.embed(tok, mu, encoded), others)
        actor_loss = -(q_pi * movable).sum() / movable.sum().clamp_min(1.0)
        return self._actor_step(actor_loss, pre, critic_loss, q)


class BiCNetE(EntityLearner):
    """BiCNet over entity tokens: the bidirectional GRU runs along the AGVs in a fixed order
    (:func:`agent_order`), after a shared entity encoder, in the actor and in the critic.

    Updates: critic L = mean_{b, i} (Q_i(o, a) - y_i)^2; actor J = mean_{b, i} Q_i(o, mu(o))
    (BiCNet's sum over i, divided by N so that the step size does not depend on N).
    """

    name = "bicnet-e"

    def __init__(self, obs_dim: int, state_dim: int, num_agents: int,
                 config: BiCNetEConfig | None = None, lifelong: bool | None = None) -> None:
        config = config or BiCNetEConfig()
        super().__init__(obs_dim, state_dim, num_agents, config, lifelong)
        self.actor = SortedBiRNN(config.hidden, 2, lifelong=self.lifelong,
                                 agent_bit=self.agent_bit,
                                 choice_head=config.choice_head,
                                 choice_rounds=config.choice_rounds,
                                 choice_regret=config.choice_regret,
                                 choice_accumulate=config.choice_accumulate,
                                 choice_sinkhorn=config.choice_sinkhorn,
                                 choice_sinkhorn_beta=config.choice_sinkhorn_beta,
                                 waypoint_drive=config.waypoint_drive,
                                 drive_sight=config.drive_sight)
        self.critic = SortedBiRNN(config.hidden, 1, action_input=True, lifelong=self.lifelong,
                                  agent_bit=self.agent_bit)
        self._finish_init()

    def q_values(self, obs: Tensor, action: Tensor, target: bool = False) -> Tensor:
        """Per-AGV Q, (B, N, O), (B, N, 2) -> (B, N)."""
        net = self.target_critic if target else self.critic
        tok, order = self._read(obs)
        return net(tok, order, action).squeeze(-1)

    def update(self, batch: Batch) -> dict[str, float]:
        """One BiCNet-E update (see the class docstring); returns the losses and mean Q."""
        cfg = self.config
        with torch.no_grad():
            tok2, order2 = self._read(batch.next_obs)
            next_action = self._policy(batch.next_obs, tok2, order2, True)
            y = self.td_target(batch, self.target_critic(tok2, order2, next_action).squeeze(-1))
        tok, order = self._read(batch.obs)
        q = self.critic(tok, order, batch.action).squeeze(-1)
        critic_loss = (q - y).pow(2).mean()
        critic_params = list(self.critic.parameters())
        self._clip_step(critic_params, torch.autograd.grad(critic_loss, critic_params),
                        self.critic_optimizer)

        pre = self.actor(tok, order)
        mu = self._squash(pre) * (self._movable(batch.obs) if cfg.mask_parked or self.lifelong
                                  else 1.0)
        actor_loss = -self.critic(tok, order, mu).mean()
        return self._actor_step(actor_loss, pre, critic_loss, q)
