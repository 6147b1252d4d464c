"""The three rewards: conformance over the registry, hand-made scenes with known values,
batch against a per-scene reference, finished environments."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sim
from sim.ipf import ipf_field
from sim.rewards import REWARDS, Greedy, IPFReward, MiniDist, make_reward

TERMS = {"minidist": {"distance", "collision"}, "greedy": {"progress", "collision"},
         "ipf": {"ipf", "goal", "collision"}}


def _env(world: sim.World, n: int, m: int, reward, **options) -> sim.AGVEnv:
    scenario = sim.Scenario(name="hand", world=world, num_agents=n, num_tasks=m, **options)
    return sim.AGVEnv(scenario, num_envs=1, reward=reward, seed=0)


def _step(env: sim.AGVEnv, agents, tasks, vel=None):
    env.set_state(torch.tensor([agents]), torch.tensor([tasks]),
                  None if vel is None else torch.tensor([vel]))
    _, reward, _, info = env.step(torch.zeros(1, env.num_agents, 2))
    terms = {k: v[0].tolist() for k, v in info["reward_terms"].items()}
    return reward[0].tolist(), terms


# ---------------------------------------------------------------------- conformance
@pytest.mark.parametrize("name", sorted(REWARDS))
def test_every_reward_reports_per_agent_terms_that_sum_to_the_reward(name: str) -> None:
    env = sim.make_env("3v3", num_envs=4, reward=name, seed=1)
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        _, reward, _, info = env.step(torch.rand(4, 3, 2, generator=gen) * 2 - 1)
        terms = info["reward_terms"]
        assert set(terms) == TERMS[name]
        for value in terms.values():
            assert value.shape == (4, 3) and torch.isfinite(value).all()
        torch.testing.assert_close(sum(terms.values()), reward)


def test_make_reward_by_name_or_callable() -> None:
    assert isinstance(make_reward("ipf"), IPFReward)
    assert isinstance(make_reward("minidist"), MiniDist)
    custom = Greedy()
    assert make_reward(custom) is custom
    with pytest.raises(ValueError, match=r"unknown reward 'ipf2'.*'greedy', 'ipf', 'minidist'"):
        make_reward("ipf2")


@pytest.mark.parametrize("reward", [["ipf"], 3, 2.5, None, b"ipf"],
                         ids=["list", "int", "float", "None", "bytes"])
def test_make_reward_refuses_what_is_neither_a_name_nor_a_callable(reward) -> None:
    with pytest.raises(ValueError, match=r"reward must be one of 'greedy', 'ipf', 'minidist' "
                                         r"or a callable"):
        make_reward(reward)


def test_make_reward_refuses_a_reward_class_instead_of_an_instance() -> None:
    with pytest.raises(ValueError, match=r"the class IPFReward; pass an instance, IPFReward\(\)"):
        make_reward(IPFReward)


@pytest.mark.parametrize("resolution", [0.0, -1.0, float("nan"), "fine"])
def test_ipf_reward_refuses_a_bad_resolution_when_it_is_made(resolution) -> None:
    with pytest.raises(ValueError, match="resolution must be a positive, finite cell size"):
        IPFReward(resolution=resolution)


@pytest.mark.parametrize("field", ["task_value", "agent_value"])
def test_ipf_reward_refuses_potentials_that_are_not_finite_numbers(field: str) -> None:
    for bad in (float("nan"), float("inf"), "5", True):
        with pytest.raises(ValueError, match=f"{field} must be a finite number"):
            IPFReward(**{field: bad})


def test_ipf_reward_shared_by_two_floors_is_refused_instead_of_using_the_last_one() -> None:
    reward = IPFReward()
    sim.make_env("3v3", reward=reward)
    sim.make_env("3v3", reward=reward)  # the same floor and kernels: fine
    with pytest.raises(ValueError, match="already set up for another environment's floor"):
        sim.make_env("warehouse", reward=reward)
    if sim.make_env("3v3").native:  # the kernels run by default here: refuse the torch path
        with pytest.raises(ValueError, match="give each environment its own IPFReward"):
            sim.make_env("3v3", reward=reward, native=False)


def test_ipf_reward_refuses_a_floor_its_resolution_does_not_fit_when_the_env_is_made() -> None:
    with pytest.raises(ValueError, match=r"MiB .* use resolution >= "):
        sim.make_env("warehouse", reward=IPFReward(resolution=0.01))



# ---------------------------------------------------------------------- hand-made scenes
STRIP = sim.World(bounds=(0.0, 0.0, 5.0, 3.0))
"""At resolution 1 a 3 x 5 grid: the free cells are the three of the middle row."""


def test_ipf_on_a_strip_whose_field_is_known() -> None:
    # AGV 1 | AGV 0 | task in the three free cells (columns 1, 2, 3), one unit apart.
    # AGV 0's field: AGV 1 at -3, the task at +5, the two other neighbours fixed at 0:
    #   Phi_0 = (-3 + 5 + 0 + 0) / 4 = 0.5.
    # AGV 1's field: AGV 0 at -3 is its only non-zero neighbour: Phi_1 = -3 / 4 = -0.75.
    # r_g = -(distance from the task to its nearest AGV) = -1; no overlap, r_c = 0.
    env = _env(STRIP, 2, 1, IPFReward(resolution=1.0))
    reward, terms = _step(env, [[2.5, 1.5], [1.5, 1.5]], [[3.5, 1.5]])
    assert terms["ipf"] == pytest.approx([0.5, -0.75], abs=1e-6)
    assert terms["goal"] == pytest.approx([-1.0, -1.0], abs=1e-6)
    assert terms["collision"] == [0.0, 0.0]
    assert reward == pytest.approx([-0.5, -1.75], abs=1e-6)


def test_ipf_matches_the_reference_field_at_the_default_resolution() -> None:
    env = sim.make_env("6v6", num_envs=3, reward="ipf", seed=4)
    gen = torch.Generator().manual_seed(1)
    for _ in range(4):
        _, _, _, info = env.step(torch.rand(3, 6, 2, generator=gen) * 2 - 1)
    got = info["reward_terms"]["ipf"]
    assert (env.agent_task >= 0).any() and (env.agent_task < 0).any()
    for b in range(3):
        claimed = env.task_claimed[b].numpy()
        for i in range(6):
            if env.agent_task[b, i] >= 0:  # parked on the task it serves: that task's +5
                assert float(got[b, i]) == 5.0
                continue
            field = ipf_field(env.agent_pos[b].numpy(), env.task_pos[b].numpy(), agent=i,
                              world=env.world, claimed=claimed)
            assert float(got[b, i]) == pytest.approx(field.value_at_agent, abs=1e-5)


COLLIDE_AGENTS = [[0.0, 0.0], [0.2, 0.0], [-0.7, -0.7]]
COLLIDE_TASKS = [[0.7, 0.7], [-0.7, 0.7]]


@pytest.mark.parametrize("name", sorted(REWARDS))
def test_collision_terms_on_a_hand_made_overlap(name: str) -> None:
    # AGVs 0 and 1 overlap (0.2 apart, two radii = 0.3); AGV 2 is clear. With zero velocity the
    # step does not move anyone (position integrates the old velocity first, as in MPE).
    env = _env(sim.World(), 3, 2, name)
    _, terms = _step(env, COLLIDE_AGENTS, COLLIDE_TASKS)
    expected = {"minidist": [-1.0, -1.0, -1.0], "greedy": [-1.0, -1.0, 0.0],
                "ipf": [-1.0, -1.0, 0.0]}[name]
    assert terms["collision"] == expected


def test_minidist_and_goal_are_the_paper_distance_term() -> None:
    # Task 0's nearest AGV is AGV 1 at sqrt(0.5^2 + 0.7^2); task 1's is AGV 0 at
    # sqrt(0.7^2 + 0.7^2) (AGV 2 is 1.4 away).
    d = np.hypot(0.5, 0.7) + np.hypot(0.7, 0.7)
    _, mini = _step(_env(sim.World(), 3, 2, "minidist"), COLLIDE_AGENTS, COLLIDE_TASKS)
    _, ipf = _step(_env(sim.World(), 3, 2, "ipf"), COLLIDE_AGENTS, COLLIDE_TASKS)
    assert mini["distance"] == pytest.approx([-d] * 3, abs=1e-6)
    assert ipf["goal"] == pytest.approx([-d] * 3, abs=1e-6)


def test_greedy_rewards_progress_and_nothing_once_parked() -> None:
    # AGV 0 moves 0.1 towards task 0 (velocity 1 for dt 0.1); AGV 1 sits 0.05 from task 1 and
    # claims it during the first step; from then on it is parked and earns no progress.
    env = _env(sim.World(), 2, 2, "greedy")
    agents, tasks = [[0.0, 0.0], [-0.5, -0.5]], [[0.5, 0.0], [-0.45, -0.5]]
    _, terms = _step(env, agents, tasks, vel=[[1.0, 0.0], [0.0, 0.0]])
    assert terms["progress"] == pytest.approx([0.1, 0.0], abs=1e-6)
    assert env.agent_task[0].tolist() == [-1, 1]
    _, _, _, info = env.step(torch.ones(1, 2, 2))
    progress = info["reward_terms"]["progress"][0]
    assert progress[0] > 0.0 and progress[1] == 0.0


def test_claimed_task_leaves_the_ipf_reward() -> None:
    # AGV 1 claims task 1 during the step; AGV 0's r_IPF then sees only task 0 (and AGV 1).
    env = _env(sim.World(), 2, 2, "ipf")
    agents, tasks = [[0.0, 0.0], [-0.5, -0.5]], [[0.6, 0.3], [-0.45, -0.5]]
    _, terms = _step(env, agents, tasks)
    assert env.task_claimed[0].tolist() == [False, True]
    open_only = ipf_field(np.array(agents), np.array(tasks[:1]), agent=0)
    every = ipf_field(np.array(agents), np.array(tasks), agent=0)
    assert terms["ipf"][0] == pytest.approx(open_only.value_at_agent, abs=1e-6)
    assert abs(every.value_at_agent - open_only.value_at_agent) > 1e-3


@pytest.mark.parametrize("name", sorted(REWARDS))
def test_finished_environments_get_zero_terms(name: str) -> None:
    env = _env(sim.World(), 3, 2, name, max_steps=1)
    env.set_state(torch.tensor([COLLIDE_AGENTS]), torch.tensor([COLLIDE_TASKS]))
    _, _, done, _ = env.step(torch.zeros(1, 3, 2))
    assert done.all()
    _, reward, _, info = env.step(torch.zeros(1, 3, 2))
    assert reward.abs().sum() == 0
    for value in info["reward_terms"].values():
        assert value.abs().sum() == 0


def test_ipf_reward_runs_on_the_warehouse() -> None:
    env = sim.make_env("warehouse", num_envs=2, reward="ipf", seed=0)
    _, reward, _, info = env.step(torch.zeros(2, env.num_agents, 2))
    assert torch.isfinite(reward).all()
    assert (info["reward_terms"]["ipf"].abs() <= 5.0).all()
