"""The paper's three rewards in lifelong mode, for pickups and drop-offs (``docs/lifelong.md``).

Each is a callable ``reward(state, ctx) -> {term: (B, N)}`` of a
:class:`sim.state.LifelongState` and a :class:`sim.state.LifelongContext`, zero in
environments that were not running.

- :class:`LifelongMiniDist` (global): every AGV gets the lifelong R_t = -(remaining work of
  every order, :func:`sim.tasks.remaining_work`) - (overlapping pairs).
- :class:`LifelongGreedy` (individual): the path length each working AGV closed during the
  step to its own target of before the step (a loaded AGV's drop-off, an assigned AGV's
  pickup, an idle AGV's nearest open pickup), along the floor's shortest paths round the
  shelves, minus the AGVs it overlaps.
- :class:`LifelongIPF`: r_IPF + r_g + r_c, where r_IPF is the AGV's own field at its own
  cell: for an AGV with a target (loaded: its drop-off; assigned: its pickup) that target
  alone at +5, otherwise every open pickup at +5; the other AGVs at -3 (broken ones too: they
  stay obstacles), walls and shelves at 0. r_g is the MiniDist distance term and r_c = -1
  while the AGV overlaps another. A broken AGV's r_IPF is 0.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch
from torch import Tensor

from sim.orders import BROKEN, OPEN
from sim.rewards.base import zero_inactive
from sim.state import LifelongContext, LifelongState
from sim.world import World

__all__ = ["LifelongGreedy", "LifelongIPF", "LifelongMiniDist"]


class LifelongMiniDist:
    """Every AGV receives the lifelong team reward R_t. Terms ``distance``, ``collision``."""

    zeroes_inactive = True

    def __call__(self, state: LifelongState, ctx: LifelongContext) -> dict[str, Tensor]:
        return {"distance": ctx.team_distance, "collision": ctx.team_collision}


class LifelongGreedy:
    """Progress towards the AGV's own target of before the step. Terms ``progress``,
    ``collision``.

    Progress is measured along the floor's shortest paths round the shelves
    (:class:`sim.floor_paths.FloorWaypoints`), so that driving round a shelf toward a target
    behind it pays and pressing against the shelf does not: the decrease of the path length
    to the AGV's own target (loaded: its drop-off; assigned: its pickup), or, for an idle AGV,
    of the path length to the nearest open pickup (the paper's Greedy: the nearest task), the
    same open pickups before and after the step. On a floor without shelves (or with
    ``path=False``) the lengths are straight lines.

    Parameters
    ----------
    path : bool
        Measure along shortest paths (default True) or straight lines.

    Raises
    ------
    ValueError
        For a ``path`` that is not a bool.
    """

    zeroes_inactive = True

    def __init__(self, path: bool = True) -> None:
        if not isinstance(path, bool):
            raise ValueError(f"path must be True or False, got {path!r}")
        self.path = path
        self._paths: Any = None
        self._ready = False

    def setup(self, world: World, kernels: Any = None) -> None:
        """Build the floor's path table (:class:`sim.floor_paths.FloorWaypoints`) when the
        floor has shelves and ``path`` is on (the env calls it)."""
        from sim.floor_paths import FloorWaypoints

        self._paths = FloorWaypoints(world) if self.path and world.has_obstacles else None
        self._ready = True

    def _length(self, points: Tensor, targets: Tensor, mask: Tensor) -> Tensor:
        if self._paths is None:
            return torch.linalg.vector_norm(points - targets, dim=-1)
        return self._paths.query(points, targets, mask)[1].to(points.dtype)

    def __call__(self, state: LifelongState, ctx: LifelongContext) -> dict[str, Tensor]:
        if self.path and not self._ready:
            raise ValueError("LifelongGreedy.setup(world) must be called before the reward "
                             "(LifelongEnv does it), or use LifelongGreedy(path=False)")
        from sim.orders import CARRYING, TO_PICKUP

        o, f = ctx.prev_orders, ctx.prev_fleet
        B, N = f.order.shape
        slot = f.order.clamp_min(0).unsqueeze(-1).expand(B, N, 2)
        carrying = f.status == CARRYING
        own = torch.where(carrying.unsqueeze(-1), o.dropoff.gather(1, slot),
                          o.pickup.gather(1, slot))
        has_own = carrying | (f.status == TO_PICKUP)
        progress = self._length(ctx.prev_agent_pos, own, has_own) \
            - self._length(state.agent_pos, own, has_own)
        progress = torch.where(has_own, progress, torch.zeros_like(progress))
        # idle AGVs: the nearest open pickup of before the step, before and after
        open_ = o.status == OPEN  # (B, Q)
        idle = (f.status != BROKEN) & ~has_own
        if bool((idle.any(1) & open_.any(1)).any()):
            Q = o.pickup.shape[1]
            pick = o.pickup.unsqueeze(1).expand(B, N, Q, 2)
            far = torch.full((B, N, Q), math.inf, dtype=progress.dtype, device=progress.device)
            keep = (idle.unsqueeze(2) & open_.unsqueeze(1))
            before = torch.where(keep, self._length(
                ctx.prev_agent_pos.unsqueeze(2).expand(B, N, Q, 2), pick, keep), far).amin(2)
            after = torch.where(keep, self._length(
                state.agent_pos.unsqueeze(2).expand(B, N, Q, 2), pick, keep), far).amin(2)
            gain = torch.where(torch.isfinite(before), before - after,
                               torch.zeros_like(before))
            progress = torch.where(idle, gain, progress)
        return zero_inactive({"progress": progress, "collision": -ctx.collisions_per_agent},
                             ctx.active)


class LifelongIPF:
    """The IPF reward in lifelong mode. Terms ``ipf``, ``goal``, ``collision``.

    Parameters
    ----------
    resolution : float, optional
        Grid cell size; default the IPF grid's default for the floor.
    task_value, agent_value : float
        The fixed potentials (+5, -3 in the paper).
    """

    zeroes_inactive = True

    def __init__(self, resolution: float | None = None, task_value: float = 5.0,
                 agent_value: float = -3.0) -> None:
        from sim.ipf import check_resolution

        self.resolution = None if resolution is None else check_resolution(resolution)
        for name, value in (("task_value", task_value), ("agent_value", agent_value)):
            if isinstance(value, bool) or not isinstance(value, numbers.Real) \
                    or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        self.task_value = float(task_value)
        self.agent_value = float(agent_value)
        self._grid: Any = None
        from sim.ipf import TaskBlockCache

        self._cache = TaskBlockCache()  # the open pickups' factors, kept between steps

    def setup(self, world: World, kernels: Any = None) -> None:
        """Make the floor's grid (refused with a ValueError if it does not fit)."""
        from sim.ipf import DEFAULT_RESOLUTION, ipf_grid

        grid = ipf_grid(world, self.resolution or DEFAULT_RESOLUTION)
        if not hasattr(grid, "lifelong_potentials"):
            raise ValueError("the IPF grid of this version has no lifelong potentials")
        self._grid = grid

    def __call__(self, state: LifelongState, ctx: LifelongContext) -> dict[str, Tensor]:
        if self._grid is None:
            raise ValueError("LifelongIPF.setup(world) must be called before the reward "
                             "(sim.make_env does it)")
        o = state.orders
        potential = self._grid.lifelong_potentials(
            state.agent_pos, o.pickup, o.status == OPEN, ctx.target, ctx.has_target,
            ctx.active, task_value=self.task_value, agent_value=self.agent_value,
            cache=self._cache, dtype=state.agent_pos.dtype)
        potential = torch.where(state.fleet.status == BROKEN, 0.0, potential)
        collision = -ctx.collisions_per_agent.clamp_max(1.0)
        return zero_inactive({"ipf": potential, "goal": ctx.team_distance,
                              "collision": collision}, ctx.active)
