"""The MPE physics of the AGV discs: contact forces, integration, shelves and walls, overlaps.

Pure functions of tensors and a :class:`~sim.world.World`; the environment (:mod:`sim.env`)
calls them on its state. They follow ``mpe2`` (dt, damping, sensitivity, soft contacts, its
integration order); walls at the world bounds and rectangular shelves come on top (see
``docs/simulator.md``). The fused C step (``sim/_native/physics.h``) computes the pairwise
distances and the overlaps exactly as :func:`pair_distances` and :func:`collisions` do.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from sim.world import World

__all__ = ["collide_obstacles", "collide_walls", "collisions", "contact_forces", "mpe_step",
           "pair_distances", "shelf_kernel"]


def pair_distances(agent_pos: Tensor) -> Tensor:
    """Pairwise AGV distances as the fused kernel computes them, (B, N, N).

    ``sqrt(dx * dx + dy * dy)`` with float32 products and sum and a correctly rounded square
    root (C's ``sqrtf``; torch's float32 ``sqrt`` and ``cdist`` may differ in the last bit,
    hence the square root in float64, which rounds to the same float32).

    Parameters
    ----------
    agent_pos : Tensor, shape (B, N, 2)
    """
    x, y = agent_pos[..., 0], agent_pos[..., 1]
    dx = x.unsqueeze(2) - x.unsqueeze(1)  # (B, N, N) planes: no (B, N, N, 2) tensor and
    dy = y.unsqueeze(2) - y.unsqueeze(1)  # no reduction over a last dimension of 2
    return dx.mul_(dx).add_(dy.mul_(dy)).double().sqrt_().float()


CONTACT_MIN_DISTANCE = 1e-3
"""Centre distance (world units) below which the soft contact force between two AGVs fades
linearly to 0 instead of keeping its magnitude (see :func:`contact_forces`)."""


def contact_forces(agent_pos: Tensor, dist: Tensor, world: World, eye: Tensor) -> Tensor:
    """MPE's soft contact force on every AGV, (B, N, 2).

    ``f_i = sum_j c * k * softplus((2r - d_ij) / k) * (p_i - p_j) / d_ij``, computed as
    ``p_i * sum_j s_ij - sum_j s_ij p_j`` with one batched matmul. ``d_ij`` is taken at least
    :data:`CONTACT_MIN_DISTANCE`, so two AGVs closer than that push each other less, down to 0
    at the same point, and no rounding error of the matmul form exceeds a small fraction of
    the force.

    Parameters
    ----------
    agent_pos : Tensor, shape (B, N, 2)
    dist : Tensor, shape (B, N, N)
        Pairwise distances.
    world : World
    eye : Tensor of bool, shape (N, N)
        The identity (no force of an AGV on itself).
    """
    ph = world.physics
    dist_min = 2.0 * world.agent_radius
    penetration = torch.nn.functional.softplus(dist_min - dist, beta=1.0 / ph.contact_margin)
    # below CONTACT_MIN_DISTANCE the force fades linearly to 0 (the direction is undefined):
    # a 1/d scale there turns float32 rounding of p_i * sum_j s_ij - sum_j s_ij p_j into
    # forces of 1e8 for a pile of AGVs within 1e-6 of one point
    scale = (ph.contact_force * penetration / dist.clamp_min(CONTACT_MIN_DISTANCE)
             ).masked_fill(eye, 0.0)
    return agent_pos * scale.sum(dim=2, keepdim=True) - torch.bmm(scale, agent_pos)


def collide_obstacles(pos: Tensor, vel: Tensor, obstacles: Tensor,
                      radius: float) -> tuple[Tensor, Tensor]:
    """Push discs out of shelves and cancel the velocity into them.

    Only the discs that touch a shelf (centre closer than ``radius`` to it, or inside it)
    go through :func:`_collide_obstacles_dense`; the others are left as they are, which is
    what it does to them, so the result is the same bit for bit.

    Parameters
    ----------
    pos, vel : Tensor, shape (B, N, 2)
    obstacles : Tensor, shape (K, 4)
        Shelves as ``(xmin, ymin, xmax, ymax)`` rows.
    radius : float
        AGV radius.

    Returns
    -------
    pos, vel : Tensor, shape (B, N, 2)
    """
    p = pos.unsqueeze(2)  # (B, N, 1, 2)
    closest = torch.minimum(torch.maximum(p, obstacles[:, :2]), obstacles[:, 2:])
    dist = torch.linalg.vector_norm(p - closest, dim=-1)  # (B, N, K)
    touch = (dist < radius).any(-1).flatten().nonzero().squeeze(1)
    if not touch.numel():
        return pos, vel
    flat_p, flat_v = pos.reshape(-1, 1, 2), vel.reshape(-1, 1, 2)
    sub_p, sub_v = _collide_obstacles_dense(flat_p[touch], flat_v[touch], obstacles, radius)
    return (flat_p.index_put((touch,), sub_p).view_as(pos),
            flat_v.index_put((touch,), sub_v).view_as(vel))


def _collide_obstacles_dense(pos: Tensor, vel: Tensor, obstacles: Tensor,
                             radius: float) -> tuple[Tensor, Tensor]:
    """:func:`collide_obstacles` computed for every disc and shelf.

    Parameters
    ----------
    pos, vel : Tensor, shape (B, N, 2)
    obstacles : Tensor, shape (K, 4)
        Shelves as ``(xmin, ymin, xmax, ymax)`` rows.
    radius : float
        AGV radius.

    Returns
    -------
    pos, vel : Tensor, shape (B, N, 2)
    """
    lo = obstacles[:, :2]  # (K, 2)
    hi = obstacles[:, 2:]
    p = pos.unsqueeze(2)  # (B, N, 1, 2)
    closest = torch.minimum(torch.maximum(p, lo), hi)  # (B, N, K, 2)
    d = p - closest
    dist = torch.linalg.vector_norm(d, dim=-1)  # (B, N, K)
    # Centre inside a shelf: leave through the nearest face.
    to_face = torch.cat([p - lo, hi - p], dim=-1)  # (B, N, K, 4): left, bottom, right, top
    face = to_face.argmin(dim=-1)
    normals = torch.tensor(
        [[-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]], device=pos.device, dtype=pos.dtype
    )
    inside = dist <= 1e-9
    normal = torch.where(
        inside.unsqueeze(-1), normals[face], d / dist.clamp_min(1e-9).unsqueeze(-1)
    )
    face_depth = to_face.gather(-1, face.unsqueeze(-1)).squeeze(-1)
    depth = torch.where(inside, face_depth + radius, radius - dist)
    hit = depth > 0
    push = (normal * (depth * hit).unsqueeze(-1)).sum(dim=2)
    inward = (vel.unsqueeze(2) * normal).sum(-1).clamp_max(0.0) * hit  # (B, N, K)
    vel = vel - (normal * inward.unsqueeze(-1)).sum(dim=2)
    return pos + push, vel


def shelf_kernel(lib: Any, obstacles: Tensor, radius: float
                 ) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """:func:`collide_obstacles` as the fused kernel of ``sim/_native/shelves.h``, for
    :func:`mpe_step`'s ``shelves``; bit for bit the same.

    Parameters
    ----------
    lib : ctypes.CDLL
        The kernels (:func:`sim.native.library_for`).
    obstacles : Tensor, shape (K, 4) float32
    radius : float
        AGV radius.

    Returns
    -------
    callable
        ``collide(pos, vel) -> (pos, vel)``, writing into ``pos`` and ``vel`` (the physics
        step's fresh tensors).
    """
    from sim.lifelong_native import torch_norm_rounding
    from sim.native import pointer

    fused = int(torch_norm_rounding()[0])  # how this torch rounds a 2-vector's length
    rects = obstacles.detach().to(torch.float32).contiguous()
    K = rects.shape[0]
    rect_ptr = pointer(rects, torch.float32, (K, 4), "obstacles")

    def collide(pos: Tensor, vel: Tensor) -> tuple[Tensor, Tensor]:
        shape = tuple(pos.shape)
        lib.agv_collide_shelves(
            pos.numel() // 2, pointer(pos, torch.float32, shape, "pos"),
            pointer(vel, torch.float32, shape, "vel"), K, rect_ptr, float(radius), fused)
        return pos, vel

    return collide


def collide_walls(pos: Tensor, vel: Tensor, world: World) -> tuple[Tensor, Tensor]:
    """Clamp discs into the world bounds and stop the velocity into a wall they touch.

    Parameters
    ----------
    pos, vel : Tensor, shape (B, N, 2)
    world : World

    Returns
    -------
    pos, vel : Tensor, shape (B, N, 2)
    """
    r = world.agent_radius
    xmin, ymin, xmax, ymax = world.bounds
    lo = torch.tensor([xmin + r, ymin + r], device=pos.device, dtype=pos.dtype)
    hi = torch.tensor([xmax - r, ymax - r], device=pos.device, dtype=pos.dtype)
    clamped = torch.minimum(torch.maximum(pos, lo), hi)
    hit_lo = pos < lo
    hit_hi = pos > hi
    vel = torch.where((hit_lo & (vel < 0)) | (hit_hi & (vel > 0)), torch.zeros_like(vel), vel)
    return clamped, vel


def mpe_step(agent_pos: Tensor, agent_vel: Tensor, actions: Tensor, movable: Tensor,
             world: World, obstacles: Tensor, pair: Tensor | None, eye: Tensor,
             shelves: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None,
             ) -> tuple[Tensor, Tensor]:
    """One MPE physics step: action and contact forces, integration, shelves, walls.

    Parameters
    ----------
    agent_pos, agent_vel : Tensor, shape (B, N, 2)
    actions : Tensor, shape (B, N, 2)
        Checked, clipped accelerations.
    movable : Tensor of bool, shape (B, N)
        AGVs that move; the others keep their position and velocity.
    world : World
    obstacles : Tensor, shape (K, 4)
        ``world.obstacles`` as a tensor of ``agent_pos``'s dtype and device.
    pair : Tensor, shape (B, N, N), optional
        Pairwise distances of ``agent_pos`` (computed when needed and not given).
    eye : Tensor of bool, shape (N, N)
    shelves : callable, optional
        ``shelves(pos, vel) -> (pos, vel)`` in place of :func:`collide_obstacles` (the fused
        kernel of :func:`shelf_kernel`, which may work in place on the fresh ``pos`` and
        ``vel``).

    Returns
    -------
    pos, vel : Tensor, shape (B, N, 2)
        New tensors; the inputs are not changed.
    """
    ph = world.physics
    # MPE physics: force from the action and soft contacts, then integrate.
    force = actions * ph.sensitivity
    if ph.contact_force > 0 and agent_pos.shape[1] > 1:
        if pair is None:
            pair = torch.cdist(agent_pos, agent_pos, compute_mode="donot_use_mm_for_euclid_dist")
        force = force + contact_forces(agent_pos, pair, world, eye)
    m = movable.unsqueeze(-1)
    pos = agent_pos + agent_vel * (ph.dt * m.to(agent_vel.dtype))
    vel = agent_vel * (1.0 - ph.damping) + force * (ph.dt / ph.mass)
    if ph.max_speed is not None:
        speed = torch.linalg.vector_norm(vel, dim=-1, keepdim=True)
        vel = vel * (ph.max_speed / speed.clamp_min(ph.max_speed))
    vel = torch.where(m, vel, agent_vel)
    if world.has_obstacles:
        if shelves is None:
            pos, vel = collide_obstacles(pos, vel, obstacles, world.agent_radius)
        else:
            pos, vel = shelves(pos.contiguous(), vel.contiguous())
    if world.walls:
        pos, vel = collide_walls(pos, vel, world)
    return torch.where(m, pos, agent_pos), vel


def collisions(pair: Tensor, active: Tensor, radius: float, eye: Tensor,
               triu: Tensor) -> tuple[Tensor, Tensor]:
    """Overlapping AGV discs: per AGV and per environment (0 where inactive).

    Parameters
    ----------
    pair : Tensor, shape (B, N, N)
        Pairwise distances (:func:`pair_distances`).
    active : Tensor of bool, shape (B,)
    radius : float
        AGV radius; two discs overlap below ``2 radius``.
    eye, triu : Tensor of bool, shape (N, N)
        The identity and the strict upper triangle.

    Returns
    -------
    per_agent : Tensor, shape (B, N)
        Number of other discs each AGV overlaps (float32).
    pairs : Tensor, shape (B,)
        Number of overlapping pairs (float32).
    """
    overlap = (pair < 2.0 * radius) & ~eye
    overlap = overlap & active.view(-1, 1, 1)
    per_agent = overlap.sum(dim=2).to(pair.dtype)
    pairs = (overlap & triu).sum(dim=(1, 2)).to(pair.dtype)
    return per_agent, pairs
