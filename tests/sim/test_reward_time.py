"""The ``time`` term of ``IPFReward(time_cost=...)`` and the ``ipf-time`` variant (issue 16):
known values on hand-made scenes, its episode sum against the time metric, bad values."""

from __future__ import annotations

import math

import pytest
import torch

import sim
from sim.rewards import GOAL_WEIGHT, REWARD_VARIANTS, REWARDS, TIME_COST, IPFReward, make_reward


def _env(n: int, m: int, reward, **options) -> sim.AGVEnv:
    scenario = sim.Scenario(name="hand", world=sim.World(), num_agents=n, num_tasks=m, **options)
    return sim.AGVEnv(scenario, num_envs=1, reward=reward, seed=0)


def _step(env: sim.AGVEnv, agents, tasks) -> dict[str, list[float]]:
    env.set_state(torch.tensor([agents]), torch.tensor([tasks]))
    _, reward, _, info = env.step(torch.zeros(1, env.num_agents, 2))
    torch.testing.assert_close(sum(info["reward_terms"].values()), reward)
    return {k: v[0].tolist() for k, v in info["reward_terms"].items()}


def test_the_paper_ipf_reward_has_no_time_term_and_the_variant_is_not_a_paper_reward() -> None:
    env = sim.make_env("3v3", num_envs=2, reward="ipf", seed=0)
    _, _, _, info = env.step(torch.zeros(2, 3, 2))
    assert set(info["reward_terms"]) == {"ipf", "goal", "collision"}
    assert IPFReward().time_cost == 0.0
    assert "ipf-time" not in REWARDS and set(REWARDS) == {"minidist", "greedy", "ipf"}


def test_time_cost_is_charged_to_every_agv_while_a_task_is_open() -> None:
    # AGV 0 stands on task 0 and claims it in the step; task 1 stays open far from AGV 1.
    terms = _step(_env(2, 2, IPFReward(time_cost=0.7)),
                  [[-0.5, -0.5], [0.6, 0.6]], [[-0.5, -0.5], [-0.5, 0.5]])
    assert terms["time"] == pytest.approx([-0.7, -0.7])


def test_the_step_that_claims_the_last_task_costs_nothing() -> None:
    env = _env(2, 2, IPFReward(time_cost=0.7))
    terms = _step(env, [[-0.5, -0.5], [0.5, 0.5]], [[-0.5, -0.5], [0.5, 0.5]])
    assert bool(env.done[0]) and bool(env.task_claimed.all())
    assert terms["time"] == [0.0, 0.0]


@pytest.mark.parametrize(("options", "term"), [({"time_cost": 2.0}, "time"),
                                               ({"assign_weight": 1.0}, "assign")])
def test_the_other_terms_are_the_paper_ipf_reward_unchanged(options, term) -> None:
    # the time term here, the assign term of tests/sim/test_reward_assign.py: each only adds
    actions = torch.rand(5, 4, 3, 2, generator=torch.Generator().manual_seed(3)) * 2 - 1
    plain = sim.make_env("3v3", num_envs=4, reward="ipf", seed=2)
    extra = sim.make_env("3v3", num_envs=4, reward=IPFReward(**options), seed=2)
    for a in actions:
        _, r0, _, i0 = plain.step(a)
        _, r1, _, i1 = extra.step(a)
        assert set(i1["reward_terms"]) == {"ipf", "goal", "collision", term}
        for name in ("ipf", "goal", "collision"):
            torch.testing.assert_close(i1["reward_terms"][name], i0["reward_terms"][name])
        torch.testing.assert_close(r1 - r0, i1["reward_terms"][term])
        assert bool((i1["reward_terms"][term] <= 0).all())


