"""The batched step against the per-environment numpy reference (``numpy_reference.py``).

At every step of a rollout of B environments to two steps past the step limit (25; the
warehouse's cut to 40), so that finished environments are stepped too, the reference steps each
environment alone, in float64, from the batched env's state before the step, with the same
actions; its outputs are compared with the batched step's. Re-starting the reference from the
env's state at every step keeps float32 rounding from compounding through the stiff contacts,
so every step's rules are compared at full precision. The IPF reward is compared on its own,
from the env's state after each step.

Tolerances (float32 env against the float64 reference, one step):
- claims, held tasks, ``done`` and step counts: equal;
- positions 1e-5, velocities 1e-4 (the contact force is stiff: 1e2 x softplus of width 1e-3,
  so a float32 distance error of 1e-7 moves it by about 1e-5 x dt), observations 1e-4
  (positions and velocities in them), rewards 1e-4 (sums of up to M float32 distances).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from numpy_reference import Rules, ipf_terms, step

import sim

B = 6
MAX_STEPS = {"3v3": 25, "6v6": 25, "warehouse": 40}
"""Step limits (the warehouse's 80 cut to 40); the rollouts run two steps past them."""
POS_TOL, VEL_TOL, OBS_TOL, REWARD_TOL = 1e-5, 1e-4, 1e-4, 1e-4


def _actions(env: sim.AGVEnv, generator: torch.Generator) -> torch.Tensor:
    """Towards the nearest open task with noise, in [-1.3, 1.3]^2 (clipped by the step)."""
    rel = env.task_pos.unsqueeze(1) - env.agent_pos.unsqueeze(2)
    dist = torch.linalg.vector_norm(rel, dim=-1).masked_fill(env.task_claimed.unsqueeze(1),
                                                             float("inf"))
    nearest = dist.argmin(dim=2)
    to_task = rel.gather(2, nearest[..., None, None].expand(-1, -1, 1, 2)).squeeze(2)
    noise = torch.rand(to_task.shape, generator=generator) * 2 - 1
    return ((4 * to_task).clamp(-1, 1) + 0.8 * noise).clamp(-1.3, 1.3)


def _state(env: sim.AGVEnv, b: int) -> dict[str, np.ndarray]:
    return {
        "agent_pos": env.agent_pos[b].double().numpy(),
        "agent_vel": env.agent_vel[b].double().numpy(),
        "task_pos": env.task_pos[b].double().numpy(),
        "task_claimed": env.task_claimed[b].numpy().copy(),
        "agent_task": env.agent_task[b].numpy().copy(),
        "steps": int(env.steps[b]),
        "done": bool(env.done[b]),
    }


def _env(scenario: str, reward: str, native: bool) -> sim.AGVEnv:
    try:
        return sim.make_env(scenario, num_envs=B, reward=reward, seed=11, native=native,
                            max_steps=MAX_STEPS[scenario])
    except ValueError as err:
        if native and "unavailable" in str(err):
            pytest.skip(str(err))
        raise


@pytest.mark.parametrize("native", [True, False], ids=["native", "torch"])
@pytest.mark.parametrize("reward", ["minidist", "greedy"])
@pytest.mark.parametrize("scenario", ["3v3", "6v6", "warehouse"])
def test_batched_step_equals_the_numpy_reference(scenario: str, reward: str,
                                                 native: bool) -> None:
    env = _env(scenario, reward, native)
    rules = Rules.of(env.scenario)
    generator = torch.Generator().manual_seed(5)
    steps = MAX_STEPS[scenario] + 2
    seen = {"claims": 0, "collisions": 0.0, "shelf": 0, "wall": 0, "done": 0}
    for t in range(steps):
        actions = _actions(env, generator)
        before = [_state(env, b) for b in range(B)]
        obs, reward_out, done, info = env.step(actions)
        for b in range(B):
            ref = step(rules, before[b], actions[b].double().numpy())
            where = f"{scenario}, step {t}, environment {b}"
            for name in ("task_claimed", "agent_task"):
                np.testing.assert_array_equal(getattr(env, name)[b].numpy(), ref[name],
                                              err_msg=f"{name}, {where}")
            np.testing.assert_array_equal(info["claimed_now"][b].numpy(), ref["claimed_now"],
                                          err_msg=f"claimed_now, {where}")
            assert int(env.steps[b]) == ref["steps"], where
            assert bool(done[b]) == ref["done"], where
            np.testing.assert_allclose(env.agent_pos[b].numpy(), ref["agent_pos"], rtol=0,
                                       atol=POS_TOL, err_msg=f"agent_pos, {where}")
            np.testing.assert_allclose(env.agent_vel[b].numpy(), ref["agent_vel"], rtol=0,
                                       atol=VEL_TOL, err_msg=f"agent_vel, {where}")
            np.testing.assert_allclose(obs[b].numpy(), ref["obs"], rtol=0, atol=OBS_TOL,
                                       err_msg=f"obs, {where}")
            assert float(info["collision_pairs"][b]) == ref["collision_pairs"], where
            np.testing.assert_array_equal(info["collisions_per_agent"][b].numpy(),
                                          ref["collisions_per_agent"], err_msg=where)
            assert float(info["team_reward"][b]) == pytest.approx(ref["team_reward"], rel=0,
                                                                  abs=REWARD_TOL), where
            terms = ref[reward]
            assert sorted(info["reward_terms"]) == sorted(terms), where
            for name, value in terms.items():
                np.testing.assert_allclose(info["reward_terms"][name][b].numpy(), value,
                                           rtol=0, atol=REWARD_TOL,
                                           err_msg=f"reward term {name}, {where}")
            np.testing.assert_allclose(reward_out[b].numpy(), sum(terms.values()), rtol=0,
                                       atol=REWARD_TOL, err_msg=f"reward, {where}")
            pos = ref["agent_pos"]
            world = env.world
            seen["shelf"] += int((world.obstacle_distance(pos) < rules.radius + 1e-6).sum())
            seen["wall"] += int((world.wall_distance(pos) < rules.radius + 1e-6).sum())
        seen["claims"] += int(info["claimed_now"].sum())
        seen["collisions"] += float(info["collision_pairs"].sum())
        seen["done"] += int(done.sum())
    # The comparison is not vacuous: claims, contacts, walls and finished episodes occurred
    # (and shelves in the warehouse).
    assert seen["claims"] > 0 and seen["collisions"] > 0 and seen["wall"] > 0, seen
    assert seen["done"] > 0, seen
    if scenario == "warehouse":
        assert seen["shelf"] > 0, seen


@pytest.mark.parametrize("native", [True, False], ids=["native", "torch"])
@pytest.mark.parametrize("scenario", ["3v3", "6v6", "warehouse"])
def test_batched_ipf_reward_equals_the_numpy_reference(scenario: str, native: bool) -> None:
    # IPF: every AGV's own field solved as a sparse Dirichlet problem, from the env's state
    # after each step (resting against a shelf puts an AGV exactly on a cell border, where
    # float32 and float64 positions fall in different cells), at three environments and 12
    # steps (a solve per AGV and step). Tolerance 1e-6: the fast solvers agree with the
    # converged field to about 1e-10; the rest is the float32 of the reported terms.
    env = sim.make_env(scenario, num_envs=3, reward="ipf", seed=4, native=native)
    rules = Rules.of(env.scenario)
    generator = torch.Generator().manual_seed(6)
    claims = 0
    for t in range(12):
        running = ~env.done.clone()
        _, _, _, info = env.step(_actions(env, generator))
        claims += int(info["claimed_now"].sum())
        for b in range(3):
            terms = ipf_terms(rules, _state(env, b), bool(running[b]))
            assert sorted(info["reward_terms"]) == sorted(terms)
            for name, value in terms.items():
                np.testing.assert_allclose(info["reward_terms"][name][b].numpy(), value,
                                           rtol=0, atol=1e-6 if name == "ipf" else REWARD_TOL,
                                           err_msg=f"{name}, {scenario}, step {t}, env {b}")
    assert claims > 0  # the parked rule is exercised
