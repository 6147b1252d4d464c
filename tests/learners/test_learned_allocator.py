"""Learned allocators: registry names, shipped/explicit weights, conformance, clear errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import allocator
import sim
from allocator.learned import LEARNED, MissingWeightsError, weights_path
from allocator.testing import check_allocator
from learners.algorithms import make_learner
from learners.checkpoint import save_checkpoint

NAMES = [f"{a}-{r}" for a in ("maddpg", "bicnet") for r in ("minidist", "greedy", "ipf")]


def _checkpoint(tmp_path, name: str, scenario: str = "3v3"):
    algo, reward = name.split("-")
    env = sim.make_env(scenario, num_envs=1)
    torch.manual_seed(0)
    learner = make_learner(algo, env.obs_dim, env.state_dim, env.num_agents, {"hidden": 16})
    meta = {"kind": "policy", "algo": algo, "reward": reward, "scenario": scenario,
            "num_agents": env.num_agents, "num_tasks": env.num_tasks, "obs_dim": env.obs_dim,
            "state_dim": env.state_dim, "config": dataclasses.asdict(learner.config)}
    return save_checkpoint(tmp_path / f"{name}.safetensors", learner.policy_tensors(), meta)


def test_every_algo_reward_pair_is_registered():
    assert set(NAMES) <= set(allocator.ALLOCATORS)
    for name in NAMES:
        assert allocator.ALLOCATORS[name].name == name


@pytest.mark.parametrize("name", NAMES)
def test_conformance(tmp_path, name):
    solver = allocator.make(name, scenario="3v3", checkpoint=_checkpoint(tmp_path, name))
    # untrained weights: the plan may leave tasks unserved, but it must be a consistent plan
    check_allocator(solver, scenario="3v3", episodes=3, complete=False)


def test_assign_reports_the_emergent_claims_with_trajectories(tmp_path):
    solver = allocator.make("bicnet-ipf", scenario="3v3",
                            checkpoint=_checkpoint(tmp_path, "bicnet-ipf"))
    agents = np.array([[-0.5, -0.5], [0.5, -0.5], [0.0, 0.6]])
    tasks = np.array([[-0.5, -0.45], [0.5, -0.45], [0.0, 0.65]])  # each within capture radius
    result = solver.assign(agents, tasks)
    np.testing.assert_array_equal(result.task_of_agent, [0, 1, 2])
    assert solver.last_trajectories.shape[1:] == (3, 2)
    for i, path in enumerate(result.paths):
        np.testing.assert_allclose(path[0], agents[i])
        np.testing.assert_allclose(path[-1], tasks[i])


def test_missing_weights_name_the_file_and_the_command():
    if weights_path("maddpg", "greedy", "9v9").exists():  # pragma: no cover
        pytest.skip("weights exist")
    with pytest.raises(MissingWeightsError) as info:
        allocator.make("maddpg-greedy", scenario="9v9")
    msg = str(info.value)
    assert "9v9/maddpg-greedy.safetensors" in msg
    assert "agv train --algo maddpg --reward greedy --scenario 9v9" in msg
    assert isinstance(info.value, ValueError) and isinstance(info.value, FileNotFoundError)


def test_checkpoint_of_another_kind_is_refused(tmp_path):
    path = _checkpoint(tmp_path, "maddpg-ipf")
    with pytest.raises(ValueError, match="algo='maddpg', expected algo='bicnet'"):
        allocator.make("bicnet-ipf", scenario="3v3", checkpoint=path)
    with pytest.raises(ValueError, match="reward='ipf', expected reward='greedy'"):
        allocator.make("maddpg-greedy", scenario="3v3", checkpoint=path)
    with pytest.raises(ValueError, match="scenario='3v3', expected scenario='6v6'"):
        allocator.make("maddpg-ipf", scenario="6v6", checkpoint=path)


@pytest.mark.parametrize("name", sorted(LEARNED))
def test_shipped_weights_load_and_respond(name):
    path = weights_path(*name.split("-"), "3v3")
    if not path.exists():
        pytest.skip(f"no shipped weights for {name} on 3v3")
    solver = allocator.make(name, scenario="3v3")
    metrics = sim.evaluate(solver, "3v3", episodes=100, seed=7)
    assert metrics.response_rate > 0.5
