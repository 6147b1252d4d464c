"""LifelongEnv.state_tensors / load_state_tensors: a run continues exactly (training resume)."""

from __future__ import annotations

import pytest
import torch

import sim
from sim.controllers import NearestTaskController


def _env(seed: int) -> sim.LifelongEnv:
    return sim.make_env("warehouse-20", num_envs=2, reward="ipf", seed=seed,
                        faults=sim.Breakdowns(0.01, repair_steps=5))


def _run(env: sim.LifelongEnv, steps: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    ctl = NearestTaskController()
    ctl.reset(env)
    out = []
    obs = env.observe()
    for _ in range(steps):
        obs, reward, _, _ = env.step(ctl.act(obs))
        out.append((obs, reward))
    return out


def test_a_restored_env_continues_exactly():
    env = _env(0)
    _run(env, 120)
    saved = env.state_tensors()
    assert int(env.delivered.sum()) > 0 and int(env.fleet.repair_left.sum()) >= 0
    after = _run(env, 80)
    env.reset(env_ids=[0])
    fresh = env.observe()
    other = _env(7)  # another seed: everything comes from the saved state
    other.load_state_tensors(saved)
    again = _run(other, 80)
    other.reset(env_ids=[0])
    for (o1, r1), (o2, r2) in zip(after, again, strict=True):
        assert torch.equal(o1, o2) and torch.equal(r1, r2)
    assert torch.equal(env.delivered, other.delivered)
    assert torch.equal(fresh, other.observe())  # the generator came back too
    assert int(other.order_balance().abs().sum()) == 0


def test_bad_state_is_a_clear_error():
    env = _env(0)
    saved = env.state_tensors()
    with pytest.raises(ValueError, match="lacks"):
        env.load_state_tensors({k: v for k, v in saved.items() if k != "orders.status"})
    small = sim.make_env("warehouse-20", num_envs=1, seed=0)
    with pytest.raises(ValueError, match="B=1"):
        small.load_state_tensors(saved)


def test_sizes_for_checkpoints():
    env = sim.make_env("warehouse-20", num_envs=2, seed=0)
    assert env.state_dim == env.global_state().shape[-1] == 220
    assert env.num_tasks == len(env.scenario.pickups) == 48
