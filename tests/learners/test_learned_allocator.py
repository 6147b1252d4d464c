"""Learned allocators: registry names, shipped/explicit weights, conformance, clear errors."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
import torch

import allocator
import sim
from allocator.learned import (
    LEARNED,
    LIFELONG_ONLY,
    TAUGHT,
    MissingWeightsError,
    any_n_weights_path,
    weights_path,
)
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


def _require_shipped(path) -> None:
    """Skip when shipped weights are missing, except under CI (``CI`` set), where it fails."""
    if path.exists():
        return
    if os.environ.get("CI"):
        pytest.fail(f"shipped weights missing: {path} (CI is set, so this is not skipped)")
    pytest.skip(f"no shipped weights at {path}")


def test_missing_shipped_weights_fail_instead_of_skipping_under_ci(tmp_path, monkeypatch):
    missing = tmp_path / "3v3" / "maddpg-ipf.safetensors"
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="shipped weights missing"):
        _require_shipped(missing)
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception):
        _require_shipped(missing)
    _require_shipped(weights_path("maddpg", "ipf", "3v3"))  # present: neither


@pytest.mark.parametrize("name", sorted(LEARNED))
def test_shipped_weights_load_and_respond(name):
    algo, reward = name.split("-", 1)
    if name in LIFELONG_ONLY:  # its lifelong floors: tests/learners/test_taught_lifelong.py
        _require_shipped(any_n_weights_path(algo, reward, lifelong=True))
        with pytest.raises(MissingWeightsError, match="lifelong floors"):
            allocator.make(name, scenario="3v3")
        return
    taught = reward in TAUGHT.get(algo, ())  # these ship for any N only
    path = any_n_weights_path(algo, reward) if taught else weights_path(algo, reward, "3v3")
    _require_shipped(path)
    solver = allocator.make(name, scenario="3v3")
    metrics = sim.evaluate(solver, solver.scenario, episodes=100, seed=7)
    assert metrics.response_rate > 0.5


@pytest.mark.parametrize("bad", [2.5, 0, -3, True, "25", float("nan")])
def test_max_steps_that_is_not_a_positive_integer_is_refused(tmp_path, bad):
    """max_steps=2.5 was accepted."""
    path = _checkpoint(tmp_path, "maddpg-ipf")
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        allocator.make("maddpg-ipf", scenario="3v3", checkpoint=path, max_steps=bad)
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        LEARNED["maddpg-ipf"](scenario="3v3", checkpoint=path, max_steps=bad)
    solver = LEARNED["maddpg-ipf"](scenario="3v3", checkpoint=path, max_steps=np.int64(4))
    assert solver.max_steps == 4 and type(solver.max_steps) is int


def test_unknown_option_of_a_learned_allocator_lists_the_valid_ones(tmp_path):
    path = _checkpoint(tmp_path, "bicnet-ipf")
    for make in (lambda **kw: allocator.make("bicnet-ipf", **kw), LEARNED["bicnet-ipf"]):
        with pytest.raises(ValueError, match="unknown option 'max_step' for allocator "
                                             "'bicnet-ipf'; valid options: checkpoint, detour, "
                                             "keep_right, max_steps, scenario"):
            make(scenario="3v3", checkpoint=path, max_step=10)
    with pytest.raises(ValueError, match="checkpoint must be a path"):
        LEARNED["bicnet-ipf"](scenario="3v3", checkpoint=3)


@pytest.mark.parametrize("name", ["maddpg-ipf", "bicnet-ipf"])
@pytest.mark.parametrize("n, m", [(3, 20), (20, 20)])
def test_explicit_scene_the_spawner_could_not_place_is_run(tmp_path, name, n, m):
    """A 3v3 policy refused 3 AGVs and 20 tasks (or 20 and 20): the scenario's random spawner
    has no room to draw such a scene, but the caller gives it, so it is run as given."""
    solver = allocator.make(name, scenario="3v3", checkpoint=_checkpoint(tmp_path, name))
    rng = np.random.default_rng(n + m)
    agents, tasks = rng.uniform(-0.8, 0.8, (n, 2)), rng.uniform(-0.8, 0.8, (m, 2))
    result = solver.assign(agents, tasks)
    assert result.task_of_agent.shape == (n,) and result.agent_of_task.shape == (m,)
    served = result.task_of_agent[result.task_of_agent >= 0]
    assert len(set(served.tolist())) == len(served)
    np.testing.assert_allclose(solver.last_trajectories[0], agents, atol=1e-6)


def test_agvs_closer_than_the_spawn_spacing_are_run_as_given(tmp_path):
    solver = allocator.make("bicnet-ipf", scenario="3v3",
                            checkpoint=_checkpoint(tmp_path, "bicnet-ipf"))
    agents = np.array([[0.0, 0.0], [0.05, 0.0], [0.0, 0.05]])  # overlapping AGV discs
    tasks = np.array([[0.0, 0.02], [0.8, 0.8], [-0.8, -0.8]])
    result = solver.assign(agents, tasks)
    np.testing.assert_allclose(solver.last_trajectories[0], agents, atol=1e-6)
    assert result.task_of_agent.shape == (3,)


@pytest.mark.parametrize("what", ["agents", "tasks"])
@pytest.mark.parametrize("big", [1e39, -3e38, 5e100])
def test_points_beyond_float32_are_reported_outside_the_world_bounds(tmp_path, what, big):
    """They were reported as "NaN or infinite" after the simulator's float32 overflowed."""
    solver = allocator.make("maddpg-ipf", scenario="3v3",
                            checkpoint=_checkpoint(tmp_path, "maddpg-ipf"))
    scene = {"agents": np.array([[0.0, 0.0], [0.5, 0.5], [-0.5, 0.5]]),
             "tasks": np.array([[0.8, 0.8], [-0.8, 0.8], [0.8, -0.8]])}
    scene[what][1, 0] = big
    with pytest.raises(ValueError, match=rf"{what} rows \[1\] lie outside the world bounds"):
        solver.assign(scene["agents"], scene["tasks"])


def test_the_ipf_time_variant_is_served_from_its_folder():
    path = weights_path("bicnet", "ipf-time", "6v6")
    assert path.parent.name == "time" and path.parent.parent.name == "6v6"
    _require_shipped(path)
    solver = allocator.make("bicnet-ipf-time", scenario="6v6")
    assert type(solver).__name__ == "BiCNetIpfTimeAllocator"
    assert Path(solver.checkpoint) == path
    with pytest.raises(ValueError, match="reward='ipf-time', expected reward='ipf'"):
        allocator.make("bicnet-ipf", scenario="6v6", checkpoint=path)
    assert "maddpg-ipf-time" not in LEARNED  # no weights: not registered
