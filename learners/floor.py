"""What an entity policy reads of a lifelong floor besides its observation: waypoints, shelves.

A lifelong observation (:class:`sim.observations.LifelongObsLayout`) gives straight-line
offsets to the AGV's target and to the nearest open pickups. On a floor with shelves the
straight line usually runs through a shelf, so the entity learners read, for each such point,
**the next waypoint toward it along a shortest path around the shelves** and the path's length
(:class:`sim.floor_paths.FloorWaypoints`, re-exported here), and the **nearest obstacle
points** (shelf faces and walls, :func:`obstacle_points`). Both depend only on the floor (a
:class:`sim.World`), which is static, so they are computed from the observation (which holds
the AGV's absolute position) at any time, in training updates too: nothing extra is stored in
the replay buffer.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from sim.floor_paths import FloorWaypoints
from sim.world import World

__all__ = ["FloorWaypoints", "obstacle_points", "OBSTACLE_SLOTS", "OBSTACLE_RANGE"]

OBSTACLE_SLOTS = 4
"""Obstacle tokens per AGV: the nearest points of the nearest shelves and walls."""
OBSTACLE_RANGE = 1.0
"""Obstacle points farther than this (world units, from the AGV's centre) are masked out."""


def obstacle_points(world: World, points: Tensor, slots: int = OBSTACLE_SLOTS,
                    reach: float = OBSTACLE_RANGE) -> tuple[Tensor, Tensor]:
    """The nearest point of each shelf and wall, the ``slots`` nearest kept, relative.

    Parameters
    ----------
    world : sim.World
    points : Tensor, shape (..., 2)
        AGV positions.
    slots : int
    reach : float
        Points farther than this are masked out.

    Returns
    -------
    rel : Tensor, shape (..., slots, 2)
        Nearest obstacle points relative to the AGV, nearest first; 0 where masked.
    mask : Tensor of bool, shape (..., slots)
    """
    p = points.float()
    xmin, ymin, xmax, ymax = (float(v) for v in world.bounds)
    cands = []
    if world.walls:
        cands += [torch.stack([torch.full_like(p[..., 0], xmin), p[..., 1]], -1),
                  torch.stack([torch.full_like(p[..., 0], xmax), p[..., 1]], -1),
                  torch.stack([p[..., 0], torch.full_like(p[..., 1], ymin)], -1),
                  torch.stack([p[..., 0], torch.full_like(p[..., 1], ymax)], -1)]
    near = torch.stack(cands, -2) if cands else p.new_zeros(*p.shape[:-1], 0, 2)
    if world.has_obstacles:
        rect = torch.tensor(np.array(world.obstacles), dtype=torch.float32)
        lo, hi = rect[:, :2], rect[:, 2:]
        shelf = torch.maximum(torch.minimum(p.unsqueeze(-2), hi), lo)  # (..., S, 2)
        near = torch.cat([near, shelf], -2)
    rel = near - p.unsqueeze(-2)
    d = torch.linalg.vector_norm(rel, dim=-1)
    k = min(slots, d.shape[-1])
    d_k, i_k = torch.topk(d, k, dim=-1, largest=False, sorted=True)
    rel_k = rel.gather(-2, i_k.unsqueeze(-1).expand(*i_k.shape, 2))
    if k < slots:
        pad = slots - k
        rel_k = torch.cat([rel_k, rel_k.new_zeros(*rel_k.shape[:-2], pad, 2)], -2)
        d_k = torch.cat([d_k, d_k.new_full((*d_k.shape[:-1], pad), math.inf)], -1)
    mask = d_k <= reach
    return rel_k * mask.unsqueeze(-1), mask
