"""sim.testing.check_env on every registered scenario and reward, and on broken rewards."""

from __future__ import annotations

import itertools

import pytest
import torch

import sim
from sim.testing import check_env


def _cases() -> list:
    """Every registered scenario with every reward; the IPF fields of the two large lifelong
    floors (a separator tree built first, seconds per step at B = 3) run with ``-m slow``."""
    cases = []
    for scenario, reward in itertools.product(sorted(sim.SCENARIOS), sorted(sim.REWARDS)):
        slow = reward == "ipf" and scenario in ("warehouse-50", "warehouse-100")
        cases.append(pytest.param(scenario, reward, marks=[pytest.mark.slow] if slow else []))
    return cases


@pytest.mark.parametrize(("scenario", "reward"), _cases())
def test_check_env_passes_on_every_registered_scenario_and_reward(scenario: str,
                                                                  reward: str) -> None:
    lifelong = getattr(sim.get_scenario(scenario), "lifelong", False)
    check_env(scenario, reward=reward, num_envs=3, steps=20 if lifelong else None)


def test_check_env_passes_on_the_torch_path() -> None:
    check_env("6v6", reward="greedy", num_envs=3, native=False)


class _Wrapped:
    """The MiniDist reward plus one extra term, ``extra(ctx, like)``."""

    def __init__(self, extra) -> None:
        self.inner = sim.REWARDS["minidist"]()
        self.extra = extra

    def __call__(self, state, ctx) -> dict[str, torch.Tensor]:
        terms = self.inner(state, ctx)
        like = next(iter(terms.values()))
        return {**terms, "extra": self.extra(ctx, like)}


def _batch_index(ctx, like: torch.Tensor) -> torch.Tensor:
    index = torch.arange(like.shape[0], dtype=like.dtype).unsqueeze(1)
    return (0.01 * index * ctx.active.unsqueeze(1)).expand_as(like).contiguous()


def _global_noise(ctx, like: torch.Tensor) -> torch.Tensor:
    return torch.rand(like.shape) * ctx.active.unsqueeze(1)


def _ones(ctx, like: torch.Tensor) -> torch.Tensor:
    return torch.ones_like(like)


def test_check_env_passes_on_a_correct_custom_reward() -> None:
    check_env("3v3", reward=_Wrapped(lambda ctx, like: torch.zeros_like(like)), num_envs=3)


def test_check_env_fails_on_a_reward_that_depends_on_the_batch_index() -> None:
    with pytest.raises(AssertionError, match=r"\[batch against loop\] environment 1 .*extra"):
        check_env("3v3", reward=_Wrapped(_batch_index), num_envs=3)


def test_check_env_fails_on_a_reward_that_uses_global_randomness() -> None:
    with pytest.raises(AssertionError, match=r"\[determinism\] .*reward"):
        check_env("3v3", reward=_Wrapped(_global_noise), num_envs=3)


def test_check_env_fails_on_a_reward_term_not_zero_after_done() -> None:
    with pytest.raises(AssertionError, match=r"\[conformance\] .*reward term 'extra' of an "
                                             r"environment that was already done"):
        check_env("3v3", reward=_Wrapped(_ones), num_envs=3)


def test_check_env_accepts_an_env_factory() -> None:
    scenario = sim.get_scenario("4v2", max_steps=10)
    check_env(lambda num_envs, seed: sim.make_env(scenario, num_envs=num_envs, seed=seed))


def test_check_env_fails_when_the_observation_size_depends_on_the_batch() -> None:
    def factory(num_envs: int, seed: int) -> sim.AGVEnv:
        return sim.make_env("3v3", num_envs=num_envs, seed=seed, k_tasks=min(num_envs, 3))

    with pytest.raises(AssertionError,
                       match=r"\[conformance\] observation size: 18 with one .*24 with 4"):
        check_env(factory)


@pytest.mark.parametrize("target", [None, 3, b"3v3"])
def test_check_env_names_a_bad_target(target: object) -> None:
    with pytest.raises(ValueError, match="scenario_or_env_factory"):
        check_env(target)


def test_check_env_refuses_a_reward_with_a_factory() -> None:
    with pytest.raises(ValueError, match="reward and native apply to a scenario"):
        check_env(lambda num_envs, seed: sim.make_env("3v3", num_envs, seed=seed),
                  reward="greedy")


@pytest.mark.parametrize(("name", "value"),
                         [("num_envs", 0), ("num_envs", True), ("steps", 2.0), ("seed", -1)])
def test_check_env_names_a_bad_count(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=name):
        check_env("3v3", **{name: value})


class _ResetsEveryEnvironment(sim.AGVEnv):
    """A deliberately broken environment: reset(env_ids) resets all of them."""

    def reset(self, env_ids: object = None, seed: int | None = None) -> torch.Tensor:
        return super().reset(None, seed)


def test_check_env_fails_on_a_partial_reset_that_resets_everything() -> None:
    with pytest.raises(AssertionError, match=r"\[conformance\] reset\(env_ids=\[0\]\): .*not "
                                             r"reset"):
        check_env(lambda num_envs, seed: _ResetsEveryEnvironment("3v3", num_envs, seed=seed))


def test_check_env_passes_a_lifelong_floor() -> None:
    check_env("warehouse-20", num_envs=2, steps=30)
    check_env("warehouse-20", reward="greedy", num_envs=2, steps=20, native=False)


def test_check_env_catches_a_lifelong_reward_that_reads_other_floors() -> None:
    def leaky(state, ctx):  # every floor's reward depends on the whole batch
        return {"x": ctx.team_distance.mean(dim=0, keepdim=True).expand_as(ctx.team_distance)
                .contiguous()}

    with pytest.raises(AssertionError, match="batch against loop"):
        check_env("warehouse-20", reward=leaky, num_envs=2, steps=10)
