"""Shared fixtures: tiny learners and a policy checkpoint, built in seconds."""

from __future__ import annotations

import pytest
import torch

import sim
from learners.buffer import Batch


@pytest.fixture(autouse=True)
def _one_thread():
    """Learner tests run single-threaded (steady timings, bit-for-bit determinism)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def make_batch(scenario: str = "3v3", num_envs: int = 64, seed: int = 0,
               reward: str = "minidist") -> tuple[sim.AGVEnv, Batch]:
    """One vectorized step of random actions, as a replay batch."""
    env = sim.make_env(scenario, num_envs=num_envs, reward=reward, seed=seed)
    obs, state = env.reset(), env.global_state()
    gen = torch.Generator().manual_seed(seed)
    action = torch.rand(num_envs, env.num_agents, 2, generator=gen) * 2 - 1
    next_obs, reward_t, _, _ = env.step(action)
    batch = Batch(obs, state, action, reward_t, next_obs, env.global_state(),
                  env.task_claimed.all(1).float())
    return env, batch


TINY = {"hidden": 16, "batch_size": 32, "num_envs": 8, "learning_starts": 64,
        "buffer_size": 2000}
"""Learner settings for smoke tests."""
