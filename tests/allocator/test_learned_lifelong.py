"""Learned allocators on lifelong floors: lifelong entity weights through sim.evaluate_lifelong."""

from __future__ import annotations

import numpy as np
import pytest

import allocator
import sim
from allocator.learned import MissingWeightsError, weights_path
from learners.train import TrainConfig, train


@pytest.fixture(scope="module")
def lifelong_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("lifelong") / "run"
    train(TrainConfig(algo="maddpg-e", reward="greedy", scenario="warehouse-20", episodes=2,
                      seed=0, run_dir=str(run_dir), eval_every=0, window=10, eval_steps=10,
                      progress=False, tensorboard=False),
          {"hidden": 8, "batch_size": 16, "num_envs": 2, "learning_starts": 10,
           "buffer_size": 100})
    return run_dir


def test_lifelong_weights_drive_a_floor_shielded(lifelong_run):
    solver = allocator.make("maddpg-greedy", scenario="warehouse-20", weights=lifelong_run,
                            shield=True)
    assert solver.any_n and solver.lifelong
    m = sim.evaluate_lifelong(solver, "warehouse-20", steps=40, seed=0)
    assert m.lost == 0 and m.steps == 40 and m.collisions_per_1000 == 0.0
    assert solver.safety.agent_steps > 0 and 0.0 <= solver.safety.intervention_rate() <= 1.0
    # one set of weights for any floor size (warehouse-50 here), unshielded too
    free = allocator.make("maddpg-greedy", scenario="warehouse-50", checkpoint=lifelong_run)
    m50 = sim.evaluate_lifelong(free, "warehouse-50", steps=5, seed=0)
    assert m50.lost == 0
    # weights=<run> and checkpoint=<its policy file> are the same policy
    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    by_weights = allocator.make("maddpg-greedy", scenario="warehouse-20", weights=lifelong_run)
    by_path = allocator.make("maddpg-greedy", scenario="warehouse-20",
                             checkpoint=lifelong_run / "policy.safetensors")
    for s in (by_weights, by_path):
        s.reset(env)
    obs = env.observe()
    a = by_path.act(obs)
    assert a.shape == (1, 20, 2) and np.array_equal(a.numpy(), by_weights.act(obs).numpy())


def test_lifelong_weights_bad_uses_are_clear_errors(lifelong_run):
    with pytest.raises(ValueError, match="trained on the lifelong floor"):
        allocator.make("maddpg-greedy", scenario="6v6", weights=lifelong_run)
    with pytest.raises(ValueError, match="algo='maddpg-e', expected algo='bicnet-e'"):
        allocator.make("bicnet-greedy", scenario="warehouse-20", weights=lifelong_run)
    with pytest.raises(ValueError, match="give the weights once"):
        allocator.make("maddpg-greedy", scenario="warehouse-20", weights=lifelong_run,
                       checkpoint=lifelong_run)
    solver = allocator.make("maddpg-greedy", scenario="warehouse-20", weights=lifelong_run)
    with pytest.raises(ValueError, match="no one-shot plan"):
        solver.assign(np.array([[0.5, 0.5]]), np.array([[1.9, 1.8]]))
    with pytest.raises(ValueError, match="not episodic scenes"):
        solver.reset(sim.make_env("6v6", num_envs=1, seed=0))
    # episodic weights: a paper policy; no weights of warehouse-20's own (the default asks for
    # those): the error points at the shipped any-floor ones, or at `agv train` where none ship
    with pytest.raises(ValueError, match="only the entity learner 'maddpg-e'"):
        allocator.make("maddpg-greedy", scenario="warehouse-20",
                       checkpoint=weights_path("maddpg", "greedy", "3v3"))
    with pytest.raises(MissingWeightsError, match="lifelong/maddpg-greedy.safetensors: pass "
                                                  "weights='any'"):
        allocator.make("maddpg-greedy", scenario="warehouse-20")
    with pytest.raises(MissingWeightsError, match="agv train --algo bicnet-e"):
        allocator.make("bicnet-greedy", scenario="warehouse-20")
    with pytest.raises(ValueError, match="weights must be one of"):
        allocator.make("maddpg-greedy", scenario="warehouse-20", weights="no/such/run")
