"""Measure environment steps per second of the simulator (used by ``agv bench`` and
``benchmarks/sim_throughput.py``)."""

from __future__ import annotations

import time

import torch

from sim.core import AGVEnv
from sim.rewards import RewardFn

__all__ = ["steps_per_second", "physics_only_steps_per_second"]


def _timeit(step, steps: int, repeats: int) -> float:
    step()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        best = min(best, time.perf_counter() - t0)
    return best / steps


@torch.no_grad()
def steps_per_second(scenario: str, num_envs: int, reward: str | RewardFn = "minidist",
                     steps: int = 100, repeats: int = 3, seed: int = 0) -> float:
    """Environment steps per second (``num_envs`` x batched steps per second) of a full step:
    physics, claiming, observations and reward, with random actions and resets of finished
    environments, as in a training loop.
    """
    env = AGVEnv(scenario, num_envs=num_envs, reward=reward, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    shape = (num_envs, env.num_agents, 2)
    actions = [torch.rand(shape, generator=gen) * 2 - 1 for _ in range(8)]
    counter = [0]

    def step() -> None:
        counter[0] += 1
        _, _, done, _ = env.step(actions[counter[0] % 8])
        if bool(done.any()):
            env.reset(done)

    return num_envs / _timeit(step, steps, repeats)


@torch.no_grad()
def physics_only_steps_per_second(scenario: str, num_envs: int, steps: int = 100,
                                  repeats: int = 3, seed: int = 0) -> float:
    """Steps per second of the bare MPE physics of the same environment
    (:meth:`~sim.core.AGVEnv.physics_step`: forces, integration, shelves, walls), without
    claiming, observations or rewards: the yardstick for their overhead."""
    env = AGVEnv(scenario, num_envs=num_envs, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    actions = torch.rand((num_envs, env.num_agents, 2), generator=gen) * 2 - 1
    movable = torch.ones(num_envs, env.num_agents, dtype=torch.bool)
    return num_envs / _timeit(lambda: env.physics_step(actions, movable), steps, repeats)
