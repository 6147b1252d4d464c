"""Every registered learning algorithm (``learners.algorithms.ALGORITHMS``) passes the same
checks: actions of the right shape and range, exploration within [-1, 1] that leaves parked
AGVs still, updates that keep the weights finite and change them, the same seed giving the same
weights, and a saved policy that acts exactly as the learner did."""

from __future__ import annotations

import pytest
import torch

import sim
from learners.algorithms import ALGORITHMS, make_learner
from learners.policy import LearnedPolicy
from learners.train import TrainConfig, train
from tests.learners.conftest import TINY, make_batch

ALGOS = sorted(ALGORITHMS)


def _config(algo: str, run_dir, seed: int = 5) -> TrainConfig:
    return TrainConfig(algo=algo, reward="minidist", scenario="3v3", episodes=24, seed=seed,
                       run_dir=str(run_dir), eval_every=24, eval_episodes=4, log_every=8,
                       checkpoint_every=24, progress=False)


@pytest.mark.parametrize("algo", ALGOS)
def test_actions_have_the_documented_shape_range_and_are_deterministic(algo: str) -> None:
    env, batch = make_batch("3v3", num_envs=16)
    learner = make_learner(algo, env.obs_dim, env.state_dim, env.num_agents, dict(TINY))
    actions = learner.act(batch.obs)
    assert actions.shape == (16, env.num_agents, 2) and actions.dtype == torch.float32
    assert torch.isfinite(actions).all() and actions.abs().max() <= 1.0
    assert torch.equal(actions, learner.act(batch.obs))
    gen = torch.Generator().manual_seed(0)
    noisy = learner.explore(batch.obs, 0.5, gen)
    assert noisy.shape == actions.shape and noisy.abs().max() <= 1.0


@pytest.mark.parametrize("algo", ALGOS)
def test_exploration_leaves_parked_agvs_still(algo: str) -> None:
    env = sim.make_env("3v3", num_envs=4, seed=0)
    env.reset()
    # AGV 0 of every environment stands on task 0 and claims it on the first step.
    agents = env.agent_pos.clone()
    agents[:, 0] = env.task_pos[:, 0]
    env.set_state(agents, env.task_pos)
    obs, *_ = env.step(torch.zeros(4, env.num_agents, 2))
    assert (env.agent_task[:, 0] == 0).all()
    learner = make_learner(algo, env.obs_dim, env.state_dim, env.num_agents, dict(TINY))
    noisy = learner.explore(obs, 0.5, torch.Generator().manual_seed(1))
    assert torch.equal(noisy[:, 0], torch.zeros(4, 2))
    assert noisy[:, 1:].abs().sum() > 0


@pytest.mark.parametrize("algo", ALGOS)
def test_training_updates_keep_weights_finite_and_repeat_with_the_seed(tmp_path,
                                                                       algo: str) -> None:
    a = train(_config(algo, tmp_path / "a"), TINY)
    b = train(_config(algo, tmp_path / "b"), TINY)
    assert a.updates == b.updates > 0
    before = make_learner(algo, a.learner.obs_dim, a.learner.state_dim, a.learner.num_agents,
                          dict(TINY)).training_tensors()
    wa, wb = a.learner.training_tensors(), b.learner.training_tensors()
    for name, value in wa.items():
        assert torch.isfinite(value).all(), name
        assert torch.equal(value, wb[name]), name
    changed = [n for n in wa if n in before and before[n].shape == wa[n].shape
               and not torch.equal(before[n], wa[n])]
    assert changed, "training changed no weight"


@pytest.mark.parametrize("algo", ALGOS)
def test_saved_policy_acts_as_the_learner(tmp_path, algo: str) -> None:
    result = train(_config(algo, tmp_path / "run"), TINY)
    policy = LearnedPolicy.load(result.run_dir / "policy.safetensors", algo=algo)
    _, batch = make_batch("3v3", num_envs=8, seed=2)
    assert torch.equal(policy.act(batch.obs), result.learner.act(batch.obs))
