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


def test_one_gather_of_rows_equals_a_gather_per_field():
    """The packed table's sample is exactly the textbook per-field indexing, after a wrap."""
    env, batch = make_batch(num_envs=24)
    buf = ReplayBuffer(40, env.num_agents, env.obs_dim, env.state_dim)
    buf.add(batch)
    buf.add(_rows(batch, 3, 23))  # 20 rows from slot 24: the block wraps to slots 0..3
    assert len(buf) == 40 and buf.pos == 4
    torch.testing.assert_close(buf.data["next_state"][:4], batch.next_state[19:23],
                               rtol=0, atol=0)
    torch.testing.assert_close(buf.data["action"][24:40], batch.action[3:19], rtol=0, atol=0)
    idx = torch.randint(buf.size, (16,), generator=torch.Generator().manual_seed(7))
    got = buf.sample(16, torch.Generator().manual_seed(7))
    for name, value in buf.data.items():
        want = value[idx]
        assert getattr(got, name).shape == want.shape, name
        assert torch.equal(getattr(got, name), want), name


def test_add_names_a_field_of_the_wrong_shape():
    env, batch = make_batch(num_envs=4)
    buf = ReplayBuffer(10, env.num_agents, env.obs_dim, env.state_dim)
    bad = Batch(**{**vars(batch), "reward": batch.reward[:, :1]})
    with pytest.raises(ValueError, match="reward"):
        buf.add(bad)
    assert len(buf) == 0
