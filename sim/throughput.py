"""Measure environment steps per second of the simulator (used by ``agv bench`` and
``benchmarks/sim_throughput.py``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from sim.env import AGVEnv
from sim.rewards import RewardFn

__all__ = ["Throughput", "best_rate", "measure", "steps_per_second"]


def best_rate(step: Callable[[], object], steps: int, repeats: int, per_call: int) -> float:
    """Calls per second of ``step`` times ``per_call`` (e.g. B environment steps per batched
    step): one warm-up call, then the best of ``repeats`` timed runs of ``steps`` calls."""
    step()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        best = min(best, time.perf_counter() - t0)
    return per_call * steps / best


@dataclass(frozen=True)
class Throughput:
    """Timings of a training-style loop: step every environment, reset the finished ones.

    Attributes
    ----------
    num_envs : int
        B, the number of parallel environments.
    step_seconds : float
        Seconds per batched :meth:`~sim.env.AGVEnv.step` (physics, claims, observations,
        reward), resets excluded.
    reset_seconds : float
        Seconds spent in resets of finished environments, per batched step.
    physics_seconds : float or None
        Seconds per bare physics step (:meth:`~sim.env.AGVEnv.physics_step`) of the same
        scene and B, timed in turns with the full steps; None when not measured.
    """

    num_envs: int
    step_seconds: float
    reset_seconds: float
    physics_seconds: float | None = None

    @property
    def steps_per_second(self) -> float:
        """Environment steps per second, resets included (``B`` per batched step)."""
        return self.num_envs / (self.step_seconds + self.reset_seconds)

    @property
    def overhead(self) -> float | None:
        """What claims, observations and the reward add to the bare physics step:
        ``step_seconds / physics_seconds - 1`` (None when the physics was not timed)."""
        if self.physics_seconds is None:
            return None
        return self.step_seconds / self.physics_seconds - 1.0


@torch.no_grad()
def measure(scenario: str, num_envs: int, reward: str | RewardFn = "minidist",
            steps: int = 100, repeats: int = 3, seed: int = 0,
            native: bool | None = None, physics: bool = False) -> Throughput:
    """Time full steps with random actions and resets of finished environments, as in a
    training loop; the best of ``repeats`` runs of ``steps`` batched steps.

    Parameters
    ----------
    native : bool, optional
        Passed to :class:`~sim.env.AGVEnv` (fused kernels or the torch path).
    physics : bool
        Also time the bare physics step of a second environment of the same scene, one run
        of ``steps`` after each run of full steps (best of ``repeats``), so that both see the
        same machine conditions.
    """
    env = AGVEnv(scenario, num_envs=num_envs, reward=reward, seed=seed, native=native)
    gen = torch.Generator().manual_seed(seed)
    shape = (num_envs, env.num_agents, 2)
    actions = [torch.rand(shape, generator=gen) * 2 - 1 for _ in range(8)]
    bare = AGVEnv(scenario, num_envs=num_envs, seed=seed, native=native) if physics else None
    movable = torch.ones(num_envs, env.num_agents, dtype=torch.bool) if physics else None
    best: tuple[float, float] | None = None
    best_physics = float("inf")
    for r in range(repeats + 1):  # the first run warms up
        t_step = t_reset = 0.0
        for k in range(steps):
            t0 = time.perf_counter()
            _, _, done, _ = env.step(actions[k % 8])
            t1 = time.perf_counter()
            if bool(done.any()):
                env.reset(done)
            t_step += t1 - t0
            t_reset += time.perf_counter() - t1
        if r and (best is None or t_step + t_reset < sum(best)):
            best = (t_step, t_reset)
        if bare is not None:
            t0 = time.perf_counter()
            for k in range(steps):
                bare.physics_step(actions[k % 8], movable)
            if r:
                best_physics = min(best_physics, time.perf_counter() - t0)
    assert best is not None
    return Throughput(num_envs, best[0] / steps, best[1] / steps,
                      best_physics / steps if physics else None)


def steps_per_second(scenario: str, num_envs: int, reward: str | RewardFn = "minidist",
                     steps: int = 100, repeats: int = 3, seed: int = 0) -> float:
    """Environment steps per second (``num_envs`` x batched steps per second) of a full step:
    physics, claiming, observations and reward, with random actions and resets of finished
    environments, as in a training loop (see :func:`measure`).
    """
    return measure(scenario, num_envs, reward, steps, repeats, seed).steps_per_second
