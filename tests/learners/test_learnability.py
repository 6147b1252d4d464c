"""Learning works: on 1 AGV and 1 task, a short run goes from random (about 10 % of tasks
reached) to most tasks reached. Fails if the losses, targets or updates are broken."""

from __future__ import annotations

import pytest

import sim
from learners.train import TrainConfig, train

FAST = {"hidden": 64, "batch_size": 256, "num_envs": 16, "learning_starts": 512,
        "noise_decay_episodes": 300}


@pytest.mark.parametrize("algo, updates_per_step", [
    ("maddpg", 4),
    pytest.param("bicnet", 2, marks=pytest.mark.slow),  # about 20 s on 2 shared cores
])
def test_learns_to_reach_a_single_task(tmp_path, algo, updates_per_step):
    random_policy = sim.evaluate(lambda obs: obs.new_zeros(*obs.shape[:2], 2).uniform_(-1, 1),
                                 "1v1", episodes=200, seed=12345)
    assert random_policy.response_rate < 0.25
    result = train(TrainConfig(algo=algo, reward="ipf", scenario="1v1", episodes=300, seed=0,
                               run_dir=str(tmp_path / algo), eval_every=100, eval_episodes=200,
                               progress=False), {**FAST, "updates_per_step": updates_per_step})
    assert result.best_response_rate >= 0.75, (
        f"{algo} reached only {result.best_response_rate:.2f} of the tasks on 1v1 after "
        f"{result.updates} updates (random policy: {random_policy.response_rate:.2f})")
