"""Batched spawning: candidate samplers and the placement of AGVs and tasks with the spacing
rules of ``DESIGN.md`` (AGVs one diameter apart, tasks 2 x (radius + capture radius) apart,
nothing inside a wall or shelf, no AGV on a task). Shared by the episodes
(:mod:`sim.scenarios`) and lifelong operation (:mod:`sim.lifelong`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sim.native import pointer
from sim.world import World

__all__ = ["Sampler", "place_entities", "uniform_sampler"]

Sampler = Callable[[int, int, torch.Generator, torch.device], Tensor]
"""``sampler(B, C, generator, device) -> (B, C, 2)`` candidate positions."""

_CANDIDATES = 16
_ROUNDS = 100


def uniform_sampler(world: World, margin: float) -> Sampler:
    xmin, ymin, xmax, ymax = world.bounds
    lo = torch.tensor([xmin + margin, ymin + margin], dtype=torch.float32)
    span = torch.tensor([xmax - xmin - 2 * margin, ymax - ymin - 2 * margin], dtype=torch.float32)

    def sample(B: int, C: int, gen: torch.Generator, device: torch.device) -> Tensor:
        u = torch.rand(B, C, 2, generator=gen, device=device, dtype=torch.float32)
        return lo.to(device) + u * span.to(device)

    return sample


def place_entities(
    world: World, n: int, m: int, agent_sampler: Sampler, task_sampler: Sampler, B: int,
    gen: torch.Generator, device: torch.device, kernels: Any = None,
) -> tuple[Tensor, Tensor]:
    """Place n AGVs then m tasks in B scenes at once, with the spacing rules of ``DESIGN.md``.

    Entities are placed one at a time, each for all B scenes at once, from ``_CANDIDATES``
    candidates per round drawn from its sampler; a candidate is kept when it clears the
    shelves and keeps its distance to everything placed before (AGVs one diameter apart,
    tasks ``world.task_spacing`` apart, an AGV and a task more than the capture radius).

    Parameters
    ----------
    world : World
    n, m : int
        AGVs and tasks (either may be 0).
    agent_sampler, task_sampler : Sampler
    B : int
    gen : torch.Generator
    device : torch.device
    kernels : ctypes.CDLL, optional
        The fused kernels to check candidates with (CPU only), or None for torch.

    Returns
    -------
    agents : Tensor, shape (B, n, 2)
    tasks : Tensor, shape (B, m, 2)

    Raises
    ------
    RuntimeError
        When the floor is too crowded to place them.
    """
    w = world
    obstacles = torch.tensor(np.array(w.obstacles), dtype=torch.float32, device=device)
    r, cap = w.agent_radius, w.capture_radius
    lib = kernels if torch.device(device).type == "cpu" else None
    # Entities are placed one at a time (agents, then tasks), each for all B scenes at once.
    # gap[k, j]: minimum distance between entity k and an earlier entity j.
    kinds = torch.tensor([True] * n + [False] * m, device=device)
    same = kinds.unsqueeze(1) == kinds.unsqueeze(0)
    f32 = dict(dtype=torch.float32, device=device)  # whatever torch's default dtype
    own_gap = torch.where(kinds, torch.tensor(2 * r, **f32),
                          torch.tensor(w.task_spacing, **f32)).unsqueeze(1)
    gap = torch.where(same, own_gap, torch.tensor(cap + 1e-3, **f32)) ** 2
    placed = torch.zeros(B, n + m, 2, dtype=torch.float32, device=device)
    rows = torch.arange(B, device=device)
    for k in range(n + m):
        sampler = agent_sampler if k < n else task_sampler
        todo = rows
        gap_k = gap[k, :k].contiguous()
        for _ in range(_ROUNDS):
            cand = sampler(len(todo), _CANDIDATES, gen, device).float()  # (b, C, 2)
            ok = _clear_of_obstacles(cand, obstacles, r)  # (b, C)
            if lib is not None:  # the same rule, one pass in C
                b = len(todo)
                cand, ok = cand.contiguous(), ok.contiguous()
                found = torch.empty(b, dtype=torch.bool)
                # todo, placed and found are made here with the kernel's dtypes and shapes.
                lib.agv_spawn_pick(
                    b, _CANDIDATES, n + m, k,
                    pointer(cand, torch.float32, (b, _CANDIDATES, 2), "candidates"),
                    pointer(ok, torch.bool, (b, _CANDIDATES), "candidate mask"),
                    todo.data_ptr(), pointer(gap_k, torch.float32, (k,), "gap"),
                    placed.data_ptr(), found.data_ptr(),
                )
            else:
                if k:
                    prev = placed[todo, :k]  # (b, k, 2)
                    d2 = ((cand.unsqueeze(2) - prev.unsqueeze(1)) ** 2).sum(-1)  # (b, C, k)
                    ok &= (d2 >= gap_k).all(dim=2)
                found = ok.any(dim=1)
                first = ok.to(torch.uint8).argmax(dim=1)
                chosen = cand[torch.arange(len(todo), device=device), first]
                placed[todo[found], k] = chosen[found]
            todo = todo[~found]
            if not len(todo):
                break
        else:
            raise RuntimeError(
                f"could not place {n} AGVs and {m} tasks with the required spacing after "
                "many tries; the floor is too crowded"
            )
    return placed[:, :n].contiguous(), placed[:, n:].contiguous()


def _clear_of_obstacles(points: Tensor, obstacles: Tensor, r: float) -> Tensor:
    """True where a disc of radius r at ``points`` (..., 2) clears every rectangle."""
    if obstacles.numel() == 0:
        return torch.ones(points.shape[:-1], dtype=torch.bool, device=points.device)
    p = points.unsqueeze(-2)
    closest = torch.minimum(torch.maximum(p, obstacles[:, :2]), obstacles[:, 2:])
    return (torch.linalg.vector_norm(p - closest, dim=-1) >= r + 1e-6).all(dim=-1)
