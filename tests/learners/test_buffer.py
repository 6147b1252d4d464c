"""The preallocated replay buffer."""

from __future__ import annotations

import pytest
import torch

from learners.buffer import Batch, ReplayBuffer
from tests.learners.conftest import make_batch


def _rows(batch: Batch, lo: int, hi: int) -> Batch:
    return Batch(**{k: v[lo:hi] for k, v in vars(batch).items()})


def test_add_wraps_around_and_keeps_the_newest():
    env, batch = make_batch(num_envs=10)
    buf = ReplayBuffer(16, env.num_agents, env.obs_dim, env.state_dim)
    buf.add(batch)
    assert len(buf) == 10 and buf.pos == 10
    buf.add(batch)  # 20 rows into 16 slots: rows 6..9 of the first add are overwritten
    assert len(buf) == 16 and buf.pos == 4
    torch.testing.assert_close(buf.data["obs"][:4], batch.obs[6:10])
    torch.testing.assert_close(buf.data["reward"][10:16], batch.reward[:6])


def test_sample_is_reproducible_with_a_generator():
    env, batch = make_batch(num_envs=32)
    buf = ReplayBuffer(100, env.num_agents, env.obs_dim, env.state_dim)
    buf.add(batch)
    a = buf.sample(8, torch.Generator().manual_seed(3))
    b = buf.sample(8, torch.Generator().manual_seed(3))
    for k in vars(a):
        torch.testing.assert_close(getattr(a, k), getattr(b, k))
    assert a.obs.shape == (8, env.num_agents, env.obs_dim) and a.terminal.shape == (8,)


def test_state_dict_round_trip_and_shape_check():
    env, batch = make_batch(num_envs=12)
    buf = ReplayBuffer(50, env.num_agents, env.obs_dim, env.state_dim)
    buf.add(batch)
    other = ReplayBuffer(50, env.num_agents, env.obs_dim, env.state_dim)
    other.load_state_dict(buf.state_dict())
    assert len(other) == 12 and other.pos == 12
    torch.testing.assert_close(other.data["next_obs"][:12], batch.next_obs)
    wrong = ReplayBuffer(50, env.num_agents, env.obs_dim + 1, env.state_dim)
    with pytest.raises(ValueError, match="obs"):
        wrong.load_state_dict(buf.state_dict())
    with pytest.raises(ValueError, match="empty"):
        ReplayBuffer(5, 1, 2, 2).sample(1, torch.Generator())
