"""Learning works: on 1 AGV and 1 task, a short run goes from random (about 10 % of tasks
reached) to most tasks reached (0.84 for MADDPG, 0.95 for BiCNet at 400 episodes, seed 0).
Fails if the losses, targets or updates are broken.

One short run is a knife edge: rounding differences of 1e-8 (the same update computed in
another order, e.g. the stacked MADDPG update against the textbook loop, or a simulator
change) grow to weight differences of 0.1 within 1000 updates, and MADDPG's 400-episode 1v1
result over seeds 0-11 ranged from 0.40 to 1.00 (mean 0.86-0.91). So the quick test asks
two of three seeds to learn, which a broken update does not (a random policy reaches 0.07)."""

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
    best = []
    for seed in (0, 1, 2):
        result = train(TrainConfig(algo=algo, reward="ipf", scenario="1v1", episodes=400,
                                   seed=seed, run_dir=str(tmp_path / f"{algo}-{seed}"),
                                   eval_every=100, eval_episodes=200, progress=False),
                       {**FAST, "updates_per_step": updates_per_step})
        best.append(result.best_response_rate)
        if sum(b >= 0.6 for b in best) >= 2:
            break
    assert sum(b >= 0.6 for b in best) >= 2, (
        f"{algo} reached only {', '.join(f'{b:.2f}' for b in best)} of the tasks on 1v1 "
        f"(seeds 0-2, {result.updates} updates each; random policy: "
        f"{random_policy.response_rate:.2f})")


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["maddpg", "bicnet"])
def test_3v3_ipf_reaches_80_percent_within_5k_episodes(tmp_path, algo):
    """The issue's short-budget target (default configs; stops at the first evaluation >= 80 %,
    about 1-2k episodes and 1-2 minutes)."""
    result = train(TrainConfig(algo=algo, reward="ipf", scenario="3v3", episodes=5000, seed=0,
                               run_dir=str(tmp_path / algo), eval_every=250,
                               stop_response=0.80, progress=False))
    assert result.best_response_rate >= 0.80, result.last_eval


@pytest.mark.slow
def test_3v3_ipf_maddpg_reaches_95_percent_within_20_minutes(tmp_path):
    """The issue's wall-clock target on a 2-core machine (about 3-5 minutes when it passes)."""
    result = train(TrainConfig(algo="maddpg", reward="ipf", scenario="3v3", episodes=10000,
                               seed=0, run_dir=str(tmp_path / "run"), eval_every=250,
                               stop_response=0.95, progress=False))
    assert result.best_response_rate >= 0.95, result.last_eval
    assert result.seconds <= 20 * 60, f"took {result.seconds:.0f} s"
