"""Scripted controllers on local observations: simple decentralized baselines and test drivers."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from sim.observations import LifelongObsLayout, ObsLayout
from sim.world import Physics

__all__ = ["NearestTaskController", "RandomController"]


class NearestTaskController:
    """Each AGV drives at its nearest visible unclaimed task, reading only its observation.

    In lifelong mode it drives at its own target (a loaded AGV's drop-off) or else at the
    nearest visible open pickup.

    A proportional velocity command towards the task, converted to the MPE acceleration
    action. No coordination: two AGVs may chase the same task (the weakest sensible policy).

    Parameters
    ----------
    physics : Physics
        The simulator constants used to turn a velocity command into an action.
    gain : float
        Desired velocity per unit distance (1/s).
    max_speed : float
        Cap on the commanded speed.
    layout : ObsLayout or LifelongObsLayout, optional
        Where the features sit in the observations; :meth:`reset` takes the environment's.
        Until then, any layout with task slots (the nearest task's slot is at the same place
        in all of them).
    """

    def __init__(self, physics: Physics | None = None, gain: float = 4.0,
                 max_speed: float = 1.2, layout: ObsLayout | None = None) -> None:
        self.physics = physics or Physics()
        self.gain = gain
        self.max_speed = max_speed
        self.layout = layout

    def reset(self, env: Any) -> None:
        """Read the observation layout of ``env`` (an :class:`~sim.env.AGVEnv` or a
        :class:`~sim.lifelong.LifelongEnv`)."""
        self.layout = env.obs_layout

    def act(self, obs: Tensor) -> Tensor:
        """Actions (B, N, 2) from observations (B, N, O)."""
        ph = self.physics
        lay = self.layout or ObsLayout(k_tasks=1, k_agents=0)
        vel = obs[..., lay.vel]
        if isinstance(lay, LifelongObsLayout):
            # Lifelong: the AGV's own target (its drop-off when loaded), else the nearest open
            # pickup, zero when none is visible.
            rel = obs[..., lay.target_rel]
            if lay.k_pickups:
                nearest = obs[..., lay.pickup_rel(0)] * obs[..., lay.pickup_mask(0)]
                rel = torch.where(obs[..., lay.target_mask] > 0, rel, nearest)
        elif lay.k_tasks:  # the nearest task, zero when none is visible
            rel = obs[..., lay.task_rel(0)] * obs[..., lay.task_mask(0)]
        else:
            rel = torch.zeros_like(vel)
        v_cmd = rel * self.gain
        speed = torch.linalg.vector_norm(v_cmd, dim=-1, keepdim=True)
        v_cmd = v_cmd * (self.max_speed / speed.clamp_min(self.max_speed))
        action = (v_cmd - vel * (1.0 - ph.damping)) / (ph.sensitivity * ph.dt / ph.mass)
        return action.clamp(-1.0, 1.0)


class RandomController:
    """Uniform random actions in [-1, 1]^2 from an explicit generator."""

    def __init__(self, seed: int = 0) -> None:
        self.generator = torch.Generator().manual_seed(seed)

    def act(self, obs: Tensor) -> Tensor:
        """Actions (B, N, 2)."""
        shape = (*obs.shape[:2], 2)
        return torch.rand(shape, generator=self.generator, dtype=obs.dtype) * 2.0 - 1.0
