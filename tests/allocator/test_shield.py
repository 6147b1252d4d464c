"""The safety shield (allocator/shield.py): any controller's actions made safe."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import allocator
import sim
from allocator.shield import SafetyShield, movable_agents
from sim.controllers import NearestTaskController


class HeadOn:
    """Drives every AGV at full thrust toward the scene's centre: they meet in the middle."""

    name = "head-on"

    def reset(self, env) -> None:
        self.env = env

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        pos = self.env.agent_pos
        return (-pos / pos.norm(dim=-1, keepdim=True).clamp_min(1e-6)).clamp(-1, 1)


def _run(env, ctl, steps: int) -> int:
    ctl.reset(env)
    obs = env.observe()
    pairs = 0
    for _ in range(steps):
        obs, _, _, info = env.step(ctl.act(obs))
        pairs += int(info["collision_pairs"].sum())
    return pairs


def _opposite_pair(num_envs: int = 2):
    env = sim.make_env("2v2", num_envs=num_envs, seed=0)
    pos = np.array([[[-0.8, 0.0], [0.8, 0.0]]] * num_envs)
    tasks = np.array([[[0.0, 0.9], [0.0, -0.9]]] * num_envs)
    env.set_state(pos, tasks)
    return env


def test_head_on_agvs_overlap_without_the_shield_and_never_with_it() -> None:
    env = _opposite_pair()
    assert _run(env, HeadOn(), 15) > 0  # the scene does collide: the test can fail
    env = _opposite_pair()
    shield = SafetyShield(HeadOn())
    assert _run(env, shield, 15) == 0
    assert shield.interventions["any"] > 0 and shield.agent_steps > 0
    assert 0 < shield.intervention_rate() <= 1


@pytest.mark.parametrize("qp", [True, False])
def test_braking_alone_is_safe_too(qp: bool) -> None:
    env = _opposite_pair()
    shield = SafetyShield(HeadOn(), qp=qp)
    assert _run(env, shield, 15) == 0
    if not qp:
        assert shield.interventions["qp"] == 0 and shield.interventions["brake"] > 0


def test_a_lone_agv_far_from_everything_is_left_alone() -> None:
    env = sim.make_env("1v1", num_envs=1, seed=0)
    env.set_state(np.array([[[0.0, 0.0]]]), np.array([[[0.9, 0.9]]]))
    shield = SafetyShield(HeadOn())
    shield.reset(env)
    action = torch.tensor([[[0.3, -0.2]]])
    out = shield.filter(action)
    assert torch.allclose(out, action, atol=1e-6)
    assert shield.interventions == {"any": 0, "qp": 0, "brake": 0, "liveness": 0, "detour": 0}
    assert shield.agent_steps == 1


def test_learned_allocator_with_shield_true() -> None:
    ctl = allocator.make("maddpg-ipf", scenario="3v3", shield=True)
    assert isinstance(ctl.safety, SafetyShield)
    env = sim.make_env("3v3", num_envs=8, seed=3)
    pairs = 0
    ctl.reset(env)
    obs = env.observe()
    while not bool(env.done.all()):
        obs, _, _, info = env.step(ctl.act(obs))
        pairs += int(info["collision_pairs"].sum())
    assert pairs == 0
    assert ctl.safety.agent_steps > 0
    # The one-shot call rolls out shielded too, with a shield of its own.
    out = ctl.assign(np.array([[-0.5, -0.5], [0.5, -0.5], [0.0, 0.5]]),
                     np.array([[0.5, 0.5], [-0.5, 0.5], [0.0, -0.6]]))
    assert out.agent_of_task.shape == (3,)
    assert ctl.safety.env is env
    plain = allocator.make("maddpg-ipf", scenario="3v3")
    assert plain.safety is None and "shield" in plain.option_names()


def test_shielded_lifelong_floor_with_breakdowns_has_no_overlap() -> None:
    env = sim.make_env("warehouse-20", num_envs=2, seed=1, faults=sim.Breakdowns(0.005, 20))
    shield = SafetyShield(NearestTaskController())
    assert _run(env, shield, 120) == 0
    assert shield.agent_steps > 0
    movable = movable_agents(env)
    broken = env.agent_status.numpy() == 3
    assert not (movable & broken).any()


@pytest.mark.parametrize("kwargs, match", [
    (dict(controller=object()), "reset\\(env\\) and act\\(obs\\)"),
    (dict(margin=-0.1), "margin must be a finite number >= 0"),
    (dict(tolerance=0.0), "tolerance must be a finite number > 0"),
    (dict(tolerance=float("nan")), "tolerance"),
    (dict(qp="yes"), "qp must be True or False"),
    (dict(avoidance_options=[1]), "avoidance_options must be a dict"),
    (dict(liveness="yes"), "liveness must be None \\(on for lifelong envs\\), True or False"),
    (dict(liveness=1), "liveness must be None"),
    (dict(seed=-1), "seed must be a non-negative integer"),
    (dict(seed=1.5), "seed must be a non-negative integer"),
    (dict(seed=True), "seed must be a non-negative integer"),
    (dict(cruise_speed=0.0), "cruise_speed must be a finite number > 0"),
    (dict(cruise_speed=float("inf")), "cruise_speed"),
    (dict(cruise_speed="fast"), "cruise_speed"),
])
def test_bad_arguments(kwargs: dict, match: str) -> None:
    args = dict(controller=HeadOn())
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        SafetyShield(**args)


def test_bad_calls() -> None:
    shield = SafetyShield(HeadOn())
    with pytest.raises(ValueError, match="reset\\(env\\) first"):
        shield.filter(torch.zeros(1, 2, 2))
    env = _opposite_pair(1)
    shield.reset(env)
    with pytest.raises(ValueError, match="shape \\(B, N, 2\\) = \\(1, 2, 2\\)"):
        shield.filter(torch.zeros(1, 3, 2))
    with pytest.raises(ValueError, match="NaN or infinite"):
        shield.filter(torch.full((1, 2, 2), float("nan")))
    with pytest.raises(ValueError, match="avoidance_options"):
        SafetyShield(HeadOn(), avoidance_options={"no_such_field": 1}).reset(env)
    with pytest.raises(ValueError, match="shield must be True or False"):
        allocator.make("maddpg-ipf", scenario="3v3", shield="on")
    with pytest.raises(ValueError, match="needs reset\\(env\\) before act"):
        allocator.make("maddpg-ipf", scenario="3v3", shield=True).act(env.observe())