def test_episode_sum_of_the_time_term_follows_the_time_metric() -> None:
    cost = 0.5
    env = sim.make_env("3v3", num_envs=64, reward=IPFReward(time_cost=cost), seed=5)
    gen = torch.Generator().manual_seed(0)
    total = torch.zeros(64)
    while not bool(env.done.all()):
        # head for the nearest task so that some episodes finish before the limit
        near = torch.cdist(env.agent_pos, env.task_pos).argmin(dim=2)
        target = env.task_pos.gather(1, near.unsqueeze(-1).expand(-1, -1, 2))
        push = (target - env.agent_pos) * 4 + torch.randn(64, 3, 2, generator=gen) * 0.3
        _, _, _, info = env.step(push.clamp(-1, 1))
        total += info["reward_terms"]["time"].mean(dim=1)
    finished = env.task_claimed.all(dim=1)
    assert bool(finished.any()) and not bool(finished.all())
    expected = torch.where(finished, -cost * (env.steps - 1), -cost * env.steps).float()
    torch.testing.assert_close(total, expected)


def test_finished_environments_get_a_zero_time_term() -> None:
    env = _env(2, 2, IPFReward(time_cost=1.0), max_steps=1)
    _step(env, [[-0.5, -0.5], [0.6, 0.6]], [[0.0, 0.0], [-0.5, 0.5]])
    assert bool(env.done[0])
    _, reward, _, info = env.step(torch.zeros(1, 2, 2))
    assert info["reward_terms"]["time"].tolist() == [[0.0, 0.0]] and reward.abs().sum() == 0


def test_the_ipf_time_variant_by_name() -> None:
    reward = make_reward("ipf-time")
    assert isinstance(reward, IPFReward) and reward.time_cost == TIME_COST > 0
    assert reward.goal_weight == GOAL_WEIGHT > 0
    assert set(REWARD_VARIANTS) == {"ipf-time"}
    env = sim.make_env("3v3", num_envs=2, reward="ipf-time", seed=0)
    _, _, _, info = env.step(torch.zeros(2, 3, 2))
    assert set(info["reward_terms"]) == {"ipf", "goal", "collision", "time"}
    assert info["reward_terms"]["time"].tolist() == [[-TIME_COST] * 3] * 2


def test_the_variant_has_no_lifelong_form_and_unknown_names_list_it() -> None:
    with pytest.raises(ValueError, match=r"'ipf-time' is a variant for the episodic"):
        make_reward("ipf-time", lifelong=True)
    with pytest.raises(ValueError, match=r"unknown reward 'ipf-tim'.*variant \('ipf-time'\)"):
        make_reward("ipf-tim")


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf, -math.inf, True, "1", None, [1.0]],
                         ids=["negative", "nan", "inf", "-inf", "bool", "str", "None", "list"])
def test_a_bad_time_cost_is_refused(bad) -> None:
    with pytest.raises(ValueError, match=r"time_cost must be a finite number >= 0"):
        IPFReward(time_cost=bad)


def test_goal_weight_scales_the_goal_term_only() -> None:
    actions = torch.rand(3, 4, 3, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    plain = sim.make_env("3v3", num_envs=4, reward="ipf", seed=2)
    heavy = sim.make_env("3v3", num_envs=4, reward=IPFReward(goal_weight=2.5), seed=2)
    for a in actions:
        _, _, _, i0 = plain.step(a)
        _, _, _, i1 = heavy.step(a)
        assert set(i1["reward_terms"]) == {"ipf", "goal", "collision"}
        torch.testing.assert_close(i1["reward_terms"]["goal"], 2.5 * i0["reward_terms"]["goal"])
        torch.testing.assert_close(i1["reward_terms"]["ipf"], i0["reward_terms"]["ipf"])
    assert IPFReward().goal_weight == 1.0


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf, False, "2", None],
                         ids=["zero", "negative", "nan", "inf", "bool", "str", "None"])
def test_a_bad_goal_weight_is_refused(bad) -> None:
    with pytest.raises(ValueError, match=r"goal_weight must be a finite number > 0"):
        IPFReward(goal_weight=bad)
